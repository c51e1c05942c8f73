"""Perceptual metrics from local weight files: LPIPS (AlexNet) and CLIP image similarity (ViT).

Both networks are written here in plain torch and load the OFFICIAL checkpoint key layouts;
nothing is ever downloaded. Images are channels-last ``(H, W, 3)`` or ``(N, H, W, 3)`` floats in
[0, 1] (numpy or torch).

LPIPS (Zhang et al. 2018, v0.1, AlexNet variant) needs two files:

- torchvision's AlexNet ImageNet weights ``alexnet-owt-7be5be79.pth``: keys ``features.{0,3,6,8,10}.
  {weight,bias}`` (``classifier.*`` keys are ignored);
- the LPIPS linear heads ``alex.pth`` from the ``lpips`` package (``lpips/weights/v0.1/alex.pth``):
  keys ``lin{0..4}.model.1.weight`` of shapes ``(1, C, 1, 1)``, C = 64, 192, 384, 256, 256.

Distance: inputs mapped to [-1, 1], then LPIPS's scaling layer ``(x - shift) / scale``; AlexNet
ReLU outputs after conv 1..5; each feature unit-normalised over channels (eps 1e-10); squared
difference weighted by the linear head (a 1x1 conv), averaged over space, summed over the five
layers. 0 for identical images; lower is better.

CLIP (Radford et al. 2021) image tower, OpenAI ViT layout (ViT-B/32, ViT-B/16, ViT-L/14, ...):
``visual.conv1.weight`` (no bias), ``visual.class_embedding``, ``visual.positional_embedding``,
``visual.ln_pre.*``, ``visual.transformer.resblocks.N.{ln_1, attn.in_proj_weight, attn.in_proj_bias,
attn.out_proj, ln_2, mlp.c_fc, mlp.c_proj}.*``, ``visual.ln_post.*``, ``visual.proj``. open_clip's
ViT checkpoints use the same names. The file may be the full OpenAI TorchScript archive
(``ViT-B-32.pt``), a state dict (``.pt``/``.pth``/``.bin``) or ``.safetensors``; text-tower keys are
ignored, and a tower-only state dict without the ``visual.`` prefix is accepted. Width, patch,
grid, depth and output size are read from the tensor shapes; heads = width // 64 (at least 1);
activation QuickGELU (the OpenAI models). Preprocessing as CLIP's: bicubic resize of the short
side to the input resolution, centre crop, normalisation by the CLIP mean/std. Similarity = cosine
of the two image embeddings (1 for identical images; higher is better).

:func:`load_lpips` (also exported by :mod:`humanvdm_core.metrics` for the splat loss) finds the AlexNet
file next to the heads file or inside it; ``LPIPS.__call__`` takes [-1, 1] images like the lpips package.

Errors: a missing file raises :class:`humanvdm_core.errors.MissingWeightsError` (the evaluate stage
reports the metric as ``"unavailable: put <file> at <path>"``); a file whose keys or shapes do not
match raises :class:`WeightsLayoutError` listing the missing and unexpected keys.
"""

from __future__ import annotations

import math
import warnings
import zipfile
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from humanvdm_core.errors import require_weights
from humanvdm_core.workflow.errors import HumanVDMError

ALEXNET_FILE = "alexnet-owt-7be5be79.pth"
LPIPS_HEADS_FILE = "alex.pth"
CLIP_FILE = "ViT-B-32.pt"
ALEXNET_SOURCE = "torchvision (https://download.pytorch.org/models/alexnet-owt-7be5be79.pth)"
LPIPS_SOURCE = "the lpips package (lpips/weights/v0.1/alex.pth; github.com/richzhang/PerceptualSimilarity)"
CLIP_SOURCE = "the OpenAI CLIP release (github.com/openai/CLIP, ViT-B/32 -> ViT-B-32.pt) or open_clip's 'openai' ViT weights"

# (conv index in torchvision's AlexNet.features, in, out, kernel, stride, padding)
ALEXNET_CONVS = ((0, 3, 64, 11, 4, 2), (3, 64, 192, 5, 1, 2), (6, 192, 384, 3, 1, 1),
                 (8, 384, 256, 3, 1, 1), (10, 256, 256, 3, 1, 1))
LPIPS_CHANNELS = tuple(c[2] for c in ALEXNET_CONVS)
LPIPS_SHIFT = (-0.030, -0.088, -0.188)
LPIPS_SCALE = (0.458, 0.448, 0.450)
CLIP_MEAN = (0.48145466, 0.4578275, 0.40821073)
CLIP_STD = (0.26862954, 0.26130258, 0.27577711)


class WeightsLayoutError(HumanVDMError):
    """A weight file whose keys or tensor shapes are not the layout this module reads."""


def load_state_dict(path: str | Path) -> dict[str, torch.Tensor]:
    """Tensors of a checkpoint file: safetensors, a torch state dict (possibly nested under
    ``state_dict``/``model``), or a TorchScript archive (its module's state dict)."""
    path = Path(path)
    if path.suffix == ".safetensors":
        from safetensors.torch import load_file

        return dict(load_file(str(path)))
    if zipfile.is_zipfile(path):
        with zipfile.ZipFile(path) as zf:
            scripted = any(n.endswith("constants.pkl") or "/code/" in n for n in zf.namelist())
        if scripted:  # OpenAI's CLIP release; torch.jit is deprecated but still reads it
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", DeprecationWarning)
                return dict(torch.jit.load(str(path), map_location="cpu").state_dict())
    try:
        obj = torch.load(str(path), map_location="cpu", weights_only=True)
    except Exception as e:  # pickles with foreign classes, corrupt files
        raise WeightsLayoutError(f"cannot read weight file {path}: {type(e).__name__}: {e}") from None
    for key in ("state_dict", "model"):
        if isinstance(obj, dict) and isinstance(obj.get(key), dict):
            obj = obj[key]
    if not isinstance(obj, dict):
        raise WeightsLayoutError(f"{path} holds a {type(obj).__name__}, not a state dict of tensors")
    return {k: v for k, v in obj.items() if isinstance(v, torch.Tensor)}


def _check_layout(path: Path, what: str, found: dict[str, torch.Tensor], expected: dict[str, tuple | None]) -> None:
    """Raise WeightsLayoutError listing missing / unexpected keys and wrong shapes."""
    missing = sorted(set(expected) - set(found))
    unexpected = sorted(set(found) - set(expected))
    wrong = sorted(f"{k}: {tuple(found[k].shape)} (expected {expected[k]})" for k in set(expected) & set(found)
                   if expected[k] is not None and tuple(found[k].shape) != tuple(expected[k]))
    if not (missing or unexpected or wrong):
        return

    def show(keys: list[str]) -> str:
        return ", ".join(keys[:12]) + (f", ... ({len(keys)} in all)" if len(keys) > 12 else "")

    parts = []
    if missing:
        parts.append(f"missing keys: {show(missing)}")
    if unexpected:
        parts.append(f"unexpected keys: {show(unexpected)}")
    if wrong:
        parts.append(f"wrong shapes: {show(wrong)}")
    raise WeightsLayoutError(f"{path} is not {what}: " + "; ".join(parts))


def _to_nchw(images) -> torch.Tensor:
    x = torch.as_tensor(images)
    if x.ndim == 3:
        x = x[None]
    if x.ndim != 4 or x.shape[-1] != 3:
        raise ValueError(f"images must be (H, W, 3) or (N, H, W, 3), got {tuple(x.shape)}")
    return x.permute(0, 3, 1, 2).float()


# ----------------------------------------------------------------------------- LPIPS

class LPIPS(nn.Module):
    """LPIPS v0.1 with AlexNet features (see the module docstring)."""

    def __init__(self) -> None:
        super().__init__()
        self.convs = nn.ModuleList(nn.Conv2d(i, o, k, stride=s, padding=p) for _, i, o, k, s, p in ALEXNET_CONVS)
        self.heads = nn.ParameterList(nn.Parameter(torch.zeros(1, c, 1, 1)) for c in LPIPS_CHANNELS)
        self.register_buffer("shift", torch.tensor(LPIPS_SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(LPIPS_SCALE).view(1, 3, 1, 1))
        self.requires_grad_(False)
        self.eval()

    @classmethod
    def from_files(cls, alexnet_path: str | Path, heads_path: str | Path) -> LPIPS:
        alexnet_path = require_weights(alexnet_path, f"torchvision AlexNet weights {ALEXNET_FILE}", ALEXNET_SOURCE)
        heads_path = require_weights(heads_path, f"LPIPS AlexNet linear heads {LPIPS_HEADS_FILE}", LPIPS_SOURCE)
        model = cls()
        feats = {k: v for k, v in load_state_dict(alexnet_path).items()
                 if not k.startswith("classifier.") and not _is_head_key(k)}
        expected: dict[str, tuple | None] = {}
        for idx, i, o, k, _, _ in ALEXNET_CONVS:
            expected[f"features.{idx}.weight"] = (o, i, k, k)
            expected[f"features.{idx}.bias"] = (o,)
        _check_layout(alexnet_path, "torchvision AlexNet weights (features.0/3/6/8/10)", feats, expected)
        heads = {k: v for k, v in load_state_dict(heads_path).items() if not k.startswith(("features.", "classifier."))}
        _check_layout(heads_path, "LPIPS AlexNet heads (lin0..lin4.model.1.weight)", heads,
                      {f"lin{n}.model.1.weight": (1, c, 1, 1) for n, c in enumerate(LPIPS_CHANNELS)})
        with torch.no_grad():
            for conv, (idx, *_rest) in zip(model.convs, ALEXNET_CONVS, strict=True):
                conv.weight.copy_(feats[f"features.{idx}.weight"].float())
                conv.bias.copy_(feats[f"features.{idx}.bias"].float())
            for n, head in enumerate(model.heads):
                head.copy_(heads[f"lin{n}.model.1.weight"].float())
        return model

    def features(self, x: torch.Tensor) -> list[torch.Tensor]:
        """The five ReLU outputs of AlexNet (relu1..relu5) for a scaled (N, 3, H, W) batch."""
        out = []
        for n, conv in enumerate(self.convs):
            if n in (1, 2):  # max-pool after relu1 and relu2, as in AlexNet.features
                x = F.max_pool2d(x, kernel_size=3, stride=2)
            x = F.relu(conv(x))
            out.append(x)
        return out

    def forward(self, pred: torch.Tensor, target: torch.Tensor, normalize: bool = False) -> torch.Tensor:
        """LPIPS distance per image, shape (N,), of (N, 3, H, W) batches in [-1, 1] (the lpips
        package's convention; ``normalize=True``: in [0, 1]). Differentiable w.r.t. the images."""
        if normalize:
            pred, target = pred * 2.0 - 1.0, target * 2.0 - 1.0
        fa = self.features((pred - self.shift) / self.scale)
        fb = self.features((target - self.shift) / self.scale)
        total = torch.zeros(pred.shape[0], device=pred.device)
        for a, b, head in zip(fa, fb, self.heads, strict=True):
            na = a / (a.square().sum(dim=1, keepdim=True).sqrt() + 1e-10)
            nb = b / (b.square().sum(dim=1, keepdim=True).sqrt() + 1e-10)
            total = total + ((na - nb).square() * head).sum(dim=1).mean(dim=(1, 2))
        return total

    def distance(self, pred, target) -> torch.Tensor:
        """LPIPS of channels-last images in [0, 1]: (N,) (or 0-d for one image pair)."""
        a, b = _to_nchw(pred), _to_nchw(target)
        with torch.no_grad():
            d = self(a, b, normalize=True)
        return d[0] if torch.as_tensor(pred).ndim == 3 else d


def _is_head_key(key: str) -> bool:
    return key.startswith("lin") and key.endswith(".model.1.weight")


def load_lpips(heads_path: str | Path, alexnet_path: str | Path | None = None) -> LPIPS:
    """LPIPS from the heads file ``alex.pth`` and torchvision's AlexNet file. Without
    ``alexnet_path``: the heads file itself when it also holds ``features.*`` (one combined file),
    else ``alexnet-owt-7be5be79.pth`` next to it. The module takes [-1, 1] images, as lpips does."""
    heads_path = Path(heads_path).expanduser()
    if alexnet_path is None:
        alexnet_path = heads_path.parent / ALEXNET_FILE
        if heads_path.is_file() and any(k.startswith("features.") for k in load_state_dict(heads_path)):
            alexnet_path = heads_path
    return LPIPS.from_files(alexnet_path, heads_path)


# ----------------------------------------------------------------------------- CLIP

class _ResidualBlock(nn.Module):
    def __init__(self, width: int, heads: int):
        super().__init__()
        self.heads = heads
        self.ln_1 = nn.LayerNorm(width)
        self.in_proj_weight = nn.Parameter(torch.zeros(3 * width, width))
        self.in_proj_bias = nn.Parameter(torch.zeros(3 * width))
        self.out_proj = nn.Linear(width, width)
        self.ln_2 = nn.LayerNorm(width)
        self.c_fc = nn.Linear(width, 4 * width)
        self.c_proj = nn.Linear(4 * width, width)

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # (N, L, width)
        n, length, width = x.shape
        q, k, v = F.linear(self.ln_1(x), self.in_proj_weight, self.in_proj_bias).chunk(3, dim=-1)
        q, k, v = (t.reshape(n, length, self.heads, width // self.heads).transpose(1, 2) for t in (q, k, v))
        attn = F.scaled_dot_product_attention(q, k, v).transpose(1, 2).reshape(n, length, width)
        x = x + self.out_proj(attn)
        h = self.c_fc(self.ln_2(x))
        return x + self.c_proj(h * torch.sigmoid(1.702 * h))  # QuickGELU


class CLIPImageEncoder(nn.Module):
    """The CLIP ViT image tower (see the module docstring)."""

    def __init__(self, width: int, layers: int, patch: int, grid: int, output_dim: int, heads: int | None = None):
        super().__init__()
        self.patch, self.grid = patch, grid
        self.input_resolution = patch * grid
        heads = heads or max(1, width // 64)
        if width % heads:
            raise ValueError(f"width {width} is not divisible by {heads} heads")
        self.conv1 = nn.Conv2d(3, width, patch, stride=patch, bias=False)
        self.class_embedding = nn.Parameter(torch.zeros(width))
        self.positional_embedding = nn.Parameter(torch.zeros(grid * grid + 1, width))
        self.ln_pre = nn.LayerNorm(width)
        self.blocks = nn.ModuleList(_ResidualBlock(width, heads) for _ in range(layers))
        self.ln_post = nn.LayerNorm(width)
        self.proj = nn.Parameter(torch.zeros(width, output_dim))
        self.register_buffer("mean", torch.tensor(CLIP_MEAN).view(1, 3, 1, 1))
        self.register_buffer("std", torch.tensor(CLIP_STD).view(1, 3, 1, 1))
        self.requires_grad_(False)
        self.eval()

    @staticmethod
    def official_keys(width: int, layers: int, patch: int, grid: int, output_dim: int) -> dict[str, tuple]:
        """Key -> shape of the OpenAI layout (with the ``visual.`` prefix) for these dimensions."""
        keys: dict[str, tuple] = {
            "visual.conv1.weight": (width, 3, patch, patch),
            "visual.class_embedding": (width,),
            "visual.positional_embedding": (grid * grid + 1, width),
            "visual.ln_pre.weight": (width,), "visual.ln_pre.bias": (width,),
            "visual.ln_post.weight": (width,), "visual.ln_post.bias": (width,),
            "visual.proj": (width, output_dim),
        }
        for n in range(layers):
            b = f"visual.transformer.resblocks.{n}."
            keys.update({
                b + "ln_1.weight": (width,), b + "ln_1.bias": (width,),
                b + "attn.in_proj_weight": (3 * width, width), b + "attn.in_proj_bias": (3 * width,),
                b + "attn.out_proj.weight": (width, width), b + "attn.out_proj.bias": (width,),
                b + "ln_2.weight": (width,), b + "ln_2.bias": (width,),
                b + "mlp.c_fc.weight": (4 * width, width), b + "mlp.c_fc.bias": (4 * width,),
                b + "mlp.c_proj.weight": (width, 4 * width), b + "mlp.c_proj.bias": (width,),
            })
        return keys

    @classmethod
    def from_file(cls, path: str | Path) -> CLIPImageEncoder:
        path = require_weights(path, f"CLIP ViT image-tower weights ({CLIP_FILE} or equivalent)", CLIP_SOURCE)
        raw = load_state_dict(path)
        if any(k.startswith("visual.") for k in raw):
            sd = {k: v for k, v in raw.items() if k.startswith("visual.")}
        else:  # a tower-only state dict
            sd = {f"visual.{k}": v for k, v in raw.items()}
        blocks = [k.split(".")[3] for k in sd if k.startswith("visual.transformer.resblocks.")]
        layers = 1 + max((int(n) for n in blocks if n.isdigit()), default=-1)
        probe = ("visual.conv1.weight", "visual.positional_embedding", "visual.proj")
        if not all(k in sd for k in probe):
            _check_layout(path, "a CLIP ViT image tower (OpenAI layout)", sd,
                          dict.fromkeys(cls.official_keys(1, layers, 1, 1, 1)))
        width, _, patch, _ = sd["visual.conv1.weight"].shape
        grid = math.isqrt(sd["visual.positional_embedding"].shape[0] - 1)
        output_dim = sd["visual.proj"].shape[1]
        _check_layout(path, "a CLIP ViT image tower (OpenAI layout)", sd,
                      cls.official_keys(width, layers, patch, grid, output_dim))
        model = cls(width, layers, patch, grid, output_dim)
        ours = {"conv1.weight": "visual.conv1.weight", "class_embedding": "visual.class_embedding",
                "positional_embedding": "visual.positional_embedding", "proj": "visual.proj"}
        for ln in ("ln_pre", "ln_post"):
            for p in ("weight", "bias"):
                ours[f"{ln}.{p}"] = f"visual.{ln}.{p}"
        for n in range(layers):
            src = f"visual.transformer.resblocks.{n}."
            for mine, theirs in (("ln_1", "ln_1"), ("out_proj", "attn.out_proj"), ("ln_2", "ln_2"),
                                 ("c_fc", "mlp.c_fc"), ("c_proj", "mlp.c_proj")):
                for p in ("weight", "bias"):
                    ours[f"blocks.{n}.{mine}.{p}"] = f"{src}{theirs}.{p}"
            ours[f"blocks.{n}.in_proj_weight"] = src + "attn.in_proj_weight"
            ours[f"blocks.{n}.in_proj_bias"] = src + "attn.in_proj_bias"
        state = {k: sd[v].float() for k, v in ours.items()}
        state.update({"mean": model.mean, "std": model.std})
        model.load_state_dict(state, strict=True)
        return model

    def preprocess(self, images) -> torch.Tensor:
        """Channels-last [0, 1] images -> normalised (N, 3, R, R): short side resized (bicubic,
        antialiased) to the input resolution R, centre-cropped."""
        x = _to_nchw(images)
        r = self.input_resolution
        h, w = x.shape[-2:]
        s = r / min(h, w)
        nh, nw = max(r, round(h * s)), max(r, round(w * s))
        x = F.interpolate(x, size=(nh, nw), mode="bicubic", align_corners=False, antialias=True).clamp(0.0, 1.0)
        top, left = (nh - r) // 2, (nw - r) // 2
        x = x[:, :, top:top + r, left:left + r]
        return (x - self.mean) / self.std

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Image embeddings (N, output_dim) of preprocessed (N, 3, R, R) images."""
        x = self.conv1(x).flatten(2).transpose(1, 2)  # (N, grid^2, width)
        cls_tok = self.class_embedding.expand(x.shape[0], 1, -1)
        x = self.ln_pre(torch.cat([cls_tok, x], dim=1) + self.positional_embedding)
        for block in self.blocks:
            x = block(x)
        return self.ln_post(x[:, 0]) @ self.proj

    def embed(self, images) -> torch.Tensor:
        with torch.no_grad():
            return self(self.preprocess(images))

    def similarity(self, pred, target) -> torch.Tensor:
        """Cosine similarity of CLIP image embeddings: (N,) (or 0-d for one image pair)."""
        ea, eb = self.embed(pred), self.embed(target)
        s = F.cosine_similarity(ea, eb, dim=-1)
        return s[0] if torch.as_tensor(pred).ndim == 3 else s

"""SV3D's image-embedding tower: OpenCLIP ViT-H/14 in pure PyTorch, official checkpoint key layout.

In SV3D's sgm config (``configs/inference/sv3d_{u,p}.yaml``) ``conditioner.embedders.0`` is a
``FrozenOpenCLIPImagePredictionEmbedder`` whose ``open_clip`` is a ``FrozenOpenCLIPImageEmbedder``
(``sgm/modules/encoders/modules.py``) holding open_clip's whole CLIP ``model`` minus the text
transformer (``del model.transformer``).  Keys under ``conditioner.embedders.0.open_clip.model.``
(:data:`OPENCLIP_PREFIX`), the layout of open_clip's ``VisionTransformer``
(``src/open_clip/transformer.py``, config ``ViT-H-14.json``: width 1280, 32 layers, head width 80
-> 16 heads, patch 14, image 224, MLP ratio 4, output 1024, no LayerScale, no attentional pool,
class-token pooling, exact GELU, LayerNorm eps 1e-5)::

    visual.conv1.weight                                      (1280, 3, 14, 14), no bias
    visual.class_embedding                                   (1280,)
    visual.positional_embedding                              (257, 1280)
    visual.ln_pre.{weight,bias}
    visual.transformer.resblocks.<i>.ln_1.{weight,bias}
    visual.transformer.resblocks.<i>.attn.in_proj_{weight,bias}      (3840, 1280), (3840,)
    visual.transformer.resblocks.<i>.attn.out_proj.{weight,bias}
    visual.transformer.resblocks.<i>.ln_2.{weight,bias}
    visual.transformer.resblocks.<i>.mlp.c_fc.{weight,bias}          (5120, 1280)
    visual.transformer.resblocks.<i>.mlp.c_proj.{weight,bias}        (1280, 5120)
    visual.ln_post.{weight,bias}
    visual.proj                                              (1280, 1024)

What remains of the text side after ``del model.transformer`` is IGNORED by these exact names
(:data:`TEXT_KEYS`): ``token_embedding.weight``, ``positional_embedding`` (the text one, 77 x 1024),
``ln_final.weight``, ``ln_final.bias``, ``text_projection``, ``logit_scale`` and ``attn_mask``
(a non-persistent buffer in current open_clip, tolerated should an older save contain it).  Any
other key outside ``visual.`` is reported as unexpected.

:meth:`OpenCLIPImageEmbedder.embed` is sgm's ``FrozenOpenCLIPImageEmbedder.forward`` at inference
(``ucg_rate`` 0 in SV3D's config, ``output_tokens`` False, no output normalisation): images in
[-1, 1] are resized to 224² as ``kornia.geometry.resize(..., interpolation="bicubic",
align_corners=True, antialias=True)`` does (a Gaussian blur of sigma (factor-1)/2 with reflect
padding before downscaling, nothing when the size already matches; :func:`resize_antialias`),
mapped to [0, 1], normalised with the OpenAI CLIP mean/std, and the class token after ``ln_post``
is projected by ``proj``: (B, 1024).  (``FrozenOpenCLIPImagePredictionEmbedder`` then only
reshapes it to (B, 1, 1024) for cross-attention -- the caller's job.)

Heads cannot be read from shapes; they are ``width // 80`` (:data:`HEAD_WIDTH`), so a tiny model
(:func:`tiny_state_dict`: width 160 -> 2 heads, 2 layers) loads through the same code.
"""

from __future__ import annotations

import math
from collections import OrderedDict

import torch
import torch.nn.functional as F
from torch import nn

from humanvdm_core.models.checkpoint import CheckpointError, load_strict

OPENCLIP_PREFIX = "conditioner.embedders.0.open_clip.model."
TEXT_KEYS = ("token_embedding.weight", "positional_embedding", "ln_final.weight", "ln_final.bias",
             "text_projection", "logit_scale", "attn_mask")
HEAD_WIDTH = 80
CLIP_MEAN = (0.48145466, 0.4578275, 0.40821073)
CLIP_STD = (0.26862954, 0.26130258, 0.27577711)
WHAT = "SV3D OpenCLIP ViT-H/14 image tower"


class ResidualAttentionBlock(nn.Module):
    """open_clip's pre-norm block: x + attn(ln_1(x)); x + mlp(ln_2(x)) (no LayerScale)."""

    def __init__(self, width: int, heads: int, mlp_width: int):
        super().__init__()
        self.ln_1 = nn.LayerNorm(width)
        self.attn = nn.MultiheadAttention(width, heads, batch_first=True)
        self.ln_2 = nn.LayerNorm(width)
        self.mlp = nn.Sequential(OrderedDict([("c_fc", nn.Linear(width, mlp_width)), ("gelu", nn.GELU()),
                                              ("c_proj", nn.Linear(mlp_width, width))]))

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # (B, L, D)
        h = self.ln_1(x)
        x = x + self.attn(h, h, h, need_weights=False)[0]
        return x + self.mlp(self.ln_2(x))


class Transformer(nn.Module):
    def __init__(self, width: int, layers: int, heads: int, mlp_width: int):
        super().__init__()
        self.resblocks = nn.ModuleList([ResidualAttentionBlock(width, heads, mlp_width) for _ in range(layers)])

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        for block in self.resblocks:
            x = block(x)
        return x


class VisionTransformer(nn.Module):
    """open_clip ``VisionTransformer`` (tok pooling, ln_pre, ln_post then ``proj``): (B, 3, S, S) -> (B, out)."""

    def __init__(self, image_size: int, patch_size: int, width: int, layers: int, heads: int, mlp_width: int,
                 output_dim: int):
        super().__init__()
        self.image_size, self.patch_size = image_size, patch_size
        grid = image_size // patch_size
        self.conv1 = nn.Conv2d(3, width, patch_size, patch_size, bias=False)
        self.class_embedding = nn.Parameter(torch.zeros(width))
        self.positional_embedding = nn.Parameter(torch.zeros(grid * grid + 1, width))
        self.ln_pre = nn.LayerNorm(width)
        self.transformer = Transformer(width, layers, heads, mlp_width)
        self.ln_post = nn.LayerNorm(width)
        self.proj = nn.Parameter(torch.zeros(width, output_dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.conv1(x).flatten(2).transpose(1, 2)  # (B, grid², width)
        cls = self.class_embedding.to(x.dtype).expand(x.shape[0], 1, -1)
        x = torch.cat([cls, x], dim=1) + self.positional_embedding.to(x.dtype)
        x = self.transformer(self.ln_pre(x))
        return self.ln_post(x[:, 0]) @ self.proj


def _gaussian_kernel(size: int, sigma: float, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    x = torch.arange(size, dtype=dtype, device=device) - size // 2
    g = torch.exp(-x.pow(2) / (2.0 * sigma * sigma))
    return g / g.sum()


def resize_antialias(x: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """(B, C, H, W) -> (B, C, *size) as ``kornia.geometry.resize(x, size, interpolation="bicubic",
    align_corners=True, antialias=True)``: unchanged when the size matches; when shrinking, a
    separable Gaussian blur (sigma (factor-1)/2 per axis, min 0.001; odd kernel of at least 3 and
    about 4 sigma; reflect padding), then bicubic interpolation with aligned corners."""
    h, w = x.shape[-2:]
    if (h, w) == tuple(size):
        return x
    factors = (h / size[0], w / size[1])
    if max(factors) > 1:
        sigmas = [max((f - 1.0) / 2.0, 0.001) for f in factors]
        ks = [int(max(4.0 * s, 3)) for s in sigmas]
        ks = [k + 1 if k % 2 == 0 else k for k in ks]
        b, c = x.shape[:2]
        flat = x.reshape(b * c, 1, h, w)
        kx = _gaussian_kernel(ks[1], sigmas[1], x.dtype, x.device).view(1, 1, 1, -1)
        flat = F.conv2d(F.pad(flat, ((ks[1] - 1) // 2, ks[1] // 2, 0, 0), mode="reflect"), kx)
        ky = _gaussian_kernel(ks[0], sigmas[0], x.dtype, x.device).view(1, 1, -1, 1)
        flat = F.conv2d(F.pad(flat, (0, 0, (ks[0] - 1) // 2, ks[0] // 2), mode="reflect"), ky)
        x = flat.reshape(b, c, h, w)
    return F.interpolate(x, size=tuple(size), mode="bicubic", align_corners=True)


class OpenCLIPImageEmbedder(nn.Module):
    """``visual`` (keys relative to :data:`OPENCLIP_PREFIX`) plus sgm's preprocessing."""

    def __init__(self, image_size: int = 224, patch_size: int = 14, width: int = 1280, layers: int = 32,
                 heads: int = 16, mlp_width: int = 5120, output_dim: int = 1024):
        super().__init__()
        self.visual = VisionTransformer(image_size, patch_size, width, layers, heads, mlp_width, output_dim)
        self.image_size, self.output_dim = image_size, output_dim
        self.register_buffer("mean", torch.tensor(CLIP_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(CLIP_STD).view(1, 3, 1, 1), persistent=False)

    def preprocess(self, images: torch.Tensor) -> torch.Tensor:
        """[-1, 1] (B, 3, H, W) -> resized to image_size², CLIP-normalised."""
        x = resize_antialias(images, (self.image_size, self.image_size))
        x = (x + 1.0) / 2.0
        return (x - self.mean.to(x.dtype)) / self.std.to(x.dtype)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.visual(self.preprocess(images))

    @torch.no_grad()
    def embed(self, images: torch.Tensor) -> torch.Tensor:
        """Images (B, 3, H, W) in [-1, 1], any size -> (B, output_dim) (1024 for ViT-H/14), unnormalised."""
        if images.ndim != 4 or images.shape[1] != 3:
            raise ValueError(f"embed needs (B, 3, H, W) images, got {tuple(images.shape)}")
        return self(images)


def config_from_state_dict(sd: dict, path: str = "state dict") -> dict:
    """``OpenCLIPImageEmbedder`` arguments from the shapes of ``visual.*`` tensors."""
    def shape(key: str) -> tuple[int, ...]:
        if key not in sd:
            raise CheckpointError(f"{path} is not a {WHAT} checkpoint in the expected key layout; missing keys: "
                                  f"{key} (found e.g. {', '.join(sorted(sd)[:5]) or 'nothing'})")
        return tuple(int(s) for s in sd[key].shape)

    width, _, patch, _ = shape("visual.conv1.weight")
    tokens = shape("visual.positional_embedding")[0]
    grid = math.isqrt(tokens - 1)
    if grid * grid != tokens - 1:
        raise CheckpointError(f"{path}: visual.positional_embedding has {tokens} rows, not 1 + a square grid")
    if width % HEAD_WIDTH:
        raise CheckpointError(f"{path}: width {width} is not a multiple of ViT-H/14's head width {HEAD_WIDTH}")
    pre = "visual.transformer.resblocks."
    layers = len({k[len(pre):].split(".", 1)[0] for k in sd if k.startswith(pre)})
    return {"image_size": grid * patch, "patch_size": patch, "width": width, "layers": layers,
            "heads": width // HEAD_WIDTH, "mlp_width": shape(pre + "0.mlp.c_fc.weight")[0],
            "output_dim": shape("visual.proj")[1]}


def build_image_embedder(state_dict: dict, path: str = "state dict") -> OpenCLIPImageEmbedder:
    """The image tower from a state dict relative to :data:`OPENCLIP_PREFIX`: the :data:`TEXT_KEYS`
    are dropped by name, everything else must match exactly (else :class:`CheckpointError` lists
    the missing / unexpected keys).  Eval mode, float32, CPU."""
    sd = {k: v for k, v in state_dict.items() if k not in TEXT_KEYS}
    cfg = config_from_state_dict(sd, path)
    try:
        model = OpenCLIPImageEmbedder(**cfg)
    except (ValueError, RuntimeError, AssertionError) as e:
        raise CheckpointError(f"{path}: unsupported {WHAT} shapes {cfg}: {e}") from None
    load_strict(model, sd, WHAT, path)
    return model.eval()


def tiny_state_dict(seed: int = 0, width: int = 2 * HEAD_WIDTH, layers: int = 2, output_dim: int = 1024,
                    patch_size: int = 14, image_size: int = 224) -> dict:
    """A tiny random ViT in the official layout, keys relative to :data:`OPENCLIP_PREFIX`: ``visual.*``
    plus small stand-ins for the text leftovers the official file carries (all :data:`TEXT_KEYS` but
    ``attn_mask``).  Default: 224² input, patch 14, width 160 (2 heads), 2 layers, output 1024."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        model = OpenCLIPImageEmbedder(image_size, patch_size, width, layers, width // HEAD_WIDTH, 4 * width,
                                      output_dim)
        gen = torch.Generator().manual_seed(seed)
        sd = {}
        for k, v in model.state_dict().items():
            if k in ("visual.class_embedding", "visual.positional_embedding", "visual.proj"):
                sd[k] = width ** -0.5 * torch.randn(v.shape, generator=gen)  # zeros in the constructor
            else:  # default init, perturbed so that zero biases and unit norms take part too
                sd[k] = (v.float() + 0.02 * torch.randn(v.shape, generator=gen)).contiguous()
        text_width = 32
        sd.update({"token_embedding.weight": torch.randn(16, text_width, generator=gen),
                   "positional_embedding": 0.01 * torch.randn(8, text_width, generator=gen),
                   "ln_final.weight": torch.ones(text_width), "ln_final.bias": torch.zeros(text_width),
                   "text_projection": torch.randn(text_width, output_dim, generator=gen) * text_width ** -0.5,
                   "logit_scale": torch.tensor(math.log(1 / 0.07))})
    return sd

"""SV3D's video UNet (sgm ``VideoUNet``) in plain PyTorch, in the official key layout.

Reference: Stability-AI/generative-models, ``sgm/modules/diffusionmodules/video_model.py``
(``VideoUNet``, ``VideoResBlock``), ``openaimodel.py`` (``ResBlock``, ``TimestepEmbedSequential``,
``Downsample``, ``Upsample``), ``sgm/modules/video_attention.py`` (``SpatialVideoTransformer``,
``VideoTransformerBlock``), ``sgm/modules/attention.py`` (``BasicTransformerBlock``,
``CrossAttention``, ``FeedForward``/``GEGLU``) and ``diffusionmodules/util.py`` (``AlphaBlender``,
``timestep_embedding``, ``GroupNorm32``), with the SV3D settings of ``configs/inference/sv3d_{u,p}.yaml``:
``in_channels 8, out_channels 4, model_channels 320, channel_mult [1, 2, 4, 4], num_res_blocks 2,
attention_resolutions [4, 2, 1], num_head_channels 64, transformer_depth 1, context_dim 1024,
use_linear_in_transformer, extra_ff_mix_layer, use_spatial_context, merge_strategy
learned_with_images, video_kernel_size [3, 1, 1], num_classes sequential, adm_in_channels`` 256
(sv3d_u: cond_aug) or 1280 (sv3d_p: cond_aug 256 + polar 512 + azimuth 512).

Key layout (relative to ``model.diffusion_model.`` in the whole checkpoint)::

    time_embed.{0,2}.{weight,bias}                    Linear(C, 4C), SiLU, Linear(4C, 4C)
    label_emb.0.{0,2}.{weight,bias}                   Linear(adm_in, 4C), SiLU, Linear(4C, 4C)
    input_blocks.0.0.{weight,bias}                    Conv2d(in, C, 3)
    input_blocks.<i>.0.*                              VideoResBlock (or ``.0.op`` = stride-2 Downsample conv)
    input_blocks.<i>.1.*                              SpatialVideoTransformer (levels with attention)
    middle_block.{0,2}.* / middle_block.1.*           VideoResBlock / SpatialVideoTransformer
    output_blocks.<i>.{0,1,2}.*                       VideoResBlock, transformer, ``.conv`` of an Upsample
    out.{0,2}.{weight,bias}                           GroupNorm32, SiLU, Conv2d(C, out, 3)

    VideoResBlock: in_layers.{0,2} (GroupNorm, Conv2d 3x3), emb_layers.1 (Linear), out_layers.{0,3},
      [skip_connection (1x1 conv) when channels change], time_stack.{in_layers.{0,2}, emb_layers.1,
      out_layers.{0,3}} (the same ResBlock with Conv3d kernel (3, 1, 1) over frames), time_mixer.mix_factor
    SpatialVideoTransformer: norm (GroupNorm eps 1e-6), proj_in / proj_out (Linear),
      transformer_blocks.<d>.{attn1,attn2}.{to_q,to_k,to_v (no bias), to_out.0}, .ff.net.{0.proj,2},
      .norm{1,2,3};  time_stack.<d>.{norm_in, ff_in.net.{0.proj,2}, attn1, attn2, ff, norm1-3}
      (attention across frames; attn2 attends to the first frame's context), time_pos_embed.{0,2},
      time_mixer.mix_factor

Forward (as sgm's ``VideoUNet.forward`` after ``OpenAIWrapper``): ``x`` (B*T, in, h, w) is the noisy
latent concatenated with the ``concat`` conditioning, ``timesteps`` (B*T,) the denoiser's c_noise,
``context`` (B*T, 1, context_dim) the ``crossattn`` conditioning, ``y`` (B*T, adm_in) the
``vector`` conditioning, ``num_video_frames`` = T, ``image_only_indicator`` (B, T) (zeros: video mode).
Mixing: ``alpha = sigmoid(mix_factor)`` (1 where ``image_only_indicator`` is set),
``alpha * spatial + (1 - alpha) * temporal``.

The architecture is built from a config dict that :func:`config_from_state_dict` reads from the
tensors' shapes (``num_head_channels``, which no shape shows, is taken as ``min(64, gcd of the
attention widths)``: 64 for SV3D, 32 for the tiny model), so a tiny model with the same keys loads
through the same code (:func:`tiny_config`, :func:`tiny_state_dict`).
"""

from __future__ import annotations

import math
from functools import reduce
from typing import Any

import torch
import torch.nn.functional as F
import torch.utils.checkpoint
from torch import nn

from humanvdm_core.models.checkpoint import CheckpointError

PREFIX = "model.diffusion_model."
DEFAULT_HEAD_CHANNELS = 64

SV3D_CONFIG: dict[str, Any] = {
    "in_channels": 8, "out_channels": 4, "model_channels": 320, "channel_mult": (1, 2, 4, 4),
    "num_res_blocks": 2, "attention_resolutions": (1, 2, 4), "num_head_channels": 64,
    "transformer_depth": (1, 1, 1, 1), "transformer_depth_middle": 1, "context_dim": 1024,
    "adm_in_channels": 1280, "video_kernel_size": (3, 1, 1), "use_linear": True,
}


def tiny_config(adm_in_channels: int = 1280, context_dim: int = 32) -> dict[str, Any]:
    """A few-hundred-kilobyte VideoUNet with every key family of the official one (two levels,
    attention at both, one res block per level)."""
    return {"in_channels": 8, "out_channels": 4, "model_channels": 32, "channel_mult": (1, 2),
            "num_res_blocks": 1, "attention_resolutions": (1, 2), "num_head_channels": 32,
            "transformer_depth": (1, 1), "transformer_depth_middle": 1, "context_dim": context_dim,
            "adm_in_channels": adm_in_channels, "video_kernel_size": (3, 1, 1), "use_linear": True}


# ----------------------------------------------------------------------------- building blocks

def timestep_embedding(t: torch.Tensor, dim: int, max_period: float = 10000.0) -> torch.Tensor:
    """sgm's sinusoidal embedding: ``[cos(t f), sin(t f)]`` with ``f = max_period^(-i / half)``."""
    half = dim // 2
    freqs = torch.exp(-math.log(max_period) * torch.arange(half, dtype=torch.float32, device=t.device) / half)
    args = t[:, None].float() * freqs[None]
    emb = torch.cat([torch.cos(args), torch.sin(args)], dim=-1)
    if dim % 2:
        emb = torch.cat([emb, torch.zeros_like(emb[:, :1])], dim=-1)
    return emb


class GroupNorm32(nn.GroupNorm):
    """GroupNorm(32) computed in float32 (sgm's ``normalization``)."""

    def __init__(self, channels: int, eps: float = 1e-5):
        super().__init__(32, channels, eps=eps)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.group_norm(x.float(), self.num_groups, self.weight.float() if self.weight is not None else None,
                            self.bias.float() if self.bias is not None else None, self.eps).type(x.dtype)


def _mix(mix_factor: torch.Tensor, image_only_indicator: torch.Tensor) -> torch.Tensor:
    """(B, T) blending weight of the spatial branch (AlphaBlender, learned_with_images)."""
    return torch.where(image_only_indicator.bool(), torch.ones_like(image_only_indicator, dtype=torch.float32),
                       torch.sigmoid(mix_factor.float()).reshape(1, 1))


class ResBlock(nn.Module):
    """openaimodel ``ResBlock`` without scale-shift norm; 2-D (spatial) or 3-D (over frames)."""

    def __init__(self, channels: int, emb_channels: int, out_channels: int, dims: int = 2,
                 kernel_size: tuple[int, ...] | int = 3, exchange_temb_dims: bool = False):
        super().__init__()
        conv = nn.Conv3d if dims == 3 else nn.Conv2d
        padding = [k // 2 for k in kernel_size] if isinstance(kernel_size, (tuple, list)) else kernel_size // 2
        self.exchange_temb_dims = exchange_temb_dims
        self.in_layers = nn.Sequential(GroupNorm32(channels), nn.SiLU(),
                                       conv(channels, out_channels, kernel_size, padding=padding))
        self.emb_layers = nn.Sequential(nn.SiLU(), nn.Linear(emb_channels, out_channels))
        self.out_layers = nn.Sequential(GroupNorm32(out_channels), nn.SiLU(), nn.Dropout(0.0),
                                        conv(out_channels, out_channels, kernel_size, padding=padding))
        self.skip_connection = nn.Identity() if out_channels == channels else conv(channels, out_channels, 1)

    def forward(self, x: torch.Tensor, emb: torch.Tensor) -> torch.Tensor:
        h = self.in_layers(x)
        e = self.emb_layers(emb).type(h.dtype)
        while e.ndim < h.ndim:
            e = e[..., None]
        if self.exchange_temb_dims:  # (b, t, c, 1, 1) -> (b, c, t, 1, 1)
            e = e.transpose(1, 2)
        return self.skip_connection(x) + self.out_layers(h + e)


class VideoResBlock(ResBlock):
    """A spatial ResBlock, then a temporal ResBlock (``time_stack``) blended by ``time_mixer``."""

    def __init__(self, channels: int, emb_channels: int, out_channels: int, video_kernel_size=(3, 1, 1)):
        super().__init__(channels, emb_channels, out_channels)
        self.time_stack = ResBlock(out_channels, emb_channels, out_channels, dims=3,
                                   kernel_size=tuple(video_kernel_size), exchange_temb_dims=True)
        self.time_mixer = _Mixer()

    def forward(self, x: torch.Tensor, emb: torch.Tensor, num_frames: int,  # type: ignore[override]
                image_only_indicator: torch.Tensor) -> torch.Tensor:
        x = super().forward(x, emb)
        bt, c, h, w = x.shape
        b = bt // num_frames
        spatial = x.reshape(b, num_frames, c, h, w).transpose(1, 2)  # b c t h w
        temporal = self.time_stack(spatial, emb.reshape(b, num_frames, -1))
        alpha = _mix(self.time_mixer.mix_factor, image_only_indicator).to(x.dtype)[:, None, :, None, None]
        out = alpha * spatial + (1.0 - alpha) * temporal
        return out.transpose(1, 2).reshape(bt, c, h, w)


class _Mixer(nn.Module):
    """Holds ``mix_factor`` (sgm ``AlphaBlender``; the key is ``time_mixer.mix_factor``)."""

    def __init__(self, alpha: float = 0.5):
        super().__init__()
        self.mix_factor = nn.Parameter(torch.tensor([alpha]))


class Downsample(nn.Module):
    def __init__(self, channels: int):
        super().__init__()
        self.op = nn.Conv2d(channels, channels, 3, stride=2, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.op(x)


class Upsample(nn.Module):
    def __init__(self, channels: int):
        super().__init__()
        self.conv = nn.Conv2d(channels, channels, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.conv(F.interpolate(x, scale_factor=2, mode="nearest"))


class CrossAttention(nn.Module):
    def __init__(self, query_dim: int, heads: int, dim_head: int, context_dim: int | None = None):
        super().__init__()
        inner = heads * dim_head
        context_dim = context_dim or query_dim
        self.heads = heads
        self.to_q = nn.Linear(query_dim, inner, bias=False)
        self.to_k = nn.Linear(context_dim, inner, bias=False)
        self.to_v = nn.Linear(context_dim, inner, bias=False)
        self.to_out = nn.Sequential(nn.Linear(inner, query_dim), nn.Dropout(0.0))

    def forward(self, x: torch.Tensor, context: torch.Tensor | None = None) -> torch.Tensor:
        context = x if context is None else context
        b, n, _ = x.shape
        h = self.heads
        q, k, v = self.to_q(x), self.to_k(context), self.to_v(context)
        q, k, v = (t.reshape(b, t.shape[1], h, -1).transpose(1, 2) for t in (q, k, v))
        out = F.scaled_dot_product_attention(q, k, v)
        return self.to_out(out.transpose(1, 2).reshape(b, n, -1))


class GEGLU(nn.Module):
    def __init__(self, dim_in: int, dim_out: int):
        super().__init__()
        self.proj = nn.Linear(dim_in, dim_out * 2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x, gate = self.proj(x).chunk(2, dim=-1)
        return x * F.gelu(gate)


class FeedForward(nn.Module):
    def __init__(self, dim: int, dim_out: int | None = None, mult: int = 4):
        super().__init__()
        inner = int(dim * mult)
        self.net = nn.Sequential(GEGLU(dim, inner), nn.Dropout(0.0), nn.Linear(inner, dim_out or dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)


class BasicTransformerBlock(nn.Module):
    """Self-attention, cross-attention to ``context``, gated feed-forward (pre-norm, residual)."""

    def __init__(self, dim: int, heads: int, dim_head: int, context_dim: int):
        super().__init__()
        self.attn1 = CrossAttention(dim, heads, dim_head)
        self.ff = FeedForward(dim)
        self.attn2 = CrossAttention(dim, heads, dim_head, context_dim)
        self.norm1, self.norm2, self.norm3 = nn.LayerNorm(dim), nn.LayerNorm(dim), nn.LayerNorm(dim)

    def forward(self, x: torch.Tensor, context: torch.Tensor) -> torch.Tensor:
        x = self.attn1(self.norm1(x)) + x
        x = self.attn2(self.norm2(x), context) + x
        return self.ff(self.norm3(x)) + x


class VideoTransformerBlock(nn.Module):
    """Attention across the T frames of each pixel (sgm ``VideoTransformerBlock`` with ``ff_in``)."""

    def __init__(self, dim: int, heads: int, dim_head: int, context_dim: int):
        super().__init__()
        self.norm_in = nn.LayerNorm(dim)
        self.ff_in = FeedForward(dim, dim_out=dim)
        self.attn1 = CrossAttention(dim, heads, dim_head)
        self.ff = FeedForward(dim, dim_out=dim)
        self.norm2 = nn.LayerNorm(dim)
        self.attn2 = CrossAttention(dim, heads, dim_head, context_dim)
        self.norm1, self.norm3 = nn.LayerNorm(dim), nn.LayerNorm(dim)

    def forward(self, x: torch.Tensor, context: torch.Tensor, num_frames: int) -> torch.Tensor:
        bt, s, c = x.shape
        b = bt // num_frames
        x = x.reshape(b, num_frames, s, c).transpose(1, 2).reshape(b * s, num_frames, c)
        x = self.ff_in(self.norm_in(x)) + x
        x = self.attn1(self.norm1(x)) + x
        x = self.attn2(self.norm2(x), context) + x
        x = self.ff(self.norm3(x)) + x
        return x.reshape(b, s, num_frames, c).transpose(1, 2).reshape(bt, s, c)


class SpatialVideoTransformer(nn.Module):
    def __init__(self, channels: int, heads: int, dim_head: int, depth: int, context_dim: int,
                 use_linear: bool = True):
        super().__init__()
        inner = heads * dim_head
        self.use_linear = use_linear
        self.norm = GroupNorm32(channels, eps=1e-6)
        self.proj_in = nn.Linear(channels, inner) if use_linear else nn.Conv2d(channels, inner, 1)
        self.transformer_blocks = nn.ModuleList(
            [BasicTransformerBlock(inner, heads, dim_head, context_dim) for _ in range(depth)])
        self.time_stack = nn.ModuleList(
            [VideoTransformerBlock(inner, heads, dim_head, context_dim) for _ in range(depth)])
        self.time_pos_embed = nn.Sequential(nn.Linear(channels, 4 * channels), nn.SiLU(),
                                            nn.Linear(4 * channels, channels))
        self.time_mixer = _Mixer()
        self.proj_out = nn.Linear(inner, channels) if use_linear else nn.Conv2d(inner, channels, 1)
        self.channels = channels

    def forward(self, x: torch.Tensor, context: torch.Tensor, num_frames: int,
                image_only_indicator: torch.Tensor) -> torch.Tensor:
        bt, c, h, w = x.shape
        b = bt // num_frames
        x_in = x
        # use_spatial_context: the temporal blocks attend to the first frame's context, per pixel
        time_context = context[::num_frames].repeat_interleave(h * w, dim=0)
        x = self.norm(x)
        if not self.use_linear:
            x = self.proj_in(x)
        x = x.permute(0, 2, 3, 1).reshape(bt, h * w, -1)
        if self.use_linear:
            x = self.proj_in(x)
        frames = torch.arange(num_frames, device=x.device).repeat(b)
        emb = self.time_pos_embed(timestep_embedding(frames, self.channels).to(x.dtype))[:, None, :]
        alpha = _mix(self.time_mixer.mix_factor, image_only_indicator).reshape(bt, 1, 1).to(x.dtype)
        for block, mix_block in zip(self.transformer_blocks, self.time_stack, strict=True):
            x = block(x, context)
            x_mix = mix_block(x + emb, time_context, num_frames)
            x = alpha * x + (1.0 - alpha) * x_mix
        if self.use_linear:
            x = self.proj_out(x)
        x = x.reshape(bt, h, w, -1).permute(0, 3, 1, 2)
        if not self.use_linear:
            x = self.proj_out(x)
        return x + x_in


class Step(nn.Sequential):
    """``TimestepEmbedSequential``: passes the embedding / context to the layers that take them."""

    def forward(self, x, emb, context, num_frames, image_only_indicator):  # type: ignore[override]
        for layer in self:
            if isinstance(layer, VideoResBlock):
                x = layer(x, emb, num_frames, image_only_indicator)
            elif isinstance(layer, SpatialVideoTransformer):
                x = layer(x, context, num_frames, image_only_indicator)
            else:
                x = layer(x)
        return x


class VideoUNet(nn.Module):
    """sgm's ``VideoUNet`` (see the module docstring); ``config`` as :data:`SV3D_CONFIG`."""

    def __init__(self, config: dict[str, Any]):
        super().__init__()
        cfg = dict(config)
        self.config = cfg
        mc, mult = cfg["model_channels"], tuple(cfg["channel_mult"])
        nrb, attn_res = cfg["num_res_blocks"], tuple(cfg["attention_resolutions"])
        depth = tuple(cfg["transformer_depth"])
        ctx, hc, kernel, lin = cfg["context_dim"], cfg["num_head_channels"], cfg["video_kernel_size"], cfg["use_linear"]
        emb_dim = 4 * mc
        self.model_channels = mc
        self.num_levels = len(mult)
        self.gradient_checkpointing = False  # recompute each block in backward (training memory)

        def res(ci: int, co: int) -> VideoResBlock:
            return VideoResBlock(ci, emb_dim, co, kernel)

        def attn(ch: int, d: int) -> SpatialVideoTransformer:
            return SpatialVideoTransformer(ch, ch // hc, hc, d, ctx, lin)

        self.time_embed = nn.Sequential(nn.Linear(mc, emb_dim), nn.SiLU(), nn.Linear(emb_dim, emb_dim))
        self.label_emb = nn.Sequential(nn.Sequential(nn.Linear(cfg["adm_in_channels"], emb_dim), nn.SiLU(),
                                                     nn.Linear(emb_dim, emb_dim)))
        self.input_blocks = nn.ModuleList([Step(nn.Conv2d(cfg["in_channels"], mc, 3, padding=1))])
        chans, ch, ds = [mc], mc, 1
        for level, m in enumerate(mult):
            for _ in range(nrb):
                layers: list[nn.Module] = [res(ch, m * mc)]
                ch = m * mc
                if ds in attn_res:
                    layers.append(attn(ch, depth[level]))
                self.input_blocks.append(Step(*layers))
                chans.append(ch)
            if level != len(mult) - 1:
                self.input_blocks.append(Step(Downsample(ch)))
                chans.append(ch)
                ds *= 2
        self.middle_block = Step(res(ch, ch), attn(ch, cfg["transformer_depth_middle"]), res(ch, ch))
        self.output_blocks = nn.ModuleList()
        for level, m in list(enumerate(mult))[::-1]:
            for i in range(nrb + 1):
                layers = [res(ch + chans.pop(), m * mc)]
                ch = m * mc
                if ds in attn_res:
                    layers.append(attn(ch, depth[level]))
                if level and i == nrb:
                    layers.append(Upsample(ch))
                    ds //= 2
                self.output_blocks.append(Step(*layers))
        self.out = nn.Sequential(GroupNorm32(ch), nn.SiLU(), nn.Conv2d(ch, cfg["out_channels"], 3, padding=1))

    @property
    def downsample_factor(self) -> int:
        """The latent's side must be a multiple of this."""
        return 2 ** (self.num_levels - 1)

    def forward(self, x: torch.Tensor, timesteps: torch.Tensor, context: torch.Tensor, y: torch.Tensor,
                num_video_frames: int, image_only_indicator: torch.Tensor) -> torch.Tensor:
        emb = self.time_embed(timestep_embedding(timesteps, self.model_channels).to(x.dtype))
        emb = emb + self.label_emb(y.to(emb.dtype))

        def run(block: Step, h: torch.Tensor) -> torch.Tensor:
            if self.gradient_checkpointing and self.training and torch.is_grad_enabled():
                return torch.utils.checkpoint.checkpoint(block, h, emb, context, num_video_frames,
                                                         image_only_indicator, use_reentrant=False)
            return block(h, emb, context, num_video_frames, image_only_indicator)

        hs, h = [], x
        for block in self.input_blocks:
            h = run(block, h)
            hs.append(h)
        h = run(self.middle_block, h)
        for block in self.output_blocks:
            h = run(block, torch.cat([h, hs.pop()], dim=1))
        return self.out(h.type(x.dtype))


# ----------------------------------------------------------------------------- config from tensors

def config_from_state_dict(sd: dict, path: str = "checkpoint") -> dict[str, Any]:
    """The :class:`VideoUNet` config of a state dict in the layout above (keys without ``PREFIX``)."""
    need = ["time_embed.0.weight", "label_emb.0.0.weight", "input_blocks.0.0.weight", "out.2.weight"]
    missing = [k for k in need if k not in sd]
    if missing:
        raise CheckpointError(f"{path}: not an SV3D VideoUNet in the sgm layout; missing keys "
                              f"{[PREFIX + k for k in missing]}")
    mc = int(sd["time_embed.0.weight"].shape[1])
    blocks = []  # per input block after the first: ("res", out_ch, has_attn, depth) or ("down",)
    i = 1
    while f"input_blocks.{i}.0.op.weight" in sd or f"input_blocks.{i}.0.in_layers.0.weight" in sd:
        if f"input_blocks.{i}.0.op.weight" in sd:
            blocks.append(("down",))
        else:
            out_ch = int(sd[f"input_blocks.{i}.0.out_layers.3.weight"].shape[0])
            depth = _transformer_depth(sd, f"input_blocks.{i}.1.")
            blocks.append(("res", out_ch, depth))
        i += 1
    levels: list[list[tuple]] = [[]]
    for b in blocks:
        if b[0] == "down":
            levels.append([])
        else:
            levels[-1].append(b)
    nrb = len(levels[0])
    if nrb == 0 or any(len(lv) != nrb for lv in levels):
        raise CheckpointError(f"{path}: unexpected VideoUNet block structure (res blocks per level "
                              f"{[len(lv) for lv in levels]})")
    channel_mult = tuple(lv[-1][1] // mc for lv in levels)
    attention_resolutions = tuple(2 ** k for k, lv in enumerate(levels) if lv[0][2] > 0)
    depth = tuple(max(lv[0][2], 1) for lv in levels)
    attn_widths = [mc * m for m, lv in zip(channel_mult, levels, strict=True) if lv[0][2] > 0]
    attn_widths.append(mc * channel_mult[-1])  # the middle block always has attention
    head_channels = min(DEFAULT_HEAD_CHANNELS, reduce(math.gcd, attn_widths))
    ctx_key = next((k for k in sd if k.endswith("transformer_blocks.0.attn2.to_k.weight")), None)
    proj_in = next((k for k in sd if k.endswith(".proj_in.weight")), None)
    kernel_key = "input_blocks.1.0.time_stack.in_layers.2.weight"
    if ctx_key is None or proj_in is None or kernel_key not in sd:
        raise CheckpointError(f"{path}: not an SV3D VideoUNet: no spatial-video transformer / temporal "
                              f"res-block keys (e.g. {PREFIX}{kernel_key})")
    return {
        "in_channels": int(sd["input_blocks.0.0.weight"].shape[1]),
        "out_channels": int(sd["out.2.weight"].shape[0]),
        "model_channels": mc,
        "channel_mult": channel_mult,
        "num_res_blocks": nrb,
        "attention_resolutions": attention_resolutions,
        "num_head_channels": head_channels,
        "transformer_depth": depth,
        "transformer_depth_middle": max(_transformer_depth(sd, "middle_block.1."), 1),
        "context_dim": int(sd[ctx_key].shape[1]),
        "adm_in_channels": int(sd["label_emb.0.0.weight"].shape[1]),
        "video_kernel_size": tuple(int(k) for k in sd[kernel_key].shape[2:]),
        "use_linear": sd[proj_in].ndim == 2,
    }


def _transformer_depth(sd: dict, prefix: str) -> int:
    d = 0
    while f"{prefix}transformer_blocks.{d}.norm1.weight" in sd:
        d += 1
    return d


def tiny_state_dict(config: dict[str, Any] | None = None, seed: int = 0) -> dict[str, torch.Tensor]:
    """Random weights of a tiny :class:`VideoUNet` (keys relative to ``PREFIX``), with random mix
    factors so that both the spatial and the temporal branches matter."""
    gen = torch.Generator().manual_seed(seed)
    net = VideoUNet(config or tiny_config())
    sd = {}
    for k, v in net.state_dict().items():
        if k.endswith("mix_factor"):
            sd[k] = torch.randn(v.shape, generator=gen)
        elif v.ndim >= 2:
            fan_in = max(1, v[0].numel())
            sd[k] = torch.randn(v.shape, generator=gen) / math.sqrt(fan_in)
        elif k.endswith("weight"):  # norms
            sd[k] = 1.0 + 0.1 * torch.randn(v.shape, generator=gen)
        else:
            sd[k] = 0.02 * torch.randn(v.shape, generator=gen)
    return sd

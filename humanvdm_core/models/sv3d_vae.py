"""SV3D's two autoencoder parts in pure PyTorch, in the official checkpoint key layout.

SV3D (``sv3d_u.safetensors`` / ``sv3d_p.safetensors``) is an sgm ``DiffusionEngine``
(Stability-AI/generative-models, ``configs/inference/sv3d_{u,p}.yaml``).  This module re-implements
(no code copied) the two autoencoder parts the sampler needs, named so that the official tensors
load with :func:`~humanvdm_core.models.checkpoint.load_strict`:

**The conditioning-frame encoder** -- ``conditioner.embedders.1`` is a
``VideoPredictionEmbedderWithEncoder`` whose ``encoder`` is an ``AutoencoderKLModeOnly``
(``sgm/models/autoencoder.py``: an ``AutoencodingEngineLegacy`` with ch 128, ch_mult [1, 2, 4, 4],
2 ResnetBlocks per level, no attention but the middle one, double_z, z 4, embed_dim 4).  Its full
state dict is stored under ``conditioner.embedders.1.encoder.`` (:data:`COND_ENCODER_PREFIX`)::

    encoder.conv_in.{weight,bias}
    encoder.down.<L>.block.<B>.{norm1,conv1,norm2,conv2}.{weight,bias} [+ nin_shortcut when widths differ]
    encoder.down.<L>.downsample.conv.{weight,bias}            (L < last level; pad (0,1,0,1), stride 2)
    encoder.mid.{block_1,block_2}.*  encoder.mid.attn_1.{norm,q,k,v,proj_out}.{weight,bias}
    encoder.norm_out.*  encoder.conv_out.*                    (-> 2 * z_channels: mean and log-variance)
    quant_conv.{weight,bias}                                  (1x1, 8 -> 8)
    decoder.*  post_quant_conv.*                              (the AE's 2-D image decoder: IGNORED)

``AutoencodingEngineLegacy`` always builds ``decoder`` and ``post_quant_conv`` and the engine saves
them (ComfyUI loads SV3D's VAE, encoder and decoder, from this very prefix), so
:func:`build_cond_encoder` drops exactly the keys starting with ``decoder.`` and ``post_quant_conv.``
(present or not) and loads everything else strictly.  ``encode`` is the ``DiagonalGaussianRegularizer
(sample=False)`` mode: the first ``embed_dim`` channels of ``quant_conv(encoder(x))``.  NOTE: sgm's
``VideoPredictionEmbedderWithEncoder`` multiplies this latent by its own ``scale_factor``, which
defaults to 1.0 and is not set in the SV3D configs -- the conditioning latent is NOT multiplied by
0.18215 (only the first-stage latents are).

**The temporal video decoder** -- ``first_stage_model`` is an ``AutoencodingEngine`` whose encoder is
``torch.nn.Identity`` (no tensors; SV3D ships no first-stage encoder) and whose decoder is
``sgm.modules.autoencoding.temporal_ae.VideoDecoder`` (time_mode "conv-only", merge_strategy
"learned", video_kernel_size [3, 1, 1]).  Keys under ``first_stage_model.`` (:data:`FIRST_STAGE_PREFIX`)::

    decoder.conv_in.{weight,bias}                              (z 4 -> 512)
    decoder.mid.block_{1,2}.{norm1,conv1,norm2,conv2}.*        (VideoResBlock: spatial ResnetBlock ...)
    decoder.mid.block_{1,2}.time_stack.in_layers.{0,2}.*       (... + GroupNorm, Conv3d (3,1,1))
    decoder.mid.block_{1,2}.time_stack.out_layers.{0,3}.*      (... + GroupNorm, Conv3d (3,1,1))
    decoder.mid.block_{1,2}.mix_factor                         (shape (1,); alpha = sigmoid(mix_factor))
    decoder.mid.attn_1.{norm,q,k,v,proj_out}.*                 (plain spatial AttnBlock: conv-only mode)
    decoder.up.<L>.block.<B>.*                                 (3 VideoResBlocks per level, as mid)
    decoder.up.<L>.upsample.conv.*                             (L > 0; nearest x2 then 3x3 conv)
    decoder.norm_out.*  decoder.conv_out.{weight,bias}         (AE3DConv: a 3x3 Conv2d ...)
    decoder.conv_out.time_mix_conv.{weight,bias}               (... followed by a Conv3d (3,1,1) over time)

The temporal layers mix the ``num_frames`` consecutive images of each group of a call's batch
(``(b t) c h w``, frames contiguous), with zero padding in time at the group's ends -- so decoding
in chunks, as sgm's ``decode_first_stage`` does with ``en_and_decode_n_samples_a_time`` (passing the
chunk length as the frame count), is not bit-identical to decoding a whole orbit at once.

Both networks are built from the tensors' shapes (level widths, res blocks per level, z channels,
attention per level, temporal kernel), so a tiny model with the same key names loads through the
same code (:func:`tiny_cond_encoder_state_dict`, :func:`tiny_video_decoder_state_dict`: ch 32 so
``GroupNorm(32, C)`` accepts every width, 4 levels, hence the real downsampling factor 8).
Normalisation: sgm's ``Normalize`` (GroupNorm 32, eps 1e-6) in the spatial layers, its
``GroupNorm32`` (eps 1e-5, computed in float32) in ``time_stack``.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from humanvdm_core.models.blocks import AttnBlock, Downsample, Upsample, group_norm
from humanvdm_core.models.checkpoint import CheckpointError, load_strict

FIRST_STAGE_PREFIX = "first_stage_model."
COND_ENCODER_PREFIX = "conditioner.embedders.1.encoder."
COND_ENCODER_IGNORED_PREFIXES = ("decoder.", "post_quant_conv.")
WHAT_ENCODER = "SV3D conditioning-frame encoder (AutoencoderKLModeOnly)"
WHAT_DECODER = "SV3D first-stage VideoDecoder"
TINY_CH, TINY_CH_MULT = 32, (1, 1, 2, 2)


class GroupNorm32(nn.GroupNorm):
    """sgm's ``GroupNorm32``: GroupNorm(32, C) (eps 1e-5) computed in float32."""

    def __init__(self, ch: int):
        super().__init__(32, ch)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return super().forward(x.float()).to(x.dtype)


class ResnetBlock(nn.Module):
    """sgm ``ResnetBlock`` without time embedding: norm1, conv1, norm2, conv2 [, nin_shortcut]."""

    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.norm1, self.conv1 = group_norm(cin), nn.Conv2d(cin, cout, 3, 1, 1)
        self.norm2, self.conv2 = group_norm(cout), nn.Conv2d(cout, cout, 3, 1, 1)
        self.nin_shortcut = nn.Conv2d(cin, cout, 1) if cin != cout else None

    def spatial(self, x: torch.Tensor) -> torch.Tensor:
        h = self.conv1(F.silu(self.norm1(x)))
        h = self.conv2(F.silu(self.norm2(h)))
        return h + (self.nin_shortcut(x) if self.nin_shortcut is not None else x)

    def forward(self, x: torch.Tensor, num_frames: int | None = None) -> torch.Tensor:
        return self.spatial(x)


class TimeStack(nn.Module):
    """sgm openaimodel ``ResBlock(dims=3, skip_t_emb=True)``: x + out_layers(in_layers(x)) on (B, C, T, H, W)."""

    def __init__(self, ch: int, kernel: tuple[int, int, int]):
        super().__init__()
        pad = tuple(k // 2 for k in kernel)
        self.in_layers = nn.Sequential(GroupNorm32(ch), nn.SiLU(), nn.Conv3d(ch, ch, kernel, padding=pad))
        self.out_layers = nn.Sequential(GroupNorm32(ch), nn.SiLU(), nn.Dropout(0.0),
                                        nn.Conv3d(ch, ch, kernel, padding=pad))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.out_layers(self.in_layers(x))


def _to_video(x: torch.Tensor, num_frames: int) -> torch.Tensor:
    """(B*T, C, H, W) -> (B, C, T, H, W)."""
    bt, c, h, w = x.shape
    if num_frames <= 0 or bt % num_frames:
        raise ValueError(f"a batch of {bt} images is not a whole number of {num_frames}-frame videos")
    return x.reshape(bt // num_frames, num_frames, c, h, w).transpose(1, 2)


def _to_images(x: torch.Tensor) -> torch.Tensor:
    """(B, C, T, H, W) -> (B*T, C, H, W)."""
    b, c, t, h, w = x.shape
    return x.transpose(1, 2).reshape(b * t, c, h, w)


class VideoResBlock(ResnetBlock):
    """sgm ``VideoResBlock``: spatial ResnetBlock, then ``time_stack`` merged with a learned alpha."""

    def __init__(self, cin: int, cout: int, kernel: tuple[int, int, int]):
        super().__init__(cin, cout)
        self.time_stack = TimeStack(cout, kernel)
        self.mix_factor = nn.Parameter(torch.zeros(1))

    def forward(self, x: torch.Tensor, num_frames: int | None = None) -> torch.Tensor:
        x = self.spatial(x)
        if num_frames is None:
            return x
        v = _to_video(x, num_frames)
        alpha = torch.sigmoid(self.mix_factor).to(v.dtype)
        return _to_images(alpha * self.time_stack(v) + (1.0 - alpha) * v)


class AE3DConv(nn.Conv2d):
    """sgm ``AE3DConv``: a Conv2d followed by ``time_mix_conv``, a Conv3d over (T, H, W)."""

    def __init__(self, cin: int, cout: int, kernel: tuple[int, int, int]):
        super().__init__(cin, cout, 3, 1, 1)
        self.time_mix_conv = nn.Conv3d(cout, cout, kernel, padding=tuple(k // 2 for k in kernel))

    def forward(self, x: torch.Tensor, num_frames: int | None = None) -> torch.Tensor:
        x = super().forward(x)
        if num_frames is None:
            return x
        return _to_images(self.time_mix_conv(_to_video(x, num_frames)))


class _Level(nn.Module):
    """One resolution of the encoder (``down.<L>``) or decoder (``up.<L>``): block, attn, resampler."""

    def __init__(self, blocks: list[nn.Module], attn: list[nn.Module]):
        super().__init__()
        self.block, self.attn = nn.ModuleList(blocks), nn.ModuleList(attn)


class _Mid(nn.Module):
    def __init__(self, make_block, ch: int):
        super().__init__()
        self.block_1, self.attn_1, self.block_2 = make_block(ch, ch), AttnBlock(ch), make_block(ch, ch)

    def forward(self, x: torch.Tensor, num_frames: int | None = None) -> torch.Tensor:
        return self.block_2(self.attn_1(self.block_1(x, num_frames)), num_frames)


class Encoder(nn.Module):
    """sgm ``Encoder`` (no time embedding): ``widths[L]`` = ch * ch_mult[L]; ``attn[L]``: attention per block."""

    def __init__(self, ch: int, widths: tuple[int, ...], num_res_blocks: int, out_channels: int,
                 attn: tuple[bool, ...] | None = None, in_channels: int = 3):
        super().__init__()
        attn = attn or (False,) * len(widths)
        self.conv_in = nn.Conv2d(in_channels, ch, 3, 1, 1)
        self.down = nn.ModuleList()
        cin = ch
        for lv, width in enumerate(widths):
            blocks, attns = [], []
            for _ in range(num_res_blocks):
                blocks.append(ResnetBlock(cin, width))
                cin = width
                if attn[lv]:
                    attns.append(AttnBlock(width))
            level = _Level(blocks, attns)
            if lv != len(widths) - 1:
                level.downsample = Downsample(width)
            self.down.append(level)
        self.mid = _Mid(ResnetBlock, cin)
        self.norm_out = group_norm(cin)
        self.conv_out = nn.Conv2d(cin, out_channels, 3, 1, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = self.conv_in(x)
        for level in self.down:
            for i, block in enumerate(level.block):
                h = block(h)
                if len(level.attn):
                    h = level.attn[i](h)
            if hasattr(level, "downsample"):
                h = level.downsample(h)
        h = self.mid(h)
        return self.conv_out(F.silu(self.norm_out(h)))


class Decoder(nn.Module):
    """sgm ``Decoder`` (``video_kernel`` None) or ``VideoDecoder`` (time_mode conv-only, learned merge).

    ``forward(z, num_frames)``: z (B*T, z, h, w) -> (B*T, out_ch, h*f, w*f) with f = 2**(levels-1),
    unclamped; ``num_frames`` is required for the video decoder (frames of a video contiguous).
    """

    def __init__(self, widths: tuple[int, ...], num_res_blocks: int, z_channels: int, out_channels: int = 3,
                 attn: tuple[bool, ...] | None = None, video_kernel: tuple[int, int, int] | None = None):
        super().__init__()
        attn = attn or (False,) * len(widths)
        self.video_kernel = video_kernel

        def block(cin: int, cout: int) -> nn.Module:
            return ResnetBlock(cin, cout) if video_kernel is None else VideoResBlock(cin, cout, video_kernel)

        cin = widths[-1]
        self.conv_in = nn.Conv2d(z_channels, cin, 3, 1, 1)
        self.mid = _Mid(block, cin)
        levels: list[nn.Module] = [nn.Module()] * len(widths)
        for lv in reversed(range(len(widths))):
            blocks, attns = [], []
            for _ in range(num_res_blocks + 1):
                blocks.append(block(cin, widths[lv]))
                cin = widths[lv]
                if attn[lv]:
                    attns.append(AttnBlock(cin))
            level = _Level(blocks, attns)
            if lv != 0:
                level.upsample = Upsample(cin)
            levels[lv] = level
        self.up = nn.ModuleList(levels)
        self.norm_out = group_norm(cin)
        self.conv_out = (nn.Conv2d(cin, out_channels, 3, 1, 1) if video_kernel is None
                         else AE3DConv(cin, out_channels, video_kernel))

    def forward(self, z: torch.Tensor, num_frames: int | None = None) -> torch.Tensor:
        if self.video_kernel is not None and num_frames is None:
            raise ValueError("the video decoder needs num_frames (the frames of one video in the batch)")
        t = num_frames if self.video_kernel is not None else None
        h = self.mid(self.conv_in(z), t)
        for lv in reversed(range(len(self.up))):
            level = self.up[lv]
            for i, block in enumerate(level.block):
                h = block(h, t)
                if len(level.attn):
                    h = level.attn[i](h)
            if hasattr(level, "upsample"):
                h = level.upsample(h)
        h = F.silu(self.norm_out(h))
        return self.conv_out(h, t) if self.video_kernel is not None else self.conv_out(h)


class CondFrameEncoder(nn.Module):
    """``encoder`` + ``quant_conv`` of SV3D's ``AutoencoderKLModeOnly`` (keys as in the module docstring)."""

    def __init__(self, ch: int, widths: tuple[int, ...], num_res_blocks: int, z_channels: int, embed_dim: int,
                 attn: tuple[bool, ...] | None = None):
        super().__init__()
        self.encoder = Encoder(ch, widths, num_res_blocks, 2 * z_channels, attn)
        self.quant_conv = nn.Conv2d(2 * z_channels, 2 * embed_dim, 1)
        self.embed_dim = embed_dim
        self.downsample_factor = 2 ** (len(widths) - 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.quant_conv(self.encoder(x))[:, : self.embed_dim]

    @torch.no_grad()
    def encode(self, x: torch.Tensor) -> torch.Tensor:
        """x (B, 3, H, W) in [-1, 1], H and W multiples of ``downsample_factor`` -> latent mean
        (B, embed_dim, H/f, W/f), unscaled (the posterior's mode, as ``AutoencoderKLModeOnly``)."""
        f = self.downsample_factor
        if x.ndim != 4 or x.shape[-1] % f or x.shape[-2] % f:
            raise ValueError(f"encode needs (B, 3, H, W) with H, W multiples of {f}, got {tuple(x.shape)}")
        return self(x)


class VideoFirstStage(nn.Module):
    """SV3D's ``first_stage_model``: only ``decoder`` has tensors -- a ``VideoDecoder`` (sv3d_p.yaml), or
    sgm's plain image ``Decoder`` (``video_kernel`` None; sv3d_u.yaml), told apart by the presence of
    any ``time_stack`` / ``time_mix_conv`` tensor; the image decoder ignores ``num_frames``."""

    def __init__(self, widths: tuple[int, ...], num_res_blocks: int, z_channels: int,
                 video_kernel: tuple[int, int, int] | None = (3, 1, 1), attn: tuple[bool, ...] | None = None):
        super().__init__()
        self.decoder = Decoder(widths, num_res_blocks, z_channels, 3, attn, video_kernel)
        self.z_channels = z_channels
        self.downsample_factor = 2 ** (len(widths) - 1)

    def forward(self, z: torch.Tensor, num_frames: int) -> torch.Tensor:
        return self.decoder(z, num_frames)

    @torch.no_grad()
    def decode(self, z: torch.Tensor, num_frames: int) -> torch.Tensor:
        """z (B*T, z, h, w), UNscaled (already divided by scale_factor 0.18215), the T frames of each
        video contiguous -> images (B*T, 3, f*h, f*w) clamped to [-1, 1]; the temporal layers mix
        the ``num_frames`` frames of each video."""
        return self.decoder(z, num_frames).clamp_(-1.0, 1.0)


def decode_chunked(model: VideoFirstStage, z: torch.Tensor, chunk: int) -> torch.Tensor:
    """``model.decode`` over ``chunk`` latents at a time, each call treating its chunk as one video of
    ``len(chunk)`` frames -- sgm's ``decode_first_stage`` with ``en_and_decode_n_samples_a_time``
    (SV3D's sampling script: ``decoding_t``).  Bounds memory; ``chunk >= len(z)`` is one call."""
    if chunk <= 0:
        raise ValueError(f"chunk must be positive, got {chunk}")
    outs = [model.decode(z[i:i + chunk], num_frames=len(z[i:i + chunk])) for i in range(0, len(z), chunk)]
    return torch.cat(outs, 0)


# ----------------------------------------------------------------------------- reading the layout

def _indices(sd: dict, prefix: str) -> list[int]:
    """The sorted distinct integers ``i`` of keys ``prefix + "<i>." + ...``."""
    out = set()
    for k in sd:
        if k.startswith(prefix):
            head = k[len(prefix):].split(".", 1)[0]
            if head.isdigit():
                out.add(int(head))
    return sorted(out)


def _shape(sd: dict, key: str, what: str, path: str) -> tuple[int, ...]:
    if key not in sd:
        raise CheckpointError(f"{path} is not a {what} checkpoint in the expected key layout; "
                              f"missing keys: {key} (found e.g. {', '.join(sorted(sd)[:5]) or 'nothing'})")
    return tuple(int(s) for s in sd[key].shape)


def _levels(sd: dict, prefix: str, what: str, path: str) -> tuple[list[int], int, tuple[bool, ...]]:
    """Per-level output widths, blocks per level and attention flags of ``<prefix><L>.block.<B>``."""
    levels = _indices(sd, prefix)
    if not levels or levels != list(range(len(levels))):
        raise CheckpointError(f"{path} is not a {what} checkpoint: no levels {prefix}<L> (found {levels})")
    widths = [_shape(sd, f"{prefix}{lv}.block.0.conv1.weight", what, path)[0] for lv in levels]
    n_blocks = len(_indices(sd, f"{prefix}0.block."))
    attn = tuple(bool(_indices(sd, f"{prefix}{lv}.attn.")) for lv in levels)
    return widths, n_blocks, attn


def cond_encoder_config(sd: dict, path: str = "state dict") -> dict:
    """``CondFrameEncoder`` arguments from the shapes of a state dict relative to :data:`COND_ENCODER_PREFIX`."""
    ch = _shape(sd, "encoder.conv_in.weight", WHAT_ENCODER, path)[0]
    widths, n_blocks, attn = _levels(sd, "encoder.down.", WHAT_ENCODER, path)
    z2 = _shape(sd, "encoder.conv_out.weight", WHAT_ENCODER, path)[0]
    e2 = _shape(sd, "quant_conv.weight", WHAT_ENCODER, path)[0]
    if z2 % 2 or e2 % 2:
        raise CheckpointError(f"{path}: {WHAT_ENCODER} must be double_z (mean and log-variance), "
                              f"found {z2} encoder and {e2} quant_conv output channels")
    return {"ch": ch, "widths": tuple(widths), "num_res_blocks": n_blocks, "z_channels": z2 // 2,
            "embed_dim": e2 // 2, "attn": attn}


def video_decoder_config(sd: dict, path: str = "state dict") -> dict:
    """``VideoFirstStage`` arguments from the shapes of a state dict relative to :data:`FIRST_STAGE_PREFIX`."""
    z = _shape(sd, "decoder.conv_in.weight", WHAT_DECODER, path)[1]
    widths, n_blocks, attn = _levels(sd, "decoder.up.", WHAT_DECODER, path)
    if not any(".time_stack." in k or ".time_mix_conv." in k for k in sd):  # sv3d_u.yaml's image Decoder
        if n_blocks < 1:
            raise CheckpointError(f"{path}: unexpected {WHAT_DECODER} layout ({n_blocks} blocks)")
        return {"widths": tuple(widths), "num_res_blocks": n_blocks - 1, "z_channels": z,
                "video_kernel": None, "attn": attn}
    kernel = _shape(sd, "decoder.conv_out.time_mix_conv.weight", WHAT_DECODER, path)[2:]
    if len(kernel) != 3 or n_blocks < 1:
        raise CheckpointError(f"{path}: unexpected {WHAT_DECODER} layout (time kernel {kernel}, {n_blocks} blocks)")
    return {"widths": tuple(widths), "num_res_blocks": n_blocks - 1, "z_channels": z,
            "video_kernel": tuple(kernel), "attn": attn}


def _construct(cls, cfg: dict, what: str, path: str):
    try:
        return cls(**cfg)
    except (ValueError, RuntimeError) as e:  # e.g. a width GroupNorm(32) cannot split
        raise CheckpointError(f"{path}: unsupported {what} shapes {cfg}: {e}") from None


def build_cond_encoder(state_dict: dict, path: str = "state dict") -> CondFrameEncoder:
    """The conditioning-frame encoder from a state dict relative to :data:`COND_ENCODER_PREFIX`.

    Keys starting with ``decoder.`` or ``post_quant_conv.`` (the AE's unused image decoder) are
    dropped; every other key must match exactly, else :class:`CheckpointError` lists the mismatch.
    Returned in eval mode, float32, on the CPU.
    """
    sd = {k: v for k, v in state_dict.items() if not k.startswith(COND_ENCODER_IGNORED_PREFIXES)}
    model = _construct(CondFrameEncoder, cond_encoder_config(sd, path), WHAT_ENCODER, path)
    load_strict(model, sd, WHAT_ENCODER, path)
    return model.eval()


def build_video_decoder(state_dict: dict, path: str = "state dict") -> VideoFirstStage:
    """The first-stage video decoder from a state dict relative to :data:`FIRST_STAGE_PREFIX` (all keys
    ``decoder.*``; any other key is reported as unexpected).  Eval mode, float32, CPU."""
    model = _construct(VideoFirstStage, video_decoder_config(state_dict, path), WHAT_DECODER, path)
    load_strict(model, state_dict, WHAT_DECODER, path)
    return model.eval()


def strip_prefix(state_dict: dict, prefix: str) -> dict:
    """The entries of ``state_dict`` under ``prefix``, with the prefix removed."""
    return {k[len(prefix):]: v for k, v in state_dict.items() if k.startswith(prefix)}


# ----------------------------------------------------------------------------- tiny random models

def _random_state_dict(module: nn.Module, seed: int) -> dict:
    """``module``'s tensors, every one perturbed by seeded noise (so zero-initialised layers and the
    mix factors take part), detached and contiguous (safetensors-ready)."""
    gen = torch.Generator().manual_seed(seed)
    out = {}
    for k, v in module.state_dict().items():
        noise = torch.randn(v.shape, generator=gen, dtype=torch.float32)
        scale = 0.5 if k.endswith("mix_factor") else 0.02
        out[k] = (v.float() + scale * noise).contiguous()
    return out


def tiny_cond_encoder_state_dict(seed: int = 0, ch: int = TINY_CH,
                                 ch_mult: tuple[int, ...] = TINY_CH_MULT) -> dict:
    """A tiny random ``AutoencoderKLModeOnly`` state dict in the official layout, keys relative to
    :data:`COND_ENCODER_PREFIX`: ``encoder.*``, ``quant_conv.*`` and, as in the official file, the 2-D
    image ``decoder.*`` and ``post_quant_conv.*`` (1 res block per level, z 4, embed_dim 4)."""
    widths = tuple(ch * m for m in ch_mult)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        enc = CondFrameEncoder(ch, widths, 1, 4, 4)
        ae = nn.Module()
        ae.encoder, ae.quant_conv = enc.encoder, enc.quant_conv
        ae.decoder = Decoder(widths, 1, 4, 3)
        ae.post_quant_conv = nn.Conv2d(4, 4, 1)
    return _random_state_dict(ae, seed)


def tiny_video_decoder_state_dict(seed: int = 0, ch: int = TINY_CH,
                                  ch_mult: tuple[int, ...] = TINY_CH_MULT, video: bool = True) -> dict:
    """A tiny random ``VideoDecoder`` (``video`` False: image ``Decoder``) state dict in the official
    layout, keys relative to :data:`FIRST_STAGE_PREFIX` (``decoder.*``; 1 res block per level, z 4,
    time kernel (3, 1, 1))."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        model = VideoFirstStage(tuple(ch * m for m in ch_mult), 1, 4, (3, 1, 1) if video else None)
    return _random_state_dict(model, seed)

"""CodeFormer (Zhou et al., NeurIPS 2022) face restoration in pure PyTorch, official key layout.

LICENCE: CodeFormer's code and weights are under the S-Lab License 1.0 -- **non-commercial use
only**.  This module re-implements the architecture (no code copied) so that users who accept that
licence can load ``codeformer.pth`` (https://github.com/sczhou/CodeFormer/releases, v0.1.0); the
weights are never shipped nor downloaded by this project.

Architecture (VQGAN encoder -> transformer code prediction -> codebook lookup -> VQGAN generator
with controllable feature transformation from the encoder), keys as in the official checkpoint
(``params_ema``)::

    encoder.blocks.<i>.*    conv, ResBlocks (norm1, conv1, norm2, conv2[, conv_out]), AttnBlocks
                            (norm, q, k, v, proj_out), Downsample (conv), GroupNorm, conv
    quantize.embedding.weight              codebook (codebook_size, emb_dim)
    generator.blocks.<i>.*  conv, ResBlocks, AttnBlocks, Upsample (conv), GroupNorm, conv
    position_emb, feat_emb, ft_layers.<i>.{self_attn, linear1, linear2, norm1, norm2}, idx_pred_layer
    fuse_convs_dict.<res>.{encode_enc, scale, shift}

The official model: nf 64, ch_mult (1, 2, 2, 4, 4, 8), two ResBlocks per resolution, attention at
16², 9 transformer layers of width 512 with 8 heads, codebook 1024 x 256, fuse at 32/64/128/256,
so the face crop is 512².  Everything but the head count (8) is read from the tensors' shapes, so
a tiny model with the same key names (e.g. nf 32, ch_mult (1, 2, 2, 4): 128² crops) loads through
the same code.

:func:`restore_face`: (S, S, 3) RGB in [0, 1] -> RGB in [0, 1]; the network sees [-1, 1] and its
output is clamped to [-1, 1], as the official inference does; ``fidelity`` is CodeFormer's ``w``
(0: best quality, 1: most faithful; the paper uses 0.7).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from humanvdm_core.models.blocks import AttnBlock, Downsample, Upsample, group_norm
from humanvdm_core.models.checkpoint import (
    CheckpointError,
    cached_model,
    deterministic,
    infer_device,
    load_strict,
    read_state_dict,
)

WHAT = "CodeFormer weights (S-Lab License 1.0, non-commercial)"
WHERE = "https://github.com/sczhou/CodeFormer/releases (v0.1.0: codeformer.pth)"
N_HEAD = 8


class ResBlock(nn.Module):
    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.norm1, self.conv1 = group_norm(cin), nn.Conv2d(cin, cout, 3, 1, 1)
        self.norm2, self.conv2 = group_norm(cout), nn.Conv2d(cout, cout, 3, 1, 1)
        self.conv_out = nn.Conv2d(cin, cout, 1) if cin != cout else None

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = self.conv1(F.silu(self.norm1(x)))
        h = self.conv2(F.silu(self.norm2(h)))
        return h + (self.conv_out(x) if self.conv_out is not None else x)


class Coder(nn.Module):
    """A VQGAN encoder or generator: ``blocks`` (ModuleList) run in order."""

    def __init__(self, blocks: list[nn.Module]):
        super().__init__()
        self.blocks = nn.ModuleList(blocks)


def encoder_blocks(nf: int, ch_mult: tuple[int, ...], emb_dim: int, res_blocks: int = 2) -> tuple[list, dict]:
    """Encoder blocks and {resolution index from the top (0 = full size): block index to tap}."""
    blocks: list[nn.Module] = [nn.Conv2d(3, nf, 3, 1, 1)]
    taps: dict[int, int] = {}
    ch = nf
    last = len(ch_mult) - 1
    for i, mult in enumerate(ch_mult):
        for _ in range(res_blocks):
            blocks.append(ResBlock(ch, nf * mult))
            ch = nf * mult
            if i == last:
                blocks.append(AttnBlock(ch))
        if i != last:
            taps[i] = len(blocks) - 1  # the last block at this resolution, before downsampling
            blocks.append(Downsample(ch))
    blocks += [ResBlock(ch, ch), AttnBlock(ch), ResBlock(ch, ch), group_norm(ch), nn.Conv2d(ch, emb_dim, 3, 1, 1)]
    return blocks, taps


def generator_blocks(nf: int, ch_mult: tuple[int, ...], emb_dim: int, res_blocks: int = 2) -> tuple[list, dict]:
    """Generator blocks and {resolution index from the top: block index after which to fuse}."""
    ch = nf * ch_mult[-1]
    blocks: list[nn.Module] = [nn.Conv2d(emb_dim, ch, 3, 1, 1), ResBlock(ch, ch), AttnBlock(ch), ResBlock(ch, ch)]
    fuse: dict[int, int] = {}
    last = len(ch_mult) - 1
    for i in reversed(range(len(ch_mult))):
        for r in range(res_blocks):
            blocks.append(ResBlock(ch, nf * ch_mult[i]))
            ch = nf * ch_mult[i]
            if r == 0 and i != last:
                fuse[i] = len(blocks) - 1  # after the first ResBlock at this resolution
            if i == last:
                blocks.append(AttnBlock(ch))
        if i != 0:
            blocks.append(Upsample(ch))
    blocks += [group_norm(ch), nn.Conv2d(ch, 3, 3, 1, 1)]
    return blocks, fuse


class Quantize(nn.Module):
    def __init__(self, codebook_size: int, emb_dim: int):
        super().__init__()
        self.embedding = nn.Embedding(codebook_size, emb_dim)


class TransformerLayer(nn.Module):
    """Pre-norm self-attention + GELU MLP; positions added to queries and keys only."""

    def __init__(self, dim: int, n_head: int, dim_mlp: int):
        super().__init__()
        self.self_attn = nn.MultiheadAttention(dim, n_head, dropout=0.0)
        self.linear1, self.linear2 = nn.Linear(dim, dim_mlp), nn.Linear(dim_mlp, dim)
        self.norm1, self.norm2 = nn.LayerNorm(dim), nn.LayerNorm(dim)

    def forward(self, x: torch.Tensor, pos: torch.Tensor) -> torch.Tensor:  # x: (tokens, batch, dim)
        h = self.norm1(x)
        x = x + self.self_attn(h + pos, h + pos, value=h, need_weights=False)[0]
        return x + self.linear2(F.gelu(self.linear1(self.norm2(x))))


class FuseSFT(nn.Module):
    """Controllable feature transformation: dec + w * (dec * scale(enc, dec) + shift(enc, dec))."""

    def __init__(self, ch: int):
        super().__init__()
        self.encode_enc = ResBlock(2 * ch, ch)
        self.scale = nn.Sequential(nn.Conv2d(ch, ch, 3, 1, 1), nn.LeakyReLU(0.2), nn.Conv2d(ch, ch, 3, 1, 1))
        self.shift = nn.Sequential(nn.Conv2d(ch, ch, 3, 1, 1), nn.LeakyReLU(0.2), nn.Conv2d(ch, ch, 3, 1, 1))

    def forward(self, enc: torch.Tensor, dec: torch.Tensor, w: float) -> torch.Tensor:
        f = self.encode_enc(torch.cat([enc, dec], 1))
        return dec + w * (dec * self.scale(f) + self.shift(f))


class CodeFormer(nn.Module):
    def __init__(self, nf: int = 64, ch_mult: tuple[int, ...] = (1, 2, 2, 4, 4, 8), emb_dim: int = 256,
                 codebook_size: int = 1024, dim_embd: int = 512, n_head: int = N_HEAD, n_layers: int = 9,
                 connect: tuple[int, ...] = (32, 64, 128, 256)):
        super().__init__()
        self.latent = 16  # attention/latent resolution of the official model
        self.size = self.latent * 2 ** (len(ch_mult) - 1)
        enc, self._taps = encoder_blocks(nf, ch_mult, emb_dim)
        gen, self._fuse = generator_blocks(nf, ch_mult, emb_dim)
        self.encoder, self.generator = Coder(enc), Coder(gen)
        self.quantize = Quantize(codebook_size, emb_dim)
        self.position_emb = nn.Parameter(torch.zeros(self.latent ** 2, dim_embd))
        self.feat_emb = nn.Linear(emb_dim, dim_embd)
        self.ft_layers = nn.Sequential(*[TransformerLayer(dim_embd, n_head, 2 * dim_embd) for _ in range(n_layers)])
        self.idx_pred_layer = nn.Sequential(nn.LayerNorm(dim_embd), nn.Linear(dim_embd, codebook_size, bias=False))
        # resolution (pixels) -> resolution index from the top, for the fuse layers
        self.connect = tuple(sorted(connect))
        level = {self.size // 2 ** i: i for i in range(len(ch_mult))}
        bad = [r for r in self.connect if r not in level or level[r] == len(ch_mult) - 1]
        if bad:
            raise ValueError(f"fuse resolutions {bad} are not decoder resolutions of a {self.size}² model")
        self._levels = {r: level[r] for r in self.connect}
        self.fuse_convs_dict = nn.ModuleDict({str(r): FuseSFT(nf * ch_mult[level[r]]) for r in self.connect})

    def forward(self, x: torch.Tensor, w: float = 0.7, adain: bool = True) -> torch.Tensor:
        """(B, 3, S, S) in [-1, 1] -> restored (B, 3, S, S), unclamped.

        ``adain``: the looked-up code features take the per-channel mean and standard deviation of
        the encoder's features (adaptive instance normalisation), as the official inference does.
        """
        tap_at = {self._taps[lv]: r for r, lv in self._levels.items()}
        enc: dict[int, torch.Tensor] = {}
        for i, block in enumerate(self.encoder.blocks):
            x = block(x)
            if i in tap_at:
                enc[tap_at[i]] = x
        b, _, h, wd = x.shape
        tokens = self.feat_emb(x.flatten(2).permute(2, 0, 1))  # (hw, b, dim)
        pos = self.position_emb[:, None, :]
        for layer in self.ft_layers:
            tokens = layer(tokens, pos)
        idx = self.idx_pred_layer(tokens).argmax(dim=-1).permute(1, 0)  # (b, hw): the top-1 code
        feat = self.quantize.embedding.weight[idx].reshape(b, h, wd, -1).permute(0, 3, 1, 2)
        if adain:
            feat = adaptive_instance_norm(feat, x)
        fuse_at = {self._fuse[lv]: r for r, lv in self._levels.items()}
        x = feat
        for i, block in enumerate(self.generator.blocks):
            x = block(x)
            if i in fuse_at and w > 0:
                r = fuse_at[i]
                x = self.fuse_convs_dict[str(r)](enc[r], x, w)
        return x


def _mean_std(feat: torch.Tensor, eps: float = 1e-5) -> tuple[torch.Tensor, torch.Tensor]:
    flat = feat.flatten(2)
    return flat.mean(2)[..., None, None], (flat.var(2) + eps).sqrt()[..., None, None]


def adaptive_instance_norm(content: torch.Tensor, style: torch.Tensor) -> torch.Tensor:
    """``content`` normalised per channel, then given ``style``'s per-channel mean and std (unbiased var)."""
    c_mean, c_std = _mean_std(content)
    s_mean, s_std = _mean_std(style)
    return (content - c_mean) / c_std * s_std + s_mean


def config_from_state_dict(sd: dict, path: str | Path = "checkpoint") -> dict:
    """CodeFormer constructor arguments read from the tensors' shapes (see module docstring)."""
    try:
        nf = int(sd["encoder.blocks.0.weight"].shape[0])
        codebook_size, emb_dim = (int(v) for v in sd["quantize.embedding.weight"].shape)
        tokens, dim_embd = (int(v) for v in sd["position_emb"].shape)
    except KeyError as e:
        raise CheckpointError(f"{path} is not a {WHAT} checkpoint: no key {e.args[0]!r} "
                              f"(found e.g. {sorted(sd)[:5]})") from None
    if tokens != 256:
        raise CheckpointError(f"{path}: position_emb has {tokens} rows; CodeFormer's latent is 16x16 = 256")
    # ch_mult: the width of the first encoder ResBlock of each resolution; a Downsample block (the
    # only one with a bare "blocks.<i>.conv.weight") separates resolutions.
    n_blocks = 1 + max(int(k.split(".")[2]) for k in sd if k.startswith("encoder.blocks."))
    segments: list[list[int]] = [[]]
    for i in range(n_blocks):
        pre = f"encoder.blocks.{i}."
        if pre + "conv1.weight" in sd:
            segments[-1].append(int(sd[pre + "conv1.weight"].shape[0]))
        elif pre + "conv.weight" in sd:
            segments.append([])
    if any(not seg or seg[0] % nf for seg in segments):
        raise CheckpointError(f"{path}: cannot read the encoder layout of a {WHAT} checkpoint")
    ch_mult = [seg[0] // nf for seg in segments]
    n_layers = len({k.split(".")[1] for k in sd if k.startswith("ft_layers.")})
    connect = tuple(sorted(int(k.split(".")[1]) for k in sd if k.startswith("fuse_convs_dict.")
                           and k.endswith("encode_enc.conv1.weight")))
    return {"nf": nf, "ch_mult": tuple(ch_mult), "emb_dim": emb_dim, "codebook_size": codebook_size,
            "dim_embd": dim_embd, "n_head": N_HEAD, "n_layers": n_layers, "connect": connect}


def build(path: Path) -> CodeFormer:
    sd = read_state_dict(path, WHAT, WHERE)
    cfg = config_from_state_dict(sd, path)
    try:
        net = CodeFormer(**cfg)
    except (ValueError, ZeroDivisionError, IndexError) as e:
        raise CheckpointError(f"{path}: unsupported CodeFormer shapes {cfg}: {e}") from None
    load_strict(net, sd, WHAT, path)
    return net.to(infer_device())


def load(path: str | Path) -> CodeFormer:
    return cached_model(build, path)


@deterministic
@torch.no_grad()
def restore_face(net: CodeFormer, face: np.ndarray, fidelity: float = 0.7) -> np.ndarray:
    """(S, S, 3) RGB in [0, 1] with S = ``net.size`` -> restored RGB in [0, 1] (float32)."""
    if face.shape[:2] != (net.size, net.size):
        raise ValueError(f"CodeFormer needs {net.size}² crops, got {face.shape[1]}x{face.shape[0]}")
    device = next(net.parameters()).device
    x = torch.from_numpy(np.ascontiguousarray(face, dtype=np.float32)).permute(2, 0, 1)[None] * 2.0 - 1.0
    y = net(x.to(device), w=float(fidelity)).float().cpu().clamp_(-1.0, 1.0)
    return ((y[0].permute(1, 2, 0).numpy() + 1.0) * 0.5).astype(np.float32)


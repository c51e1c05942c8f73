"""Layers of the VQGAN / latent-diffusion autoencoder family, shared by CodeFormer's VQGAN
(:mod:`humanvdm_core.upscale.codeformer`) and SV3D's autoencoder (:mod:`.sv3d_vae`), with their
checkpoint names:

- :func:`group_norm`: GroupNorm(32, C), eps 1e-6, affine (``Normalize`` in both code bases);
- :class:`AttnBlock`: single-head spatial self-attention, 1x1 ``q``/``k``/``v``/``proj_out`` convs
  after ``norm``, residual;
- :class:`Downsample`: ``conv`` 3x3 stride 2 after padding right/bottom by one (no padding in the conv);
- :class:`Upsample`: nearest-neighbour ×2, then ``conv`` 3x3.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


def group_norm(ch: int) -> nn.GroupNorm:
    return nn.GroupNorm(32, ch, eps=1e-6, affine=True)


class AttnBlock(nn.Module):
    """Single-head spatial self-attention with 1x1 q/k/v/proj_out convs, residual."""

    def __init__(self, ch: int):
        super().__init__()
        self.norm = group_norm(ch)
        self.q, self.k, self.v = nn.Conv2d(ch, ch, 1), nn.Conv2d(ch, ch, 1), nn.Conv2d(ch, ch, 1)
        self.proj_out = nn.Conv2d(ch, ch, 1)

    def forward(self, x: torch.Tensor, num_frames: int | None = None) -> torch.Tensor:
        """``num_frames`` is accepted and ignored (the attention is per image)."""
        b, c, h, w = x.shape
        n = self.norm(x)
        q, k, v = (m(n).reshape(b, 1, c, h * w).transpose(2, 3) for m in (self.q, self.k, self.v))
        out = F.scaled_dot_product_attention(q, k, v)[:, 0].transpose(1, 2).reshape(b, c, h, w)
        return x + self.proj_out(out)


class Downsample(nn.Module):
    def __init__(self, ch: int):
        super().__init__()
        self.conv = nn.Conv2d(ch, ch, 3, 2, 0)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.conv(F.pad(x, (0, 1, 0, 1)))


class Upsample(nn.Module):
    def __init__(self, ch: int):
        super().__init__()
        self.conv = nn.Conv2d(ch, ch, 3, 1, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.conv(F.interpolate(x, scale_factor=2.0, mode="nearest"))

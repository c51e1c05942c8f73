"""RIFE v4.6 (Huang et al., ECCV 2022; Practical-RIFE) frame interpolation in pure PyTorch.

Loads Practical-RIFE's ``flownet.pkl`` of the v4.6 release (MIT licence; from
https://github.com/hzwer/Practical-RIFE, "v4.6" in its model list) in its key layout, with or
without the DataParallel ``module.`` prefix::

    block<k>.conv0.{0,1}.0.{weight,bias}                 two stride-2 3x3 convs (LeakyReLU 0.2)
    block<k>.convblock.<i>.{conv.weight, conv.bias, beta} residual convs: lrelu(conv(x) * beta + x)
    block<k>.lastconv.0.{weight,bias}                     ConvTranspose2d(c, 24, 4, 2, 1) + PixelShuffle(2)

Block 0 sees (img0, img1, t) at 1/8 resolution; each later block sees both frames warped by the
current flow, t, the current mask logit and the flow, at 1/4, 1/2, 1/1, and adds a flow and mask
residual.  The frame at time t is ``sigmoid(mask) * warp(img0, F_t0) + (1 - sigmoid(mask)) *
warp(img1, F_t1)`` (backward warping with ``grid_sample``, border padding).  The number of blocks,
their widths and input channels are read from the tensors' shapes (the official model: widths 192,
128, 96, 64), so a tiny model with the same keys loads through the same code.

v4.x models take the time ``t`` as an input, so any t in (0, 1) is synthesised directly.  Frames
are padded (replicate) to a multiple of 64 and cropped back; RGB goes through the flow network
and every channel (RGBA here) is warped and blended with the same flows and mask.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from humanvdm_core.models.checkpoint import (
    CheckpointError,
    build_strict,
    cached_model,
    deterministic,
)

WHAT = "RIFE v4.6 IFNet weights (flownet.pkl)"
WHERE = "https://github.com/hzwer/Practical-RIFE (model list: v4.6, unpack train_log/flownet.pkl; MIT)"
PAD = 64


def _conv(cin: int, cout: int, stride: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, stride, 1), nn.LeakyReLU(0.2))


class ResConv(nn.Module):
    def __init__(self, c: int):
        super().__init__()
        self.conv = nn.Conv2d(c, c, 3, 1, 1)
        self.beta = nn.Parameter(torch.ones(1, c, 1, 1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.leaky_relu(self.conv(x) * self.beta + x, 0.2)


class IFBlock(nn.Module):
    """Predicts (flow residual (4 ch: F_t0, F_t1), mask residual) at 1/``scale`` resolution."""

    def __init__(self, in_planes: int, c: int, n_res: int = 8):
        super().__init__()
        self.conv0 = nn.Sequential(_conv(in_planes, c // 2, 2), _conv(c // 2, c, 2))
        self.convblock = nn.Sequential(*[ResConv(c) for _ in range(n_res)])
        self.lastconv = nn.Sequential(nn.ConvTranspose2d(c, 24, 4, 2, 1), nn.PixelShuffle(2))

    def forward(self, x: torch.Tensor, flow: torch.Tensor | None, scale: float) -> tuple[torch.Tensor, torch.Tensor]:
        if scale != 1:
            x = F.interpolate(x, scale_factor=1.0 / scale, mode="bilinear", align_corners=False)
        if flow is not None:
            if scale != 1:
                flow = F.interpolate(flow, scale_factor=1.0 / scale, mode="bilinear", align_corners=False) / scale
            x = torch.cat((x, flow), 1)
        out = self.lastconv(self.convblock(self.conv0(x)))
        if scale != 1:
            out = F.interpolate(out, scale_factor=scale, mode="bilinear", align_corners=False)
        return out[:, :4] * scale, out[:, 4:5]


def backward_warp(image: torch.Tensor, flow: torch.Tensor) -> torch.Tensor:
    """``out(x) = image(x + flow(x))``, bilinear, border-clamped (flow in pixels)."""
    _, _, h, w = image.shape
    ys = torch.linspace(-1.0, 1.0, h, device=image.device).view(1, h, 1).expand(1, h, w)
    xs = torch.linspace(-1.0, 1.0, w, device=image.device).view(1, 1, w).expand(1, h, w)
    gx = xs + flow[:, 0] * (2.0 / max(w - 1, 1))
    gy = ys + flow[:, 1] * (2.0 / max(h - 1, 1))
    return F.grid_sample(image, torch.stack((gx, gy), -1), mode="bilinear", padding_mode="border", align_corners=True)


class IFNet(nn.Module):
    def __init__(self, blocks: list[tuple[int, int, int]]):
        """``blocks``: (input channels, width, residual convs) per block, coarse to fine."""
        super().__init__()
        for k, (cin, c, n_res) in enumerate(blocks):
            self.add_module(f"block{k}", IFBlock(cin, c, n_res))
        self.n_blocks = len(blocks)
        self.scales = [2.0 ** (len(blocks) - 1 - k) for k in range(len(blocks))]  # 8, 4, 2, 1

    def forward(self, img0: torch.Tensor, img1: torch.Tensor, t: float) -> torch.Tensor:
        """Frames (B, C >= 3, H, W) in [0, 1], H and W multiples of 64 -> the frame at time ``t``."""
        tt = torch.full_like(img0[:, :1], float(t))
        flow = mask = None
        w0, w1 = img0, img1
        for k in range(self.n_blocks):
            block = getattr(self, f"block{k}")
            if flow is None:
                flow, mask = block(torch.cat((img0[:, :3], img1[:, :3], tt), 1), None, self.scales[k])
            else:
                df, dm = block(torch.cat((w0[:, :3], w1[:, :3], tt, mask), 1), flow, self.scales[k])
                flow, mask = flow + df, mask + dm
            w0, w1 = backward_warp(img0, flow[:, :2]), backward_warp(img1, flow[:, 2:4])
        m = torch.sigmoid(mask)
        return w0 * m + w1 * (1.0 - m)


def config_from_state_dict(sd: dict, path: str | Path = "checkpoint") -> list[tuple[int, int, int]]:
    """Per block (input channels, width, residual convs), read from the tensors' shapes."""
    blocks = []
    k = 0
    while f"block{k}.conv0.0.0.weight" in sd:
        pre = f"block{k}."
        cin = int(sd[pre + "conv0.0.0.weight"].shape[1])
        c = int(sd[pre + "conv0.1.0.weight"].shape[0])
        n_res = len({key.split(".")[2] for key in sd if key.startswith(pre + "convblock.")})
        blocks.append((cin, c, n_res))
        k += 1
    if not blocks:
        raise CheckpointError(f"{path} is not a {WHAT} checkpoint: no key 'block0.conv0.0.0.weight' "
                              f"(found e.g. {sorted(sd)[:5]})")
    if "block0.lastconv.0.weight" not in sd:
        raise CheckpointError(f"{path}: no 'block0.lastconv.0.weight'; only the RIFE v4.6 layout is supported "
                              "(older v4.0-v4.5 and newer v4.7+ releases differ)")
    return blocks


def build(path: Path) -> IFNet:
    return build_strict(path, WHAT, WHERE, lambda sd, p: IFNet(config_from_state_dict(sd, p)))


def load(path: str | Path) -> IFNet:
    return cached_model(build, path)


@deterministic
@torch.no_grad()
def interpolate_pair(net: IFNet, frame0: np.ndarray, frame1: np.ndarray, times: list[float]) -> list[np.ndarray]:
    """(H, W, C) frames in [0, 1] (C >= 3) -> the frames at each ``t`` in ``times``, clamped to [0, 1]."""
    device = next(net.parameters()).device
    h, w = frame0.shape[:2]
    ph, pw = (-h) % PAD, (-w) % PAD

    def prep(f: np.ndarray) -> torch.Tensor:
        x = torch.from_numpy(np.ascontiguousarray(f, dtype=np.float32)).permute(2, 0, 1)[None]
        return F.pad(x, (0, pw, 0, ph), mode="replicate").to(device) if ph or pw else x.to(device)

    a, b = prep(frame0), prep(frame1)
    out = []
    for t in times:
        y = net(a, b, t)[0, :, :h, :w].float().cpu().clamp_(0.0, 1.0)
        out.append(y.permute(1, 2, 0).numpy().astype(np.float32))
    return out

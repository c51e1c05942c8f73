"""PerVFI (Wu et al., CVPR 2024, "Perception-Oriented Video Frame Interpolation via Asymmetric
Blending") in plain PyTorch: no cupy, no CUDA-only kernels, no torchvision.

Weights (the PerVFI release, https://huggingface.co/Mulns/PerVFI-v1-0, linked from
github.com/mulns/PerVFI; code and models under the Apache License 2.0):

- ``PerVFI/v00.pth``: the generator the official ``raft+pervfi`` model uses (``src/test``:
  ``build_generator_arch("v00")`` -> ``PFlowVFI_V0.Network(dilate_size=9)``), a flat state dict
  (``module.`` prefixes stripped as the official loader does);
- ``RAFT/raft-sintel.pth``: its optical-flow estimator (:mod:`humanvdm_core.interpolate.raft`; RAFT is
  BSD-3-Clause, github.com/princeton-vl/RAFT).

Generator key layout (reference: ``src/test/models/generators/PFlowVFI_V0.py``,
``normalizing_flow.py``, ``msfusion.py`` and the softmax-splatting ``Encode``/``Softmetric``
networks of github.com/sniklaus/softmax-splatting ``run.py`` that PerVFI imports)::

    featurePyramid.netEncode.net{One,Two,Thr}.{0,2}.weight, .{1,3}.weight (PReLU)
    featurePyramid.netSoftmetric.net{Input,Error}.weight, "<r>x<c> - <r'>x<c'>".netMain.*, netOutput.*
    deformableAlign.{offset_conv1,offset_conv2,offset_conv3,feat_conv,merge_conv1,merge_conv2}.l<i>.*,
    deformableAlign.deform_conv.l<i>.{conv_offset.*, dconv.weight, dconv.bias}    (DCNv2)
    attentionMerge.softbinary.<i>.{conv1.{0,2,4}.weight, att.*, fc.{0,2}.weight, conv2.weight}
    multiscaleFuse.{stems, layer1, transition1, extra1, stage2, transition2, extra2, stage3, final_layers}.*
    condFLownet.blocks.<i>.{actnorm.{loc,logs,initialized}, invconv.weight, prior.{conv.*,scale},
                            flows.<k>.{actnorm.*, invconv.weight, coupling.{affine.tail.{0,2,4}.*, scale, scale_shift}}}

Official sizes: encoder widths 32/64/96 (condition channels 35/64/96), soft-metric U-Net
16/32/64/96, deformable groups 7/8/8, soft-binary width 64 (kernel 9), HRNet-style fusion (stem 64,
4 bottlenecks, stages [32, 64] and [32, 64, 96] of 2 modules x 2 blocks), normalizing flow of
3 levels x K = 16 steps with 64-channel coupling nets.  Every width, count and kernel size is read
from the tensors' shapes (:func:`config_from_state_dict`), so a tiny random model in the same key
layout loads through the same code.

Inference (``Pipeline_infer.inference_rand_noise`` as ``build_models.py`` calls it): pad to a
multiple of 8, RAFT flows F_01, F_10 (12 iterations each way), frames normalised to [-1, 1];
feature pyramids of both frames; soft metrics; frame 0's features forward-splatted to t (softmax
splatting, metric ``-clip(m, -20, 20)``), hole masks; frame 1's features aligned to t by
deformable convolutions guided by F_t1 (frame 1's flow splatted to t); the asymmetric soft-binary
blend per level; multi-scale fusion; then the conditional normalizing flow run in reverse from a
latent ``z ~ N(0, heat^2)`` with ``heat = 0.3`` as the official inference does -- drawn here from a
generator seeded with ``seed`` (default 0), so the same inputs give the same frame; ``heat = 0``
decodes the mean.  The network takes ``time`` (``t`` scales the flows and metrics) but the released
weights are trained on Vimeo-90K triplets (t = 0.5); the ``interpolate`` stage runs PerVFI ×2
recursively as the paper does.

The official softsplat is a cupy kernel; :func:`softsplat` is a pure-PyTorch summation splat
(``index_add_`` of bilinear weights: each source pixel adds ``value * w`` to the four pixels around
``x + flow(x)``, corners outside the frame and non-finite flows dropped) with the same modes
(``sum``, ``avg``, ``soft``) and normalisation (divide by the splatted weight + 1e-7).  The
deformable convolution (torchvision's ``DeformConv2d`` with a modulation mask) is rebuilt from
``grid_sample``, one kernel tap at a time.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from humanvdm_core.interpolate import raft
from humanvdm_core.models.checkpoint import (
    CheckpointError,
    build_strict,
    cached_model,
    deterministic,
)

WHAT = "PerVFI generator weights (v00.pth)"
WHERE = "https://huggingface.co/Mulns/PerVFI-v1-0 (file PerVFI/v00.pth; github.com/mulns/PerVFI, Apache-2.0)"
PAD = 8
HEAT = 0.3  # the official inference's latent temperature
SEED = 0


# ----------------------------------------------------------------------------- warping

def softsplat(ten_in: torch.Tensor, flow: torch.Tensor, metric: torch.Tensor | None = None,
              mode: str = "sum") -> torch.Tensor:
    """Forward warping (softmax splatting, Niklaus & Liu 2020) of ``ten_in`` (B, C, H, W) by ``flow``.

    ``sum``: bilinear summation splat; ``avg``: divided by the splatted weight; ``soft``: values
    weighted by ``exp(metric)`` and divided by the splatted ``exp(metric)``.  Normalising modes add
    1e-7 to the denominator, as the reference does by default.
    """
    if mode == "avg":
        ten_in = torch.cat([ten_in, ten_in.new_ones(ten_in.shape[0], 1, *ten_in.shape[2:])], 1)
    elif mode == "soft":
        e = metric.exp()
        ten_in = torch.cat([ten_in * e, e], 1)
    elif mode != "sum":
        raise ValueError(f"unknown softsplat mode {mode!r}")
    out = _splat_sum(ten_in, flow)
    if mode == "sum":
        return out
    return out[:, :-1] / (out[:, -1:] + 1e-7)


def _splat_sum(x: torch.Tensor, flow: torch.Tensor) -> torch.Tensor:
    b, c, h, w = x.shape
    ys, xs = torch.meshgrid(torch.arange(h, device=x.device, dtype=flow.dtype),
                            torch.arange(w, device=x.device, dtype=flow.dtype), indexing="ij")
    fx = (xs + flow[:, 0]).reshape(b, -1)
    fy = (ys + flow[:, 1]).reshape(b, -1)
    finite = torch.isfinite(fx) & torch.isfinite(fy)
    fx, fy = torch.where(finite, fx, 0.0), torch.where(finite, fy, 0.0)
    x0, y0 = torch.floor(fx), torch.floor(fy)
    vals = x.reshape(b, c, -1).permute(1, 0, 2).reshape(c, -1)  # (C, B*H*W)
    base = (torch.arange(b, device=x.device) * (h * w)).view(b, 1)
    out = x.new_zeros(c, b * h * w)
    for dx, dy in ((0, 0), (1, 0), (0, 1), (1, 1)):
        cx, cy = x0 + dx, y0 + dy
        wt = (1 - (fx - cx).abs()) * (1 - (fy - cy).abs())
        ok = finite & (cx >= 0) & (cx < w) & (cy >= 0) & (cy < h)
        idx = torch.where(ok, base + cy.long() * w + cx.long(), 0).reshape(-1)
        out.index_add_(1, idx, vals * torch.where(ok, wt, 0.0).reshape(1, -1).to(x.dtype))
    return out.view(c, b, h * w).permute(1, 0, 2).reshape(b, c, h, w)


def backwarp(ten_in: torch.Tensor, flow: torch.Tensor) -> torch.Tensor:
    """``out(x) = in(x + flow(x))``, bilinear, zeros outside (softmax-splatting's ``backwarp``)."""
    h, w = ten_in.shape[-2:]
    ys, xs = torch.meshgrid(torch.arange(h, device=ten_in.device, dtype=flow.dtype),
                            torch.arange(w, device=ten_in.device, dtype=flow.dtype), indexing="ij")
    gx = 2 * (xs + flow[:, 0]) / max(w - 1, 1) - 1
    gy = 2 * (ys + flow[:, 1]) / max(h - 1, 1) - 1
    return F.grid_sample(ten_in, torch.stack([gx, gy], -1), mode="bilinear", padding_mode="zeros", align_corners=True)


def resize(x: torch.Tensor, size: tuple[int, int], scale: bool) -> torch.Tensor:
    out = F.interpolate(x, size, mode="bilinear", align_corners=False)
    return out * (size[0] / x.shape[-2]) if scale else out


def binary_hole(flow: torch.Tensor) -> torch.Tensor:
    """1 where nothing splats to a pixel under ``flow`` (average-splatted ones <= 0.5), else 0."""
    n, _, h, w = flow.shape
    mask = softsplat(flow.new_ones(n, 1, h, w), flow, None, "avg")
    return (mask <= 0.5).to(flow.dtype)


def deform_conv2d(x: torch.Tensor, offset: torch.Tensor, mask: torch.Tensor, weight: torch.Tensor,
                  bias: torch.Tensor | None) -> torch.Tensor:
    """Modulated deformable convolution (DCNv2; torchvision's ``deform_conv2d`` semantics, stride 1,
    padding k // 2, dilation 1, one weight group): ``offset`` holds (dy, dx) per offset group and
    kernel tap, ``mask`` one modulation per group and tap; samples outside the frame are zero."""
    b, c, h, w = x.shape
    cout, _, kh, kw = weight.shape
    taps = kh * kw
    groups = offset.shape[1] // (2 * taps)
    off = offset.view(b, groups, taps, 2, h, w)
    mod = mask.view(b, groups, 1, taps, h, w)
    ys, xs = torch.meshgrid(torch.arange(h, device=x.device, dtype=x.dtype),
                            torch.arange(w, device=x.device, dtype=x.dtype), indexing="ij")
    xg = x.reshape(b * groups, c // groups, h, w)
    out = x.new_zeros(b, cout, h, w) if bias is None else bias.view(1, -1, 1, 1).expand(b, cout, h, w).clone()
    for k in range(taps):
        i, j = divmod(k, kw)
        py = ys + (i - kh // 2) + off[:, :, k, 0]
        px = xs + (j - kw // 2) + off[:, :, k, 1]
        grid = torch.stack([2 * px / max(w - 1, 1) - 1, 2 * py / max(h - 1, 1) - 1], -1).view(b * groups, h, w, 2)
        s = F.grid_sample(xg, grid, mode="bilinear", padding_mode="zeros", align_corners=True)
        s = (s.view(b, groups, c // groups, h, w) * mod[:, :, :, k]).view(b, c, h, w)
        out = out + torch.einsum("bchw,oc->bohw", s, weight[:, :, i, j])
    return out


# ----------------------------------------------------------------------------- softmax-splatting parts

class Basic(nn.Module):
    def __init__(self, kind: str, ch: tuple[int, int, int], skip: bool = True):
        super().__init__()
        conv = [nn.Conv2d(ch[0], ch[1], 3, 1, 1, bias=False), nn.PReLU(ch[1], 0.25),
                nn.Conv2d(ch[1], ch[2], 3, 1, 1, bias=False)]
        self.netMain = nn.Sequential(nn.PReLU(ch[0], 0.25), *conv) if kind == "relu-conv-relu-conv" else nn.Sequential(*conv)
        self.skip = skip
        self.netShortcut = nn.Conv2d(ch[0], ch[2], 1, bias=False) if skip and ch[0] != ch[2] else None

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not self.skip:
            return self.netMain(x)
        return self.netMain(x) + (x if self.netShortcut is None else self.netShortcut(x))


class Downsample(nn.Module):
    def __init__(self, ch: tuple[int, int, int]):
        super().__init__()
        self.netMain = nn.Sequential(nn.PReLU(ch[0], 0.25), nn.Conv2d(ch[0], ch[1], 3, 2, 1, bias=False),
                                     nn.PReLU(ch[1], 0.25), nn.Conv2d(ch[1], ch[2], 3, 1, 1, bias=False))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.netMain(x)


class Upsample(nn.Module):
    def __init__(self, ch: tuple[int, int, int]):
        super().__init__()
        self.netMain = nn.Sequential(nn.Upsample(scale_factor=2, mode="bilinear", align_corners=False),
                                     nn.PReLU(ch[0], 0.25), nn.Conv2d(ch[0], ch[1], 3, 1, 1, bias=False),
                                     nn.PReLU(ch[1], 0.25), nn.Conv2d(ch[1], ch[2], 3, 1, 1, bias=False))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.netMain(x)


class Encode(nn.Module):
    """Three-level feature pyramid; level 0 is the input concatenated with its features."""

    def __init__(self, widths: tuple[int, int, int]):
        super().__init__()
        cin = 3
        for name, c, stride in zip(("netOne", "netTwo", "netThr"), widths, (1, 2, 2), strict=True):
            self.add_module(name, nn.Sequential(nn.Conv2d(cin, c, 3, stride, 1, bias=False), nn.PReLU(c, 0.25),
                                                nn.Conv2d(c, c, 3, 1, 1, bias=False), nn.PReLU(c, 0.25)))
            cin = c

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        one = self.netOne(x)
        two = self.netTwo(one)
        return [torch.cat([x, one], 1), two, self.netThr(two)]


def _trim_add(x: torch.Tensor, up: torch.Tensor) -> torch.Tensor:
    if up.shape[2] != x.shape[2]:
        up = up[:, :, :x.shape[2]]
    if up.shape[3] != x.shape[3]:
        up = up[:, :, :, :x.shape[3]]
    return x + up


class Softmetric(nn.Module):
    """The splatting importance metric: a small U-Net on (frame features, warping error)."""

    def __init__(self, c_input: int, c_error: int, widths: tuple[int, int, int, int]):
        super().__init__()
        self.netInput = nn.Conv2d(3, c_input, 3, 1, 1, bias=False)
        self.netError = nn.Conv2d(1, c_error, 3, 1, 1, bias=False)
        for r, c in enumerate(widths):
            self.add_module(f"{r}x0 - {r}x1", Basic("relu-conv-relu-conv", (c, c, c)))
        for r in range(3):
            self.add_module(f"{r}x0 - {r + 1}x0", Downsample((widths[r], widths[r + 1], widths[r + 1])))
            self.add_module(f"{r + 1}x1 - {r}x1", Upsample((widths[r + 1], widths[r], widths[r])))
        self.netOutput = Basic("conv-relu-conv", (widths[0], widths[0], 1))

    def forward(self, enc_one: list, enc_two: list, flow: torch.Tensor) -> torch.Tensor:
        err = (enc_one[0] - backwarp(enc_two[0], flow)).abs().mean(1, keepdim=True)
        col = [torch.cat([self.netInput(enc_one[0][:, :3]), self.netError(err)], 1)]
        for r in range(3):
            col.append(self._modules[f"{r}x0 - {r + 1}x0"](col[-1]))
        for r in range(3, -1, -1):
            col[r] = self._modules[f"{r}x0 - {r}x1"](col[r])
            if r != 3:
                col[r] = _trim_add(col[r], self._modules[f"{r + 1}x1 - {r}x1"](col[r + 1]))
        return self.netOutput(col[0])


# ----------------------------------------------------------------------------- PerVFI conditioning

class FeaturePyramid(nn.Module):
    def __init__(self, cfg: dict):
        super().__init__()
        self.netEncode = Encode(cfg["encode"])
        self.netSoftmetric = Softmetric(*cfg["metric"])

    def forward(self, img0, img1, f01, f10, time: float):
        x0s, x1s = self.netEncode(img0), self.netEncode(img1)
        m0t = self.netSoftmetric(x0s, x1s, f01) * 2 * time
        f0t = time * f01
        m1t = self.netSoftmetric(x1s, x0s, f10) * 2 * (1 - time)
        f1t = (1 - time) * f10
        ft1 = -softsplat(f1t, f1t, m1t.neg().clip(-20.0, 20.0), "soft")  # flow from t to frame 1
        warped, holes = [], []
        metric, flow = m0t, f0t
        for lv, fea in enumerate(x0s):
            if lv:
                metric = resize(metric, fea.shape[-2:], scale=False)
                flow = resize(flow, fea.shape[-2:], scale=True)
            warped.append(softsplat(fea, flow, metric.neg().clip(-20.0, 20.0), "soft"))
            holes.append(binary_hole(flow))
        aux = {"m0t": m0t, "f0t": f0t, "ft1": ft1}
        return list(zip(warped, x1s, strict=True)), holes, ft1, aux


class DCNPack(nn.Module):
    def __init__(self, c: int, groups: int, k: int):
        super().__init__()
        self.conv_offset = nn.Conv2d(c, groups * 3 * k * k, 3, 1, 1)
        self.dconv = _DeformConv(c, k)

    def forward(self, x, feat):
        o1, o2, mask = torch.chunk(self.conv_offset(feat), 3, dim=1)
        return self.dconv(x, torch.cat([o1, o2], 1), torch.sigmoid(mask))


class _DeformConv(nn.Module):
    """Parameters laid out as torchvision's ``DeformConv2d(c, c, k, padding=k // 2)``."""

    def __init__(self, c: int, k: int):
        super().__init__()
        self.weight = nn.Parameter(torch.zeros(c, c, k, k))
        self.bias = nn.Parameter(torch.zeros(c))
        nn.init.kaiming_uniform_(self.weight, a=5 ** 0.5)

    def forward(self, x, offset, mask):
        return deform_conv2d(x, offset, mask, self.weight, self.bias)


class DeformableAlign(nn.Module):
    def __init__(self, ch: tuple[int, int, int], groups: tuple[int, int, int], k: int):
        super().__init__()
        for name in ("offset_conv1", "offset_conv2", "offset_conv3", "deform_conv", "feat_conv", "merge_conv1",
                     "merge_conv2"):
            self.add_module(name, nn.ModuleDict())
        for i in range(2, -1, -1):
            lv, c = f"l{i}", ch[i]
            self.offset_conv1[lv] = nn.Conv2d(c * 2 + 3, c, 3, 1, 1)
            if i == 2:
                self.offset_conv2[lv] = nn.Conv2d(c, c, 3, 1, 1)
            else:
                self.offset_conv2[lv] = nn.Conv2d(c + ch[i + 1], c, 3, 1, 1)
                self.offset_conv3[lv] = nn.Conv2d(c, c, 3, 1, 1)
            self.deform_conv[lv] = DCNPack(c, groups[i], k)
            self.merge_conv1[lv] = nn.Conv2d(c + c + 1, c, 3, 1, 1)
            if i < 2:
                self.feat_conv[lv] = nn.Conv2d(c + ch[i + 1], c, 3, 1, 1)
                self.merge_conv2[lv] = nn.Conv2d(c + ch[i + 1], c, 3, 1, 1)

    def forward(self, features, holes, ft1):
        def up(x):
            return F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=False)

        outs = []
        up_offset = up_fea = up_merged = None
        for i in range(2, -1, -1):
            lv = f"l{i}"
            fea0, fea1 = features[i]
            hole = holes[i]
            flow = resize(ft1, hole.shape[2:], scale=True)
            offset = F.leaky_relu(self.offset_conv1[lv](torch.cat([fea0, fea1, hole, flow], 1)), 0.1)
            if i == 2:
                offset = F.leaky_relu(self.offset_conv2[lv](offset), 0.1)
            else:
                offset = F.leaky_relu(self.offset_conv2[lv](torch.cat([offset, up_offset], 1)), 0.1)
                offset = F.leaky_relu(self.offset_conv3[lv](offset), 0.1)
            aligned = self.deform_conv[lv](fea1, offset)
            if i < 2:
                aligned = self.feat_conv[lv](torch.cat([aligned, up_fea], 1))
            merged = self.merge_conv1[lv](torch.cat([fea0, aligned, hole], 1))
            if i < 2:
                merged = self.merge_conv2[lv](torch.cat([merged, up_merged], 1))
            outs.append(merged)
            if i > 0:
                up_offset = up(offset) * 2
                up_fea = up(F.leaky_relu(aligned, 0.1))
                up_merged = up(merged)
        return outs


class SoftBinary(nn.Module):
    def __init__(self, cin: int, channel: int, hidden: int, dilate: int):
        super().__init__()
        self.conv1 = nn.Sequential(nn.Conv2d(1, channel, dilate, 1, padding="same", bias=False), nn.ReLU(inplace=True),
                                   nn.Conv2d(channel, channel, 3, 1, padding="same", bias=False), nn.ReLU(inplace=True),
                                   nn.Conv2d(channel, channel, 1, 1, padding="same", bias=False))
        self.att = nn.Conv2d(cin * 2, channel, 3, 1, padding="same")
        self.fc = nn.Sequential(nn.Linear(channel, hidden, bias=False), nn.ReLU(inplace=True),
                                nn.Linear(hidden, channel, bias=False), nn.Sigmoid())
        self.conv2 = nn.Conv2d(channel, 1, 1, 1, padding="same", bias=False)

    def forward(self, hole, fea0, fea1):
        x = self.att(torch.cat([fea0, fea1], 1)).mean((2, 3))
        x = self.conv1(hole) * self.fc(x)[:, :, None, None]
        return torch.tanh(torch.abs(self.conv2(x)))


class AttentionMerge(nn.Module):
    def __init__(self, ch: tuple[int, int, int], channel: int, hidden: int, dilate: int):
        super().__init__()
        self.softbinary = nn.ModuleDict()
        for i in range(2, -1, -1):
            self.softbinary[str(i)] = SoftBinary(ch[i], channel, hidden, dilate)

    def forward(self, fea0, fea1, holes):
        outs, masks = [], []
        for i in range(2, -1, -1):
            sm = self.softbinary[str(i)](holes[i], fea0[i], fea1[i])
            masks.append(sm)
            outs.append(fea0[i] * (1 - sm) + fea1[i] * sm)
        return outs, masks


# ----------------------------------------------------------------------------- multi-scale fusion (HRNet-like)

def _conv3(cin: int, cout: int, stride: int = 1) -> nn.Conv2d:
    return nn.Conv2d(cin, cout, 3, stride, 1, bias=False)


class BasicBlock(nn.Module):
    def __init__(self, cin: int, c: int):
        super().__init__()
        self.conv1, self.conv2 = _conv3(cin, c), _conv3(c, c)
        self.downsample = nn.Conv2d(cin, c, 1, bias=False) if cin != c else None

    def forward(self, x):
        y = self.conv2(F.relu(self.conv1(x)))
        return F.relu(y + (x if self.downsample is None else self.downsample(x)))


class Bottleneck(nn.Module):
    def __init__(self, cin: int, planes: int):
        super().__init__()
        self.conv1 = nn.Conv2d(cin, planes, 1, bias=False)
        self.conv2 = _conv3(planes, planes)
        self.conv3 = nn.Conv2d(planes, planes * 4, 1, bias=False)
        self.downsample = nn.Conv2d(cin, planes * 4, 1, bias=False) if cin != planes * 4 else None

    def forward(self, x):
        y = self.conv3(F.relu(self.conv2(F.relu(self.conv1(x)))))
        return F.relu(y + (x if self.downsample is None else self.downsample(x)))


class HRModule(nn.Module):
    def __init__(self, cins: list[int], chs: list[int], blocks: int):
        super().__init__()
        n = len(chs)
        self.branches = nn.ModuleList(
            nn.Sequential(*[BasicBlock(cins[i] if b == 0 else chs[i], chs[i]) for b in range(blocks)]) for i in range(n))
        self.fuse_layers = None
        if n > 1:
            self.fuse_layers = nn.ModuleList()
            for i in range(n):
                row = []
                for j in range(n):
                    if j > i:
                        row.append(nn.Sequential(nn.Conv2d(chs[j], chs[i], 1, 1, 0, bias=False),
                                                 nn.Upsample(scale_factor=2 ** (j - i), mode="nearest")))
                    elif j == i:
                        row.append(None)
                    else:
                        steps = [nn.Sequential(_conv3(chs[j], chs[j], 2), nn.ReLU(True)) for _ in range(i - j - 1)]
                        row.append(nn.Sequential(*steps, _conv3(chs[j], chs[i], 2)))
                self.fuse_layers.append(nn.ModuleList(row))

    def forward(self, x: list) -> list:
        x = [branch(xi) for branch, xi in zip(self.branches, x, strict=True)]
        if self.fuse_layers is None:
            return x
        out = []
        for i, row in enumerate(self.fuse_layers):
            y = x[0] if i == 0 else row[0](x[0])
            for j in range(1, len(x)):
                y = y + (x[j] if i == j else row[j](x[j]))
            out.append(F.relu(y))
        return out


def _transition(pre: list[int], cur: list[int]) -> nn.ModuleList:
    layers = []
    for i, c in enumerate(cur):
        if i < len(pre):
            layers.append(nn.Sequential(_conv3(pre[i], c), nn.ReLU(True)) if pre[i] != c else None)
        else:
            steps = [nn.Sequential(_conv3(pre[-1], c if k == i - len(pre) else pre[-1], 2), nn.ReLU(True))
                     for k in range(i + 1 - len(pre))]
            layers.append(nn.Sequential(*steps))
    return nn.ModuleList(layers)


class MultiscaleFuse(nn.Module):
    def __init__(self, cins: tuple[int, int, int], cfg: dict):
        super().__init__()
        stem, planes = cfg["stem"], cfg["planes"]
        self.stems = nn.ModuleList(nn.Sequential(_conv3(cins[i], stem), nn.ReLU(True)) for i in range(3))
        self.layer1 = nn.Sequential(*[Bottleneck(stem if b == 0 else planes * 4, planes)
                                      for b in range(cfg["bottlenecks"])])
        s2, s3 = list(cfg["stage2"]), list(cfg["stage3"])
        self.transition1 = _transition([planes * 4], s2)
        self.extra1 = nn.Sequential(_conv3(stem + s2[-1], s2[-1]), nn.ReLU(True))
        self.stage2 = nn.Sequential(*[HRModule(s2, s2, cfg["blocks2"]) for _ in range(cfg["modules2"])])
        self.transition2 = _transition(s2, s3)
        self.extra2 = nn.Sequential(_conv3(stem + s3[-1], s3[-1]), nn.ReLU(True))
        self.stage3 = nn.Sequential(*[HRModule(s3, s3, cfg["blocks3"]) for _ in range(cfg["modules3"])])
        self.final_layers = nn.ModuleList(nn.Conv2d(s3[i], cins[i], 3, 2, 1) for i in range(3))

    def forward(self, xs: list) -> list:
        x0, x1, x2 = (stem(x) for stem, x in zip(self.stems, xs, strict=True))
        x = self.layer1(x0)
        xl = [x if t is None else t(x) for t in self.transition1]
        xl[-1] = self.extra1(torch.cat([x1, xl[-1]], 1))
        yl = self.stage2(xl)
        xl = [yl[i] if t is None else t(yl[-1]) for i, t in enumerate(self.transition2)]
        xl[-1] = self.extra2(torch.cat([x2, xl[-1]], 1))
        yl = self.stage3(xl)
        return [layer(y) for layer, y in zip(self.final_layers, yl, strict=True)]


# ----------------------------------------------------------------------------- conditional normalizing flow

class ActNorm(nn.Module):
    def __init__(self, c: int):
        super().__init__()
        self.loc = nn.Parameter(torch.zeros(1, c, 1, 1))
        self.logs = nn.Parameter(torch.zeros(1, c, 1, 1))
        self.register_buffer("initialized", torch.tensor(1, dtype=torch.uint8))

    def reverse(self, x):
        return x * torch.exp(-self.logs) - self.loc


class InvConv2d(nn.Module):
    def __init__(self, c: int):
        super().__init__()
        self.weight = nn.Parameter(torch.linalg.qr(torch.randn(c, c))[0][:, :, None, None])

    def reverse(self, x):
        inv = torch.linalg.inv(self.weight[:, :, 0, 0].double()).to(x.dtype)
        return F.conv2d(x, inv[:, :, None, None])


class ZeroConv2d(nn.Module):
    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.conv = nn.Conv2d(cin, cout, 3, padding=1)
        self.scale = nn.Parameter(torch.zeros(1, cout, 1, 1))

    def forward(self, x):
        return self.conv(x) * torch.exp(self.scale * 3)


class CondAffineNet(nn.Module):
    def __init__(self, cin: int, ccond: int, cout: int, hidden: int):
        super().__init__()
        self.tail = nn.Sequential(nn.Conv2d(cin + ccond, hidden, 3, 1, 1), nn.ReLU(),
                                  nn.Conv2d(hidden, hidden, 1, 1, 0), nn.ReLU(), ZeroConv2d(hidden, cout))

    def forward(self, x, cond):
        return self.tail(torch.cat([x, cond], 1))


class CondAffineCoupling(nn.Module):
    def __init__(self, cin: int, ccond: int, hidden: int):
        super().__init__()
        self.affine = CondAffineNet(cin // 2, ccond, cin, hidden)
        self.scale = nn.Parameter(torch.zeros(1))
        self.scale_shift = nn.Parameter(torch.zeros(1))

    def reverse(self, x, cond):
        on, off = x.chunk(2, 1)
        shift, log_rescale = self.affine(off, cond).chunk(2, 1)
        log_rescale = self.scale * torch.tanh(log_rescale) + self.scale_shift
        return torch.cat([(on - shift) * torch.exp(-log_rescale), off], 1)


class FlowStep(nn.Module):
    def __init__(self, c: int, ccond: int, hidden: int):
        super().__init__()
        self.actnorm = ActNorm(c)
        self.invconv = InvConv2d(c)
        self.coupling = CondAffineCoupling(c, ccond, hidden)

    def reverse(self, x, cond):
        return self.actnorm.reverse(self.invconv.reverse(self.coupling.reverse(x, cond)))


def squeeze2d(x: torch.Tensor) -> torch.Tensor:
    b, c, h, w = x.shape
    return x.view(b, c, h // 2, 2, w // 2, 2).permute(0, 1, 3, 5, 2, 4).reshape(b, c * 4, h // 2, w // 2)


def unsqueeze2d(x: torch.Tensor) -> torch.Tensor:
    b, c, h, w = x.shape
    return x.view(b, c // 4, 2, 2, h, w).permute(0, 1, 4, 2, 5, 3).reshape(b, c // 4, h * 2, w * 2)


class FlowBlock(nn.Module):
    """squeeze -> K flow steps -> split (the last level: no split, prior from zeros)."""

    def __init__(self, k: int, cin: int, ccond: int, split: bool, hidden: int):
        super().__init__()
        c = cin * 4
        self.split = split
        self.actnorm = ActNorm(c)
        self.invconv = InvConv2d(c)
        self.flows = nn.ModuleList(FlowStep(c, ccond, hidden) for _ in range(k))
        self.prior = ZeroConv2d(cin * 2, cin * 4) if split else ZeroConv2d(cin * 4, cin * 8)

    def reverse(self, x, cond, eps):
        if self.split:
            mean, log_sd = self.prior(x).chunk(2, 1)
            x = torch.cat([x, mean + torch.exp(log_sd) * eps], 1)
        else:
            mean, log_sd = self.prior(torch.zeros_like(x)).chunk(2, 1)
            x = mean + torch.exp(log_sd) * eps
        for flow in self.flows[::-1]:
            x = flow.reverse(x, cond)
        return unsqueeze2d(self.actnorm.reverse(self.invconv.reverse(x)))


class CondFlowNet(nn.Module):
    def __init__(self, cins: tuple[int, int, int], k: int, hidden: int):
        super().__init__()
        self.blocks = nn.ModuleList([FlowBlock(k, 3, cins[0], True, hidden), FlowBlock(k, 6, cins[1], True, hidden),
                                     FlowBlock(k, 12, cins[2], False, hidden)])

    def decode(self, zs: list, conds: list) -> torch.Tensor:
        """Latents (fine to coarse) and conditions (fine to coarse) -> the image in [-1, 1]."""
        x = zs[-1]
        for i in range(len(self.blocks) - 1, -1, -1):
            x = self.blocks[i].reverse(x, conds[i], zs[i])
        return x


def z_shapes(h: int, w: int) -> list[tuple[int, int, int]]:
    """Latent shapes (C, H, W) per level for an (h, w) frame (h, w multiples of 8)."""
    return [(6, h // 2, w // 2), (12, h // 4, w // 4), (48, h // 8, w // 8)]


# ----------------------------------------------------------------------------- the generator

class Generator(nn.Module):
    """PFlowVFI_V0 ``Network`` in its key layout; :meth:`decode` is ``code="decode"``."""

    def __init__(self, cfg: dict):
        super().__init__()
        self.cfg = cfg
        cond = (3 + cfg["encode"][0], cfg["encode"][1], cfg["encode"][2])
        self.featurePyramid = FeaturePyramid(cfg)
        self.deformableAlign = DeformableAlign(cond, cfg["dcn_groups"], cfg["dcn_kernel"])
        self.attentionMerge = AttentionMerge(cond, *cfg["softbinary"])
        self.multiscaleFuse = MultiscaleFuse(cond, cfg["fuse"])
        self.condFLownet = CondFlowNet(cond, cfg["flow_steps"], cfg["coupling_width"])

    def conditions(self, img0, img1, f01, f10, time: float):
        feas, holes, ft1, aux = self.featurePyramid(img0, img1, f01, f10, time)
        fea1 = self.deformableAlign(feas, holes, ft1)[::-1]
        fea0 = [f[0] for f in feas]
        merged, masks = self.attentionMerge(fea0, fea1, holes)
        aux["soft_masks"] = masks  # coarse to fine
        return self.multiscaleFuse(merged[::-1]), aux

    def decode(self, zs: list, img0, img1, f01, f10, time: float = 0.5):
        """Frames in [0, 1] (B, 3, H, W), H, W multiples of 8, flows in pixels -> (frame in [0, 1], aux)."""
        conds, aux = self.conditions(img0 * 2 - 1, img1 * 2 - 1, f01, f10, time)
        return (self.condFLownet.decode(zs, conds) + 1) / 2, aux


OFFICIAL = {"encode": (32, 64, 96), "metric": (12, 4, (16, 32, 64, 96)), "dcn_groups": (7, 8, 8), "dcn_kernel": 3,
            "softbinary": (64, 8, 9),
            "fuse": {"stem": 64, "planes": 64, "bottlenecks": 4, "stage2": (32, 64), "modules2": 2, "blocks2": 2,
                     "stage3": (32, 64, 96), "modules3": 2, "blocks3": 2},
            "flow_steps": 16, "coupling_width": 64}
TINY = {"encode": (5, 8, 8), "metric": (3, 1, (4, 4, 4, 4)), "dcn_groups": (2, 2, 2), "dcn_kernel": 3,
        "softbinary": (8, 2, 3),
        "fuse": {"stem": 8, "planes": 4, "bottlenecks": 1, "stage2": (4, 8), "modules2": 1, "blocks2": 1,
                 "stage3": (4, 8, 8), "modules3": 1, "blocks3": 1},
        "flow_steps": 2, "coupling_width": 8}


def _count(sd: dict, prefix: str) -> int:
    """Number of consecutive integer children ``prefix.<i>`` that have a key."""
    n = 0
    while any(k.startswith(f"{prefix}.{n}.") for k in sd):
        n += 1
    return n


def config_from_state_dict(sd: dict, path: str | Path = "checkpoint") -> dict:
    """The generator's sizes read from the tensors' shapes (the official model: :data:`OFFICIAL`)."""
    def shape(key: str) -> tuple[int, ...]:
        if key not in sd:
            raise CheckpointError(f"{path} is not a {WHAT} checkpoint in the expected key layout: no key {key!r} "
                                  f"(found e.g. {sorted(sd)[:5]})")
        return tuple(sd[key].shape)

    shape("featurePyramid.netEncode.netOne.0.weight")
    if "condFLownet.blocks.0.actnorm.loc" not in sd:
        vb = any(k.startswith("generator.") for k in sd)
        raise CheckpointError(f"{path}: no 'condFLownet.blocks.0.actnorm.loc'" + (
            "; this looks like PerVFI's vb.pth (multi-scale decoder), which is not supported: use v00.pth"
            if vb else f" (found e.g. {sorted(sd)[:5]})"))
    enc = tuple(shape(f"featurePyramid.netEncode.{n}.0.weight")[0] for n in ("netOne", "netTwo", "netThr"))
    sm = "featurePyramid.netSoftmetric."
    metric = (shape(sm + "netInput.weight")[0], shape(sm + "netError.weight")[0],
              (shape(sm + "0x0 - 0x1.netMain.1.weight")[0],)
              + tuple(shape(f"{sm}{r}x0 - {r + 1}x0.netMain.1.weight")[0] for r in range(3)))
    k = shape("deformableAlign.deform_conv.l0.dconv.weight")[-1]
    groups = tuple(shape(f"deformableAlign.deform_conv.l{i}.conv_offset.weight")[0] // (3 * k * k) for i in range(3))
    sb = "attentionMerge.softbinary.0."
    softbinary = (shape(sb + "conv1.0.weight")[0], shape(sb + "fc.0.weight")[0], shape(sb + "conv1.0.weight")[-1])
    mf = "multiscaleFuse."
    fuse = {"stem": shape(mf + "stems.0.0.weight")[0], "planes": shape(mf + "layer1.0.conv1.weight")[0],
            "bottlenecks": _count(sd, mf + "layer1"),
            "stage2": tuple(shape(f"{mf}stage2.0.branches.{i}.0.conv1.weight")[0]
                            for i in range(_count(sd, mf + "stage2.0.branches"))),
            "modules2": _count(sd, mf + "stage2"), "blocks2": _count(sd, mf + "stage2.0.branches.0"),
            "stage3": tuple(shape(f"{mf}stage3.0.branches.{i}.0.conv1.weight")[0]
                            for i in range(_count(sd, mf + "stage3.0.branches"))),
            "modules3": _count(sd, mf + "stage3"), "blocks3": _count(sd, mf + "stage3.0.branches.0")}
    if len(fuse["stage2"]) != 2 or len(fuse["stage3"]) != 3:
        raise CheckpointError(f"{path}: the multi-scale fusion must have 2 then 3 branches, found "
                              f"{len(fuse['stage2'])} and {len(fuse['stage3'])}")
    return {"encode": enc, "metric": metric, "dcn_groups": groups, "dcn_kernel": k, "softbinary": softbinary,
            "fuse": fuse, "flow_steps": _count(sd, "condFLownet.blocks.0.flows"),
            "coupling_width": shape("condFLownet.blocks.0.flows.0.coupling.affine.tail.0.weight")[0]}


def build_generator(path: Path) -> Generator:
    return build_strict(path, WHAT, WHERE, lambda sd, p: Generator(config_from_state_dict(sd, p)))


class PerVFI(nn.Module):
    """The generator and its flow estimator (each cached per weight file)."""

    def __init__(self, generator: Generator, flownet: raft.RAFT):
        super().__init__()
        self.generator = generator
        self.flownet = flownet


def load(generator_path: str | Path, flow_path: str | Path) -> PerVFI:
    """PerVFI from ``v00.pth`` and RAFT's ``raft-sintel.pth``; a missing file raises MissingWeightsError."""
    return PerVFI(cached_model(build_generator, generator_path), raft.load(flow_path))


def latents(h: int, w: int, heat: float = HEAT, seed: int = SEED, batch: int = 1,
            device: torch.device | str = "cpu") -> list[torch.Tensor]:
    """``z ~ N(0, heat^2)`` per level (as the official ``get_z``), from a generator seeded with ``seed``."""
    gen = torch.Generator().manual_seed(seed)
    return [(torch.randn(batch, *s, generator=gen) * heat).to(device) for s in z_shapes(h, w)]


@torch.no_grad()
def synthesize(model: PerVFI, img0: torch.Tensor, img1: torch.Tensor, time: float = 0.5, heat: float = HEAT,
               seed: int = SEED, flows: tuple[torch.Tensor, torch.Tensor] | None = None):
    """(B, 3, H, W) frames in [0, 1], H, W multiples of 8 -> (frame at ``time`` clamped to [0, 1], aux).

    ``flows`` = (F_01, F_10) replaces the RAFT estimate (the official pipeline's ``flows=``).
    """
    f01, f10 = raft.flows(model.flownet, img0, img1) if flows is None else flows
    h, w = img0.shape[-2:]
    zs = latents(h, w, heat, seed, img0.shape[0], img0.device)
    pred, aux = model.generator.decode(zs, img0, img1, f01, f10, time)
    return pred.clamp(0.0, 1.0), aux


def blend_alpha(alpha0: torch.Tensor, alpha1: torch.Tensor, aux: dict) -> torch.Tensor:
    """Alpha at time t with the generator's own warps and asymmetric blend: frame 0's alpha
    softmax-splatted like its level-0 features, frame 1's backward-warped by F_t1, mixed by the
    finest soft-binary mask (the weight the network gives frame 1's features)."""
    a0 = softsplat(alpha0, aux["f0t"], aux["m0t"].neg().clip(-20.0, 20.0), "soft")
    a1 = backwarp(alpha1, aux["ft1"])
    sm = aux["soft_masks"][-1]
    return (a0 * (1 - sm) + a1 * sm).clamp(0.0, 1.0)


@deterministic
@torch.no_grad()
def interpolate_pair(model: PerVFI, frame0: np.ndarray, frame1: np.ndarray, time: float = 0.5,
                     heat: float = HEAT, seed: int = SEED) -> np.ndarray:
    """(H, W, C) frames in [0, 1] (C = 3 or 4) -> the frame at ``time`` (0.5: PerVFI's ×2).

    RGB goes through PerVFI; an alpha channel is carried by :func:`blend_alpha`.  Frames are padded
    (replicate) to a multiple of 8 and cropped back.
    """
    device = next(model.generator.parameters()).device
    h, w = frame0.shape[:2]
    ph, pw = (-h) % PAD, (-w) % PAD

    def prep(f: np.ndarray) -> torch.Tensor:
        x = torch.from_numpy(np.ascontiguousarray(f, dtype=np.float32)).permute(2, 0, 1)[None].to(device)
        return F.pad(x, (0, pw, 0, ph), mode="replicate") if ph or pw else x

    a, b = prep(frame0), prep(frame1)
    pred, aux = synthesize(model, a[:, :3], b[:, :3], time, heat, seed)
    out = [pred]
    if a.shape[1] > 3:
        out.append(blend_alpha(a[:, 3:], b[:, 3:], aux))
    y = torch.cat(out, 1)[0, :, :h, :w].float().cpu()
    return y.permute(1, 2, 0).numpy().astype(np.float32)


# ----------------------------------------------------------------------------- tiny models (tests, benchmarks)

def random_state_dicts(generator_cfg: dict | None = None, raft_cfg: dict | None = None,
                       seed: int = 0) -> tuple[dict, dict]:
    """Random-weight (generator, RAFT) state dicts in the official key layouts (tiny by default)."""
    torch.manual_seed(seed)
    gen = Generator(generator_cfg or TINY)
    with torch.no_grad():  # random but non-trivial: the zero-initialised layers get small values
        for name, p in gen.named_parameters():
            if name.endswith(("conv_offset.weight", "conv_offset.bias", "tail.4.conv.weight", "tail.4.conv.bias",
                              "prior.conv.weight", "prior.conv.bias")):
                p.normal_(0.0, 0.01)
    flow = raft.RAFT(raft_cfg or raft.TINY)
    return gen.state_dict(), flow.state_dict()


def save_random(generator_path: str | Path, flow_path: str | Path, generator_cfg: dict | None = None,
                raft_cfg: dict | None = None, seed: int = 0) -> tuple[Path, Path]:
    """Save random models as the release ships them (RAFT with the DataParallel ``module.`` prefix)."""
    g, f = random_state_dicts(generator_cfg, raft_cfg, seed)
    torch.save(g, generator_path)
    torch.save({f"module.{k}": v for k, v in f.items()}, flow_path)
    return Path(generator_path), Path(flow_path)

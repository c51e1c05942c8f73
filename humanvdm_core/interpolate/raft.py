"""RAFT optical flow (Teed & Deng, ECCV 2020) in plain PyTorch: the flow estimator of PerVFI.

Loads the official RAFT checkpoints (princeton-vl/RAFT, BSD-3-Clause; PerVFI's release ships
``RAFT/raft-sintel.pth``, which its ``raft+pervfi`` model uses) in their key layout, with or
without the DataParallel ``module.`` prefix::

    fnet.conv1.{weight,bias}, fnet.layer{1,2,3}.{0,1}.conv{1,2}.*, fnet.layer{2,3}.0.downsample.0.*,
    fnet.conv2.*                              feature encoder (instance norm: no parameters)
    cnet.* (same) + cnet.norm1.*, cnet.layerN.M.norm{1,2,3}.*, downsample.1.*   context encoder (batch norm)
    update_block.encoder.conv{c1,c2,f1,f2,}.*  motion encoder
    update_block.gru.conv{z,r,q}{1,2}.*        separable ConvGRU (1x5 then 5x1)
    update_block.flow_head.conv{1,2}.*         flow head
    update_block.mask.{0,2}.*                  convex-upsampling mask (64 * 9 channels)

Only the full RAFT ("raft-things/sintel/kitti/chairs.pth") is supported, not ``raft-small``.
Widths (encoders, hidden/context split, motion encoder, heads) and the correlation radius (4
pyramid levels) are read from the tensors' shapes, so a tiny model with the same keys runs the
same code.  Inference follows the reference: frames in [0, 1] -> ``2 x - 1``, all-pairs
correlation pyramid (4 levels, radius 4), ``iters`` GRU updates at 1/8 resolution, convex
upsampling ×8.  :func:`flows` pads frames to a multiple of 8 (at least 64) and crops back.
"""

from __future__ import annotations

from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from humanvdm_core.models.checkpoint import (
    CheckpointError,
    build_strict,
    cached_model,
)

WHAT = "RAFT optical-flow weights (raft-sintel.pth, PerVFI's flow estimator)"
WHERE = ("https://huggingface.co/Mulns/PerVFI-v1-0 (file RAFT/raft-sintel.pth; the PerVFI release, "
         "github.com/mulns/PerVFI) or github.com/princeton-vl/RAFT (models.zip; BSD-3-Clause)")
LEVELS = 4


class ResidualBlock(nn.Module):
    def __init__(self, cin: int, c: int, norm: str, stride: int):
        super().__init__()
        self.conv1 = nn.Conv2d(cin, c, 3, stride, 1)
        self.conv2 = nn.Conv2d(c, c, 3, 1, 1)
        make = (lambda: nn.BatchNorm2d(c)) if norm == "batch" else (lambda: nn.InstanceNorm2d(c))
        self.norm1, self.norm2 = make(), make()
        self.downsample = None
        if stride != 1:
            self.norm3 = make()
            self.downsample = nn.Sequential(nn.Conv2d(cin, c, 1, stride), self.norm3)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = F.relu(self.norm1(self.conv1(x)))
        y = F.relu(self.norm2(self.conv2(y)))
        return F.relu((x if self.downsample is None else self.downsample(x)) + y)


class Encoder(nn.Module):
    """RAFT's BasicEncoder: 7x7/2 conv, three stages of two residual blocks (/1, /2, /2), 1x1 out."""

    def __init__(self, widths: tuple[int, int, int, int], out: int, norm: str):
        super().__init__()
        w0, w1, w2, w3 = widths
        self.conv1 = nn.Conv2d(3, w0, 7, 2, 3)
        self.norm1 = nn.BatchNorm2d(w0) if norm == "batch" else nn.InstanceNorm2d(w0)
        self.layer1 = nn.Sequential(ResidualBlock(w0, w1, norm, 1), ResidualBlock(w1, w1, norm, 1))
        self.layer2 = nn.Sequential(ResidualBlock(w1, w2, norm, 2), ResidualBlock(w2, w2, norm, 1))
        self.layer3 = nn.Sequential(ResidualBlock(w2, w3, norm, 2), ResidualBlock(w3, w3, norm, 1))
        self.conv2 = nn.Conv2d(w3, out, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = F.relu(self.norm1(self.conv1(x)))
        return self.conv2(self.layer3(self.layer2(self.layer1(x))))


class MotionEncoder(nn.Module):
    def __init__(self, cor_planes: int, c1: int, c2: int, f1: int, f2: int, out: int):
        super().__init__()
        self.convc1 = nn.Conv2d(cor_planes, c1, 1)
        self.convc2 = nn.Conv2d(c1, c2, 3, padding=1)
        self.convf1 = nn.Conv2d(2, f1, 7, padding=3)
        self.convf2 = nn.Conv2d(f1, f2, 3, padding=1)
        self.conv = nn.Conv2d(c2 + f2, out - 2, 3, padding=1)

    def forward(self, flow: torch.Tensor, corr: torch.Tensor) -> torch.Tensor:
        cor = F.relu(self.convc2(F.relu(self.convc1(corr))))
        flo = F.relu(self.convf2(F.relu(self.convf1(flow))))
        return torch.cat([F.relu(self.conv(torch.cat([cor, flo], 1))), flow], 1)


class SepConvGRU(nn.Module):
    def __init__(self, hidden: int, cin: int):
        super().__init__()
        for axis, (k, p) in (("1", ((1, 5), (0, 2))), ("2", ((5, 1), (2, 0)))):
            for gate in "zrq":
                self.add_module(f"conv{gate}{axis}", nn.Conv2d(hidden + cin, hidden, k, padding=p))

    def forward(self, h: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        for axis in "12":
            hx = torch.cat([h, x], 1)
            z = torch.sigmoid(getattr(self, f"convz{axis}")(hx))
            r = torch.sigmoid(getattr(self, f"convr{axis}")(hx))
            q = torch.tanh(getattr(self, f"convq{axis}")(torch.cat([r * h, x], 1)))
            h = (1 - z) * h + z * q
        return h


class FlowHead(nn.Module):
    def __init__(self, cin: int, hidden: int):
        super().__init__()
        self.conv1 = nn.Conv2d(cin, hidden, 3, padding=1)
        self.conv2 = nn.Conv2d(hidden, 2, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.conv2(F.relu(self.conv1(x)))


class UpdateBlock(nn.Module):
    def __init__(self, cfg: dict):
        super().__init__()
        h, m = cfg["hidden"], cfg["motion"]
        self.encoder = MotionEncoder(LEVELS * (2 * cfg["radius"] + 1) ** 2, *cfg["motion_widths"], m)
        self.gru = SepConvGRU(h, cfg["context"] + m)
        self.flow_head = FlowHead(h, cfg["head"])
        self.mask = nn.Sequential(nn.Conv2d(h, cfg["mask"], 3, padding=1), nn.ReLU(inplace=True),
                                  nn.Conv2d(cfg["mask"], 64 * 9, 1))

    def forward(self, net, inp, corr, flow):
        net = self.gru(net, torch.cat([inp, self.encoder(flow, corr)], 1))
        return net, 0.25 * self.mask(net), self.flow_head(net)


def _sample(img: torch.Tensor, coords: torch.Tensor) -> torch.Tensor:
    """Bilinear sampling at pixel coordinates (x, y) (zeros outside), as RAFT's bilinear_sampler."""
    h, w = img.shape[-2:]
    gx = 2 * coords[..., 0] / max(w - 1, 1) - 1
    gy = 2 * coords[..., 1] / max(h - 1, 1) - 1
    return F.grid_sample(img, torch.stack([gx, gy], -1), mode="bilinear", padding_mode="zeros", align_corners=True)


class CorrPyramid:
    """All-pairs correlation volume and its average-pooled pyramid, looked up around ``coords``."""

    def __init__(self, f1: torch.Tensor, f2: torch.Tensor, radius: int):
        b, c, h, w = f1.shape
        corr = torch.matmul(f1.view(b, c, h * w).transpose(1, 2), f2.view(b, c, h * w)) / c ** 0.5
        corr = corr.reshape(b * h * w, 1, h, w)
        self.pyramid = [corr]
        for _ in range(LEVELS - 1):
            corr = F.avg_pool2d(corr, 2, stride=2)
            self.pyramid.append(corr)
        self.radius = radius

    def __call__(self, coords: torch.Tensor) -> torch.Tensor:
        r = self.radius
        b, _, h, w = coords.shape
        xy = coords.permute(0, 2, 3, 1).reshape(b * h * w, 1, 1, 2)
        d = torch.linspace(-r, r, 2 * r + 1, device=coords.device, dtype=coords.dtype)
        # The reference builds the window with meshgrid(dy, dx) and adds it to (x, y): window row i
        # offsets x by d[i] and column j offsets y by d[j].  Kept as is: the weights expect it.
        dx, dy = torch.meshgrid(d, d, indexing="ij")
        delta = torch.stack([dx, dy], -1).view(1, 2 * r + 1, 2 * r + 1, 2)
        out = [_sample(corr, xy / 2 ** i + delta).view(b, h, w, -1) for i, corr in enumerate(self.pyramid)]
        return torch.cat(out, -1).permute(0, 3, 1, 2).contiguous()


class RAFT(nn.Module):
    def __init__(self, cfg: dict):
        super().__init__()
        self.cfg = cfg
        self.fnet = Encoder(cfg["fnet"], cfg["feature"], "instance")
        self.cnet = Encoder(cfg["cnet"], cfg["hidden"] + cfg["context"], "batch")
        self.update_block = UpdateBlock(cfg)

    @staticmethod
    def _upsample(flow: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        n, _, h, w = flow.shape
        mask = torch.softmax(mask.view(n, 1, 9, 8, 8, h, w), dim=2)
        up = F.unfold(8 * flow, [3, 3], padding=1).view(n, 2, 9, 1, 1, h, w)
        up = torch.sum(mask * up, dim=2).permute(0, 1, 4, 2, 5, 3)
        return up.reshape(n, 2, 8 * h, 8 * w)

    def forward(self, image1: torch.Tensor, image2: torch.Tensor, iters: int = 12) -> torch.Tensor:
        """Flow from ``image1`` to ``image2`` (B, 3, H, W) in [0, 1], H and W multiples of 8, in pixels."""
        b = image1.shape[0]
        fmaps = self.fnet(torch.cat([2 * image1 - 1, 2 * image2 - 1], 0)).float()
        return self.refine(image1, fmaps[:b], fmaps[b:], iters)

    def refine(self, image1: torch.Tensor, fmap1: torch.Tensor, fmap2: torch.Tensor, iters: int) -> torch.Tensor:
        """The recurrent part, from the feature maps of both frames (``fnet`` output)."""
        image1 = 2 * image1 - 1
        b = image1.shape[0]
        corr_fn = CorrPyramid(fmap1, fmap2, self.cfg["radius"])
        net, inp = torch.split(self.cnet(image1), [self.cfg["hidden"], self.cfg["context"]], 1)
        net, inp = torch.tanh(net), torch.relu(inp)
        h, w = image1.shape[2] // 8, image1.shape[3] // 8
        ys, xs = torch.meshgrid(torch.arange(h, device=image1.device, dtype=torch.float32),
                                torch.arange(w, device=image1.device, dtype=torch.float32), indexing="ij")
        coords0 = torch.stack([xs, ys], 0)[None].expand(b, 2, h, w)
        coords1 = coords0.clone()
        mask = None
        for _ in range(iters):
            net, mask, delta = self.update_block(net, inp, corr_fn(coords1), coords1 - coords0)
            coords1 = coords1 + delta
        return self._upsample(coords1 - coords0, mask)


def config_from_state_dict(sd: dict, path: str | Path = "checkpoint") -> dict:
    """RAFT widths read from the tensors' shapes (the official model: see :data:`OFFICIAL`)."""
    def out(key: str) -> int:
        if key not in sd:
            raise CheckpointError(f"{path} is not a {WHAT} checkpoint: no key {key!r} (found e.g. {sorted(sd)[:5]})")
        return int(sd[key].shape[0])

    if "update_block.encoder.convc1.weight" not in sd:
        out("fnet.conv1.weight")
        raise CheckpointError(f"{path}: no 'update_block.encoder.convc1.weight'; only the full RAFT is supported "
                              "(raft-sintel/things/kitti.pth, not raft-small)")
    hidden = out("update_block.gru.convz1.weight")
    planes = int(sd["update_block.encoder.convc1.weight"].shape[1])
    radius = int(round(((planes / LEVELS) ** 0.5 - 1) / 2))
    if LEVELS * (2 * radius + 1) ** 2 != planes:
        raise CheckpointError(f"{path}: correlation input of {planes} channels is not {LEVELS} levels of a square window")
    enc = {name: tuple(out(f"{name}.{k}.weight") for k in ("conv1", "layer1.0.conv1", "layer2.0.conv1",
                                                           "layer3.0.conv1")) for name in ("fnet", "cnet")}
    return {"fnet": enc["fnet"], "cnet": enc["cnet"], "feature": out("fnet.conv2.weight"), "hidden": hidden,
            "context": out("cnet.conv2.weight") - hidden, "radius": radius,
            "motion_widths": tuple(out(f"update_block.encoder.{k}.weight") for k in ("convc1", "convc2", "convf1",
                                                                                     "convf2")),
            "motion": out("update_block.encoder.conv.weight") + 2, "head": out("update_block.flow_head.conv1.weight"),
            "mask": out("update_block.mask.0.weight")}


OFFICIAL = {"fnet": (64, 64, 96, 128), "cnet": (64, 64, 96, 128), "feature": 256, "hidden": 128, "context": 128,
            "radius": 4, "motion_widths": (256, 192, 128, 64), "motion": 128, "head": 256, "mask": 256}
TINY = {"fnet": (8, 8, 8, 8), "cnet": (8, 8, 8, 8), "feature": 8, "hidden": 8, "context": 8, "radius": 1,
        "motion_widths": (8, 8, 8, 8), "motion": 8, "head": 8, "mask": 8}


def build(path: Path) -> RAFT:
    return build_strict(path, WHAT, WHERE, lambda sd, p: RAFT(config_from_state_dict(sd, p)))


def load(path: str | Path) -> RAFT:
    return cached_model(build, path)


@torch.no_grad()
def flows(net: RAFT, img0: torch.Tensor, img1: torch.Tensor, iters: int = 12) -> tuple[torch.Tensor, torch.Tensor]:
    """(F_01, F_10) for (B, 3, H, W) frames in [0, 1]; pads (replicate) to a multiple of 8 (at least
    64, the smallest size the 4-level correlation pyramid takes) and crops back.

    PerVFI runs RAFT with 12 iterations in both directions (``model(I1, I2)``, ``model(I2, I1)``);
    here both directions go through one batch.
    """
    h, w = img0.shape[-2:]
    ph, pw = max((-h) % 8, 64 - h), max((-w) % 8, 64 - w)  # the 4-level pyramid needs >= 64 px
    a, b = (F.pad(x, (0, pw, 0, ph), mode="replicate") if ph or pw else x for x in (img0, img1))
    n = img0.shape[0]
    fmaps = net.fnet(torch.cat([2 * a - 1, 2 * b - 1], 0)).float()  # each frame encoded once
    fa, fb = fmaps[:n], fmaps[n:]
    out = net.refine(torch.cat([a, b], 0), torch.cat([fa, fb], 0), torch.cat([fb, fa], 0), iters)[..., :h, :w]
    return out[:n], out[n:]

"""Real-ESRGAN's generator, RRDBNet (ESRGAN's Residual-in-Residual Dense Blocks), in pure PyTorch.

Loads the official checkpoints (``RealESRGAN_x4plus.pth``, ``RealESRNet_x4plus.pth``,
``RealESRGAN_x2plus.pth``, ``RealESRGAN_x4plus_anime_6B.pth``; BSD-3-Clause, from
https://github.com/xinntao/Real-ESRGAN/releases) in BasicSR's key layout::

    conv_first, body.<i>.rdb{1,2,3}.conv{1..5}, conv_body, conv_up1, conv_up2, conv_hr, conv_last

wrapped in ``params_ema``.  The hyper-parameters come from the tensors: ``num_feat`` and the
scale from ``conv_first`` (3 input channels: ×4; 12: ×2 via pixel-unshuffle by 2; 48: ×1 via
pixel-unshuffle by 4), ``num_grow_ch`` from ``body.0.rdb1.conv1``, ``num_block`` from the
number of ``body.<i>`` entries.  The official x4plus model is num_feat 64, num_block 23,
num_grow_ch 32 (16.7 M parameters).

Inference (:func:`upscale_rgb`): RGB in [0, 1] (sRGB-encoded, as the model was trained), tiled
with an overlap of ``tile_pad`` input pixels on every side so memory stays bounded whatever the
frame size; each tile's padded border is cut away before it is placed, so seams never show
(the model's receptive field is covered by the padding).  Output clamped to [0, 1].
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from humanvdm_core.models.checkpoint import (
    CheckpointError,
    cached_model,
    deterministic,
    infer_device,
    load_strict,
    read_state_dict,
)

WHAT = "Real-ESRGAN RRDBNet weights"
WHERE = ("https://github.com/xinntao/Real-ESRGAN/releases (v0.1.0: RealESRGAN_x4plus.pth; "
         "BSD-3-Clause)")


class DenseBlock(nn.Module):
    """Five 3x3 convs, each seeing the block input and all previous outputs; residual scaled by 0.2."""

    def __init__(self, num_feat: int, num_grow_ch: int):
        super().__init__()
        self.conv1 = nn.Conv2d(num_feat, num_grow_ch, 3, 1, 1)
        self.conv2 = nn.Conv2d(num_feat + num_grow_ch, num_grow_ch, 3, 1, 1)
        self.conv3 = nn.Conv2d(num_feat + 2 * num_grow_ch, num_grow_ch, 3, 1, 1)
        self.conv4 = nn.Conv2d(num_feat + 3 * num_grow_ch, num_grow_ch, 3, 1, 1)
        self.conv5 = nn.Conv2d(num_feat + 4 * num_grow_ch, num_feat, 3, 1, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        feats = [x]
        for conv in (self.conv1, self.conv2, self.conv3, self.conv4):
            feats.append(F.leaky_relu(conv(torch.cat(feats, 1)), 0.2))
        return x + 0.2 * self.conv5(torch.cat(feats, 1))


class RRDB(nn.Module):
    """Three dense blocks in a residual, scaled by 0.2."""

    def __init__(self, num_feat: int, num_grow_ch: int):
        super().__init__()
        self.rdb1 = DenseBlock(num_feat, num_grow_ch)
        self.rdb2 = DenseBlock(num_feat, num_grow_ch)
        self.rdb3 = DenseBlock(num_feat, num_grow_ch)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + 0.2 * self.rdb3(self.rdb2(self.rdb1(x)))


class RRDBNet(nn.Module):
    """RRDBNet; output is ``scale`` times the input size (×4 always inside, after pixel-unshuffle)."""

    def __init__(self, scale: int = 4, num_feat: int = 64, num_block: int = 23, num_grow_ch: int = 32):
        super().__init__()
        if scale not in (1, 2, 4):
            raise ValueError(f"RRDBNet scale must be 1, 2 or 4, got {scale}")
        self.scale = scale
        self.unshuffle = 4 // scale  # x2: unshuffle by 2; x1: by 4
        self.conv_first = nn.Conv2d(3 * self.unshuffle ** 2, num_feat, 3, 1, 1)
        self.body = nn.Sequential(*[RRDB(num_feat, num_grow_ch) for _ in range(num_block)])
        self.conv_body = nn.Conv2d(num_feat, num_feat, 3, 1, 1)
        self.conv_up1 = nn.Conv2d(num_feat, num_feat, 3, 1, 1)
        self.conv_up2 = nn.Conv2d(num_feat, num_feat, 3, 1, 1)
        self.conv_hr = nn.Conv2d(num_feat, num_feat, 3, 1, 1)
        self.conv_last = nn.Conv2d(num_feat, 3, 3, 1, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.unshuffle > 1:
            x = F.pixel_unshuffle(x, self.unshuffle)
        feat = self.conv_first(x)
        feat = feat + self.conv_body(self.body(feat))
        feat = F.leaky_relu(self.conv_up1(F.interpolate(feat, scale_factor=2, mode="nearest")), 0.2)
        feat = F.leaky_relu(self.conv_up2(F.interpolate(feat, scale_factor=2, mode="nearest")), 0.2)
        return self.conv_last(F.leaky_relu(self.conv_hr(feat), 0.2))


def config_from_state_dict(sd: dict, path: str | Path = "checkpoint") -> dict:
    """RRDBNet constructor arguments read from the tensors' shapes (see module docstring)."""
    try:
        in_ch, num_feat = int(sd["conv_first.weight"].shape[1]), int(sd["conv_first.weight"].shape[0])
        num_grow_ch = int(sd["body.0.rdb1.conv1.weight"].shape[0])
    except KeyError as e:
        raise CheckpointError(f"{path} is not a {WHAT} checkpoint: no key {e.args[0]!r} "
                              f"(found e.g. {sorted(sd)[:5]})") from None
    scales = {3: 4, 12: 2, 48: 1}
    if in_ch not in scales:
        raise CheckpointError(f"{path}: conv_first takes {in_ch} channels; RRDBNet takes 3 (x4), 12 (x2) or 48 (x1)")
    num_block = len({k.split(".")[1] for k in sd if k.startswith("body.")})
    return {"scale": scales[in_ch], "num_feat": num_feat, "num_block": num_block, "num_grow_ch": num_grow_ch}


def build(path: Path) -> RRDBNet:
    """An RRDBNet with the weights of ``path``, on the inference device."""
    sd = read_state_dict(path, WHAT, WHERE)
    net = RRDBNet(**config_from_state_dict(sd, path))
    load_strict(net, sd, WHAT, path)
    return net.to(infer_device())


def load(path: str | Path) -> RRDBNet:
    """The model of ``path``, built once per process."""
    return cached_model(build, path)


@deterministic
@torch.no_grad()
def upscale_rgb(net: RRDBNet, rgb: np.ndarray, tile: int = 256, tile_pad: int = 16) -> np.ndarray:
    """(H, W, 3) float RGB in [0, 1] -> (scale H, scale W, 3) float32, tile by tile (``tile`` <= 0: whole).

    Each tile of ``tile`` x ``tile`` input pixels is run with ``tile_pad`` pixels of real context
    on each side (reflect-padded at the frame border), and only its centre is kept.
    """
    s = net.scale
    device = next(net.parameters()).device
    img = torch.from_numpy(np.ascontiguousarray(np.clip(rgb, 0.0, 1.0), dtype=np.float32)).permute(2, 0, 1)[None]
    h, w = img.shape[-2:]
    # x2/x1 models pixel-unshuffle: every window must be a multiple of the unshuffle factor m.
    m = net.unshuffle
    ph, pw = (-h) % m, (-w) % m
    pad = -(-max(tile_pad, 0) // m) * m  # context on each side, rounded up to a multiple of m
    mode = "reflect" if min(h, w) > pad + m else "replicate"
    src = F.pad(img, (pad, pad + pw, pad, pad + ph), mode=mode) if pad or pw or ph else img
    hh, ww = h + ph, w + pw
    out = torch.empty(1, 3, hh * s, ww * s)
    step = tile if tile > 0 else max(hh, ww)
    step = max(m, step - step % m)
    for y in range(0, hh, step):
        for x in range(0, ww, step):
            y1, x1 = min(y + step, hh), min(x + step, ww)
            # window = the tile plus ``pad`` context pixels each side (src is offset by pad)
            res = net(src[..., y:y1 + 2 * pad, x:x1 + 2 * pad].to(device)).float().cpu()
            out[..., y * s:y1 * s, x * s:x1 * s] = res[..., pad * s:(pad + y1 - y) * s, pad * s:(pad + x1 - x) * s]
    return out[0, :, :h * s, :w * s].clamp_(0.0, 1.0).permute(1, 2, 0).numpy()

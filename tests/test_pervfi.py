"""The ``pervfi`` interpolate backend (PerVFI v00 generator + RAFT flow estimator) with TINY random
models saved in the official checkpoints' key layouts and loaded through the real code path:
shapes, determinism, the pure-PyTorch forward warp (softsplat) and deformable convolution against
brute-force references, alpha handling, layout errors, missing weights, and the stage end to end."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from humanvdm_core.errors import MissingWeightsError  # noqa: E402
from humanvdm_core.models.checkpoint import CheckpointError  # noqa: E402

REPO = Path(__file__).resolve().parents[1]

# Key names of the official checkpoints (a sample of each module family).
GENERATOR_KEYS = [
    "featurePyramid.netEncode.netOne.0.weight", "featurePyramid.netEncode.netThr.3.weight",
    "featurePyramid.netSoftmetric.netInput.weight", "featurePyramid.netSoftmetric.netError.weight",
    "featurePyramid.netSoftmetric.0x0 - 1x0.netMain.1.weight", "featurePyramid.netSoftmetric.3x1 - 2x1.netMain.2.weight",
    "featurePyramid.netSoftmetric.netOutput.netShortcut.weight",
    "deformableAlign.offset_conv1.l2.weight", "deformableAlign.offset_conv3.l0.bias",
    "deformableAlign.deform_conv.l0.conv_offset.weight", "deformableAlign.deform_conv.l1.dconv.weight",
    "deformableAlign.deform_conv.l1.dconv.bias", "deformableAlign.merge_conv2.l1.weight",
    "attentionMerge.softbinary.0.conv1.0.weight", "attentionMerge.softbinary.2.fc.2.weight",
    "attentionMerge.softbinary.1.att.bias", "attentionMerge.softbinary.1.conv2.weight",
    "multiscaleFuse.stems.2.0.weight", "multiscaleFuse.layer1.0.downsample.weight", "multiscaleFuse.layer1.0.conv3.weight",
    "multiscaleFuse.transition1.0.0.weight", "multiscaleFuse.transition1.1.0.0.weight", "multiscaleFuse.extra1.0.weight",
    "multiscaleFuse.stage2.0.branches.1.0.conv2.weight", "multiscaleFuse.stage2.0.fuse_layers.0.1.0.weight",
    "multiscaleFuse.stage3.0.fuse_layers.2.0.0.0.weight", "multiscaleFuse.stage3.0.fuse_layers.2.0.1.weight",
    "multiscaleFuse.transition2.2.0.0.weight", "multiscaleFuse.final_layers.0.bias",
    "condFLownet.blocks.0.actnorm.loc", "condFLownet.blocks.0.actnorm.initialized", "condFLownet.blocks.1.invconv.weight",
    "condFLownet.blocks.2.flows.1.coupling.affine.tail.0.weight", "condFLownet.blocks.2.flows.1.coupling.affine.tail.4.scale",
    "condFLownet.blocks.0.flows.0.coupling.scale_shift", "condFLownet.blocks.1.prior.conv.weight",
    "condFLownet.blocks.2.prior.scale",
]
RAFT_KEYS = ["module.fnet.conv1.weight", "module.fnet.layer2.0.downsample.0.weight", "module.cnet.norm1.running_var",
             "module.cnet.layer3.0.norm3.weight", "module.cnet.layer3.0.downsample.1.weight",
             "module.update_block.encoder.convc1.weight", "module.update_block.gru.convq2.bias",
             "module.update_block.flow_head.conv2.weight", "module.update_block.mask.2.weight"]


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> tuple[Path, Path]:
    from humanvdm_core.interpolate import pervfi

    folder = tmp_path_factory.mktemp("pervfi")
    return pervfi.save_random(folder / "v00.pth", folder / "raft-sintel.pth")


def frame(h: int, w: int, seed: int = 0) -> np.ndarray:
    """A smooth RGBA frame: a disc of texture on white, alpha the disc."""
    rng = np.random.default_rng(seed)
    ys, xs = np.mgrid[0:h, 0:w] + 0.5
    alpha = np.clip(min(h, w) * 0.35 - np.hypot(xs - w / 2 - seed, ys - h / 2), 0.0, 1.0).astype(np.float32)
    tex = rng.random((h // 4 + 1, w // 4 + 1, 3)).astype(np.float32).repeat(4, 0).repeat(4, 1)[:h, :w]
    rgb = tex * alpha[..., None] + (1.0 - alpha[..., None])
    return np.concatenate([rgb, alpha[..., None]], axis=-1)


def run_stage(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "stages.interpolate", *args], cwd=REPO, capture_output=True,
                          text=True, timeout=180, env={**os.environ, "OMP_NUM_THREADS": "1"})


# ----------------------------------------------------------------------------- layout and loading

def test_tiny_checkpoints_have_the_official_layout_and_sizes_come_from_shapes(tiny):
    from humanvdm_core.interpolate import pervfi, raft

    gen_path, flow_path = tiny
    gsd = torch.load(gen_path, weights_only=True)
    fsd = torch.load(flow_path, weights_only=True)
    assert set(GENERATOR_KEYS) <= set(gsd)
    assert set(RAFT_KEYS) <= set(fsd)
    assert pervfi.config_from_state_dict(gsd) == pervfi.TINY
    assert raft.config_from_state_dict({k[len("module."):]: v for k, v in fsd.items()}) == raft.TINY
    model = pervfi.load(gen_path, flow_path)
    assert pervfi.load(gen_path, flow_path).generator is model.generator  # cached per file


def test_official_sizes_are_read_from_shapes():
    from humanvdm_core.interpolate import pervfi, raft

    with torch.device("meta"):  # shapes only, no memory
        gen = pervfi.Generator(pervfi.OFFICIAL).state_dict()
        flow = raft.RAFT(raft.OFFICIAL).state_dict()
    assert set(GENERATOR_KEYS) <= set(gen)
    assert pervfi.config_from_state_dict(gen) == pervfi.OFFICIAL
    assert raft.config_from_state_dict(flow) == raft.OFFICIAL
    assert tuple(gen["multiscaleFuse.final_layers.0.weight"].shape) == (35, 32, 3, 3)  # condition channels 35/64/96
    assert tuple(gen["deformableAlign.deform_conv.l0.conv_offset.weight"].shape)[0] == 7 * 27  # 7 groups at level 0
    assert sum(v.numel() for v in flow.values() if v.dtype.is_floating_point) == pytest.approx(5.26e6, rel=0.01)


def test_layout_errors_name_missing_and_unexpected_keys(tmp_path, tiny):
    from humanvdm_core.interpolate import pervfi, raft

    sd = torch.load(tiny[0], weights_only=True)
    sd["attentionMerge.softbinary.1.att_renamed.weight"] = sd.pop("attentionMerge.softbinary.1.att.weight")
    torch.save(sd, tmp_path / "bad.pth")
    with pytest.raises(CheckpointError) as e:
        pervfi.build_generator(tmp_path / "bad.pth")
    msg = str(e.value)
    assert "bad.pth" in msg and "missing keys: attentionMerge.softbinary.1.att.weight" in msg
    assert "unexpected keys: attentionMerge.softbinary.1.att_renamed.weight" in msg
    torch.save({"generator.conv1.netMain.0.weight": torch.zeros(1)}, tmp_path / "foreign.pth")
    with pytest.raises(CheckpointError, match="no key 'featurePyramid.netEncode.netOne.0.weight'"):
        pervfi.build_generator(tmp_path / "foreign.pth")
    vb = {k: v for k, v in sd.items() if not k.startswith("condFLownet.")}
    vb["generator.conv1.netMain.0.weight"] = torch.zeros(1)
    torch.save(vb, tmp_path / "vb.pth")
    with pytest.raises(CheckpointError, match="vb.pth .*not supported: use v00.pth"):
        pervfi.build_generator(tmp_path / "vb.pth")
    fsd = torch.load(tiny[1], weights_only=True)
    fsd.pop("module.update_block.mask.2.bias")
    torch.save(fsd, tmp_path / "raft-bad.pth")
    with pytest.raises(CheckpointError, match=r"missing keys: update_block\.mask\.2\.bias"):
        raft.build(tmp_path / "raft-bad.pth")
    torch.save({"module.fnet.conv1.weight": torch.zeros(32, 3, 7, 7)}, tmp_path / "raft-small.pth")
    with pytest.raises(CheckpointError, match="not raft-small"):
        raft.build(tmp_path / "raft-small.pth")


def test_missing_weights_name_each_file_and_where_to_get_it(tmp_path, tiny):
    from humanvdm_core.interpolate import pervfi

    with pytest.raises(MissingWeightsError) as e:
        pervfi.load(tmp_path / "v00.pth", tiny[1])
    assert str(tmp_path / "v00.pth") in str(e.value) and "Mulns/PerVFI-v1-0" in str(e.value)
    with pytest.raises(MissingWeightsError) as e:
        pervfi.load(tiny[0], tmp_path / "raft-sintel.pth")
    assert str(tmp_path / "raft-sintel.pth") in str(e.value) and "RAFT/raft-sintel.pth" in str(e.value)


# ----------------------------------------------------------------------------- warping primitives

def brute_force_splat(x: np.ndarray, flow: np.ndarray) -> np.ndarray:
    """Summation splat, pixel by pixel: the cupy kernel's loop written out."""
    c, h, w = x.shape
    out = np.zeros_like(x, dtype=np.float64)
    for y in range(h):
        for xx in range(w):
            fx, fy = xx + flow[0, y, xx], y + flow[1, y, xx]
            if not (np.isfinite(fx) and np.isfinite(fy)):
                continue
            x0, y0 = int(np.floor(fx)), int(np.floor(fy))
            for cx, cy, wt in ((x0, y0, (x0 + 1 - fx) * (y0 + 1 - fy)), (x0 + 1, y0, (fx - x0) * (y0 + 1 - fy)),
                               (x0, y0 + 1, (x0 + 1 - fx) * (fy - y0)), (x0 + 1, y0 + 1, (fx - x0) * (fy - y0))):
                if 0 <= cx < w and 0 <= cy < h:
                    out[:, cy, cx] += x[:, y, xx] * wt
    return out


def test_softsplat_matches_a_brute_force_splat():
    from humanvdm_core.interpolate.pervfi import softsplat

    rng = np.random.default_rng(0)
    x = rng.random((2, 3, 7, 9)).astype(np.float32)
    flow = (rng.standard_normal((2, 2, 7, 9)) * 3).astype(np.float32)  # some leave the frame
    flow[0, 0, 2, 3] = np.nan  # a non-finite flow splats nothing
    metric = rng.standard_normal((2, 1, 7, 9)).astype(np.float32)
    tx, tf, tm = torch.from_numpy(x), torch.from_numpy(flow), torch.from_numpy(metric)
    summed = softsplat(tx, tf, None, "sum").numpy()
    avg = softsplat(tx, tf, None, "avg").numpy()
    soft = softsplat(tx, tf, tm, "soft").numpy()
    for b in range(2):
        ref = brute_force_splat(x[b], flow[b])
        wsum = brute_force_splat(np.ones_like(x[b][:1]), flow[b])
        assert np.abs(summed[b] - ref).max() < 1e-5
        assert np.abs(avg[b] - ref / (wsum + 1e-7)).max() < 1e-4
        e = np.exp(metric[b])
        ref_soft = brute_force_splat(x[b] * e, flow[b]) / (brute_force_splat(e, flow[b]) + 1e-7)
        assert np.abs(soft[b] - ref_soft).max() < 1e-4


def test_zero_flow_splat_is_the_identity_and_holes_are_found():
    from humanvdm_core.interpolate.pervfi import binary_hole, softsplat

    x = torch.rand(1, 4, 6, 8)
    zero = torch.zeros(1, 2, 6, 8)
    assert torch.equal(softsplat(x, zero, None, "sum"), x)
    assert torch.allclose(softsplat(x, zero, None, "avg"), x, atol=1e-6)
    assert torch.allclose(softsplat(x, zero, torch.randn(1, 1, 6, 8), "soft"), x, atol=1e-5)
    assert binary_hole(zero).sum() == 0
    shift = zero.clone()
    shift[:, 0] = 2.0  # everything moves two pixels right: the two left columns are holes
    holes = binary_hole(shift)[0, 0]
    assert holes[:, :2].eq(1).all() and holes[:, 2:].eq(0).all()


def test_deform_conv_matches_conv_and_shifts():
    from humanvdm_core.interpolate.pervfi import deform_conv2d

    torch.manual_seed(0)
    x, weight, bias = torch.randn(1, 4, 6, 7), torch.randn(5, 4, 3, 3), torch.randn(5)
    groups = 2
    offset = torch.zeros(1, groups * 2 * 9, 6, 7)
    mask = torch.ones(1, groups * 9, 6, 7)
    ref = torch.nn.functional.conv2d(x, weight, bias, padding=1)
    assert torch.allclose(deform_conv2d(x, offset, mask, weight, bias), ref, atol=1e-5)
    offset.view(1, groups, 9, 2, 6, 7)[:, :, :, 1] = 1.0  # every tap one pixel to the right (dx)
    shifted = torch.nn.functional.pad(x, (0, 2, 1, 1))  # tap (i, j) at x reads x(y + i - 1, x + j), zeros outside
    assert torch.allclose(deform_conv2d(x, offset, mask, weight, bias),
                          torch.nn.functional.conv2d(shifted, weight, bias), atol=1e-5)
    assert torch.allclose(deform_conv2d(x, offset, mask * 0.5, weight, None),
                          0.5 * torch.nn.functional.conv2d(shifted, weight, None), atol=1e-5)


def brute_force_dcn(x, offset, mask, weight, bias):
    """torchvision's modulated deformable convolution written out (its bilinear_interpolate: zero
    outside, nothing at or beyond one pixel outside the frame)."""
    c, h, w = x.shape
    cout, _, kh, kw = weight.shape
    groups = offset.shape[0] // (2 * kh * kw)
    cg = c // groups

    def bilinear(img, y, xx):
        if y <= -1 or y >= h or xx <= -1 or xx >= w:
            return np.zeros(img.shape[0])
        y0, x0 = int(np.floor(y)), int(np.floor(xx))
        ly, lx = y - y0, xx - x0
        out = np.zeros(img.shape[0])
        for yy, xq, wt in ((y0, x0, (1 - ly) * (1 - lx)), (y0, x0 + 1, (1 - ly) * lx),
                           (y0 + 1, x0, ly * (1 - lx)), (y0 + 1, x0 + 1, ly * lx)):
            if 0 <= yy < h and 0 <= xq < w:
                out += wt * img[:, yy, xq]
        return out

    out = np.zeros((cout, h, w)) + bias[:, None, None]
    for y in range(h):
        for xx in range(w):
            cols = np.zeros((c, kh, kw))
            for g in range(groups):
                for i in range(kh):
                    for j in range(kw):
                        k = i * kw + j
                        dy, dx = offset[g * 2 * kh * kw + 2 * k, y, xx], offset[g * 2 * kh * kw + 2 * k + 1, y, xx]
                        v = bilinear(x[g * cg:(g + 1) * cg], y - kh // 2 + i + dy, xx - kw // 2 + j + dx)
                        cols[g * cg:(g + 1) * cg, i, j] = v * mask[g * kh * kw + k, y, xx]
            out[:, y, xx] += np.einsum("ocij,cij->o", weight, cols)
    return out


def test_deform_conv_matches_a_brute_force_reference():
    from humanvdm_core.interpolate.pervfi import deform_conv2d

    rng = np.random.default_rng(1)
    x = rng.standard_normal((4, 5, 6))
    weight, bias = rng.standard_normal((3, 4, 3, 3)), rng.standard_normal(3)
    offset = rng.standard_normal((2 * 2 * 9, 5, 6)) * 2.0  # 2 offset groups; some taps leave the frame
    mask = rng.random((2 * 9, 5, 6))
    ours = deform_conv2d(*(torch.from_numpy(a).float()[None] for a in (x, offset, mask)),
                         torch.from_numpy(weight).float(), torch.from_numpy(bias).float())[0].numpy()
    assert np.abs(ours - brute_force_dcn(x, offset, mask, weight, bias)).max() < 1e-4


def test_raft_correlation_lookup_keeps_the_reference_window_order():
    from humanvdm_core.interpolate.raft import LEVELS, CorrPyramid

    torch.manual_seed(0)
    f1, f2 = torch.randn(1, 5, 16, 16), torch.randn(1, 5, 16, 16)
    ys, xs = torch.meshgrid(torch.arange(16.0), torch.arange(16.0), indexing="ij")
    out = CorrPyramid(f1, f2, radius=1)(torch.stack([xs, ys])[None])
    assert out.shape == (1, LEVELS * 9, 16, 16)
    y, x = 7, 9
    for i, di in enumerate((-1, 0, 1)):
        for j, dj in enumerate((-1, 0, 1)):  # channel i * 3 + j looks at (x + d_i, y + d_j)
            ref = (f1[0, :, y, x] * f2[0, :, y + dj, x + di]).sum() / 5 ** 0.5
            assert torch.allclose(out[0, i * 3 + j, y, x], ref, atol=1e-5)


def test_normalizing_flow_squeeze_round_trips():
    from humanvdm_core.interpolate.pervfi import squeeze2d, unsqueeze2d, z_shapes

    x = torch.randn(2, 3, 8, 12)
    assert torch.equal(unsqueeze2d(squeeze2d(x)), x)
    assert z_shapes(16, 24) == [(6, 8, 12), (12, 4, 6), (48, 2, 3)]


# ----------------------------------------------------------------------------- inference

def test_interpolate_pair_shape_determinism_and_seed(tiny):
    from humanvdm_core.interpolate import pervfi

    model = pervfi.load(*tiny)
    f0, f1 = frame(60, 70, 0), frame(60, 70, 1)  # padded to 64 x 72 and cropped back
    a = pervfi.interpolate_pair(model, f0, f1)
    assert a.shape == (60, 70, 4) and a.dtype == np.float32
    assert 0.0 <= a.min() and a.max() <= 1.0
    assert np.array_equal(a, pervfi.interpolate_pair(model, f0, f1))  # same inputs, same frame
    other = pervfi.interpolate_pair(model, f0, f1, seed=1)
    assert not np.array_equal(a[..., :3], other[..., :3])  # the latent is sampled (heat 0.3) ...
    assert np.array_equal(a[..., 3], other[..., 3])  # ... alpha is not
    mean = pervfi.interpolate_pair(model, f0, f1, heat=0.0)
    assert np.array_equal(mean, pervfi.interpolate_pair(model, f0, f1, heat=0.0, seed=5))  # heat 0: the mean
    rgb = pervfi.interpolate_pair(model, f0[..., :3], f1[..., :3])
    assert rgb.shape == (60, 70, 3) and np.array_equal(rgb, a[..., :3])


def test_identical_frames_keep_their_alpha_with_zero_flow(tiny):
    """The generator's RGB is sampled (random weights here: no identity), but the alpha path
    splats and warps with the network's flows: two identical frames and zero flow give the same alpha."""
    from humanvdm_core.interpolate import pervfi

    model = pervfi.load(*tiny)
    device = next(model.generator.parameters()).device  # CUDA where present (tensors in, tensors out)
    f = torch.from_numpy(frame(32, 40, 2)).permute(2, 0, 1)[None].to(device)
    zero = torch.zeros(1, 2, 32, 40, device=device)
    pred, aux = pervfi.synthesize(model, f[:, :3], f[:, :3], flows=(zero, zero))
    assert pred.shape == (1, 3, 32, 40)
    assert torch.equal(aux["ft1"], torch.zeros_like(aux["ft1"]))
    alpha = pervfi.blend_alpha(f[:, 3:], f[:, 3:], aux)
    assert torch.allclose(alpha, f[:, 3:], atol=1e-5)


def test_backend_runs_recursive_whatever_the_schedule(tiny):
    from humanvdm_core.interpolate import pervfi
    from humanvdm_core.interpolate.core import (
        BACKENDS,
        InterpolateOptions,
        effective_schedule,
        interpolate_interval,
    )

    opts = InterpolateOptions(passes=2, schedule="direct", pervfi_weights=str(tiny[0]),
                              pervfi_flow_weights=str(tiny[1]))
    assert effective_schedule(opts, "pervfi") == "recursive" and effective_schedule(opts, "rife") == "direct"
    f0, f1 = frame(32, 32, 0), frame(32, 32, 1)
    mids = interpolate_interval(f0, f1, opts, backend="pervfi")
    assert len(mids) == 3
    half = pervfi.interpolate_pair(pervfi.load(*tiny), f0, f1)
    assert np.array_equal(mids[1], half)  # t = 1/2 from the key pair, t = 1/4 and 3/4 from it
    assert np.array_equal(mids[0], pervfi.interpolate_pair(pervfi.load(*tiny), f0, half))
    assert np.array_equal(BACKENDS["pervfi"](f0, f1, [0.5], opts)[0], half)


# ----------------------------------------------------------------------------- the stage

def test_stage_params_and_backend_registration():
    from humanvdm_core.interpolate import core as interpolate
    from stages.interpolate import SPEC

    assert "pervfi" in SPEC.backends and "pervfi" in interpolate.BACKENDS
    for name, file in (("pervfi_weights", "v00.pth"), ("pervfi_flow_weights", "raft-sintel.pth")):
        p = SPEC.params[name]
        assert p.weights and p.default == f"~/.cache/humanvdm/weights/pervfi/{file}"
        assert p.applies_to("pervfi") and not p.applies_to("rife") and not p.applies_to("embedded")


def test_interpolate_stage_cli_pervfi(tmp_path, tiny):
    from humanvdm_core.cameras import orbit_cameras
    from humanvdm_core.frames import frame_paths, read_cameras, write_frames
    from humanvdm_core.io import read_exr

    src = tmp_path / "src"
    write_frames(src, [frame(32, 32, i) for i in range(3)], orbit_cameras(3, size=32), attrs={"stage": "test"})
    r = run_stage("--frames", str(src), "--out-frames", str(tmp_path / "out"), "--backend", "pervfi",
                  "--pervfi-weights", str(tiny[0]), "--pervfi-flow-weights", str(tiny[1]))
    assert r.returncode == 0, r.stderr
    paths = frame_paths(tmp_path / "out")
    assert len(paths) == 9  # 3 -> 5 -> 9 (21 -> 41 -> 81 for an SV3D orbit)
    assert np.array_equal(read_exr(paths[4]), read_exr(frame_paths(src)[1]))  # key frames unchanged
    img, attrs = read_exr(paths[2], with_attrs=True)
    assert img.shape == (32, 32, 4) and str(attrs.get("humanvdm:interpolate_schedule")) == "recursive"
    assert len(read_cameras(tmp_path / "out")) == 9
    missing = tmp_path / "nowhere" / "raft-sintel.pth"  # the second file: both are checked before any frame
    r = run_stage("--frames", str(src), "--out-frames", str(tmp_path / "out2"), "--backend", "pervfi",
                  "--pervfi-weights", str(tiny[0]), "--pervfi-flow-weights", str(missing))
    assert r.returncode == 3 and str(missing) in r.stderr and "Mulns/PerVFI-v1-0" in r.stderr
    assert "Traceback" not in r.stderr

"""Tests of the upscale stage: halo-free sharpened resampling, cameras and layers, byte-identical
pass-through, the stage command line and its input errors."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from humanvdm_core.cameras import orbit_cameras
from humanvdm_core.frames import frame_paths, read_cameras, read_frames, write_frames
from humanvdm_core.io import read_exr, write_exr
from humanvdm_core.upscale.core import UpscaleOptions, resample_color, upscale_embedded, upscale_frame_set
from humanvdm_core.workflow.errors import InputError

REPO = Path(__file__).resolve().parents[1]


def textured(size: int, seed: int = 0) -> np.ndarray:
    """A smooth-noise colour texture in [0, 1] (detail at several scales)."""
    import cv2

    rng = np.random.default_rng(seed)
    out = np.zeros((size, size, 3), np.float32)
    for sigma, amp in ((1.5, 0.3), (4.0, 0.4), (10.0, 0.3)):
        noise = cv2.GaussianBlur(rng.standard_normal((size, size, 3)).astype(np.float32), (0, 0), sigma)
        out += amp * noise / noise.std()
    return np.clip(0.5 + 0.15 * out, 0.0, 1.0)


def subject_frame(size: int, seed: int = 0) -> np.ndarray:
    """RGBA: a textured disc composited over a white background, alpha = coverage."""
    ys, xs = np.mgrid[0:size, 0:size] + 0.5
    r = np.hypot(xs - size / 2, ys - size / 2)
    alpha = np.clip(size * 0.35 - r + 0.5, 0.0, 1.0).astype(np.float32)
    rgb = textured(size, seed) * 0.6 * alpha[..., None] + (1.0 - alpha[..., None])
    return np.concatenate([rgb, alpha[..., None]], axis=-1).astype(np.float32)


def make_frame_set(root: Path, size: int = 48, n: int = 3, layers: bool = True) -> Path:
    frames = [subject_frame(size, seed=i) for i in range(n)]
    write_frames(root, frames, orbit_cameras(n, size=size), attrs={"stage": "test"})
    if layers:
        depth = [np.where(f[..., 3:] > 0.5, 2.0 + 0.1 * i, 0.0).astype(np.float32) for i, f in enumerate(frames)]
        write_frames(root, depth, None, layer="depth")
        write_frames(root, [np.dstack([f[..., 3]] * 3) for f in frames], None, layer="normals")
    (root / "notes.txt").write_text("not a frame layer\n")
    return root


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(10 * np.log10(1.0 / np.mean((a - b) ** 2)))


def test_sharpening_adds_detail_without_halos():
    import cv2

    truth = textured(216, seed=3)
    small = cv2.resize(truth, (115, 115), interpolation=cv2.INTER_AREA)
    plain = resample_color(small, 216, sharpen=0.0)
    sharp = resample_color(small, 216)  # default amount
    assert psnr(sharp, truth) > psnr(plain, truth) + 0.3

    # a dark subject edge on a white background: an unsharp mask alone overshoots (halo) ...
    edge = np.ones((40, 40, 3), np.float32)
    edge[:, :20] = 0.2
    up = cv2.resize(edge, (80, 80), interpolation=cv2.INTER_LANCZOS4)
    naive = up + 1.0 * (up - cv2.GaussianBlur(up, (0, 0), 1.0))
    assert naive.min() < 0.15 or naive.max() > 1.0
    # ... the clamped version never leaves the source range, however strong the sharpening
    out = resample_color(edge, 80, sharpen=3.0)
    assert out.min() >= 0.2 - 1e-6 and out.max() <= 1.0 + 1e-6
    assert np.abs(out[:, :36] - 0.2).max() < 1e-5 and np.abs(out[:, 44:] - 1.0).max() < 1e-5


def test_alpha_is_resampled_not_sharpened():
    frame = subject_frame(40)
    out = upscale_embedded(frame, UpscaleOptions(target_size=100, sharpen=3.0))
    assert out.shape == (100, 100, 4) and out.dtype == np.float32
    alpha = out[..., 3]
    assert alpha.min() >= 0.0 and alpha.max() <= 1.0
    unsharpened = upscale_embedded(frame, UpscaleOptions(target_size=100, sharpen=0.0))
    np.testing.assert_array_equal(alpha, unsharpened[..., 3])


def test_upscale_frame_set_scales_cameras_and_layers(tmp_path, caplog):
    import logging

    src = make_frame_set(tmp_path / "in", size=48)
    log = logging.getLogger("test_upscale")
    with caplog.at_level(logging.INFO, logger="test_upscale"):
        info = upscale_frame_set(src, tmp_path / "out", UpscaleOptions(target_size=90), log=log)
    out = tmp_path / "out"
    assert not info["passthrough"] and info["layers"] == ["depth", "normals"] and info["skipped"] == ["notes.txt"]
    # a file left behind (diffuse's proxy.npz, read from diffuse) is said in the log, not warned of in the summary
    assert any("not carried over" in r.message for r in caplog.records)
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]
    frames = read_frames(out)
    assert frames.shape == (3, 90, 90, 4)
    cams, src_cams = read_cameras(out), read_cameras(src)
    assert (cams.width, cams.height) == (90, 90)
    np.testing.assert_allclose(cams.K[:, 0, 0], src_cams.K[:, 0, 0] * 90 / 48)
    np.testing.assert_allclose(cams.K[:, :2, 2], 45.0)
    np.testing.assert_array_equal(cams.c2w, src_cams.c2w)
    depth = read_frames(out, layer="depth")
    assert depth.shape == (3, 90, 90, 1)
    for i in range(3):  # nearest neighbour: no depth value is invented at the silhouette
        assert set(np.unique(depth[i])) <= set(np.unique(read_frames(src, layer="depth")[i]))
    assert read_frames(out, layer="normals").shape == (3, 90, 90, 3)


def test_downscale_uses_area_averaging(tmp_path):
    src = make_frame_set(tmp_path / "in", size=64, layers=False)
    upscale_frame_set(src, tmp_path / "out", UpscaleOptions(target_size=32))
    frames = read_frames(tmp_path / "out")
    assert frames.shape == (3, 32, 32, 4)
    np.testing.assert_allclose(frames[0], read_frames(src)[0].reshape(32, 2, 32, 2, 4).mean(axis=(1, 3)), atol=2e-3)


def test_passthrough_is_a_byte_identical_copy(tmp_path):
    src = make_frame_set(tmp_path / "in", size=48)
    info = upscale_frame_set(src, tmp_path / "out", UpscaleOptions(target_size=48))
    assert info["passthrough"]
    src_files = sorted(p.relative_to(src) for p in src.rglob("*") if p.is_file())
    out_files = sorted(p.relative_to(tmp_path / "out") for p in (tmp_path / "out").rglob("*") if p.is_file())
    assert src_files == out_files and len(src_files) == 3 * 3 + 2
    for rel in src_files:
        assert (src / rel).read_bytes() == (tmp_path / "out" / rel).read_bytes(), rel


def test_bad_inputs_raise_input_error(tmp_path):
    nonsquare = tmp_path / "nonsquare"
    write_frames(nonsquare, [np.zeros((32, 48, 4), np.float32)] * 2, orbit_cameras(2, size=32).scaled(48, 32))
    with pytest.raises(InputError, match="square"):
        upscale_frame_set(nonsquare, tmp_path / "o1", UpscaleOptions(target_size=64))
    mixed = make_frame_set(tmp_path / "mixed", size=32, layers=False)
    write_exr(frame_paths(mixed)[1], subject_frame(40))
    with pytest.raises(InputError, match="same size"):
        upscale_frame_set(mixed, tmp_path / "o2", UpscaleOptions(target_size=64))
    wrong_cams = tmp_path / "wrong_cams"
    write_frames(wrong_cams, [subject_frame(32)] * 2, orbit_cameras(2, size=64))
    with pytest.raises(InputError, match="cameras are for 64x64"):
        upscale_frame_set(wrong_cams, tmp_path / "o3", UpscaleOptions(target_size=64))


def _stage(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "stages.upscale", *args], cwd=REPO, capture_output=True,
                          text=True, timeout=120)


def test_stage_command_line(tmp_path):
    src = make_frame_set(tmp_path / "in", size=32, layers=False)
    proc = _stage("--frames", str(src), "--out-frames", str(tmp_path / "out"), "--target-size", "72")
    assert proc.returncode == 0, proc.stderr
    assert read_frames(tmp_path / "out").shape == (3, 72, 72, 4)
    _, attrs = read_exr(frame_paths(tmp_path / "out")[0], with_attrs=True)
    assert attrs["humanvdm:stage"] == "upscale" and attrs["humanvdm:backend"] == "embedded"

    proc = _stage("--frames", str(src), "--out-frames", str(tmp_path / "same"), "--target-size", "32")
    assert proc.returncode == 0, proc.stderr
    assert [p.read_bytes() for p in frame_paths(tmp_path / "same")] == [p.read_bytes() for p in frame_paths(src)]

    nonsquare = tmp_path / "nonsquare"
    write_frames(nonsquare, [np.zeros((32, 48, 4), np.float32)] * 2, orbit_cameras(2, size=32).scaled(48, 32))
    proc = _stage("--frames", str(nonsquare), "--out-frames", str(tmp_path / "bad"))
    assert proc.returncode == 3
    assert "square" in proc.stderr and "Traceback" not in proc.stderr
    proc = _stage("--frames", str(src), "--out-frames", str(tmp_path / "bad2"), "--sharpen", "-1")
    assert proc.returncode == 3 and "sharpen" in proc.stderr


def test_stage_defaults_match_the_library():
    from humanvdm_core.upscale import core as upscale
    from stages.upscale import SPEC

    defaults = {k: p.default for k, p in SPEC.params.items() if not p.weights}
    assert defaults == {"target_size": upscale.DEFAULT_TARGET_SIZE, "method": "lanczos",
                        "sharpen": upscale.DEFAULT_SHARPEN, "sharpen_sigma": upscale.DEFAULT_SHARPEN_SIGMA,
                        "fidelity": upscale.UpscaleOptions().fidelity, "tile": upscale.UpscaleOptions().tile}
    assert SPEC.backends == tuple(upscale.BACKENDS)

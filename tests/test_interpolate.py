"""Tests of the interpolate stage: flow interpolation quality on synthetic motion with a known
in-between frame, 21 -> 81 frames with orbit cameras, key frames kept, clear input errors."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from humanvdm_core.cameras import orbit_azimuths, orbit_cameras
from humanvdm_core.frames import frame_paths, read_cameras, read_frames, write_frames
from humanvdm_core.interpolate.core import (
    InterpolateOptions,
    interpolate_frame_set,
    interpolate_interval,
    time_flows,
)
from humanvdm_core.io import read_exr
from humanvdm_core.workflow.errors import InputError

REPO = Path(__file__).resolve().parents[1]
BACKGROUND = np.array([0.45, 0.5, 0.55], np.float32)


def _texture(seed: int, n: int = 256) -> np.ndarray:
    """Multi-scale colour noise: textured enough for optical flow, without periodic patterns."""
    import cv2

    rng = np.random.default_rng(seed)
    out = np.zeros((n, n, 3), np.float32)
    for sigma, amp in ((1.0, 0.25), (3.0, 0.35), (8.0, 0.4)):
        noise = cv2.GaussianBlur(rng.standard_normal((n, n, 3)).astype(np.float32), (0, 0), sigma)
        out += amp * noise / noise.std()
    return np.clip(0.5 + 0.18 * out, 0.0, 1.0).astype(np.float32)


def synthetic_frame(t: float, size: int = 128, shift: float = 6.0, turn: float = 8.0) -> np.ndarray:
    """RGBA frame at time t: a textured ellipse moving right and turning, and a textured disc in
    front of it moving left and turning the other way (so there are occlusions), over a flat
    background. Motion is linear in t, so frame(t) is the exact in-between of frame(0), frame(1)."""
    import cv2

    s = size / 128
    ys, xs = np.mgrid[0:size, 0:size].astype(np.float32) + 0.5
    img = np.tile(BACKGROUND, (size, size, 1))
    alpha = np.zeros((size, size), np.float32)
    objects = [((48 + shift * t) * s, 64 * s, 34 * s, 28 * s, np.radians(turn * t), 1),
               ((84 - 1.5 * shift * t) * s, 70 * s, 16 * s, 16 * s, np.radians(-2 * turn * t), 2)]
    for cx, cy, rx, ry, angle, seed in objects:
        dx, dy = xs - cx, ys - cy
        u = np.cos(angle) * dx + np.sin(angle) * dy
        v = -np.sin(angle) * dx + np.cos(angle) * dy
        cover = np.clip((1 - np.sqrt((u / rx) ** 2 + (v / ry) ** 2)) * min(rx, ry) + 0.5, 0, 1)
        tex = cv2.remap(_texture(seed), (u / s + 128).astype(np.float32), (v / s + 128).astype(np.float32),
                        cv2.INTER_LINEAR)
        img = img * (1 - cover[..., None]) + tex * cover[..., None]
        alpha = alpha * (1 - cover) + cover
    return np.concatenate([img, alpha[..., None]], axis=-1).astype(np.float32)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(10 * np.log10(1.0 / np.mean((a - b) ** 2)))


def make_frame_set(root: Path, frames: list[np.ndarray]) -> Path:
    h = frames[0].shape[0]
    write_frames(root, frames, orbit_cameras(len(frames), size=h))
    return root


def test_flow_beats_crossfade_on_known_motion():
    f0, f1 = synthetic_frame(0.0), synthetic_frame(1.0)
    flow = interpolate_interval(f0, f1, InterpolateOptions())
    fade = interpolate_interval(f0, f1, InterpolateOptions(method="crossfade"))
    assert len(flow) == len(fade) == 3
    for k, (a, b) in enumerate(zip(flow, fade, strict=True), start=1):
        truth = synthetic_frame(k / 4)
        assert a.shape == truth.shape and a.dtype == np.float32
        assert psnr(a, truth) > psnr(b, truth) + 3.0, (k, psnr(a, truth), psnr(b, truth))
        assert 0.0 <= a[..., 3].min() and a[..., 3].max() <= 1.0
        # alpha is interpolated too: coverage moves with the objects instead of fading
        assert np.mean(np.abs(a[..., 3] - truth[..., 3])) < np.mean(np.abs(b[..., 3] - truth[..., 3]))


def test_recursive_schedule_and_time_flow_variants_also_beat_crossfade():
    f0, f1 = synthetic_frame(0.0), synthetic_frame(1.0)
    truth = synthetic_frame(0.5)
    fade = psnr(interpolate_interval(f0, f1, InterpolateOptions(method="crossfade", passes=1))[0], truth)
    for opts in (InterpolateOptions(passes=1, schedule="recursive"), InterpolateOptions(passes=1, time_flow="approx")):
        (mid,) = interpolate_interval(f0, f1, opts)
        assert psnr(mid, truth) > fade + 3.0, opts


def test_time_flows_of_a_uniform_translation_are_exact():
    f01 = np.zeros((16, 16, 2), np.float32)
    f01[..., 0] = 4.0
    f10 = -f01
    zero = np.zeros((16, 16), np.float32)
    for mode in ("splat", "approx"):
        ft0, ft1 = time_flows(f01, f10, zero, zero, 0.25, mode)
        inner = (slice(2, 14), slice(4, 12))
        np.testing.assert_allclose(ft0[inner], np.broadcast_to([-1.0, 0.0], ft0[inner].shape), atol=1e-5)
        np.testing.assert_allclose(ft1[inner], np.broadcast_to([3.0, 0.0], ft1[inner].shape), atol=1e-5)


def test_crossfade_is_the_linear_blend():
    a, b = synthetic_frame(0.0, size=32), synthetic_frame(1.0, size=32)
    (mid,) = interpolate_interval(a, b, InterpolateOptions(passes=1, method="crossfade"))
    np.testing.assert_allclose(mid, 0.5 * a + 0.5 * b, atol=1e-6)


def test_21_frames_become_81_with_orbit_cameras(tmp_path):
    frames = [synthetic_frame(i / 20, size=32, shift=40.0) for i in range(21)]
    src = make_frame_set(tmp_path / "in", frames)
    info = interpolate_frame_set(src, tmp_path / "out", InterpolateOptions())
    assert info["frames_out"] == 81
    out = tmp_path / "out"
    assert len(frame_paths(out)) == 81
    cams = read_cameras(out)
    assert len(cams) == 81 and (cams.width, cams.height) == (32, 32)
    key_az = orbit_azimuths(21)
    np.testing.assert_allclose(cams.azimuth_deg[::4], key_az)
    step = 360.0 / 21
    expected = np.concatenate([(key_az[i] + np.arange(4) * step / 4) % 360 for i in range(20)] + [[key_az[20]]])
    np.testing.assert_allclose(cams.azimuth_deg, expected, atol=1e-9)
    # 18.57 -> ... -> 360/0: the last interval crosses azimuth 0 along the shorter arc
    np.testing.assert_allclose(cams.azimuth_deg[76:81], [key_az[19] + k * step / 4 for k in range(4)] + [0.0],
                               atol=1e-9)
    src_cams = read_cameras(src)
    np.testing.assert_allclose(cams.c2w[::4], src_cams.c2w)
    radius = np.linalg.norm(cams.c2w[:, :3, 3], axis=1)
    np.testing.assert_allclose(radius, src_cams.radius[0], rtol=1e-9)  # in-betweens stay on the orbit
    out_frames = read_frames(out)
    np.testing.assert_array_equal(out_frames[::4], read_frames(src))  # key frames unchanged
    _, attrs = read_exr(frame_paths(out)[5], with_attrs=True)
    assert attrs["humanvdm:keyframe"] == 0 and attrs["humanvdm:time"] == pytest.approx(1.25)
    _, attrs = read_exr(frame_paths(out)[8], with_attrs=True)
    assert attrs["humanvdm:keyframe"] == 1


def test_one_pass_recursive_gives_2n_minus_1(tmp_path):
    src = make_frame_set(tmp_path / "in", [synthetic_frame(i / 2, size=32) for i in range(3)])
    info = interpolate_frame_set(src, tmp_path / "out", InterpolateOptions(passes=1, schedule="recursive"))
    assert info["frames_out"] == 5 and len(read_cameras(tmp_path / "out")) == 5


def test_bad_inputs_raise_input_error(tmp_path):
    one = make_frame_set(tmp_path / "one", [synthetic_frame(0.0, size=32)])
    with pytest.raises(InputError, match="at least 2 frames"):
        interpolate_frame_set(one, tmp_path / "o1", InterpolateOptions())
    mixed = tmp_path / "mixed"
    make_frame_set(mixed, [synthetic_frame(0.0, size=32), synthetic_frame(1.0, size=32)])
    from humanvdm_core.io import write_exr
    write_exr(mixed / "frames" / "0001.exr", synthetic_frame(1.0, size=48))
    with pytest.raises(InputError, match="same size"):
        interpolate_frame_set(mixed, tmp_path / "o2", InterpolateOptions())
    rgb = tmp_path / "rgb"
    write_frames(rgb, [synthetic_frame(0.0, size=32)[..., :3]] * 2, orbit_cameras(2, size=32))
    with pytest.raises(InputError, match="RGBA"):
        interpolate_frame_set(rgb, tmp_path / "o3", InterpolateOptions())
    with pytest.raises(InputError, match="cameras.npz"):
        (tmp_path / "nocams" / "frames").mkdir(parents=True)
        write_exr(tmp_path / "nocams" / "frames" / "0000.exr", synthetic_frame(0.0, size=32))
        interpolate_frame_set(tmp_path / "nocams", tmp_path / "o4", InterpolateOptions())


def _stage(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "stages.interpolate", *args], cwd=REPO, capture_output=True,
                          text=True, timeout=120)


def test_stage_command_line(tmp_path):
    src = make_frame_set(tmp_path / "in", [synthetic_frame(i / 2, size=48) for i in range(3)])
    proc = _stage("--frames", str(src), "--out-frames", str(tmp_path / "out"), "--passes", "1")
    assert proc.returncode == 0, proc.stderr
    assert len(frame_paths(tmp_path / "out")) == 5
    one = make_frame_set(tmp_path / "one", [synthetic_frame(0.0, size=48)])
    proc = _stage("--frames", str(one), "--out-frames", str(tmp_path / "bad"))
    assert proc.returncode == 3
    assert "at least 2 frames" in proc.stderr and "Traceback" not in proc.stderr
    proc = _stage("--frames", str(src), "--out-frames", str(tmp_path / "bad2"), "--flow-scale", "2")
    assert proc.returncode == 3 and "flow_scale" in proc.stderr


def test_stage_defaults_match_the_library():
    from humanvdm_core.interpolate import core as interpolate
    from stages.interpolate import SPEC

    lib = interpolate.InterpolateOptions()
    assert {k: p.default for k, p in SPEC.params.items() if not p.weights} == {
        "passes": lib.passes, "method": lib.method, "schedule": lib.schedule, "flow_scale": lib.flow_scale,
        "preset": lib.preset, "time_flow": lib.time_flow}
    assert SPEC.params["preset"].choices == interpolate.DIS_PRESETS
    assert SPEC.params["time_flow"].choices == interpolate.TIME_FLOWS
    assert SPEC.backends == tuple(interpolate.BACKENDS)


@pytest.mark.fixtures
def test_flow_beats_crossfade_on_a_rendered_scan_orbit(fixtures_dir):
    """Real content: the RenderPeople scan rendered on the last two SV3D key intervals and their
    in-between cameras (192², small for speed; the full measurement is benchmarks/bench_interpolate.py)."""
    from humanvdm_core.cameras import upsample_cameras
    from humanvdm_core.render import render_views
    from humanvdm_core.scans import framing_radius, load_scan, normalize_scan

    mesh = normalize_scan(load_scan(fixtures_dir / "scans" / "renderpeople_rp_mei_posed_001"))
    keys = orbit_cameras(21, size=192, radius=framing_radius()).subset([18, 19, 20])
    frames = render_views(mesh, upsample_cameras(keys, 4)).rgba
    for i in range(2):
        flow = interpolate_interval(frames[4 * i], frames[4 * i + 4], InterpolateOptions())
        fade = interpolate_interval(frames[4 * i], frames[4 * i + 4], InterpolateOptions(method="crossfade"))
        for k, (a, b) in enumerate(zip(flow, fade, strict=True), start=1):
            truth = frames[4 * i + k]
            assert psnr(a[..., :3], truth[..., :3]) > psnr(b[..., :3], truth[..., :3]) + 3.0, (i, k)

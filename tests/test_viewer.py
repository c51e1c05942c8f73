"""``humanvdm view``: the viewer served for real and looked at in headless Chromium (skipped without it)."""

from __future__ import annotations

import socket
import subprocess
import sys
import time

import numpy as np
import pytest

from tests import browser

pytestmark = pytest.mark.slow


def synthetic_person(seed: int = 0) -> dict[str, np.ndarray]:
    """Gaussians shaped like a standing person in our world (y up, facing +z, centred at the origin): skin head,
    red torso and arms, blue legs apart."""
    rng = np.random.default_rng(seed)
    parts = [  # (centre, half extents, colour, count)
        ((0.0, 0.72, 0.0), (0.10, 0.11, 0.10), (0.90, 0.75, 0.62), 300),  # head
        ((0.0, 0.30, 0.0), (0.19, 0.28, 0.10), (0.85, 0.12, 0.12), 900),  # torso
        ((-0.25, 0.28, 0.0), (0.05, 0.28, 0.05), (0.85, 0.12, 0.12), 250),  # arms
        ((0.25, 0.28, 0.0), (0.05, 0.28, 0.05), (0.85, 0.12, 0.12), 250),
        ((-0.09, -0.45, 0.0), (0.07, 0.43, 0.07), (0.12, 0.20, 0.85), 500),  # legs
        ((0.09, -0.45, 0.0), (0.07, 0.43, 0.07), (0.12, 0.20, 0.85), 500),
    ]
    means, colors = [], []
    for c, h, col, n in parts:
        means.append(np.asarray(c) + rng.uniform(-1, 1, (n, 3)) * h)
        colors.append(np.tile(col, (n, 1)))
    means = np.concatenate(means).astype(np.float32)
    n = len(means)
    return {"means": means, "quats": np.tile([1.0, 0, 0, 0], (n, 1)).astype(np.float32),
            "scales": np.full((n, 3), 0.025, np.float32), "opacities": np.full(n, 0.95, np.float32),
            "colors": np.concatenate(colors).astype(np.float32)}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _box(mask: np.ndarray) -> tuple[int, int, int, int]:
    ys, xs = np.nonzero(mask)
    return ys.min(), ys.max() + 1, xs.min(), xs.max() + 1


def _normalised(mask: np.ndarray, size=(48, 96)) -> np.ndarray:
    import cv2

    y0, y1, x0, x1 = _box(mask)
    return cv2.resize(mask[y0:y1, x0:x1].astype(np.float32), size, interpolation=cv2.INTER_AREA) > 0.5


def test_viewer_shows_the_person_upright(tmp_path):
    browser.require_webgl()
    pytest.importorskip("viser")
    from humanvdm_core.cameras import orbit_cameras
    from humanvdm_core.evaluate import render_gaussians
    from humanvdm_core.splat import human as H

    g = synthetic_person()
    ply = tmp_path / "point_cloud.ply"
    H.write_ply(ply, g["means"], g["quats"], g["scales"], g["opacities"], g["colors"])  # 3DGS axes: y down
    port = _free_port()
    proc = subprocess.Popen([sys.executable, "-m", "humanvdm_core.cli", "view", str(ply), "--port", str(port)],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        deadline, up = time.time() + 90, False
        while time.time() < deadline and not up and proc.poll() is None:
            try:
                socket.create_connection(("127.0.0.1", port), timeout=1).close()
                up = True
            except OSError:
                time.sleep(0.3)
        assert up, proc.stdout.read() if proc.poll() is not None else "viewer did not start"
        shot = browser.screenshot(f"http://127.0.0.1:{port}", tmp_path / "viewer.png", size=(1200, 800))
    finally:
        proc.terminate()
        out = proc.communicate(timeout=30)[0]
    assert f"http://localhost:{port}" in out

    # the middle of the page (left of the control panel, right of the notifications): the person on white
    mid = shot[:, 330:860].astype(np.int32)
    red = (mid[..., 0] > 150) & (mid[..., 1] < 90) & (mid[..., 2] < 90)
    blue = (mid[..., 2] > 150) & (mid[..., 0] < 90)
    person = np.abs(mid - 255).max(axis=-1) > 40
    assert red.sum() > 2000 and blue.sum() > 2000, (red.sum(), blue.sum())
    ys = np.nonzero(person)[0]
    assert ys.max() - ys.min() > 300  # she fills the view's height, not a speck
    # upright: the red torso above the blue legs, the skin-coloured head on top
    assert np.nonzero(red)[0].mean() < np.nonzero(blue)[0].mean() - 100
    y0, _, _, _ = _box(person)
    assert not red[y0:y0 + 10].any()

    # her silhouette matches our rasterizer's front view of the same Gaussians (each cropped to its box)
    cam = orbit_cameras(1, 256, 33.8, 0.0, 4.0, azimuths_deg=[0.0])
    _, alpha = render_gaussians(g, cam, np.ones(3))
    ours, theirs = _normalised(alpha[0] > 0.5), _normalised(person)
    iou = (ours & theirs).sum() / (ours | theirs).sum()
    assert iou > 0.75, iou


def test_viewer_finds_a_run_and_serves_its_page(tmp_path):
    """Without a browser: a run name resolves to its Gaussians, body and orbit; the server answers."""
    pytest.importorskip("viser")
    import urllib.request

    from humanvdm_core.cameras import orbit_cameras
    from humanvdm_core.frames import write_frames
    from humanvdm_core.viewer import load_scene, serve
    from humanvdm_core.workflow.errors import HumanVDMError
    from tests.test_report import fake_run

    root, run = fake_run(tmp_path)
    body = run / "fit-smpl" / "body"
    body.mkdir(parents=True)
    np.savez(body / "body.npz", vertices=np.random.default_rng(0).normal(size=(4, 3)),
             faces=np.array([[0, 1, 2], [0, 2, 3]]))
    cams = orbit_cameras(3, 16, 33.8, 10.0, 2.5)
    write_frames(run / "diffuse" / "orbit", np.full((3, 16, 16, 4), 0.5, np.float32), cams)
    scene = load_scene("demo", root)
    assert set(scene.sources) == {"gaussians", "body", "orbit"} and len(scene.thumbnails) == 3
    assert scene.sources["gaussians"].endswith("point_cloud.ply")
    with pytest.raises(HumanVDMError, match="runs with Gaussians: demo"):
        load_scene("nobody", root)
    server = serve(scene, port=_free_port(), show=("gaussians", "body", "cameras"))
    try:
        page = urllib.request.urlopen(f"http://127.0.0.1:{server.get_port()}", timeout=30).read()
        assert b"<html" in page.lower()
    finally:
        server.stop()

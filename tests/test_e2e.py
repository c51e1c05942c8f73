"""End to end through the real pipeline.yaml and the `humanvdm` command, on a tiny procedural scan."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys

import numpy as np
import pytest

from humanvdm_core.frames import frame_paths, read_cameras
from humanvdm_core.workflow.scheduler import read_lockfile
from humanvdm_core.workflow.store import Store
from testdata.procedural import write_person

pytestmark = pytest.mark.slow

TINY = ["--set", "render-training-orbits.resolution=96", "--set", "upscale.target_size=128"]


def humanvdm(store, *args):
    return subprocess.run([sys.executable, "-m", "humanvdm_core.cli", *args[:1], "--store", str(store), *args[1:]],
                          capture_output=True, text=True, timeout=900)  # a guard against hangs, not a speed test


def test_scan_runs_render_upscale_interpolate_then_only_what_changed(tmp_path):
    scan = write_person(tmp_path / "person", name="person", segments=12).parent
    store = tmp_path / "artifacts"
    first = humanvdm(store, "run", str(scan), "--until", "interpolate", *TINY)
    assert first.returncode == 0, first.stdout + first.stderr
    assert "3 stage run(s) ran, 0 cached" in first.stdout
    view = store / "runs" / "person"
    assert len(frame_paths(view / "render-training-orbits" / "orbit")) == 21
    out = view / "interpolate" / "frames"
    assert len(frame_paths(out)) == 81 and read_cameras(out).width == 128

    again = humanvdm(store, "run", str(scan), "--until", "interpolate", *TINY)
    assert "0 stage run(s) ran, 3 cached" in again.stdout

    changed = humanvdm(store, "run", str(scan), "--until", "interpolate", *TINY, "--set", "interpolate.passes=1")
    assert changed.returncode == 0
    lock = read_lockfile(Store(store), "person")
    assert [s for s, e in lock["stages"].items() if e["status"] == "ran"] == ["interpolate"]
    assert len(frame_paths(out)) == 41


FULL = ["--set", "render-training-orbits.resolution=256", "--set", "upscale.target_size=256",
        "--set", "interpolate.passes=1", "--set", "fit-smpl.iterations=60", "--set", "fit-smpl.fit_frames=6",
        "--set", "fit-smpl.uv_resolution=64", "--set", "splat-optimize.preset=tiny",
        "--set", "splat-optimize.turntable_views=4", "--set", "splat-optimize.turntable_size=96",
        "--set", "evaluate.resolution=96", "--set", "evaluate.heldout_azimuths=45,225",
        "--set", "evaluate.heldout_elevations=0"]


def test_whole_pipeline_on_a_synthetic_subject(tmp_path):
    """Scan in, every implemented stage through the scheduler, Gaussians and a report out."""
    import json

    from humanvdm_core.splat.human import read_ply
    from testdata.synthetic import SubjectSpec, make_subject

    scan = tmp_path / "subject"
    make_subject(SubjectSpec(pose="a-pose", seed=3), scan, texture_size=512)
    store = tmp_path / "artifacts"
    res = humanvdm(store, "run", str(scan), *FULL)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "6 stage run(s) ran" in res.stdout
    view = store / "runs" / "subject"
    lock = read_lockfile(Store(store), "subject")
    # 256^2 frames already meet upscale's target: passed through as the same artifact
    assert lock["stages"]["upscale"]["outputs"]["frames"] == lock["stages"]["render-training-orbits"]["outputs"]["orbit"]
    gaussians = view / "splat-optimize" / "gaussians"
    ply = read_ply(gaussians / "point_cloud.ply")
    assert len(ply["means"]) > 1000
    metrics = json.loads((view / "evaluate" / "report" / "metrics.json").read_text())
    text = json.dumps(metrics)
    assert "psnr" in text and "unavailable" in text  # LPIPS/CLIP weights are not installed in tests
    assert (view / "evaluate" / "report" / "report.html").is_file()
    assert metrics["basis"]["heldout"].startswith("accuracy")
    assert "A scan run" in (view / "report.html").read_text()
    again = humanvdm(store, "run", str(scan), *FULL)
    assert "0 stage run(s) ran, 6 cached" in again.stdout


def test_photo_in_gaussians_out(tmp_path):
    """The README's example photo through every stage (tiny settings), then an identical rerun."""
    import json

    from humanvdm_core.cli import REPO_ROOT

    photo = REPO_ROOT / "examples" / "ryota.png"
    store = tmp_path / "artifacts"
    args = [*FULL, "--set", "diffuse.resolution=256", "--set", "diffuse.fit_iterations=60"]
    res = humanvdm(store, "run", str(photo), *args)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "6 stage run(s) ran" in res.stdout
    view = store / "runs" / "ryota"
    assert len(frame_paths(view / "diffuse" / "orbit")) == 21
    assert (view / "splat-optimize" / "gaussians" / "point_cloud.ply").stat().st_size > 10_000
    metrics = json.loads((view / "evaluate" / "report" / "metrics.json").read_text())
    # a 41-frame orbit (one interpolation pass) holds the front and back views of the paper's four
    assert metrics["mean"]["protocol"]["views"] == 2 and metrics["mean"]["protocol"]["iou"] > 0.5
    report = view / "evaluate" / "report"
    assert metrics["media"] == {"orbit": "orbit.gif", "turntable": "turntable.gif", "fit_overlay": "fit_overlay.png"}
    assert all((report / name).stat().st_size > 1000 for name in metrics["media"].values())
    for rel in ("splat-optimize/gaussians/point_cloud.ply", "evaluate/report/report.html", "evaluate/report/orbit.gif"):
        assert f"  {rel}" in res.stdout  # the summary points at what a person opens
    assert "  report.html   <- open this first" in res.stdout and "humanvdm view ryota --store" in res.stdout
    assert "ryota/splat-optimize: ran in" in res.stderr and "ryota/diffuse: started (log:" in res.stderr
    html = (view / "report.html").read_text()
    assert "Fit to the generated video — not accuracy" in html and "body-prior" in html
    assert metrics["basis"] == {"protocol": "fit to the generated video — not accuracy"}
    # the PLY is in the 3DGS axes (y down, z forward): our y-up world turned 180 degrees about x
    from humanvdm_core.io import read_npz
    from humanvdm_core.splat.human import read_ply

    npz = read_npz(view / "splat-optimize" / "gaussians" / "gaussians.npz")
    ply = read_ply(view / "splat-optimize" / "gaussians" / "point_cloud.ply", world=False)
    np.testing.assert_allclose(ply["means"], npz["means"] * [1, -1, -1], atol=1e-6)
    if shutil.which("chromium"):  # every picture of the report loads in a browser
        from tests import browser

        imgs = re.findall(r"<img [^>]*>", browser.dump_dom((view / "report.html").as_uri(), 3000))
        assert len(imgs) >= 5 and all('data-loaded="1"' in i for i in imgs), imgs
    again = humanvdm(store, "run", str(photo), *args)
    assert "0 stage run(s) ran, 6 cached" in again.stdout

"""The run's report.html: what it leads with, what it says the metrics measure, provenance from the lockfile,
and (in headless Chromium, skipped without it) that every picture loads."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from PIL import Image

from humanvdm_core.io import write_png
from humanvdm_core.report import write_run_report
from humanvdm_core.splat import human as H
from humanvdm_core.workflow.scheduler import write_lockfile
from humanvdm_core.workflow.store import Store
from tests import browser

VERSIONS = {"python": "3.11.7", "numpy": "2.4.6", "torch": "2.13.0+cpu"}


def _gif(path, size=32, frames=3):
    ims = [Image.new("RGB", (size, size), (40 * i, 90, 160)) for i in range(frames)]
    ims[0].save(path, save_all=True, append_images=ims[1:], duration=80, loop=0)


def fake_run(tmp_path, scan: bool = False):
    """A run folder as `humanvdm run` leaves it (small files), and its lockfile."""
    root = tmp_path / "artifacts"
    store = Store(root)
    run = root / "runs" / "demo"
    photo = tmp_path / "demo.png"
    Image.new("RGB", (300, 400), (200, 120, 90)).save(photo)
    g = run / "splat-optimize" / "gaussians"
    g.mkdir(parents=True)
    rng = np.random.default_rng(0)
    n = 50
    args = (rng.normal(size=(n, 3)), np.tile([1.0, 0, 0, 0], (n, 1)), np.full((n, 3), 0.01), np.ones(n),
            rng.uniform(size=(n, 3)))
    H.write_ply(g / "point_cloud.ply", *args)
    H.write_splat(g / "point_cloud.splat", *args)
    _gif(g / "turntable.gif")
    (g / "train_log.json").write_text(json.dumps({"settings": {"preset": "cpu", "uv_resolution": 128,
                                                               "train_resolution": 192, "iterations": 500},
                                                  "num_gaussians": 10253, "device": "cpu", "train_psnr": 24.1}))
    rep = run / "evaluate" / "report"
    rep.mkdir(parents=True)
    _gif(rep / "orbit.gif")
    _gif(rep / "turntable.gif")
    write_png(rep / "grid.png", np.full((64, 96, 3), 0.5, np.float32))
    write_png(rep / "fit_overlay.png", np.full((32, 64, 3), 0.3, np.float32))
    views = {"protocol": [{"name": "front", "metrics": {"psnr": 26.3, "ssim": 0.91, "iou": 0.95,
                                                        "lpips": "unavailable: put alex.pth at x"}}]}
    basis = {"protocol": "fit to the generated video — not accuracy"}
    if scan:
        views["heldout"] = [{"name": "az45_el0", "metrics": {"psnr": 17.0, "ssim": 0.8, "iou": 0.9}}]
        basis = {"protocol": "fit to the training views (rendered from the scan) — not held out",
                 "heldout": "accuracy: against the scan, at views the Gaussians were not fitted to",
                 "geometry": "accuracy: against the scan's surface"}
    (rep / "metrics.json").write_text(json.dumps({
        "views": views, "mean": {k: {"psnr": v[0]["metrics"]["psnr"]} for k, v in views.items()},
        "basis": basis, "geometry": {"chamfer": 0.01} if scan else "unavailable: no scan input",
        "perceptual": {"lpips": "unavailable: put alex.pth at x", "clip": "ok"}, "definitions": {"psnr": "dB"}}))
    first = "render-training-orbits" if scan else "diffuse"
    stages = {}
    for i, name in enumerate([first, "upscale", "interpolate", "fit-smpl", "splat-optimize", "evaluate"]):
        stages[name] = {"params": {"seed": 0} if name != "splat-optimize" else {"preset": "auto", "ply_axes": "y-down"},
                        "backend": "body-prior" if name == "diffuse" else "embedded", "wall_s": 10.0 + i,
                        "peak_rss_mb": 1000.0 + 100 * i, "warnings": [], "versions": VERSIONS,
                        "status": "cached" if name == "upscale" else "ran"}
    kind = "scan" if scan else "photo"
    write_lockfile(store, "demo", {"schema": 1, "input": {kind: {"path": str(photo), "id": None}}, "stages": stages})
    return root, run


def test_report_leads_with_the_input_and_labels_what_metrics_mean(tmp_path):
    root, run = fake_run(tmp_path)
    path = write_run_report(root, "demo")
    assert path == run / "report.html"
    text = path.read_text()
    imgs = re.findall(r"<img src='([^']+)'", text)
    assert imgs[:3] == ["report_files/input.png", "evaluate/report/turntable.gif", "evaluate/report/orbit.gif"]
    assert (run / "report_files" / "input.png").is_file()
    assert "Fit to the generated video — not accuracy" in text and "body-prior" in text and "made, not known" in text
    assert "humanvdm view demo" in text
    assert "href='splat-optimize/gaussians/point_cloud.ply'" in text and "point_cloud.splat" in text
    assert "y down" in text and "metres" in text
    assert "preset <b>cpu</b>" in text and "10,253" in text
    assert "14.0 s" in text and "1400 MB" in text and "11.0 s (when computed)" in text  # times, memory, cache
    assert "torch 2.13.0+cpu" in text and "humanvdm.lock" in text
    assert "the generated frame it was fitted to (not ground truth)" in text


def test_scan_report_says_which_numbers_are_accuracy(tmp_path):
    root, run = fake_run(tmp_path, scan=True)
    text = write_run_report(root, "demo", store_flag="/data/store").read_text()
    assert "not accuracy" not in text and "A scan run" in text
    assert "accuracy: against the scan, at views the Gaussians were not fitted to" in text
    assert "rendered from your scan" in text and "humanvdm view demo --store /data/store" in text


def test_report_pictures_load_in_chromium(tmp_path):
    browser.chromium()
    root, run = fake_run(tmp_path)
    path = write_run_report(root, "demo")
    dom = browser.dump_dom(path.as_uri(), budget_ms=3000)
    imgs = re.findall(r"<img [^>]*>", dom)
    assert len(imgs) >= 5, dom[:2000]
    assert all("data-loaded=\"1\"" in i for i in imgs), [i for i in imgs if "data-loaded" not in i]
    assert not any("data-broken" in i for i in imgs)


@pytest.mark.parametrize("missing", ["evaluate", "splat-optimize"])
def test_report_of_a_partial_run(tmp_path, missing):
    import shutil

    root, run = fake_run(tmp_path)
    shutil.rmtree(run / missing)
    text = write_run_report(root, "demo").read_text()
    assert "report_files/input.png" in text
    assert ("No metrics yet" in text) if missing == "evaluate" else ("No Gaussians yet" in text)

"""Tests of the evaluate stage on tiny hand-made artifacts: a Gaussian human sampled from the
procedural person's surface, a frame set rendered from it, and the scan itself (oracle path)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from humanvdm_core.cameras import orbit_cameras
from humanvdm_core.frames import write_frames
from humanvdm_core.io import read_npz, write_npz
from humanvdm_core.metrics import triangle_areas
from humanvdm_core.perceptual import ALEXNET_CONVS, LPIPS_CHANNELS, CLIPImageEncoder
from humanvdm_core.scans import framing_radius, load_scan, normalization_transform
from testdata.procedural import write_person

REPO = Path(__file__).resolve().parents[1]
FRAME_SIZE = 96
RES = 64


def surface_gaussians(mesh, count: int, seed: int = 0) -> dict[str, np.ndarray]:
    """Small round Gaussians on the mesh surface, coloured from its texture (the ``humanvdm.gaussians`` v1 members)."""
    rng = np.random.default_rng(seed)
    v, f = mesh.vertices.astype(np.float64), mesh.faces
    areas = triangle_areas(v, f)
    fi = rng.choice(len(f), count, p=areas / areas.sum())
    s, r2 = np.sqrt(rng.random(count)), rng.random(count)
    w = np.stack([1.0 - s, s * (1.0 - r2), s * r2], axis=1)
    means = (v[f[fi]] * w[..., None]).sum(axis=1)
    uv = (mesh.uvs[f[fi]] * w[..., None]).sum(axis=1)
    th, tw = mesh.texture.shape[:2]
    rows = np.clip(((1.0 - uv[:, 1]) * th).astype(int), 0, th - 1)
    cols = np.clip((uv[:, 0] * tw).astype(int), 0, tw - 1)
    spacing = np.sqrt(areas.sum() / count)
    return {
        "means": means.astype(np.float32),
        "quats": np.tile(np.array([1.0, 0.0, 0.0, 0.0], np.float32), (count, 1)),
        "scales": np.full((count, 3), 0.5 * spacing, np.float32),
        "opacities": np.full(count, 0.95, np.float32),
        "colors": (mesh.texture[rows, cols] / 255.0).astype(np.float32),
    }


@pytest.fixture(scope="module")
def subject(tmp_path_factory) -> dict[str, Path]:
    """scan/, frames/ (azimuths 0, 90, 180, 270 at elevation 10, from the scan), gaussians/, a
    frame set without the 270 view and without scan extras (photo-like), and tiny weight files."""
    from humanvdm_core.render import render_views

    root = tmp_path_factory.mktemp("evaluate")
    write_person(root / "scan", segments=16)
    scan = load_scan(root / "scan")
    wfs = normalization_transform(scan, 1.7)
    mesh = scan.transformed(wfs)
    background = (0.2, 0.3, 0.4)
    cams = orbit_cameras(size=FRAME_SIZE, elevation_deg=10.0, radius=framing_radius(1.7),
                         azimuths_deg=[0.0, 90.0, 180.0, 270.0])
    cams.extra.update({"background": np.array(background), "world_from_scan": wfs,
                       "subject_height": np.float64(1.7), "fill": np.float64(0.85)})
    rgba = render_views(mesh, cams, background).rgba
    write_frames(root / "frames", rgba, cams)
    photo_cams = cams.subset([0, 1, 2])
    photo_cams.extra = {"background": np.array(background)}
    write_frames(root / "frames_photo", rgba[:3], photo_cams)
    (root / "gaussians").mkdir()
    write_npz(root / "gaussians" / "gaussians.npz", surface_gaussians(mesh, 8000), "humanvdm.gaussians", 1)

    g = torch.Generator().manual_seed(0)
    feats = {}
    for idx, cin, cout, k, _, _ in ALEXNET_CONVS:
        feats[f"features.{idx}.weight"] = torch.randn(cout, cin, k, k, generator=g) * (2.0 / (cin * k * k)) ** 0.5
        feats[f"features.{idx}.bias"] = torch.zeros(cout)
    feats["classifier.1.weight"] = torch.zeros(2, 2)  # the real file has a classifier: ignored
    torch.save(feats, root / "alexnet.pth")
    torch.save({f"lin{n}.model.1.weight": torch.rand(1, c, 1, 1, generator=g) for n, c in enumerate(LPIPS_CHANNELS)},
               root / "alex.pth")
    clip = {k: 0.05 * torch.randn(*shape, generator=g)
            for k, shape in CLIPImageEncoder.official_keys(32, 2, 8, 4, 16).items()}
    torch.save(clip, root / "clip.pt")
    torch.save({"visual.conv1.weight": torch.zeros(32, 3, 8, 8)}, root / "clip_bad.pt")
    return {"root": root}


def run_stage(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "stages.evaluate", *args], cwd=REPO, capture_output=True,
                          text=True, timeout=120)


def test_evaluate_scan_run(subject):
    from PIL import Image

    from humanvdm_core.frames import frame_paths
    from humanvdm_core.io import write_png

    root = subject["root"]
    out = root / "report_scan"
    body = root / "body_stub"
    write_png(body / "overlay.png", np.full((8, 8, 3), 0.5, np.float32))
    proc = run_stage("--gaussians", str(root / "gaussians"), "--frames", str(root / "frames"),
                     "--scan", str(root / "scan"), "--body", str(body), "--out-report", str(out),
                     "--resolution", str(RES), "--media-size", "48",
                     "--heldout-elevations", "0,10", "--heldout-azimuths", "45,90",
                     "--geometry-samples", "20000", "--cell-size", "64",
                     "--alexnet-weights", str(root / "alexnet.pth"), "--lpips-weights", str(root / "alex.pth"),
                     "--clip-weights", str(root / "clip.pt"))
    assert proc.returncode == 0, proc.stderr
    report = json.loads((out / "metrics.json").read_text())
    assert [v["name"] for v in report["views"]["protocol"]] == ["front", "back", "left", "right"]
    assert [v["frame_index"] for v in report["views"]["protocol"]] == [0, 2, 1, 3]
    # (90, 10) is a training view: skipped; the other three are held out
    assert [v["name"] for v in report["views"]["heldout"]] == ["az45_el0", "az90_el0", "az45_el10"]
    assert report["skipped_heldout_views"][0]["azimuth_deg"] == 90.0
    for group in ("protocol", "heldout"):
        mean = report["mean"][group]
        # 64 px: the rasterizer's 0.3 px² screen-space dilation fattens the thin limbs (IoU 0.6; 0.87 at 256 px)
        assert mean["psnr"] > 20.0 and mean["ssim"] > 0.7 and mean["iou"] > 0.5, (group, mean)
        assert mean["masked_psnr"] < mean["psnr"]  # the background is easy
        assert isinstance(mean["lpips"], float) and mean["lpips"] >= 0.0
        assert isinstance(mean["clip"], float) and -1.0 <= mean["clip"] <= 1.0
    assert report["perceptual"] == {"lpips": "ok", "clip": "ok"}
    geo = report["geometry"]
    assert geo["p2s"] < 0.002 and geo["s2p"] < 0.03 and geo["chamfer_rel"] < 0.01, geo
    grid = (out / "grid.png")
    import cv2

    img = cv2.imread(str(grid))
    assert img.shape == (7 * 64, 3 * 64, 3)
    html = (out / "report.html").read_text()
    assert "grid.png" in html and "az45_el0" in html
    # the pictures for people: the orbit video, the fit overlay (no turntable in this Gaussians artifact)
    with Image.open(out / "orbit.gif") as gif:
        assert gif.size == (48, 48) and gif.n_frames == len(frame_paths(root / "frames"))
    assert (out / "fit_overlay.png").read_bytes() == (body / "overlay.png").read_bytes()
    assert report["media"] == {"orbit": "orbit.gif", "fit_overlay": "fit_overlay.png"}
    assert "src='orbit.gif'" in html and "src='fit_overlay.png'" in html and "turntable" not in html


def test_evaluate_photo_run_without_weights(subject):
    root = subject["root"]
    out = root / "report_photo"
    proc = run_stage("--gaussians", str(root / "gaussians" / "gaussians.npz"), "--frames", str(root / "frames_photo"),
                     "--out-report", str(out), "--resolution", str(RES), "--cell-size", "64",
                     "--alexnet-weights", str(root / "nope" / "alexnet-owt-7be5be79.pth"),
                     "--lpips-weights", str(root / "alex.pth"), "--clip-weights", str(root / "nope" / "ViT-B-32.pt"))
    assert proc.returncode == 0, proc.stderr
    report = json.loads((out / "metrics.json").read_text())
    views = report["views"]["protocol"]
    assert "metrics" not in views[3] and views[3]["frame_index"] is None  # no frame at azimuth 270
    assert report["mean"]["protocol"]["views"] == 3
    assert "heldout" not in report["views"]
    want = f"unavailable: put alexnet-owt-7be5be79.pth at {root / 'nope' / 'alexnet-owt-7be5be79.pth'}"
    assert report["perceptual"]["lpips"] == want
    assert views[0]["metrics"]["lpips"] == want
    assert report["mean"]["protocol"]["clip"].startswith("unavailable: put ViT-B-32.pt at ")
    assert report["geometry"].startswith("unavailable")
    html = (out / "report.html").read_text()
    assert "LPIPS: unavailable: put alexnet-owt-7be5be79.pth at" in html and "<td>n/a</td>" in html


def test_evaluate_bad_inputs(subject, tmp_path, capsys):
    """User errors exit 3 with a clear message (in-process through the real command line, for speed)."""
    from stages.evaluate import SPEC, run

    root = subject["root"]

    def stage(*args: str) -> tuple[int, str]:
        code = SPEC.main(run, list(args))
        return code, capsys.readouterr().err

    (tmp_path / "empty").mkdir()
    code, err = stage("--gaussians", str(tmp_path / "empty"), "--frames", str(root / "frames"),
                      "--out-report", str(tmp_path / "r1"))
    assert code == 3 and "no gaussians.npz" in err, err
    # a scan run needs frames rendered from the scan (world_from_scan)
    code, err = stage("--gaussians", str(root / "gaussians"), "--frames", str(root / "frames_photo"),
                      "--scan", str(root / "scan"), "--out-report", str(tmp_path / "r2"), "--resolution", "32")
    assert code == 3 and "world_from_scan" in err, err
    # a CLIP file with the wrong keys: a clear error naming them
    code, err = stage("--gaussians", str(root / "gaussians"), "--frames", str(root / "frames_photo"),
                      "--out-report", str(tmp_path / "r3"), "--resolution", "32",
                      "--clip-weights", str(root / "clip_bad.pt"), "--alexnet-weights", str(tmp_path / "none.pth"))
    assert code == 3 and "missing keys: visual.class_embedding" in err, err
    # gaussians with inconsistent shapes
    g = read_npz(root / "gaussians" / "gaussians.npz")
    g["scales"] = g["scales"][:, :2]
    (tmp_path / "bad").mkdir()
    write_npz(tmp_path / "bad" / "gaussians.npz", g, "humanvdm.gaussians", 1)
    code, err = stage("--gaussians", str(tmp_path / "bad"), "--frames", str(root / "frames"),
                      "--out-report", str(tmp_path / "r4"))
    assert code == 3 and "scales has shape" in err, err
    # a bad param
    code, err = stage("--gaussians", str(root / "gaussians"), "--frames", str(root / "frames"),
                      "--out-report", str(tmp_path / "r5"), "--heldout-azimuths", "front")
    assert code == 3 and "heldout_azimuths" in err, err

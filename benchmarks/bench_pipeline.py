"""The whole pipeline from one photo, scored against the truth (issue 5's end-to-end benchmark).

Per synthetic Anny subject (``testdata.synthetic``, known geometry and texture):

1. the subject is rendered at azimuth 0, elevation 10 deg (the orbit's input view) at
   ``--photo-size``; that RGBA render is the *photo* (the only thing the pipeline sees);
2. ``humanvdm run photo.png`` runs every stage through the scheduler in a scratch store, with the
   defaults (``diffuse`` = body-prior, ``splat-optimize`` = ``--preset``); per-stage wall time and
   peak memory come from the run's lockfile;
3. the paper's protocol views -- front, back, left, right (azimuth 0/90/180/270, the orbit's
   elevation) -- are rendered three ways: the truth (the subject mesh), **ours** (the final
   Gaussians) and the **proxy** (the body-prior stand-in of ``diffuse`` rendered directly, i.e.
   what the learned video model would have to beat, without upscale/interpolate/splats);
4. every image is re-framed the same way before scoring (its silhouette's box centred and scaled
   to ``FILL`` of the frame height, ``--eval-size``²), so the scores compare appearance and shape,
   not the arbitrary world scale of a single-photo reconstruction; PSNR and SSIM over the whole
   frame (white background), masked PSNR over the union of the silhouettes, silhouette IoU.

Run:  .venv/bin/python -m benchmarks.bench_pipeline [--subjects 3] [--preset cpu]
Writes benchmarks/results/pipeline.json and pipeline_<subject>.png (truth | ours | proxy per view).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import cv2  # noqa: E402
import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.common import RESULTS, save_result  # noqa: E402

VIEWS = {"front": 0.0, "left": 90.0, "back": 180.0, "right": 270.0}
ELEVATION = 10.0
FILL = 0.85
WHITE = (1.0, 1.0, 1.0)


def reframe(rgb: np.ndarray, alpha: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """``rgb`` over white and ``alpha`` with the silhouette's box centred, its height FILL of ``size``."""
    ys, xs = np.nonzero(alpha > 0.5)
    if len(ys) == 0:
        return np.ones((size, size, 3), np.float32), np.zeros((size, size), np.float32)
    x0, x1, y0, y1 = xs.min(), xs.max() + 1, ys.min(), ys.max() + 1
    s = min(FILL * size / (y1 - y0), 0.95 * size / (x1 - x0))
    m = np.array([[s, 0.0, size / 2 - s * (x0 + x1) / 2], [0.0, s, size / 2 - s * (y0 + y1) / 2]])
    out_rgb = cv2.warpAffine(np.ascontiguousarray(rgb, np.float32), m, (size, size), flags=cv2.INTER_AREA,
                             borderMode=cv2.BORDER_CONSTANT, borderValue=WHITE)
    out_a = cv2.warpAffine(np.ascontiguousarray(alpha, np.float32), m, (size, size), flags=cv2.INTER_AREA,
                           borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
    return np.clip(out_rgb, 0, 1), np.clip(out_a, 0, 1)


def resized(rgb: np.ndarray, alpha: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """``rgb`` and ``alpha`` as rendered, only resized to ``size``² (the alternative to :func:`reframe`)."""
    out_rgb = cv2.resize(np.ascontiguousarray(rgb, np.float32), (size, size), interpolation=cv2.INTER_AREA)
    out_a = cv2.resize(np.ascontiguousarray(alpha, np.float32), (size, size), interpolation=cv2.INTER_AREA)
    return np.clip(out_rgb, 0, 1), np.clip(out_a, 0, 1)


def scores(pred: tuple[np.ndarray, np.ndarray], gt: tuple[np.ndarray, np.ndarray]) -> dict:
    from humanvdm_core import metrics as M

    union = M.union_mask(pred[1], gt[1])
    return {"psnr": float(M.psnr(pred[0], gt[0])), "ssim": float(M.ssim(pred[0], gt[0])),
            "masked_psnr": float(M.psnr(pred[0], gt[0], union)), "iou": float(M.silhouette_iou(pred[1], gt[1]))}


def view_cameras(reference, size: int):
    """Cameras at the VIEWS azimuths with ``reference``'s elevation, radius and field of view."""
    from humanvdm_core.cameras import orbit_cameras

    fov = float(np.degrees(2 * np.arctan(0.5 * reference.height / reference.K[0, 1, 1])))
    return orbit_cameras(len(VIEWS), size, fov, float(reference.elevation_deg[0]), float(reference.radius[0]),
                         azimuths_deg=np.array(list(VIEWS.values())))


def run_subject(index: int, spec, work: Path, args) -> dict:
    from humanvdm_core.body_prior import build_body_proxy
    from humanvdm_core.cameras import orbit_cameras
    from humanvdm_core.evaluate import load_gaussians, render_gaussians
    from humanvdm_core.frames import read_cameras
    from humanvdm_core.io import write_png
    from humanvdm_core.render import render_views
    from humanvdm_core.scans import framing_radius, load_scan, normalize_scan
    from humanvdm_core.workflow.scheduler import read_lockfile
    from humanvdm_core.workflow.store import Store
    from testdata.synthetic import make_subject

    name = f"subject{index}"
    mesh = normalize_scan(load_scan(make_subject(spec, work / name)))
    radius = framing_radius()
    photo_cam = orbit_cameras(1, args.photo_size, elevation_deg=ELEVATION, radius=radius,
                              azimuths_deg=np.array([0.0]))
    photo = work / f"{name}.png"
    write_png(photo, render_views(mesh, photo_cam, WHITE).rgba[0])

    store = work / "store"
    cmd = [str(REPO / ".venv" / "bin" / "humanvdm"), "run", str(photo), "--store", str(store), "--no-progress",
           "--set", f"splat-optimize.preset={args.preset}"]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode:
        return {"subject": name, "error": (proc.stdout + proc.stderr)[-2000:]}
    run_dir = store / "runs" / name
    lock = read_lockfile(Store(store), name)
    stages = {k: {"wall_s": v.get("wall_s"), "peak_rss_mb": v.get("peak_rss_mb")}
              for k, v in lock.get("stages", {}).items()}

    orbit = read_cameras(run_dir / "diffuse" / "orbit")
    ours_cams = view_cameras(orbit, args.eval_size)
    gt = render_views(mesh, orbit_cameras(len(VIEWS), args.eval_size, elevation_deg=ELEVATION, radius=radius,
                                          azimuths_deg=np.array(list(VIEWS.values()))), WHITE).rgba
    ours_rgb, ours_a = render_gaussians(load_gaussians(run_dir / "splat-optimize" / "gaussians"), ours_cams, WHITE)
    proxy = build_body_proxy(photo, size=orbit.width, elevation_deg=ELEVATION, background=WHITE)
    proxy_rgba = proxy.render(ours_cams)

    per_view, rows = {}, []
    for i, view in enumerate(VIEWS):
        g = reframe(gt[i, ..., :3], gt[i, ..., 3], args.eval_size)
        o = reframe(ours_rgb[i], ours_a[i], args.eval_size)
        p = reframe(proxy_rgba[i, ..., :3], proxy_rgba[i, ..., 3], args.eval_size)
        per_view[view] = {"ours": scores(o, g), "proxy": scores(p, g)}
        rows.append(np.concatenate([g[0], o[0], p[0]], axis=1))
    write_png(RESULTS / f"pipeline_{name}.png", cv2.resize(np.concatenate(rows, axis=0), None, fx=0.5, fy=0.5,
                                                           interpolation=cv2.INTER_AREA))
    mean = {who: {k: float(np.mean([per_view[v][who][k] for v in VIEWS])) for k in per_view["front"][who]}
            for who in ("ours", "proxy")}
    return {"subject": name, "spec": spec.to_dict(), "pipeline_wall_s": wall, "stages": stages,
            "views": per_view, "mean": mean}


def save_summary(results: list[dict], args) -> tuple[dict, Path]:
    """Mean scores over the subjects that ran; writes results/pipeline.json."""
    ok = [r for r in results if "mean" in r]
    summary = {who: {k: float(np.mean([r["mean"][who][k] for r in ok])) for k in ok[0]["mean"][who]}
               for who in ("ours", "proxy")} if ok else {}
    out = save_result("pipeline", {"preset": args.preset, "subjects": results, "summary": summary,
                                   "failed": [r["subject"] for r in results if "error" in r]},
                      "python -m benchmarks.bench_pipeline " + " ".join(sys.argv[1:]))
    return summary, out


def main() -> None:
    import torch

    from testdata.synthetic import random_specs

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--subjects", type=int, default=3)
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--photo-size", type=int, default=1024)
    parser.add_argument("--eval-size", type=int, default=512)
    parser.add_argument("--work", type=Path, default=None, help="scratch folder (default: a temporary one)")
    args = parser.parse_args()
    torch.set_num_threads(1)

    RESULTS.mkdir(parents=True, exist_ok=True)
    results: list[dict] = []
    with tempfile.TemporaryDirectory(prefix="bench_pipeline_") as tmp:
        work = args.work or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        for i, spec in enumerate(random_specs(args.subjects, args.seed)):
            r = run_subject(i, spec, work, args)
            results.append(r)
            print(json.dumps({k: r[k] for k in ("subject", "pipeline_wall_s", "mean", "error") if k in r}),
                  flush=True)
            summary, out = save_summary(results, args)  # after every subject: a long run keeps what it has
    print(json.dumps(summary, indent=1))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()

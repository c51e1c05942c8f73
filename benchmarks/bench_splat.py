"""Benchmark of the Gaussian human (``humanvdm_core.splat``, stage ``splat-optimize``): oracle fits.

Subjects: ``synthetic`` (an Anny subject in a striped shirt, its clothes painted on: the body template's
best case), ``gown`` (``synthetic.GARMENT_EXAMPLES['gown']``: an ankle-length gown and long hair, which
are not the body) -- both with their true body params as the body fit -- and, when present, the
RenderPeople fixture scan Mei (``../shared/fixtures/scans/renderpeople_rp_mei_posed_001``; its body from
the ``fit-smpl`` stage run on its 21-frame 576² orbit). Each is rendered like ``render-training-orbits``
(normalised to 1.7 units, fill 0.85, elevation 10°, fixed background) along 81 cameras
``upsample_cameras(orbit_cameras(21), 4)`` at ``--render-size``² (the training views; area-resampled to
the training resolution), plus 8 held-out views that are never trained on: elevations 0° and 25° at
azimuths 45/135/225/315, rendered at ``--eval-size``².

Runs, all with the ``cpu`` preset's settings (as the stage runs them: template, closed-form colours,
coarse-to-fine, densify): ``template=body`` and ``template=subject`` (here the visual hull of the
frames merged with the body: an oracle orbit has no clothed proxy), and for ``gown`` and ``renderpeople``
the subject template started from points 32 / 22 / 11 mm apart (16 mm is the preset's; the count sweep), and
``subject, even spacing`` (``detail_spacing`` 1: no finer points where the input view shows detail). As in the
stage, the training view at azimuth 0 stands in for the input photo (its share of the batches, trained at the
preset's ``input_view_resolution``, the template's detail test). Per run: held-out PSNR,
SSIM, masked PSNR and masked SSIM (within the union of the two silhouettes: blur does not win there),
silhouette IoU; wall time of the template, colour init and training on this CPU (data preparation and
evaluation excluded); Gaussian counts (start, end).

Charts: ``splat_speed_accuracy.png`` (held-out PSNR against wall time) and ``splat_count.png``
(held-out PSNR and masked SSIM against the final Gaussian count).

Run:  .venv/bin/python benchmarks/bench_splat.py [--quick] [--no-renderpeople] [--chart-only]
Writes benchmarks/results/splat.json and the charts.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
import traceback
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.common import RESULTS, save_result  # noqa: E402
from stages.splat_optimize import SPEC  # noqa: E402

SCAN = REPO.parent / "shared" / "fixtures" / "scans" / "renderpeople_rp_mei_posed_001"
BACKGROUND = (0.3, 0.45, 0.6)
DETAIL_SPACING = SPEC.params["detail_spacing"].default  # the stage's defaults
INPUT_VIEW_SHARE = SPEC.params["input_view_share"].default
HEIGHT, FOV, FILL, ELEVATION = 1.7, 33.8, 0.85, 10.0


def held_out_cameras(size: int):
    from humanvdm_core.cameras import Cameras, orbit_cameras
    from humanvdm_core.scans import framing_radius

    radius = framing_radius(HEIGHT, FOV, FILL)
    parts = [orbit_cameras(4, size, FOV, el, radius, azimuths_deg=np.array([45.0, 135.0, 225.0, 315.0]))
             for el in (0.0, 25.0)]
    return Cameras(np.concatenate([c.K for c in parts]), np.concatenate([c.c2w for c in parts]), size, size,
                   np.concatenate([c.azimuth_deg for c in parts]), np.concatenate([c.elevation_deg for c in parts]),
                   np.concatenate([c.radius for c in parts]), {"background": np.asarray(BACKGROUND)})


def prepare_subject(name: str, work: Path, render_size: int, eval_size: int, uv_resolution: int = 64) -> dict:
    """Render the training orbit + held-out views and make the body fit; returns paths and arrays."""
    from humanvdm_core.body.model import BodyParams
    from humanvdm_core.cameras import orbit_cameras, upsample_cameras
    from humanvdm_core.frames import write_frames
    from humanvdm_core.io import read_npz
    from humanvdm_core.render import render_views
    from humanvdm_core.scans import framing_radius, load_scan, normalization_transform
    from humanvdm_core.splat.human import write_oracle_body
    from testdata.synthetic import GARMENT_EXAMPLES, SubjectSpec, make_subject

    root = work / name
    (root / "body").mkdir(parents=True, exist_ok=True)
    if name in ("synthetic", "gown"):
        spec = GARMENT_EXAMPLES["gown"] if name == "gown" else SubjectSpec(shirt_pattern="stripes", shirt_text="42", seed=3)
        obj = make_subject(spec, root / "subject")
        scan = load_scan(obj)
    else:
        scan = load_scan(SCAN)
    world_from_scan = normalization_transform(scan, HEIGHT)
    mesh = scan.transformed(world_from_scan)
    radius = framing_radius(HEIGHT, FOV, FILL)
    keys = orbit_cameras(21, render_size, FOV, ELEVATION, radius)
    cams = upsample_cameras(keys, 4)
    cams.extra["background"] = np.asarray(BACKGROUND)
    write_frames(root / "orbit", render_views(mesh, cams, BACKGROUND).rgba, cams)
    held = held_out_cameras(eval_size)
    held_rgba = render_views(mesh, held, BACKGROUND).rgba
    body_source = "truth"
    if name in ("synthetic", "gown"):
        truth = read_npz(obj.parent / "truth.npz")
        write_oracle_body(root / "body" / "body.npz", BodyParams.from_numpy(truth), world_from_scan, uv_resolution)
    else:  # fit-smpl on the 21 key views at 576²
        k576 = orbit_cameras(21, 576, FOV, ELEVATION, radius)
        k576.extra["background"] = np.asarray(BACKGROUND)
        write_frames(root / "orbit21", render_views(mesh, k576, BACKGROUND).rgba, k576)
        t0 = time.perf_counter()
        r = subprocess.run([sys.executable, "-m", "stages.fit_smpl", "--frames", str(root / "orbit21"),
                            "--out-body", str(root / "body_fit"), "--uv-resolution", str(uv_resolution)],
                           cwd=REPO, capture_output=True, text=True)
        if r.returncode != 0:
            raise RuntimeError(f"fit-smpl failed: {r.stderr[-2000:]}")
        (root / "body" / "body.npz").write_bytes((root / "body_fit" / "body.npz").read_bytes())
        body_source = f"fit-smpl ({time.perf_counter() - t0:.0f} s)"
    return {"name": name, "root": root, "held": held, "held_rgb": held_rgba[..., :3], "held_alpha": held_rgba[..., 3],
            "body_source": body_source}


def evaluate(human, subject: dict, tile_size: int) -> dict:
    """Held-out scores: full-image PSNR/SSIM, masked PSNR/SSIM (union of the silhouettes), IoU."""
    import torch

    from humanvdm_core import metrics
    from humanvdm_core.splat.human import render

    cams = subject["held"]
    bg = torch.as_tensor(np.asarray(BACKGROUND, np.float32))
    with torch.no_grad():
        gs = human()
        pred, alpha = render(gs, torch.as_tensor(cams.w2c, dtype=torch.float32), torch.as_tensor(cams.K, dtype=torch.float32),
                             cams.width, cams.height, bg, tile_size)
    pred, alpha = pred.clamp(0, 1).numpy(), alpha.numpy()
    truth, t_alpha = subject["held_rgb"].astype(np.float32), subject["held_alpha"].astype(np.float32)
    per = []
    for i in range(len(pred)):
        per.append([float(metrics.psnr(pred[i], truth[i])), float(metrics.ssim(pred[i], truth[i])),
                    float(metrics.masked_psnr(pred[i], truth[i], alpha[i], t_alpha[i])),
                    float(metrics.masked_ssim(pred[i], truth[i], alpha[i], t_alpha[i])),
                    metrics.silhouette_iou(alpha[i], t_alpha[i])])
    m = np.mean(per, axis=0)
    return {"psnr": round(float(m[0]), 3), "ssim": round(float(m[1]), 4), "masked_psnr": round(float(m[2]), 3),
            "masked_ssim": round(float(m[3]), 4), "iou": round(float(m[4]), 4)}


def run_fit(subject: dict, label: str, template: str, spacing: float | None = None, seed: int = 0,
            detail_spacing: float = DETAIL_SPACING) -> dict:
    """One stage-equivalent fit with the cpu preset's settings (the view at azimuth 0 as the input photo's:
    its share of the batches, trained at the preset's ``input_view_resolution``, the template finer where it
    shows detail); returns its row."""
    import torch

    from humanvdm_core.splat import human as H
    from humanvdm_core.splat.template import init_colors, start_anchor

    preset = H.PRESETS["cpu"]
    torch.manual_seed(seed)
    t0 = time.perf_counter()
    anchor = H.load_body_anchor(subject["root"] / "body" / "body.npz", preset["uv_resolution"])
    views = H.load_views(subject["root"] / "orbit", preset["train_resolution"])
    input_view, photo, detail_view = H.load_input_view(subject["root"] / "orbit", views,
                                                       preset["input_view_resolution"])
    t_load = time.perf_counter() - t0
    t0 = time.perf_counter()
    anchor, desc = start_anchor(anchor, views, template, spacing or preset["subject_spacing"], None, seed,
                                detail_view, detail_spacing)
    human = H.GaussianHuman(anchor, seed=seed, learn_opacity=True)
    start = human.num_gaussians
    init_colors(human, views)
    t_init = time.perf_counter() - t0
    initial_scores = evaluate(human, subject, preset["tile_size"])
    config = H.FitConfig(iterations=preset["iterations"], seed=seed, tile_size=preset["tile_size"],
                         coarse_fraction=preset["coarse_fraction"], densify_at=tuple(preset["densify_at"]),
                         max_gaussians=preset["max_gaussians"], input_view=input_view,
                         input_view_share=INPUT_VIEW_SHARE)
    result = H.fit_gaussians(human, views, config, photo=photo)
    row = {"subject": subject["name"], "run": label, "template": desc, "start_points": start,
           "num_gaussians": human.num_gaussians, "train_resolution": preset["train_resolution"],
           "iterations": preset["iterations"], "load_s": round(t_load, 1), "init_s": round(t_init, 1),
           "fit_s": round(result.wall_s, 1), "wall_s": round(t_init + result.wall_s, 1),
           "step0_psnr": initial_scores["psnr"], **evaluate(human, subject, preset["tile_size"])}
    print(row, flush=True)
    with (RESULTS / "splat_partial.jsonl").open("a") as fh:  # a line per row: an interrupted run keeps them
        fh.write(json.dumps(row) + "\n")
    return row


def chart(rows: list[dict], path: Path, count_path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    subjects = list(dict.fromkeys(r["subject"] for r in rows))
    fig, ax = plt.subplots(figsize=(7, 4.8))
    for subject in subjects:
        for r in rows:
            if r["subject"] == subject and r["run"] in ("body", "subject"):
                ax.plot(r["wall_s"], r["psnr"], "o" if r["run"] == "subject" else "s",
                        label=f"{subject}: {r['run']}")
    ax.set_xlabel("template + colour init + training wall time on this CPU (s)")
    ax.set_ylabel("held-out PSNR (dB)")
    ax.set_title("splat-optimize, cpu preset, oracle fits")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.8))
    for subject in subjects:
        pts = sorted((r for r in rows if r["subject"] == subject and r["run"].startswith("subject")),
                     key=lambda r: r["num_gaussians"])
        if len(pts) < 2:
            continue
        for ax, key in zip(axes, ("psnr", "masked_ssim"), strict=True):
            ax.plot([r["num_gaussians"] for r in pts], [r[key] for r in pts], "o-", label=subject)
    for ax, key in zip(axes, ("held-out PSNR (dB)", "held-out masked SSIM"), strict=True):
        ax.set_xscale("log")
        ax.set_xlabel("final Gaussian count (subject template, starting points 11-32 mm apart, densified)")
        ax.set_ylabel(key)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle("Where more Gaussians stop paying")
    fig.tight_layout()
    fig.savefig(count_path, dpi=110)
    plt.close(fig)


def bench_subject(name: str, render_size: int, eval_size: int, quick: bool) -> tuple[list[dict], dict]:
    """All runs of one subject (in its own process): (rows, notes)."""
    import torch

    torch.set_num_threads(1)
    rows: list[dict] = []
    with tempfile.TemporaryDirectory(prefix=f"bench_splat_{name}_") as tmp:
        try:
            t0 = time.perf_counter()
            subject = prepare_subject(name, Path(tmp), render_size, eval_size)
            notes = {"body": subject["body_source"], "prepare_s": round(time.perf_counter() - t0, 1)}
            rows.append(run_fit(subject, "body", "body"))
            rows.append(run_fit(subject, "subject", "subject"))
            rows.append(run_fit(subject, "subject, even spacing", "subject", detail_spacing=1.0))
            if name != "synthetic" and not quick:
                for spacing in (0.032, 0.022, 0.011):
                    rows.append(run_fit(subject, f"subject {1000 * spacing:g} mm apart", "subject", spacing))
        except Exception as exc:  # a failing subject is reported, the others still run
            traceback.print_exc()
            notes = {"error": f"{type(exc).__name__}: {exc}"}
    return rows, notes


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer grid points (a smoke run)")
    ap.add_argument("--no-renderpeople", action="store_true")
    ap.add_argument("--render-size", type=int, default=512)
    ap.add_argument("--eval-size", type=int, default=256)
    ap.add_argument("--workers", type=int, default=2, help="subjects benchmarked in parallel (1 thread each)")
    ap.add_argument("--chart-only", action="store_true", help="redraw the chart from results/splat.json")
    args = ap.parse_args()
    if args.chart_only:
        chart(json.loads((RESULTS / "splat.json").read_text())["result"]["runs"], RESULTS / "splat_speed_accuracy.png",
              RESULTS / "splat_count.png")
        return
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    from humanvdm_core.splat.human import PRESETS

    subjects = ["synthetic", "gown"] + ([] if args.no_renderpeople or not SCAN.is_dir() else ["renderpeople"])
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "splat_partial.jsonl").unlink(missing_ok=True)
    rows: list[dict] = []
    notes: dict = {}
    ctx = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=max(1, args.workers), mp_context=ctx) as pool:
        futures = {name: pool.submit(bench_subject, name, args.render_size, args.eval_size, args.quick)
                   for name in subjects}
        for name, fut in futures.items():
            sub_rows, notes[name] = fut.result()
            rows += sub_rows
    RESULTS.mkdir(parents=True, exist_ok=True)
    chart(rows, RESULTS / "splat_speed_accuracy.png", RESULTS / "splat_count.png")
    result = {"presets": {k: PRESETS[k] for k in ("tiny", "cpu", "full")}, "subjects": notes, "runs": rows,
              "held_out": "8 views: elevation 0 and 25 deg x azimuth 45/135/225/315; PSNR/SSIM of the full images, "
                          "masked PSNR/SSIM within the union of the silhouettes, silhouette IoU",
              "eval_size": args.eval_size, "render_size": args.render_size,
              "parallel_workers": args.workers,
              "note": "wall times measured with subjects running in parallel on a shared 2-core CPU"}
    cmd = "python benchmarks/bench_splat.py" + (" --quick" if args.quick else "")
    print(save_result("splat", result, command=cmd))
    (RESULTS / "splat_partial.jsonl").unlink(missing_ok=True)


if __name__ == "__main__":
    main()

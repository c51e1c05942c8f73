"""Benchmark of the Gaussian human (``humanvdm_core.splat.human``, stage ``splat-optimize``): oracle fits.

Subjects: a synthetic Anny subject (``humanvdm_core.synthetic``; its true body params make the body fit)
and, when present, the RenderPeople fixture scan (``../shared/fixtures/scans/renderpeople_rp_mei_posed_001``;
its body comes from the ``fit-smpl`` stage run on its 21-frame 576² orbit). Each is rendered like
``render-training-orbits`` (normalised to 1.7 units, fill 0.85, elevation 10°, fixed background) along
81 cameras ``upsample_cameras(orbit_cameras(21), 4)`` at ``--render-size``² (the training views; area-
resampled to each run's training resolution), plus 8 held-out views that are never trained on:
elevations 0° and 25° at azimuths 45/135/225/315, rendered at ``--eval-size``².

Per run: PSNR and SSIM (Gaussian 11x11 window) of the full held-out images at ``--eval-size``², training
wall time on this CPU (1 thread; data preparation excluded), Gaussian count. Runs: the ``tiny`` and
``cpu`` presets; a grid over Gaussian count (UV resolution) x iterations at the cpu preset's training
resolution (iterations are checkpoints of one run per count: wall time at the checkpoint).
The chart ``splat_speed_accuracy.png`` plots held-out PSNR against wall time.

Run:  .venv/bin/python benchmarks/bench_splat.py [--quick] [--no-renderpeople] [--chart-only]
Writes benchmarks/results/splat.json and benchmarks/results/splat_speed_accuracy.png.
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

SCAN = REPO.parent / "shared" / "fixtures" / "scans" / "renderpeople_rp_mei_posed_001"
BACKGROUND = (0.3, 0.45, 0.6)
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
    from humanvdm_core.synthetic import SubjectSpec, make_subject

    root = work / name
    (root / "body").mkdir(parents=True, exist_ok=True)
    if name == "synthetic":
        obj = make_subject(SubjectSpec(shirt_pattern="stripes", shirt_text="42", seed=3), root / "subject")
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
    if name == "synthetic":
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
    return {"name": name, "root": root, "held": held, "held_rgb": held_rgba[..., :3], "body_source": body_source}


def evaluate(human, subject: dict, tile_size: int) -> dict:
    import torch

    from humanvdm_core.splat.human import psnr, render_views_np, ssim

    pred = render_views_np(human, subject["held"], np.asarray(BACKGROUND), tile_size=tile_size)
    truth = subject["held_rgb"].astype(np.float32)
    p, t = torch.as_tensor(pred).permute(0, 3, 1, 2), torch.as_tensor(truth).permute(0, 3, 1, 2)
    return {"psnr": round(float(np.mean([psnr(a, b) for a, b in zip(pred, truth, strict=True)])), 3),
            "ssim": round(float(np.mean([float(ssim(p[i:i + 1], t[i:i + 1])) for i in range(len(p))])), 4)}


def run_fit(subject: dict, uv_resolution: int, train_resolution: int, checkpoints: list[int], tile_size: int,
            label: str, seed: int = 0, partial: Path | None = None) -> list[dict]:
    """One training run, evaluated at each checkpoint (iterations); wall time excludes evaluation."""
    import torch

    from humanvdm_core.splat import human as H

    torch.manual_seed(seed)
    anchor = H.load_body_anchor(subject["root"] / "body" / "body.npz", uv_resolution)
    views = H.load_views(subject["root"] / "orbit", train_resolution)
    human = H.GaussianHuman(anchor, seed=seed)
    rows, done, wall = [], 0, 0.0
    for ck in checkpoints:
        # continue the same run: fit_gaussians restarts Adam, so run the whole schedule in segments of
        # one optimiser (see fit_segmented)
        res = fit_segment(human, views, ck - done, seed, tile_size, done)
        wall += res
        done = ck
        scores = evaluate(human, subject, tile_size)
        row = {"subject": subject["name"], "run": label, "uv_resolution": uv_resolution, "num_gaussians": human.num_gaussians,
               "train_resolution": train_resolution, "iterations": ck, "wall_s": round(wall, 1), **scores}
        print(row, flush=True)
        rows.append(row)
        if partial is not None:  # a line per row, so an interrupted benchmark keeps what it measured
            with partial.open("a") as fh:
                fh.write(json.dumps(row) + "\n")
    return rows


_OPTIMISERS: dict[int, object] = {}


def fit_segment(human, views, iterations: int, seed: int, tile_size: int, start: int) -> float:
    """Continue training ``human`` for ``iterations`` steps with one persistent optimiser; returns seconds."""
    import torch

    from humanvdm_core.splat import human as H

    cfg = H.FitConfig(iterations=start + iterations, seed=seed, tile_size=tile_size)
    key = id(human)
    if key not in _OPTIMISERS:
        _OPTIMISERS[key] = torch.optim.Adam([
            {"params": [human.features, *human.decoder.parameters()], "lr": cfg.lr},
            {"params": [human.delta_pose, human.delta_transl], "lr": cfg.pose_lr}])
    opt = _OPTIMISERS[key]
    batches = H.view_order(len(views.images), cfg.iterations, cfg.batch_views, seed)[start:]
    t0 = time.perf_counter()
    for idx in batches:
        loss = H.training_loss(human, views, torch.as_tensor(idx), cfg)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
    return time.perf_counter() - t0


def chart(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.8))
    for ax, subject in zip(axes, sorted({r["subject"] for r in rows}), strict=False):
        sub = [r for r in rows if r["subject"] == subject]
        for label in dict.fromkeys(r["run"] for r in sub):
            pts = [r for r in sub if r["run"] == label]
            ax.plot([r["wall_s"] for r in pts], [r["psnr"] for r in pts], "o-", label=label)
            for r in pts:
                ax.annotate(str(r["iterations"]), (r["wall_s"], r["psnr"]), fontsize=7, xytext=(3, 3),
                            textcoords="offset points")
        ax.set_xscale("log")
        ax.xaxis.set_major_formatter(matplotlib.ticker.FuncFormatter(lambda v, _: f"{v:g}"))
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.set_xlabel("training wall time on this CPU (s, log; labels: iterations)")
        ax.set_ylabel("held-out PSNR (dB)")
        ax.set_title(f"splat-optimize, oracle fit: {subject}")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def bench_subject(name: str, render_size: int, eval_size: int, quick: bool) -> tuple[list[dict], dict]:
    """All runs of one subject (in its own process): (rows, notes)."""
    import torch

    from humanvdm_core.splat.human import PRESETS

    torch.set_num_threads(1)
    tiny, cpu = PRESETS["tiny"], PRESETS["cpu"]
    rows: list[dict] = []
    with tempfile.TemporaryDirectory(prefix=f"bench_splat_{name}_") as tmp:
        try:
            t0 = time.perf_counter()
            subject = prepare_subject(name, Path(tmp), render_size, eval_size)
            notes = {"body": subject["body_source"], "prepare_s": round(time.perf_counter() - t0, 1)}
            plan = [("tiny", tiny["uv_resolution"], tiny["train_resolution"], [tiny["iterations"]], tiny["tile_size"])]
            cpu_its = sorted({cpu["iterations"] // 4, cpu["iterations"] // 2, cpu["iterations"]})
            plan.append(("cpu", cpu["uv_resolution"], cpu["train_resolution"], cpu_its, cpu["tile_size"]))
            if name == "synthetic" and not quick:
                for R in (48, 96):
                    plan.append((f"grid R={R}", R, cpu["train_resolution"], cpu_its[:2], cpu["tile_size"]))
            for label, R, S, its, ts in plan:
                rows += run_fit(subject, R, S, its, ts, label, partial=RESULTS / "splat_partial.jsonl")
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
        chart(json.loads((RESULTS / "splat.json").read_text())["result"]["runs"], RESULTS / "splat_speed_accuracy.png")
        return
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    from humanvdm_core.splat.human import PRESETS

    subjects = ["synthetic"] + ([] if args.no_renderpeople or not SCAN.is_dir() else ["renderpeople"])
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
    chart(rows, RESULTS / "splat_speed_accuracy.png")
    result = {"presets": {k: PRESETS[k] for k in ("tiny", "cpu", "full")}, "subjects": notes, "runs": rows,
              "held_out": "8 views: elevation 0 and 25 deg x azimuth 45/135/225/315, full-image PSNR/SSIM",
              "eval_size": args.eval_size, "render_size": args.render_size,
              "parallel_workers": args.workers,
              "note": "wall times measured with subjects running in parallel on a shared 2-core CPU"}
    cmd = "python benchmarks/bench_splat.py" + (" --quick" if args.quick else "")
    print(save_result("splat", result, command=cmd))
    (RESULTS / "splat_partial.jsonl").unlink(missing_ok=True)


if __name__ == "__main__":
    main()

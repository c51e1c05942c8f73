"""The paper's four-view protocol on real textured scans: one rendered photo -> the whole pipeline.

Per textured scan in ``../shared/fixtures/scans/`` (RenderPeople Mei and Eric, the three.js Soldier;
skipped with a message when that folder is absent):

1. the scan (``load_scan`` + ``normalize_scan``, turned to face +Z; ``--turn DEG`` turns it further,
   90 for a photo in profile) is rendered at azimuth 0, elevation 10 deg (``--photo-elevation``: 30
   for a photo taken from above), at the orbit framing radius (``framing_radius()``),
   ``--photo-size``² over white; that PNG (RGBA, RGB already over white; ``--opaque`` drops the
   alpha) is the *photo*, the only thing the pipeline sees;
2. ``humanvdm run photo.png --store <work>/store --no-progress`` runs the default pipeline with the
   default presets (``--set`` passes overrides through); per-stage wall time and peak memory come
   from the run's lockfile, the total wall time from the clock;
3. the four protocol views -- front, left, back, right = azimuth 0, 90, 180, 270 at the orbit's
   elevation; azimuth 90 is the camera on +X, which sees the subject's LEFT side (the convention of
   ``humanvdm_core.cameras``) -- are scored against the scan rendered at the same cameras, for
   (a) ``diffuse``'s orbit: it has 21 frames at azimuths ``linspace(0, 360, 22)[1:] % 360``, so each
       view takes the frame of nearest azimuth (ties: the lower azimuth, so "back" is 171.4 deg) and
       is compared with the scan rendered at THAT frame's own camera;
   (b) the final Gaussians (``splat-optimize/gaussians``) rendered at the exact protocol cameras
       (the orbit's radius and field of view);
   every image is re-framed as in ``bench_pipeline`` (silhouette box centred, 85 % of the frame
   height, ``--eval-size``²) unless ``--no-reframe``; PSNR and SSIM over the whole frame (white
   background), masked PSNR over the union of the silhouettes, silhouette IoU; per view and mean,
   plus ``unseen_mean`` (mean PSNR of left/back/right) and ``side_iou`` (mean IoU of left and right).

Outputs (``benchmarks/results/``):

- ``protocol.json`` (label ``after`` only), a plain shape any reader can check, views in
  front/left/back/right order::

      {"<scan>": {"orbit": {"psnr": [F, L, B, R], "ssim": [...], "iou": [...], "masked_psnr": [...]},
                  "gaussians": {...the same...}}}

- ``protocol_<label>.json`` (``benchmarks.common.save_result``): everything -- per-view scores and
  frames, means, per-stage timings, the pipeline command, the machine; with label ``after`` and a
  ``protocol_before.json`` present (``--before``), also before -> after per scan;
- ``protocol_<scan>.png`` (``protocol_<scan>_<label>.png`` for other labels): rows = the four views,
  columns = truth | orbit (nearest frame) | Gaussians | where the orbit's silhouette misses (both grey,
  the truth's alone red, the orbit's alone blue; per view in the JSON too, ``misses``: the pixels
  each has alone per height band of the two silhouettes' union, :data:`BANDS`).

The "before" numbers come from the old code in a git worktree of HEAD, e.g.::

    git worktree add /tmp/hvdm_head HEAD
    cp benchmarks/bench_protocol.py /tmp/hvdm_head/benchmarks/
    (cd /tmp/hvdm_head && /work/main/.venv/bin/python -m benchmarks.bench_protocol --label before)
    cp /tmp/hvdm_head/benchmarks/results/protocol_before.json benchmarks/results/
    .venv/bin/python -m benchmarks.bench_protocol            # label after: protocol.json + the comparison

The pipeline runs as ``<this python> -m humanvdm_core.cli run`` from this file's repository, so a
worktree runs its own code (the venv's ``humanvdm`` script would import the editable install's).

Run:  .venv/bin/python -m benchmarks.bench_protocol [--subjects mei eric soldier] [--label after]
      [--skip-pipeline] [--work DIR] [--set splat-optimize.preset=tiny] [--turn 90 --label profile]
      [--skip-pipeline --subjects mei --gaussians gaussians.npz --label full_gpu]  (Gaussians trained elsewhere)
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import cv2  # noqa: E402
import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.bench_pipeline import ELEVATION, VIEWS, WHITE, reframe, resized, scores, view_cameras  # noqa: E402
from benchmarks.common import RESULTS, save_result  # noqa: E402

SCANS = REPO.parent / "shared" / "fixtures" / "scans"
YAW_DEG = {"threejs_soldier": 180.0}  # scans that do not face +Z (the Soldier faces -Z)
METRICS = ("psnr", "ssim", "iou", "masked_psnr")
MEANS = (*METRICS, "unseen_mean", "side_iou")
STRIP_MAX_BYTES = 1_500_000
DEFAULT_WORK = Path("/tmp/humanvdm_bench_protocol")
# height bands of a silhouette overlay, as fractions of the union's height from its top (a standing adult)
BANDS = {"head": (0.0, 0.16), "torso": (0.16, 0.52), "legs": (0.52, 1.0)}
LEFT_IS = "azimuth 90 deg: the camera on +X, seeing the subject's left side (subject faces +Z, azimuth 0 = front)"


def find_scans(wanted: list[str] | None) -> list[Path]:
    """The scan folders under SCANS, those whose name contains one of ``wanted`` (all when None)."""
    folders = sorted(p for p in SCANS.iterdir() if p.is_dir() and not p.name.startswith("."))
    if not wanted:
        return folders
    picked = [p for p in folders if any(w.lower() in p.name.lower() for w in wanted)]
    missing = [w for w in wanted if not any(w.lower() in p.name.lower() for p in folders)]
    if missing:
        raise SystemExit(f"no scan matches {missing}; have {[p.name for p in folders]}")
    return picked


def nearest_frame(azimuths: np.ndarray, target: float) -> int:
    """Index of the azimuth nearest ``target`` on the circle (the lower azimuth on a tie)."""
    az = np.asarray(azimuths, np.float64) % 360.0
    d = np.abs((az - target + 180.0) % 360.0 - 180.0)
    best = np.flatnonzero(d <= d.min() + 1e-6)
    return int(best[np.argmin(az[best])])


def summarize(per_view: dict) -> dict:
    """Per-metric lists in VIEWS order, their means, unseen_mean (L/B/R PSNR), side_iou (L, R IoU)."""
    lists = {k: [per_view[v][k] for v in VIEWS] for k in METRICS}
    mean = {k: float(np.mean(lists[k])) for k in METRICS}
    mean["unseen_mean"] = float(np.mean([per_view[v]["psnr"] for v in ("left", "back", "right")]))
    mean["side_iou"] = float(np.mean([per_view[v]["iou"] for v in ("left", "right")]))
    return {**lists, "mean": mean}


def label_cell(img: np.ndarray, text: str) -> np.ndarray:
    """``img`` (float RGB in [0, 1]) as uint8 with ``text`` written in its top-left corner."""
    from humanvdm_core.io import to_uint8

    img = np.ascontiguousarray(to_uint8(img))
    scale = img.shape[0] / 640
    cv2.putText(img, text, (int(8 * scale), int(28 * scale)), cv2.FONT_HERSHEY_SIMPLEX, 0.8 * scale, (0, 0, 0),
                max(1, int(round(2 * scale))), cv2.LINE_AA)
    return img


def silhouette_misses(alpha: np.ndarray, truth_alpha: np.ndarray) -> tuple[np.ndarray, dict[str, list[int]]]:
    """Two re-framed silhouettes compared: an RGB uint8 overlay (both grey, ``truth_alpha``'s alone red,
    ``alpha``'s alone blue) and, per height band of their union (:data:`BANDS`), the pixels
    ``[truth alone, alpha alone]``."""
    a, t = alpha > 0.5, truth_alpha > 0.5
    img = np.full(a.shape + (3,), 255, np.uint8)
    img[a & t] = 150
    img[t & ~a] = (235, 60, 60)
    img[a & ~t] = (60, 80, 235)
    rows = np.nonzero((a | t).any(axis=1))[0]
    if not len(rows):
        return img, {band: [0, 0] for band in BANDS}
    top, height = rows.min(), rows.max() + 1 - rows.min()
    misses = {}
    for band, (lo, hi) in BANDS.items():
        sl = slice(top + int(round(lo * height)), top + int(round(hi * height)))
        misses[band] = [int((t & ~a)[sl].sum()), int((a & ~t)[sl].sum())]
    return img, misses


def write_strip(path: Path, rows: list[np.ndarray]) -> None:
    """Rows stacked, downscaled until the PNG is under STRIP_MAX_BYTES."""
    strip = np.concatenate(rows, axis=0)
    factor = 0.5
    while True:
        small = cv2.resize(strip, None, fx=factor, fy=factor, interpolation=cv2.INTER_AREA)
        ok, data = cv2.imencode(".png", cv2.cvtColor(small, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_PNG_COMPRESSION, 9])
        if not ok:
            raise OSError(f"cannot encode {path}")
        if len(data) < STRIP_MAX_BYTES or factor < 0.1:
            break
        factor *= 0.8
    path.write_bytes(data.tobytes())


def run_pipeline(photo: Path, store: Path, args) -> dict:
    """``humanvdm run`` on the photo in a new process; returns the command, exit code, wall time, log tail."""
    cmd = [sys.executable, "-m", "humanvdm_core.cli", "run", str(photo), "--store", str(store), "--no-progress",
           "--jobs", str(args.jobs)] + (["--until", "diffuse"] if args.orbit_only else [])
    for s in args.set or []:
        cmd += ["--set", s]
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), env.get("PYTHONPATH")]))
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, env=env)
    wall = time.perf_counter() - t0
    shown = ["humanvdm", *cmd[3:]]  # what a person would type
    return {"command": " ".join(shown), "returncode": proc.returncode, "wall_s": round(wall, 2),
            "log_tail": (proc.stdout + proc.stderr)[-3000:]}


def run_scan(folder: Path, work: Path, args) -> dict:
    from humanvdm_core.cameras import orbit_cameras
    from humanvdm_core.evaluate import load_gaussians, render_gaussians
    from humanvdm_core.frames import read_cameras, read_frames
    from humanvdm_core.io import write_png
    from humanvdm_core.render import render_views
    from humanvdm_core.scans import framing_radius, load_scan, normalize_scan
    from humanvdm_core.workflow.scheduler import read_lockfile
    from humanvdm_core.workflow.store import Store

    name = folder.name
    yaw = YAW_DEG.get(name, 0.0) + args.turn
    mesh = normalize_scan(load_scan(folder), yaw_deg=yaw)
    radius = framing_radius()
    store = work / "store"
    photo = work / f"{name}.png"
    record = work / f"{name}.run.json"

    if args.skip_pipeline:
        if not record.exists() or not (store / "runs" / name).exists():
            return {"scan": name, "error": f"--skip-pipeline: no earlier run of {name} in {work}"}
        run = json.loads(record.read_text())
    else:
        photo_cam = orbit_cameras(1, args.photo_size, elevation_deg=args.photo_elevation, radius=radius,
                                  azimuths_deg=np.array([0.0]))
        rgba = render_views(mesh, photo_cam, WHITE).rgba[0]
        write_png(photo, rgba[..., :3] if args.opaque else rgba)
        run = run_pipeline(photo, store, args)
        record.write_text(json.dumps(run, indent=1) + "\n")
    if run["returncode"]:
        return {"scan": name, "error": run["log_tail"], "command": run["command"]}

    run_dir = store / "runs" / name
    lock = read_lockfile(Store(store), name)
    stages = {k: {"wall_s": v.get("wall_s"), "peak_rss_mb": v.get("peak_rss_mb")}
              for k, v in (lock.get("stages") or {}).items()}

    # (a) the orbit: nearest frame per view, against the scan at that frame's camera
    orbit_dir = run_dir / "diffuse" / "orbit"
    orbit_cams = read_cameras(orbit_dir)
    picks = {v: nearest_frame(orbit_cams.azimuth_deg, az) for v, az in VIEWS.items()}
    idx = list(picks.values())
    frames = read_frames(orbit_dir, indices=idx)
    orbit_truth = render_views(mesh, orbit_cams.subset(idx), WHITE).rgba

    # (b) the Gaussians at the exact protocol cameras, against the scan at the same cameras
    cams = view_cameras(orbit_cams, args.eval_size)
    truth = render_views(mesh, cams, WHITE).rgba
    if args.orbit_only:
        g_rgb, g_a = np.ones((len(VIEWS), args.eval_size, args.eval_size, 3), np.float32), None
    else:
        g_rgb, g_a = render_gaussians(load_gaussians(args.gaussians or run_dir / "splat-optimize" / "gaussians"),
                                      cams, WHITE)

    def prep(rgb, alpha):
        return (resized if args.no_reframe else reframe)(rgb, alpha, args.eval_size)

    orbit_views, gauss_views, rows = {}, {}, []
    for i, (view, az) in enumerate(VIEWS.items()):
        o = prep(frames[i, ..., :3], frames[i, ..., 3])
        ot = prep(orbit_truth[i, ..., :3], orbit_truth[i, ..., 3])
        t = prep(truth[i, ..., :3], truth[i, ..., 3])
        g = (g_rgb[i], None) if g_a is None else prep(g_rgb[i], g_a[i])
        frame_az = float(orbit_cams.azimuth_deg[idx[i]])
        overlay, misses = silhouette_misses(o[1], ot[1])
        orbit_views[view] = {**scores(o, ot), "frame": idx[i], "frame_azimuth_deg": round(frame_az, 3),
                             "misses": misses}
        if g_a is not None:
            gauss_views[view] = {**scores(g, t), "azimuth_deg": az}
        rows.append(np.concatenate([label_cell(t[0], f"{view}: truth az {az:.0f}"),
                                    label_cell(o[0], f"orbit frame {idx[i]} az {frame_az:.1f}"),
                                    label_cell(g[0], "Gaussians" if g_a is not None else "Gaussians: not run"),
                                    label_cell(overlay.astype(np.float32) / 255.0,
                                               f"IoU {orbit_views[view]['iou']:.3f}: truth red, orbit blue")], axis=1))
    suffix = "" if args.label == "after" else f"_{args.label}"
    strip = RESULTS / f"protocol_{name}{suffix}.png"
    write_strip(strip, rows)

    return {"scan": name, "path": str(folder), "yaw_deg": yaw, "faces": int(mesh.num_faces),
            "command": run["command"], "pipeline_wall_s": run["wall_s"], "stages": stages,
            "orbit": {"views": orbit_views, **summarize(orbit_views)},
            "gaussians": {"views": gauss_views, **summarize(gauss_views)} if gauss_views else None,
            "strip": str(strip.relative_to(REPO))}


def plain(results: dict) -> dict:
    """The protocol.json shape: per scan, per source, per metric, four numbers in F/L/B/R order."""
    return {name: {src: {k: r[src][k] for k in METRICS} for src in ("orbit", "gaussians") if r.get(src)}
            for name, r in results.items() if "error" not in r}


def compare(before_path: Path, results: dict) -> dict:
    """Per scan and source: {metric: [before, after]} of the means, for scans in both runs."""
    if not before_path.exists():
        return {}
    before = json.loads(before_path.read_text()).get("result", {}).get("scans", {})
    out = {}
    for name, r in results.items():
        b = before.get(name)
        if "error" in r or not b or "error" in b:
            continue
        out[name] = {src: {k: [b[src]["mean"][k], r[src]["mean"][k]] for k in MEANS}
                     for src in ("orbit", "gaussians") if r.get(src) and b.get(src)}
    return out


def report(results: dict, comparison: dict) -> str:
    lines = []
    for name, r in results.items():
        if "error" in r:
            lines.append(f"{name}: FAILED ({r['error'].strip().splitlines()[-1] if r['error'].strip() else '?'})")
            continue
        for src in ("orbit", "gaussians"):
            if not r.get(src):
                continue
            m = r[src]["mean"]
            per = " ".join(f"{v[0].upper()}{p:.2f}" for v, p in zip(VIEWS, r[src]["psnr"], strict=True))
            line = (f"{name} {src:9s} PSNR {m['psnr']:.2f} ({per}) SSIM {m['ssim']:.3f} masked {m['masked_psnr']:.2f}"
                    f" IoU {m['iou']:.3f} unseen {m['unseen_mean']:.2f} side_iou {m['side_iou']:.3f}")
            lines.append(line)
            if src in comparison.get(name, {}):
                c = comparison[name][src]
                lines.append("    before -> after: " + ", ".join(
                    f"{k} {c[k][0]:.3f} -> {c[k][1]:.3f} ({c[k][1] - c[k][0]:+.3f})" for k in MEANS))
        lines.append(f"{name} pipeline {r['pipeline_wall_s']} s: " + ", ".join(
            f"{k} {v['wall_s']}" for k, v in r["stages"].items()))
    return "\n".join(lines)


def save(results: dict, args) -> Path:
    comparison = compare(args.before, results) if args.label != "before" else {}
    ok = [r for r in results.values() if "error" not in r]
    mean = {src: {k: float(np.mean([r[src]["mean"][k] for r in ok if r.get(src)])) for k in MEANS}
            for src in ("orbit", "gaussians") if any(r.get(src) for r in ok)}
    doc = {"views": {v: {"azimuth_deg": az} for v, az in VIEWS.items()}, "view_order": list(VIEWS),
           "left_is": LEFT_IS, "elevation_deg": ELEVATION, "photo_size": args.photo_size,
           "photo_alpha": not args.opaque, "eval_size": args.eval_size, "reframed": not args.no_reframe,
           "turn_deg": args.turn, "photo_elevation_deg": args.photo_elevation,
           "orbit_frame_rule": "nearest azimuth on the circle, lower azimuth on a tie; scored against the scan "
                               "rendered at that frame's own camera",
           "overrides": args.set or [], "label": args.label, "work": str(args.work),
           "scans": results, "mean_over_scans": mean, "before_after": comparison,
           "failed": [n for n, r in results.items() if "error" in r]}
    if args.label == "after":
        (RESULTS / "protocol.json").write_text(json.dumps(plain(results), indent=1) + "\n")
    return save_result(f"protocol_{args.label}", doc, "python -m benchmarks.bench_protocol " + " ".join(sys.argv[1:]))


def main() -> int:
    import torch

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--subjects", nargs="*", default=None,
                        help="scans whose folder name contains one of these (default: every scan)")
    parser.add_argument("--label", default="after",
                        help="after (default): protocol.json + protocol_after.json; other labels: "
                             "protocol_<label>.json and strips suffixed _<label>")
    parser.add_argument("--work", type=Path, default=None,
                        help=f"persistent scratch folder (default {DEFAULT_WORK}/<label>)")
    parser.add_argument("--skip-pipeline", action="store_true", help="rescore the runs already in --work")
    parser.add_argument("--gaussians", type=Path, default=None,
                        help="with --skip-pipeline and one subject: score these Gaussians (a gaussians.npz, e.g. "
                             "bench_gpu --keep-gaussians) instead of the run's splat-optimize output")
    parser.add_argument("--orbit-only", action="store_true",
                        help="run the pipeline until diffuse and score the orbit only (no Gaussians)")
    parser.add_argument("--set", action="append", metavar="STAGE.PARAM=VALUE",
                        help="passed to humanvdm run (e.g. splat-optimize.preset=tiny); repeatable")
    parser.add_argument("--jobs", type=int, default=1, help="humanvdm run --jobs")
    parser.add_argument("--before", type=Path, default=RESULTS / "protocol_before.json",
                        help="the before run to compare with")
    parser.add_argument("--photo-size", type=int, default=768)
    parser.add_argument("--eval-size", type=int, default=512)
    parser.add_argument("--opaque", action="store_true", help="write the photo without alpha (RGB over white)")
    parser.add_argument("--photo-elevation", type=float, default=ELEVATION,
                        help="the photo's camera elevation in degrees (30: a photo taken from above)")
    parser.add_argument("--turn", type=float, default=0.0,
                        help="turn each scan by this many degrees about the vertical before the photo "
                             "(90: a profile; the views are then relative to the photo, not the scan's front)")
    parser.add_argument("--no-reframe", action="store_true", help="score the renders as they are (resized only)")
    parser.add_argument("--merge", action="store_true",
                        help="keep scans of an earlier protocol_<label>.json that this run does not redo")
    args = parser.parse_args()
    if args.gaussians and not (args.skip_pipeline and args.subjects and len(args.subjects) == 1):
        parser.error("--gaussians needs --skip-pipeline and one --subjects")
    torch.set_num_threads(1)

    if not SCANS.is_dir():
        print(f"bench_protocol: skipped, no scan fixtures at {SCANS}")
        return 0
    args.work = (args.work or DEFAULT_WORK / args.label).resolve()
    args.work.mkdir(parents=True, exist_ok=True)
    RESULTS.mkdir(parents=True, exist_ok=True)

    results: dict = {}
    earlier = RESULTS / f"protocol_{args.label}.json"
    if args.merge and earlier.exists():
        results.update(json.loads(earlier.read_text()).get("result", {}).get("scans", {}))
    for folder in find_scans(args.subjects):
        print(f"== {folder.name}", flush=True)
        r = run_scan(folder, args.work, args)
        results[folder.name] = r
        out = save(results, args)  # after every scan: a long run keeps what it has
        print(report({folder.name: r}, compare(args.before, {folder.name: r}) if args.label != "before" else {}),
              flush=True)
    doc = json.loads(out.read_text())["result"]
    print("\n== summary")
    print(report(results, doc["before_after"]))
    print(f"wrote {out}" + (f" and {RESULTS / 'protocol.json'}" if args.label == "after" else ""))
    return 1 if doc["failed"] else 0


if __name__ == "__main__":
    raise SystemExit(main())

"""The paper's experiments and ours from one command, through the scheduler and its cache (issue 13).

    python -m benchmarks.experiments [--quick] [--only protocol,ablations,stability,speed]
    make experiments ARGS=--quick

Every pipeline run is ``humanvdm run PHOTO --store WORK/store --set ...`` (``benchmarks.cached_runs``)
into ONE persistent store (``--work``, default :data:`DEFAULT_WORK`): a second call, or a call after
a change to one stage, recomputes only the stage runs whose keys changed; each step prints how many
stage runs ran and how many were reused, and the end prints the totals and where the results are.

Parts (each writes ``experiments_<part>.json``, ``experiments_quick_<part>.json`` with ``--quick``,
into ``--results``, default ``benchmarks/results``; ``experiments[_quick]_report.md`` holds every table):

1. ``protocol`` -- the paper's Table 1 form on the real fixture scans (``../shared/fixtures/scans``):
   each scan rendered as a photo (azimuth 0, elevation 10) and scored by
   ``benchmarks.bench_protocol.run_scan`` at front/left/back/right, for the orbit and the final
   Gaussians: PSNR, SSIM, masked PSNR, IoU, plus masked SSIM of the Gaussians and LPIPS / CLIP
   similarity when the user's weights are present ("unavailable" otherwise); per diffuse backend
   (body-prior always; ``sv3d_p`` only when its weights file exists); next to the paper's own
   numbers (:data:`PAPER_TABLE1`, another dataset).
2. ``ablations`` -- the paper's Table 2 form on Mei: full; without interpolate
   (``interpolate.passes=0``: the 21 orbit frames); without upscale (``upscale.target_size`` = the
   orbit's resolution: a pass-through copy); body vs subject template; without pose refinement;
   stock vs fine-tuned SV3D when both weight files exist. Every variant is a ``--set`` of the same
   pipeline; its time is the sum of the stage wall times in the run's lockfile.
3. ``stability`` -- ``benchmarks.stability``: one case per failure category with truth, a measured
   criterion, a pass/fail table and a contact sheet per case (``stability_<case>.png``).
4. ``speed`` -- speed vs accuracy: the splat presets this machine can run (tiny, cpu; full only
   with CUDA) and the main knobs (iterations, Gaussian count, training resolution, interpolation
   passes) on the protocol scans: time per photo (stage wall times summed, ``evaluate`` left out)
   vs the Gaussians' four-view PSNR and masked SSIM, means over the scans; the Pareto front is
   marked and each point carries its Gaussian count (``experiments[_quick]_speed.png``).

``--quick``: tiny settings everywhere (tiny splat preset, 256 px photos, 128 px orbits, one scan, two
ablations, two stability cases, two speed points): a few minutes on a 2-core CPU machine (CI).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import shutil
import sys
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks import stability  # noqa: E402
from benchmarks.bench_pipeline import VIEWS, WHITE, reframe, view_cameras  # noqa: E402
from benchmarks.bench_protocol import RESULTS as PROTOCOL_RESULTS  # noqa: E402
from benchmarks.bench_protocol import SCANS, YAW_DEG, run_scan  # noqa: E402
from benchmarks.cached_runs import PipelineRun, Tally, num_gaussians, pipeline_time, run_pipeline, stage_times  # noqa: E402
from benchmarks.common import RESULTS, machine  # noqa: E402

DEFAULT_WORK = Path("/tmp/humanvdm_experiments")
PARTS = ("protocol", "ablations", "stability", "speed")
METRICS = ("psnr", "ssim", "masked_psnr", "iou")
SHORT = {"renderpeople_rp_mei_posed_001": "mei", "renderpeople_rp_eric_rigged_001": "eric",
         "threejs_soldier": "soldier"}
ABLATION_SCAN = "renderpeople_rp_mei_posed_001"

# Human-VDM paper, Table 1: quoted from the paper, measured on ANOTHER dataset (THuman2.0-style scans,
# their renders and their models), so not comparable number for number with ours.
PAPER_TABLE1 = {"dataset": "ANOTHER dataset: the paper's THuman2.0-style test set (quoted, not measured here)",
                "psnr": 20.068, "ssim": 0.9209, "lpips": 0.0958, "clip": 0.9231}

QUICK_SETS = [
    "diffuse.resolution=128", "diffuse.fit_iterations=30", "upscale.target_size=128", "interpolate.passes=1",
    "fit-smpl.iterations=30", "fit-smpl.fit_frames=4", "fit-smpl.uv_resolution=64", "splat-optimize.preset=tiny",
    "splat-optimize.iterations=40", "splat-optimize.turntable_views=0", "evaluate.resolution=64",
    "evaluate.media_size=0", "evaluate.heldout_azimuths=45", "evaluate.heldout_elevations=0",
]


@dataclass
class Mode:
    """Sizes and settings of one mode (quick or full)."""

    name: str
    photo_size: int
    eval_size: int
    base_sets: list[str]
    scans: list[str] | None  # folder-name filters; None: every scan
    ablations: list[str]
    cases: tuple[str, ...]
    speed: list[tuple[str, list[str]]]
    orbit_resolution: int = 576


def default_preset() -> str:
    """What splat-optimize's ``auto`` preset picks here: ``full`` with CUDA, else ``cpu``."""
    import torch

    return "full" if torch.cuda.is_available() else "cpu"


def full_mode() -> Mode:
    from humanvdm_core.splat.human import PRESETS

    preset = default_preset()
    p = PRESETS[preset]
    presets = ["tiny", "cpu"] + (["full"] if preset == "full" else [])
    speed = [(f"preset {name}", [f"splat-optimize.preset={name}"]) for name in presets]
    speed += [
        (f"iterations {p['iterations'] // 2}", [f"splat-optimize.iterations={p['iterations'] // 2}"]),
        (f"iterations {p['iterations'] * 2}", [f"splat-optimize.iterations={p['iterations'] * 2}"]),
        # Gaussian count: the subject template's spacing (x1.4 spacing ~ half the points, /1.4 ~ twice)
        (f"subject_spacing {p['subject_spacing'] * 1.4:.4f}",
         [f"splat-optimize.subject_spacing={p['subject_spacing'] * 1.4:.4f}"]),
        (f"subject_spacing {p['subject_spacing'] / 1.4:.4f}",
         [f"splat-optimize.subject_spacing={p['subject_spacing'] / 1.4:.4f}"]),
        (f"train_resolution {p['train_resolution'] * 2 // 3}",
         [f"splat-optimize.train_resolution={p['train_resolution'] * 2 // 3}"]),
        (f"train_resolution {p['train_resolution'] * 4 // 3}",
         [f"splat-optimize.train_resolution={p['train_resolution'] * 4 // 3}"]),
        ("interpolate.passes 0", ["interpolate.passes=0"]),
        ("interpolate.passes 1", ["interpolate.passes=1"]),
    ]
    return Mode("full", photo_size=768, eval_size=512, base_sets=[f"splat-optimize.preset={preset}"], scans=None,
                ablations=["full", "no_interpolate", "no_upscale", "body_template", "subject_template",
                           "pose_refinement", "sv3d_finetuned"],
                cases=tuple(c.name for c in stability.CASES), speed=speed)


def quick_mode() -> Mode:
    return Mode("quick", photo_size=256, eval_size=128, base_sets=list(QUICK_SETS), scans=["mei"],
                ablations=["full", "no_interpolate"], cases=stability.QUICK_CASES,
                speed=[("tiny, 40 iterations", []), ("tiny, 80 iterations", ["splat-optimize.iterations=80"])],
                orbit_resolution=128)


@dataclass
class Context:
    """What every part needs: the mode, the folders, the running tally of stage runs."""

    mode: Mode
    work: Path
    results: Path
    jobs: int
    threshold: float
    tally: Tally = field(default_factory=Tally)
    meshes: dict = field(default_factory=dict)
    perceptual: object | None = None

    @property
    def store(self) -> Path:
        return self.work / "store"  # bench_protocol.run_scan reads WORK/store

    def out(self, name: str) -> Path:
        prefix = "experiments_quick_" if self.mode.name == "quick" else "experiments_"
        return self.results / f"{prefix}{name}"


def say(text: str) -> None:
    print(text, flush=True)


def run_line(run: PipelineRun) -> str:
    return f"{run.ran} stage run(s) ran, {run.cached} reused, {run.failed} failed ({run.wall_s:.1f} s)"


# ----------------------------------------------------------------------------- weights

def sv3d_weights(kind: str = "sv3d_p") -> Path:
    """Where the diffuse stage looks for the SV3D weights by default (its ``<kind>_weights`` param)."""
    from stages.diffuse import SPEC

    return Path(SPEC.params[f"{kind}_weights"].default).expanduser()


def finetuned_weights() -> Path:
    """A fine-tuned SV3D_p checkpoint (the ``finetune`` stage's output name) beside the stock one."""
    return sv3d_weights().with_name("sv3d_p_finetuned.safetensors")


def make_perceptual():
    """LPIPS / CLIP from the evaluate stage's default weight paths; each 'unavailable: ...' without its files."""
    from humanvdm_core.evaluate import EvaluateOptions, Perceptual
    from stages.evaluate import SPEC

    d = {k: str(Path(SPEC.params[k].default).expanduser()) for k in ("lpips_weights", "alexnet_weights",
                                                                      "clip_weights")}
    return Perceptual(EvaluateOptions(**d), logging.getLogger("experiments"))


# ----------------------------------------------------------------------------- one scored protocol run

def scan_mesh(ctx: Context, folder: Path):
    """The scan as ``run_scan`` sees it (normalised, turned to face +Z), loaded once."""
    from humanvdm_core.scans import load_scan, normalize_scan

    if folder.name not in ctx.meshes:
        ctx.meshes[folder.name] = normalize_scan(load_scan(folder), yaw_deg=YAW_DEG.get(folder.name, 0.0))
    return ctx.meshes[folder.name]


def gaussian_extras(ctx: Context, run_dir: Path, mesh) -> dict:
    """Per protocol view: masked SSIM of the Gaussians vs the scan, and LPIPS / CLIP (or 'unavailable')."""
    from humanvdm_core import metrics as M
    from humanvdm_core.evaluate import load_gaussians, render_gaussians
    from humanvdm_core.frames import read_cameras
    from humanvdm_core.render import render_views

    size = ctx.mode.eval_size
    cams = view_cameras(read_cameras(run_dir / "diffuse" / "orbit"), size)
    rgb, alpha = render_gaussians(load_gaussians(run_dir / "splat-optimize" / "gaussians"), cams, WHITE)
    truth = render_views(mesh, cams, WHITE).rgba
    if ctx.perceptual is None:
        ctx.perceptual = make_perceptual()
    out = {}
    for i, view in enumerate(VIEWS):
        g = reframe(rgb[i], alpha[i], size)
        t = reframe(truth[i, ..., :3], truth[i, ..., 3], size)
        out[view] = {"masked_ssim": float(M.masked_ssim(g[0], t[0], g[1], t[1])),
                     **ctx.perceptual.scores(g[0], t[0])}
    return out


def protocol_run(ctx: Context, folder: Path, extra_sets: list[str], strip_name: str | None) -> dict:
    """Render the scan's photo, run the pipeline (cached), score it with bench_protocol.run_scan."""
    from humanvdm_core.io import write_png

    name = folder.name
    mesh = scan_mesh(ctx, folder)
    photo = ctx.work / f"{name}.png"  # where run_scan expects it
    write_png(photo, stability.render_front(mesh, ctx.mode.photo_size))
    sets = ctx.mode.base_sets + extra_sets
    run = run_pipeline(photo, ctx.store, sets, jobs=ctx.jobs)
    ctx.tally.add(run)
    (ctx.work / f"{name}.run.json").write_text(json.dumps(run.record(), indent=1) + "\n")
    args = argparse.Namespace(skip_pipeline=True, photo_size=ctx.mode.photo_size, opaque=False, jobs=ctx.jobs,
                              orbit_only=False, set=sets, eval_size=ctx.mode.eval_size, no_reframe=False,
                              label="experiments", turn=0.0, gaussians=None)
    try:
        result = run_scan(folder, ctx.work, args)
    except Exception:  # scoring broke (a bug here or in the code it calls): a row saying so; the parts go on
        result = {"scan": name, "error": traceback.format_exc()[-3000:]}
    result["run"] = run.summary()
    strip = PROTOCOL_RESULTS / f"protocol_{name}_experiments.png"  # where run_scan wrote it
    if strip.exists():
        if strip_name:
            shutil.move(str(strip), ctx.out(strip_name))
            result["strip"] = str(ctx.out(strip_name))
        else:
            strip.unlink()
            result.pop("strip", None)
    if "error" in result:
        return result
    run_dir = ctx.store / "runs" / name
    times = stage_times(ctx.store, name)
    result["stage_wall_s"] = times
    result["time_s"] = pipeline_time(times)
    result["num_gaussians"] = num_gaussians(run_dir)
    try:
        extras = gaussian_extras(ctx, run_dir, mesh)
    except Exception:
        return {**result, "error": traceback.format_exc()[-3000:]}
    g = result["gaussians"]
    for key in ("masked_ssim", "lpips", "clip"):
        g[key] = [extras[v][key] for v in VIEWS]
        values = [x for x in g[key] if isinstance(x, float)]
        g["mean"][key] = float(np.mean(values)) if len(values) == len(VIEWS) else g[key][0]
    return result


def short_line(r: dict) -> str:
    if "error" in r:
        lines = [ln for ln in r["error"].strip().splitlines() if ln.strip()]
        return f"FAILED ({lines[-1] if lines else '?'})"
    g, o = r["gaussians"]["mean"], r["orbit"]["mean"]
    return (f"Gaussians PSNR {g['psnr']:.2f} SSIM {g['ssim']:.3f} masked SSIM {g['masked_ssim']:.3f} "
            f"IoU {g['iou']:.3f} | orbit PSNR {o['psnr']:.2f} | {r['time_s']:.0f} s, {r['num_gaussians']} Gaussians")


def scan_folders(mode: Mode) -> list[Path]:
    folders = sorted(p for p in SCANS.iterdir() if p.is_dir() and not p.name.startswith("."))
    if mode.scans:
        folders = [p for p in folders if any(w in p.name for w in mode.scans)]
    return folders


# ----------------------------------------------------------------------------- parts

def part_protocol(ctx: Context) -> dict:
    backends = {"body-prior": []}
    notes = []
    if sv3d_weights().is_file():
        backends["sv3d_p"] = ["diffuse.backend=sv3d_p"]
    else:
        notes.append(f"sv3d_p skipped: no weights at {sv3d_weights()} (the diffuse stage's default path)")
        say(f"  {notes[-1]}")
    folders = scan_folders(ctx.mode)
    table: dict = {}
    steps = [(b, f) for b in backends for f in folders]
    for i, (backend, folder) in enumerate(steps, 1):
        short = SHORT.get(folder.name, folder.name)
        r = protocol_run(ctx, folder, backends[backend], f"protocol_{short}_{backend}.png")
        table.setdefault(backend, {})[folder.name] = r
        say(f"[protocol {i}/{len(steps)}] {short} {backend}: {run_line_of(r)} -> {short_line(r)}")
    return {"backends": list(backends), "notes": notes, "views": VIEWS, "paper_table1": PAPER_TABLE1,
            "perceptual": getattr(ctx.perceptual, "status", None), "table": table}


def run_line_of(r: dict) -> str:
    run = r.get("run") or {}
    if not run:
        return "not run"
    return (f"{run['ran']} stage run(s) ran, {run['cached']} reused, {run['failed']} failed "
            f"({run['call_wall_s']:.1f} s)")


def ablation_variants(ctx: Context) -> dict[str, tuple[list[str], str]]:
    """Name -> (the --set overrides on top of the mode's, what it means); unavailable ones left out."""
    res = ctx.mode.orbit_resolution
    variants = {
        "full": ([], "every stage (the mode's settings)"),
        "no_interpolate": (["interpolate.passes=0"], "without interpolate: the 21 orbit frames"),
        "no_upscale": ([f"upscale.target_size={res}"], f"without upscale: frames stay {res} px (pass-through)"),
        "body_template": (["splat-optimize.template=body"], "body template (one Gaussian per UV texel, the paper)"),
        "subject_template": (["splat-optimize.template=subject"], "subject template (clothed proxy / visual hull)"),
        "pose_refinement": (["splat-optimize.refine_pose=true"], "with pose refinement (the paper's; off by default)"),
    }
    if sv3d_weights().is_file() and finetuned_weights().is_file():
        variants["sv3d_stock"] = (["diffuse.backend=sv3d_p"], "SV3D_p, stock weights")
        variants["sv3d_finetuned"] = (["diffuse.backend=sv3d_p", f"diffuse.sv3d_p_weights={finetuned_weights()}"],
                                      "SV3D_p, fine-tuned weights")
    return variants


def part_ablations(ctx: Context) -> dict:
    folder = SCANS / ABLATION_SCAN
    variants = ablation_variants(ctx)
    notes = []
    if "sv3d_finetuned" in ctx.mode.ablations and "sv3d_finetuned" not in variants:
        notes.append(f"without fine-tuned SV3D: skipped, needs {sv3d_weights()} and {finetuned_weights()}")
        say(f"  {notes[-1]}")
    names = [n for n in ctx.mode.ablations if n in variants]
    if "sv3d_finetuned" in names:
        names.insert(names.index("sv3d_finetuned"), "sv3d_stock")
    rows = {}
    for i, name in enumerate(names, 1):
        sets, meaning = variants[name]
        r = protocol_run(ctx, folder, sets, f"ablation_{name}.png" if ctx.mode.name == "full" else None)
        rows[name] = {"meaning": meaning, "sets": sets, **r}
        say(f"[ablations {i}/{len(names)}] {name}: {run_line_of(r)} -> {short_line(r)}")
    return {"scan": ABLATION_SCAN, "notes": notes, "variants": rows}


def part_stability(ctx: Context, only: list[str] | None) -> dict:
    cases = [c for c in stability.CASES if c.name in (only or ctx.mode.cases)]
    unknown = sorted(set(only or []) - {c.name for c in stability.CASES})
    if unknown:
        raise SystemExit(f"unknown stability cases {unknown}; have {[c.name for c in stability.CASES]}")
    rows = []
    for i, case in enumerate(cases, 1):
        try:
            row, run = stability.run_case(case, ctx.work, ctx.store, ctx.mode.base_sets, ctx.mode.photo_size,
                                          ctx.mode.eval_size, ctx.threshold, ctx.out(f"stability_{case.name}.png"),
                                          jobs=ctx.jobs)
        except Exception:  # a bug of this harness on one case: a row saying so; the suite goes on
            row, run = {"case": case.name, "category": case.category, "passed": False,
                        "error": traceback.format_exc()[-2000:]}, None
        if run is not None:
            ctx.tally.add(run)
        rows.append(row)
        verdict = ("skipped" if row["passed"] is None else "ERROR (harness: see the JSON)" if "error" in row
                   else "PASS" if row["passed"] else "FAIL")
        seen = "; ".join(str(c["seen"])[:80] for c in row.get("checks", []))
        say(f"[stability {i}/{len(cases)}] {case.name}: {run_line_of(row)} -> {verdict} ({seen or row.get('skipped')})")
    return {"threshold_side_iou": ctx.threshold, "cases": rows, "not_covered": stability.NOT_COVERED,
            "criteria": {"iou": "the run finished and the orbit's mean silhouette IoU at azimuth 90/270 vs truth "
                                "is at least the threshold",
                         "warns": "the run finished and a warning names the photo and says the text",
                         "refuses": "the run stopped with a FAILED line naming the photo and saying the text"}}


def pareto(points: list[dict], key: str) -> None:
    """Mark ``pareto_<key>``: no other point is at least as fast and at least as good, and better in one."""
    for p in points:
        p[f"pareto_{key}"] = not any(q is not p and q["time_s"] <= p["time_s"] and q[key] >= p[key]
                                     and (q["time_s"] < p["time_s"] or q[key] > p[key]) for q in points)


def part_speed(ctx: Context) -> dict:
    folders = scan_folders(ctx.mode)
    steps = [(label, sets, f) for label, sets in ctx.mode.speed for f in folders]
    per_point: dict[str, list[dict]] = {}
    for i, (label, sets, folder) in enumerate(steps, 1):
        r = protocol_run(ctx, folder, sets, None)
        entry = {"scan": folder.name, "run": r.get("run")}
        if "error" in r:
            entry["error"] = r["error"][-500:]
        else:
            entry.update(time_s=r["time_s"], psnr=r["gaussians"]["mean"]["psnr"],
                         masked_ssim=r["gaussians"]["mean"]["masked_ssim"], num_gaussians=r["num_gaussians"],
                         stage_wall_s=r["stage_wall_s"])
        per_point.setdefault(label, []).append(entry)
        say(f"[speed {i}/{len(steps)}] {label} / {SHORT.get(folder.name, folder.name)}: {run_line_of(r)} -> "
            f"{short_line(r)}")
    points = []
    for label, sets in ctx.mode.speed:
        ok = [e for e in per_point.get(label, []) if "error" not in e]
        point = {"label": label, "sets": sets, "scans": per_point.get(label, [])}
        if ok:
            point.update(time_s=float(np.mean([e["time_s"] for e in ok])),
                         psnr=float(np.mean([e["psnr"] for e in ok])),
                         masked_ssim=float(np.mean([e["masked_ssim"] for e in ok])),
                         num_gaussians=int(np.mean([e["num_gaussians"] or 0 for e in ok])))
        points.append(point)
    scored = [p for p in points if "time_s" in p]
    pareto(scored, "psnr")
    pareto(scored, "masked_ssim")
    chart = ctx.out("speed.png")
    speed_chart(chart, scored, ctx.mode.name)
    return {"time": "per photo: the reconstruction stages' wall times from the lockfile, summed (evaluate left out); "
                    "mean over the scans", "accuracy": "the Gaussians at the four protocol views vs the scan",
            "points": points, "chart": str(chart)}


def speed_chart(path: Path, points: list[dict], mode: str) -> None:
    """Two panels (PSNR, masked SSIM) vs time; the Pareto front joined; each point numbered, the numbers
    keyed below the panels with the point's label and Gaussian count (labels next to clustered points
    would overlap)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 6.2))
    for ax, key, name in zip(axes, ("psnr", "masked_ssim"), ("four-view PSNR (dB)", "four-view masked SSIM"),
                             strict=True):
        for i, p in enumerate(points, 1):
            front = p[f"pareto_{key}"]
            ax.scatter(p["time_s"], p[key], s=60 if front else 30, c="tab:red" if front else "tab:gray",
                       zorder=3)
            ax.annotate(str(i), (p["time_s"], p[key]), fontsize=8, xytext=(4, 4), textcoords="offset points")
        front = sorted((p for p in points if p[f"pareto_{key}"]), key=lambda p: p["time_s"])
        if front:
            ax.plot([p["time_s"] for p in front], [p[key] for p in front], "-o", c="tab:red", lw=1, ms=3,
                    label="Pareto front (no point is faster and better)")
            ax.legend(loc="lower right", fontsize=8)
        if len(points) > 1 and max(p["time_s"] for p in points) > 4 * min(p["time_s"] for p in points):
            ax.set_xscale("log")
        ax.margins(x=0.25, y=0.25)
        ax.set_xlabel("time per photo (s, stage wall times summed)")
        ax.set_ylabel(name)
        ax.grid(alpha=0.3)
    fig.suptitle(f"speed vs accuracy ({mode} mode)")
    key_lines = [f"{i}  {p['label']} ({p['num_gaussians']:,} Gaussians)" for i, p in enumerate(points, 1)]
    columns = 3
    rows = -(-len(key_lines) // columns)
    for c in range(columns):
        fig.text(0.03 + c / columns, 0.02, "\n".join(key_lines[c * rows:(c + 1) * rows]), fontsize=8, va="bottom")
    fig.tight_layout(rect=(0, 0.05 + 0.035 * rows, 1, 1))
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ----------------------------------------------------------------------------- report

def fmt(x, digits: int = 3) -> str:
    """A number with ``digits`` decimals; 'n/a' for an 'unavailable: ...' metric."""
    if isinstance(x, str) and x.startswith("unavailable"):
        return "n/a"
    return f"{x:.{digits}f}" if isinstance(x, float) else str(x)


def view_values(scored: dict, view: str) -> dict:
    """One row of the protocol table: each metric at ``view`` (or the mean), '' where not measured."""
    keys = (*METRICS, "masked_ssim", "lpips", "clip")
    if view == "mean":
        return {k: scored["mean"].get(k, "") for k in keys}
    i = list(VIEWS).index(view)
    return {k: scored[k][i] if k in scored else "" for k in keys}


def report_markdown(ctx: Context, parts: dict, earlier: dict[str, str] | None = None) -> str:
    """Every table in one Markdown file; ``earlier`` names the parts this call did not run (their
    tables come from the last call that did, on the date given)."""
    lines = [f"# Experiments ({ctx.mode.name} mode)", "", f"Store: `{ctx.store}`; stage runs: {ctx.tally.line()}.", ""]
    if earlier:
        lines += ["Not run by this call, from earlier calls: "
                  + ", ".join(f"{p} ({d})" for p, d in earlier.items()) + ".", ""]
    if "protocol" in parts:
        p = parts["protocol"]
        lines += ["## Protocol (paper Table 1 form)", "",
                  "Four views (front/left/back/right = azimuth 0/90/180/270), re-framed; LPIPS lower is better.", ""]
        for backend, scans in p["table"].items():
            for scan, r in scans.items():
                lines.append(f"**{SHORT.get(scan, scan)}, diffuse {backend}**")
                lines.append("")
                if "error" in r:
                    lines += [f"failed: {short_line(r)}", ""]
                    continue
                lines += ["| source | view | PSNR | SSIM | masked PSNR | IoU | masked SSIM | LPIPS | CLIP |",
                          "|---|---|---|---|---|---|---|---|---|"]
                for src in ("orbit", "gaussians"):
                    for view in [*VIEWS, "mean"]:
                        v = view_values(r[src], view)
                        lines.append(f"| {src} | {view} | {fmt(v['psnr'], 2)} | {fmt(v['ssim'])} | "
                                     f"{fmt(v['masked_psnr'], 2)} | {fmt(v['iou'])} | {fmt(v['masked_ssim'])} | "
                                     f"{fmt(v['lpips'])} | {fmt(v['clip'])} |")
                lines.append("")
        t = PAPER_TABLE1
        lines += ["**Table 1 form: means of the four views, final Gaussians**", "",
                  "| method | data | PSNR | SSIM | LPIPS | CLIP | masked PSNR | IoU |", "|---|---|---|---|---|---|---|---|"]
        for backend, scans in p["table"].items():
            for scan, r in scans.items():
                if "error" not in r:
                    m = r["gaussians"]["mean"]
                    lines.append(f"| ours, diffuse {backend} | {SHORT.get(scan, scan)} (fixture scan) | "
                                 f"{m['psnr']:.3f} | {m['ssim']:.4f} | {fmt(m['lpips'], 4)} | {fmt(m['clip'], 4)} | "
                                 f"{m['masked_psnr']:.3f} | {m['iou']:.3f} |")
        lines += [f"| Human-VDM paper (quoted) | {t['dataset']} | {t['psnr']} | {t['ssim']} | "
                  f"{t['lpips']} | {t['clip']} | | |", ""]
        status = p.get("perceptual") or {}
        lines += [f"- {n}" for n in p["notes"]] + [f"- {k}: {v}" for k, v in status.items()] + [""]
    if "ablations" in parts:
        a = parts["ablations"]
        lines += [f"## Ablations (paper Table 2 form) on {SHORT.get(a['scan'], a['scan'])}", "",
                  "| variant | --set | time (s) | Gaussians | PSNR | SSIM | masked SSIM | IoU | orbit PSNR |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for name, r in a["variants"].items():
            if "error" in r:
                lines.append(f"| {name} | {' '.join(r['sets'])} | failed | | | | | | |")
                continue
            g, o = r["gaussians"]["mean"], r["orbit"]["mean"]
            lines.append(f"| {name} | {' '.join(r['sets']) or '(none)'} | {r['time_s']:.1f} | {r['num_gaussians']} | "
                         f"{g['psnr']:.2f} | {g['ssim']:.3f} | {fmt(g['masked_ssim'])} | {g['iou']:.3f} | "
                         f"{o['psnr']:.2f} |")
        lines += [""] + [f"- {n}" for n in a["notes"]] + [""]
    if "stability" in parts:
        s = parts["stability"]
        lines += ["## Stability suite", "", f"Side IoU threshold {s['threshold_side_iou']}.", "",
                  "| case | category | result | side IoU (orbit) | side IoU (Gaussians) | checks | sheet |",
                  "|---|---|---|---|---|---|---|"]
        for r in s["cases"]:
            verdict = ("skipped" if r["passed"] is None else "ERROR" if "error" in r
                       else "PASS" if r["passed"] else "FAIL")
            folder = str(Path(r["photo"]).parent) + "/" if "photo" in r else "\0"
            checks = "; ".join(f"{c['check']}: {'ok' if c['passed'] else 'no'} "
                               f"({str(c['seen']).replace(folder, '')[:100]})"
                               for c in r.get("checks", [])) or r.get("skipped") or "harness error (JSON)"
            lines.append(f"| {r['case']} | {r['category']} | {verdict} | {fmt(r.get('side_iou', ''))} | "
                         f"{fmt(r.get('gaussians_side_iou', ''))} | {checks.replace('|', '/')} | "
                         f"{Path(r.get('sheet', '')).name} |")
        lines += ["", "Not covered yet:"] + [f"- {k}: {v}" for k, v in s["not_covered"].items()] + [""]
    if "speed" in parts:
        sp = parts["speed"]
        lines += ["## Speed vs accuracy", "", f"Time: {sp['time']}. Chart: `{Path(sp['chart']).name}`.", "",
                  "| point | time (s) | Gaussians | PSNR | masked SSIM | Pareto (PSNR) | Pareto (masked SSIM) |",
                  "|---|---|---|---|---|---|---|"]
        for p in sp["points"]:
            if "time_s" not in p:
                lines.append(f"| {p['label']} | failed | | | | | |")
                continue
            lines.append(f"| {p['label']} | {p['time_s']:.1f} | {p['num_gaussians']:,} | {p['psnr']:.2f} | "
                         f"{p['masked_ssim']:.3f} | {'*' if p['pareto_psnr'] else ''} | "
                         f"{'*' if p['pareto_masked_ssim'] else ''} |")
        lines.append("")
    return "\n".join(lines)


def save(ctx: Context, part: str, result: dict, tally: dict, command: str) -> Path:
    path = ctx.out(f"{part}.json")
    doc = {"benchmark": f"experiments_{part}", "mode": ctx.mode.name, "command": command,
           "date": time.strftime("%Y-%m-%d"), "machine": machine(), "store": str(ctx.store),
           "settings": {"photo_size": ctx.mode.photo_size, "eval_size": ctx.mode.eval_size,
                        "base_sets": ctx.mode.base_sets},
           "stage_runs": tally, "result": result}
    path.write_text(json.dumps(doc, indent=1, default=str) + "\n")
    return path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="tiny settings everywhere (a few minutes on a CPU)")
    parser.add_argument("--only", default=",".join(PARTS), help=f"comma-separated parts of {','.join(PARTS)}")
    parser.add_argument("--work", type=Path, default=DEFAULT_WORK,
                        help=f"persistent folder; the one cache store is WORK/store (default {DEFAULT_WORK})")
    parser.add_argument("--results", type=Path, default=RESULTS, help="where the JSON, PNG and Markdown go")
    parser.add_argument("--jobs", type=int, default=1, help="humanvdm run --jobs")
    parser.add_argument("--scans", default=None, help="comma-separated scan name filters (default: the mode's)")
    parser.add_argument("--cases", default=None, help="comma-separated stability cases (default: the mode's)")
    parser.add_argument("--side-iou-threshold", type=float, default=stability.SIDE_IOU_PASS,
                        help="side-view IoU an 'iou' stability check needs (default %(default)s)")
    args = parser.parse_args(argv)
    parts = [p.strip() for p in args.only.split(",") if p.strip()]
    bad = sorted(set(parts) - set(PARTS))
    if bad:
        parser.error(f"unknown parts {bad}; choose from {','.join(PARTS)}")

    import torch

    torch.set_num_threads(1)
    mode = quick_mode() if args.quick else full_mode()
    if args.scans:
        mode.scans = [s.strip() for s in args.scans.split(",") if s.strip()]
    ctx = Context(mode=mode, work=args.work.resolve(), results=args.results.resolve(), jobs=args.jobs,
                  threshold=args.side_iou_threshold)
    ctx.work.mkdir(parents=True, exist_ok=True)
    ctx.results.mkdir(parents=True, exist_ok=True)
    command = "python -m benchmarks.experiments " + " ".join(argv if argv is not None else sys.argv[1:])
    say(f"experiments ({mode.name} mode): parts {', '.join(parts)}; store {ctx.store}; results {ctx.results}")
    t0 = time.perf_counter()
    done: dict = {}
    written: list[Path] = []
    for part in parts:
        if part != "stability" and not SCANS.is_dir():
            say(f"== {part}: skipped, no scan fixtures at {SCANS}")
            continue
        say(f"== {part}")
        before = ctx.tally.copy()
        if part == "stability":
            only = [c.strip() for c in args.cases.split(",")] if args.cases else None
            result = part_stability(ctx, only)
        else:
            result = {"protocol": part_protocol, "ablations": part_ablations, "speed": part_speed}[part](ctx)
        tally = ctx.tally.since(before)
        done[part] = result
        written.append(save(ctx, part, result, tally.as_dict(), command))
        say(f"   {part}: {tally.line()} -> {written[-1]}")
    earlier = {}  # parts not run by this call: their tables from the last call that ran them
    for part in PARTS:
        saved = ctx.out(f"{part}.json")
        if part not in done and saved.is_file():
            doc = json.loads(saved.read_text())
            earlier[part] = doc.get("date", "?")
            done[part] = doc["result"]
    report = ctx.out("report.md")
    report.write_text(report_markdown(ctx, {p: done[p] for p in PARTS if p in done}, earlier) + "\n")
    written.append(report)
    say(f"\ndone in {time.perf_counter() - t0:.0f} s; stage runs: {ctx.tally.line()}")
    say(f"results in {ctx.results}:")
    for path in written:
        say(f"  {path.name}")
    pngs = sorted(p.name for p in ctx.results.glob(ctx.out("*.png").name))
    if pngs:
        say(f"  and {len(pngs)} PNG(s): {', '.join(pngs)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

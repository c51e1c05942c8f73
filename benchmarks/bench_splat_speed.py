"""splat-optimize before and after, on the same inputs in one run, and the headline figures of issue 10.

For each protocol scan already run by ``bench_protocol`` (``--work``, default its ``after`` folder), the
``splat-optimize`` stage is run as the scheduler runs it (``python -m stages.splat_optimize`` on that run's
``interpolate`` frames and ``fit-smpl`` body, ``cpu`` preset, no turntable) twice, one after the other:
with the code of ``--before-repo`` (a checkout from before the change) and with this tree's code (also
given ``diffuse``'s orbit, so it finds the clothed proxy), each with the thread environment its
scheduler gave (before: ``OMP_NUM_THREADS`` = all cores; after: :func:`humanvdm_core.workflow.threads.thread_env`).
Wall times are of the whole stage process (loading, training, writing).

``benchmarks/results/splat_speed.json`` then gathers, as the issue asks: ``before_s`` / ``after_s`` (medians
over the scans of the runs above), ``heldout_psnr_before`` / ``heldout_psnr_after`` (oracle held-out PSNR
per subject: ``results/splat_before.json``, the old ``bench_splat.py`` run from ``--before-repo``, and
``results/splat.json``), ``input_view_psnr`` (the final Gaussians at the input view, ``results/protocol.json``),
``busy_slowdown_before`` / ``busy_slowdown_after`` (``results/busy.json``) and ``gaussians`` (final counts).

Run:  .venv/bin/python benchmarks/bench_splat_speed.py --before-repo /tmp/before_wt
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.common import RESULTS, save_result  # noqa: E402

DEFAULT_WORK = Path("/tmp/humanvdm_bench_protocol/after")


def run_stage(repo: Path, run_dir: Path, out: Path, env: dict[str, str], with_orbit: bool) -> float:
    """Seconds one ``splat-optimize`` process took (cpu preset, no turntable) on ``run_dir``'s inputs."""
    cmd = [sys.executable, "-m", "stages.splat_optimize", "--frames", str(run_dir / "interpolate" / "frames"),
           "--body", str(run_dir / "fit-smpl" / "body"), "--out-gaussians", str(out), "--preset", "cpu",
           "--turntable-views", "0"]
    if with_orbit:
        cmd += ["--orbit", str(run_dir / "diffuse" / "orbit")]
    t0 = time.perf_counter()
    r = subprocess.run(cmd, cwd=repo, env=dict(env, PYTHONPATH=str(repo)), capture_output=True, text=True)
    if r.returncode:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{r.stderr[-2000:]}")
    return time.perf_counter() - t0


def load(name: str) -> dict:
    path = RESULTS / name
    return json.loads(path.read_text())["result"] if path.is_file() else {}


def main() -> None:
    from humanvdm_core.workflow.threads import THREAD_VARS, stage_threads, thread_env

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--before-repo", type=Path, required=True)
    ap.add_argument("--work", type=Path, default=DEFAULT_WORK, help="bench_protocol's work folder")
    ap.add_argument("--subjects", nargs="*", default=None, help="protocol runs to time (default: all in --work)")
    args = ap.parse_args()
    runs = sorted(p for p in (args.work / "store" / "runs").iterdir() if (p / "interpolate").exists()
                  and (args.subjects is None or p.name in args.subjects))
    clean = {k: v for k, v in os.environ.items() if k not in THREAD_VARS + ("OMP_WAIT_POLICY", "KMP_BLOCKTIME")}
    envs = {"before": dict(clean, OMP_NUM_THREADS=str(os.cpu_count() or 1)),
            "after": thread_env(stage_threads(1), clean)}
    stage: dict[str, dict[str, float]] = {}
    with tempfile.TemporaryDirectory(prefix="bench_splat_speed_") as tmp:
        for run in runs:
            stage[run.name] = {}
            for label, repo in (("before", args.before_repo.resolve()), ("after", REPO)):
                out = Path(tmp) / label / run.name
                out.parent.mkdir(parents=True, exist_ok=True)
                stage[run.name][f"{label}_s"] = round(run_stage(repo, run, out, envs[label], label == "after"), 1)
                print(run.name, label, stage[run.name][f"{label}_s"], "s", flush=True)
            log = json.loads((Path(tmp) / "after" / run.name / "train_log.json").read_text())
            stage[run.name]["gaussians_after"] = log["num_gaussians"]

    before_bench, after_bench = load("splat_before.json"), load("splat.json")
    protocol = json.loads((RESULTS / "protocol.json").read_text()) if (RESULTS / "protocol.json").is_file() else {}
    busy = load("busy.json")
    heldout_before = {r["subject"]: r["psnr"] for r in before_bench.get("runs", [])
                      if r.get("run") == "cpu" and r.get("iterations") == 500}
    heldout_after = {r["subject"]: r["psnr"] for r in after_bench.get("runs", []) if r.get("run") == "subject"}
    gaussians = {r["subject"]: r["num_gaussians"] for r in after_bench.get("runs", []) if r.get("run") == "subject"}
    gaussians.update({f"{k} (photo pipeline)": v["gaussians_after"] for k, v in stage.items()})
    result = {
        "before_s": statistics.median(v["before_s"] for v in stage.values()),
        "after_s": statistics.median(v["after_s"] for v in stage.values()),
        "heldout_psnr_before": heldout_before,
        "heldout_psnr_after": heldout_after,
        "input_view_psnr": {k: round(v["gaussians"]["psnr"][0], 2) for k, v in protocol.items() if v.get("gaussians")},
        "busy_slowdown_before": busy.get("before", {}).get("slowdown"),
        "busy_slowdown_after": busy.get("after", {}).get("slowdown"),
        "gaussians": gaussians,
        "stage_runs": stage,
        "sources": {"stage times": "this run: splat-optimize on the protocol runs' inputs, before then after",
                    "held-out PSNR": "results/splat_before.json (old bench_splat.py, cpu preset, 500 iterations, "
                                     "body template) and results/splat.json (template subject, cpu preset)",
                    "input view": "results/protocol.json, final Gaussians, front view",
                    "busy": "results/busy.json"},
    }
    print(save_result("splat_speed", result, command=f"python benchmarks/bench_splat_speed.py --before-repo "
                                                      f"{args.before_repo}"))


if __name__ == "__main__":
    main()

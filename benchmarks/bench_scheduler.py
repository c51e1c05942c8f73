"""Scheduler and store overhead.

1. A no-op rerun of N inputs x all stages, fully cached (the toy pipeline of tests/toyproject.py:
   3 stages, each output an 81-file artifact like a frame set), in seconds, median of repeats.
2. Checking one unchanged 81-frame 1080^2 EXR frame set: full hash (first commit / ``verify``)
   against the stat-cached check every cache lookup does.

    python -m benchmarks.bench_scheduler [--inputs 100] [--repeats 3]
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.common import save_result
from humanvdm_core.cameras import orbit_cameras
from humanvdm_core.frames import write_frames
from humanvdm_core.workflow.pipeline import load_pipeline
from humanvdm_core.workflow.scheduler import CACHED, Scheduler
from humanvdm_core.workflow.store import Store
from tests.toyproject import STAGES, ToyProject


def _wide_stages() -> dict[str, str]:
    out = {}
    for name, body in STAGES.items():
        lines = []
        for ln in body.splitlines():
            if 'ctx.outputs["out"] /' in ln:
                indent = ln[: len(ln) - len(ln.lstrip())]
                lines.append(f"{indent}for i in range(81):")
                lines.append(indent + "    " + ln.strip().replace('/ "', '/ f"{i:02d}_'))
            else:
                lines.append(ln)
        out[name] = "\n".join(lines) + "\n"
    return out


def bench_noop_rerun(n_inputs: int, repeats: int, jobs: int) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        toy = ToyProject(Path(tmp), stages=_wide_stages())
        subjects = [toy.subject(f"s{i:03d}", f"input number {i} " * (i % 7 + 1)) for i in range(n_inputs)]
        t0 = time.perf_counter()
        first = toy.scheduler(jobs=jobs).run(subjects)
        first_s = time.perf_counter() - t0
        assert first.ok, [r.reason for r in first.failed]
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            pipe = load_pipeline(toy.pipeline_path)
            store = Store(toy.store.root)
            for s in subjects:  # what the CLI does: re-import (stat-cached hash) every input
                s.input_id = store.import_path(s.source)
            summary = Scheduler(pipe, store, jobs=jobs, progress=False).run(subjects)
            times.append(time.perf_counter() - t0)
            assert all(r.state == CACHED for r in summary.runs)
        return {"inputs": n_inputs, "stages": 3, "files_per_artifact": 81, "jobs": jobs,
                "first_run_s": round(first_s, 2), "noop_rerun_s_median": round(statistics.median(times), 3),
                "noop_rerun_s_all": [round(t, 3) for t in times],
                "per_stage_run_ms": round(1000 * statistics.median(times) / (3 * n_inputs), 2)}


def bench_frameset_check(repeats: int) -> dict:
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:1080, 0:1080] / 1080.0
    base = np.stack([xx, yy, 0.5 * (xx + yy), np.ones_like(xx)], -1).astype(np.float32)
    frames = (np.clip(base + 0.02 * rng.standard_normal(base.shape, dtype=np.float32), 0, 1) for _ in range(81))
    with tempfile.TemporaryDirectory() as tmp:
        store = Store(Path(tmp) / "store")
        staged = store.new_staging_dir("bench")
        write_frames(staged, frames, orbit_cameras(81, size=1080, azimuths_deg=np.linspace(0, 360, 81)))
        size_mb = sum(f.stat().st_size for f in staged.rglob("*") if f.is_file()) / 1e6
        t0 = time.perf_counter()
        artifact_id = store.commit_dir(staged)
        commit_s = time.perf_counter() - t0
        cached, full = [], []
        for _ in range(repeats):
            fresh = Store(store.root)  # a new process's view: only the on-disk stat cache helps
            t0 = time.perf_counter()
            assert fresh.has(artifact_id)
            cached.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            assert fresh._check(artifact_id, trust_cache=False)
            full.append(time.perf_counter() - t0)
        return {"frames": 81, "size": 1080, "artifact_mb": round(size_mb, 1), "commit_s": round(commit_s, 3),
                "check_stat_cached_s_median": round(statistics.median(cached), 4),
                "check_full_rehash_s_median": round(statistics.median(full), 3),
                "speedup": round(statistics.median(full) / statistics.median(cached), 1)}


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--inputs", type=int, default=100)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--jobs", type=int, default=2)
    args = ap.parse_args(argv)
    result = {"noop_rerun": bench_noop_rerun(args.inputs, args.repeats, args.jobs),
              "frameset_check": bench_frameset_check(args.repeats)}
    save_result("scheduler", result, command=f"python -m benchmarks.bench_scheduler --inputs {args.inputs}")
    print(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()

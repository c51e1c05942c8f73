"""The Ray executor's overhead per stage run, against the local executor.

The same N toy inputs x 3 stages (tests/toyproject.py: each stage run is a ~0.1 s Python process)
run into fresh stores, alternately: locally with ``--jobs 2``, and as Ray tasks on a Ray instance of
2 CPUs started here (``ray.init(num_cpus=2)``, what ``humanvdm run --executor ray`` does without
``--address``) with the command's default of stage runs in flight; medians of the repeats. Inputs
whose stage run has the same key as another's are cache hits within the run and are not counted.
Both executors have 2 slots, so

    per stage run (slot-ms) = wall x 2 / stage runs
    executor overhead (ms)  = per stage run - the stage process's own wall time (mean of the runs'
                              ``wall_s``, timed around the subprocess in both executors)
    Ray's cost per stage run = its per stage run - the local one (end to end: it includes stage
                              processes slowed by Ray's own processes on the same 2 cores)

also: ``ray.init``, a no-op task's round trip, and the fully cached rerun on each (Ray submits
nothing then). Skips, with a message, where Ray is not installed.

    python -m benchmarks.bench_ray [--inputs 100] [--repeats 3]
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

from benchmarks.common import save_result
from humanvdm_core.workflow.cli import RAY_JOBS
from humanvdm_core.workflow.pipeline import load_pipeline
from humanvdm_core.workflow.scheduler import CACHED, RAN, Scheduler, read_lockfile
from humanvdm_core.workflow.store import Store
from tests.toyproject import ToyProject

SLOTS = 2


def _timed_run(toy: ToyProject, store: Store, subjects, **kw) -> tuple[float, list]:
    t0 = time.perf_counter()
    summary = Scheduler(load_pipeline(toy.pipeline_path), store, progress="quiet", **kw).run(subjects)
    wall = time.perf_counter() - t0
    assert summary.ok, [r.reason for r in summary.failed]
    return wall, summary.runs


def _per_run(wall: float, runs: list) -> dict:
    ran = [r for r in runs if r.state == RAN]  # a cached run (same key as another subject's) carries its wall_s
    per_run_ms = 1000 * wall * SLOTS / len(ran)
    stage_ms = 1000 * statistics.mean(r.wall_s for r in ran)
    return {"wall_s": round(wall, 2), "stage_runs": len(ran), "per_stage_run_slot_ms": round(per_run_ms, 1),
            "stage_process_ms_mean": round(stage_ms, 1), "overhead_ms": round(per_run_ms - stage_ms, 1)}


def _median_run(results: list[dict]) -> dict:
    """The repeat with the median wall time, plus every repeat's wall time."""
    ordered = sorted(results, key=lambda r: r["wall_s"])
    return {**ordered[len(ordered) // 2], "wall_s_all": [r["wall_s"] for r in results]}


def bench(n_inputs: int, repeats: int) -> dict:
    """Local and Ray runs alternate, each into a fresh store, after Ray has started (so both run
    beside the same idle Ray processes, and machine load drifting during the benchmark hits both)."""
    import ray

    from humanvdm_core.workflow.executors import RayExecutor

    with tempfile.TemporaryDirectory() as tmp:
        toy = ToyProject(Path(tmp))
        subjects = [toy.subject(f"s{i:03d}", f"input number {i} " * (i % 7 + 1)) for i in range(n_inputs)]
        t0 = time.perf_counter()
        ray.init(num_cpus=SLOTS, include_dashboard=False, log_to_driver=False)
        init_s = time.perf_counter() - t0
        try:
            noop = ray.remote(lambda: None)
            ray.get([noop.remote() for _ in range(4)])  # start the workers
            trips = []
            for _ in range(50):
                t0 = time.perf_counter()
                ray.get(noop.remote())
                trips.append(time.perf_counter() - t0)
            local, on_ray, stores = [], [], {}
            for rep in range(repeats):
                for name, kw in (("local", {"jobs": SLOTS}), ("ray", {"jobs": RAY_JOBS, "executor": RayExecutor()})):
                    store = stores[name] = Store(Path(tmp) / f"{name}-{rep}")
                    for s in subjects:
                        store.import_path(s.source)
                    wall, runs = _timed_run(toy, store, subjects, **kw)
                    (local if name == "local" else on_ray).append(_per_run(wall, runs))
            local_rerun, _ = _timed_run(toy, stores["local"], subjects, jobs=SLOTS)
            ray_rerun, rerun_runs = _timed_run(toy, stores["ray"], subjects, jobs=RAY_JOBS, executor=RayExecutor())
            assert all(r.state == CACHED for r in rerun_runs)
        finally:
            ray.shutdown()

        def entries(store: Store, s) -> list[dict]:
            stages = read_lockfile(store, s.name)["stages"]
            return [{k: v for k, v in stages[st].items() if k not in ("wall_s", "peak_rss_mb")} for st in sorted(stages)]

        same = all(entries(stores["local"], s) == entries(stores["ray"], s) for s in subjects)
        local_m, ray_m = _median_run(local), _median_run(on_ray)
        ray_m.update({"ray_init_s": round(init_s, 2), "jobs_in_flight": RAY_JOBS,
                      "noop_task_roundtrip_ms_median": round(1000 * statistics.median(trips), 2)})
        return {"inputs": n_inputs, "stages": 3, "slots": SLOTS, "repeats": repeats,
                "local_jobs_2": local_m, "ray_2_cpus": ray_m,
                "ray_extra_ms_per_stage_run": round(ray_m["per_stage_run_slot_ms"] - local_m["per_stage_run_slot_ms"], 1),
                "ray_extra_executor_overhead_ms": round(ray_m["overhead_ms"] - local_m["overhead_ms"], 1),
                "cached_rerun_s": {"local": round(local_rerun, 2), "ray": round(ray_rerun, 2)},
                "lockfiles_equal_but_timings": same}


def main(argv: list[str] | None = None) -> dict | None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--inputs", type=int, default=100)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)
    try:
        import ray  # noqa: F401
    except ImportError:
        print("bench_ray: Ray is not installed (pip install -e '.[cluster]'); skipped")
        return None
    result = bench(args.inputs, args.repeats)
    save_result("ray", result, command=f"python -m benchmarks.bench_ray --inputs {args.inputs} --repeats {args.repeats}")
    print(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()

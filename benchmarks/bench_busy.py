"""splat-optimize on a busy machine: seconds per training step alone and beside one CPU-bound process.

A synthetic subject's 81-view orbit (``bench_splat.prepare_subject``, 512² renders, its true body) is
trained with the ``cpu`` preset's model size (body template, UV 128, 192² views, 2 views a step) for
``--iterations`` steps in a fresh process started the way the scheduler starts a stage: ``after``
with this tree's code and the scheduler's thread environment (:func:`humanvdm_core.workflow.threads.thread_env`:
the affinity's cores, passive OpenMP waiting); ``before`` (with ``--before-repo``, a checkout of the code
before that change) with that code and the environment the scheduler used to give (``OMP_NUM_THREADS``
= all cores, OpenMP's default spinning). Each is run alone and next to a pure-Python busy loop (one
core's worth of other work). Reported: median seconds per step (the first 2 steps, with any JIT
compile, excluded) and the slowdown ratio busy/alone.

Run:  .venv/bin/python benchmarks/bench_busy.py [--before-repo PATH] [--iterations 12]
Writes benchmarks/results/busy.json.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.common import save_result  # noqa: E402

CHILD = r"""
import json, sys, time
import numpy as np, torch
from humanvdm_core.splat import human as H
root, iterations = sys.argv[1], int(sys.argv[2])
anchor = H.load_body_anchor(root + "/body/body.npz", 128)
views = H.load_views(root + "/orbit", 192)
human = H.GaussianHuman(anchor, seed=0)
config = H.FitConfig(iterations=iterations, tile_size=8)
opt = torch.optim.Adam(human.parameters(), lr=1e-3)
times = []
for it in range(iterations):
    t0 = time.perf_counter()
    loss = H.training_loss(human, views, torch.as_tensor([it % 81, (it + 40) % 81]), config)
    opt.zero_grad()
    loss.backward()
    opt.step()
    times.append(time.perf_counter() - t0)
print(json.dumps({"median_s": float(np.median(times[2:])), "threads": torch.get_num_threads()}))
"""


def run_child(repo: Path, root: Path, iterations: int, env: dict[str, str], busy: bool) -> dict:
    hog = subprocess.Popen([sys.executable, "-c", "while True: pass"]) if busy else None
    try:
        r = subprocess.run([sys.executable, "-c", CHILD, str(root), str(iterations)], cwd=repo, capture_output=True,
                           text=True, env=dict(env, PYTHONPATH=str(repo)), timeout=3600)
    finally:
        if hog is not None:
            hog.kill()
            hog.wait()
    if r.returncode:
        raise RuntimeError(r.stderr[-2000:])
    return json.loads(r.stdout.strip().splitlines()[-1])


def main() -> None:
    from benchmarks.bench_splat import prepare_subject
    from humanvdm_core.workflow.threads import THREAD_VARS, available_cores, stage_threads, thread_env

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--before-repo", type=Path, default=None, help="a checkout of the code before the change")
    ap.add_argument("--iterations", type=int, default=12)
    args = ap.parse_args()
    clean = {k: v for k, v in os.environ.items() if k not in THREAD_VARS + ("OMP_WAIT_POLICY", "KMP_BLOCKTIME")}
    variants = {"after": (REPO, thread_env(stage_threads(1), clean))}
    if args.before_repo is not None:
        variants["before"] = (args.before_repo.resolve(), dict(clean, OMP_NUM_THREADS=str(os.cpu_count() or 1)))
    result: dict = {"cores": available_cores(), "iterations": args.iterations}
    with tempfile.TemporaryDirectory(prefix="bench_busy_") as tmp:
        subject = prepare_subject("synthetic", Path(tmp), 512, 64)
        for label, (repo, env) in variants.items():
            alone = run_child(repo, subject["root"], args.iterations, env, busy=False)
            busy = run_child(repo, subject["root"], args.iterations, env, busy=True)
            result[label] = {"alone_s_per_step": round(alone["median_s"], 3), "busy_s_per_step": round(busy["median_s"], 3),
                             "slowdown": round(busy["median_s"] / alone["median_s"], 2), "torch_threads": alone["threads"],
                             "env": {k: env[k] for k in THREAD_VARS + ("OMP_WAIT_POLICY",) if k in env}}
            print(label, result[label], flush=True)
    cmd = "python benchmarks/bench_busy.py" + (f" --before-repo {args.before_repo}" if args.before_repo else "")
    print(save_result("busy", result, command=cmd))


if __name__ == "__main__":
    main()

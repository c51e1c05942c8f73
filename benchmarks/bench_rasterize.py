"""Benchmark: the CPU Gaussian rasterizers, torch (pure PyTorch) vs numba (compiled compositing).

Scenes (``--scene``): N Gaussians on the surface of a 1.75 m body-like shape (ellipsoid torso, head, limbs)
at the origin, opacities 0.5-1, RGB colours; ``iso``: isotropic, every scale the mean surface spacing
sqrt(area / N), like splat-optimize's UV-texel Gaussians; ``aniso``: scales 5-10 mm per axis, random
rotations. One camera on a 3 m orbit at 10 deg elevation with the SV3D vertical FOV of 33.8 deg.

For each (N, image size) in ``--configs``, thread count in ``--threads`` and backend in ``--backends``, in
its own process with a stage's thread environment (:func:`humanvdm_core.workflow.threads.thread_env`:
OMP/MKL/NUMBA_NUM_THREADS, ``OMP_WAIT_POLICY=PASSIVE``), after one warm-up call, over ``--repeats``:

- ``forward_s``: ``rasterize_gaussians(..., backend=...)`` under ``torch.no_grad()`` (rendering);
- ``forward_backward_s``: the same with gradients enabled plus ``loss.backward()`` w.r.t. means, quats,
  scales, opacities, colours (one view of an optimisation step's rasterizer work);

medians, with every run and the fastest (``*_min_s``: the least disturbed by other work on a shared
machine), ``forward_cpu_s`` and ``forward_backward_cpu_s`` (median process CPU seconds: near 2x wall when
a second thread got a core; with one thread, the work done whatever the machine's load), the
tile-Gaussian intersections, ``peak_rss_mb`` and ``base_rss_mb`` (after building the
scene). ``speedups`` gives torch / numba per configuration (medians, fastest runs, CPU seconds). ``numba_compile`` times the first numba call
(forward + backward, a tiny scene) in a fresh process with an empty ``NUMBA_CACHE_DIR`` (compiling) and
again with that cache filled (loading).

Writes ``benchmarks/results/rasterize.json``.
Run: ``.venv/bin/python benchmarks/bench_rasterize.py [--repeats 5] [--configs 10000x192,200000x576]
[--threads 1,2] [--backends torch,numba] [--scene iso]``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))


def body_cloud(n: int, seed: int = 0, isotropic: bool = False):
    """(means, quats, scales, opacities, colors) for n Gaussians on a body-like union of ellipsoids;
    ``isotropic``: identity rotations and every scale the mean surface spacing sqrt(area / n)."""
    import torch

    g = torch.Generator().manual_seed(seed)
    # (centre xyz, radii xyz) in metres, y up; a standing person ~1.75 m tall centred at the origin.
    parts = torch.tensor([
        [0.0, 0.75, 0.0, 0.10, 0.12, 0.11],     # head
        [0.0, 0.30, 0.0, 0.19, 0.32, 0.12],     # torso
        [-0.26, 0.28, 0.0, 0.05, 0.30, 0.05],   # arms
        [0.26, 0.28, 0.0, 0.05, 0.30, 0.05],
        [-0.10, -0.45, 0.0, 0.08, 0.42, 0.08],  # legs
        [0.10, -0.45, 0.0, 0.08, 0.42, 0.08],
    ])
    # Approximate surface areas (Knud Thomsen's formula) to spread points evenly over the parts.
    a, b, c = parts[:, 3], parts[:, 4], parts[:, 5]
    p = 1.6075
    area = 4 * math.pi * (((a * b) ** p + (a * c) ** p + (b * c) ** p) / 3) ** (1 / p)
    part = torch.multinomial(area / area.sum(), n, replacement=True, generator=g)
    direction = torch.randn(n, 3, generator=g)
    direction = direction / direction.norm(dim=1, keepdim=True)
    means = parts[part, :3] + direction * parts[part, 3:]
    means[:, 1] = -means[:, 1]  # OpenCV world: y down
    quats = torch.randn(n, 4, generator=g)
    scales = 0.005 + 0.005 * torch.rand(n, 3, generator=g)
    if isotropic:
        quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(n, 1)
        scales = torch.full((n, 3), math.sqrt(float(area.sum()) / n))
    opacities = 0.5 + 0.5 * torch.rand(n, generator=g)
    colors = torch.rand(n, 3, generator=g)
    return means, quats, scales, opacities, colors


def orbit_camera(size: int, radius: float = 3.0, elevation_deg: float = 10.0, azimuth_deg: float = 30.0,
                 fov_deg: float = 33.8):
    """(viewmats (1,4,4), Ks (1,3,3)): OpenCV camera on an orbit around the origin looking at it (y down)."""
    import torch

    el, az = math.radians(elevation_deg), math.radians(azimuth_deg)
    eye = torch.tensor([radius * math.cos(el) * math.sin(az), -radius * math.sin(el),
                        -radius * math.cos(el) * math.cos(az)])
    forward = -eye / eye.norm()
    right = torch.linalg.cross(torch.tensor([0.0, 1.0, 0.0]), forward)  # world down x forward = right
    right = right / right.norm()
    down = torch.linalg.cross(forward, right)
    rot = torch.stack([right, down, forward])
    viewmat = torch.eye(4)
    viewmat[:3, :3] = rot
    viewmat[:3, 3] = -rot @ eye
    f = 0.5 * size / math.tan(math.radians(fov_deg) / 2)
    K = torch.tensor([[f, 0.0, size / 2], [0.0, f, size / 2], [0.0, 0.0, 1.0]])
    return viewmat[None], K[None]


def rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def run_one(n: int, size: int, threads: int, backend: str, scene: str, repeats: int) -> dict:
    import torch

    from humanvdm_core.splat import rasterize_gaussians

    torch.set_num_threads(threads)
    params = body_cloud(n, isotropic=scene == "iso")
    viewmats, Ks = orbit_camera(size)
    base = rss_mb()

    def step(grad: bool) -> tuple:
        leaves = [t.clone().requires_grad_(grad) for t in params]
        colors, alphas, meta = rasterize_gaussians(*leaves, viewmats, Ks, size, size, backend=backend)
        if grad:
            (colors.square().mean() + alphas.mean()).backward()
        return colors, alphas, meta

    step(True)  # warm-up: numba loads (or compiles) its kernels here
    fwd, fwd_bwd, fwd_cpu = [], [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        with torch.no_grad():
            colors, alphas, meta = step(False)
        fwd.append(time.perf_counter() - t0)
        fwd_cpu.append(time.process_time() - c0)
    fwd_bwd_cpu = []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        step(True)
        fwd_bwd.append(time.perf_counter() - t0)
        fwd_bwd_cpu.append(time.process_time() - c0)
    return {
        "backend": meta["backend"], "scene": scene, "n_gaussians": n, "size": size, "threads": threads,
        "forward_s": round(statistics.median(fwd), 4), "forward_backward_s": round(statistics.median(fwd_bwd), 4),
        "forward_min_s": round(min(fwd), 4), "forward_backward_min_s": round(min(fwd_bwd), 4),
        "forward_cpu_s": round(statistics.median(fwd_cpu), 4),
        "forward_backward_cpu_s": round(statistics.median(fwd_bwd_cpu), 4),
        "forward_runs_s": [round(t, 4) for t in fwd], "forward_backward_runs_s": [round(t, 4) for t in fwd_bwd],
        "n_intersections": meta["n_intersections"][0], "coverage": round(float((alphas > 0.5).float().mean()), 4),
        "base_rss_mb": round(base, 1),
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
        "loadavg_1min_at_end": round(os.getloadavg()[0], 2),
    }


def first_numba_call() -> dict:
    """Seconds of the first numba-backend forward + backward of a tiny scene in this process."""
    import torch

    from humanvdm_core.splat import rasterize_gaussians

    torch.set_num_threads(1)
    leaves = [t.requires_grad_(True) for t in body_cloud(500, isotropic=True)]
    viewmats, Ks = orbit_camera(64)
    t0 = time.perf_counter()
    colors, alphas, _ = rasterize_gaussians(*leaves, viewmats, Ks, 64, 64, backend="numba")
    (colors.sum() + alphas.sum()).backward()
    return {"first_call_s": round(time.perf_counter() - t0, 3)}


def _child(args: list[str], threads: int, **env: str) -> dict:
    from humanvdm_core.workflow.threads import thread_env

    out = subprocess.run([sys.executable, __file__, *args], env=thread_env(threads, dict(os.environ, **env),
                                                                             override=True),
                         capture_output=True, text=True, check=True, cwd=REPO)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--configs", default="10000x192,200000x576",
                    help="comma-separated NxSIZE: Gaussians x square image size")
    ap.add_argument("--threads", default="1,2")
    ap.add_argument("--backends", default="torch,numba")
    ap.add_argument("--scene", default="iso", choices=("iso", "aniso"))
    ap.add_argument("--one", help=argparse.SUPPRESS)  # internal: "n,size,threads,backend" -> JSON on stdout
    ap.add_argument("--first-call", action="store_true", help=argparse.SUPPRESS)  # internal
    args = ap.parse_args()
    if args.one:
        n, size, threads, backend = args.one.split(",")
        print(json.dumps(run_one(int(n), int(size), int(threads), backend, args.scene, args.repeats)))
        return
    if args.first_call:
        print(json.dumps(first_numba_call()))
        return

    from benchmarks.common import save_result

    result: dict = {"loadavg_at_start": os.getloadavg()}
    backends = args.backends.split(",")
    if "numba" in backends:
        with tempfile.TemporaryDirectory() as cache:
            cold = _child(["--first-call"], 1, NUMBA_CACHE_DIR=cache)["first_call_s"]
            warm = _child(["--first-call"], 1, NUMBA_CACHE_DIR=cache)["first_call_s"]
        result["numba_compile"] = {"cold_first_call_s": cold, "cached_first_call_s": warm}
        print(f"numba first call: {cold:.2f} s compiling, {warm:.2f} s from the cache", flush=True)
    rows = []
    print("| N | size | threads | backend | forward s | fwd+bwd s (min) | intersections | peak RSS |")
    for config in args.configs.split(","):
        n, size = (int(v) for v in config.split("x"))
        for threads in (int(v) for v in args.threads.split(",")):
            for backend in backends:
                row = _child(["--one", f"{n},{size},{threads},{backend}", "--repeats", str(args.repeats),
                              "--scene", args.scene], threads)
                rows.append(row)
                print(f"| {n} | {size}² | {threads} | {backend} | {row['forward_s']:.4f} | "
                      f"{row['forward_backward_s']:.4f} ({row['forward_backward_min_s']:.4f}) | "
                      f"{row['n_intersections']} | {row['peak_rss_mb']:.0f} MB |", flush=True)
    result["rows"] = rows
    speedups = []
    for row in rows:
        if row["backend"] != "numba":
            continue
        ref = [r for r in rows if r["backend"] == "torch" and all(r[k] == row[k] for k in
                                                                  ("n_gaussians", "size", "threads"))]
        if ref:
            speedups.append({k: row[k] for k in ("n_gaussians", "size", "threads")} | {
                "forward": round(ref[0]["forward_s"] / row["forward_s"], 2),
                "forward_backward": round(ref[0]["forward_backward_s"] / row["forward_backward_s"], 2),
                "forward_backward_min": round(ref[0]["forward_backward_min_s"] / row["forward_backward_min_s"], 2),
                "forward_backward_cpu": round(ref[0]["forward_backward_cpu_s"] / row["forward_backward_cpu_s"], 2),
            })
    result["speedups"] = speedups
    for sp in speedups:
        print(f"speedup torch/numba at {sp['n_gaussians']} x {sp['size']}², {sp['threads']} thread(s): "
              f"forward {sp['forward']}x, forward+backward {sp['forward_backward']}x "
              f"(fastest runs: {sp['forward_backward_min']}x; CPU seconds: {sp['forward_backward_cpu']}x)")
    command = "python benchmarks/bench_rasterize.py " + " ".join(sys.argv[1:])
    path = save_result("rasterize", result, command=command.strip())
    print(f"wrote {path}")


if __name__ == "__main__":
    main()

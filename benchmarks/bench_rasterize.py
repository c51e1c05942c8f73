"""Benchmark: the pure-PyTorch tiled Gaussian rasterizer on a human-sized cloud (CPU).

Scene: N Gaussians on the surface of a 1.75 m body-like shape (ellipsoid torso, head, limbs) at the
origin, scales 5-10 mm, random rotations, opacities 0.5-1, RGB colours; one camera on a 3 m orbit at 10 deg
elevation with the SV3D vertical FOV of 33.8 deg. For N in {20k, 200k}, image size in {256, 576} and
torch threads in {1, 2}, each configuration in its own process, the median over ``--repeats`` of

- ``forward_s``: ``rasterize_gaussians(..., backend="torch")`` under ``torch.no_grad()`` (rendering);
- ``forward_backward_s``: the same with gradients enabled plus ``loss.backward()`` w.r.t. means, quats,
  scales, opacities, colours (one optimisation step's rasterizer work);

and ``peak_rss_mb`` (the process's peak resident memory, torch and the scene included) with
``base_rss_mb`` (resident memory after building the scene, before the first render), plus the number
of tile-Gaussian intersections. The machine may be shared: the load average at the start and after each
configuration is recorded, and ``forward_cpu_s`` (process CPU seconds of the median forward) shows
whether a second thread actually got a core (cpu/wall near 2) or waited (near or below 1).

Writes ``benchmarks/results/rasterize.json``.
Run: ``.venv/bin/python benchmarks/bench_rasterize.py [--repeats 3] [--sizes 20000,200000] [--res 256,576]``.
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
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))


def body_cloud(n: int, seed: int = 0):
    """(means, quats, scales, opacities, colors) for n Gaussians on a body-like union of ellipsoids."""
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


def run_one(n: int, size: int, threads: int, repeats: int) -> dict:
    import torch

    from humanvdm_core.splat import rasterize_gaussians

    torch.set_num_threads(threads)
    params = body_cloud(n)
    viewmats, Ks = orbit_camera(size)
    base = rss_mb()

    def forward() -> tuple:
        return rasterize_gaussians(*params, viewmats, Ks, size, size, backend="torch")

    fwd, fwd_bwd, fwd_cpu = [], [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        with torch.no_grad():
            colors, alphas, meta = forward()
        fwd.append(time.perf_counter() - t0)
        fwd_cpu.append(time.process_time() - c0)
    leaves = [t.clone().requires_grad_(True) for t in params]
    for _ in range(repeats):
        t0 = time.perf_counter()
        colors, alphas, _ = rasterize_gaussians(*leaves, viewmats, Ks, size, size, backend="torch")
        (colors.square().mean() + alphas.mean()).backward()
        fwd_bwd.append(time.perf_counter() - t0)
        for t in leaves:
            t.grad = None
    return {
        "n_gaussians": n, "size": size, "threads": threads,
        "forward_s": round(statistics.median(fwd), 4), "forward_backward_s": round(statistics.median(fwd_bwd), 4),
        "forward_cpu_s": round(statistics.median(fwd_cpu), 4), "forward_runs_s": [round(t, 4) for t in fwd], "forward_backward_runs_s": [round(t, 4) for t in fwd_bwd],
        "n_intersections": meta["n_intersections"][0], "coverage": round(float((alphas > 0.5).float().mean()), 4),
        "base_rss_mb": round(base, 1),
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
        "loadavg_1min_at_end": round(os.getloadavg()[0], 2),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--sizes", default="20000,200000", help="numbers of Gaussians, comma-separated")
    ap.add_argument("--res", default="256,576", help="square image sizes, comma-separated")
    ap.add_argument("--threads", default="1,2")
    ap.add_argument("--one", help=argparse.SUPPRESS)  # internal: "n,size,threads" -> JSON on stdout
    args = ap.parse_args()
    if args.one:
        n, size, threads = (int(v) for v in args.one.split(","))
        print(json.dumps(run_one(n, size, threads, args.repeats)))
        return

    from benchmarks.common import save_result

    load = os.getloadavg()
    rows = []
    for n in (int(v) for v in args.sizes.split(",")):
        for size in (int(v) for v in args.res.split(",")):
            for threads in (int(v) for v in args.threads.split(",")):
                env = dict(os.environ, OMP_NUM_THREADS=str(threads))
                out = subprocess.run([sys.executable, __file__, "--one", f"{n},{size},{threads}",
                                      "--repeats", str(args.repeats)], env=env, capture_output=True, text=True,
                                     check=True, cwd=REPO)
                row = json.loads(out.stdout.strip().splitlines()[-1])
                rows.append(row)
                print(f"| {n} | {size}² | {threads} | {row['forward_s']:.3f} | {row['forward_backward_s']:.3f} | "
                      f"{row['n_intersections']} | {row['peak_rss_mb']:.0f} MB |", flush=True)
    command = "python benchmarks/bench_rasterize.py " + " ".join(sys.argv[1:])
    path = save_result("rasterize", {"loadavg_at_start": load, "rows": rows}, command=command.strip())
    print(f"wrote {path}")


if __name__ == "__main__":
    main()

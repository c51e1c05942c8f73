"""Benchmark: seconds to render a 21-view SV3D orbit at 576^2 (RGBA + depth + normals).

Meshes: the RenderPeople fixture scan (30k faces) and the same scan subdivided once (120k faces)
when ``../shared/fixtures`` is present, and the procedural person tessellated to about 100k faces
(always). For each: the median over ``--repeats`` of

- ``render_s``: :func:`humanvdm_core.render.Renderer.render` with a warm context (mesh upload,
  21 draws + resolves, read-back; what a stage pays per subject after the first), and
  ``render_cpu_s``, the CPU seconds of all the process's threads for it (llvmpipe rasterizes on
  every core; its geometry stage is single-threaded), which load on a shared machine disturbs less;
- ``render_with_context_s``: a new GL context created, then the same render (what one stage run
  pays, less imports and scan loading);

plus ``first_context_s`` (the first context in the process, EGL/llvmpipe start-up included) and
each mesh's ``load_s`` (:func:`humanvdm_core.scans.load_scan`). The load average at the start is
recorded: the machine may be shared, which inflates every number.

Writes ``benchmarks/results/render.json`` and prints one markdown table row per mesh.
Run: ``.venv/bin/python benchmarks/bench_render.py [--repeats 3] [--samples 4]``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

RESULTS = REPO / "benchmarks" / "results" / "render.json"
RENDERPEOPLE = REPO.parent / "shared" / "fixtures" / "scans" / "renderpeople_rp_mei_posed_001"


def _meshes() -> list[tuple[str, object, float]]:
    """(name, normalised TexturedMesh, load seconds) for every benchmark mesh available here."""
    import trimesh

    from humanvdm_core.scans import TexturedMesh, load_scan, normalize_scan
    from testdata.procedural import make_person

    out = []
    if RENDERPEOPLE.is_dir():
        t0 = time.perf_counter()
        scan = load_scan(RENDERPEOPLE)
        load_s = time.perf_counter() - t0
        out.append(("renderpeople_30k", normalize_scan(scan), load_s))
        v, f, attrs = trimesh.remesh.subdivide(scan.vertices, scan.faces, vertex_attributes={"uv": scan.uvs})
        fine = TexturedMesh(v, f, uvs=attrs["uv"], texture=scan.texture)
        out.append(("renderpeople_subdivided_120k", normalize_scan(fine), float("nan")))
    t0 = time.perf_counter()
    person = make_person(segments=87)
    out.append(("procedural_person_100k", normalize_scan(person), time.perf_counter() - t0))
    return out


def run(repeats: int = 3, samples: int = 4, views: int = 21, size: int = 576) -> dict:
    from humanvdm_core.cameras import orbit_cameras
    from humanvdm_core.render import Renderer
    from humanvdm_core.scans import framing_radius

    load_avg = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    t0 = time.perf_counter()
    renderer = Renderer(samples)
    first_context_s = time.perf_counter() - t0
    cameras = orbit_cameras(views, size, radius=framing_radius())
    rows = []
    for name, mesh, load_s in _meshes():
        renderer.render(mesh, cameras.subset([0]))  # warm-up: shader compile, framebuffers
        warm, cpu = [], []
        for _ in range(repeats):
            t0, c0 = time.perf_counter(), time.process_time()
            renderer.render(mesh, cameras)
            warm.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
        cold = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            fresh = Renderer(samples)
            fresh.render(mesh, cameras)
            cold.append(time.perf_counter() - t0)
            fresh.release()
        rows.append({
            "mesh": name, "faces": int(mesh.num_faces), "vertices": int(len(mesh.vertices)),
            "texture": None if mesh.texture is None else list(mesh.texture.shape[:2]),
            "load_s": None if load_s != load_s else round(load_s, 3),
            "render_s": round(statistics.median(warm), 3), "render_s_all": [round(t, 3) for t in warm],
            "render_cpu_s": round(statistics.median(cpu), 3),
            "render_with_context_s": round(statistics.median(cold), 3),
            "render_with_context_s_all": [round(t, 3) for t in cold],
        })
    gl_renderer = str(renderer.ctx.info.get("GL_RENDERER", "?"))
    renderer.release()
    return {
        "benchmark": "render-training-orbits renderer",
        "views": views, "resolution": size, "msaa_samples": samples, "repeats": repeats,
        "first_context_s": round(first_context_s, 3),
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count(), "load_avg_1min_at_start": load_avg,
                    "gl_renderer": gl_renderer},
        "results": rows,
    }


def markdown(report: dict) -> str:
    lines = [f"| mesh | faces | {report['views']} views {report['resolution']}² warm (s) | CPU (s) "
             "| with new context (s) |", "|---|---|---|---|---|"]
    for r in report["results"]:
        lines.append(f"| {r['mesh']} | {r['faces']:,} | {r['render_s']:.2f} | {r['render_cpu_s']:.2f} "
                     f"| {r['render_with_context_s']:.2f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--samples", type=int, default=4)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    report = run(args.repeats, args.samples)
    report["markdown"] = markdown(report)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2) + "\n")
    print(report["markdown"])
    print(f"first GL context: {report['first_context_s']:.2f} s; load average at start "
          f"{report['machine']['load_avg_1min_at_start']:.2f} on {report['machine']['cpus']} CPUs; wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Benchmark of the ``diffuse`` stage's ``body-prior`` backend (``humanvdm_core.body_prior``) on the
fixture photos and on stress cases, with contact sheets to look at.

Inputs: every photo in ../shared/fixtures/photos (``*_mask`` files are ground truth, not inputs) and
the stress cases in ``--cases`` (made once by ``--make-cases``, so a run of older code reads the very
same photos): the RenderPeople scans rendered from the front, from behind, turned by 35 deg and in profile;
synthetic subjects with a skirt and long hair, a gown, a seated pose and hands on the hips
(:data:`testdata.synthetic.GARMENT_EXAMPLES`). At ``--size`` (576, the SV3D resolution) with
``--iterations`` fit steps (150, the stage's default), one thread, per input:

- ``ok`` / ``error``: whether it ran (a user-facing error is recorded, not raised);
- ``seconds``: the whole photo -> 21 frames (detection, fit, proxy, rendering), the first input
  including the one-off imports and model loading (``first_photo_s`` in the summary);
- ``proxy_iou``: silhouette IoU of the proxy rendered at azimuth 0 vs the preprocessed photo's mask
  (how much of the person the orbit keeps); ``side_coverage``: fraction of the azimuth-~90 frame
  the person covers; ``warnings``: what the run says it guessed; ``side_roughness``: the mean change of the
  proxy's rendered normal between neighbouring image rows, over its silhouette (eroded 2 px) seen from
  azimuth 60, 90, 120, 240, 270 and 300 at 768² (:func:`side_roughness`): ridges along the proxy grid's
  rows raise it (the fitted naked body alone reads 0.033-0.036);
- a contact sheet row (input | orbit at azimuth ~0, ~86, ~171, ~274) in
  ``benchmarks/results/diffuse_<label>.png`` and one image per input ``diffuse_<name>[_<label>].png``.

Run:  .venv/bin/python -m benchmarks.bench_diffuse [--make-cases] [--label after|before]
Writes benchmarks/results/diffuse.json (label ``after``) or diffuse_<label>.json.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import cv2  # noqa: E402
import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.common import RESULTS, save_result  # noqa: E402

FIXTURES = REPO.parent / "shared" / "fixtures"
PHOTOS = FIXTURES / "photos"
CASES = Path("/tmp/humanvdm_diffuse_cases")
SHEET_FRAMES = (20, 4, 9, 15)  # azimuth 0 (the input view), ~86, ~171, ~274
CELL = 192


def make_cases(out: Path) -> list[Path]:
    """Render the stress cases as PNG photos (RGB over white, 768²) into ``out``."""
    from humanvdm_core.cameras import orbit_cameras
    from humanvdm_core.io import write_png
    from humanvdm_core.render import render_views
    from humanvdm_core.scans import framing_radius, load_scan, normalize_scan
    from testdata.synthetic import GARMENT_EXAMPLES, SubjectSpec, make_subject

    out.mkdir(parents=True, exist_ok=True)
    meshes = {}
    scans = FIXTURES / "scans"
    for name, folder in (("mei", "renderpeople_rp_mei_posed_001"), ("eric", "renderpeople_rp_eric_rigged_001")):
        if (scans / folder).is_dir():
            meshes[name] = normalize_scan(load_scan(scans / folder))
    views = {f"{n}_{tag}": (mesh, az) for n, mesh in meshes.items() for tag, az in (("front", 0.0), ("back", 180.0),
                                                                                        ("turned35", 35.0),
                                                                                        ("profile", 90.0))}
    work = out / "subjects"
    specs = dict(GARMENT_EXAMPLES)
    specs["seated"] = SubjectSpec(pose="seated", seed=5)
    specs["hands_on_hips"] = SubjectSpec(pose="hands-on-hips", seed=6)
    for name, spec in specs.items():
        views[f"synthetic_{name}"] = (normalize_scan(load_scan(make_subject(spec, work / name, texture_size=512))), 0.0)
    paths = []
    for name, (mesh, az) in views.items():
        cam = orbit_cameras(1, 768, 33.8, 10.0, framing_radius(), azimuths_deg=np.array([az]))
        path = out / f"{name}.png"
        write_png(path, render_views(mesh, cam, (1.0, 1.0, 1.0)).rgba[0, ..., :3])
        paths.append(path)
    return paths


def sheet_row(photo: Path, frames: np.ndarray | None) -> np.ndarray:
    """input | orbit frames at SHEET_FRAMES, each CELL², RGB float."""
    from humanvdm_core.perception import load_photo

    rgb = load_photo(photo).rgb
    h, w = rgb.shape[:2]
    s = CELL / max(h, w)
    small = cv2.resize(rgb, (max(1, round(w * s)), max(1, round(h * s))), interpolation=cv2.INTER_AREA)
    cell = np.ones((CELL, CELL, 3), np.float32)
    y, x = (CELL - small.shape[0]) // 2, (CELL - small.shape[1]) // 2
    cell[y:y + small.shape[0], x:x + small.shape[1]] = small
    cells = [cell]
    for i in SHEET_FRAMES:
        if frames is None:
            cells.append(np.full((CELL, CELL, 3), 0.5, np.float32))
        else:
            cells.append(cv2.resize(frames[i, ..., :3], (CELL, CELL), interpolation=cv2.INTER_AREA))
    row = (np.clip(np.concatenate(cells, axis=1), 0, 1) * 255 + 0.5).astype(np.uint8)
    cv2.putText(row, photo.stem[:40], (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (200, 0, 0), 1, cv2.LINE_AA)
    return row.astype(np.float32) / 255.0


def side_roughness(proxy, size: int = 768) -> float:
    """The mean change of ``proxy``'s rendered normal (radians, nearly) between neighbouring image rows over
    its silhouette, eroded 2 px, from azimuth 60, 90, 120, 240, 270 and 300 at ``size``² (the orbit's
    elevation and radius): what the side views show of ridges along the proxy grid's rows."""
    from humanvdm_core.cameras import orbit_cameras
    from humanvdm_core.render import render_views
    from humanvdm_core.scans import framing_radius

    azimuths = np.array([60.0, 90.0, 120.0, 240.0, 270.0, 300.0])
    cams = orbit_cameras(len(azimuths), size, elevation_deg=float(proxy.cameras.elevation_deg[0]),
                         radius=framing_radius(), azimuths_deg=azimuths)
    seen = render_views(proxy.mesh, cams, (1.0, 1.0, 1.0))
    change = []
    for rgba, normals in zip(seen.rgba, seen.normals, strict=True):
        inside = cv2.erode((rgba[..., 3] > 0.5).astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
        both = inside[1:] & inside[:-1]
        change.append(float(np.linalg.norm(normals[1:] - normals[:-1], axis=-1)[both].mean()))
    return float(np.mean(change))


def main() -> None:
    import torch

    from humanvdm_core.body_prior import build_body_proxy
    from humanvdm_core.io import write_png
    from humanvdm_core.workflow.errors import HumanVDMError

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--size", type=int, default=576)
    parser.add_argument("--iterations", type=int, default=150)
    parser.add_argument("--cases", type=Path, default=CASES, help="folder of stress-case photos")
    parser.add_argument("--make-cases", action="store_true", help="(re)render the stress cases first")
    parser.add_argument("--label", default="after", help="after (diffuse.json) or another label (diffuse_<label>.json)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    if args.make_cases or not args.cases.is_dir():
        make_cases(args.cases)
    photos = sorted(p for p in PHOTOS.glob("*.png") if not p.stem.endswith("_mask")) if PHOTOS.is_dir() else []
    photos += sorted(args.cases.glob("*.png"))
    if not photos:
        print(f"no fixture photos in {PHOTOS} and no cases in {args.cases}; nothing to do")
        return
    suffix = "" if args.label == "after" else f"_{args.label}"
    per_photo: dict[str, dict] = {}
    rows = []
    for photo in photos:
        t0 = time.perf_counter()
        try:
            proxy = build_body_proxy(photo, size=args.size, iterations=args.iterations)
            frames = proxy.orbit_frames()
        except HumanVDMError as e:
            per_photo[photo.stem] = {"ok": False, "error": str(e), "seconds": round(time.perf_counter() - t0, 2)}
            print(f"{photo.name}: error: {e}")
            rows.append(sheet_row(photo, None))
            continue
        seconds = time.perf_counter() - t0
        cams = proxy.cameras
        side = int(np.argmin(np.abs(cams.azimuth_deg - 90.0)))
        raw_front = proxy.render(cams.subset([proxy.front_index]))[0, ..., 3] > 0.5
        mask = proxy.input_view.mask > 0.5
        iou = float((raw_front & mask).sum() / max(1, (raw_front | mask).sum()))
        row = sheet_row(photo, frames)
        rows.append(row)
        write_png(RESULTS / f"diffuse_{photo.stem}{suffix}.png", row)
        per_photo[photo.stem] = {
            "ok": True, "seconds": round(seconds, 2), "proxy_iou": round(iou, 3),
            "reprojection_px": round(proxy.reprojection_px, 2),
            "side_coverage": round(float((frames[side, ..., 3] > 0.5).mean()), 4),
            "side_roughness": round(side_roughness(proxy), 4),
            "warnings": proxy.warnings,
        }
        print(f"{photo.name}: {seconds:.1f} s, IoU {iou:.3f}, reprojection {proxy.reprojection_px:.1f} px; "
              f"{len(proxy.warnings)} warning(s)")
    write_png(RESULTS / f"diffuse_contact{suffix or '_after'}.png", np.concatenate(rows, axis=0))
    timed = [v["seconds"] for v in per_photo.values() if v["ok"]]
    rough = [v["side_roughness"] for v in per_photo.values() if v["ok"]]
    result = {
        "size": args.size, "iterations": args.iterations, "num_frames": 21, "threads": 1,
        "photos": per_photo,
        "first_photo_s": timed[0] if timed else None,
        "median_s_after_first": float(np.median(timed[1:])) if len(timed) > 1 else None,
        "median_side_roughness": float(np.median(rough)) if rough else None,
    }
    cmd = f".venv/bin/python -m benchmarks.bench_diffuse --size {args.size} --iterations {args.iterations} --label {args.label}"
    print(save_result("diffuse" + suffix, result, cmd))


if __name__ == "__main__":
    main()

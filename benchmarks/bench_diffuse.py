"""Benchmark of the ``diffuse`` stage's ``body-prior`` backend (``humanvdm_core.body_prior``) on the
fixture photos.

Per photo in ../shared/fixtures/photos (``*_mask`` files are ground truth, not inputs), at
``--size`` (default 576, the SV3D resolution) with ``--iterations`` fit steps (default 150, the
stage's default), one thread:

- ``ok`` / ``error``: whether it ran (a user-facing error is recorded, not raised);
- ``seconds``: the whole photo -> 21 frames (detection, fit, colouring, rendering), the first photo
  including the one-off imports and model loading (``first_photo_s`` in the summary);
- ``proxy_iou``: silhouette IoU of the coloured body rendered at azimuth 0 vs the preprocessed
  photo's mask (how well the single-view fit covers the person); ``reprojection_px``;
- ``side_coverage``: fraction of the azimuth-~90 frame the person covers;
- a strip of 5 orbit frames (azimuths 0 = the input view, then ~86, ~171, ~206, ~274) saved as
  ``benchmarks/results/diffuse_<name>.png`` (~600 px wide).

Run:  .venv/bin/python benchmarks/bench_diffuse.py [--size 576] [--iterations 150]
Writes benchmarks/results/diffuse.json.
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

PHOTOS = REPO.parent / "shared" / "fixtures" / "photos"
STRIP_FRAMES = (20, 4, 8, 11, 15)  # azimuth 0 (the input view), then around the orbit
STRIP_WIDTH = 600


def strip(frames: np.ndarray, path: Path) -> None:
    """The STRIP_FRAMES side by side, ~STRIP_WIDTH px wide, as a PNG."""
    from humanvdm_core.io import write_png

    tile = STRIP_WIDTH // len(STRIP_FRAMES)
    tiles = [cv2.resize(np.clip(frames[i, ..., :3], 0, 1), (tile, tile), interpolation=cv2.INTER_AREA)
             for i in STRIP_FRAMES if i < len(frames)]
    write_png(path, np.concatenate(tiles, axis=1))


def main() -> None:
    import torch

    from humanvdm_core.body_prior import build_body_proxy
    from humanvdm_core.errors import HumanVDMError

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--size", type=int, default=576)
    parser.add_argument("--iterations", type=int, default=150)
    args = parser.parse_args()
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    photos = sorted(p for p in PHOTOS.glob("*.png") if not p.stem.endswith("_mask")) if PHOTOS.is_dir() else []
    if not photos:
        print(f"no fixture photos in {PHOTOS}; nothing to do")
        return
    per_photo: dict[str, dict] = {}
    for photo in photos:
        t0 = time.perf_counter()
        try:
            proxy = build_body_proxy(photo, size=args.size, iterations=args.iterations)
            frames = proxy.orbit_frames()
        except HumanVDMError as e:
            per_photo[photo.stem] = {"ok": False, "error": str(e), "seconds": round(time.perf_counter() - t0, 2)}
            print(f"{photo.name}: error: {e}")
            continue
        seconds = time.perf_counter() - t0
        cams = proxy.cameras
        side = int(np.argmin(np.abs(cams.azimuth_deg - 90.0)))
        raw_front = proxy.render(cams.subset([proxy.front_index]))[0, ..., 3] > 0.5
        mask = proxy.input_view.mask > 0.5
        iou = float((raw_front & mask).sum() / max(1, (raw_front | mask).sum()))
        strip(frames, RESULTS / f"diffuse_{photo.stem}.png")
        per_photo[photo.stem] = {
            "ok": True, "seconds": round(seconds, 2), "proxy_iou": round(iou, 3),
            "reprojection_px": round(proxy.reprojection_px, 2),
            "side_coverage": round(float((frames[side, ..., 3] > 0.5).mean()), 4),
            "warnings": proxy.warnings,
        }
        print(f"{photo.name}: {seconds:.1f} s, IoU {iou:.3f}, reprojection {proxy.reprojection_px:.1f} px")
    timed = [v["seconds"] for v in per_photo.values() if v["ok"]]
    result = {
        "size": args.size, "iterations": args.iterations, "num_frames": 21, "threads": 1,
        "photos": per_photo,
        "first_photo_s": timed[0] if timed else None,
        "median_s_after_first": float(np.median(timed[1:])) if len(timed) > 1 else None,
    }
    cmd = f".venv/bin/python benchmarks/bench_diffuse.py --size {args.size} --iterations {args.iterations}"
    print(save_result("diffuse", result, cmd))


if __name__ == "__main__":
    main()

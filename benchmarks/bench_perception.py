"""Benchmark of person perception (``humanvdm_core.perception``) on the fixture photos.

Per photo in ../shared/fixtures/photos (skipped with a message when absent; ``*_mask`` files are
ground truth, not inputs):

- ``load_s``: seconds for ``load_photo``; ``detect_s``: seconds for ``detect_person``, the median
  of ``--repeats`` runs, and ``detect_first_s``: the very first run in this process (it includes
  importing MediaPipe and building its graphs);
- ``mask_source`` (alpha or segmentation), ``num_people``, ``confident_keypoints`` (of 17, confidence
  >= 0.5), ``warnings``;
- ``mask_iou``: IoU of ``mask > 0.5`` with the ground-truth mask ``<name>_mask.png`` when it exists;
- for photos with a real alpha cut-out, the alpha is dropped and the segmentation path's mask is
  compared with the alpha (a second, pseudo ground truth): ``segmentation_iou_vs_alpha`` on the RGB
  composited over black, ``segmentation_iou_vs_alpha_raw_rgb`` on the file's RGB as stored (whatever
  background it holds under the transparent pixels: a red blur for pshuman_3930);
- ``baselines``: the same IoUs for the raw masks of MediaPipe's selfie segmentation (general model)
  and of the pose model's segmentation without the guided-filter refinement, both bilinearly
  upsampled: why the default is the pose's mask, refined.

``composites``: opaque photos with a known silhouette, as a camera gives them: each photo with an alpha
cut-out and each scan in ../shared/fixtures/scans (rendered at azimuth 0, elevation 10 deg, 768²; the
stylised Soldier left out) composited over white, a plain wall with a floor, and clutter
(``benchmarks.stability.clutter_background``); per composite the segmentation's IoU with the alpha
and its false positives / negatives (share of the true silhouette), the PSNR of the photo over white
through the mask against the subject over white (the input view, on the person's box), untrimmed
(``trim=False``) and trimmed (the default, ``trim_background``), and the seconds of each
``detect_person``.

Run:  .venv/bin/python benchmarks/bench_perception.py [--repeats 3]
Writes benchmarks/results/perception.json.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.common import save_result  # noqa: E402
from humanvdm_core.perception import Photo, detect_person, load_photo  # noqa: E402

PHOTOS = REPO.parent / "shared" / "fixtures" / "photos"


def iou(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a > 0.5, b > 0.5
    return float((a & b).sum() / max(1, (a | b).sum()))


def baselines(rgb: np.ndarray, truth: np.ndarray) -> dict:
    """IoU of the raw MediaPipe masks (no refinement) with ``truth``."""
    from mediapipe.python.solutions import pose, selfie_segmentation

    h, w = truth.shape
    s = min(1.0, 1024 / max(h, w))
    work = cv2.resize(rgb, (round(w * s), round(h * s)), interpolation=cv2.INTER_AREA) if s < 1 else rgb
    work = np.ascontiguousarray(np.clip(np.rint(work * 255), 0, 255).astype(np.uint8))
    with selfie_segmentation.SelfieSegmentation(model_selection=0) as model:
        selfie = model.process(work).segmentation_mask
    with pose.Pose(static_image_mode=True, model_complexity=1, enable_segmentation=True) as model:
        pose_mask = model.process(work).segmentation_mask
    up = lambda m: cv2.resize(np.asarray(m, np.float32), (w, h), interpolation=cv2.INTER_LINEAR)  # noqa: E731
    return {"selfie_segmentation_raw": round(iou(up(selfie), truth), 4),
            "pose_segmentation_raw": round(iou(up(pose_mask), truth), 4)}


def bench_photo(path: Path, repeats: int) -> dict:
    t = time.perf_counter()
    photo = load_photo(path)
    load_s = time.perf_counter() - t
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        det = detect_person(photo)
        times.append(time.perf_counter() - t)
    row = {
        "size": [photo.width, photo.height],
        "load_s": round(load_s, 4),
        "detect_s": round(statistics.median(times), 4),
        "mask_source": det.mask_source,
        "num_people": det.num_people,
        "confident_keypoints": int(det.confident().sum()),
        "warnings": det.warnings,
    }
    gt_path = path.with_name(f"{path.stem}_mask.png")
    if gt_path.is_file():
        gt = cv2.imread(str(gt_path), cv2.IMREAD_GRAYSCALE) / 255.0
        row["mask_iou"] = round(iou(det.mask, gt), 4)
        row["baselines"] = {"mask_iou": baselines(photo.rgb, gt)}
    if det.mask_source == "alpha":
        row["baselines"] = {}
        for key, rgb in (("segmentation_iou_vs_alpha", photo.rgb * photo.alpha[:, :, None]),
                         ("segmentation_iou_vs_alpha_raw_rgb", photo.rgb)):
            flat = Photo(rgb=np.ascontiguousarray(rgb), alpha=None, path=photo.path,
                         original_size=photo.original_size)
            row[key] = round(iou(detect_person(flat).mask, photo.alpha), 4)
            row["baselines"][key] = baselines(flat.rgb, photo.alpha)
    return row


BACKGROUNDS = ("white", "wall", "clutter")


def background(kind: str, height: int, width: int) -> np.ndarray:
    """(H, W, 3) float: plain white, a warm wall with a darker floor (its lowest tenth), or clutter."""
    if kind == "white":
        return np.ones((height, width, 3), np.float32)
    if kind == "wall":
        img = np.empty((height, width, 3), np.float32)
        img[:] = (0.78, 0.74, 0.66)
        img[int(0.9 * height):] = (0.45, 0.36, 0.28)
        return img
    from benchmarks.stability import clutter_background

    return clutter_background(height, width)


def cutouts() -> dict[str, np.ndarray]:
    """Name -> (H, W, 4) float RGBA: the fixture photos with an alpha cut-out and the scans' front renders."""
    out = {}
    for path in sorted(PHOTOS.glob("*.png")):
        photo = load_photo(path)
        if photo.alpha is not None and 0.01 <= float(np.mean(photo.alpha < 0.5)) <= 0.99:
            out[path.stem] = np.dstack([photo.rgb, photo.alpha])
    from benchmarks.bench_pipeline import ELEVATION, WHITE
    from benchmarks.bench_protocol import SCANS, find_scans
    from humanvdm_core.cameras import orbit_cameras
    from humanvdm_core.render import render_views
    from humanvdm_core.scans import framing_radius, load_scan, normalize_scan

    if SCANS.is_dir():
        cam = orbit_cameras(1, 768, elevation_deg=ELEVATION, radius=framing_radius(), azimuths_deg=np.array([0.0]))
        for folder in find_scans(None):
            if "soldier" in folder.name:
                continue
            out[folder.name] = render_views(normalize_scan(load_scan(folder)), cam, WHITE).rgba[0]
    return out


def bench_composites() -> dict:
    rows = {}
    for name, rgba in cutouts().items():
        truth = rgba[..., 3] > 0.5
        for kind in BACKGROUNDS:
            a = rgba[..., 3:]
            rgb = rgba[..., :3] * a + background(kind, *rgba.shape[:2]) * (1.0 - a)
            photo = Photo(rgb=np.ascontiguousarray(rgb, np.float32), alpha=None, path=Path(f"{name}_{kind}.png"),
                          original_size=(rgba.shape[1], rgba.shape[0]))
            over_white = rgba[..., :3] * a + (1.0 - a)
            ys, xs = np.nonzero(truth)
            box = (slice(max(0, ys.min() - 10), ys.max() + 11), slice(max(0, xs.min() - 10), xs.max() + 11))
            row = {}
            for label, trim in (("untrimmed", False), ("trimmed", True)):
                t = time.perf_counter()
                soft = detect_person(photo, trim=trim).mask
                seconds = time.perf_counter() - t
                mask = soft > 0.5
                view = rgb * soft[..., None] + (1.0 - soft[..., None])  # the input view: the photo over white
                mse = float(np.mean((view[box] - over_white[box]) ** 2))
                row[label] = {"iou": round(iou(mask, truth), 4),
                              "false_positive": round(float((mask & ~truth).sum() / truth.sum()), 4),
                              "false_negative": round(float((~mask & truth).sum() / truth.sum()), 4),
                              "input_view_psnr": round(10 * np.log10(1.0 / max(mse, 1e-10)), 2),
                              "detect_s": round(seconds, 3)}
            rows[f"{name}_{kind}"] = row
            print(f"{name}_{kind}", row)
    means = {label: {k: round(float(np.mean([r[label][k] for r in rows.values()])), 4)
                     for k in ("iou", "false_positive", "false_negative", "input_view_psnr", "detect_s")}
             for label in ("untrimmed", "trimmed")}
    return {"per_photo": rows, "mean": means}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    cv2.setNumThreads(1)
    if not PHOTOS.is_dir():
        print(f"fixtures not present at {PHOTOS}: nothing to benchmark")
        return 0
    photos = sorted(p for p in PHOTOS.iterdir() if p.suffix.lower() in {".png", ".jpg", ".jpeg", ".webp"}
                    and not p.stem.endswith("_mask"))
    t = time.perf_counter()
    detect_person(load_photo(photos[0]))
    first = time.perf_counter() - t
    rows = {}
    for path in photos:
        rows[path.name] = bench_photo(path, args.repeats)
        print(path.name, rows[path.name])
    result = {"detect_first_s": round(first, 3), "repeats": args.repeats, "photos": rows,
              "composites": bench_composites()}
    out = save_result("perception", result, command=f"benchmarks/bench_perception.py --repeats {args.repeats}")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

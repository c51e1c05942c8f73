"""Benchmark of the body fit (``humanvdm_core.body.fit``, stage ``fit-smpl``).

Synthetic subjects (``testdata.synthetic.random_specs``, known true parameters), each rendered
by the ``render-training-orbits`` stage (21 frames, 576²); MediaPipe detections on every frame are
computed once per subject, then:

- ``orbit``: one static body fitted to all 21 frames; ``single``: fitted to the input view
  (azimuth 0) alone;
- ``joint_error_mm``: mean 3D distance of the fitted model's COCO-17 keypoints from the true ones,
  expressed at the true subject's size (the orbit frame normalises every subject to 1.7 units
  tall; distances are scaled back by the known normalisation): absolute, and ``..._hip_centred``
  (both sets translated so their hip midpoints coincide; what a single view can hope for);
- ``iou_used``: silhouette IoU (fitted mesh rasterised by ``humanvdm_core.render`` vs the frame's
  mask) on the frames fitted; ``iou_all_views``: on all 21 views (for the single fit: how the body
  fitted to one photo looks from the other views);
- ``reprojection_px``: mean keypoint reprojection error (px at 576²); ``seconds``: fit time on this
  CPU (1 thread; detection excluded, ``detect_s_per_frame`` separately);
- ``topologies``: seconds and joint error of the orbit fit per Anny topology on the first subject
  (which ones work).

Fixture photos (``../shared/fixtures/photos``, single photo each, ``*_mask`` files skipped): an
assumed camera (the SV3D field of view 33.8°, azimuth 0, at the orbit's distance), reprojection
error, IoU against the detected mask, and ``fit_<name>.png`` overlays in benchmarks/results/.

Run:  .venv/bin/python benchmarks/bench_fit.py [--subjects 3] [--iterations 250]
Writes benchmarks/results/fit.json.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
import traceback
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.common import RESULTS, save_result  # noqa: E402

PHOTOS = REPO.parent / "shared" / "fixtures" / "photos"
TOPOLOGIES = ("anny", "notoes", "notoes_collapse10pc", "notoes_collapse5pc")


def _errors(fitted: np.ndarray, truth: np.ndarray, norm: float) -> dict:
    from humanvdm_core.body.fit import joint_error_mm

    def centred(x):
        return x - x[[11, 12]].mean(0)

    return {"joint_error_mm": round(joint_error_mm(fitted, truth) / norm, 1),
            "joint_error_mm_hip_centred": round(joint_error_mm(centred(fitted), centred(truth)) / norm, 1)}


def bench_subject(spec, work: Path, iterations: int, topologies: tuple[str, ...]) -> dict:
    import torch

    from humanvdm_core.body.fit import FitOptions, fit_body, load_body_model, observe_frames, silhouette_iou
    from humanvdm_core.frames import read_cameras, read_frames
    from humanvdm_core.io import read_npz
    from testdata.synthetic import make_subject

    make_subject(spec, work / "subject")
    subprocess.run([sys.executable, "-m", "stages.render_training_orbits", "--scan", str(work / "subject"),
                    "--out-orbit", str(work / "orbit")], cwd=REPO, check=True, capture_output=True)
    truth = read_npz(work / "subject" / "truth.npz")
    N = truth["normalized_from_world"].astype(np.float64)
    true_coco = truth["coco17"] @ N[:3, :3].T + N[:3, 3]
    norm = float(N[0, 0])
    frames = read_frames(work / "orbit")
    cams = read_cameras(work / "orbit")
    t = time.perf_counter()
    obs, failed = observe_frames(frames, list(range(len(frames))))
    detect_s = (time.perf_counter() - t) / len(frames)
    masks_all = [f[..., 3] for f in frames]
    out: dict = {"pose": spec.pose, "shape_true": [round(float(v), 3) for v in truth["shape"][0]],
                 "detect_s_per_frame": round(detect_s, 3), "frames_without_detection": sorted(failed)}
    for topo in topologies:
        try:
            torch.manual_seed(0)
            model = load_body_model("anny", topology=topo)
        except Exception as exc:  # noqa: BLE001 - a topology that does not build is a result, not a crash
            out.setdefault("topologies", {})[topo] = {"error": f"{type(exc).__name__}: {exc}"}
            continue
        faces = model.faces.numpy()
        runs = {"orbit": obs, "single": [o for o in obs if o.index == len(frames) - 1]} if topo == "anny" \
            else {"orbit": obs}
        for name, use in runs.items():
            t = time.perf_counter()
            res = fit_body(model, cams, use, FitOptions(iterations=iterations))
            seconds = time.perf_counter() - t
            verts = res.output.vertices[0].numpy()
            iou_all = silhouette_iou(verts, faces, cams, masks_all)
            used = np.array(res.frame_indices)
            row = {**_errors(res.output.coco17[0].numpy(), true_coco, norm),
                   "iou_used": round(float(iou_all[used].mean()), 3), "iou_all_views": round(float(iou_all.mean()), 3),
                   "reprojection_px": round(float(np.nanmean(res.reprojection_px)), 2),
                   "frames": len(use), "seconds": round(seconds, 2),
                   "shape_fit": [round(float(v), 3) for v in res.params.shape[0]]}
            if topo == "anny":
                out[name] = row
            else:
                out.setdefault("topologies", {})[topo] = {k: row[k] for k in ("joint_error_mm", "seconds", "iou_used")}
        if topo == "anny":
            out.setdefault("topologies", {})[topo] = {k: out["orbit"][k] for k in ("joint_error_mm", "seconds",
                                                                                   "iou_used")}
    return out


def bench_photo(path: Path, iterations: int) -> dict:
    from humanvdm_core.body.fit import FitOptions, FrameObservation, fit_body, load_body_model, silhouette_iou
    from humanvdm_core.cameras import Cameras, intrinsics, look_at, orbit_position
    from humanvdm_core.perception import detect_person, load_photo
    from humanvdm_core.scans import framing_radius
    from stages.fit_smpl import write_overlay

    photo = load_photo(path)
    det = detect_person(photo)
    H, W = photo.height, photo.width
    radius = framing_radius(1.7, 33.8, 0.85)
    c2w = look_at(orbit_position(0.0, 0.0, radius))
    cams = Cameras(intrinsics(33.8, W, H)[None], c2w[None], W, H, np.zeros(1), np.zeros(1), np.array([radius]))
    obs = [FrameObservation(0, det.keypoints, det.confidences, det.fit_mask, list(det.warnings),
                            world_keypoints=det.world_keypoints)]
    model = load_body_model("anny", topology="anny")
    t = time.perf_counter()
    res = fit_body(model, cams, obs, FitOptions(iterations=iterations))
    seconds = time.perf_counter() - t
    verts = res.output.vertices[0].numpy()
    iou = silhouette_iou(verts, model.faces.numpy(), cams, [det.mask])
    frame = np.concatenate([photo.rgb, det.mask[..., None]], axis=-1)[None]
    overlay = RESULTS / f"fit_{path.stem}.png"
    write_overlay(overlay, frame, [0], res, verts, model.faces.numpy(), cams, tiles=1, tile_px=256)
    return {"size": [W, H], "reprojection_px": round(float(res.reprojection_px[0]), 2),
            "reprojection_frac_of_height": round(float(res.reprojection_px[0]) / H, 4),
            "iou": round(float(iou[0]), 3), "seconds": round(seconds, 2), "mask_source": det.mask_source,
            "overlay": overlay.name, "warnings": det.warnings}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--subjects", type=int, default=3)
    parser.add_argument("--iterations", type=int, default=250)
    parser.add_argument("--seed", type=int, default=7)
    args = parser.parse_args()
    import cv2
    import torch

    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    from testdata.synthetic import random_specs

    result: dict = {"iterations": args.iterations, "subjects": [], "photos": {}, "failures": []}
    with tempfile.TemporaryDirectory() as tmp:
        for i, spec in enumerate(random_specs(args.subjects, seed=args.seed)):
            print(f"subject {i}: {spec.pose}", flush=True)
            try:
                row = bench_subject(spec, Path(tmp) / f"s{i}", args.iterations, TOPOLOGIES if i == 0 else ("anny",))
                result["subjects"].append(row)
                print("  ", {k: row.get(k) for k in ("orbit", "single")}, flush=True)
            except Exception as exc:  # noqa: BLE001
                result["failures"].append({"subject": i, "pose": spec.pose, "error": f"{type(exc).__name__}: {exc}",
                                           "trace": traceback.format_exc(limit=3)})
    subs = [s for s in result["subjects"] if "orbit" in s]
    for name in ("orbit", "single"):
        if subs:
            result[f"{name}_mean"] = {k: round(float(np.mean([s[name][k] for s in subs])), 3) for k in
                                      ("joint_error_mm", "joint_error_mm_hip_centred", "iou_used", "iou_all_views",
                                       "reprojection_px", "seconds")}
    if PHOTOS.is_dir():
        for path in sorted(PHOTOS.glob("*.png")):
            if path.stem.endswith("_mask"):
                continue
            print(f"photo {path.name}", flush=True)
            try:
                result["photos"][path.name] = bench_photo(path, args.iterations)
                print("  ", result["photos"][path.name], flush=True)
            except Exception as exc:  # noqa: BLE001
                result["failures"].append({"photo": path.name, "error": f"{type(exc).__name__}: {exc}"})
    else:
        result["photos_skipped"] = f"no fixtures at {PHOTOS}"
    cmd = f".venv/bin/python benchmarks/bench_fit.py --subjects {args.subjects} --iterations {args.iterations}"
    print(save_result("fit", result, cmd))


if __name__ == "__main__":
    main()

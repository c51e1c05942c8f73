"""Stage ``fit-smpl`` (paper section 3.3): fit a parametric body to the orbit frames.

Input ``frames``: a frame set (:mod:`humanvdm_core.frames`; normally the 21-frame 576² orbit, whose
last frame, azimuth 0, is the input photo's view). The person is detected (COCO-17 keypoints and
mask) on ``fit_frames`` of them ("all" or a count spread evenly around the orbit, always including the
frame nearest azimuth 0), and ONE static body is fitted to all of them
(:func:`humanvdm_core.body.fit.fit_body`: 2D keypoints + the detector's 3D bone directions +
one-sided silhouettes (the body inside each mask; covering the mask is off by default, so loose
clothing does not widen the body) + priors, left/right swaps of back views resolved against the 3D
estimate). ``fit_frames=1`` is a single-photo fit.

Output ``body``:

- ``body.npz`` (schema ``humanvdm.body_fit`` v1): ``model_name``, ``backend``, ``topology``,
  ``joint_names``, ``pose_joint_names``, ``shape_names``; the fitted ``BodyParams`` arrays ``pose``
  (1, P, 3), ``shape`` (1, S), ``global_orient`` (1, 3), ``transl`` (1, 3), ``scale`` (1, 1); the
  posed body in the frame set's world: ``vertices`` (V, 3), ``joints`` (J, 3), ``coco17`` (17, 3),
  ``bone_transforms`` (J, 4, 4), ``rest_vertices`` (V, 3); ``faces`` (F, 3);
  ``skinning_weights`` (V, J); the canonical body (the backend's da-pose with the fitted shape, unit
  scale, no global transform): ``canonical_pose``, ``canonical_vertices`` (V, 3),
  ``canonical_joints``, ``canonical_bone_transforms`` (J, 4, 4) (so
  ``lbs(points, weights, bone_transforms[None], canonical_bone_transforms[None])`` poses canonical
  points); per frame used (N): ``frame_indices``, ``frame_azimuth_deg``, ``keypoints`` (N, 17, 2)
  (detections as used, after any left/right swap), ``keypoint_confidences`` (N, 17),
  ``projected_coco17`` (N, 17, 2), ``reprojection_px`` (N,) (nan without keypoints), ``iou`` (N,),
  ``lr_swapped`` (N, 3) (face, arms, legs); ``per_frame_pose`` (N, P, 3) only with
  ``refine_per_frame``; the UV position map at ``uv_resolution`` R when the topology has a UV
  layout (``has_uv_map``): ``uv_resolution``, ``uv_face_ids`` (M,), ``uv_barycentrics`` (M, 3),
  ``uv_rows``/``uv_cols`` (M,), ``uv_mask`` (R, R), ``uv_positions`` (M, 3) on the canonical body,
  ``uv_weights`` (M, J) skinning weights.
- ``overlay.png``: up to four frames with the fitted mesh's outline (green), the detections (red)
  and the model's keypoints (blue), for people.
- ``report.json``: fit quality per frame and overall, frames used/skipped and why, warnings (every
  per-frame one) and ``warnings_summary``: the same, one line per kind with the frames it concerns
  (e.g. "keypoints unusable in 6 of 21 frames (0003, 0007, ...)"; joints hidden only in some frames,
  as an orbit's side views hide the far arm, or seen in the input photo's frame (the one nearest
  azimuth 0), make no line), plus skipped frames and fit-quality
  warnings (a keypoint reprojection error over 3 % of the frame; a body partly outside the person's
  masks, or covering little of them: ``silhouette_doubts``; ``mean_iou``, ``mean_outside`` and
  ``mean_cover`` hold the numbers). The summary lines are also logged as warnings, so they reach the run
  summary.

Bad input: no person in any selected frame -> an error naming the frames; fewer usable frames than
needed (at least ``min(3, selected)``, one of them with keypoints) -> an error saying how many.
"""

from __future__ import annotations

import re

from humanvdm_core.workflow.stage import Param, StageContext, StageSpec

SCHEMA = "humanvdm.body_fit"
SCHEMA_VERSION = 1

SPEC = StageSpec(
    name="fit-smpl",
    summary="Fit a parametric body (Anny; SMPL/SMPL-X from your files) to the orbit frames: params, meshes, joints, UV position map.",
    inputs={"frames": "frame set (RGBA frames + cameras), normally the 21-frame orbit"},
    outputs={"body": "body.npz (fitted body, canonical body, UV position map), overlay.png, report.json"},
    params={
        "topology": Param("anny", "body mesh topology (only 'anny' has the UV layout the splats need)",
                          choices=("anny", "notoes", "notoes_collapse10pc", "notoes_collapse5pc",
                                   "notoes_collapse3pc")),
        "uv_resolution": Param(256, "UV position map size (R x R texels)"),
        "iterations": Param(250, "optimiser steps of the full fit (the global phase adds a third)"),
        "fit_frames": Param("all", "frames to detect and fit on: 'all' or a count spread around the orbit "
                                "(1 = the input view alone)"),
        "seed": Param(0, "seed (silhouette vertex subsample)"),
        "refine_per_frame": Param(False, "also fit a small per-frame pose correction (stored as per_frame_pose)"),
        "keypoint_weight": Param(1.0, "weight of the 2D keypoint term"),
        "silhouette_weight": Param(0.3, "weight of the one-sided silhouette term: the body must lie inside "
                                        "the person's mask in every frame"),
        "silhouette_cover_weight": Param(0.0, "weight of the other side: the body must cover the mask's contour. "
                                              "Off by default: loose clothing (a gown, a coat) is in the mask but "
                                              "is not body, and covering it widens and stretches the body"),
        "bone_direction_weight": Param(2.0, "weight of the 3D bone-direction term: the fitted limbs, torso and "
                                            "neck point like the detector's 3D landmarks (MediaPipe's "
                                            "world landmarks) in each frame; the depth cue of a single view"),
        "pose_prior_weight": Param(0.05, "weight of the pose prior (squared joint angles)"),
        "single_view_pose_prior_weight": Param(1.0, "pose prior with one view and no 3D landmarks "
                                               "(bone_direction_weight 0); with n views it is "
                                               "max(pose_prior_weight, this / n^2)"),
        "single_view_pose_prior_weight_3d": Param(0.1, "the same with 3D landmarks (the bone directions "
                                                   "observe the limbs' depth, so the prior can be weak)"),
        "shape_prior_weight": Param(0.05, "weight of the shape prior (distance from the average shape)"),
        "model_dir": Param("~/.cache/humanvdm/weights/body_models",
                           "smpl/smplx backends: folder holding smpl/SMPL_NEUTRAL.pkl or smplx/SMPLX_NEUTRAL.npz "
                           "(your own download from smpl.is.tue.mpg.de / smpl-x.is.tue.mpg.de)",
                           weights=True, backend=("smpl", "smplx")),
        "gender": Param("neutral", "smpl/smplx backends: model gender", choices=("neutral", "male", "female")),
    },
    backends=("anny", "smpl", "smplx"),
)


def select_frames(azimuth_deg, spec: str) -> list[int]:
    """Frame indices to use: all, or ``n`` spread evenly by azimuth starting at the frame nearest 0."""
    import numpy as np

    from humanvdm_core.workflow.errors import ConfigError

    n_total = len(azimuth_deg)
    key = spec.strip().lower()
    if key == "all":
        return list(range(n_total))
    try:
        n = int(key)
    except ValueError:
        raise ConfigError(f"param fit_frames: {spec!r} is neither 'all' nor a frame count") from None
    if n < 1:
        raise ConfigError(f"param fit_frames must be >= 1, got {n}")
    az = np.asarray(azimuth_deg, dtype=np.float64)
    start = int(np.argmin(np.abs((az + 180.0) % 360.0 - 180.0)))
    order = np.argsort((az - az[start]) % 360.0, kind="stable")
    n = min(n, n_total)
    picks = np.floor(np.arange(n) * n_total / n).astype(np.int64)
    return sorted(int(order[p]) for p in picks)


_FRAME = r"frame (\S+)"
HIDDEN_MOST = 0.5  # a joint not clearly visible in more than this share of the frames is posed by guesswork
_HIDDEN = "joints not clearly visible"
# per-frame warnings (from observe_frames / detect_person): pattern (group 1 the frame, group 2 the joints
# when counted), the summary's head and tail, whether the joints are counted
_PER_FRAME = (
    (re.compile(rf"^{_FRAME}: keypoints unusable \((.*)\)$", re.S), "keypoints unusable",
     "; only the silhouette was fitted there", False),
    (re.compile(rf"^not clearly visible in {_FRAME}: (.*)$", re.S), _HIDDEN, "", True),
    (re.compile(rf"^part of the body is outside {_FRAME} \(cut off by the frame\): (.*?);.*$", re.S),
     "body cut off by the frame", "", True),
    (re.compile(rf"^{_FRAME} shows (\d+) people.*$", re.S), "more than one person", "; the largest one was used",
     False),
)
MAX_LISTED = 6  # frames named per summary line


def _frames_text(frames: list[str], total: int) -> str:
    shown = ", ".join(frames[:MAX_LISTED]) + (", ..." if len(frames) > MAX_LISTED else "")
    return f"{len(frames)} of {total} frame{'s' if total != 1 else ''} ({shown})"


def summarize_warnings(warnings: list[str], frames_total: int, skipped: dict[str, str] | None = None,
                       seen_in: str | None = None) -> list[str]:
    """One line per kind of warning instead of one per frame: "keypoints unusable in 6 of 21 frames
    (0003, 0007, ...)"; joint names are counted ("left wrist 5x"); warnings that name no frame are
    kept once each, in order. ``skipped`` (frame name -> why) adds a line for frames not used at all.
    Joints not clearly visible make a line only when hidden in more than :data:`HIDDEN_MOST` of the
    frames (an orbit's side views hide the far arm; the other frames show it) and, with ``seen_in``
    (the name of the input photo's frame), hidden there too: the photo shows the others (hands on the
    hips, which the orbit's side and back views hide), and ``diffuse`` says what it hides. report.json
    keeps every per-frame warning."""
    kinds: dict[tuple[str, str], tuple[list[str], dict[str, int]]] = {}
    hidden_in_photo: set[str] = set()
    other: dict[str, list[str]] = {}  # message (its frame name replaced by "*") -> frames
    for w in warnings:
        for pattern, head, tail, count in _PER_FRAME:
            m = pattern.match(w)
            if m:
                frames, items = kinds.setdefault((head, tail), ([], {}))
                if m.group(1) not in frames:
                    frames.append(m.group(1))
                for item in (x.strip() for x in m.group(2).split(",")) if count else ():
                    if item:
                        items[item] = items.get(item, 0) + 1
                        if head == _HIDDEN and m.group(1) == seen_in:
                            hidden_in_photo.add(item)
                break
        else:
            m = re.search(rf"\b{_FRAME}", w)
            frames = other.setdefault(re.sub(rf"\b{_FRAME}", "frame *", w) if m else w, [])
            if m and m.group(1) not in frames:
                frames.append(m.group(1))
    out = []
    if skipped:
        out.append(f"frames skipped (no usable person): {_frames_text(list(skipped), frames_total)}")
    for (head, tail), (frames, items) in kinds.items():
        if head == _HIDDEN:  # hidden in a few frames of an orbit is normal: the others show the joint
            most = {k: n for k, n in items.items()
                    if n > HIDDEN_MOST * frames_total and (seen_in is None or k in hidden_in_photo)}
            if most:
                ranked = sorted(most.items(), key=lambda kv: (-kv[1], kv[0]))
                out.append(f"{head} in most frames, so their pose is a guess: "
                           + ", ".join(f"{k} (hidden in {n} of {frames_total})" for k, n in ranked))
            continue
        line = f"{head} in {_frames_text(frames, frames_total)}"
        if items:
            line += ": " + ", ".join(f"{k} {n}x" if n > 1 else k
                                     for k, n in sorted(items.items(), key=lambda kv: (-kv[1], kv[0])))
        out.append(line + tail)
    for w, frames in other.items():
        out.append(f"{w}: {_frames_text(frames, frames_total)}" if len(frames) > 1
                   else w.replace("frame *", f"frame {frames[0]}") if frames else w)
    return out


def run(ctx: StageContext) -> None:
    import json
    from pathlib import Path

    import numpy as np
    import torch

    from humanvdm_core.body.fit import (
        FitOptions,
        fit_body,
        load_body_model,
        observe_frames,
        silhouette_doubts,
        silhouette_scores,
    )
    from humanvdm_core.frames import open_frame_set, read_frames
    from humanvdm_core.io import write_npz
    from humanvdm_core.workflow.atomic import atomic_write_text
    from humanvdm_core.workflow.errors import ConfigError, InputError

    p = ctx.params
    if not 8 <= p["uv_resolution"] <= 4096:
        raise ConfigError(f"param uv_resolution must be in [8, 4096], got {p['uv_resolution']}")
    options = FitOptions(iterations=p["iterations"], keypoint_weight=p["keypoint_weight"],
                         silhouette_weight=p["silhouette_weight"],
                         silhouette_cover_weight=p["silhouette_cover_weight"],
                         bone_direction_weight=p["bone_direction_weight"], pose_prior_weight=p["pose_prior_weight"],
                         single_view_pose_prior_weight=p["single_view_pose_prior_weight"],
                         single_view_pose_prior_weight_3d=p["single_view_pose_prior_weight_3d"],
                         shape_prior_weight=p["shape_prior_weight"], refine_per_frame=p["refine_per_frame"],
                         seed=p["seed"])
    options.check()
    if ctx.backend == "anny":  # the body model first: a missing model file fails before any detection
        model = load_body_model("anny", topology=p["topology"])
    else:
        model = load_body_model(ctx.backend, model_dir=Path(p["model_dir"]).expanduser(), gender=p["gender"])
    root = ctx.inputs["frames"]
    paths, cameras = open_frame_set(root)
    selected = select_frames(cameras.azimuth_deg, p["fit_frames"])
    frames = read_frames(root, indices=selected)
    names = [f"frame {paths[i].stem}" for i in selected]
    ctx.log.info("detecting the person in %d of %d frames", len(selected), len(paths))
    ctx.progress(0, 3, "steps", f"detect the person in {len(selected)} frames")
    observations, failed = observe_frames(frames, list(range(len(selected))), names)
    for o in observations:  # back to frame-set indices
        o.index = selected[o.index]
    failed = {selected[k]: v for k, v in failed.items()}
    if not observations:
        listed = ", ".join(f"{paths[i].stem}" for i in selected)
        raise InputError(f"no person found in frames {listed} of {root}: every selected frame failed "
                         f"(first: {next(iter(failed.values()))})")
    with_kp = [o for o in observations if o.has_keypoints]
    need = min(3, len(selected))
    if len(observations) < need or not with_kp:
        raise InputError(f"too few usable frames to fit the body: {len(observations)} of {len(selected)} usable "
                         f"({len(with_kp)} with keypoints); at least {need}, one with keypoints, are needed. "
                         f"Skipped: " + "; ".join(f"{paths[i].stem}: {why}" for i, why in failed.items()))

    torch.manual_seed(p["seed"])
    ctx.progress(1, 3, "steps", f"fit the body ({p['iterations']} iterations)")
    fit = fit_body(model, cameras, observations, options, logger=ctx.log)
    ctx.progress(2, 3, "steps", "measure the fit, write the outputs")
    used_cams = cameras.subset(fit.frame_indices)
    faces = model.faces.numpy().astype(np.int64)
    vertices = fit.output.vertices[0].numpy()
    iou, outside, cover = silhouette_scores(vertices, faces, used_cams, [o.mask for o in observations])

    with torch.no_grad():
        canon_params = model.canonical_params(1)
        canon_params.shape = fit.params.shape.clone()
        canon = model(canon_params)
    f32 = np.float32
    arrays: dict[str, np.ndarray] = {
        "model_name": np.array(model.name), "backend": np.array(ctx.backend), "topology": np.array(p["topology"]),
        "joint_names": np.array(model.joint_names), "pose_joint_names": np.array(model.pose_joint_names),
        "shape_names": np.array(model.shape_names),
        **{k: v.astype(f32) for k, v in fit.params.to_numpy().items()},
        "vertices": vertices.astype(f32), "faces": faces,
        "joints": fit.output.joints[0].numpy().astype(f32), "coco17": fit.output.coco17[0].numpy().astype(f32),
        "bone_transforms": fit.output.bone_transforms[0].numpy().astype(f32),
        "rest_vertices": fit.output.rest_vertices[0].numpy().astype(f32),
        "skinning_weights": model.skinning_weights.numpy().astype(f32),
        "canonical_pose": canon_params.pose.numpy().astype(f32),
        "canonical_vertices": canon.vertices[0].numpy().astype(f32),
        "canonical_joints": canon.joints[0].numpy().astype(f32),
        "canonical_bone_transforms": canon.bone_transforms[0].numpy().astype(f32),
        "frame_indices": np.array(fit.frame_indices, dtype=np.int64),
        "frame_azimuth_deg": used_cams.azimuth_deg.astype(np.float64),
        "keypoints": fit.keypoints.astype(f32), "keypoint_confidences": fit.confidences.astype(f32),
        "projected_coco17": fit.projected.astype(f32),
        "reprojection_px": fit.reprojection_px.astype(np.float64), "iou": iou.astype(np.float64),
        "lr_swapped": fit.swapped,
        "has_uv_map": np.array(model.uvs is not None),
    }
    if fit.per_frame_pose is not None:
        arrays["per_frame_pose"] = fit.per_frame_pose.astype(f32)
    warnings = list(dict.fromkeys(fit.warnings))
    if model.uvs is not None:
        from humanvdm_core.body.uvmap import UVPositionMap

        uvm = UVPositionMap.from_model(model, p["uv_resolution"])
        arrays.update({
            "uv_resolution": np.int64(uvm.resolution), "uv_face_ids": uvm.face_ids,
            "uv_barycentrics": uvm.barycentrics.astype(f32), "uv_rows": uvm.rows, "uv_cols": uvm.cols,
            "uv_mask": uvm.mask, "uv_positions": uvm.positions(canon.vertices[0].numpy()).astype(f32),
            "uv_weights": uvm.weights(model.skinning_weights.numpy()).astype(f32),
        })
    else:
        warnings.append(f"topology {p['topology']!r} has no UV layout: body.npz holds no UV position map "
                        "(the splat stage needs one; use topology 'anny')")
    out = ctx.outputs["body"]
    write_npz(out / "body.npz", arrays, SCHEMA, SCHEMA_VERSION)
    write_overlay(out / "overlay.png", frames, selected, fit, vertices, faces, cameras)

    def r(x: float) -> float | None:
        return None if not np.isfinite(x) else round(float(x), 3)

    mean_reproj = float(np.nanmean(fit.reprojection_px)) if np.any(np.isfinite(fit.reprojection_px)) else np.nan
    if np.isfinite(mean_reproj) and mean_reproj > 0.03 * cameras.height:
        warnings.append(f"poor keypoint fit: mean reprojection error {mean_reproj:.1f} px")
    warnings += silhouette_doubts(outside, cover)
    photo_frame = paths[select_frames(cameras.azimuth_deg, "1")[0]].stem  # nearest azimuth 0: the photo's view
    summary = summarize_warnings(warnings, len(selected),
                                 {paths[i].stem: why for i, why in sorted(failed.items())}, seen_in=photo_frame)
    for line in summary:
        ctx.log.warning("%s", line)
    report = {
        "schema": "humanvdm.body_fit_report", "version": 1, "model": model.name, "backend": ctx.backend,
        "topology": p["topology"], "frames_total": len(paths), "frames_selected": selected,
        "frames_used": fit.frame_indices,
        "frames_skipped": {paths[i].stem: why for i, why in sorted(failed.items())},
        "mean_reprojection_px": r(mean_reproj), "mean_iou": r(float(iou.mean())),
        "mean_outside": r(float(outside.mean())), "mean_cover": r(float(cover.mean())),
        "per_frame": [{"frame": int(i), "azimuth_deg": r(float(a)), "reprojection_px": r(float(e)), "iou": r(float(u)),
                       "lr_swapped": {g: bool(s) for g, s in zip(("face", "arms", "legs"), sw, strict=True)}}
                      for i, a, e, u, sw in zip(fit.frame_indices, used_cams.azimuth_deg, fit.reprojection_px, iou,
                                                fit.swapped, strict=True)],
        "shape": {n: r(float(v)) for n, v in zip(model.shape_names, fit.params.shape[0].tolist(), strict=True)},
        "scale": r(float(fit.params.scale)), "uv_resolution": p["uv_resolution"] if model.uvs is not None else None,
        "warnings": warnings, "warnings_summary": summary,
    }
    atomic_write_text(out / "report.json", json.dumps(report, indent=1) + "\n")
    ctx.progress(3, 3, "steps", "measure the fit, write the outputs")
    ctx.log.info("body fit: mean reprojection %.1f px, mean IoU %.3f over %d frame(s)%s", mean_reproj,
                 float(iou.mean()), len(fit.frame_indices), f"; {len(warnings)} warning(s)" if warnings else "")


def write_overlay(path, frames, selected, fit, vertices, faces, cameras, tiles: int = 4, tile_px: int = 256) -> None:
    """Up to ``tiles`` used frames side by side: the fitted mesh's outline (green), detections (red),
    the model's keypoints (blue)."""
    import cv2
    import numpy as np

    from humanvdm_core.body.fit import render_masks
    from humanvdm_core.io import write_png

    used = fit.frame_indices
    picks = sorted({used[int(k)] for k in np.floor(np.arange(min(tiles, len(used))) * len(used)
                                                  / min(tiles, len(used))).astype(int)})
    masks = render_masks(vertices, faces, cameras.subset(picks), max_size=tile_px)
    row = []
    for i, m in zip(picks, masks, strict=True):
        j = used.index(i)
        img = frames[selected.index(i)][..., :3]
        s = tile_px / img.shape[0]
        tile = cv2.resize(np.clip(img, 0, 1), (round(img.shape[1] * s), tile_px), interpolation=cv2.INTER_AREA)
        tile = np.ascontiguousarray((tile * 255).astype(np.uint8))
        m = cv2.resize(m, (tile.shape[1], tile.shape[0]), interpolation=cv2.INTER_LINEAR)
        contours, _ = cv2.findContours((m > 0.5).astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        cv2.drawContours(tile, contours, -1, (40, 220, 40), 1, lineType=cv2.LINE_AA)
        for k in range(17):
            if fit.confidences[j, k] > 0:
                x, y = fit.keypoints[j, k] * s
                cv2.circle(tile, (int(round(x)), int(round(y))), 3, (230, 30, 30), -1, lineType=cv2.LINE_AA)
            x, y = fit.projected[j, k] * s
            cv2.circle(tile, (int(round(x)), int(round(y))), 2, (40, 80, 255), -1, lineType=cv2.LINE_AA)
        row.append(tile)
    write_png(path, np.concatenate(row, axis=1))


if __name__ == "__main__":
    raise SystemExit(SPEC.main(run))

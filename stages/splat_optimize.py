"""Stage ``splat-optimize`` (paper section 3.3 + supplement): fit skinned 3D Gaussians to the frames.

Inputs: ``frames`` (a frame set, normally the 81-frame 1080² interpolated orbit; every frame is a training
view), ``body`` (``body.npz`` from ``fit-smpl``, schema ``humanvdm.body_fit`` v1) and, optionally, ``orbit``
(diffuse's orbit, for the clothed proxy ``proxy.npz`` beside it). The model and the loss are
:mod:`humanvdm_core.splat.human`'s; where the Gaussians start is ``template``
(:mod:`humanvdm_core.splat.template`):

- ``subject`` (``auto``'s choice): points ``subject_spacing`` apart on the subject's own surface (so a gown
  gets more than a T-shirt), ``detail_spacing`` x that where the input photo shows detail (a face, a print,
  a logo: :func:`humanvdm_core.splat.template.detail_points`) -- the clothed
  proxy when the orbit has one, else the visual hull of the frames' silhouettes merged with the body --
  each skinned and un-posed with its nearest body vertex, so a dress, a coat, long hair or a held object
  has Gaussians of its own;
- ``body``: one Gaussian per valid UV texel of the body (``uv_resolution``² map), as the paper.

Colours start in closed form (``init_colors``: the frames projected onto the Gaussians with a visibility
test and averaged; Gaussians no frame sees are dropped), so the first step already shows the person.
Then: a per-Gaussian feature + MLP decoder for offsets / colour residuals / scales, learned opacities
(``learn_opacity``), LBS posing (``refine_pose``: the paper's joint pose refinement, off by default), 0.8 L1 + 0.2 (1 - SSIM) (+ 0.2 LPIPS with
``lpips_weights``) + 10 offset² + 1 scale² + 1 feature², Adam lr 3e-3, 2 views a batch (a quarter of the
batches hold the input photo's view, ``input_view_share``: the photo is the one view not generated; that
view trains at ``input_view_resolution``, finer than the others, and its finer residuals count when
splitting), the first steps at half resolution, and (``densify``) pruning and splitting at the preset's steps, so the count
follows the subject; the counts go to ``train_log.json``.

Presets (``preset``; ``auto`` = ``full`` with CUDA, else ``cpu``) set ``subject_spacing`` / ``uv_resolution`` /
``train_resolution`` / ``input_view_resolution`` / ``iterations`` / ``tile_size`` unless those params are set
(non-zero), and the coarse share, the densify steps and the cap on the count (see :data:`humanvdm_core.splat.human.PRESETS`):
``tiny`` (tests), ``cpu`` (a CPU run of minutes), ``full`` (paper size, for a GPU with gsplat).

Output ``gaussians``:

- ``gaussians.npz`` (schema ``humanvdm.gaussians`` v1, see :func:`humanvdm_core.splat.human.gaussians_arrays`):
  posed ``means``, ``quats`` (wxyz), ``scales`` (linear), ``opacities``, ``colors`` (sRGB [0, 1]),
  ``canonical_means``, ``skinning_weights``, UV texel indices, refined ``pose``/``transl``, ``background``;
- ``point_cloud.ply``: the standard 3DGS binary PLY, by default in the 3DGS/COLMAP axes (``ply_axes``
  ``y-down``: x right, y down, z forward, the subject facing -z; upright in SuperSplat); ``y-up`` keeps our
  world's axes (y up, the subject facing +z; upright in gaussian-splats-3d's default view). Metres. The
  header's comments state the axes. See :data:`humanvdm_core.splat.human.PLY_AXES`;
- ``point_cloud.splat``: the same Gaussians in the compact web ``.splat`` format (32 bytes each, same axes);
- ``turntable/NNNN.png`` (``turntable_views`` views at ``turntable_size``², on the input orbit's
  elevation and radius) and ``turntable.gif``, for people (``turntable_views=0`` skips them);
- ``train_log.json``: loss curve, final training PSNR, resolved settings, the template, the Gaussian counts
  (initial, after each densify step, final); no timings (those are the lockfile's).

Deterministic on the CPU: same inputs + params + seed -> identical ``gaussians.npz`` and PLY bytes on one
machine (on CUDA, gsplat's backward adds in parallel, so the last bits may vary between runs).
"""

from __future__ import annotations

from humanvdm_core.workflow.stage import Param, StageContext, StageSpec

SPEC = StageSpec(
    name="splat-optimize",
    summary="Fit skinned 3D Gaussians (on the subject's surface or the body's UV map; features + MLP decoder) "
            "to the orbit frames.",
    inputs={"frames": "frame set (RGBA frames + cameras), normally the 81-frame interpolated orbit",
            "body": "body fit directory holding body.npz (fit-smpl)",
            "orbit": "diffuse's orbit; its proxy.npz (the clothed proxy), when present, is the subject template"},
    optional=("orbit",),
    outputs={"gaussians": "gaussians.npz, point_cloud.ply (3DGS), point_cloud.splat, turntable/ + turntable.gif, "
                          "train_log.json"},
    params={
        "preset": Param("auto", "size/quality preset (auto: full with CUDA, else cpu)",
                        choices=("auto", "tiny", "cpu", "full")),
        "template": Param("auto", "where the Gaussians start: subject (the clothed proxy diffuse wrote, else the "
                                  "visual hull of the frames, merged with the body), body (one per texel of the body's "
                                  "UV map, as the paper), auto (subject)", choices=("auto", "subject", "body")),
        "subject_spacing": Param(0.0, "subject template: metres between its starting points (their count follows "
                                      "the subject's surface area); 0: from the preset"),
        "detail_spacing": Param(0.5, "subject template: points this fraction of subject_spacing apart where the "
                                     "input photo shows detail (a face, a print, a logo: local texture variation); "
                                     "1: even spacing"),
        "uv_resolution": Param(0, "body template: UV map size R (Gaussian count ~0.62 R^2); 0: from the preset"),
        "init_colors": Param(True, "initialise colours in closed form (the frames projected onto the Gaussians, "
                                   "visibility-tested, averaged), so training starts from the person"),
        "densify": Param(True, "prune transparent Gaussians and split those the renders miss, at the preset's "
                               "densify steps (up to its max_gaussians)"),
        "learn_opacity": Param(True, "optimise each Gaussian's opacity (False: opacity 1, as the paper)"),
        "split_residual": Param(0.1, "render error (mean |colour| + |alpha|) above which a Gaussian is split"),
        "train_resolution": Param(0, "training image size in pixels; 0: from the preset"),
        "input_view_resolution": Param(0, "the input photo's view trains at this size (at most the frames' own; "
                                          "at or below train_resolution: as the others); 0: from the preset"),
        "iterations": Param(0, "optimiser steps; 0: from the preset"),
        "tile_size": Param(0, "rasterizer tile size; 0: from the preset"),
        "scale_mode": Param("isotropic", "Gaussian scales: one (isotropic) or three per Gaussian",
                            choices=("isotropic", "anisotropic")),
        "min_scale": Param(0.5, "smallest Gaussian scale, as a fraction of its texel's spacing (keeps the "
                                "surface closed when viewed at a higher resolution than trained)"),
        "feature_dim": Param(16, "channels of the optimisable feature tensor"),
        "hidden": Param(64, "width of the decoder MLP"),
        "refine_pose": Param(False, "jointly refine the body pose and translation (the paper's; off by default: on the "
                                    "protocol scans it cost 0.2-0.8 dB, the Gaussians already sit on the subject's surface)"),
        "lr": Param(3e-3, "Adam learning rate (features, decoder)"),
        "input_view_share": Param(0.25, "share of the training batches that hold the input photo's view (the "
                                        "orbit's frame at azimuth 0, the one view that is not generated); "
                                        "0: uniform, as the paper"),
        "pose_lr": Param(3e-4, "Adam learning rate of the pose/translation refinement"),
        "batch_views": Param(2, "training views per step"),
        "l1_weight": Param(0.8, "weight of the L1 term"),
        "ssim_weight": Param(0.2, "weight of the (1 - SSIM) term"),
        "lpips_weight": Param(0.2, "weight of the LPIPS term (only with lpips_weights)"),
        "lpips_weights": Param("", "local LPIPS weight file; empty: no LPIPS term", weights=True),
        "offset_weight": Param(10.0, "weight of the offset^2 regulariser"),
        "scale_weight": Param(1.0, "weight of the scale^2 regulariser"),
        "feature_weight": Param(1.0, "weight of the feature^2 regulariser"),
        "mask_weight": Param(0.0, "weight of an L1 term on the rendered vs the frames' alpha (0: off, as the paper)"),
        "seed": Param(0, "seed (feature/decoder initialisation, view order)"),
        "turntable_views": Param(36, "turntable renders (0: none)"),
        "turntable_size": Param(512, "turntable render size in pixels"),
        "ply_axes": Param("y-down", "axes of point_cloud.ply/.splat: y-down (3DGS/COLMAP: x right, y down, z forward; "
                                    "upright in SuperSplat) or y-up (ours: y up, subject facing +z; upright in "
                                    "gaussian-splats-3d's default view)", choices=("y-down", "y-up")),
    },
    backends=("embedded",),
)


def resolve_settings(p: dict, cuda: bool) -> dict:
    """The preset's uv_resolution / train_resolution / iterations / tile_size with explicit params applied."""
    from humanvdm_core.splat.human import PRESETS
    from humanvdm_core.workflow.errors import ConfigError

    name = p["preset"] if p["preset"] != "auto" else ("full" if cuda else "cpu")
    out = {"preset": name, **PRESETS[name]}
    for key in ("uv_resolution", "subject_spacing", "train_resolution", "input_view_resolution", "iterations",
                "tile_size"):
        if p[key] < 0:
            raise ConfigError(f"param {key} must be >= 0, got {p[key]}")
        if p[key] > 0:
            out[key] = p[key]
    if not 8 <= out["uv_resolution"] <= 4096:
        raise ConfigError(f"param uv_resolution must be in [8, 4096], got {out['uv_resolution']}")
    if not 16 <= out["train_resolution"] <= 8192:
        raise ConfigError(f"param train_resolution must be in [16, 8192], got {out['train_resolution']}")
    return out


def run(ctx: StageContext) -> None:
    import numpy as np
    import torch

    from humanvdm_core.frames import read_cameras
    from humanvdm_core.io import write_npz, write_png
    from humanvdm_core.splat import human as H
    from humanvdm_core.splat.rasterize import gsplat_missing_warning
    from humanvdm_core.splat.template import init_colors, start_anchor
    from humanvdm_core.workflow.errors import ConfigError

    p = ctx.params
    cuda = torch.cuda.is_available()
    s = resolve_settings(p, cuda)
    if p["turntable_views"] < 0 or p["turntable_size"] < 16:
        raise ConfigError("turntable_views must be >= 0 and turntable_size >= 16")
    if not 0.0 < p["detail_spacing"] <= 1.0:
        raise ConfigError(f"param detail_spacing must be in (0, 1], got {p['detail_spacing']}")
    if p["lpips_weights"]:  # fail before any work when the file is missing
        from humanvdm_core.errors import require_weights

        require_weights(p["lpips_weights"], "LPIPS weights for the splat loss", "the LPIPS project's releases")
    device = torch.device("cuda" if cuda else "cpu")
    if (warning := gsplat_missing_warning()) is not None:
        ctx.log.warning("%s", warning)
    torch.manual_seed(p["seed"])
    body_path = ctx.inputs["body"]
    body_path = body_path / "body.npz" if body_path.is_dir() else body_path
    anchor = H.load_body_anchor(body_path, s["uv_resolution"], load_model=p["refine_pose"])
    views = H.load_views(ctx.inputs["frames"], s["train_resolution"])
    cameras = read_cameras(ctx.inputs["frames"])
    input_view, photo, detail_view = H.load_input_view(ctx.inputs["frames"], views, s["input_view_resolution"])
    proxy = ctx.inputs["orbit"] / "proxy.npz" if "orbit" in ctx.inputs else None
    ctx.progress(0, 1, "steps", "place the Gaussians on the subject")
    anchor, template = start_anchor(anchor, views, p["template"], s["subject_spacing"], proxy, p["seed"],
                                    detail_view, p["detail_spacing"])
    ctx.log.info("preset %s, template %s: %d Gaussians, %d views at %d² (the input view at %d²), %d iterations on %s",
                 s["preset"], template, len(anchor.positions), len(views.images), s["train_resolution"],
                 photo.size if photo is not None else s["train_resolution"], s["iterations"], device.type)
    human = H.GaussianHuman(anchor, feature_dim=p["feature_dim"], hidden=p["hidden"], scale_mode=p["scale_mode"],
                            refine_pose=p["refine_pose"], seed=p["seed"], min_scale=p["min_scale"],
                            learn_opacity=p["learn_opacity"]).to(device)
    initial = human.num_gaussians
    if p["init_colors"]:
        unseen = init_colors(human, views)
        ctx.log.info("colours from %d views in closed form; %d Gaussians no view sees pruned", len(views.images),
                     unseen)
    config = H.FitConfig(
        iterations=s["iterations"], lr=p["lr"], pose_lr=p["pose_lr"], batch_views=p["batch_views"],
        l1_weight=p["l1_weight"], ssim_weight=p["ssim_weight"], lpips_weight=p["lpips_weight"],
        lpips_weights=p["lpips_weights"], offset_weight=p["offset_weight"], scale_weight=p["scale_weight"],
        feature_weight=p["feature_weight"], mask_weight=p["mask_weight"], seed=p["seed"],
        tile_size=s["tile_size"], log_every=max(1, s["iterations"] // 50), coarse_fraction=s["coarse_fraction"],
        densify_at=tuple(s["densify_at"]) if p["densify"] else (), max_gaussians=s["max_gaussians"],
        split_residual=p["split_residual"],
        input_view=input_view, input_view_share=p["input_view_share"])
    result = H.fit_gaussians(human, views, config, log=ctx.log.info, photo=photo)  # progress in the stage log
    ctx.log.info("trained in %.1f s: loss %.4f -> %.4f, training PSNR %.2f dB", result.wall_s,
                 result.losses[0] if result.losses else float("nan"),
                 result.losses[-1] if result.losses else float("nan"), result.train_psnr)

    out = ctx.outputs["gaussians"]
    background = views.background.cpu().numpy()
    arrays = H.gaussians_arrays(human, background)
    write_npz(out / "gaussians.npz", arrays, H.GAUSSIANS_SCHEMA, H.GAUSSIANS_VERSION)
    export = (arrays["means"], arrays["quats"], arrays["scales"], arrays["opacities"], arrays["colors"])
    H.write_ply(out / "point_cloud.ply", *export, axes=p["ply_axes"])
    H.write_splat(out / "point_cloud.splat", *export, axes=p["ply_axes"])
    if p["turntable_views"] > 0:
        from PIL import Image

        cams = H.turntable_cameras(cameras, p["turntable_views"], p["turntable_size"])
        images = H.render_views_np(human, cams, background, tile_size=s["tile_size"])
        (out / "turntable").mkdir()
        for i, img in enumerate(images):
            write_png(out / "turntable" / f"{i:04d}.png", img)
        frames = [Image.fromarray(np.clip(np.rint(img * 255), 0, 255).astype(np.uint8)) for img in images]
        frames[0].save(out / "turntable.gif", save_all=True, append_images=frames[1:], duration=80, loop=0)
    H.write_train_log(out / "train_log.json", result, {
        "settings": s, "template": template, "initial_gaussians": initial, "densify_steps": result.counts,
        "num_gaussians": human.num_gaussians, "num_views": int(len(views.images)),
        "device": device.type, "refined_pose_max_abs_rad": float(human.delta_pose.detach().abs().max()),
        "refined_transl": [round(float(v), 6) for v in human.delta_transl.detach().cpu()]})


if __name__ == "__main__":
    raise SystemExit(SPEC.main(run))

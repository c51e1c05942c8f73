"""Stage ``diffuse`` (paper section 3.1): one photo -> an orbit video of the person, with cameras.

Input ``photo``: the photo artifact (a folder holding ``input.<ext>``) or, when run by hand, the image
file itself.

Output ``orbit``: a frame set (:mod:`humanvdm_core.frames`)::

    frames/NNNN.exr    RGBA half: RGB (sRGB values) over the background colour, A = the person's coverage
    cameras.npz        the SV3D_p orbit cameras (``num_frames``, ``resolution``², 33.8 deg vertical FOV,
                       ``elevation_deg`` -- body-prior: raised for a photo taken from above --, radius
                       framing a 1.7-unit subject at ``fill`` of the frame);
                       extra: background (3,), fill
    proxy.npz          body-prior with ``geometry: clothed`` only: the clothed proxy the orbit was rendered
                       from (:class:`humanvdm_core.clothed_proxy.ClothedProxy`: vertices and faces in the
                       orbit's world, texture + UVs, vertex colours, skinning to the Anny rig, front flags)

The last frame (azimuth 0) is the preprocessed input photo itself (person scaled to ``fill`` of the
frame, centred, composited over the background; A = its mask).

Backends:

- ``body-prior``: NOT a learned model. A deterministic stand-in for the learned multi-view prior: a
  body fitted to the photo (2D keypoints, MediaPipe's 3D landmarks, the mask from inside), a clothed
  proxy built around it that fills the person's whole silhouette with depth (clothing, hair, held
  objects; :mod:`humanvdm_core.clothed_proxy`), coloured from the photo (the unseen side from the
  same body part's visible colour, print-free; hair on the back of the head), centred so the orbit
  turns about its middle, rendered along the orbit
  (:mod:`humanvdm_core.body_prior`, whose docstring is the contract and lists its limits). A photo
  taken from behind is built facing away. What it had to guess (hidden legs or hands, a seated pose,
  clothing far from the body, the facing) is said in warnings. It keeps the pipeline runnable on a CPU.
- ``sv3d_p`` / ``sv3d_u``: Stability AI's SV3D video diffusion model from YOUR checkpoint
  (``--sv3d-p-weights`` / ``--sv3d-u-weights``, default ``~/.cache/humanvdm/weights/sv3d_p.safetensors``
  / ``sv3d_u.safetensors``; from huggingface.co/stabilityai/sv3d under the Stability AI Community
  License; a fine-tuned checkpoint in the same layout works too). EDM Euler sampling (``steps``),
  triangle CFG ``cfg_min`` -> ``cfg_max`` -> ``cfg_min`` across frames, ``cond_aug`` noise on the
  conditioning image, the VAE decoding ``decoding_chunk`` frames at a time; fp16 on CUDA. sv3d_p
  follows the orbit's cameras (elevation, azimuths); sv3d_u ignores them. A is estimated from the
  white background (SV3D gives no mask). See :mod:`humanvdm_core.models.sv3d`. Nothing is
  downloaded: a missing weight file stops the stage (exit 3) before any work, naming the file.

Bad input (no person, body cut off, unreadable photo) exits 3 with a one-line message.
"""

from __future__ import annotations

from pathlib import Path

from humanvdm_core.workflow.stage import Param, StageContext, StageSpec

SV3D_BACKENDS = ("sv3d_p", "sv3d_u")

SPEC = StageSpec(
    name="diffuse",
    summary="Photo -> orbit video of the person (21 frames, 576², SV3D_p cameras); body-prior: a geometric "
            "stand-in for the learned prior; sv3d_p / sv3d_u: SV3D from your checkpoint.",
    inputs={"photo": "the photo: a folder holding input.<ext>, or the image file"},
    outputs={"orbit": "frame set: frames/ (RGBA), cameras.npz (extra: background, fill)"},
    params={
        "num_frames": Param(21, "frames on the orbit; the last is azimuth 0 (the input view)"),
        "resolution": Param(576, "frame width and height in pixels"),
        "elevation_deg": Param(10.0, "camera elevation in degrees (body-prior: raised for a photo taken from "
                                     "above, see raise_from_above)"),
        "fill": Param(0.85, "fraction of the frame height the person spans (the orbit framing)"),
        "fit_iterations": Param(150, "body-prior: optimiser steps of the single-view body fit",
                                backend="body-prior"),
        "raise_from_above": Param(True, "body-prior: a photo taken from above (MediaPipe's 3D torso and legs leaning "
                                        "towards the camera) raises the orbit above elevation_deg so the person "
                                        "stands or sits upright",
                                  backend="body-prior"),
        "geometry": Param("clothed", "body-prior: render the orbit from the clothed proxy (the person's whole "
                                     "silhouette given depth) or from the naked fitted body (the ablation)",
                          choices=("clothed", "body"), backend="body-prior"),
        "seed": Param(0, "seed (body fit; SV3D sampling noise)"),
        "sv3d_p_weights": Param("~/.cache/humanvdm/weights/sv3d_p.safetensors",
                                "SV3D_p checkpoint (sgm layout) from huggingface.co/stabilityai/sv3d "
                                "(Stability AI Community License), or a fine-tuned one",
                                weights=True, backend="sv3d_p"),
        "sv3d_u_weights": Param("~/.cache/humanvdm/weights/sv3d_u.safetensors",
                                "SV3D_u checkpoint (sgm layout) from huggingface.co/stabilityai/sv3d "
                                "(Stability AI Community License), or a fine-tuned one",
                                weights=True, backend="sv3d_u"),
        "steps": Param(50, "SV3D: EDM Euler sampling steps", backend=SV3D_BACKENDS),
        "cfg_min": Param(1.0, "SV3D: guidance scale at the first and last frame", backend=SV3D_BACKENDS),
        "cfg_max": Param(2.5, "SV3D: guidance scale in the middle of the orbit", backend=SV3D_BACKENDS),
        "cond_aug": Param(1e-5, "SV3D: noise level added to the conditioning image", backend=SV3D_BACKENDS),
        "decoding_chunk": Param(14, "SV3D: frames the VAE decodes at a time (memory)", backend=SV3D_BACKENDS),
    },
    backends=("body-prior", "sv3d_p", "sv3d_u"),
)

BACKGROUND = (1.0, 1.0, 1.0)  # SV3D-style white background
PROXY_FILE = "proxy.npz"  # the clothed proxy beside the orbit (body-prior, geometry "clothed")


def _check_params(p: dict, backend: str = "body-prior") -> None:
    from humanvdm_core.workflow.errors import ConfigError

    checks = [
        (p["num_frames"] >= 1, "num_frames must be >= 1"),
        (64 <= p["resolution"] <= 4096, "resolution must be in [64, 4096]"),
        (-60.0 <= p["elevation_deg"] <= 60.0, "elevation_deg must be in [-60, 60]"),
        (0.1 <= p["fill"] <= 1.0, "fill must be in [0.1, 1]"),
        (p["fit_iterations"] >= 1, "fit_iterations must be >= 1"),
        (p["steps"] >= 1, "steps must be >= 1"),
        (0.0 <= p["cfg_min"] <= p["cfg_max"], "need 0 <= cfg_min <= cfg_max"),
        (0.0 <= p["cond_aug"] <= 1.0, "cond_aug must be in [0, 1]"),
        (p["decoding_chunk"] >= 1, "decoding_chunk must be >= 1"),
    ]
    if backend in SV3D_BACKENDS:
        checks += [(p["resolution"] % 64 == 0, "resolution must be a multiple of 64 for SV3D (576 is its size)"),
                   (p["num_frames"] >= 2, "num_frames must be >= 2 for SV3D")]
    for ok, message in checks:
        if not ok:
            raise ConfigError(f"stage {SPEC.name}: {message}")


def run(ctx: StageContext) -> None:
    p = ctx.params
    _check_params(p, ctx.backend)
    if ctx.backend in SV3D_BACKENDS:
        _run_sv3d(ctx)
        return

    import torch

    from humanvdm_core.body_prior import build_body_proxy
    from humanvdm_core.frames import write_frames

    torch.manual_seed(p["seed"])
    ctx.progress(0, 2, "steps", "fit a body to the photo, build the proxy")
    proxy = build_body_proxy(ctx.inputs["photo"], num_frames=p["num_frames"], size=p["resolution"],
                             elevation_deg=p["elevation_deg"], background=BACKGROUND,
                             iterations=p["fit_iterations"], fill=p["fill"], seed=p["seed"],
                             geometry=p["geometry"], raise_from_above=p["raise_from_above"], logger=ctx.log)
    for warning in proxy.warnings:
        ctx.log.warning("%s", warning)
    ctx.progress(1, 2, "steps", "render and write the orbit")
    frames = proxy.orbit_frames()
    write_frames(ctx.outputs["orbit"], frames, proxy.cameras, {**ctx.attrs(), "layer": "rgba"})
    if proxy.clothed is not None:
        proxy.clothed.save(Path(ctx.outputs["orbit"]) / PROXY_FILE)
    ctx.progress(2, 2, "steps", "render and write the orbit")
    ctx.log.info("wrote %d frames at %d² (frame %d is the input view)", len(frames), p["resolution"],
                 proxy.front_index)


def _run_sv3d(ctx: StageContext) -> None:
    from humanvdm_core.errors import require_weights
    from humanvdm_core.frames import write_frames
    from humanvdm_core.models import sv3d

    p = ctx.params
    weights = require_weights(p[f"{ctx.backend}_weights"], sv3d.WHAT[ctx.backend], sv3d.WHERE)  # before any work
    frames, cameras, warnings = sv3d.synthesize_orbit(
        ctx.inputs["photo"], weights, ctx.backend, num_frames=p["num_frames"], size=p["resolution"],
        elevation_deg=p["elevation_deg"], fill=p["fill"], steps=p["steps"], seed=p["seed"], cfg_min=p["cfg_min"],
        cfg_max=p["cfg_max"], cond_aug=p["cond_aug"], decoding_chunk=p["decoding_chunk"], logger=ctx.log)
    for warning in warnings:
        ctx.log.warning("%s", warning)
    write_frames(ctx.outputs["orbit"], frames, cameras, {**ctx.attrs(), "layer": "rgba"})
    ctx.log.info("wrote %d %s frames at %d² (the last is the input view)", len(frames), ctx.backend, p["resolution"])


if __name__ == "__main__":
    raise SystemExit(SPEC.main(run))

"""Stage ``diffuse`` (paper section 3.1): one photo -> an orbit video of the person, with cameras.

Input ``photo``: the photo artifact (a folder holding ``input.<ext>``) or, when run by hand, the image
file itself.

Output ``orbit``: a frame set (:mod:`humanvdm_core.frames`)::

    frames/NNNN.exr    RGBA half: RGB (sRGB values) over the background colour, A = the person's coverage
    cameras.npz        the SV3D_p orbit cameras (``num_frames``, ``resolution``², 33.8 deg vertical FOV,
                       ``elevation_deg``, radius framing a 1.7-unit subject at ``fill`` of the frame);
                       extra: background (3,), fill

The last frame (azimuth 0) is the preprocessed input photo itself (person scaled to ``fill`` of the
frame, centred, composited over the background; A = its mask).

Backends:

- ``body-prior``: NOT a learned model. A deterministic stand-in for the learned multi-view prior: a
  body fitted to the photo, coloured from the photo (the back mirrored from the front, hair colour
  on the back of the head), rendered along the orbit (:mod:`humanvdm_core.body_prior`, whose
  docstring is the contract and lists its limits). It keeps the pipeline runnable on a CPU.

Bad input (no person, body cut off, unreadable photo) exits 3 with a one-line message.
"""

from __future__ import annotations

from humanvdm_core.stage import Param, StageContext, StageSpec

SPEC = StageSpec(
    name="diffuse",
    summary="Photo -> orbit video of the person (21 frames, 576², SV3D_p cameras); body-prior: a geometric "
            "stand-in for the learned prior.",
    inputs={"photo": "the photo: a folder holding input.<ext>, or the image file"},
    outputs={"orbit": "frame set: frames/ (RGBA), cameras.npz (extra: background, fill)"},
    params={
        "num_frames": Param(21, "frames on the orbit; the last is azimuth 0 (the input view)"),
        "resolution": Param(576, "frame width and height in pixels"),
        "elevation_deg": Param(10.0, "camera elevation in degrees"),
        "fill": Param(0.85, "fraction of the frame height the person spans (the orbit framing)"),
        "fit_iterations": Param(150, "body-prior: optimiser steps of the single-view body fit",
                                backend="body-prior"),
        "seed": Param(0, "seed (body fit)"),
    },
    backends=("body-prior",),
)

BACKGROUND = (1.0, 1.0, 1.0)  # SV3D-style white background


def _check_params(p: dict) -> None:
    from humanvdm_core.errors import ConfigError

    checks = [
        (p["num_frames"] >= 1, "num_frames must be >= 1"),
        (64 <= p["resolution"] <= 4096, "resolution must be in [64, 4096]"),
        (-60.0 <= p["elevation_deg"] <= 60.0, "elevation_deg must be in [-60, 60]"),
        (0.1 <= p["fill"] <= 1.0, "fill must be in [0.1, 1]"),
        (p["fit_iterations"] >= 1, "fit_iterations must be >= 1"),
    ]
    for ok, message in checks:
        if not ok:
            raise ConfigError(f"stage {SPEC.name}: {message}")


def run(ctx: StageContext) -> None:
    import torch

    from humanvdm_core.body_prior import build_body_proxy
    from humanvdm_core.frames import write_frames

    p = ctx.params
    _check_params(p)
    torch.manual_seed(p["seed"])
    proxy = build_body_proxy(ctx.inputs["photo"], num_frames=p["num_frames"], size=p["resolution"],
                             elevation_deg=p["elevation_deg"], background=BACKGROUND,
                             iterations=p["fit_iterations"], fill=p["fill"], seed=p["seed"], logger=ctx.log)
    for warning in proxy.warnings:
        ctx.log.warning("%s", warning)
    frames = proxy.orbit_frames()
    write_frames(ctx.outputs["orbit"], frames, proxy.cameras, {**ctx.attrs(), "layer": "rgba"})
    ctx.log.info("wrote %d frames at %d² (frame %d is the input view)", len(frames), p["resolution"],
                 proxy.front_index)


if __name__ == "__main__":
    raise SystemExit(SPEC.main(run))

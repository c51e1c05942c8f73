"""Stage ``evaluate`` (paper section 4): metrics, a view grid and an HTML report for a Gaussian human.

Inputs:

- ``gaussians``: the splat-optimize artifact (a folder holding ``gaussians.npz``, schema
  ``humanvdm.gaussians`` v1: ``means``, ``quats`` wxyz, ``scales`` linear, ``opacities``, ``colors``
  sRGB [0, 1]), or the ``.npz`` itself;
- ``frames``: the frame set the Gaussians were fitted to (its cameras define the orbit);
- ``scan`` (optional; oracle runs on a textured scan): the scan the frames were rendered from.
  The frame set's ``cameras.extra['world_from_scan']`` places it in the world;
- ``body`` (optional): the ``fit-smpl`` output, for its overlay in the report.

Views (all rendered at ``resolution``², the Gaussians by :func:`humanvdm_core.splat.rasterize.
rasterize_gaussians` over the frames' background colour):

- ``protocol``: front, back, left, right = azimuth 0, 180, 90, 270 at the orbit's elevation and
  radius, compared with the frame set's frame at that azimuth when the orbit has one (the 81-frame
  orbit has all four); a view without a frame is rendered for the grid but has no metrics;
- ``heldout`` (scan runs only): ground truth rendered from the scan at ``heldout_elevations`` x
  ``heldout_azimuths``; a camera that coincides with a training camera is dropped (never scored).

Output ``report``:

- ``metrics.json``: per view and the mean per group: ``psnr``, ``ssim``, ``masked_psnr``,
  ``masked_ssim``, ``iou``, ``lpips``, ``clip`` (definitions in :mod:`humanvdm_core.metrics` and
  :mod:`humanvdm_core.perceptual`, repeated under ``definitions``); ``geometry`` (scan runs):
  ``p2s``/``s2p``/``chamfer`` in world units and ``*_rel`` as fractions of the subject height.
  A perceptual metric whose weight file is missing reads ``"unavailable: put <file> at <path>"``;
  geometry without a scan reads ``"unavailable: ..."``. Infinite PSNR is written as ``"inf"``. ``basis`` says
  what each group measures: without a scan the protocol views are a *fit to the generated video — not
  accuracy* (the frames are what the Gaussians were fitted to); with a scan the protocol views are a fit
  to its training views, the held-out views and the geometry are accuracy against the scan.
- ``grid.png``: one row per view; columns ground truth | ours | |error| heatmap (mean absolute RGB
  error, 0 -> 0.5 mapped through the inferno colour map);
- ``orbit.gif`` (the frame set as a video, ``media_size``²), ``turntable.gif`` (copied from the
  Gaussians artifact when it has one), ``fit_overlay.png`` (the ``body`` input's overlay, when given);
- ``report.html``: those pictures, the numbers (labelled with their ``basis``) and the grid. The run's own
  report (input photo, viewer, backends, params, times, memory, versions from the lockfile) is
  ``runs/<subject>/report.html``, written by ``humanvdm run`` (:mod:`humanvdm_core.report`).

Errors a user can fix (no gaussians.npz, a wrong schema, a frame set without cameras, a scan run
whose frames lack ``world_from_scan``, a perceptual weight file with the wrong keys) exit 3.
"""

from __future__ import annotations

from humanvdm_core.workflow.stage import Param, StageContext, StageSpec

WEIGHTS_DIR = "~/.cache/humanvdm/weights"

SPEC = StageSpec(
    name="evaluate",
    summary="Render the Gaussians at the protocol (and held-out scan) views; write metrics.json, grid.png, report.html.",
    inputs={"gaussians": "splat-optimize output (gaussians.npz)",
            "frames": "the frame set the Gaussians were fitted to (frames + cameras)",
            "scan": "the textured scan of an oracle run (ground truth for held-out views and geometry)",
            "body": "the fit-smpl output (its overlay.png goes into the report)"},
    outputs={"report": "metrics.json, grid.png, orbit.gif, turntable.gif, fit_overlay.png, report.html"},
    params={
        "resolution": Param(512, "render and compare at this many pixels square"),
        "heldout_elevations": Param("0,25", "elevations (degrees) of the held-out scan views, comma-separated"),
        "heldout_azimuths": Param("45,135,225,315", "azimuths (degrees) of the held-out scan views"),
        "lpips_weights": Param(f"{WEIGHTS_DIR}/lpips/alex.pth", "LPIPS v0.1 AlexNet linear heads (lpips package)",
                               weights=True),
        "alexnet_weights": Param(f"{WEIGHTS_DIR}/lpips/alexnet-owt-7be5be79.pth",
                                 "torchvision AlexNet ImageNet weights (LPIPS features)", weights=True),
        "clip_weights": Param(f"{WEIGHTS_DIR}/clip/ViT-B-32.pt", "OpenAI CLIP ViT checkpoint (image tower used)",
                              weights=True),
        "geometry_samples": Param(100000, "uniform scan-surface samples for the geometry error"),
        "min_opacity": Param(0.05, "Gaussians below this opacity are left out of the geometry error"),
        "cell_size": Param(256, "pixel size of one grid.png cell"),
        "media_size": Param(256, "pixel size of orbit.gif, the orbit video in the report (0: none)"),
    },
    optional=("scan", "body"),
)


def run(ctx: StageContext) -> None:
    from humanvdm_core.evaluate import EvaluateOptions, evaluate_gaussians, float_list

    p = ctx.params
    opts = EvaluateOptions(
        resolution=p["resolution"],
        heldout_elevations=float_list("heldout_elevations", p["heldout_elevations"]),
        heldout_azimuths=float_list("heldout_azimuths", p["heldout_azimuths"]),
        lpips_weights=p["lpips_weights"], alexnet_weights=p["alexnet_weights"], clip_weights=p["clip_weights"],
        geometry_samples=p["geometry_samples"], min_opacity=p["min_opacity"], cell_size=p["cell_size"],
        media_size=p["media_size"])
    evaluate_gaussians(ctx.inputs["gaussians"], ctx.inputs["frames"], ctx.inputs.get("scan"),
                       ctx.outputs["report"], opts, ctx.log, body=ctx.inputs.get("body"))


if __name__ == "__main__":
    raise SystemExit(SPEC.main(run))

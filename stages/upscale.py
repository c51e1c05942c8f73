"""Stage ``upscale`` (paper section 3.2): orbit frames -> ``target_size``² frames.

Reads a frame set, writes a frame set (see :mod:`humanvdm_core.upscale` for the full contract).
Frames already at ``target_size``² pass through as a byte-identical copy (same artifact id).
"""

from __future__ import annotations

from humanvdm_core.stage import Param, StageContext, StageSpec

SPEC = StageSpec(
    name="upscale",
    summary="Upscale orbit frames to target_size x target_size (pass-through when already there).",
    inputs={"frames": "frame set (square RGBA frames + cameras)"},
    outputs={"frames": "frame set at target_size x target_size with rescaled cameras"},
    params={
        "target_size": Param(1080, "output width and height in pixels"),
        "method": Param("lanczos", "resampling kernel for colour and alpha", choices=("lanczos", "bicubic")),
        "sharpen": Param(0.8, "unsharp-mask amount after upscaling (0 = none); overshoot is clamped, no halos"),
        "sharpen_sigma": Param(0.55, "unsharp-mask Gaussian sigma in input pixels"),
    },
    backends=("embedded",),
)


def run(ctx: StageContext) -> None:
    from humanvdm_core.errors import ConfigError
    from humanvdm_core.upscale import UpscaleOptions, upscale_frame_set

    p = ctx.params
    if p["target_size"] < 1:
        raise ConfigError(f"upscale.target_size must be positive, got {p['target_size']}")
    if p["sharpen"] < 0 or p["sharpen_sigma"] <= 0:
        raise ConfigError(f"sharpen must be >= 0 and sharpen_sigma > 0, got {p['sharpen']}, {p['sharpen_sigma']}")
    opts = UpscaleOptions(target_size=p["target_size"], method=p["method"], sharpen=p["sharpen"],
                          sharpen_sigma=p["sharpen_sigma"])
    upscale_frame_set(ctx.inputs["frames"], ctx.outputs["frames"], opts, backend=ctx.backend,
                      attrs=ctx.attrs(), log=ctx.log)


if __name__ == "__main__":
    raise SystemExit(SPEC.main(run))

"""Stage ``upscale`` (paper section 3.2): orbit frames -> ``target_size``² frames.

Reads a frame set, writes a frame set (see :mod:`humanvdm_core.upscale.core` for the full contract).
Frames already at ``target_size``² pass through as a byte-identical copy (same artifact id).

Backends: ``embedded`` (no weights, the default); ``realesrgan`` (Real-ESRGAN RRDBNet on the whole
frame, ``--realesrgan-weights``); ``codeformer`` (CodeFormer on detected faces, w = ``fidelity``,
pasted onto a Real-ESRGAN background: needs ``--codeformer-weights`` and ``--realesrgan-weights``;
CodeFormer's weights are non-commercial, S-Lab License 1.0).  Nothing is downloaded: a missing
weight file stops the stage (exit 3) naming the file and where to get it.
"""

from __future__ import annotations

from humanvdm_core.workflow.stage import Param, StageContext, StageSpec

WEIGHTS = "~/.cache/humanvdm/weights"

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
        "realesrgan_weights": Param(f"{WEIGHTS}/RealESRGAN_x4plus.pth",
                                    "Real-ESRGAN RRDBNet checkpoint (x4plus or x2plus; BSD-3-Clause) from "
                                    "github.com/xinntao/Real-ESRGAN/releases",
                                    weights=True, backend=("realesrgan", "codeformer")),
        "codeformer_weights": Param(f"{WEIGHTS}/codeformer.pth",
                                    "CodeFormer checkpoint (non-commercial S-Lab License) from "
                                    "github.com/sczhou/CodeFormer/releases", weights=True, backend="codeformer"),
        "fidelity": Param(0.7, "CodeFormer w in [0, 1]: 0 = best quality, 1 = most faithful (paper: 0.7)"),
        "tile": Param(384, "Real-ESRGAN tile size in input pixels, bounds memory (0 = whole frame)"),
    },
    backends=("embedded", "realesrgan", "codeformer"),
)


def run(ctx: StageContext) -> None:
    from humanvdm_core.upscale.core import UpscaleOptions, upscale_frame_set
    from humanvdm_core.workflow.errors import ConfigError

    p = ctx.params
    if p["target_size"] < 1:
        raise ConfigError(f"upscale.target_size must be positive, got {p['target_size']}")
    if p["sharpen"] < 0 or p["sharpen_sigma"] <= 0:
        raise ConfigError(f"sharpen must be >= 0 and sharpen_sigma > 0, got {p['sharpen']}, {p['sharpen_sigma']}")
    if not 0.0 <= p["fidelity"] <= 1.0:
        raise ConfigError(f"upscale.fidelity must be in [0, 1], got {p['fidelity']}")
    if p["tile"] < 0:
        raise ConfigError(f"upscale.tile must be >= 0, got {p['tile']}")
    opts = UpscaleOptions(target_size=p["target_size"], method=p["method"], sharpen=p["sharpen"],
                          sharpen_sigma=p["sharpen_sigma"], realesrgan_weights=p["realesrgan_weights"],
                          codeformer_weights=p["codeformer_weights"], fidelity=p["fidelity"], tile=p["tile"])
    if ctx.backend in ("realesrgan", "codeformer"):  # fail before reading any frame
        from humanvdm_core.upscale import rrdbnet

        rrdbnet.load(opts.realesrgan_weights)
        if ctx.backend == "codeformer":
            from humanvdm_core.upscale import codeformer

            codeformer.load(opts.codeformer_weights)
    upscale_frame_set(ctx.inputs["frames"], ctx.outputs["frames"], opts, backend=ctx.backend,
                      attrs=ctx.attrs(), log=ctx.log)


if __name__ == "__main__":
    raise SystemExit(SPEC.main(run))

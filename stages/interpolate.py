"""Stage ``interpolate`` (paper section 3.2): N orbit frames -> (N-1)*2**passes+1 frames with cameras.

Reads a frame set, writes a frame set (see :mod:`humanvdm_core.interpolate.core` for the full contract):
21 key frames become 81 with the default two ×2 passes; key frames are kept unchanged, the
in-between cameras are slerped along the orbit; depth/normals layers are not carried over.

Backends: ``embedded`` (optical flow, no weights; the default), ``rife`` (RIFE v4.6 from the
local ``--rife-weights`` flownet.pkl; with ``--schedule recursive`` it runs ×2 per pass as the paper
does with PerVFI, with ``direct`` it synthesises t = 1/4, 1/2, 3/4 from the key pair) and ``pervfi``
(PerVFI, the paper's model: generator ``--pervfi-weights`` v00.pth + RAFT ``--pervfi-flow-weights``
raft-sintel.pth, from huggingface.co/Mulns/PerVFI-v1-0; a ×2 model, so it always runs the
``recursive`` schedule, whatever ``--schedule`` says, and the frames record the schedule that ran).
Nothing is downloaded: a missing weight file stops the stage (exit 3) naming the file and where to
get it, before any frame is read.
"""

from __future__ import annotations

from humanvdm_core.workflow.stage import Param, StageContext, StageSpec

SPEC = StageSpec(
    name="interpolate",
    summary="Interpolate an orbit video ×2 per pass (21 -> 41 -> 81 frames) with interpolated cameras.",
    inputs={"frames": "frame set (RGBA frames + cameras), at least 2 frames of one size"},
    outputs={"frames": "frame set with (N-1)*2**passes+1 frames and upsampled cameras"},
    params={
        "passes": Param(2, "number of ×2 passes (2: 21 -> 41 -> 81 frames)"),
        "method": Param("flow", "embedded method: optical-flow warping, or the cross-fade baseline",
                        choices=("flow", "crossfade")),
        "schedule": Param("direct", "direct: all in-between times from the key pair; recursive: ×2 per pass "
                          "(pervfi always runs recursive)", choices=("direct", "recursive")),
        "flow_scale": Param(0.5, "resolution factor at which optical flow is computed (0 < s <= 1)"),
        "preset": Param("fine", "OpenCV DIS preset (fine = medium with finest scale 0, patch stride 2)",
                        choices=("ultrafast", "fast", "medium", "fine")),
        "time_flow": Param("splat", "in-between flows: splat (flow reversal) or approx (Super SloMo formula)",
                           choices=("splat", "approx")),
        "rife_weights": Param("~/.cache/humanvdm/weights/rife-v4.6/flownet.pkl",
                              "RIFE v4.6 IFNet checkpoint (MIT) from github.com/hzwer/Practical-RIFE",
                              weights=True, backend="rife"),
        "pervfi_weights": Param("~/.cache/humanvdm/weights/pervfi/v00.pth",
                                "PerVFI generator checkpoint (Apache-2.0), PerVFI/v00.pth from "
                                "huggingface.co/Mulns/PerVFI-v1-0 (github.com/mulns/PerVFI)",
                                weights=True, backend="pervfi"),
        "pervfi_flow_weights": Param("~/.cache/humanvdm/weights/pervfi/raft-sintel.pth",
                                     "PerVFI's RAFT flow estimator (BSD-3-Clause), RAFT/raft-sintel.pth from "
                                     "huggingface.co/Mulns/PerVFI-v1-0", weights=True, backend="pervfi"),
    },
    backends=("embedded", "rife", "pervfi"),
)


def run(ctx: StageContext) -> None:
    from humanvdm_core.interpolate.core import InterpolateOptions, interpolate_frame_set
    from humanvdm_core.workflow.errors import ConfigError

    p = ctx.params
    if not 0 <= p["passes"] <= 6:
        raise ConfigError(f"interpolate.passes must be in [0, 6], got {p['passes']}")
    if not 0.0 < p["flow_scale"] <= 1.0:
        raise ConfigError(f"interpolate.flow_scale must be in (0, 1], got {p['flow_scale']}")
    opts = InterpolateOptions(passes=p["passes"], method=p["method"], schedule=p["schedule"],
                              flow_scale=p["flow_scale"], preset=p["preset"], time_flow=p["time_flow"],
                              rife_weights=p["rife_weights"], pervfi_weights=p["pervfi_weights"],
                              pervfi_flow_weights=p["pervfi_flow_weights"])
    if ctx.backend == "rife":  # fail before reading any frame
        from humanvdm_core.interpolate import rife

        rife.load(opts.rife_weights)
    elif ctx.backend == "pervfi":
        from humanvdm_core.interpolate import pervfi

        pervfi.load(opts.pervfi_weights, opts.pervfi_flow_weights)
    interpolate_frame_set(ctx.inputs["frames"], ctx.outputs["frames"], opts, backend=ctx.backend,
                          attrs=ctx.attrs(), log=ctx.log)


if __name__ == "__main__":
    raise SystemExit(SPEC.main(run))

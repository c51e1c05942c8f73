"""Stage ``finetune`` (training side, paper section 3.1): fine-tune SV3D's video UNet on rendered orbits.

Input ``orbits``: ``render-training-orbits`` output: one frame set, or a folder of frame sets (one
orbit per scan). Each orbit is a training video, its input view (azimuth 0, the last frame) the
condition, all its frames the targets (:mod:`humanvdm_core.models.sv3d_finetune` is the contract).

Output ``checkpoint``::

    sv3d_p_finetuned.safetensors   (or sv3d_u_...) the base checkpoint with the trained UNet: a full
                                   SV3D checkpoint in the official layout, for diffuse's
                                   --sv3d-p-weights / --sv3d-u-weights
    checkpoints/unet_step_NNNNNN.safetensors   UNet snapshots every ``snapshot_every`` steps
    train_log.json                 per-step losses, a fixed-draw probe loss before/after, the options

The VAE and the CLIP image tower stay frozen; AdamW at ``lr`` (5e-6), ``batch_size`` (13) videos
per step by gradient accumulation. Interrupted runs resume: the training state is saved every
``save_every`` steps under ``state_dir`` (a sub-folder named by the job: base weights, data and
options) and a rerun of the same job continues from it; it is removed once the outputs are written.
The base weights (``base_weights``: stock ``sv3d_p.safetensors`` from huggingface.co/stabilityai/sv3d,
Stability AI Community License) are never downloaded: a missing file exits 3 before any work.
"""

from __future__ import annotations

from humanvdm_core.workflow.stage import Param, StageContext, StageSpec

SPEC = StageSpec(
    name="finetune",
    summary="Fine-tune the SV3D UNet on rendered training orbits (VAE and CLIP frozen); writes a full checkpoint.",
    inputs={"orbits": "render-training-orbits output: a frame set, or a folder of frame sets"},
    outputs={"checkpoint": "sv3d_<kind>_finetuned.safetensors, checkpoints/ (UNet snapshots), train_log.json"},
    params={
        "base_weights": Param("~/.cache/humanvdm/weights/sv3d_p.safetensors",
                              "the SV3D checkpoint to start from (sgm layout; huggingface.co/stabilityai/sv3d, "
                              "Stability AI Community License)", weights=True),
        "steps": Param(500, "optimiser steps"),
        "lr": Param(5e-6, "AdamW learning rate"),
        "batch_size": Param(13, "videos per optimiser step (gradient accumulation)"),
        "micro_batch": Param(1, "videos per forward/backward pass (memory)"),
        "resolution": Param(576, "training frame size (SV3D: 576; a multiple of 64)"),
        "p_mean": Param(0.7, "mean of log sigma of the training noise levels (EDM sampling)"),
        "p_std": Param(1.6, "std of log sigma of the training noise levels"),
        "uncond_prob": Param(0.1, "probability of dropping the image conditioning (keeps CFG working)"),
        "cond_aug": Param(1e-5, "noise level added to the conditioning image"),
        "seed": Param(0, "seed (video order, noise levels, noise, dropout)"),
        "save_every": Param(25, "optimiser steps between resumable training-state saves"),
        "snapshot_every": Param(100, "optimiser steps between UNet snapshots in the output (0: none)"),
        "state_dir": Param("~/.cache/humanvdm/finetune-state", "where interrupted jobs' training state lives"),
    },
    backends=("sv3d",),
)


def run(ctx: StageContext) -> None:
    import json
    import shutil

    import torch

    from humanvdm_core.errors import require_weights
    from humanvdm_core.models import sv3d
    from humanvdm_core.models import sv3d_finetune as ft
    from humanvdm_core.workflow.atomic import atomic_write_text

    p = ctx.params
    opts = ft.FinetuneOptions(steps=p["steps"], lr=p["lr"], batch_size=p["batch_size"], micro_batch=p["micro_batch"],
                              resolution=p["resolution"], p_mean=p["p_mean"], p_std=p["p_std"],
                              uncond_prob=p["uncond_prob"], cond_aug=p["cond_aug"], seed=p["seed"],
                              save_every=p["save_every"], snapshot_every=p["snapshot_every"])
    opts.check()
    base = require_weights(p["base_weights"], "SV3D base checkpoint (sv3d_p.safetensors / sv3d_u.safetensors)",
                           sv3d.WHERE)  # before any work
    orbits_root = ctx.inputs["orbits"]
    state_dir = ft.default_state_dir(p["state_dir"], ft.state_key(base, orbits_root, opts))
    torch.manual_seed(opts.seed)
    model = sv3d.build(base)  # not the shared cache: training changes the weights
    orbits = ft.load_training_orbits(orbits_root, opts.resolution)
    ctx.log.info("fine-tuning %s on %d orbit(s) of %d frames at %d² (state: %s)", model.kind, len(orbits),
                 len(orbits[0].frames), opts.resolution, state_dir)
    encoded = [ft.encode_orbit(model, o, opts.cond_aug) for o in orbits]
    probe_before = ft.probe_loss(model, encoded, opts)
    result = ft.finetune(model, orbits, opts, state_dir, ctx.log, encoded=encoded)
    if result.resumed_from:
        ctx.log.info("resumed an interrupted job at step %d", result.resumed_from)
    probe_after = ft.probe_loss(model, encoded, opts)

    out = ctx.outputs["checkpoint"]
    ft.save_finetuned_checkpoint(base, model, out / f"{model.kind}_finetuned.safetensors")
    snaps = ft.snapshots(state_dir)
    if snaps:
        (out / "checkpoints").mkdir()
        for snap in snaps:
            shutil.copyfile(snap, out / "checkpoints" / snap.name)
    log = {"kind": model.kind, "steps": result.steps_done, "losses": result.losses,  # content only: no paths
           "probe_loss_before": probe_before, "probe_loss_after": probe_after, "orbits": [o.name for o in orbits],
           "options": {k: v for k, v in p.items() if k not in ("state_dir", "base_weights")}}
    atomic_write_text(out / "train_log.json", json.dumps(log, indent=1))
    shutil.rmtree(state_dir, ignore_errors=True)
    ctx.log.info("probe loss %.5f -> %.5f after %d steps", probe_before, probe_after, result.steps_done)


if __name__ == "__main__":
    raise SystemExit(SPEC.main(run))

"""Fine-tuning SV3D's video UNet on rendered human orbits (the paper's training side, section 3.1).

Data: frame sets of ``render-training-orbits`` (:mod:`humanvdm_core.frames`; one frame set, or a
folder whose sub-folders are frame sets). Each orbit is one training video: its frames composited
over WHITE (SV3D's background) and resized to ``resolution``², in orbit order with the input view
(the frame nearest azimuth 0; the LAST frame in the project's SV3D_p convention) last.  The
conditioning image is that input view, exactly as at sampling time (:mod:`.sv3d`): its CLIP
embedding (``crossattn``) and its VAE latent plus ``cond_aug`` noise (``concat``), and the
per-frame camera vector (cond_aug, polar = 90° - elevation, azimuth relative to the input view).
The targets are every frame's latent (the frozen VAE encoder's mode times 0.18215).

Frozen: the VAE and the CLIP image tower (encoded once, no gradients). Trained: the UNet, AdamW
(``lr`` 5e-6 as the paper, no weight decay), ``batch_size`` videos per optimiser step by gradient
accumulation over ``micro_batch``-video forward passes (13 = the paper's batch).

Loss (sgm ``StandardDiffusionLoss`` for this denoiser): per video one noise level
``σ = exp(p_mean + p_std · N(0, 1))`` (``EDMSampling``), ``x_σ = x₀ + σ ε``, the denoiser
``D = c_skip x_σ + c_out UNet(c_in x_σ, ¼ ln σ, cond)`` (VScalingWithEDMcNoise), weight
``(σ² + 1) / σ²`` (``VWeighting``), mean of ``w (D - x₀)²``.  With probability ``uncond_prob`` a
video's image conditioning (crossattn and concat) is zeroed, so classifier-free guidance keeps working.

Resumable: every ``save_every`` optimiser steps the training state (UNet weights, optimiser
moments, step, losses, the noise generator's state) is written atomically to ``state_dir`` (and
every ``snapshot_every`` steps a UNet snapshot next to it); a run
with the same data, base weights and options resumes from it and ends with the same weights as an
uninterrupted run (on one machine). CUDA: bf16 autocast and gradient checkpointing (sgm's
``use_checkpoint``); CPU: float32.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from humanvdm_core.models import sv3d
from humanvdm_core.workflow.errors import InputError
from humanvdm_core.workflow.progress import report

log = logging.getLogger("humanvdm.sv3d_finetune")

STATE_FILE = "state.pt"


@dataclass
class FinetuneOptions:
    steps: int = 500  # optimiser steps
    lr: float = 5e-6
    batch_size: int = 13  # videos per optimiser step (gradient accumulation)
    micro_batch: int = 1  # videos per forward/backward pass
    resolution: int = 576
    p_mean: float = 0.7
    p_std: float = 1.6
    uncond_prob: float = 0.1
    cond_aug: float = sv3d.COND_AUG
    seed: int = 0
    save_every: int = 25  # optimiser steps between resumable state saves
    snapshot_every: int = 0  # optimiser steps between UNet snapshots kept in the state dir (0: none)
    gradient_checkpointing: bool = True

    def check(self) -> None:
        from humanvdm_core.workflow.errors import ConfigError

        checks = [(self.steps >= 1, "steps must be >= 1"), (self.lr > 0, "lr must be > 0"),
                  (self.batch_size >= 1, "batch_size must be >= 1"),
                  (1 <= self.micro_batch <= self.batch_size, "micro_batch must be in [1, batch_size]"),
                  (self.resolution >= 64 and self.resolution % 64 == 0, "resolution must be a multiple of 64"),
                  (self.p_std > 0, "p_std must be > 0"), (0.0 <= self.uncond_prob < 1.0, "uncond_prob must be in [0, 1)"),
                  (self.cond_aug >= 0, "cond_aug must be >= 0"), (self.save_every >= 1, "save_every must be >= 1"),
                  (self.snapshot_every >= 0, "snapshot_every must be >= 0")]
        for ok, message in checks:
            if not ok:
                raise ConfigError(f"finetune: {message}")


@dataclass
class TrainingOrbit:
    """One training video: ``frames`` (T, 3, S, S) in [-1, 1] over white, input view last;
    ``elevation_deg`` / ``azimuth_deg`` (T,) in the same order."""

    name: str
    frames: torch.Tensor
    elevation_deg: np.ndarray
    azimuth_deg: np.ndarray


@dataclass
class EncodedOrbit:
    """The frozen parts' outputs for one orbit (no gradients): target latents (T, 4, h, w) scaled,
    the conditioning image (1, 3, S, S), its CLIP embedding (1, D), the camera vector (T, adm)."""

    latents: torch.Tensor
    cond_image: torch.Tensor
    clip: torch.Tensor
    vector: torch.Tensor


@dataclass
class FinetuneResult:
    steps_done: int
    losses: list[float] = field(default_factory=list)
    resumed_from: int = 0
    finished: bool = False


# ----------------------------------------------------------------------------- data

def find_frame_sets(root: str | Path) -> list[Path]:
    """``root`` itself when it is a frame set (has ``cameras.npz``), else its sub-folders that are."""
    root = Path(root)
    if (root / "cameras.npz").is_file():
        return [root]
    sets = sorted(p for p in root.iterdir() if p.is_dir() and (p / "cameras.npz").is_file()) if root.is_dir() else []
    if not sets:
        raise InputError(f"no training orbits in {root}: expected a frame set (frames/ + cameras.npz, as "
                         "render-training-orbits writes) or a folder of them")
    return sets


def load_training_orbit(root: str | Path, resolution: int) -> TrainingOrbit:
    import cv2

    from humanvdm_core.frames import open_frame_set, read_frame

    paths, cams = open_frame_set(root)
    bg = np.asarray(cams.extra.get("background", np.ones(3)), np.float32).reshape(3)
    out = []
    for p in paths:
        f = read_frame(p)
        rgb = f[..., :3]
        if f.shape[-1] >= 4:  # RGB is over the set's background: put it over white instead
            rgb = rgb + (1.0 - f[..., 3:4]) * (1.0 - bg)
        if rgb.shape[0] != resolution or rgb.shape[1] != resolution:
            interp = cv2.INTER_AREA if rgb.shape[0] > resolution else cv2.INTER_LINEAR
            rgb = cv2.resize(rgb, (resolution, resolution), interpolation=interp)
        out.append(np.clip(rgb, 0.0, 1.0))
    az = np.asarray(cams.azimuth_deg, np.float64)
    front = int(np.argmin(np.abs((az + 180.0) % 360.0 - 180.0)))
    order = np.roll(np.arange(len(az)), len(az) - 1 - front)  # the input view (azimuth ~0) last
    frames = torch.from_numpy(np.stack(out)[order]).permute(0, 3, 1, 2).float() * 2.0 - 1.0
    return TrainingOrbit(Path(root).name, frames.contiguous(), np.asarray(cams.elevation_deg, np.float64)[order],
                         az[order])


def load_training_orbits(root: str | Path, resolution: int) -> list[TrainingOrbit]:
    orbits = [load_training_orbit(p, resolution) for p in find_frame_sets(root)]
    lengths = {len(o.frames) for o in orbits}
    if len(lengths) != 1 or min(lengths) < 2:
        raise InputError(f"training orbits must all have the same number (>= 2) of frames; found {sorted(lengths)}")
    return orbits


@torch.no_grad()
def encode_orbit(model: sv3d.SV3D, orbit: TrainingOrbit, cond_aug: float) -> EncodedOrbit:
    device = model.device
    frames = orbit.frames.to(device)
    latents = torch.cat([model.encoder.encode(frames[i:i + 4]) for i in range(0, len(frames), 4)]) * sv3d.SCALE_FACTOR
    cond = frames[-1:]
    with sv3d._autocast(device):
        clip = model.clip.embed(cond).float()
    polars, azimuths = sv3d.sv3d_angles(orbit.elevation_deg, orbit.azimuth_deg)
    vector = sv3d.vector_conditioning(model.kind, len(frames), cond_aug, polars, azimuths).to(device)
    return EncodedOrbit(latents.float(), cond, clip, vector)


# ----------------------------------------------------------------------------- loss

def batch_loss(model: sv3d.SV3D, videos: list[EncodedOrbit], sigmas: torch.Tensor, noises: list[torch.Tensor],
               cond_noises: list[torch.Tensor], keep: torch.Tensor, cond_aug: float) -> torch.Tensor:
    """The weighted denoising loss of a micro-batch of videos (module docstring), mean over videos."""
    device = model.device
    T = videos[0].latents.shape[0]
    x0 = torch.cat([v.latents for v in videos])  # (B*T, 4, h, w)
    sig = sigmas.to(device).repeat_interleave(T)[:, None, None, None]
    xn = x0 + torch.cat(noises).to(device) * sig
    with torch.no_grad():
        concat = torch.cat([model.encoder.encode(v.cond_image + cond_aug * n.to(device))
                            for v, n in zip(videos, cond_noises, strict=True)]).float()
    k = keep.to(device).float()
    concat = (concat * k[:, None, None, None]).repeat_interleave(T, dim=0)
    ctx = (torch.cat([v.clip for v in videos]) * k[:, None]).repeat_interleave(T, dim=0)[:, None, :]
    y = torch.cat([v.vector for v in videos])
    c_skip, c_out, c_in, c_noise = sv3d.denoiser_scalings(sig)
    ioi = torch.zeros(len(videos), T, device=device)
    amp = torch.autocast("cuda", dtype=torch.bfloat16) if device.type == "cuda" else _null()
    with amp:
        out = model.unet(torch.cat([xn * c_in, concat], dim=1), c_noise.reshape(-1), ctx, y, T, ioi)
    denoised = out.float() * c_out + xn * c_skip
    w = (sig ** 2 + 1.0) / sig ** 2
    per_video = (w * (denoised - x0) ** 2).reshape(len(videos), -1).mean(dim=1)
    return per_video.mean()


def _null():
    from contextlib import nullcontext

    return nullcontext()


def _draw(gen: torch.Generator, encoded: list[EncodedOrbit], opts: FinetuneOptions, n: int):
    """Which videos, their noise levels, noises, cond noises and conditioning dropout (from ``gen``)."""
    idx = torch.randint(len(encoded), (n,), generator=gen).tolist()
    sigmas = torch.exp(opts.p_mean + opts.p_std * torch.randn(n, generator=gen))
    noises = [torch.randn(encoded[i].latents.shape, generator=gen) for i in idx]
    cond_noises = [torch.randn(encoded[i].cond_image.shape, generator=gen) for i in idx]
    keep = (torch.rand(n, generator=gen) >= opts.uncond_prob)
    return [encoded[i] for i in idx], sigmas, noises, cond_noises, keep


@torch.no_grad()
def probe_loss(model: sv3d.SV3D, encoded: list[EncodedOrbit], opts: FinetuneOptions, seed: int = 1234,
               n: int = 4) -> float:
    """The loss on a FIXED draw of videos / noise levels / noises (``seed``): a training-progress probe."""
    gen = torch.Generator().manual_seed(seed)
    videos, sigmas, noises, cond_noises, keep = _draw(gen, encoded, FinetuneOptions(**{**asdict(opts),
                                                                                       "uncond_prob": 0.0}), n)
    was = model.unet.training
    model.unet.eval()
    loss = float(batch_loss(model, videos, sigmas, noises, cond_noises, keep, opts.cond_aug))
    model.unet.train(was)
    return loss


# ----------------------------------------------------------------------------- training

def state_key(base_weights: str | Path, orbits_root: str | Path, opts: FinetuneOptions) -> str:
    """Names the resumable state of one training job: base file (path, size, mtime), the training
    frame sets' files (names, sizes) and the options that change the result."""
    base = Path(base_weights).expanduser().resolve()
    st = base.stat()
    files = []
    for fs in find_frame_sets(orbits_root):
        for p in sorted(fs.rglob("*")):
            if p.is_file():
                files.append([str(p.relative_to(fs.parent)), p.stat().st_size])
    material = {"base": [str(base), st.st_size, st.st_mtime_ns], "files": files,
                "opts": {k: v for k, v in asdict(opts).items() if k != "save_every"}}
    return hashlib.sha256(json.dumps(material, sort_keys=True).encode()).hexdigest()[:20]


def _save_state(path: Path, model: sv3d.SV3D, optimizer, gen: torch.Generator, step: int, losses: list[float]) -> None:
    from humanvdm_core.workflow.atomic import atomic_path

    state = {"step": step, "losses": losses, "unet": model.unet.state_dict(), "optimizer": optimizer.state_dict(),
             "generator": gen.get_state()}
    with atomic_path(path) as tmp:
        torch.save(state, tmp)


def finetune(model: sv3d.SV3D, orbits: list[TrainingOrbit], opts: FinetuneOptions, state_dir: str | Path | None = None,
             logger: logging.Logger | None = None, stop_after: int | None = None,
             encoded: list[EncodedOrbit] | None = None) -> FinetuneResult:
    """Train ``model.unet`` in place (module docstring). ``state_dir``: where the resumable state
    lives (None: no saves, no resume). ``stop_after``: end after this many optimiser steps in total
    (an interruption, for tests); the result then has ``finished`` False. ``encoded``: the orbits
    already through :func:`encode_orbit` (else encoded here)."""
    lg = logger or log
    opts.check()
    device = model.device
    for part in (model.clip, model.encoder, model.decoder):
        part.eval()
        for p in part.parameters():
            p.requires_grad_(False)
    if encoded is None:
        encoded = [encode_orbit(model, o, opts.cond_aug) for o in orbits]
    unet = model.unet
    unet.gradient_checkpointing = opts.gradient_checkpointing and device.type == "cuda"
    for p in unet.parameters():
        p.requires_grad_(True)
    optimizer = torch.optim.AdamW(unet.parameters(), lr=opts.lr, weight_decay=0.0)
    gen = torch.Generator().manual_seed(opts.seed)
    step, losses, resumed = 0, [], 0
    state_path = Path(state_dir).expanduser() / STATE_FILE if state_dir is not None else None
    if state_path is not None and state_path.is_file():
        state = torch.load(state_path, map_location=device, weights_only=True)
        unet.load_state_dict(state["unet"])
        optimizer.load_state_dict(state["optimizer"])
        gen.set_state(state["generator"].cpu())
        step, losses, resumed = int(state["step"]), [float(x) for x in state["losses"]], int(state["step"])
        lg.info("resuming fine-tuning at step %d of %d from %s", step, opts.steps, state_path)
    unet.train()
    micro = opts.micro_batch
    while step < opts.steps and (stop_after is None or step < stop_after):
        optimizer.zero_grad(set_to_none=True)
        total, done = 0.0, 0
        while done < opts.batch_size:
            n = min(micro, opts.batch_size - done)
            videos, sigmas, noises, cond_noises, keep = _draw(gen, encoded, opts, n)
            loss = batch_loss(model, videos, sigmas, noises, cond_noises, keep, opts.cond_aug) * (n / opts.batch_size)
            loss.backward()
            total += float(loss.detach())
            done += n
        optimizer.step()
        step += 1
        report(step, opts.steps, "steps", "fine-tune SV3D")
        losses.append(total)
        if step == 1 or step % max(1, opts.steps // 10) == 0 or step == opts.steps:
            lg.info("fine-tuning step %d/%d: loss %.5f", step, opts.steps, total)
        if state_path is not None and opts.snapshot_every and step % opts.snapshot_every == 0:
            save_unet_checkpoint(model, state_path.parent / snapshot_name(step))
        if state_path is not None and (step % opts.save_every == 0 or step == opts.steps):
            _save_state(state_path, model, optimizer, gen, step, losses)
    unet.eval()
    for p in unet.parameters():
        p.requires_grad_(False)
    unet.gradient_checkpointing = False
    return FinetuneResult(step, losses, resumed, finished=step >= opts.steps)


def save_finetuned_checkpoint(base_weights: str | Path, model: sv3d.SV3D, path: str | Path) -> Path:
    """The base checkpoint with its UNet replaced by ``model.unet``: a full SV3D checkpoint in the
    official layout (the diffuse stage's ``sv3d_p_weights`` / ``sv3d_u_weights`` take it)."""
    from safetensors.torch import load_file, save_file

    from humanvdm_core.workflow.atomic import atomic_path

    sd = load_file(str(Path(base_weights).expanduser()))
    unet_sd = {sv3d.UNET_PREFIX + k: v.detach().to("cpu", torch.float32).contiguous()
               for k, v in model.unet.state_dict().items()}
    missing = set(unet_sd) - set(sd)
    if missing:
        raise ValueError(f"trained UNet keys absent from the base checkpoint: {sorted(missing)[:5]}")
    sd.update(unet_sd)
    with atomic_path(path) as tmp:
        save_file(sd, str(tmp))
    return Path(path)


def save_unet_checkpoint(model: sv3d.SV3D, path: str | Path) -> Path:
    """The UNet alone, keys with the official ``model.diffusion_model.`` prefix (an intermediate snapshot)."""
    from safetensors.torch import save_file

    from humanvdm_core.workflow.atomic import atomic_path

    sd = {sv3d.UNET_PREFIX + k: v.detach().to("cpu", torch.float32).contiguous()
          for k, v in model.unet.state_dict().items()}
    with atomic_path(path) as tmp:
        save_file(sd, str(tmp))
    return Path(path)


def snapshot_name(step: int) -> str:
    return f"unet_step_{step:06d}.safetensors"


def snapshots(state_dir: str | Path) -> list[Path]:
    """The UNet snapshots a training job kept, in step order."""
    return sorted(Path(state_dir).expanduser().glob("unet_step_*.safetensors"))


def default_state_dir(root: str | Path, key: str) -> Path:
    return Path(os.path.expanduser(str(root))) / key

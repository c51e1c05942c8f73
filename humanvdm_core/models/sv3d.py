"""SV3D (Voleti et al. 2024; ``sv3d_u`` / ``sv3d_p``): one image -> a 21-frame orbit video, offline.

Loads the official checkpoint files from https://huggingface.co/stabilityai/sv3d
(``sv3d_u.safetensors``, ``sv3d_p.safetensors``; Stability AI Community License, accepted on that
page) or a fine-tuned checkpoint in the same layout, from a local path; nothing is downloaded.
Reference: Stability-AI/generative-models (sgm), ``configs/inference/sv3d_{u,p}.yaml``,
``scripts/sampling/simple_video_sample.py`` and the sgm modules named below.

Checkpoint layout (one flat ``.safetensors`` state dict, split here by prefix; each part is built
from its tensors' shapes and loaded with :func:`~humanvdm_core.models.checkpoint.load_strict`)::

    model.diffusion_model.*                   the video UNet (:mod:`.sv3d_unet`)
    conditioner.embedders.0.open_clip.model.* the OpenCLIP ViT-H/14 image tower ``visual.*``
                                              (:mod:`.openclip_vision`; the text-tower leftovers sgm
                                              keeps after ``del model.transformer`` are dropped by name)
    conditioner.embedders.1.encoder.*         AutoencoderKLModeOnly: ``encoder.*``, ``quant_conv.*``
                                              (its unused ``decoder.*`` / ``post_quant_conv.*`` dropped)
    first_stage_model.*                       ``decoder.*``: the temporal VideoDecoder (:mod:`.sv3d_vae`)

Any other key (or a missing part) is a :class:`~humanvdm_core.models.checkpoint.CheckpointError`
listing the keys.  ``sv3d_u`` and ``sv3d_p`` are told apart by the UNet's ``label_emb.0.0.weight``
input width (``adm_in_channels``): 256 (cond_aug) or 1280 (cond_aug 256 + polar 512 + azimuth 512).
A file whose first-stage decoder has no temporal layers (sgm's ``sv3d_u.yaml`` names a plain image
``Decoder``) loads as that image decoder (:mod:`.sv3d_vae`), decoding every frame on its own.

Conditioning (sgm ``GeneralConditioner`` with the SV3D embedders, routed by output rank):

- ``crossattn`` (B*T, 1, 1024): the CLIP image embedding of the conditioning image (in [-1, 1]),
  repeated for every frame; the unconditional branch uses zeros.
- ``concat`` (B*T, 4, h, w): the VAE latent (encoder mode, NOT multiplied by the 0.18215 scale
  factor) of the conditioning image plus ``cond_aug`` * N(0, 1) noise, repeated per frame,
  concatenated to the noisy latent on the channel axis (UNet input 8 channels); zeros when unconditional.
- ``vector`` -> ``y`` (B*T, adm_in): ``ConcatTimestepEmbedderND`` = the sinusoidal
  ``timestep_embedding`` of each per-frame scalar, concatenated in this order: cond_aug (256),
  polar in radians (512), azimuth in radians (512); the same for both branches.
- ``num_video_frames`` = T and ``image_only_indicator`` = zeros (2, T) (video mode).

Sampling: ``Denoiser`` with ``VScalingWithEDMcNoise`` (c_skip = 1/(σ²+1), c_out = -σ/√(σ²+1),
c_in = 1/√(σ²+1), c_noise = ¼ ln σ); ``EDMDiscretization`` (σ_min 0.002, σ_max 700, ρ 7, then 0);
``EulerEDMSampler`` (s_churn 0: deterministic given the initial noise, x₀ = N(0, 1)·√(1+σ₀²));
``TrianglePredictionGuider`` (per-frame CFG scale ``min + (max - min) * tri(linspace(0, 1, T))``,
1.0 at the first and last frame, 2.5 in the middle).  The latents are divided by 0.18215 and
decoded ``decoding_chunk`` frames at a time (the temporal decoder sees each chunk as one clip);
the last frame is then replaced by the conditioning image, as sgm's script does.

Cameras (sv3d_p, as ``simple_video_sample.py``): polar = 90° - elevation and azimuth relative to
the last frame, ``(az - az[-1]) % 360``, both in radians.  The project's orbit
(:func:`humanvdm_core.cameras.orbit_cameras`) ends at azimuth 0 (the input view) and uses SV3D_p's
default azimuths ``linspace(0, 360, 22)[1:] % 360``, so its azimuths pass through unchanged
(:data:`AZIMUTH_SIGN`: the direction is the project's stated convention, unverified on real weights).

On CUDA the UNet and the CLIP tower run under fp16 autocast (weights stay fp32, as sgm's
``torch.autocast``); the VAE runs in fp32 (sgm disables autocast for it).  All noise comes from
one CPU generator seeded with ``seed``: same inputs and seed, same frames (on one machine).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from contextlib import nullcontext
from pathlib import Path

import numpy as np
import torch
from torch import nn

from humanvdm_core.models import openclip_vision, sv3d_unet, sv3d_vae
from humanvdm_core.models.checkpoint import (
    CheckpointError,
    cached_model,
    infer_device,
    load_strict,
    read_state_dict,
)
from humanvdm_core.workflow.errors import ConfigError

log = logging.getLogger("humanvdm.sv3d")

KINDS = ("sv3d_u", "sv3d_p")
WHAT = {"sv3d_u": "SV3D_u checkpoint (sv3d_u.safetensors)", "sv3d_p": "SV3D_p checkpoint (sv3d_p.safetensors)"}
WHERE = ("https://huggingface.co/stabilityai/sv3d (files sv3d_p.safetensors, sv3d_u.safetensors; licence: "
         "Stability AI Community License, accept it on that page after logging in)")

UNET_PREFIX = sv3d_unet.PREFIX
CLIP_PREFIX = "conditioner.embedders.0.open_clip.model."
ENCODER_PREFIX = "conditioner.embedders.1.encoder."
DECODER_PREFIX = "first_stage_model."

SCALE_FACTOR = 0.18215
SIGMA_MIN, SIGMA_MAX, RHO = 0.002, 700.0, 7.0
DEFAULT_STEPS = 50
CFG_MIN, CFG_MAX = 1.0, 2.5
COND_AUG = 1e-5
DECODING_CHUNK = 14
NUM_FRAMES = 21
SIZE = 576
ADM_CHANNELS = {256: "sv3d_u", 1280: "sv3d_p"}
VECTOR_DIMS = (("cond_aug", 256), ("polars_rad", 512), ("azimuths_rad", 512))
TINY_CONTEXT_DIM = 32
# SV3D_p azimuth = AZIMUTH_SIGN * (project azimuth - the last frame's), mod 360. +1 takes the project's
# claim (humanvdm_core.cameras) that its orbit IS SV3D_p's convention; not yet checked against the
# real weights (a -1 here would mean SV3D turns the other way: frames would mirror the cameras).
AZIMUTH_SIGN = 1.0


# ----------------------------------------------------------------------------- the model

class SV3D(nn.Module):
    """The parts of one SV3D checkpoint: ``unet``, ``clip`` (image tower), ``encoder`` (the
    conditioning-frame VAE encoder), ``decoder`` (the first-stage decoder); ``kind`` sv3d_u/sv3d_p."""

    def __init__(self, kind: str, unet: nn.Module, clip: nn.Module, encoder: nn.Module, decoder: nn.Module):
        super().__init__()
        self.kind = kind
        self.unet, self.clip, self.encoder, self.decoder = unet, clip, encoder, decoder

    @property
    def device(self) -> torch.device:
        return next(self.unet.parameters()).device


def split_checkpoint(sd: dict, path: str | Path = "checkpoint") -> dict[str, dict]:
    """``{"unet", "clip", "encoder", "decoder"}`` -> that part's tensors, prefixes stripped.

    Keys that belong to no part raise CheckpointError listing them (a different model's file)."""
    parts: dict[str, dict] = {"unet": {}, "clip": {}, "encoder": {}, "decoder": {}}
    prefixes = (("unet", UNET_PREFIX), ("clip", CLIP_PREFIX), ("encoder", ENCODER_PREFIX),
                ("decoder", DECODER_PREFIX))
    unknown = []
    for key, value in sd.items():
        for name, prefix in prefixes:
            if key.startswith(prefix):
                parts[name][key[len(prefix):]] = value
                break
        else:
            unknown.append(key)
    if unknown:
        shown = ", ".join(sorted(unknown)[:8]) + (f" (+{len(unknown) - 8} more)" if len(unknown) > 8 else "")
        raise CheckpointError(f"{path} is not an SV3D checkpoint in the sgm key layout; unexpected keys: {shown}")
    empty = [prefix for name, prefix in prefixes if not parts[name]]
    if empty:
        raise CheckpointError(f"{path} is not an SV3D checkpoint in the sgm key layout; missing keys: no "
                              f"{', '.join(p + '*' for p in empty)}")
    return parts


def kind_of(unet_config: dict, path: str | Path = "checkpoint") -> str:
    adm = unet_config["adm_in_channels"]
    if adm not in ADM_CHANNELS:
        raise CheckpointError(f"{path}: UNet vector conditioning is {adm} wide; SV3D_u has 256, SV3D_p 1280")
    return ADM_CHANNELS[adm]


def build(path: Path) -> SV3D:
    """Read, split, build and strictly load every part of an SV3D checkpoint (no cache)."""
    sd = read_state_dict(path, "SV3D checkpoint (sv3d_p.safetensors / sv3d_u.safetensors)", WHERE)
    parts = split_checkpoint(sd, path)
    cfg = sv3d_unet.config_from_state_dict(parts["unet"], str(path))
    kind = kind_of(cfg, path)
    with torch.device("meta"):  # no random init of 1.5 B parameters: every tensor is loaded next
        unet = sv3d_unet.VideoUNet(cfg)
    unet = unet.to_empty(device="cpu")
    load_strict(unet, parts["unet"], f"{kind} video UNet ({UNET_PREFIX}*)", path)
    clip = openclip_vision.build_image_embedder(parts["clip"], str(path))
    encoder = sv3d_vae.build_cond_encoder(parts["encoder"], str(path))
    decoder = sv3d_vae.build_video_decoder(parts["decoder"], str(path))
    return SV3D(kind, unet, clip, encoder, decoder).to(infer_device())


def load(path: str | Path) -> SV3D:
    """The SV3D model of ``path``, built once per process (eval mode, no grad).

    Missing file -> MissingWeightsError naming it and where to get it; wrong layout -> CheckpointError."""
    return cached_model(build, path)


def _clip_embed(model: SV3D, image: torch.Tensor) -> torch.Tensor:
    """(B, 3, H, W) in [-1, 1] -> (B, D)."""
    return model.clip.embed(image)


def _vae_encode(model: SV3D, image: torch.Tensor) -> torch.Tensor:
    """(B, 3, H, W) in [-1, 1] -> the posterior mode (B, 4, h, w), unscaled."""
    return model.encoder.encode(image)


def _vae_decode(model: SV3D, z: torch.Tensor, chunk: int) -> torch.Tensor:
    """Scaled latents (T, 4, h, w) -> frames (T, 3, H, W) in [-1, 1]."""
    return sv3d_vae.decode_chunked(model.decoder, z / SCALE_FACTOR, chunk)


# ----------------------------------------------------------------------------- sampling pieces

def edm_sigmas(steps: int, sigma_min: float = SIGMA_MIN, sigma_max: float = SIGMA_MAX, rho: float = RHO) -> torch.Tensor:
    """``steps`` EDM noise levels from σ_max down to σ_min (ρ spacing), then 0: ``steps + 1`` values."""
    ramp = torch.linspace(0, 1, steps)
    lo, hi = sigma_min ** (1 / rho), sigma_max ** (1 / rho)
    sigmas = (hi + ramp * (lo - hi)) ** rho
    return torch.cat([sigmas, sigmas.new_zeros(1)])


def triangle_cfg_scales(num_frames: int, min_scale: float = CFG_MIN, max_scale: float = CFG_MAX) -> torch.Tensor:
    """Per-frame guidance scale of sgm's TrianglePredictionGuider (period 1): ``min`` at both ends,
    ``max`` in the middle, linear in between."""
    values = torch.linspace(0, 1, num_frames)
    tri = 2 * (values - torch.floor(values + 0.5)).abs()
    return tri * (max_scale - min_scale) + min_scale


def scalar_embedding(values: torch.Tensor, dim: int) -> torch.Tensor:
    """``ConcatTimestepEmbedderND`` for one scalar per row: (N,) -> (N, dim)."""
    return sv3d_unet.timestep_embedding(values.reshape(-1).float(), dim)


def sv3d_angles(elevation_deg: float | Sequence[float], azimuths_deg: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame (polar, azimuth) in radians as sgm's SV3D_p script computes them: polar = 90° -
    elevation, azimuth relative to the last frame ``(az - az[-1]) % 360``."""
    az = np.asarray(azimuths_deg, dtype=np.float64)
    el = np.broadcast_to(np.asarray(elevation_deg, dtype=np.float64), az.shape)
    return np.deg2rad(90.0 - el), np.deg2rad((AZIMUTH_SIGN * (az - az[-1])) % 360.0)


def vector_conditioning(kind: str, num_frames: int, cond_aug: float, polars_rad: np.ndarray | None = None,
                        azimuths_rad: np.ndarray | None = None) -> torch.Tensor:
    """The UNet's ``y``: (T, 256) for sv3d_u, (T, 1280) for sv3d_p (module docstring)."""
    cols = [scalar_embedding(torch.full((num_frames,), float(cond_aug)), VECTOR_DIMS[0][1])]
    if kind == "sv3d_p":
        if polars_rad is None or azimuths_rad is None:
            raise ValueError("sv3d_p needs per-frame polar and azimuth angles")
        cols.append(scalar_embedding(torch.as_tensor(np.asarray(polars_rad), dtype=torch.float32), VECTOR_DIMS[1][1]))
        cols.append(scalar_embedding(torch.as_tensor(np.asarray(azimuths_rad), dtype=torch.float32), VECTOR_DIMS[2][1]))
    return torch.cat(cols, dim=1)


def denoiser_scalings(sigma: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """VScalingWithEDMcNoise: (c_skip, c_out, c_in, c_noise)."""
    c_skip = 1.0 / (sigma ** 2 + 1.0)
    c_out = -sigma / (sigma ** 2 + 1.0) ** 0.5
    c_in = 1.0 / (sigma ** 2 + 1.0) ** 0.5
    return c_skip, c_out, c_in, 0.25 * sigma.log()


def _autocast(device: torch.device):
    return torch.autocast("cuda", dtype=torch.float16) if device.type == "cuda" else nullcontext()


def to_model_image(image: np.ndarray, device: torch.device) -> torch.Tensor:
    """(S, S, 3|4) float in [0, 1], RGB already over white -> (1, 3, S, S) in [-1, 1]."""
    rgb = np.asarray(image, dtype=np.float32)[..., :3]
    return torch.from_numpy(np.ascontiguousarray(rgb)).permute(2, 0, 1)[None].to(device) * 2.0 - 1.0


@torch.no_grad()
def sample_latents(model: SV3D, cond_image: torch.Tensor, vector: torch.Tensor, steps: int, generator: torch.Generator,
                   cfg_min: float = CFG_MIN, cfg_max: float = CFG_MAX, cond_aug: float = COND_AUG,
                   progress: Callable[[int, int], None] | None = None) -> torch.Tensor:
    """The EDM Euler sampling loop with triangle CFG: (T, 4, h, w) latents (scaled latent space).

    ``cond_image`` (1, 3, S, S) in [-1, 1]; ``vector`` (T, adm_in); noise from ``generator`` (CPU):
    first the cond_aug noise of the conditioning image, then the initial latent noise."""
    device = model.device
    T = vector.shape[0]
    noisy_cond = cond_image + cond_aug * torch.randn(cond_image.shape, generator=generator).to(device)
    with _autocast(device):
        crossattn = _clip_embed(model, cond_image).float()  # (1, D)
    concat = _vae_encode(model, noisy_cond).float()  # (1, 4, h, w)
    _, c, h, w = concat.shape
    factor = model.unet.downsample_factor
    if h % factor or w % factor:
        raise ConfigError(f"SV3D: latent size {h}x{w} must be a multiple of {factor} (image side a multiple "
                          f"of {factor * cond_image.shape[-1] // w}); SV3D was trained at 576²")
    ctx = torch.cat([torch.zeros_like(crossattn), crossattn])[:, None, :].repeat_interleave(T, dim=0)
    cat = torch.cat([torch.zeros_like(concat), concat]).repeat_interleave(T, dim=0)
    y = vector.to(device).repeat(2, 1)
    ioi = torch.zeros(2, T, device=device)
    scales = triangle_cfg_scales(T, cfg_min, cfg_max).to(device)[:, None, None, None]
    sigmas = edm_sigmas(steps).to(device)
    x = torch.randn((T, model.unet.config["out_channels"], h, w), generator=generator).to(device)
    x = x * torch.sqrt(1.0 + sigmas[0] ** 2)
    for i in range(steps):
        sigma, nxt = sigmas[i], sigmas[i + 1]
        xin = torch.cat([x, x])
        c_skip, c_out, c_in, c_noise = denoiser_scalings(sigma)
        with _autocast(device):
            out = model.unet(torch.cat([xin * c_in, cat], dim=1), c_noise.expand(2 * T), ctx, y, T, ioi)
        denoised = out.float() * c_out + xin * c_skip
        d_u, d_c = denoised.chunk(2)
        guided = d_u + scales * (d_c - d_u)
        x = x + (nxt - sigma) * (x - guided) / sigma  # Euler step of dx/dσ = (x - D(x)) / σ
        if progress is not None:
            progress(i + 1, steps)
    return x


@torch.no_grad()
def generate_orbit(model: SV3D, image_rgba_576: np.ndarray, elevation_deg: float = 10.0,
                   azimuths_deg: Sequence[float] | None = None, steps: int = DEFAULT_STEPS, seed: int = 0,
                   cfg_min: float = CFG_MIN, cfg_max: float = CFG_MAX, cond_aug: float = COND_AUG,
                   decoding_chunk: int = DECODING_CHUNK, num_frames: int = NUM_FRAMES,
                   progress: Callable[[int, int], None] | None = None) -> np.ndarray:
    """The SV3D orbit of one preprocessed image: (T, S, S, 3) float32 in [0, 1].

    ``image_rgba_576``: (S, S, 3|4) float in [0, 1], the person centred with RGB already composited
    over WHITE (S = 576 for the real model; alpha, if any, is not used). ``azimuths_deg``: the
    project's orbit azimuths (default :func:`humanvdm_core.cameras.orbit_azimuths`; the last one is
    the input view); T = their count. ``elevation_deg``: scalar or per frame (sv3d_p only; sv3d_u
    generates at the input's own elevation). The last frame returned is the input image itself.
    """
    from humanvdm_core.cameras import orbit_azimuths

    if steps < 1:
        raise ConfigError("SV3D: steps must be >= 1")
    if decoding_chunk < 1:
        raise ConfigError("SV3D: decoding_chunk must be >= 1")
    az = orbit_azimuths(num_frames) if azimuths_deg is None else np.asarray(azimuths_deg, dtype=np.float64)
    T = len(az)
    if T < 2:
        raise ConfigError("SV3D: at least 2 frames")
    polars, azimuths = sv3d_angles(elevation_deg, az)
    vector = vector_conditioning(model.kind, T, cond_aug, polars, azimuths)
    device = model.device
    image = to_model_image(image_rgba_576, device)
    gen = torch.Generator().manual_seed(int(seed))
    z = sample_latents(model, image, vector, steps, gen, cfg_min, cfg_max, cond_aug, progress)
    frames = _vae_decode(model, z, decoding_chunk).float()
    if frames.shape[-2:] != image.shape[-2:]:
        raise CheckpointError(f"SV3D decoder returned {tuple(frames.shape[-2:])} frames for a "
                              f"{tuple(image.shape[-2:])} input: the VAE's encoder and decoder do not match")
    frames[-1:] = image  # as sgm's script: the input view is the conditioning image itself
    out = torch.clamp((frames + 1.0) / 2.0, 0.0, 1.0)
    return out.permute(0, 2, 3, 1).cpu().numpy().astype(np.float32)


# ----------------------------------------------------------------------------- photo -> frame set

MATTE_LO, MATTE_HI = 0.03, 0.12  # distance from white (max over RGB) where the matte ramps from 0 to 1


def matte_from_white(rgb: np.ndarray, lo: float = MATTE_LO, hi: float = MATTE_HI) -> np.ndarray:
    """A coverage estimate (H, W) float32 of a subject generated over a white background.

    SV3D outputs no mask: a pixel's alpha ramps from 0 to 1 as its distance from white (the largest
    of 1 - R, 1 - G, 1 - B) goes from ``lo`` to ``hi``; only the largest connected region counts
    (stray specks are dropped) and holes inside it are filled (white clothing inside the silhouette
    stays opaque).  White clothing ON the silhouette's border is lost: a known limit."""
    import cv2

    dist = (1.0 - np.asarray(rgb, dtype=np.float32)[..., :3]).max(axis=-1)
    soft = np.clip((dist - lo) / max(hi - lo, 1e-6), 0.0, 1.0)
    core = (dist > 0.5 * (lo + hi)).astype(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(core, connectivity=8)
    if n <= 1:
        return np.zeros(dist.shape, np.float32)
    keep = (labels == 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))).astype(np.uint8)
    background = np.pad(1 - keep, 1, constant_values=1)  # a border ring joins every outside pixel
    _, bg_labels = cv2.connectedComponents(background, connectivity=4)
    holes = (bg_labels[1:-1, 1:-1] != bg_labels[0, 0]) & (keep == 0)
    region = cv2.dilate(keep, np.ones((3, 3), np.uint8), iterations=2).astype(bool) | holes
    alpha = np.where(holes, 1.0, soft * region)
    return alpha.astype(np.float32)


def synthesize_orbit(photo_path: str | Path, weights: str | Path, backend: str = "sv3d_p", num_frames: int = NUM_FRAMES,
                     size: int = SIZE, elevation_deg: float = 10.0, fill: float = 0.85, steps: int = DEFAULT_STEPS,
                     seed: int = 0, cfg_min: float = CFG_MIN, cfg_max: float = CFG_MAX, cond_aug: float = COND_AUG,
                     decoding_chunk: int = DECODING_CHUNK, logger: logging.Logger | None = None):
    """The ``sv3d_u`` / ``sv3d_p`` backend of the diffuse stage: photo -> (frames, cameras, warnings).

    The same frame-set contract as :func:`humanvdm_core.body_prior.synthesize_orbit`: the photo is
    preprocessed by :func:`~humanvdm_core.body_prior.prepare_input_view` (person detected, scaled to
    ``fill`` of the frame, centred, over white: SV3D's expected input), the cameras are the project's
    SV3D_p orbit at ``elevation_deg`` (``extra``: background, fill), frames are (N, size, size, 4)
    float32: RGB from SV3D, A from :func:`matte_from_white`; the last frame (azimuth 0) is the
    preprocessed input view itself (RGB and mask)."""
    from humanvdm_core.body_prior import FOV_DEG, SUBJECT_HEIGHT, prepare_input_view
    from humanvdm_core.cameras import orbit_cameras
    from humanvdm_core.scans import framing_radius

    lg = logger or log
    model = load(weights)
    if model.kind != backend:
        raise ConfigError(f"{weights} is an {model.kind} checkpoint, but the backend is {backend}: choose "
                          f"backend {model.kind} or point the {backend} weights param at an {backend} file")
    warnings = []
    if size != SIZE:
        warnings.append(f"SV3D was trained at {SIZE}²; running at {size}² lowers quality")
    if num_frames != NUM_FRAMES:
        warnings.append(f"SV3D was trained on {NUM_FRAMES}-frame orbits; {num_frames} frames lower quality")
    view = prepare_input_view(photo_path, size, fill, (1.0, 1.0, 1.0))
    warnings += list(view.warnings)
    cameras = orbit_cameras(num_frames, size, FOV_DEG, elevation_deg, framing_radius(SUBJECT_HEIGHT, FOV_DEG, fill))
    cameras.extra.update({"background": np.ones(3, np.float64), "fill": np.float64(fill)})

    def progress(i: int, n: int) -> None:
        from humanvdm_core.workflow.progress import report

        report(i, n, "steps", f"{model.kind} sampling")
        if i == n or i % max(1, n // 5) == 0:
            lg.info("%s: sampling step %d/%d", model.kind, i, n)

    rgb = generate_orbit(model, view.rgba, elevation_deg, cameras.azimuth_deg, steps, seed, cfg_min, cfg_max,
                         cond_aug, decoding_chunk, progress=progress)
    frames = np.empty((len(rgb), size, size, 4), np.float32)
    frames[..., :3] = rgb
    for i in range(len(rgb) - 1):
        frames[i, ..., 3] = matte_from_white(rgb[i])
    frames[-1] = view.rgba
    return frames, cameras, list(dict.fromkeys(warnings))


# ----------------------------------------------------------------------------- tiny test checkpoint

def tiny_state_dict(kind: str = "sv3d_p", seed: int = 0, context_dim: int = TINY_CONTEXT_DIM) -> dict[str, torch.Tensor]:
    """A whole tiny SV3D checkpoint in the official layout (random weights under every prefix, the
    CLIP text leftovers included): tiny UNet (:func:`.sv3d_unet.tiny_config`), tiny CLIP tower with a
    ``context_dim``-wide embedding, tiny VAE encoder/decoder (downsampling 8, as the real one)."""
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS}")
    adm = 256 if kind == "sv3d_u" else 1280
    parts = ((UNET_PREFIX, sv3d_unet.tiny_state_dict(sv3d_unet.tiny_config(adm, context_dim), seed=seed)),
             (CLIP_PREFIX, openclip_vision.tiny_state_dict(seed=seed, output_dim=context_dim)),
             (ENCODER_PREFIX, sv3d_vae.tiny_cond_encoder_state_dict(seed=seed)),
             (DECODER_PREFIX, sv3d_vae.tiny_video_decoder_state_dict(seed=seed)))
    return {prefix + k: v.contiguous() for prefix, part in parts for k, v in part.items()}


def write_tiny_checkpoint(path: str | Path, kind: str = "sv3d_p", seed: int = 0) -> Path:
    """Write :func:`tiny_state_dict` as ``.safetensors`` at ``path`` (for tests); returns the path."""
    from safetensors.torch import save_file

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    save_file(tiny_state_dict(kind, seed), str(path))
    return path

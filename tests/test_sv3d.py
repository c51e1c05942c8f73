"""The SV3D backend of ``diffuse`` (humanvdm_core.models.sv3d / sv3d_unet) with a TINY random model
written in the official sgm checkpoint layout (every prefix: UNet, CLIP tower, conditioning-frame
encoder, video decoder) and loaded through the real path: key layout, config inference, the EDM
sigmas, the triangle CFG, the camera vector, a 21-frame orbit (shapes, determinism, seeds),
layout errors, missing weights (exit 3 naming the file) and the stage end to end."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("safetensors")

from humanvdm_core.errors import MissingWeightsError  # noqa: E402
from humanvdm_core.models import sv3d, sv3d_unet  # noqa: E402
from humanvdm_core.models.checkpoint import CheckpointError  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
PHOTO = REPO / "examples" / "ryota.png"
SIZE = 64  # the tiny VAE downsamples by 8 as the real one: 8x8 latents

# Official key names (relative to model.diffusion_model.), a sample of every family.
UNET_KEYS = [
    "time_embed.0.weight", "time_embed.2.bias", "label_emb.0.0.weight", "label_emb.0.2.weight",
    "input_blocks.0.0.weight", "input_blocks.1.0.in_layers.2.weight", "input_blocks.1.0.emb_layers.1.weight",
    "input_blocks.1.0.out_layers.3.weight", "input_blocks.1.0.time_stack.in_layers.2.weight",
    "input_blocks.1.0.time_stack.emb_layers.1.weight", "input_blocks.1.0.time_mixer.mix_factor",
    "input_blocks.1.1.norm.weight", "input_blocks.1.1.proj_in.weight", "input_blocks.1.1.proj_out.weight",
    "input_blocks.1.1.transformer_blocks.0.attn1.to_q.weight", "input_blocks.1.1.transformer_blocks.0.attn2.to_k.weight",
    "input_blocks.1.1.transformer_blocks.0.attn2.to_out.0.bias", "input_blocks.1.1.transformer_blocks.0.ff.net.0.proj.weight",
    "input_blocks.1.1.transformer_blocks.0.ff.net.2.weight", "input_blocks.1.1.transformer_blocks.0.norm3.weight",
    "input_blocks.1.1.time_stack.0.ff_in.net.0.proj.weight", "input_blocks.1.1.time_stack.0.norm_in.weight",
    "input_blocks.1.1.time_stack.0.attn2.to_k.weight", "input_blocks.1.1.time_pos_embed.0.weight",
    "input_blocks.1.1.time_mixer.mix_factor", "middle_block.0.time_stack.out_layers.3.weight",
    "middle_block.1.time_stack.0.attn1.to_v.weight", "middle_block.2.out_layers.0.weight", "output_blocks.0.0.skip_connection.weight", "out.0.weight",
    "out.2.weight",
]


@pytest.fixture(scope="module")
def tiny_p(tmp_path_factory) -> Path:
    return sv3d.write_tiny_checkpoint(tmp_path_factory.mktemp("sv3d") / "sv3d_p.safetensors", "sv3d_p", seed=0)


def _image(size: int = SIZE) -> np.ndarray:
    """A centred dark figure over white, RGBA (RGB already over white)."""
    ys, xs = np.mgrid[0:size, 0:size] + 0.5
    a = ((np.abs(xs - size / 2) < size * 0.15) & (np.abs(ys - size / 2) < size * 0.4)).astype(np.float32)
    rgb = np.stack([0.2 + 0.6 * xs / size, 0.3 * np.ones_like(xs), 0.8 - 0.5 * ys / size], -1).astype(np.float32)
    rgb = rgb * a[..., None] + (1.0 - a[..., None])
    return np.concatenate([rgb, a[..., None]], -1)


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "stages.diffuse", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=120, env={**os.environ, "OMP_NUM_THREADS": "1"})


# ----------------------------------------------------------------------------- layout and pieces

def test_unet_official_layout_and_config_inference():
    with torch.device("meta"):  # the full-size SV3D UNet, no memory
        net = sv3d_unet.VideoUNet(sv3d_unet.SV3D_CONFIG)
    sd = net.state_dict()
    assert set(UNET_KEYS) <= set(sd)
    assert tuple(sd["label_emb.0.0.weight"].shape) == (1280, 1280)  # sv3d_p: 256 + 512 + 512
    assert tuple(sd["time_embed.0.weight"].shape) == (1280, 320)
    assert tuple(sd["input_blocks.1.1.transformer_blocks.0.attn2.to_k.weight"].shape) == (320, 1024)
    assert tuple(sd["input_blocks.1.0.time_stack.in_layers.2.weight"].shape) == (320, 320, 3, 1, 1)
    assert {k for k in sd if k.endswith(".op.weight")} == {f"input_blocks.{i}.0.op.weight" for i in (3, 6, 9)}
    assert "output_blocks.2.1.conv.weight" in sd and "output_blocks.5.2.conv.weight" in sd
    assert not any(k.startswith("input_blocks.10.1.") for k in sd)  # no attention at the coarsest level
    assert 1.50e9 < sum(v.numel() for v in sd.values()) < 1.55e9  # SV3D's UNet: ~1.52 B parameters
    assert sv3d_unet.config_from_state_dict(sd) == sv3d_unet.SV3D_CONFIG
    tiny = sv3d_unet.tiny_state_dict(sv3d_unet.tiny_config(256, 32))
    assert sv3d_unet.config_from_state_dict(tiny) == sv3d_unet.tiny_config(256, 32)


def test_edm_sigmas():
    s = sv3d.edm_sigmas(50)
    assert len(s) == 51 and s[-1] == 0.0
    assert s[0].item() == pytest.approx(700.0, rel=1e-5) and s[-2].item() == pytest.approx(0.002, rel=1e-4)
    assert torch.all(s[1:] < s[:-1])
    step = s[:-1] ** (1 / 7)  # rho = 7: equal steps in sigma^(1/rho)
    assert torch.allclose(step[1:] - step[:-1], (step[1] - step[0]).expand(49), atol=1e-4)


def test_triangle_cfg_per_frame():
    s = sv3d.triangle_cfg_scales(21, 1.0, 2.5)
    expected = 1.0 + 1.5 * (1.0 - np.abs(np.arange(21) - 10) / 10.0)
    assert np.allclose(s.numpy(), expected, atol=1e-5)
    assert s[0] == pytest.approx(1.0) and s[-1] == pytest.approx(1.0) and s[10] == pytest.approx(2.5)


def test_camera_vector_conditioning():
    from humanvdm_core.cameras import orbit_azimuths

    az = orbit_azimuths(21)
    polar, azr = sv3d.sv3d_angles(10.0, az)
    assert np.allclose(polar, np.deg2rad(80.0)) and np.allclose(azr, np.deg2rad(az))  # last frame = 0
    assert np.allclose(sv3d.sv3d_angles(0.0, az + 30.0)[1], np.deg2rad(az))  # relative to the last frame
    y = sv3d.vector_conditioning("sv3d_p", 21, 1e-5, polar, azr)
    assert y.shape == (21, 1280)
    assert torch.allclose(y[:, :256], sv3d_unet.timestep_embedding(torch.full((21,), 1e-5), 256))
    assert torch.allclose(y[3, 256:768], sv3d_unet.timestep_embedding(torch.tensor([polar[3]]), 512)[0])
    assert torch.allclose(y[3, 768:], sv3d_unet.timestep_embedding(torch.tensor([azr[3]]), 512)[0])
    assert torch.allclose(y[-1, 768:1024], torch.ones(256))  # azimuth 0: cos part 1, sin part 0
    assert sv3d.vector_conditioning("sv3d_u", 21, 1e-5).shape == (21, 256)


# ----------------------------------------------------------------------------- the tiny model end to end

def test_tiny_checkpoint_layout_and_kind(tiny_p, tmp_path):
    from safetensors.torch import load_file

    sd = load_file(str(tiny_p))
    prefixes = ("model.diffusion_model.", "conditioner.embedders.0.open_clip.model.visual.",
                "conditioner.embedders.1.encoder.encoder.", "conditioner.embedders.1.encoder.quant_conv.",
                "first_stage_model.decoder.")
    for prefix in prefixes:
        assert any(k.startswith(prefix) for k in sd), prefix
    assert {"model.diffusion_model." + k for k in UNET_KEYS} <= set(sd)
    assert "conditioner.embedders.0.open_clip.model.logit_scale" in sd  # text leftovers, as released
    assert sv3d.load(tiny_p).kind == "sv3d_p"
    assert sv3d.load(sv3d.write_tiny_checkpoint(tmp_path / "u.safetensors", "sv3d_u")).kind == "sv3d_u"


def test_generate_orbit_shapes_determinism_and_seed(tiny_p):
    model = sv3d.load(tiny_p)
    img = _image()
    a = sv3d.generate_orbit(model, img, elevation_deg=10.0, steps=3, seed=0, decoding_chunk=7)
    b = sv3d.generate_orbit(model, img, elevation_deg=10.0, steps=3, seed=0, decoding_chunk=7)
    c = sv3d.generate_orbit(model, img, elevation_deg=10.0, steps=3, seed=1, decoding_chunk=7)
    assert a.shape == (21, SIZE, SIZE, 3) and a.dtype == np.float32
    assert 0.0 <= a.min() and a.max() <= 1.0
    assert np.array_equal(a, b)  # same seed, same frames
    assert np.abs(a[:-1] - c[:-1]).mean() > 1e-3  # another seed, other frames
    assert np.allclose(a[-1], img[..., :3], atol=1e-6)  # the last frame is the input view
    assert a[:-1].std() > 1e-3
    # sv3d_p follows the cameras: another elevation changes the frames
    d = sv3d.generate_orbit(model, img, elevation_deg=-20.0, steps=3, seed=0, decoding_chunk=7)
    assert np.abs(a[:-1] - d[:-1]).mean() > 1e-4


def test_layout_errors_list_missing_and_unexpected_keys(tiny_p, tmp_path):
    from safetensors.torch import load_file, save_file

    sd = load_file(str(tiny_p))
    extra = dict(sd)
    extra["model_ema.decay"] = torch.tensor(0.999)
    save_file(extra, str(tmp_path / "extra.safetensors"))
    with pytest.raises(CheckpointError, match="unexpected keys: model_ema.decay"):
        sv3d.build(tmp_path / "extra.safetensors")

    missing = {k: v for k, v in sd.items() if k != "model.diffusion_model.input_blocks.1.0.time_mixer.mix_factor"}
    save_file(missing, str(tmp_path / "missing.safetensors"))
    with pytest.raises(CheckpointError, match=r"missing keys: .*input_blocks\.1\.0\.time_mixer\.mix_factor"):
        sv3d.build(tmp_path / "missing.safetensors")

    no_decoder = {k: v for k, v in sd.items() if not k.startswith("first_stage_model.")}
    save_file(no_decoder, str(tmp_path / "nodec.safetensors"))
    with pytest.raises(CheckpointError, match=r"missing keys: no first_stage_model\.\*"):
        sv3d.build(tmp_path / "nodec.safetensors")

    with pytest.raises(MissingWeightsError, match="sv3d_q.safetensors.*huggingface.co/stabilityai/sv3d"):
        sv3d.load(tmp_path / "sv3d_q.safetensors")


def test_matte_from_white():
    rgb = np.ones((40, 40, 3), np.float32)
    rgb[8:32, 10:30] = 0.2  # the subject
    rgb[15:20, 15:20] = 1.0  # white clothing inside it: a hole to fill
    rgb[2, 2] = 0.0  # a speck
    a = sv3d.matte_from_white(rgb)
    assert a[20, 20] == 1.0 and a[17, 17] == 1.0  # subject and filled hole
    assert a[2, 2] == 0.0 and a[0, 39] == 0.0 and a[36, 20] == 0.0
    assert sv3d.matte_from_white(np.ones((8, 8, 3), np.float32)).max() == 0.0


# ----------------------------------------------------------------------------- the stage

def test_stage_sv3d_p_end_to_end(tiny_p, tmp_path):
    pytest.importorskip("mediapipe")
    from humanvdm_core.frames import read_cameras, read_frames

    out = tmp_path / "orbit"
    proc = _run("--photo", str(PHOTO), "--out-orbit", str(out), "--backend", "sv3d_p", "--sv3d-p-weights",
                str(tiny_p), "--resolution", str(SIZE), "--steps", "2", "--decoding-chunk", "21")
    assert proc.returncode == 0, proc.stderr
    frames, cams = read_frames(out), read_cameras(out)
    assert frames.shape == (21, SIZE, SIZE, 4) and len(cams) == 21
    assert cams.azimuth_deg[-1] == 0.0 and np.allclose(cams.elevation_deg, 10.0)
    assert np.allclose(cams.extra["background"], 1.0)
    mask = frames[-1, ..., 3]
    assert 0.05 < (mask > 0.5).mean() < 0.6  # the input view keeps the person's mask
    assert np.allclose(frames[-1, ..., :3][mask < 0.01], 1.0, atol=1e-2)  # over white


def test_stage_missing_weights_exit_3_and_wrong_kind(tiny_p, tmp_path):
    missing = tmp_path / "nowhere" / "sv3d_p.safetensors"
    proc = _run("--photo", str(PHOTO), "--out-orbit", str(tmp_path / "o1"), "--backend", "sv3d_p",
                "--sv3d-p-weights", str(missing))
    assert proc.returncode == 3, proc.stderr
    assert str(missing) in proc.stderr and "huggingface.co/stabilityai/sv3d" in proc.stderr
    assert "Community License" in proc.stderr
    proc = _run("--photo", str(PHOTO), "--out-orbit", str(tmp_path / "o2"), "--backend", "sv3d_u",
                "--sv3d-u-weights", str(tiny_p), "--resolution", str(SIZE))
    assert proc.returncode == 3 and "is an sv3d_p checkpoint" in proc.stderr, proc.stderr
    proc = _run("--photo", str(PHOTO), "--out-orbit", str(tmp_path / "o3"), "--backend", "sv3d_p",
                "--sv3d-p-weights", str(tiny_p), "--resolution", "100")
    assert proc.returncode == 3 and "multiple of 64" in proc.stderr, proc.stderr

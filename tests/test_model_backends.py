"""Tests of the real-model backends (Real-ESRGAN, CodeFormer, RIFE) with TINY randomly initialised
models saved in each official checkpoint's key layout and loaded through the real code path:
shapes, determinism, tiling, checkpoint-layout errors, missing weights (exit 3 naming the file),
the weight hash in the stage-run key, and the face path on a fixture photo."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from humanvdm_core.cameras import orbit_cameras  # noqa: E402
from humanvdm_core.errors import MissingWeightsError  # noqa: E402
from humanvdm_core.frames import frame_paths, read_cameras, write_frames  # noqa: E402
from humanvdm_core.io import read_exr  # noqa: E402
from humanvdm_core.models.checkpoint import CheckpointError  # noqa: E402
from humanvdm_core.upscale.core import UpscaleOptions, upscale_embedded  # noqa: E402

REPO = Path(__file__).resolve().parents[1]

# Key names of the official checkpoints (a sample of each layout's families).
REALESRGAN_KEYS = ["conv_first.weight", "body.0.rdb1.conv1.weight", "body.0.rdb3.conv5.bias", "conv_body.weight",
                   "conv_up1.weight", "conv_up2.weight", "conv_hr.weight", "conv_last.weight"]
CODEFORMER_KEYS = ["position_emb", "encoder.blocks.0.weight", "encoder.blocks.1.norm1.weight",
                   "quantize.embedding.weight", "generator.blocks.0.weight", "feat_emb.weight",
                   "ft_layers.0.self_attn.in_proj_weight", "ft_layers.0.self_attn.out_proj.weight",
                   "ft_layers.0.linear1.weight", "idx_pred_layer.0.weight", "idx_pred_layer.1.weight",
                   "fuse_convs_dict.32.encode_enc.conv1.weight", "fuse_convs_dict.32.scale.0.weight",
                   "fuse_convs_dict.32.shift.2.bias"]
RIFE_KEYS = ["module.block0.conv0.0.0.weight", "module.block0.conv0.1.0.bias", "module.block0.convblock.0.beta",
             "module.block0.convblock.0.conv.weight", "module.block0.lastconv.0.weight",
             "module.block3.lastconv.0.bias"]


def _seeded(seed: int = 0) -> None:
    torch.manual_seed(seed)


def save_tiny_realesrgan(path: Path, scale: int = 4, seed: int = 0) -> Path:
    from humanvdm_core.upscale.rrdbnet import RRDBNet

    _seeded(seed)
    net = RRDBNet(scale=scale, num_feat=8, num_block=1, num_grow_ch=4)
    torch.save({"params_ema": net.state_dict()}, path)  # the official wrapper
    return path


def save_tiny_codeformer(path: Path, seed: int = 0) -> Path:
    from humanvdm_core.upscale.codeformer import CodeFormer

    _seeded(seed)
    net = CodeFormer(nf=32, ch_mult=(1, 1, 1, 1), emb_dim=8, codebook_size=16, dim_embd=16, n_layers=1,
                     connect=(32, 64, 128))
    torch.save({"params_ema": net.state_dict()}, path)
    return path


def save_tiny_rife(path: Path, seed: int = 0) -> Path:
    from humanvdm_core.interpolate.rife import IFNet

    _seeded(seed)
    net = IFNet([(7, 16, 1), (12, 16, 1), (12, 8, 1), (12, 8, 1)])
    torch.save({f"module.{k}": v for k, v in net.state_dict().items()}, path)  # DataParallel prefix, as released
    return path


def frame(size: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    ys, xs = np.mgrid[0:size, 0:size] + 0.5
    alpha = np.clip(size * 0.35 - np.hypot(xs - size / 2, ys - size / 2), 0.0, 1.0).astype(np.float32)
    rgb = rng.random((size, size, 3)).astype(np.float32) * alpha[..., None] + (1.0 - alpha[..., None])
    return np.concatenate([rgb, alpha[..., None]], axis=-1)


def make_frame_set(root: Path, size: int = 24, n: int = 2) -> Path:
    write_frames(root, [frame(size, i) for i in range(n)], orbit_cameras(n, size=size), attrs={"stage": "test"})
    return root


def run_stage(module: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", module, *args], cwd=REPO, capture_output=True, text=True,
                          timeout=120, env={**__import__("os").environ, "OMP_NUM_THREADS": "1"})


# ----------------------------------------------------------------------------- Real-ESRGAN

def test_realesrgan_layout_shapes_determinism_and_alpha(tmp_path):
    from humanvdm_core.upscale import rrdbnet
    from humanvdm_core.upscale.core import BACKENDS

    path = save_tiny_realesrgan(tmp_path / "RealESRGAN_x4plus.pth")
    sd = torch.load(path, weights_only=True)["params_ema"]
    assert set(REALESRGAN_KEYS) <= set(sd)
    assert rrdbnet.config_from_state_dict(sd) == {"scale": 4, "num_feat": 8, "num_block": 1, "num_grow_ch": 4}
    f = frame(20)
    opts = UpscaleOptions(target_size=48, realesrgan_weights=str(path), tile=8)
    a, b = BACKENDS["realesrgan"](f, opts), BACKENDS["realesrgan"](f, opts)
    assert a.shape == (48, 48, 4) and a.dtype == np.float32
    assert np.array_equal(a, b)  # deterministic
    assert 0.0 <= a.min() and a.max() <= 1.0
    assert np.array_equal(a[..., 3], upscale_embedded(f, opts)[..., 3])  # alpha never goes through the model
    # the model did run: its output differs from the embedded resampler's
    assert np.abs(a[..., :3] - upscale_embedded(f, opts)[..., :3]).mean() > 1e-3


def test_realesrgan_tiling_matches_whole_frame(tmp_path):
    from humanvdm_core.upscale import rrdbnet

    net = rrdbnet.load(save_tiny_realesrgan(tmp_path / "x4.pth"))
    rgb = np.random.default_rng(1).random((30, 26, 3)).astype(np.float32)
    whole = rrdbnet.upscale_rgb(net, rgb, tile=0, tile_pad=24)
    tiled = rrdbnet.upscale_rgb(net, rgb, tile=8, tile_pad=24)  # context >= the tiny model's receptive field
    assert whole.shape == (120, 104, 3)
    assert np.abs(whole - tiled).max() < 1e-5


@pytest.mark.parametrize("scale", [2, 1])
def test_realesrgan_x2_and_x1_checkpoints(tmp_path, scale):
    from humanvdm_core.upscale import rrdbnet

    net = rrdbnet.load(save_tiny_realesrgan(tmp_path / f"x{scale}.pth", scale=scale))
    assert net.scale == scale
    out = rrdbnet.upscale_rgb(net, np.random.default_rng(0).random((13, 15, 3)).astype(np.float32), tile=8)
    assert out.shape == (13 * scale, 15 * scale, 3)  # odd sizes padded for the pixel-unshuffle and cropped


def test_wrong_checkpoint_layout_lists_missing_and_unexpected_keys(tmp_path):
    from humanvdm_core.upscale import rrdbnet

    sd = torch.load(save_tiny_realesrgan(tmp_path / "ok.pth"), weights_only=True)["params_ema"]
    sd["conv_hr_renamed.weight"] = sd.pop("conv_hr.weight")
    torch.save({"params_ema": sd}, tmp_path / "bad.pth")
    with pytest.raises(CheckpointError) as e:
        rrdbnet.build(tmp_path / "bad.pth")
    msg = str(e.value)
    assert "bad.pth" in msg and "missing keys: conv_hr.weight" in msg
    assert "unexpected keys: conv_hr_renamed.weight" in msg
    torch.save({"params_ema": {"foo": torch.zeros(1)}}, tmp_path / "foreign.pth")
    with pytest.raises(CheckpointError, match="no key 'conv_first.weight'"):
        rrdbnet.build(tmp_path / "foreign.pth")
    (tmp_path / "garbage.pth").write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match="cannot read"):
        rrdbnet.build(tmp_path / "garbage.pth")


def test_missing_weights_name_the_file_and_where_to_get_it(tmp_path):
    from humanvdm_core.interpolate import rife
    from humanvdm_core.upscale import codeformer, rrdbnet

    for mod, name, where in ((rrdbnet, "RealESRGAN_x4plus.pth", "xinntao/Real-ESRGAN"),
                             (codeformer, "codeformer.pth", "sczhou/CodeFormer"),
                             (rife, "flownet.pkl", "hzwer/Practical-RIFE")):
        with pytest.raises(MissingWeightsError) as e:
            mod.load(tmp_path / name)
        assert str(tmp_path / name) in str(e.value) and where in str(e.value)


def test_upscale_stage_cli_realesrgan_and_missing_weights(tmp_path):
    src = make_frame_set(tmp_path / "src", size=24)
    weights = save_tiny_realesrgan(tmp_path / "tiny.pth")
    r = run_stage("stages.upscale", "--frames", str(src), "--out-frames", str(tmp_path / "out"), "--target-size", "40",
                  "--backend", "realesrgan", "--realesrgan-weights", str(weights), "--tile", "16")
    assert r.returncode == 0, r.stderr
    paths = frame_paths(tmp_path / "out")
    assert len(paths) == 2 and read_exr(paths[0]).shape == (40, 40, 4)
    assert read_cameras(tmp_path / "out").width == 40
    missing = tmp_path / "nowhere" / "RealESRGAN_x4plus.pth"
    r = run_stage("stages.upscale", "--frames", str(src), "--out-frames", str(tmp_path / "out2"), "--target-size", "40",
                  "--backend", "realesrgan", "--realesrgan-weights", str(missing))
    assert r.returncode == 3
    assert str(missing) in r.stderr and "github.com/xinntao/Real-ESRGAN/releases" in r.stderr
    assert "Traceback" not in r.stderr


def test_weight_file_hash_joins_the_stage_key_only_for_its_backends(tmp_path):
    from humanvdm_core.workflow.pipeline import load_pipeline
    from humanvdm_core.workflow.scheduler import Scheduler
    from humanvdm_core.workflow.store import Store

    weights = save_tiny_realesrgan(tmp_path / "w.pth", seed=0)
    pipeline = load_pipeline(REPO / "pipeline.yaml")
    store = Store(tmp_path / "artifacts")
    sched = Scheduler(pipeline, store, overrides={"upscale": {"realesrgan_weights": str(weights)}}, progress=False)
    pipeline.stages["upscale"].backend = "embedded"
    assert sched._weight_hashes("upscale") == {}
    pipeline.stages["upscale"].backend = "realesrgan"
    first = sched._weight_hashes("upscale")
    assert set(first) == {"realesrgan_weights"} and first["realesrgan_weights"] != "missing"
    pipeline.stages["upscale"].backend = "codeformer"
    assert set(sched._weight_hashes("upscale")) == {"realesrgan_weights", "codeformer_weights"}
    pipeline.stages["upscale"].backend = "realesrgan"
    save_tiny_realesrgan(weights, seed=1)  # new weights in the same file
    sched2 = Scheduler(pipeline, Store(tmp_path / "artifacts"),
                       overrides={"upscale": {"realesrgan_weights": str(weights)}}, progress=False)
    assert sched2._weight_hashes("upscale")["realesrgan_weights"] != first["realesrgan_weights"]
    pipeline.stages["interpolate"].backend = "rife"
    assert set(sched2._weight_hashes("interpolate")) == {"rife_weights"}


# ----------------------------------------------------------------------------- CodeFormer

def test_codeformer_layout_and_restore(tmp_path):
    from humanvdm_core.upscale import codeformer

    path = save_tiny_codeformer(tmp_path / "codeformer.pth")
    sd = torch.load(path, weights_only=True)["params_ema"]
    assert set(CODEFORMER_KEYS) <= set(sd)
    net = codeformer.load(path)
    assert net.size == 128
    face = np.random.default_rng(0).random((128, 128, 3)).astype(np.float32)
    a = codeformer.restore_face(net, face, fidelity=0.7)
    assert a.shape == (128, 128, 3) and 0.0 <= a.min() and a.max() <= 1.0
    assert np.array_equal(a, codeformer.restore_face(net, face, fidelity=0.7))
    assert not np.array_equal(a, codeformer.restore_face(net, face, fidelity=0.0))  # w changes the fusion


def test_codeformer_official_config_is_read_from_shapes():
    from humanvdm_core.upscale.codeformer import CodeFormer, config_from_state_dict

    with torch.device("meta"):  # no memory: shapes only
        sd = CodeFormer().state_dict()
    assert config_from_state_dict(sd) == {"nf": 64, "ch_mult": (1, 2, 2, 4, 4, 8), "emb_dim": 256,
                                          "codebook_size": 1024, "dim_embd": 512, "n_head": 8, "n_layers": 9,
                                          "connect": (32, 64, 128, 256)}


def test_codeformer_face_path_on_a_photo(tmp_path, fixtures_dir):
    import cv2

    from humanvdm_core.upscale import faces
    from humanvdm_core.upscale.core import BACKENDS

    photo = fixtures_dir / "photos" / "pifu_ryota.png"
    if not photo.is_file():
        pytest.skip(f"{photo} not present")
    bgra = cv2.imread(str(photo), cv2.IMREAD_UNCHANGED)
    rgb = cv2.cvtColor(bgra[..., :3], cv2.COLOR_BGR2RGB).astype(np.float32) / 255.0
    found = faces.detect_faces(rgb)
    assert len(found) >= 1
    lm = found[0].landmarks
    x, y, w, h = found[0].box
    assert np.all((lm[:, 0] > x - w) & (lm[:, 0] < x + 2 * w) & (lm[:, 1] > y - h) & (lm[:, 1] < y + 2 * h))
    assert lm[0, 0] < lm[1, 0] and lm[3, 0] < lm[4, 0] and lm[0, 1] < lm[3, 1]  # eyes above mouth, left to right
    # alignment puts the landmarks on the template
    m = faces.alignment(lm, 128)
    mapped = lm @ m[:, :2].T + m[:, 2]
    assert np.abs(mapped - faces.FFHQ_TEMPLATE_512 / 4).max() < 12

    size = 160  # a small frame around the person's head keeps the test fast
    cx, cy = int(x + w / 2), int(y + h / 2)
    half = size // 2
    crop = bgra[max(cy - half, 0):max(cy - half, 0) + size, max(cx - half, 0):max(cx - half, 0) + size]
    crop = cv2.copyMakeBorder(crop, 0, size - crop.shape[0], 0, size - crop.shape[1], cv2.BORDER_REPLICATE)
    f = np.concatenate([cv2.cvtColor(crop[..., :3], cv2.COLOR_BGR2RGB), crop[..., 3:]], -1).astype(np.float32) / 255
    opts = UpscaleOptions(target_size=200, realesrgan_weights=str(save_tiny_realesrgan(tmp_path / "x4.pth")),
                          codeformer_weights=str(save_tiny_codeformer(tmp_path / "cf.pth")), tile=0)
    with_faces = BACKENDS["codeformer"](f, opts)
    background = BACKENDS["realesrgan"](f, opts)
    assert with_faces.shape == (200, 200, 4)
    assert np.array_equal(with_faces[..., 3], background[..., 3])
    diff = np.abs(with_faces[..., :3] - background[..., :3]).max(-1)
    changed = np.argwhere(diff > 1e-4)
    assert len(changed) > 100  # the face was replaced ...
    # ... only around the face (centre of the frame), and the frame corners are untouched
    cyx = changed.mean(0) / 200 * size
    assert np.hypot(cyx[0] - (cy - max(cy - half, 0)), cyx[1] - (cx - max(cx - half, 0))) < w
    assert diff[:10, :10].max() == 0 and diff[-10:, -10:].max() == 0


def test_paste_back_is_feathered_and_aligned():
    from humanvdm_core.upscale import faces

    lm = faces.FFHQ_TEMPLATE_512 / 8 + 10  # a face of 64 px at (10, 10) in a 96 px image
    m = faces.alignment(lm, 128)
    bg = np.zeros((192, 192, 3), np.float32)  # source upscaled x2
    out = faces.paste_face(bg, np.ones((128, 128, 3), np.float32), m, 2.0)
    assert out.max() == pytest.approx(1.0) and out[0, 0, 0] == 0.0
    inside = out[(10 + 32) * 2, (10 + 32) * 2, 0]
    assert inside == pytest.approx(1.0)
    ramp = out[(10 + 32) * 2, :, 0]
    assert np.any((ramp > 0.05) & (ramp < 0.95))  # a soft edge, not a hard seam


# ----------------------------------------------------------------------------- RIFE

def test_rife_layout_shapes_determinism_and_identity(tmp_path):
    from humanvdm_core.interpolate import rife
    from humanvdm_core.interpolate.core import BACKENDS, InterpolateOptions

    path = save_tiny_rife(tmp_path / "flownet.pkl")
    assert set(RIFE_KEYS) <= set(torch.load(path, weights_only=True))
    opts = InterpolateOptions(rife_weights=str(path))
    f0, f1 = frame(40, 0)[:36], frame(40, 1)[:36]  # 36 x 40: padded to 64 and cropped back
    out = BACKENDS["rife"](f0, f1, [0.25, 0.5], opts)
    assert [o.shape for o in out] == [(36, 40, 4)] * 2
    assert np.array_equal(out[1], BACKENDS["rife"](f0, f1, [0.5], opts)[0])
    # two identical frames: every warp of a constant-in-time image blends back to it (up to edge clamping)
    same = rife.interpolate_pair(rife.load(path), f0, f0, [0.5])[0]
    assert np.abs(same - f0).mean() < 0.05


def test_rife_warp_moves_pixels_by_the_flow():
    from humanvdm_core.interpolate.rife import backward_warp

    img = torch.arange(5 * 7, dtype=torch.float32).reshape(1, 1, 5, 7)
    flow = torch.zeros(1, 2, 5, 7)
    flow[:, 0] = 1.0  # sample one pixel to the right
    out = backward_warp(img, flow)
    assert torch.allclose(out[0, 0, :, :-1], img[0, 0, :, 1:], atol=1e-4)
    assert torch.allclose(out[0, 0, :, -1], img[0, 0, :, -1], atol=1e-4)  # border clamped


def test_interpolate_stage_cli_rife(tmp_path):
    src = make_frame_set(tmp_path / "src", size=32, n=3)
    weights = save_tiny_rife(tmp_path / "flownet.pkl")
    r = run_stage("stages.interpolate", "--frames", str(src), "--out-frames", str(tmp_path / "out"),
                  "--backend", "rife", "--schedule", "recursive", "--rife-weights", str(weights))
    assert r.returncode == 0, r.stderr
    paths = frame_paths(tmp_path / "out")
    assert len(paths) == 9  # 3 -> 5 -> 9
    assert np.array_equal(read_exr(paths[4]), read_exr(frame_paths(src)[1]))  # key frames unchanged
    r = run_stage("stages.interpolate", "--frames", str(src), "--out-frames", str(tmp_path / "out2"),
                  "--backend", "rife", "--rife-weights", str(tmp_path / "missing.pkl"))
    assert r.returncode == 3 and "missing.pkl" in r.stderr and "Practical-RIFE" in r.stderr


# ----------------------------------------------------------------------------- stage wiring

def test_stage_params_match_the_library_and_mark_weights():
    from humanvdm_core.interpolate import core as interpolate
    from humanvdm_core.upscale import core as upscale
    from stages.interpolate import SPEC as INTERP
    from stages.upscale import SPEC as UP

    lib = upscale.UpscaleOptions()
    assert UP.params["fidelity"].default == lib.fidelity == 0.7 and UP.params["tile"].default == lib.tile
    assert set(UP.backends) == set(upscale.BACKENDS) == {"embedded", "realesrgan", "codeformer"}
    assert set(INTERP.backends) == set(interpolate.BACKENDS) == {"embedded", "rife", "pervfi"}
    for spec, name, backends in ((UP, "realesrgan_weights", ("realesrgan", "codeformer")),
                                 (UP, "codeformer_weights", ("codeformer",)),
                                 (INTERP, "rife_weights", ("rife",)),
                                 (INTERP, "pervfi_weights", ("pervfi",)),
                                 (INTERP, "pervfi_flow_weights", ("pervfi",))):
        p = spec.params[name]
        assert p.weights and p.default.startswith("~/.cache/humanvdm/weights/")
        assert all(p.applies_to(b) for b in backends) and not p.applies_to("embedded")


def test_codeformer_stage_missing_codeformer_weights(tmp_path):
    src = make_frame_set(tmp_path / "src", size=24)
    r = run_stage("stages.upscale", "--frames", str(src), "--out-frames", str(tmp_path / "out"), "--target-size", "40",
                  "--backend", "codeformer", "--realesrgan-weights", str(save_tiny_realesrgan(tmp_path / "x4.pth")),
                  "--codeformer-weights", str(tmp_path / "codeformer.pth"))
    assert r.returncode == 3
    assert str(tmp_path / "codeformer.pth") in r.stderr and "sczhou/CodeFormer" in r.stderr
    assert "non-commercial" in r.stderr


def test_deterministic_runs_a_model_with_torch_deterministic_on_cuda_and_restores(monkeypatch):
    """``checkpoint.deterministic`` (on PerVFI, RIFE, Real-ESRGAN, CodeFormer inference): with CUDA the call
    runs under torch's deterministic algorithms (PerVFI's index_add_ splatting otherwise varies in the last
    bits between runs on a GPU, as measured on an H200), cuDNN deterministic, no autotuning, a fixed cuBLAS
    workspace; the settings are restored afterwards; without CUDA nothing changes."""
    import os

    from humanvdm_core.models.checkpoint import deterministic

    def flags() -> tuple[bool, bool, bool]:
        return (torch.are_deterministic_algorithms_enabled(), torch.backends.cudnn.deterministic,
                torch.backends.cudnn.benchmark)

    seen = []

    @deterministic
    def infer(x: int) -> int:
        seen.append(flags())
        return x + 1

    before = flags()
    monkeypatch.delenv("CUBLAS_WORKSPACE_CONFIG", raising=False)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert infer(1) == 2 and seen[-1] == before and "CUBLAS_WORKSPACE_CONFIG" not in os.environ
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert infer(2) == 3 and seen[-1] == (True, True, False)
    assert flags() == before and os.environ["CUBLAS_WORKSPACE_CONFIG"] == ":4096:8"

"""The ``finetune`` stage (humanvdm_core.models.sv3d_finetune) with the TINY random SV3D checkpoint
(official layout) on small synthetic orbits: the loss on a fixed draw goes down, an interrupted job
resumes to the same weights as an uninterrupted one, the stage writes a full checkpoint that the
diffuse backend loads, and a missing base checkpoint exits 3."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("safetensors")

from humanvdm_core.cameras import orbit_cameras  # noqa: E402
from humanvdm_core.frames import write_frames  # noqa: E402
from humanvdm_core.models import sv3d  # noqa: E402
from humanvdm_core.models import sv3d_finetune as ft  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
SIZE = 64
FRAMES = 5


def make_orbit(root: Path, seed: int = 0, n: int = FRAMES, size: int = SIZE, background=(0.5, 0.5, 0.5)) -> Path:
    """A rendered-orbit-like frame set: a coloured box that turns with the azimuth, over ``background``."""
    rng = np.random.default_rng(seed)
    cams = orbit_cameras(n, size=size)
    cams.extra["background"] = np.asarray(background, np.float64)
    ys, xs = np.mgrid[0:size, 0:size] + 0.5
    colour = rng.random(3)
    frames = []
    for i, az in enumerate(cams.azimuth_deg):
        half_w = size * (0.1 + 0.1 * abs(np.cos(np.radians(az))))
        a = ((np.abs(xs - size / 2) < half_w) & (np.abs(ys - size / 2) < size * 0.4)).astype(np.float32)
        rgb = colour * (0.6 + 0.4 * i / n) * a[..., None] + np.asarray(background) * (1 - a[..., None])
        frames.append(np.concatenate([rgb, a[..., None]], -1).astype(np.float32))
    write_frames(root, frames, cams, attrs={"stage": "test"})
    return root


@pytest.fixture(scope="module")
def tiny_base(tmp_path_factory) -> Path:
    return sv3d.write_tiny_checkpoint(tmp_path_factory.mktemp("ft") / "sv3d_p.safetensors", "sv3d_p", seed=0)


@pytest.fixture(scope="module")
def orbits_dir(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("orbits")
    make_orbit(root / "subject_a", seed=0)
    make_orbit(root / "subject_b", seed=1)
    return root


def _opts(**kw) -> ft.FinetuneOptions:
    base = {"steps": 6, "lr": 1e-3, "batch_size": 2, "micro_batch": 1, "resolution": SIZE, "seed": 0,
            "save_every": 1, "gradient_checkpointing": False}
    return ft.FinetuneOptions(**{**base, **kw})


def test_training_data_white_background_and_input_view_last(orbits_dir):
    orbits = ft.load_training_orbits(orbits_dir, SIZE)
    assert [o.name for o in orbits] == ["subject_a", "subject_b"]
    o = orbits[0]
    assert o.frames.shape == (FRAMES, 3, SIZE, SIZE)
    assert o.azimuth_deg[-1] == 0.0  # the input view is the condition, last as in SV3D
    assert torch.allclose(o.frames[:, :, 0, 0], torch.ones(FRAMES, 3), atol=1e-2)  # grey background -> white


def test_loss_goes_down_on_a_fixed_draw(tiny_base, orbits_dir):
    model = sv3d.build(tiny_base)
    orbits = ft.load_training_orbits(orbits_dir, SIZE)
    opts = _opts(steps=8, uncond_prob=0.0)
    encoded = [ft.encode_orbit(model, o, opts.cond_aug) for o in orbits]
    before = ft.probe_loss(model, encoded, opts)
    frozen = {k: v.clone() for k, v in model.encoder.state_dict().items()}
    result = ft.finetune(model, orbits, opts, None, encoded=encoded)
    after = ft.probe_loss(model, encoded, opts)
    assert result.finished and result.steps_done == 8 and len(result.losses) == 8
    assert after < 0.9 * before, (before, after)
    assert all(torch.equal(v, model.encoder.state_dict()[k]) for k, v in frozen.items())  # VAE frozen
    assert not any(p.requires_grad for p in model.unet.parameters())  # back to inference


def test_interrupted_job_resumes_to_the_same_weights(tiny_base, orbits_dir, tmp_path):
    orbits = ft.load_training_orbits(orbits_dir, SIZE)
    opts = _opts(steps=4, snapshot_every=2)
    whole = sv3d.build(tiny_base)
    ft.finetune(whole, orbits, opts, tmp_path / "whole")

    first = sv3d.build(tiny_base)
    r1 = ft.finetune(first, orbits, opts, tmp_path / "job", stop_after=3)  # "killed" after step 3
    assert not r1.finished and r1.steps_done == 3
    second = sv3d.build(tiny_base)  # a new process: fresh weights, state from disk
    r2 = ft.finetune(second, orbits, opts, tmp_path / "job")
    assert r2.resumed_from == 3 and r2.finished and len(r2.losses) == 4
    for k, v in whole.unet.state_dict().items():
        assert torch.equal(v, second.unet.state_dict()[k]), k
    assert [p.name for p in ft.snapshots(tmp_path / "job")] == ["unet_step_000002.safetensors",
                                                                "unet_step_000004.safetensors"]


def _stage(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "stages.finetune", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=120, env={**os.environ, "OMP_NUM_THREADS": "1"})


def test_stage_writes_a_loadable_checkpoint(tiny_base, orbits_dir, tmp_path):
    out = tmp_path / "ckpt"
    proc = _stage("--orbits", str(orbits_dir), "--out-checkpoint", str(out), "--base-weights", str(tiny_base),
                  "--steps", "3", "--batch-size", "2", "--lr", "0.001", "--resolution", str(SIZE),
                  "--snapshot-every", "2", "--state-dir", str(tmp_path / "state"))
    assert proc.returncode == 0, proc.stderr
    ckpt = out / "sv3d_p_finetuned.safetensors"
    model, base = sv3d.build(ckpt), sv3d.build(tiny_base)
    assert model.kind == "sv3d_p"
    changed = [k for k, v in model.unet.state_dict().items() if not torch.equal(v, base.unet.state_dict()[k])]
    assert changed  # the UNet trained ...
    for part in ("clip", "encoder", "decoder"):  # ... the rest is the base's
        a, b = getattr(model, part).state_dict(), getattr(base, part).state_dict()
        assert all(torch.equal(v, b[k]) for k, v in a.items())
    assert (out / "checkpoints" / "unet_step_000002.safetensors").is_file()
    log = json.loads((out / "train_log.json").read_text())
    assert log["steps"] == 3 and len(log["losses"]) == 3
    assert not list((tmp_path / "state").glob("*/state.pt"))  # the job's state is cleaned up


def test_stage_missing_base_weights_exit_3(orbits_dir, tmp_path):
    missing = tmp_path / "none" / "sv3d_p.safetensors"
    proc = _stage("--orbits", str(orbits_dir), "--out-checkpoint", str(tmp_path / "o"), "--base-weights",
                  str(missing))
    assert proc.returncode == 3 and str(missing) in proc.stderr, proc.stderr


def test_training_pipeline_renders_a_scan_then_finetunes_and_caches(tiny_base, tmp_path):
    """training.yaml through the scheduler: scan -> render-training-orbits -> finetune; a rerun does no work,
    a new finetune param reruns finetune alone."""
    from humanvdm_core.workflow.scheduler import read_lockfile
    from humanvdm_core.workflow.store import Store
    from testdata.procedural import write_person

    scan = write_person(tmp_path / "person", name="person", segments=8).parent
    store = tmp_path / "artifacts"
    args = [str(scan), "--pipeline", str(REPO / "training.yaml"), "--store", str(store),
            "--set", f"finetune.base_weights={tiny_base}", "--set", f"finetune.state_dir={tmp_path / 'state'}",
            "--set", "render-training-orbits.resolution=64", "--set", f"finetune.resolution={SIZE}",
            "--set", "finetune.steps=2", "--set", "finetune.batch_size=1", "--set", "finetune.snapshot_every=0"]

    def run(*extra: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "humanvdm_core.cli", "run", *args, *extra], cwd=REPO,
                              capture_output=True, text=True, timeout=300, env={**os.environ, "OMP_NUM_THREADS": "1"})

    first = run()
    assert first.returncode == 0, first.stdout + first.stderr
    assert "2 stage run(s) ran, 0 cached" in first.stdout
    ckpt = store / "runs" / "person" / "finetune" / "checkpoint" / "sv3d_p_finetuned.safetensors"
    assert sv3d.build(ckpt).kind == "sv3d_p"
    assert "0 stage run(s) ran, 2 cached" in run().stdout
    changed = run("--set", "finetune.lr=0.0001")
    assert changed.returncode == 0, changed.stdout + changed.stderr
    lock = read_lockfile(Store(store), "person")
    assert [s for s, e in lock["stages"].items() if e["status"] == "ran"] == ["finetune"]

"""End to end through the real pipeline.yaml and the `humanvdm` command, on a tiny procedural scan."""

from __future__ import annotations

import subprocess
import sys

import pytest

from humanvdm_core.frames import frame_paths, read_cameras
from humanvdm_core.procedural import write_person
from humanvdm_core.scheduler import read_lockfile
from humanvdm_core.store import Store

pytestmark = pytest.mark.slow

TINY = ["--set", "render-training-orbits.resolution=96", "--set", "upscale.target_size=128"]


def humanvdm(store, *args):
    return subprocess.run([sys.executable, "-m", "humanvdm_core.cli", *args[:1], "--store", str(store), *args[1:]],
                          capture_output=True, text=True, timeout=300)


def test_scan_runs_render_upscale_interpolate_then_only_what_changed(tmp_path):
    scan = write_person(tmp_path / "person", name="person", segments=12).parent
    store = tmp_path / "artifacts"
    first = humanvdm(store, "run", str(scan), "--until", "interpolate", *TINY)
    assert first.returncode == 0, first.stdout + first.stderr
    assert "3 stage run(s) ran, 0 cached" in first.stdout
    view = store / "runs" / "person"
    assert len(frame_paths(view / "render-training-orbits" / "orbit")) == 21
    out = view / "interpolate" / "frames"
    assert len(frame_paths(out)) == 81 and read_cameras(out).width == 128

    again = humanvdm(store, "run", str(scan), "--until", "interpolate", *TINY)
    assert "0 stage run(s) ran, 3 cached" in again.stdout

    changed = humanvdm(store, "run", str(scan), "--until", "interpolate", *TINY, "--set", "interpolate.passes=1")
    assert changed.returncode == 0
    lock = read_lockfile(Store(store), "person")
    assert [s for s, e in lock["stages"].items() if e["status"] == "ran"] == ["interpolate"]
    assert len(frame_paths(out)) == 41

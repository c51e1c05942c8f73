"""Live progress: the stage -> scheduler channel (JSON lines in $HUMANVDM_PROGRESS) and what a person sees."""

from __future__ import annotations

import io
import json
import os
import re
import select
import subprocess
import sys
import time

import pytest

from humanvdm_core.workflow import progress as P
from tests.test_cli import cli, write_input
from tests.toyproject import ToyProject


@pytest.fixture
def toy(tmp_path) -> ToyProject:
    return ToyProject(tmp_path)


def test_channel_round_trip_rate_eta_and_throttle(tmp_path, monkeypatch):
    path = tmp_path / "p.progress"
    monkeypatch.delenv(P.PROGRESS_ENV, raising=False)
    P.report(1, 10)  # no channel: nothing happens
    assert not path.exists()
    monkeypatch.setenv(P.PROGRESS_ENV, str(path))
    for i in range(1, 101):  # a burst: throttled, but the phase's first and last lines are kept
        P.report(i, 100, "it", "optimise")
    lines = [json.loads(ln) for ln in path.read_text().splitlines()]
    assert lines[0]["done"] == 1 and lines[-1]["done"] == 100 and len(lines) < 10
    assert set(lines[0]) == {"t", "done", "total", "unit", "what"}

    reader = P.ProgressReader(path)
    assert reader.poll()["done"] == 100
    now = time.time()
    with open(path, "a") as f:  # a new phase at 5 units/s, its last line incomplete (being written)
        for k, t in enumerate([now, now + 1.0, now + 2.0]):
            f.write(json.dumps({"t": t, "done": 5 * k, "total": 40, "unit": "frames", "what": "render"}) + "\n")
        f.write('{"t": 1, "done"')
    rec = reader.poll()
    assert rec["what"] == "render" and rec["done"] == 10
    assert reader.rate == pytest.approx(5.0) and reader.eta_s == pytest.approx(6.0)  # its last record is "now"


def test_plain_lines_name_each_active_run_with_its_own_progress(toy):
    """Two inputs, --jobs 2, no terminal: periodic plain lines per active run (phase, count, rate, ETA)."""
    a, b = write_input(toy, "a", "hello"), write_input(toy, "b", "world")
    res = cli(toy, "run", a, b, "--kind", "text", "--jobs", "2", "--set", "shout.sleep=2.4",
              "--set", "shout.steps=12", "--progress-interval", "0.4")
    assert res.returncode == 0, res.stdout + res.stderr
    err = res.stderr
    for name in ("a", "b"):
        assert re.search(rf"^{name}/shout: started \(log: .*shout\.log\)$", err, re.M), err
        status = re.findall(rf"^\[ *\d+:\d\d\] {name}/shout: shouting (\d+)/12 steps \(\d+%\)(.*)$", err, re.M)
        assert status, err
        assert any("steps/s" in rest and "ETA" in rest and "elapsed" in rest for _, rest in status), status
        assert re.search(rf"^{name}/shout: ran in [\d.]+ s$", err, re.M)
    assert re.search(r"stage runs: \d/6 done.*, 2 running", err), err
    assert (toy.store.root / "runs" / "a" / "logs" / "shout.progress").read_text().count("\n") >= 2

    again = cli(toy, "run", a, "--kind", "text", "--set", "shout.sleep=2.4", "--set", "shout.steps=12")
    assert "a/shout: cached" in again.stderr and "a/report: cached" in again.stderr
    quiet = cli(toy, "run", a, "--kind", "text", "--set", "shout.sleep=2.4", "--set", "shout.steps=12", "--quiet")
    assert quiet.returncode == 0 and quiet.stderr == "" and "0 stage run(s) ran, 3 cached" in quiet.stdout


@pytest.mark.skipif(not hasattr(os, "openpty"), reason="needs a pseudo-terminal")
def test_live_display_on_a_terminal(toy):
    """On a terminal: rich's live table shows the running stage's phase and bar; finished runs are listed."""
    inp = write_input(toy, "a", "hello")
    master, slave = os.openpty()
    cmd = [sys.executable, "-m", "humanvdm_core.cli", "run", "--pipeline", str(toy.pipeline_path),
           "--store", str(toy.store.root), inp, "--kind", "text", "--set", "shout.sleep=2", "--set", "shout.steps=8"]
    env = dict(os.environ, TERM="xterm", COLUMNS="150", LINES="40")
    proc = subprocess.Popen(cmd, stdin=slave, stdout=slave, stderr=slave, env=env)
    os.close(slave)
    out = b""
    deadline = time.time() + 120
    while time.time() < deadline:
        ready, _, _ = select.select([master], [], [], 0.5)
        if ready:
            try:
                chunk = os.read(master, 65536)
            except OSError:
                break
            if not chunk:
                break
            out += chunk
        elif proc.poll() is not None:
            break
    proc.wait(timeout=30)
    os.close(master)
    text = re.sub(r"\x1b\[[0-9;?]*[A-Za-z]", "", out.decode(errors="replace"))
    assert proc.returncode == 0, text
    assert re.search(r"a\s+shout\s+shouting\s+\S*\s*\d/8 steps", text), text
    assert "━" in text and "elapsed" in text
    assert "a/shout: ran in" in text and "a/report: ran in" in text


def test_live_table_renders_rate_and_eta():
    from rich.console import Console

    d = P.Display("plain", total=3, interval=60, stream=io.StringIO())
    try:
        d.started(1, "ryota", "splat-optimize", None, None)
        active = d._active[1]
        active.reader = P.ProgressReader(os.devnull)
        now = time.time()
        active.reader.last = {"t": now, "done": 120, "total": 500, "unit": "it", "what": "optimise Gaussians"}
        active.reader._history.extend([(now - 10.0, 100.0), (now, 120.0)])
        buf = io.StringIO()
        Console(file=buf, width=160, color_system=None).print(d._render())
        line = d.describe(active)
    finally:
        d.close()
    assert "ryota" in buf.getvalue() and "120/500 it" in buf.getvalue() and "ETA 3:10" in buf.getvalue()
    assert line.startswith("ryota/splat-optimize: optimise Gaussians 120/500 it (24%), 2.0 it/s, ETA 3:10")

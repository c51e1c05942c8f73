"""``python -m benchmarks.experiments --quick`` on a subset: every run goes through the scheduler's cache,
a second call recomputes nothing, and a stability case that fails its check is a row, not an error."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

pytestmark = [pytest.mark.slow, pytest.mark.fixtures]


def experiments(tmp_path: Path, *args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "benchmarks.experiments", "--quick", "--work", str(tmp_path / "work"),
           "--results", str(tmp_path / "results"), *args]
    return subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, env=env, timeout=900)


def test_quick_experiments_cached_and_failures_are_rows(tmp_path, fixtures_dir):
    # protocol on Mei; the stability suite's reference case (the very same photo, so every stage run is
    # reused) and a 100 px photo that must be refused; an IoU threshold no case can reach, so the
    # reference case fails its check and must still come back as a row
    args = ("--only", "protocol,stability", "--cases", "reference_front,tiny_100px", "--side-iou-threshold", "1.01")
    first = experiments(tmp_path, *args)
    out = first.stdout + first.stderr
    assert first.returncode == 0, out
    assert "[protocol 1/1] mei body-prior: 6 stage run(s) ran" in first.stdout, out
    assert "[stability 1/2] reference_front: 0 stage run(s) ran, 6 reused" in first.stdout, out
    assert f"results in {tmp_path / 'results'}" in first.stdout

    results = tmp_path / "results"
    protocol = json.loads((results / "experiments_quick_protocol.json").read_text())
    mei = protocol["result"]["table"]["body-prior"]["renderpeople_rp_mei_posed_001"]
    for src in ("orbit", "gaussians"):
        assert len(mei[src]["psnr"]) == 4 and all(10 < x < 60 for x in mei[src]["psnr"])
        assert 0 < mei[src]["mean"]["iou"] <= 1
    assert 0 < mei["gaussians"]["mean"]["masked_ssim"] <= 1 and mei["num_gaussians"] > 100 and mei["time_s"] > 0
    assert protocol["result"]["paper_table1"]["psnr"] == 20.068
    assert (results / "experiments_quick_protocol_mei_body-prior.png").stat().st_size > 10_000

    stab = json.loads((results / "experiments_quick_stability.json").read_text())
    rows = {r["case"]: r for r in stab["result"]["cases"]}
    ref, tiny = rows["reference_front"], rows["tiny_100px"]
    assert ref["passed"] is False and 0 < ref["side_iou"] < 1.01  # measured, below the impossible threshold
    assert ref["checks"][0]["passed"] is False and ref["run"]["returncode"] == 0
    assert tiny["passed"] is True and tiny["run"]["returncode"] != 0  # refused clearly: a pass, and a row
    assert "too small" in tiny["checks"][0]["seen"] and "tiny_100px.png" in tiny["checks"][0]["seen"]
    for case in rows:
        assert (results / f"experiments_quick_stability_{case}.png").stat().st_size > 5_000
    assert "| reference_front |" in (results / "experiments_quick_report.md").read_text()

    second = experiments(tmp_path, *args)
    assert second.returncode == 0, second.stdout + second.stderr
    assert "0 stage run(s) ran, 12 reused from the cache" in second.stdout, second.stdout
    again = json.loads((results / "experiments_quick_protocol.json").read_text())
    assert again["stage_runs"]["ran"] == 0 and again["stage_runs"]["reused"] == 6
    assert again["result"]["table"]["body-prior"]["renderpeople_rp_mei_posed_001"]["gaussians"]["psnr"] == \
        mei["gaussians"]["psnr"]

    # a call that runs one part keeps the other part's table in the report, marked as from earlier
    third = experiments(tmp_path, "--only", "stability", "--cases", "tiny_100px")
    assert third.returncode == 0, third.stdout + third.stderr
    report = (results / "experiments_quick_report.md").read_text()
    assert "## Protocol" in report and "| tiny_100px |" in report
    assert "Not run by this call, from earlier calls: protocol" in report

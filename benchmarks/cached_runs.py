"""Pipeline runs for the experiments (``benchmarks.experiments``): through the scheduler and its cache.

Every run is ``<this python> -m humanvdm_core.cli run PHOTO --store STORE --no-progress --set ...`` in
a new process from this repository (as ``benchmarks.bench_protocol`` runs it), so a stage run whose
key is already in the store is reused, not recomputed. What a run did is read from its own output:

- the summary line ``N input(s): R stage run(s) ran, C cached, F failed, S skipped``;
- the per-stage lines ``<subject>/<stage>: ran in 1.2 s`` / ``: cached`` / ``: failed ...`` (so a
  failed stage is told apart from an older successful output still linked in ``runs/<subject>``);
- the ``warning <subject>/<stage>: ...`` and ``FAILED <subject>/<stage>: ...`` lines.

Times come from the run's lockfile (``runs/<subject>/humanvdm.lock``, via
:func:`humanvdm_core.workflow.scheduler.read_lockfile`): each stage's ``wall_s`` is the time the stage run took
when it was computed, also when this call reused it, so a fully cached rerun reports the same time.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SUMMARY_RE = re.compile(r"(\d+) input\(s\): (\d+) stage run\(s\) ran, (\d+) cached, (\d+) failed, (\d+) skipped")
STAGE_RE = re.compile(r"^(?P<subject>[^\s/]+)/(?P<stage>[\w-]+): (?P<state>ran|cached|failed|skipped|blocked)\b",
                      re.MULTILINE)
RECONSTRUCTION_STAGES = ("diffuse", "upscale", "interpolate", "fit-smpl", "splat-optimize")  # photo -> Gaussians


@dataclass
class PipelineRun:
    """One ``humanvdm run`` call: what it was, what it did, what it said."""

    subject: str
    command: str
    returncode: int
    wall_s: float
    ran: int = 0
    cached: int = 0
    failed: int = 0
    skipped: int = 0
    states: dict[str, str] = field(default_factory=dict)  # stage -> ran | cached | failed | skipped
    warnings: list[str] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)
    output: str = ""

    def ok(self, stage: str) -> bool:
        """Whether ``stage`` produced its outputs in this run (ran or reused)."""
        return self.states.get(stage) in ("ran", "cached")

    def record(self) -> dict:
        """The shape ``benchmarks.bench_protocol.run_pipeline`` returns (read by its ``run_scan``)."""
        return {"command": self.command, "returncode": self.returncode, "wall_s": round(self.wall_s, 2),
                "log_tail": self.output[-3000:]}

    def summary(self) -> dict:
        return {"command": self.command, "returncode": self.returncode, "call_wall_s": round(self.wall_s, 2),
                "ran": self.ran, "cached": self.cached, "failed": self.failed, "skipped": self.skipped,
                "states": self.states, "warnings": self.warnings, "errors": self.errors}


@dataclass
class Tally:
    """Stage runs over many pipeline calls: how many ran, how many were reused from the cache."""

    calls: int = 0
    ran: int = 0
    cached: int = 0
    failed: int = 0
    skipped: int = 0

    def add(self, run: PipelineRun) -> None:
        self.calls += 1
        self.ran += run.ran
        self.cached += run.cached
        self.failed += run.failed
        self.skipped += run.skipped

    def copy(self) -> Tally:
        return Tally(self.calls, self.ran, self.cached, self.failed, self.skipped)

    def since(self, before: Tally) -> Tally:
        """What was added after ``before`` (a copy taken earlier)."""
        return Tally(self.calls - before.calls, self.ran - before.ran, self.cached - before.cached,
                     self.failed - before.failed, self.skipped - before.skipped)

    def as_dict(self) -> dict:
        return {"pipeline_calls": self.calls, "ran": self.ran, "reused": self.cached, "failed": self.failed,
                "skipped": self.skipped}

    def line(self) -> str:
        return (f"{self.calls} pipeline call(s): {self.ran} stage run(s) ran, {self.cached} reused from the cache, "
                f"{self.failed} failed, {self.skipped} skipped")


def parse_output(subject: str, text: str) -> dict:
    """Counts, per-stage states, warnings and errors of one subject from a run's stdout + stderr."""
    counts = dict(ran=0, cached=0, failed=0, skipped=0)
    found = SUMMARY_RE.findall(text)
    if found:
        _, ran, cached, failed, skipped = (int(x) for x in found[-1])
        counts = dict(ran=ran, cached=cached, failed=failed, skipped=skipped)
    states = {m["stage"]: m["state"] for m in STAGE_RE.finditer(text) if m["subject"] == subject}
    warnings = [ln.strip() for ln in text.splitlines() if ln.startswith(f"warning {subject}/")]
    errors = [ln.strip() for ln in text.splitlines() if ln.startswith(f"FAILED {subject}/")]
    return {**counts, "states": states, "warnings": warnings, "errors": errors}


def run_pipeline(photo: Path, store: Path, sets: list[str], jobs: int = 1, until: str | None = None) -> PipelineRun:
    """``humanvdm run photo --store store --set ...`` in a new process; the subject is the photo's stem."""
    cmd = [sys.executable, "-m", "humanvdm_core.cli", "run", str(photo), "--store", str(store), "--no-progress",
           "--jobs", str(jobs)]
    if until:
        cmd += ["--until", until]
    for s in sets:
        cmd += ["--set", s]
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), env.get("PYTHONPATH")]))
    env.setdefault("OMP_NUM_THREADS", "1")
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, env=env)
    wall = time.perf_counter() - t0
    text = proc.stdout + "\n" + proc.stderr
    subject = photo.stem
    return PipelineRun(subject=subject, command=" ".join(["humanvdm", *cmd[3:]]), returncode=proc.returncode,
                       wall_s=wall, output=text, **parse_output(subject, text))


def stage_times(store: Path, subject: str) -> dict[str, float]:
    """Per stage, the wall time its (possibly reused) stage run took when computed, from the lockfile."""
    from humanvdm_core.workflow.scheduler import read_lockfile
    from humanvdm_core.workflow.store import Store

    lock = read_lockfile(Store(store), subject)
    return {k: float(v["wall_s"]) for k, v in (lock.get("stages") or {}).items() if v.get("wall_s") is not None}


def pipeline_time(times: dict[str, float]) -> float:
    """Whole-pipeline time per photo: the reconstruction stages' wall times summed (``evaluate`` left out)."""
    return float(sum(times.get(s, 0.0) for s in RECONSTRUCTION_STAGES))


def num_gaussians(run_dir: Path) -> int | None:
    """``num_gaussians`` of splat-optimize's ``train_log.json`` in a run folder, None when absent."""
    path = run_dir / "splat-optimize" / "gaussians" / "train_log.json"
    try:
        value = json.loads(path.read_text()).get("num_gaussians")
    except (OSError, ValueError):
        return None
    return int(value) if value is not None else None

"""The Ray executor on a real Ray instance started here (``ray.init`` with 2 CPUs), on the toy pipeline.

- the same subjects run locally and on Ray give the same artifacts (ids) and the same lockfiles but
  for the timings; a rerun on Ray is all cache hits and submits nothing;
- a Ray worker killed mid-stage (SIGKILL) is retried by Ray: the stage process of the killed attempt
  dies with it, the retry starts from an empty staging folder, and one complete result is committed;
- a user error (exit 3) is not retried, and the summary lists it with its log, as locally;
- ``humanvdm run --executor ray --address ...`` connects to a running cluster.

Skipped when Ray is not installed (``pip install -e '.[cluster]'``).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time

import pytest

ray = pytest.importorskip("ray", reason="Ray is not installed (the 'cluster' extra)")
psutil = pytest.importorskip("psutil")

from humanvdm_core.workflow.executors import RETRY_NOTE, RayExecutor  # noqa: E402
from humanvdm_core.workflow.pipeline import load_pipeline  # noqa: E402
from humanvdm_core.workflow.scheduler import CACHED, RAN, Scheduler, read_lockfile  # noqa: E402
from humanvdm_core.workflow.store import Store  # noqa: E402
from tests.toyproject import ToyProject  # noqa: E402

pytestmark = pytest.mark.slow

TIMINGS = ("wall_s", "peak_rss_mb")


@pytest.fixture(scope="module")
def ray_cluster():
    """A Ray instance of 2 CPUs for this module; its address for a second driver (the CLI)."""
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, configure_logging=False)
    try:
        yield ray.get_runtime_context().gcs_address
    finally:
        ray.shutdown()


class CountingRayExecutor(RayExecutor):
    """Counts what reaches the cluster."""

    def __init__(self) -> None:
        super().__init__()
        self.submitted = 0

    def run(self, command):
        self.submitted += 1
        return super().run(command)


def _without_timings(lock: dict) -> dict:
    return {**lock, "stages": {s: {k: v for k, v in e.items() if k not in TIMINGS} for s, e in lock["stages"].items()}}


def test_ray_gives_the_local_artifacts_and_lockfiles_and_cached_runs_never_reach_it(tmp_path, ray_cluster):
    toy = ToyProject(tmp_path)
    subjects = [toy.subject("a", "hello world"), toy.subject("b", "x" * 25)]
    local = toy.scheduler(jobs=2).run(subjects)
    ray_store = Store(tmp_path / "ray-artifacts")
    for s in subjects:
        assert ray_store.import_path(s.source) == s.input_id
    executor = CountingRayExecutor()
    on_ray = Scheduler(load_pipeline(toy.pipeline_path), ray_store, progress=False, jobs=8, executor=executor).run(subjects)
    assert on_ray.ok and executor.submitted == 6
    assert [(r.label, r.state, r.outputs) for r in on_ray.runs] == [(r.label, r.state, r.outputs) for r in local.runs]
    for s in subjects:
        assert _without_timings(read_lockfile(ray_store, s.name)) == _without_timings(read_lockfile(toy.store, s.name))
    assert sorted(ray_store.all_ids()) == sorted(toy.store.all_ids())  # the same bytes
    assert ray_store.verify().corrupt == [] and list((ray_store.root / "tmp").iterdir()) == []

    again = CountingRayExecutor()
    rerun = Scheduler(load_pipeline(toy.pipeline_path), ray_store, progress=False, jobs=8, executor=again).run(subjects)
    assert {r.state for r in rerun.runs} == {CACHED} and again.submitted == 0


def test_a_worker_killed_mid_stage_is_retried_and_leaves_nothing_complete(tmp_path, ray_cluster):
    toy = ToyProject(tmp_path)
    subj = toy.subject("a", "slow text")
    sched = Scheduler(load_pipeline(toy.pipeline_path), toy.store, progress=False, executor=RayExecutor(),
                      overrides={"shout": {"sleep": 4.0}})
    result = {}
    runner = threading.Thread(target=lambda: result.setdefault("summary", sched.run([subj])))
    runner.start()
    stage = _wait_for_stage_process(toy, timeout=60)
    worker = stage.parent()
    assert worker.pid != os.getpid()  # a Ray worker process runs it, not this driver
    os.kill(worker.pid, signal.SIGKILL)  # the Ray worker running the task, mid-stage
    _, alive = psutil.wait_procs([stage], timeout=5)
    assert alive == [], "the stage process outlived its worker"
    runner.join(timeout=90)
    assert not runner.is_alive()
    by = {r.stage: r for r in result["summary"].runs}
    assert [by[s].state for s in ("shout", "measure", "report")] == [RAN, RAN, RAN]
    assert toy.ran() == ["shout", "measure", "report"]  # the killed attempt never finished
    log = by["shout"].log.read_text()
    assert RETRY_NOTE in log and log.count("$ ") == 2
    assert list((toy.store.root / "tmp").iterdir()) == []
    outputs = read_lockfile(toy.store, "a")["stages"]["shout"]["outputs"]["out"]
    assert (toy.store.object_path(outputs) / "text.txt").read_text() == "slow text"
    assert toy.store.verify().corrupt == []


def _wait_for_stage_process(toy, timeout: float):
    end = time.time() + timeout
    while time.time() < end:
        if any((toy.store.root / "tmp").glob("shout-*/out")):
            for p in psutil.process_iter(["cmdline"]):
                if f"{toy.pkg}.shout" in " ".join(p.info["cmdline"] or []):
                    return p
        time.sleep(0.05)
    raise AssertionError("the stage never started")


def test_user_error_is_not_retried_and_listed_with_its_log_by_the_command(tmp_path, ray_cluster):
    toy = ToyProject(tmp_path)
    inputs = {}
    for name, text in {"one": "first", "two": "FAIL"}.items():
        inputs[name] = toy.root / "inputs" / f"{name}.txt"
        inputs[name].write_text(text)
    cmd = [sys.executable, "-m", "humanvdm_core.cli", "run", "--pipeline", str(toy.pipeline_path), "--store",
           str(toy.store.root), *map(str, inputs.values()), "--kind", "text", "--no-progress",
           "--executor", "ray", "--address", ray_cluster]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert res.returncode == 1, res.stdout + res.stderr
    assert "2 input(s): 3 stage run(s) ran, 0 cached, 1 failed, 2 skipped" in res.stdout
    lines = res.stdout.splitlines()
    failed = lines.index("FAILED two/shout: shout: this text cannot be shouted")
    log = toy.store.root / "runs" / "two" / "logs" / "shout.log"
    assert lines[failed + 1] == f"  log: {log}"
    text = log.read_text()
    assert text.count("$ ") == 1 and RETRY_NOTE not in text  # one attempt: a user error is not retried
    assert read_lockfile(toy.store, "one")["stages"]["report"]["status"] == "ran"
    assert not read_lockfile(toy.store, "two")
    assert len(list((toy.store.root / "runcache").glob("*/*.json"))) == 3  # one's three stage runs only

"""The ``humanvdm`` command: real processes sharing a store, interruption, and the subcommands."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time

import pytest

from humanvdm_core.workflow.scheduler import read_lockfile
from humanvdm_core.workflow.store import Store
from tests.toyproject import ToyProject


@pytest.fixture
def toy(tmp_path) -> ToyProject:
    return ToyProject(tmp_path)


def cli(toy, *args, background=False, **popen):
    """Run ``humanvdm`` on the toy project; ``background`` returns the Popen at once."""
    cmd = [sys.executable, "-m", "humanvdm_core.cli", *args[:1], "--pipeline", str(toy.pipeline_path),
           "--store", str(toy.store.root), *args[1:]]
    if background:
        return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, **popen)
    return subprocess.run(cmd, capture_output=True, text=True, timeout=120)


def write_input(toy, name, text):
    p = toy.root / "inputs" / f"{name}.txt"
    p.write_text(text)
    return str(p)


def test_run_status_show_and_dry_run(toy):
    inp = write_input(toy, "a", "hello")
    dry = cli(toy, "run", inp, "--kind", "text", "--dry-run")
    assert dry.returncode == 0 and "never run for this input" in dry.stdout
    assert toy.ran() == []
    first = cli(toy, "run", inp, "--kind", "text", "--no-progress")
    assert first.returncode == 0, first.stdout + first.stderr
    assert "3 stage run(s) ran, 0 cached" in first.stdout
    again = cli(toy, "run", inp, "--kind", "text")
    assert "0 stage run(s) ran, 3 cached" in again.stdout
    st = cli(toy, "status", inp, "--kind", "text", "--set", "measure.bucket=3")
    assert "params changed (bucket: 10 -> 3)" in st.stdout and "reruns only if its input changes" in st.stdout
    show = cli(toy, "show", "a")
    assert show.returncode == 0 and "measure" in show.stdout
    dag = cli(toy, "dag")
    assert "shout" in dag.stdout and "measure" in dag.stdout


def test_bad_set_fails_before_running(toy):
    inp = write_input(toy, "a", "hello")
    res = cli(toy, "run", inp, "--kind", "text", "--set", "measure.bukket=3")
    assert res.returncode == 2 and "stage measure: unknown param(s) ['bukket']" in res.stderr
    assert toy.ran() == []


def test_batch_with_a_failing_input_reports_it_and_exits_nonzero(toy):
    folder = toy.root / "batch"
    folder.mkdir()
    for name, text in {"one": "first", "two": "FAIL", "three": "the third one, much longer"}.items():
        (folder / f"{name}.txt").write_text(text)
    res = cli(toy, "run", str(folder / "one.txt"), str(folder / "two.txt"), str(folder / "three.txt"),
              "--kind", "text", "--jobs", "2")
    assert res.returncode == 1
    assert "FAILED two/shout: shout: this text cannot be shouted" in res.stdout
    assert "log: " in res.stdout and "two/logs/shout.log" in res.stdout
    assert read_lockfile(toy.store, "one")["stages"]["report"]["status"] == "ran"
    assert read_lockfile(toy.store, "three")["stages"]["report"]["status"] == "ran"


def test_two_processes_on_one_store_compute_once_and_agree(toy):
    inp = write_input(toy, "a", "shared work")
    procs = [cli(toy, "run", inp, "--kind", "text", "--set", "shout.sleep=1.5", "--no-progress", background=True)
             for _ in range(2)]
    outs = [p.communicate(timeout=120)[0] for p in procs]
    assert [p.returncode for p in procs] == [0, 0], outs
    assert toy.ran().count("shout") == 1  # the second process waited for the first and reused its result
    assert Store(toy.store.root).verify().corrupt == []


def _wait_for_staging(toy, timeout=30.0):
    tmp = toy.store.root / "tmp"
    end = time.time() + timeout
    while time.time() < end:
        if any(tmp.glob("shout-*/out")):
            return
        time.sleep(0.05)
    raise AssertionError("the stage never started")


def test_killed_run_leaves_nothing_complete_and_rerun_recovers(toy):
    inp = write_input(toy, "a", "slow text")
    before = set(Store(toy.store.root).all_ids())
    p = cli(toy, "run", inp, "--kind", "text", "--set", "shout.sleep=30", background=True, start_new_session=True)
    _wait_for_staging(toy)
    os.killpg(p.pid, signal.SIGKILL)  # the scheduler and its stage, mid-run
    p.wait(timeout=30)
    store = Store(toy.store.root)
    assert set(store.all_ids()) - before <= {i for i in store.all_ids() if (store.object_path(i) / "input.txt").exists()}
    assert not list((store.root / "runcache").glob("*/*.json"))
    res = cli(toy, "run", inp, "--kind", "text")
    assert res.returncode == 0 and "3 stage run(s) ran" in res.stdout
    assert store.verify().corrupt == []


def test_ctrl_c_stops_the_stage_and_exits_130(toy):
    inp = write_input(toy, "a", "slow text")
    # as from a terminal: a shell without job control starts background jobs (a test run with `&`)
    # with SIGINT ignored, and Python then installs no KeyboardInterrupt handler
    p = cli(toy, "run", inp, "--kind", "text", "--set", "shout.sleep=30", "--no-progress", background=True,
            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    _wait_for_staging(toy)
    p.send_signal(signal.SIGINT)
    out, _ = p.communicate(timeout=30)
    assert p.returncode == 130 and "interrupted" in out
    assert not list((toy.store.root / "runcache").glob("*/*.json"))


def test_verify_and_gc_commands(toy):
    inp = write_input(toy, "a", "x" * 25)
    cli(toy, "run", inp, "--kind", "text")
    cli(toy, "run", inp, "--kind", "text", "--set", "measure.bucket=5")
    ok = cli(toy, "verify")
    assert ok.returncode == 0 and "0 corrupt" in ok.stdout
    gc = cli(toy, "gc")
    assert gc.returncode == 0 and "removed 2 unreferenced artifacts" in gc.stdout
    lock = read_lockfile(toy.store, "a")
    obj = Store(toy.store.root).object_path(lock["stages"]["report"]["outputs"]["out"]) / "report.txt"
    obj.chmod(0o644)
    obj.write_text("tampered")
    bad = cli(toy, "verify")
    assert bad.returncode == 1 and "1 corrupt" in bad.stdout


def test_params_lists_every_stage_param_and_run_help_points_there(toy):
    out = cli(toy, "params")
    assert out.returncode == 0, out.stderr
    assert "shout.steps = 0  (int)" in out.stdout and "sleep in this many steps" in out.stdout
    assert "measure.bucket = 10  (int)" in out.stdout and "backend: embedded (default)" in out.stdout
    one = cli(toy, "params", "measure")
    assert "measure.bucket" in one.stdout and "shout.times" not in one.stdout
    assert cli(toy, "params", "nope").returncode == 2
    assert "shout.upper = False" in cli(toy, "dag", "--params").stdout
    helptext = cli(toy, "run", "--help").stdout
    assert "humanvdm params [STAGE]" in helptext and "--quiet" in helptext and "plain progress lines" in helptext


def test_params_of_the_real_pipeline_show_choices():
    res = subprocess.run([sys.executable, "-m", "humanvdm_core.cli", "params", "splat-optimize"],
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    assert "splat-optimize.preset = 'auto'  (str)  choices: auto, tiny, cpu, full" in res.stdout
    assert "splat-optimize.ply_axes = 'y-down'" in res.stdout


def test_kill_9_of_run_takes_its_stage_along_and_the_next_run_removes_its_staging(toy):
    """``kill -9`` of ``humanvdm run`` alone (not its process group): the stage process dies with it
    (PR_SET_PDEATHSIG) instead of running on as an orphan, and the next run removes the dead run's
    staging folder (named for its owner's pid) before it starts."""
    psutil = pytest.importorskip("psutil")
    inp = write_input(toy, "a", "slow text")
    p = cli(toy, "run", inp, "--kind", "text", "--set", "shout.sleep=30", "--no-progress", background=True)
    _wait_for_staging(toy)
    stages = [c for c in psutil.Process(p.pid).children(recursive=True) if f"{toy.pkg}.shout" in " ".join(c.cmdline())]
    assert len(stages) == 1
    staging = sorted((toy.store.root / "tmp").glob("shout-*"))
    assert len(staging) == 1 and f"-pid{p.pid}." in staging[0].name
    os.kill(p.pid, signal.SIGKILL)
    p.wait(timeout=30)
    p.stdout.close()
    _, alive = psutil.wait_procs(stages, timeout=5)
    assert alive == [], "the stage process outlived the killed run"
    assert staging[0].exists()  # the dead run's partial work, until ...
    res = cli(toy, "run", inp, "--kind", "text")
    assert res.returncode == 0 and "3 stage run(s) ran" in res.stdout, res.stdout + res.stderr
    assert not staging[0].exists() and list((toy.store.root / "tmp").iterdir()) == []  # ... the next run


def test_full_disk_gives_one_line_and_leaves_nothing_half_written(toy):
    """The store on a real, tiny file system (a 2 MB tmpfs in a private mount namespace): a stage that
    fills it fails with one line; its partial output is gone; nothing is recorded or linked."""
    from tests.toyproject import in_tiny_filesystem

    inp = write_input(toy, "a", "a line of text that will be repeated many times over\n")
    mount = toy.root / "small"
    store = mount / "artifacts"
    cmd = (f"{sys.executable} -m humanvdm_core.cli run {inp} --kind text --pipeline {toy.pipeline_path} "
           f"--store {store} --set shout.times=100000 --no-progress; echo rc=$?; "
           f"echo tmp=$(ls -A {store}/tmp | wc -l) records=$(find {store}/runcache -name '*.json' | wc -l) "
           f"objects=$(ls {store}/objects/*/ | grep -c .) links=$(ls {store}/runs/a | grep -vc logs)")
    res = in_tiny_filesystem(mount, "2m", cmd)
    if res is None:
        pytest.skip("cannot mount a tmpfs in a private namespace here (unshare)")
    out = res.stdout
    failed = [ln for ln in out.splitlines() if ln.startswith("FAILED ")]
    assert len(failed) == 1, out + res.stderr
    assert re.fullmatch(rf"FAILED a/shout: no space left on device writing {re.escape(str(store))}; "
                        r"free \d+ MB and rerun", failed[0]), failed[0]
    assert "rc=1" in out and "Traceback" not in out + res.stderr
    assert "tmp=0 records=0 objects=1 links=0" in out, out  # the input only; no staging, record or link


def test_a_local_run_never_imports_ray(toy):
    inp = write_input(toy, "a", "hello")
    args = ["run", "--pipeline", str(toy.pipeline_path), "--store", str(toy.store.root), inp, "--kind", "text", "-q"]
    code = f"import sys; from humanvdm_core import cli; rc = cli.main({args!r}); print('RESULT', rc, 'ray' in sys.modules)"
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert "RESULT 0 False" in res.stdout, res.stdout + res.stderr

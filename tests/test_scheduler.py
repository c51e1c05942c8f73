"""The scheduler: caching, invalidation, early cutoff, status, batch, failures, lockfiles."""

from __future__ import annotations

import contextlib
import time

import pytest
import yaml

from humanvdm_core.workflow.errors import ConfigError
from humanvdm_core.workflow.scheduler import (
    BLOCKED,
    CACHED,
    FAILED,
    MAY_RUN,
    NOT_IMPLEMENTED,
    RAN,
    SKIPPED,
    UP_TO_DATE,
    WILL_RUN,
    Scheduler,
    read_lockfile,
)
from tests.toyproject import ToyProject


@pytest.fixture
def toy(tmp_path) -> ToyProject:
    return ToyProject(tmp_path)


def states(summary_or_runs) -> dict[str, str]:
    runs = getattr(summary_or_runs, "runs", summary_or_runs)
    return {r.stage: r.state for r in runs}


def test_second_run_is_all_cache_hits(toy):
    subj = toy.subject("a", "hello world")
    first = toy.scheduler().run([subj])
    assert states(first) == {"shout": RAN, "measure": RAN, "report": RAN}
    assert toy.ran() == ["shout", "measure", "report"]
    second = toy.scheduler().run([subj])
    assert states(second) == {"shout": CACHED, "measure": CACHED, "report": CACHED}
    assert toy.ran() == []
    assert [r.outputs for r in first.runs] == [r.outputs for r in second.runs]


def test_param_change_reruns_that_stage_and_downstream_only_if_output_changed(toy):
    subj = toy.subject("a", "x" * 25)  # len 25: bucket 10 -> 2
    toy.scheduler().run([subj])
    toy.ran()
    # shout.times 1 -> 2: text changes (len 50 -> 5), so measure and report rerun
    s = toy.scheduler(overrides={"shout": {"times": 2}}).run([subj])
    assert states(s) == {"shout": RAN, "measure": RAN, "report": RAN}
    assert toy.ran() == ["shout", "measure", "report"]
    # measure.bucket 10 -> 11: measure reruns, 50 // 11 = 4 != 5, report reruns
    s = toy.scheduler(overrides={"shout": {"times": 2}, "measure": {"bucket": 11}}).run([subj])
    assert states(s) == {"shout": CACHED, "measure": RAN, "report": RAN}
    # measure.bucket 11 -> 12: 50 // 12 = 4 again: same artifact id, report is a hit (early cutoff)
    s = toy.scheduler(overrides={"shout": {"times": 2}, "measure": {"bucket": 12}}).run([subj])
    assert states(s) == {"shout": CACHED, "measure": RAN, "report": CACHED}
    assert toy.ran() == ["measure", "report", "measure"]


def test_upstream_rerun_with_identical_output_stops_there(toy):
    subj = toy.subject("a", "ALREADY UPPER")
    toy.scheduler().run([subj])
    toy.ran()
    s = toy.scheduler(overrides={"shout": {"upper": True}}).run([subj])  # same bytes out
    assert states(s) == {"shout": RAN, "measure": CACHED, "report": CACHED}
    assert toy.ran() == ["shout"]


def test_code_change_reruns_that_stage_only(toy):
    from tests.toyproject import STAGES

    subj = toy.subject("a", "some text here")
    toy.scheduler().run([subj])
    toy.ran()
    toy.write_stage("measure", STAGES["measure"] + "\n# a harmless edit that still changes the code\n")
    s = toy.scheduler().run([subj])
    assert states(s) == {"shout": CACHED, "measure": RAN, "report": CACHED}
    assert toy.ran() == ["measure"]


def test_input_change_reruns_everything_downstream(toy):
    toy.scheduler().run([toy.subject("a", "first")])
    toy.ran()
    s = toy.scheduler().run([toy.subject("a", "second, longer input text")])
    assert states(s) == {"shout": RAN, "measure": RAN, "report": RAN}


def test_status_explains_why(toy):
    subj = toy.subject("a", "x" * 25)
    st = states(toy.scheduler().status([subj]))
    assert st == {"shout": WILL_RUN, "measure": WILL_RUN, "report": WILL_RUN}
    toy.scheduler().run([subj])
    runs = toy.scheduler(overrides={"measure": {"bucket": 5}}).status([subj])
    by = {r.stage: r for r in runs}
    assert by["shout"].state == UP_TO_DATE and by["shout"].reason == "cached"
    assert by["measure"].state == WILL_RUN
    assert "params changed (bucket: 10 -> 5)" in by["measure"].reason
    assert by["report"].state == MAY_RUN and "measure" in by["report"].reason
    assert toy.ran() == ["shout", "measure", "report"]  # status ran nothing


def test_force_until_and_dry_status(toy):
    subj = toy.subject("a", "abc")
    s = toy.scheduler(until="measure").run([subj])
    assert states(s) == {"shout": RAN, "measure": RAN}
    toy.ran()
    s = toy.scheduler(force={"shout"}).run([subj])
    assert states(s) == {"shout": RAN, "measure": CACHED, "report": RAN}
    assert toy.ran() == ["shout", "report"]


def test_batch_failure_does_not_stop_others_and_is_reported(toy):
    good, bad, bug = toy.subject("good", "fine"), toy.subject("bad", "FAIL me"), toy.subject("bug", "CRASH")
    s = toy.scheduler(jobs=2).run([good, bad, bug])
    by = {(r.subject.name, r.stage): r for r in s.runs}
    assert by["good", "report"].state == RAN
    assert by["bad", "shout"].state == FAILED
    assert by["bad", "shout"].reason == "shout: this text cannot be shouted"
    assert by["bad", "shout"].log.is_file()
    assert by["bad", "measure"].state == SKIPPED and by["bad", "report"].state == SKIPPED
    assert by["bug", "shout"].state == FAILED and "RuntimeError: a bug" in by["bug", "shout"].reason
    assert "Traceback" in by["bug", "shout"].log.read_text()
    assert not s.ok


def test_parallel_jobs_overlap(toy):
    subjects = [toy.subject(f"s{i}", f"text {i}") for i in range(2)]
    toy.scheduler(jobs=2, overrides={"shout": {"sleep": 1.0}}).run(subjects)
    (_, _, a0, a1), (_, _, b0, b1) = [r for r in toy.ledger() if r[0] == "shout"]
    assert a0 < b1 and b0 < a1, "the two shout runs should have overlapped in time"


def test_a_downstream_run_starts_only_once_its_upstream_outputs_are_known(toy, monkeypatch):
    """In parallel, one subject's upstream run finishing wakes the loop while another's is still
    committing; the loop must not mistake the half-finished run for done (CI saw KeyError: 'out')."""
    key_lock = Scheduler._key_lock

    @contextlib.contextmanager
    def slow_exit(self, key):
        with key_lock(self, key):
            yield
        time.sleep(0.3)  # a slow machine between committing a run and publishing its outputs

    monkeypatch.setattr(Scheduler, "_key_lock", slow_exit)
    subjects = [toy.subject("a", "hello world"), toy.subject("b", "x" * 25)]
    s = toy.scheduler(jobs=2).run(subjects)
    assert s.ok, [(r.label, r.state, r.reason) for r in s.runs if r.state != RAN]
    assert {r.state for r in s.runs} == {RAN}


def test_lockfile_records_provenance(toy):
    subj = toy.subject("a", "hello")
    toy.scheduler().run([subj])
    lock = read_lockfile(toy.store, "a")
    entry = lock["stages"]["measure"]
    assert entry["params"] == {"bucket": 10}
    assert entry["backend"] == "embedded"
    assert entry["wall_s"] > 0 and entry["peak_rss_mb"] > 1
    assert entry["inputs"]["src"] == lock["stages"]["shout"]["outputs"]["out"]
    assert "python" in entry["versions"]
    link = toy.store.root / "runs" / "a" / "report" / "out"
    assert (link / "report.txt").read_text() == "size=0"


def test_not_implemented_stage_blocks_downstream(tmp_path):
    from tests.toyproject import PIPELINE, STAGES

    text = PIPELINE.replace("{pkg}.measure", "{pkg}.missing_module")
    toy = ToyProject(tmp_path, pipeline_text=text, stages={k: v for k, v in STAGES.items() if k != "measure"})
    s = toy.scheduler().run([toy.subject("a", "abc")])
    assert states(s) == {"shout": RAN, "measure": NOT_IMPLEMENTED, "report": BLOCKED}
    assert s.ok


def test_unknown_set_params_fail_before_running(toy):
    with pytest.raises(ConfigError, match="stage measure: unknown param"):
        toy.scheduler(overrides={"measure": {"nope": 1}})
    with pytest.raises(ConfigError, match="measure.bucket"):
        toy.scheduler(overrides={"measure": {"bucket": "ten"}})
    with pytest.raises(ConfigError, match="unknown stage"):
        toy.scheduler(overrides={"nostage": {"x": 1}})
    assert toy.ran() == []


@pytest.mark.parametrize("edit,message", [
    (lambda t: t + "\n  measure:\n    module: x\n    outputs: [y]\n", "duplicate key 'measure'"),
    (lambda t: t.replace("{src: $text}", "{src: report.out}"), "cycle in pipeline: shout -> report -> measure -> shout"),
    (lambda t: t.replace("{src: shout.out}", "{src: shout.nothing}"), "stage measure: input src refers to shout.nothing"),
    (lambda t: t.replace("{src: shout.out}", "{src: ghost.out}"), "stage measure: input src refers to unknown stage"),
    (lambda t: t.replace("{src: $text}", "{src: $photo}"), "stage shout: input src refers to unknown run input"),
    (lambda t: t.replace("{bucket: 10}", "{buckets: 10}"), "stage measure: unknown param"),
    (lambda t: t.replace("outputs: [out]\n    params", "outputs: [out, out]\n    params"), "stage measure: duplicate outputs"),
    (lambda t: t.replace("    params: {bucket: 10}", "    param: {bucket: 10}"), "stage measure: unknown keys"),
    (lambda t: t.replace("stages:", "stages: [\n"), "invalid YAML"),
])
def test_invalid_pipelines_fail_naming_the_problem(tmp_path, edit, message):
    from humanvdm_core.workflow.pipeline import load_pipeline
    from tests.toyproject import PIPELINE

    toy = ToyProject(tmp_path)
    toy.pipeline_path.write_text(edit(PIPELINE.format(pkg=toy.pkg)))
    with pytest.raises(ConfigError, match=message.replace("$", r"\$").replace("[", r"\[")):
        load_pipeline(toy.pipeline_path)


def test_real_pipeline_yaml_is_valid():
    from humanvdm_core.cli import REPO_ROOT
    from humanvdm_core.workflow.pipeline import load_pipeline

    pipe = load_pipeline(REPO_ROOT / "pipeline.yaml")
    assert {"render-training-orbits", "upscale", "interpolate"} <= {n for n, s in pipe.stages.items() if s.implemented}
    order = pipe.order()
    assert order.index("upscale") < order.index("interpolate") < order.index("splat-optimize")
    doc = yaml.safe_load((REPO_ROOT / "pipeline.yaml").read_text())
    assert set(doc["inputs"]) == {"photo", "scan"}


def test_photo_run_chooses_diffuse_scan_run_chooses_renderer():
    from humanvdm_core.cli import REPO_ROOT
    from humanvdm_core.workflow.pipeline import load_pipeline
    from humanvdm_core.workflow.scheduler import Subject
    from humanvdm_core.workflow.store import Store

    pipe = load_pipeline(REPO_ROOT / "pipeline.yaml")
    sched = Scheduler(pipe, Store.__new__(Store))
    photo = {r.stage: r for r in sched.plan([Subject("p", "photo", REPO_ROOT)])}
    scan = {r.stage: r for r in sched.plan([Subject("s", "scan", REPO_ROOT)])}
    assert str(photo["upscale"].chosen["frames"]) == "diffuse.orbit"
    assert str(scan["upscale"].chosen["frames"]) == "render-training-orbits.orbit"
    assert "render-training-orbits" not in photo and "diffuse" not in scan


def test_code_fingerprint_follows_project_imports_only():
    from humanvdm_core.workflow.pipeline import _project_sources

    sources = _project_sources("stages.upscale", ("humanvdm_core", "stages"))
    assert {"stages.upscale", "humanvdm_core.upscale.core", "humanvdm_core.io", "humanvdm_core.workflow.stage"} <= set(sources)
    assert "humanvdm_core.render" not in sources and "humanvdm_core.body.anny_model" not in sources
    assert not any(name.startswith(("numpy", "cv2", "torch")) for name in sources)


def test_editing_a_helper_module_reruns_the_stage_that_imports_it(toy):
    (toy.root / toy.pkg / "helper.py").write_text("FACTOR = 1\n")
    from tests.toyproject import STAGES

    toy.write_stage("measure", STAGES["measure"].replace("def run(ctx):", "def run(ctx):\n    from . import helper  # noqa: F401"))
    subj = toy.subject("a", "text")
    toy.scheduler().run([subj])
    toy.ran()
    (toy.root / toy.pkg / "helper.py").write_text("FACTOR = 2\n")
    s = toy.scheduler().run([subj])
    assert states(s) == {"shout": CACHED, "measure": RAN, "report": CACHED}


def test_optional_input_absent_from_the_run(tmp_path):
    from tests.toyproject import PIPELINE, STAGES

    stages = dict(STAGES)
    stages["report"] = STAGES["report"].replace(
        'outputs={"out": "report"})', 'outputs={"out": "report"}, optional=("note",))').replace(
        'inputs={"src": "number"}', 'inputs={"src": "number", "note": "a note"}').replace(
        'f"size={n}"', 'f"size={n} note={\'note\' in ctx.inputs}"')
    text = PIPELINE.replace("inputs: {{src: measure.out}}", "inputs: {{src: measure.out, note: \"$note?\"}}").replace(
        "  text: {{kind: text}}", "  text: {{kind: text}}\n  note: {{kind: text}}")
    toy = ToyProject(tmp_path, pipeline_text=text, stages=stages)
    s = toy.scheduler().run([toy.subject("a", "abc")])
    assert states(s)["report"] == RAN
    assert (toy.store.root / "runs" / "a" / "report" / "out" / "report.txt").read_text() == "size=0 note=False"
    toy.pipeline_path.write_text(toy.pipeline_path.read_text().replace("$note?", "$note"))
    with pytest.raises(ConfigError, match="optional"):
        toy.scheduler()


def test_set_backend_chooses_a_stage_backend():
    from humanvdm_core.cli import REPO_ROOT
    from humanvdm_core.workflow.pipeline import load_pipeline
    from humanvdm_core.workflow.scheduler import Subject
    from humanvdm_core.workflow.store import Store

    pipe = load_pipeline(REPO_ROOT / "pipeline.yaml")
    photo = Subject("p", "photo", REPO_ROOT)
    default = Scheduler(pipe, Store.__new__(Store))
    chosen = Scheduler(pipe, Store.__new__(Store), overrides={"diffuse": {"backend": "sv3d_p"}})
    assert chosen.pipeline.stages["diffuse"].backend == "sv3d_p"
    assert pipe.stages["diffuse"].backend == default.pipeline.stages["diffuse"].backend == "body-prior"
    assert "sv3d_p_weights" in chosen.params["diffuse"]  # the backend is not left among the params
    assert "backend" not in chosen.params["diffuse"]
    with pytest.raises(ConfigError, match=r"stage diffuse: unknown backend 'sv3dd'; choose from \['body-prior'"):
        Scheduler(pipe, Store.__new__(Store), overrides={"diffuse": {"backend": "sv3dd"}})
    assert default.plan([photo]) and chosen.plan([photo])


# ----------------------------------------------------------------------------- a full disk

def _nothing_left_of(toy, subject_name: str) -> None:
    """No staging folder, no run record and no lockfile entry from a failed stage run."""
    assert list((toy.store.root / "tmp").iterdir()) == []
    lock = read_lockfile(toy.store, subject_name)
    assert "shout" not in (lock.get("stages") or {})


def test_disk_full_in_a_stage_fails_that_run_with_one_line_and_leaves_nothing(toy):
    """A stage's ENOSPC (exit 4) becomes one line naming the store and the room to make; the staged
    partial output is removed, nothing is recorded, and the rest of the batch runs."""
    ok, full = toy.subject("ok", "fine text"), toy.subject("full", "NOSPACE here")
    s = toy.scheduler().run([ok, full])
    by = {(r.subject.name, r.stage): r for r in s.runs}
    assert by["ok", "report"].state == RAN
    failed = by["full", "shout"]
    assert failed.state == FAILED
    # N: what the stage had written (300 kB) or the same stage's largest output in this run: 1 MB
    assert failed.reason == f"no space left on device writing {toy.store.root}; free 1 MB and rerun"
    assert "no space left on device" in failed.log.read_text() and "Traceback" not in failed.log.read_text()
    assert by["full", "measure"].state == SKIPPED
    _nothing_left_of(toy, "full")
    assert len(list((toy.store.root / "runcache").glob("*/*.json"))) == 3  # ok's three stage runs only


def test_disk_full_while_committing_fails_the_run_and_commits_nothing(toy, monkeypatch):
    import errno

    from humanvdm_core.workflow.store import Store

    subj = toy.subject("a", "x" * 2_500_000)  # shout's output: 2.5 MB
    before = set(toy.store.all_ids())

    def disk_full(self, staged):
        raise OSError(errno.ENOSPC, "No space left on device", str(staged))

    monkeypatch.setattr(Store, "_commit_dir", disk_full)
    s = toy.scheduler().run([subj])
    shout = next(r for r in s.runs if r.stage == "shout")
    assert shout.state == FAILED
    assert shout.reason == f"no space left on device writing {toy.store.root}; free 3 MB and rerun"
    assert set(toy.store.all_ids()) == before
    assert not list((toy.store.root / "runcache").glob("*/*.json"))
    _nothing_left_of(toy, "a")
    monkeypatch.undo()  # room made: the rerun computes it
    assert states(toy.scheduler().run([subj])) == {"shout": RAN, "measure": RAN, "report": RAN}


# ----------------------------------------------------------------------------- resources (for Ray)

RESOURCES = """
    resources:
      num_cpus: 2
      memory: 512MB
      when: {{times=3: {{num_gpus: 1, memory: 1GiB}}, backend=embedded: {{num_cpus: 0.5}}}}
"""


def test_resources_come_from_the_pipeline_its_when_and_set(tmp_path):
    from humanvdm_core.workflow.pipeline import Resources
    from tests.toyproject import PIPELINE

    text = PIPELINE.replace("    inputs: {{src: $text}}\n    outputs: [out]\n",
                            "    inputs: {{src: $text}}\n    outputs: [out]\n" + RESOURCES.lstrip("\n"))
    toy = ToyProject(tmp_path, pipeline_text=text)
    assert toy.scheduler().resources("measure") == Resources()  # the default: one CPU
    assert toy.scheduler().resources("shout") == Resources(num_cpus=0.5, num_gpus=0, memory=512 * 10**6)
    sched = toy.scheduler(overrides={"shout": {"times": 3}})
    assert sched.resources("shout") == Resources(num_cpus=0.5, num_gpus=1, memory=2**30)
    sched = toy.scheduler(overrides={"shout": {"resources.num_gpus": "2", "resources.memory": "4GB"}})
    assert sched.resources("shout") == Resources(num_cpus=0.5, num_gpus=2, memory=4 * 10**9)
    assert "resources.num_gpus" not in sched.params["shout"]  # never a param, never in the key
    subj = toy.subject("a", "abc")
    assert len({sch.status([subj])[0].key for sch in (toy.scheduler(), sched)}) == 1  # shout's key: the same
    with pytest.raises(ConfigError, match="stage shout: resources.num_gpus must be a number >= 0"):
        toy.scheduler(overrides={"shout": {"resources.num_gpus": "-1"}})
    with pytest.raises(ConfigError, match="stage shout: unknown resource 'gpus'"):
        toy.scheduler(overrides={"shout": {"resources.gpus": "1"}})


@pytest.mark.parametrize("resources,message", [
    ("{num_cpus: -1}", "stage shout: resources.num_cpus must be a number >= 0"),
    ("{memory: lots}", "stage shout: resources.memory 'lots' is not a size"),
    ("{cpus: 1}", "stage shout: unknown resource 'cpus'"),
    ("{when: {backend=gpu: {num_gpus: 1}}}", "stage shout: unknown backend 'gpu'"),
    ("{when: {timez=3: {num_gpus: 1}}}", "stage shout: resources.when: unknown param 'timez'"),
    ("{when: {times: {num_gpus: 1}}}", "stage shout: resources.when: expected 'backend=NAME' or 'PARAM=VALUE'"),
    ("[1, 2]", "stage shout: resources must be a mapping"),
])
def test_invalid_resources_fail_naming_the_stage(tmp_path, resources, message):
    from humanvdm_core.workflow.pipeline import load_pipeline
    from tests.toyproject import PIPELINE

    toy = ToyProject(tmp_path)
    toy.pipeline_path.write_text(PIPELINE.format(pkg=toy.pkg).replace(
        "    inputs: {src: $text}\n", f"    inputs: {{src: $text}}\n    resources: {resources}\n"))
    with pytest.raises(ConfigError, match=message.replace("[", r"\[")):
        load_pipeline(toy.pipeline_path)


def test_real_pipeline_asks_a_gpu_only_for_gpu_settings():
    from humanvdm_core.cli import REPO_ROOT
    from humanvdm_core.workflow.pipeline import load_pipeline
    from humanvdm_core.workflow.store import Store

    pipe = load_pipeline(REPO_ROOT / "pipeline.yaml")
    default = Scheduler(pipe, Store.__new__(Store))
    assert all(default.resources(s).num_gpus == 0 for s in pipe.stages)
    gpu = Scheduler(pipe, Store.__new__(Store), overrides={"diffuse": {"backend": "sv3d_p"},
                                                          "splat-optimize": {"preset": "full"}})
    assert gpu.resources("diffuse").num_gpus == 1 and gpu.resources("splat-optimize").num_gpus == 1
    assert gpu.resources("upscale").num_gpus == 0


def test_a_stage_process_started_while_stopping_is_stopped_at_once(tmp_path):
    """Ctrl-C can land between a stage's staging folder appearing and its process starting: once
    ``stop_all`` has begun, a process that starts is terminated, not waited for."""
    from humanvdm_core.workflow.executors import LocalExecutor, StageCommand

    executor = LocalExecutor()
    executor.stop_all()
    command = StageCommand(label="a/slow", argv=["-c", "import time; time.sleep(30)"], cwd=str(tmp_path), env={},
                           log=str(tmp_path / "slow.log"), outputs=[])
    t0 = time.perf_counter()
    result = executor.run(command)
    assert result.returncode != 0 and time.perf_counter() - t0 < 10

"""The scheduler: plans, explains and executes stage runs over the artifact store.

A *subject* is one run input (a photo, a scan). For each subject the scheduler walks the pipeline
in topological order; each stage run has a key::

    sha256(stage, module, code fingerprint, resolved params, backend, weight-file hashes, input ids)

A key with an intact record in the store is a cache hit: nothing runs. Otherwise the stage's
executable runs in a subprocess (``python -m <module> ...``) into a staging folder, its outputs are
committed to the store, and a record is written. A downstream stage's key contains its inputs'
artifact *ids*, so when an upstream rerun reproduces the same bytes the downstream stage is a hit
(early cutoff).

Independent stage runs (other subjects, parallel branches) go to a bounded pool (``jobs``) and
run on an executor (:mod:`humanvdm_core.workflow.executors`: subprocesses here, or Ray tasks on a cluster);
keys, cache lookups and commits always happen here, in the driver. A failure skips only what
depends on it. Per subject, ``runs/<subject>/humanvdm.lock`` records every stage's key, params,
input and output ids, backend, wall time, peak memory and versions, and
``runs/<subject>/<stage>/<output>`` links to the artifacts.

Faults: a run first removes staging folders of dead runs on this host; a stage process dies with
the process that started it (see :mod:`humanvdm_core.workflow.stage`); a full disk, in the stage or while
committing, fails that stage run with one line ("no space left on device writing STORE; free N MB
and rerun", N: the larger of what the stage had written when the disk filled and what the same
stage's outputs took earlier in this run) and leaves no staging folder and no record; messages
name the user's input file, never the store's copy of it.

While it runs, each stage process reports its own progress through ``runs/<subject>/logs/<stage>.progress``
(the channel of :mod:`humanvdm_core.workflow.progress`, named in ``$HUMANVDM_PROGRESS``); a
:class:`~humanvdm_core.workflow.progress.Display` shows it, per active stage run.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import platform
import re
import threading
import time
from collections.abc import Iterator
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from dataclasses import dataclass, field, replace
from importlib import metadata
from pathlib import Path
from typing import Any

import yaml

from humanvdm_core.workflow.atomic import atomic_write_text
from humanvdm_core.workflow.errors import ConfigError, DiskFullError, HumanVDMError, is_disk_full
from humanvdm_core.workflow.executors import LocalExecutor, RayExecutor, StageCommand
from humanvdm_core.workflow.hashing import hash_tree
from humanvdm_core.workflow.pipeline import Pipeline, Ref, Resources, code_fingerprint
from humanvdm_core.workflow.progress import PROGRESS_ENV, Display
from humanvdm_core.workflow.stage import EXIT_NO_SPACE
from humanvdm_core.workflow.store import Store, discard, tree_size
from humanvdm_core.workflow.threads import stage_threads, thread_env

LOCK_NAME = "humanvdm.lock"
_YamlLoader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)  # libyaml when the wheel has it
_YamlDumper = getattr(yaml, "CSafeDumper", yaml.SafeDumper)
VERSIONED_PACKAGES = ("humanvdm", "numpy", "torch", "opencv-contrib-python-headless", "openimageio", "moderngl", "trimesh",
                      "anny", "mediapipe", "gsplat")

# Stage-run states.
CACHED, RAN, FAILED = "cached", "ran", "failed"
NOT_IMPLEMENTED, BLOCKED, SKIPPED = "not-implemented", "blocked", "skipped"
WILL_RUN, UP_TO_DATE, MAY_RUN = "will-run", "up-to-date", "may-run"


@dataclass
class Subject:
    """One run input bound to one of the pipeline's declared inputs (``kind``)."""

    name: str
    kind: str
    source: Path
    input_id: str | None = None
    error: str | None = None  # why the input cannot be used (e.g. an empty file): its stages fail with this


@dataclass
class StageRun:
    subject: Subject
    stage: str
    chosen: dict[str, Ref]
    deps: list[StageRun] = field(default_factory=list)
    state: str = "pending"
    reason: str = ""
    key: str | None = None
    inputs: dict[str, str] = field(default_factory=dict)
    outputs: dict[str, str] = field(default_factory=dict)
    wall_s: float | None = None
    peak_rss_mb: float | None = None
    log: Path | None = None
    warnings: list[str] = field(default_factory=list)  # the stage's own warnings (kept with its record)
    user_paths: dict[str, str] = field(default_factory=dict)  # store path of an input file -> the user's path

    @property
    def label(self) -> str:
        return f"{self.subject.name}/{self.stage}"


@dataclass
class Summary:
    runs: list[StageRun]

    def count(self, state: str) -> int:
        return sum(r.state == state for r in self.runs)

    @property
    def failed(self) -> list[StageRun]:
        return [r for r in self.runs if r.state == FAILED]

    @property
    def ok(self) -> bool:
        return not self.failed and not any(r.state == SKIPPED for r in self.runs)


class Scheduler:
    def __init__(
        self,
        pipeline: Pipeline,
        store: Store,
        overrides: dict[str, dict[str, Any]] | None = None,
        force: set[str] | None = None,
        until: str | None = None,
        jobs: int = 1,
        threads: int | None = None,
        progress: str | bool | None = None,
        progress_interval: float | None = None,
        executor: LocalExecutor | RayExecutor | None = None,
    ):
        self.pipeline = pipeline
        self.store = store
        self.overrides = overrides or {}
        self.force = set(force or ())
        self.until = until
        self.jobs = max(1, int(jobs))
        self.threads = threads  # compute threads per stage process; None: available cores / jobs
        # what the run shows (humanvdm_core.workflow.progress.Display): "auto" (None), "live" (True), "plain" (False), "quiet"
        self.progress = {None: "auto", True: "live", False: "plain"}.get(progress, progress)
        self.progress_interval = progress_interval
        for stage in self.overrides:
            if stage not in pipeline.stages:
                raise ConfigError(f"--set: unknown stage {stage!r}; stages: {list(pipeline.stages)}")
            if pipeline.stages[stage].spec is None:
                raise ConfigError(f"--set: stage {stage} is not implemented yet")
        self.overrides = {s: dict(o) for s, o in self.overrides.items()}
        backends = {s: str(o.pop("backend")) for s, o in self.overrides.items() if "backend" in o}
        if backends:  # `--set stage.backend=name` chooses the stage's backend (the caller's pipeline is kept)
            stages = dict(pipeline.stages)
            for stage, backend in backends.items():
                stages[stage] = replace(stages[stage], backend=stages[stage].spec.check_backend(backend))
            pipeline = self.pipeline = replace(pipeline, stages=stages)
        # `--set stage.resources.num_gpus=1`: applied after pipeline.yaml's resources and their `when`
        self.resource_overrides = {s: {k.partition(".")[2]: o.pop(k) for k in list(o) if k.startswith("resources.")}
                                   for s, o in self.overrides.items()}
        for stage, fields in self.resource_overrides.items():
            Resources().updated(stage, fields)  # fail now on a bad value
        self.executor = executor or LocalExecutor()
        for stage in self.force | ({until} if until else set()):
            if stage not in pipeline.stages:
                raise ConfigError(f"unknown stage {stage!r}; stages: {list(pipeline.stages)}")
        self.params = {s: pipeline.resolve_params(s, self.overrides.get(s)) for s in pipeline.stages}
        self._fingerprints: dict[str, str] = {}
        self._lock = threading.Lock()
        self._fp_lock = threading.Lock()
        self._key_locks: dict[str, threading.Lock] = {}  # one stage-run key runs once in this process
        self._output_bytes: dict[str, int] = {}  # per stage: the largest output committed in this run
        self._versions: dict[str, str] | None = None
        self._lockfiles: dict[str, dict] = {}
        self._dirty: set[str] = set()
        self._display: Display | None = None

    # ------------------------------------------------------------------ planning

    def plan(self, subjects: list[Subject]) -> list[StageRun]:
        """Stage runs for every subject, in an order where dependencies come first."""
        wanted = None
        if self.until:
            wanted = self.pipeline.upstream(self.until) | {self.until}
        runs: list[StageRun] = []
        for subj in subjects:
            if subj.kind not in self.pipeline.inputs:
                raise ConfigError(f"{subj.source}: input kind {subj.kind!r} is not declared in {self.pipeline.path}")
            by_stage: dict[str, StageRun] = {}
            for name in self.pipeline.order():
                sd = self.pipeline.stages[name]
                chosen: dict[str, Ref] = {}
                for inp, alts in sd.inputs.items():
                    ref = next((r for r in alts if (r.stage is None and r.name == subj.kind)
                                or (r.stage is not None and r.stage in by_stage)), None)
                    if ref is None:
                        if inp in sd.optional:
                            continue
                        break
                    chosen[inp] = ref
                else:
                    if wanted is not None and name not in wanted:
                        continue
                    run = StageRun(subj, name, chosen, [by_stage[r.stage] for r in chosen.values() if r.stage])
                    if subj.error and any(r.stage is None for r in chosen.values()):
                        run.state, run.reason = FAILED, subj.error
                    elif not sd.implemented:
                        run.state, run.reason = NOT_IMPLEMENTED, f"not implemented yet (no module {sd.module})"
                    else:
                        missing = [d.stage for d in run.deps if d.state in (NOT_IMPLEMENTED, BLOCKED)]
                        if missing:
                            run.state, run.reason = BLOCKED, f"needs {', '.join(missing)} (not implemented yet)"
                    by_stage[name] = run
                    runs.append(run)
        return runs

    def fingerprint(self, stage: str) -> str:
        with self._fp_lock:  # ast.parse is not thread-safe in CPython 3.11
            if stage not in self._fingerprints:
                self._fingerprints[stage] = code_fingerprint(self.pipeline.stages[stage].module)
            return self._fingerprints[stage]

    def key_material(self, run: StageRun) -> dict[str, Any]:
        sd = self.pipeline.stages[run.stage]
        return {
            "stage": run.stage,
            "module": sd.module,
            "code": self.fingerprint(run.stage),
            "params": self.params[run.stage],
            "backend": sd.backend,
            "weights": self._weight_hashes(run.stage),
            "inputs": run.inputs,
        }

    def _weight_hashes(self, stage: str) -> dict[str, str]:
        sd = self.pipeline.stages[stage]
        out = {}
        for name, p in sd.spec.params.items():
            value = str(self.params[stage][name]).strip()
            if p.weights and p.applies_to(sd.backend) and value:  # "" means: not used
                path = Path(value).expanduser()
                if path.is_file():
                    out[name] = self.store.stat_cache.file_hash(path)
                elif path.is_dir():  # a folder of model files (e.g. SMPL's)
                    out[name] = hash_tree(path, self.store.stat_cache)[0]
                else:
                    out[name] = "missing"
        return out

    def resources(self, stage: str) -> Resources:
        """What one run of ``stage`` asks of an executor: pipeline.yaml's resources, their ``when`` for the
        resolved params and backend, then ``--set stage.resources.X=V``."""
        sd = self.pipeline.stages[stage]
        out = sd.resources_for(self.params[stage], sd.backend)
        return out.updated(stage, self.resource_overrides.get(stage, {}))

    def _resolve_inputs(self, run: StageRun) -> None:
        run.inputs = {}
        for inp, ref in run.chosen.items():
            if ref.stage is None:
                run.inputs[inp] = run.subject.input_id
                run.user_paths.update(self._user_paths(run.subject))
            else:
                dep = next(d for d in run.deps if d.stage == ref.stage)
                run.inputs[inp] = dep.outputs[ref.name]
        run.key = _hash_json(self.key_material(run))

    def _user_paths(self, subject: Subject) -> dict[str, str]:
        """The store's paths of a subject's input files (and folder) -> the user's own paths."""
        if subject.input_id is None:
            return {}
        obj = self.store.object_path(subject.input_id)
        src = subject.source
        files = self.store.manifest(subject.input_id) or {}
        out = {str(obj / rel): str(src if src.is_file() else src / rel) for rel in files}
        if src.is_dir():
            out[str(obj)] = str(src)
        return out

    # ------------------------------------------------------------------ status

    def status(self, subjects: list[Subject]) -> list[StageRun]:
        """Say, per stage run, whether it would run and why (nothing runs)."""
        runs = self.plan(subjects)
        locks = {s.name: read_lockfile(self.store, s.name) for s in subjects}
        for run in runs:
            if run.state in (NOT_IMPLEMENTED, BLOCKED, FAILED):
                continue
            bad = [d for d in run.deps if d.state in (FAILED, SKIPPED)]
            if bad:
                run.state, run.reason = SKIPPED, f"upstream {bad[0].stage} {bad[0].state}"
                continue
            pending = [d.stage for d in run.deps if d.state != UP_TO_DATE]
            if pending:  # input ids unknown until upstream runs; own changes still tell
                previous = locks[run.subject.name].get("stages", {}).get(run.stage)
                own = self._why_changed(run, previous, with_inputs=False)
                if run.stage in self.force:
                    run.state, run.reason = WILL_RUN, "forced (--force)"
                elif own:
                    run.state, run.reason = WILL_RUN, own
                else:
                    run.state = MAY_RUN
                    run.reason = f"after {', '.join(pending)}: reruns only if its input changes"
                continue
            self._resolve_inputs(run)
            record = self.store.get_record(run.key)
            previous = locks[run.subject.name].get("stages", {}).get(run.stage)
            if run.stage in self.force:
                run.state, run.reason = WILL_RUN, "forced (--force)"
            elif record is not None:
                run.state = UP_TO_DATE
                run.outputs = dict(record["outputs"])
                same = previous is not None and previous.get("key") == run.key
                run.reason = "cached" if same else "cached (computed by another run; will be reused)"
            else:
                run.state, run.reason = WILL_RUN, self._why_changed(run, previous)
        return runs

    def _why_changed(self, run: StageRun, previous: dict | None, with_inputs: bool = True) -> str:
        """Why the key differs from the previous run's; without inputs, '' when only they may differ."""
        if previous is None:
            return "never run for this input"
        material = self.key_material(run) if with_inputs else {**self.key_material(run), "inputs": {}}
        reasons = []
        if previous.get("code") != material["code"]:
            reasons.append("code changed")
        old_params = previous.get("params", {})
        changed = [f"{k}: {old_params.get(k)!r} -> {v!r}" for k, v in material["params"].items()
                   if old_params.get(k) != v]
        if changed:
            reasons.append("params changed (" + "; ".join(changed) + ")")
        if previous.get("backend") != material["backend"]:
            reasons.append(f"backend {previous.get('backend')} -> {material['backend']}")
        if previous.get("weights", {}) != material["weights"]:
            reasons.append("weight files changed")
        changed_inputs = [k for k, v in material["inputs"].items() if previous.get("inputs", {}).get(k) != v]
        if changed_inputs:
            reasons.append(f"input {', '.join(changed_inputs)} changed")
        if not reasons and with_inputs:
            reasons.append("outputs missing or corrupt in the store")
        return "; ".join(reasons)

    # ------------------------------------------------------------------ execution

    def run(self, subjects: list[Subject]) -> Summary:
        runs = self.plan(subjects)
        todo = [r for r in runs if r.state == "pending"]
        with self.store.shared_use():
            self.store.clean_stale_staging()  # partial outputs of runs killed on this host
            display = Display(self.progress, total=len(todo), interval=self.progress_interval)
            try:
                self._execute(todo, display)
            finally:
                display.close()
                with self._lock:
                    self._flush_lockfiles()
        return Summary(runs)

    def _execute(self, todo: list[StageRun], display) -> None:
        self._display = display
        pending = list(todo)
        futures: dict[Future, StageRun] = {}
        with ThreadPoolExecutor(max_workers=self.jobs) as pool:
            try:
                while pending or futures:
                    for run in list(pending):
                        bad = [d for d in run.deps if d.state in (FAILED, SKIPPED)]
                        if bad:
                            run.state, run.reason = SKIPPED, f"upstream {bad[0].stage} {bad[0].state}"
                            pending.remove(run)
                            self._report(run, display)
                        elif all(d.state in (CACHED, RAN) for d in run.deps):
                            pending.remove(run)
                            futures[pool.submit(self._run_one, run)] = run
                    if not futures:
                        continue
                    done, _ = wait(futures, return_when=FIRST_COMPLETED)
                    for fut in done:
                        run = futures.pop(fut)
                        exc = fut.exception()
                        if exc is not None:
                            run.state, run.reason = FAILED, self._failure_text(exc)
                        self._report(run, display)
            except BaseException:  # Ctrl-C: stop the running stages before the pool waits for them
                for fut in futures:
                    fut.cancel()
                self.executor.stop_all()
                raise

    def _failure_text(self, exc: BaseException) -> str:
        if is_disk_full(exc) and not isinstance(exc, DiskFullError):
            return str(DiskFullError(self.store.root))
        if isinstance(exc, HumanVDMError):
            return str(exc)
        return f"{type(exc).__name__}: {exc}"

    def _report(self, run: StageRun, display) -> None:
        timing = f" in {run.wall_s:.1f} s" if run.state == RAN and run.wall_s is not None else ""
        extra = f": {run.reason}" if run.reason and run.state not in (RAN, CACHED) else ""
        log = f" (log: {run.log})" if run.state == FAILED and run.log else ""
        display.finished(id(run), run.label, run.state, f"{run.label}: {run.state}{timing}{extra}{log}")

    def _run_one(self, run: StageRun) -> None:
        """Runs in a pool thread. ``run.state`` becomes RAN or CACHED last of all: the scheduling loop
        submits downstream runs as soon as it sees that state, and they read ``run.outputs``."""
        self._resolve_inputs(run)
        sd = self.pipeline.stages[run.stage]
        forced = run.stage in self.force
        state = CACHED
        record = None if forced else self.store.get_record(run.key)
        if record is None:
            with self._key_lock(run.key):
                record = None if forced else self.store.get_record(run.key)  # another run may have made it
                if record is None:
                    record = self._execute_stage(run)
                    if record is None:
                        return
                    state = RAN
        if state == CACHED:
            run.reason = ""
        run.outputs = dict(record["outputs"])
        run.wall_s = record.get("wall_s")
        run.peak_rss_mb = record.get("peak_rss_mb")
        run.warnings = list(record.get("warnings") or [])
        self._update_view(run, sd.backend, record, state)
        run.state = state

    @contextlib.contextmanager
    def _key_lock(self, key: str) -> Iterator[None]:
        """Held while a stage-run key is looked up and computed: a thread lock (the same key twice in one
        batch runs once), plus the store's file lock when the executor runs stages on this machine (other
        processes sharing the store wait). The Ray executor takes no file lock: this driver is the store's
        single committer, and a commit is an atomic rename, so at worst two drivers compute a key twice."""
        with self._lock:
            lock = self._key_locks.setdefault(key, threading.Lock())
        with lock:
            if self.executor.uses_file_locks:
                with self.store.key_lock(key):
                    yield
            else:
                yield

    def _stage_env(self, progress_file: Path, resources: Resources) -> dict[str, str]:
        """What a stage process's environment adds to the executing machine's: unbuffered output, the
        progress channel, the pipeline's folder on PYTHONPATH, and its compute-thread budget (locally: the
        cores / --jobs or --threads; on Ray: the task's num_cpus or --threads)."""
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        env[PROGRESS_ENV] = str(progress_file)
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(self.pipeline.path.parent), env.get("PYTHONPATH")]))
        if isinstance(self.executor, LocalExecutor):
            env = thread_env(stage_threads(self.jobs, self.threads), env, override=self.threads is not None)
        else:
            env = thread_env(stage_threads(1, self.threads or max(1, round(resources.num_cpus))), env, override=True)
        return {k: v for k, v in env.items() if os.environ.get(k) != v}

    def _execute_stage(self, run: StageRun) -> dict | None:
        """Run one stage run on the executor into a fresh staging folder, then (here, in the driver)
        commit its outputs and write its record. Returns the record, or None with ``run`` FAILED. The
        staging folder is gone afterwards, whatever happened."""
        staging: Path | None = None
        try:
            staging = self.store.new_staging_dir(run.stage)
            return self._execute_in(run, staging)
        except OSError as e:
            if not is_disk_full(e):
                raise
            run.state, run.reason = FAILED, str(DiskFullError(self.store.root, self._space_needed(run, staging)))
            return None
        except DiskFullError as e:  # from a commit, which already removed what it staged
            run.state, run.reason = FAILED, str(DiskFullError(e.where, max(e.need_bytes, self._space_needed(run, None))))
            return None
        finally:
            if staging is not None:
                discard(staging)

    def _execute_in(self, run: StageRun, staging: Path) -> dict | None:
        sd = self.pipeline.stages[run.stage]
        outputs = {o: staging / o for o in sd.outputs}
        inputs = {k: self.store.object_path(v) for k, v in run.inputs.items()}
        argv = sd.spec.argv(inputs, outputs, self.params[run.stage], sd.backend)
        log_dir = self.store.root / "runs" / run.subject.name / "logs"
        log_dir.mkdir(parents=True, exist_ok=True)
        run.log = log_dir / f"{run.stage}.log"
        run.log.write_bytes(b"")  # the executor appends: one log per stage run, every attempt in it
        progress_file = log_dir / f"{run.stage}.progress"  # the stage's progress channel (humanvdm_core.workflow.progress)
        progress_file.write_bytes(b"")
        resources = self.resources(run.stage)
        command = StageCommand(label=run.label, argv=["-m", sd.module, *argv], cwd=str(self.pipeline.path.parent),
                               env=self._stage_env(progress_file, resources), log=str(run.log),
                               outputs=[str(p) for p in outputs.values()], resources=resources)
        if self._display is not None:
            self._display.started(id(run), run.subject.name, run.stage, progress_file, run.log)
        result = self.executor.run(command)
        run.wall_s, run.peak_rss_mb = result.wall_s, result.peak_rss_mb
        if result.returncode != 0:
            run.state = FAILED
            line = _error_line(run.log)
            if result.returncode == EXIT_NO_SPACE or is_disk_full(line):
                run.reason = str(DiskFullError(self.store.root, self._space_needed(run, staging)))
            else:
                run.reason = user_names(run, line) or f"exit code {result.returncode}"
            return None
        out_ids = {}
        for name, path in outputs.items():
            if not path.is_dir() or not any(path.rglob("*")):
                run.state, run.reason = FAILED, f"stage wrote nothing to its output {name}"
                return None
        size = tree_size(staging)
        for name, path in outputs.items():
            out_ids[name] = self.store.commit_dir(path)
        with self._lock:
            self._output_bytes[run.stage] = max(size, self._output_bytes.get(run.stage, 0))
        record = {
            **self.key_material(run),
            "key": run.key,
            "outputs": out_ids,
            "wall_s": round(result.wall_s, 3),
            "peak_rss_mb": round(result.peak_rss_mb, 1),
            "warnings": _warning_lines(run.log),
            "versions": self.versions(),
            "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        }
        self.store.put_record(run.key, record)  # the commit point: before it, nothing is a cache hit
        return record

    def _space_needed(self, run: StageRun, staging: Path | None) -> int:
        """Bytes a stage run needs, at least: what it had staged when the disk filled, or what the same
        stage's largest output took earlier in this run, whichever is larger."""
        staged = tree_size(staging) if staging is not None else 0
        with self._lock:
            return max(staged, self._output_bytes.get(run.stage, 0))

    def _update_view(self, run: StageRun, backend: str, record: dict, state: str) -> None:
        view = self.store.root / "runs" / run.subject.name
        for name, artifact_id in run.outputs.items():
            link = view / run.stage / name
            target = self.store.object_path(artifact_id)
            if link.is_symlink() and os.readlink(link) == str(target):
                continue
            link.parent.mkdir(parents=True, exist_ok=True)
            tmp = link.with_name(f".{name}.{os.getpid()}.{threading.get_ident()}")
            tmp.unlink(missing_ok=True)
            tmp.symlink_to(target)
            os.replace(tmp, link)
        entry = {k: record.get(k) for k in ("key", "module", "code", "params", "backend", "weights", "inputs",
                                            "outputs", "wall_s", "peak_rss_mb", "warnings", "versions")}
        entry["warnings"] = [user_names(run, w) for w in entry["warnings"] or []]  # this subject's file names
        entry["status"] = state
        with self._lock:
            lock = self._lockfiles.get(run.subject.name)
            if lock is None:
                lock = self._lockfiles[run.subject.name] = read_lockfile(self.store, run.subject.name)
            lock["schema"] = 1
            lock.setdefault("input", {})[run.subject.kind] = {"path": str(run.subject.source),
                                                              "id": run.subject.input_id}
            lock.setdefault("stages", {})[run.stage] = entry
            self._dirty.add(run.subject.name)
            if state == RAN:  # new work is on record at once; cache hits are written at the end
                self._flush_lockfiles()

    def _flush_lockfiles(self) -> None:
        for name in sorted(self._dirty):
            write_lockfile(self.store, name, self._lockfiles[name])
        self._dirty.clear()

    def versions(self) -> dict[str, str]:
        if self._versions is None:
            v = {"python": platform.python_version()}
            for pkg in VERSIONED_PACKAGES:
                try:
                    v[pkg] = metadata.version(pkg)
                except metadata.PackageNotFoundError:
                    pass
            self._versions = v
        return self._versions


# ---------------------------------------------------------------------- lockfiles

def lockfile_path(store: Store, subject: str) -> Path:
    return store.root / "runs" / subject / LOCK_NAME


def read_lockfile(store: Store, subject: str) -> dict:
    try:
        data = yaml.load(lockfile_path(store, subject).read_text(), Loader=_YamlLoader)
        return data if isinstance(data, dict) else {}
    except (OSError, yaml.YAMLError):
        return {}


def write_lockfile(store: Store, subject: str, data: dict) -> None:
    atomic_write_text(lockfile_path(store, subject), yaml.dump(data, Dumper=_YamlDumper, sort_keys=False))


def referenced_ids(store: Store) -> set[str]:
    """Artifact ids that some run's lockfile references (inputs and outputs)."""
    ids: set[str] = set()
    for lock_file in (store.root / "runs").glob(f"*/{LOCK_NAME}"):
        data = read_lockfile(store, lock_file.parent.name)
        for inp in (data.get("input") or {}).values():
            if isinstance(inp, dict) and inp.get("id"):
                ids.add(inp["id"])
        for entry in (data.get("stages") or {}).values():
            ids.update((entry.get("inputs") or {}).values())
            ids.update((entry.get("outputs") or {}).values())
    return ids


# ---------------------------------------------------------------------- helpers

def _hash_json(obj: Any) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def _error_line(log: Path) -> str | None:
    """The stage's own 'error: ...' line, or the last line of a traceback."""
    try:
        lines = [ln.strip() for ln in log.read_text(errors="replace").splitlines() if ln.strip()]
    except OSError:
        return None
    for ln in reversed(lines):
        if ln.startswith("error:"):
            return ln[len("error:"):].strip()
    return lines[-1] if len(lines) > 1 else None


def _warning_lines(log: Path | None) -> list[str]:
    """The stage's ``warning: ...`` log lines (see :mod:`humanvdm_core.workflow.stage`), without their prefix."""
    try:
        lines = log.read_text(errors="replace").splitlines() if log else []
    except OSError:
        return []
    marker = ": warning: "
    return list(dict.fromkeys(ln.split(marker, 1)[1].strip() for ln in lines if marker in ln))


def user_names(run: StageRun, message: str | None) -> str | None:
    """``message`` with the store's copies of the run's input files named as the user named them.

    A stage reads a run input from the store (``.../objects/ab/<id>/input.jpg``, a single file stored
    as ``input.<ext>``); the user knows it as the path they gave. Full store paths are replaced first
    (``run.user_paths``, set when the run's inputs are resolved), then a bare ``input.<ext>``."""
    if not message:
        return message
    for stored in sorted(run.user_paths, key=len, reverse=True):
        message = message.replace(stored, run.user_paths[stored])
    src = run.subject.source
    if not src.is_file() or not any(ref.stage is None for ref in run.chosen.values()):
        return message
    stored = f"input{src.suffix.lower()}"  # the name Store.import_path gives a single file
    return re.sub(rf"(?<![\w./-]){re.escape(stored)}\b", lambda _: str(src), message)


__all__ = ["Scheduler", "Subject", "StageRun", "Summary", "HumanVDMError", "referenced_ids", "user_names"]

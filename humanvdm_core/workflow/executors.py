"""Where stage runs execute: on this machine (``local``) or as tasks on a Ray cluster (``ray``).

Both executors run the same command, ``python -m <stage module> --<input> DIR ... --out-<output>
DIR ...`` (the contract of :mod:`humanvdm_core.workflow.stage`), with the same environment additions, into
a staging folder the driver made in the store. Everything else stays on the driver (the
:class:`~humanvdm_core.workflow.scheduler.Scheduler`): stage-run keys and cache lookups before anything is
submitted, committing outputs, run records and lockfiles. So outputs are byte-identical whichever
executor ran a stage, cached stage runs never reach a cluster, and the store has one committer.

- :class:`LocalExecutor`: a subprocess of the driver; ``--jobs`` bound how many run at once.
- :class:`RayExecutor`: each stage run is one Ray task asking for the stage's resources
  (``num_cpus``/``num_gpus``/``memory`` from pipeline.yaml, see :mod:`humanvdm_core.workflow.pipeline`); its
  body runs the same subprocess on whichever node Ray picks (:func:`run_stage_process`, with that
  node's Python: the project and its environment must be at the same paths on every node, the store
  on a file system every node sees). ``ray`` is imported only by this executor.

  Retries: when the worker process (or its node) dies mid-stage, Ray runs the task again, up to
  ``max_retries`` times; each attempt first empties the staging outputs, the stage process of the
  dead attempt died with its worker (``PR_SET_PDEATHSIG``), and nothing is committed unless an
  attempt exits 0. A stage's own failure (exit 3: a user error; 1: a bug; 4: disk full) is a
  result, not a crash: it is returned, never retried. The log keeps every attempt.
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from humanvdm_core.workflow.errors import ConfigError, HumanVDMError
from humanvdm_core.workflow.pipeline import Resources
from humanvdm_core.workflow.stage import PARENT_PID_ENV

EXECUTORS = ("local", "ray")
RAY_MAX_RETRIES = 3
RETRY_NOTE = "--- the previous attempt's worker died; Ray runs the stage again ---"


@dataclass(frozen=True)
class StageCommand:
    """One stage run, as an executor needs it (picklable: it travels to Ray workers).

    ``argv`` follows the interpreter (``["-m", module, ...]``); the executing machine's own Python
    runs it. ``env`` holds only additions to that machine's environment (so a Ray worker keeps the
    ``CUDA_VISIBLE_DEVICES`` Ray gave it). ``outputs`` are the staging output folders, emptied
    before each attempt; ``log`` receives the command line and the stage's stdout and stderr.
    """

    label: str
    argv: list[str]
    cwd: str
    env: dict[str, str]
    log: str
    outputs: list[str]
    resources: Resources = field(default_factory=Resources)


@dataclass(frozen=True)
class StageResult:
    """How a stage process ended: its exit code (negative: killed by that signal), its wall time and
    peak resident memory, and the host it ran on."""

    returncode: int
    wall_s: float
    peak_rss_mb: float
    host: str = ""


class WorkerLostError(HumanVDMError):
    """A Ray task's worker died more often than Ray retries (or the cluster went away)."""


def run_stage_process(command: StageCommand, on_start: Callable[[subprocess.Popen], None] | None = None,
                      on_end: Callable[[subprocess.Popen], None] | None = None) -> StageResult:
    """Run ``command``'s stage process here and wait for it (the body of both executors).

    Output folders left by an earlier attempt are removed first; the log is appended to (an earlier
    attempt's lines stay, after a note). ``on_start``/``on_end`` see the process (to stop it on Ctrl-C).
    """
    from humanvdm_core.workflow.store import discard

    for out in command.outputs:
        discard(Path(out))
    env = dict(os.environ)
    env.update(command.env)
    env[PARENT_PID_ENV] = str(os.getpid())
    cmd = [sys.executable, *command.argv]
    t0 = time.perf_counter()
    with open(command.log, "a") as log:
        if log.tell() > 0:
            log.write(f"\n{RETRY_NOTE}\n")
        log.write("$ " + " ".join(cmd) + "\n")
        log.flush()
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, cwd=command.cwd, env=env)
        if on_start is not None:
            on_start(proc)
        try:
            _, status, rusage = os.wait4(proc.pid, 0)
            proc.returncode = os.waitstatus_to_exitcode(status)
        finally:
            if on_end is not None:
                on_end(proc)
    return StageResult(proc.returncode, time.perf_counter() - t0, rusage.ru_maxrss / 1024.0, os.uname().nodename)


class LocalExecutor:
    """Stage processes on this machine, children of the driver."""

    name = "local"
    uses_file_locks = True  # stage-run key locks coordinate processes on this machine

    def __init__(self) -> None:
        self._procs: set[subprocess.Popen] = set()
        self._lock = threading.Lock()
        self._stopping = False

    def run(self, command: StageCommand) -> StageResult:
        return run_stage_process(command, self._started, self._ended)

    def _started(self, proc: subprocess.Popen) -> None:
        with self._lock:
            self._procs.add(proc)
            if self._stopping:  # started while Ctrl-C was being handled: it must not run on
                proc.terminate()

    def _ended(self, proc: subprocess.Popen) -> None:
        with self._lock:
            self._procs.discard(proc)

    def stop_all(self) -> None:
        """Terminate every running stage process (Ctrl-C), and any that starts from now on, then kill
        what does not stop in 10 s."""
        with self._lock:
            self._stopping = True
            procs = list(self._procs)
        for p in procs:
            p.terminate()
        for p in procs:
            try:
                p.wait(timeout=10)
            except (subprocess.TimeoutExpired, ChildProcessError):
                p.kill()

    def close(self) -> None:
        pass


def _ray_task(command: StageCommand) -> StageResult:
    """The body of a Ray task: the stage process on the worker's node."""
    return run_stage_process(command)


class RayExecutor:
    """Stage runs as Ray tasks. Connects on the first submission (a fully cached run never does):
    to ``address`` (``auto``, ``HOST:PORT``, ``ray://HOST:PORT``), to ``$RAY_ADDRESS``, or else to a
    new single-machine Ray instance; a Ray already initialised in this process is used as it is."""

    name = "ray"
    uses_file_locks = False  # the driver is the single committer; nothing relies on locks across nodes

    def __init__(self, address: str | None = None, max_retries: int = RAY_MAX_RETRIES):
        try:
            import ray  # noqa: F401
        except ImportError:
            raise ConfigError("--executor ray needs Ray: pip install 'humanvdm[cluster]' "
                              "(or pip install 'ray[default]')") from None
        self.address = address
        self.max_retries = max_retries
        self._lock = threading.Lock()
        self._remote: Any = None
        self._owns_ray = False
        self._running: set[Any] = set()

    def _connect(self) -> Any:
        import ray

        with self._lock:
            if self._remote is None:
                if not ray.is_initialized():
                    kwargs: dict[str, Any] = {"address": self.address} if self.address else {}
                    ray.init(log_to_driver=False, **kwargs)
                    self._owns_ray = True
                self._remote = ray.remote(_ray_task)
            return self._remote

    def run(self, command: StageCommand) -> StageResult:
        import ray
        from ray.exceptions import RayError, TaskCancelledError

        remote = self._connect()
        r = command.resources
        options: dict[str, Any] = {"num_cpus": r.num_cpus, "num_gpus": r.num_gpus,
                                   "max_retries": self.max_retries, "retry_exceptions": False}
        if r.memory:
            options["memory"] = r.memory
        ref = remote.options(**options).remote(command)
        with self._lock:
            self._running.add(ref)
        try:
            return ray.get(ref)
        except TaskCancelledError:
            raise WorkerLostError("the Ray task was cancelled (the run was interrupted)") from None
        except RayError as e:
            first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            raise WorkerLostError(f"the Ray task failed after {self.max_retries} retries: "
                                  f"{type(e).__name__}: {first}") from None
        finally:
            with self._lock:
                self._running.discard(ref)

    def stop_all(self) -> None:
        """Cancel every running task (its worker is killed; its stage process dies with it)."""
        import ray

        with self._lock:
            refs = list(self._running)
        for ref in refs:
            try:
                ray.cancel(ref, force=True)
            except Exception:  # already finished or gone
                pass

    def close(self) -> None:
        if self._owns_ray:
            import ray

            ray.shutdown()
            self._owns_ray = False

    def cluster_cpus(self) -> int:
        """CPUs of the cluster (connects); the default number of stage runs in flight."""
        import ray

        self._connect()
        return max(1, int(ray.cluster_resources().get("CPU", 1)))


def make_executor(name: str, address: str | None = None) -> LocalExecutor | RayExecutor:
    if name == "local":
        if address:
            raise ConfigError("--address is for --executor ray")
        return LocalExecutor()
    if name == "ray":
        return RayExecutor(address)
    raise ConfigError(f"unknown executor {name!r}; choose from {list(EXECUTORS)}")

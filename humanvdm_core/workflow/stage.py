"""The stage executable contract.

Every stage is a module ``stages/<name>.py`` that defines ``SPEC`` (a :class:`StageSpec`) and a
``run(ctx)`` function, and ends with ``raise SystemExit(SPEC.main(run))``. Its command line::

    python -m stages.<module> --<input> PATH ... --out-<output> DIR ... [--<param> VALUE ...] [--backend B]

- inputs are artifact directories (read-only); outputs are directories the stage creates and fills;
- params are typed with defaults (``pipeline.yaml`` may override them, ``--set`` may override both);
- exit 0 on success, 3 with a one-line message for a user-facing error (:mod:`humanvdm_core.workflow.errors`),
  4 when the disk (or quota) is full (an ``OSError`` ENOSPC/EDQUOT, or an error carrying its text:
  the scheduler turns it into "no space left on device writing STORE; free N MB and rerun"),
  2 for a bad command line, 1 for a bug (with traceback);
- started by the scheduler (``$HUMANVDM_PARENT_PID`` set), a stage process dies with the process
  that started it: on Linux it asks the kernel for SIGKILL when that process dies
  (``PR_SET_PDEATHSIG``), so ``kill -9`` of ``humanvdm run`` (or of a Ray worker) leaves no orphan.

Module-level imports of a stage must stay light (no torch): the scheduler imports ``SPEC`` to
validate the pipeline before anything runs. Heavy imports go inside ``run``.

Progress: a stage reports how far it is with ``ctx.progress(done, total, unit, what)`` (e.g.
``ctx.progress(120, 500, "it", "optimise Gaussians")``; library code it calls uses
:func:`humanvdm_core.workflow.progress.report`, the same call). The scheduler passes a file path in
``$HUMANVDM_PROGRESS``; each report appends one JSON line ``{"t", "done", "total", "unit", "what"}``
to it (throttled to a few per second), which the scheduler reads to show every active run's phase,
count, rate and ETA. Without the variable a report does nothing. The format is in
:mod:`humanvdm_core.workflow.progress`. The log (stdout/stderr) is for people and is never parsed for progress.
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import logging
import os
import signal
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from humanvdm_core.workflow.errors import ConfigError, HumanVDMError, is_disk_full

EXIT_OK, EXIT_BUG, EXIT_USAGE, EXIT_USER_ERROR, EXIT_NO_SPACE = 0, 1, 2, 3, 4
PARENT_PID_ENV = "HUMANVDM_PARENT_PID"  # set by the executor: the pid of the process that started the stage
_PR_SET_PDEATHSIG = 1


def die_with_parent() -> None:
    """When ``$HUMANVDM_PARENT_PID`` is set (Linux only): have the kernel SIGKILL this process when
    the thread that started it ends, and exit now if that process is already gone (it may have died
    before the request was made). Elsewhere, or without the variable, nothing happens."""
    parent = os.environ.get(PARENT_PID_ENV, "")
    if not parent.isdigit() or not sys.platform.startswith("linux"):
        return
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) != 0:
            return
    except (OSError, AttributeError):
        return
    if os.getppid() != int(parent):
        os._exit(EXIT_BUG)


@dataclass(frozen=True)
class Param:
    """A stage parameter. ``weights=True`` marks a local checkpoint file or folder whose content hash
    joins the stage-run key (only while the stage runs a backend in ``backend``)."""

    default: Any
    help: str
    choices: tuple | None = None
    weights: bool = False
    backend: str | tuple[str, ...] | None = None

    def applies_to(self, backend: str) -> bool:
        """Whether this param matters for ``backend`` (``backend=None``: for every backend)."""
        return self.backend is None or backend in ((self.backend,) if isinstance(self.backend, str) else self.backend)

    @property
    def type(self) -> type:
        return type(self.default) if self.default is not None else str

    def coerce(self, name: str, value: Any) -> Any:
        """Convert a value from YAML or a command line to this param's type, or raise ConfigError."""
        t = self.type
        try:
            if isinstance(value, str) and t is bool:
                low = value.strip().lower()
                if low not in ("1", "0", "true", "false", "yes", "no", "on", "off"):
                    raise ValueError(value)
                out = low in ("1", "true", "yes", "on")
            elif t is bool and not isinstance(value, bool):
                raise ValueError(value)
            elif t is float and isinstance(value, (int, float, str)) and not isinstance(value, bool):
                out = float(value)
            elif t is int and isinstance(value, (int, str)) and not isinstance(value, bool):
                out = int(value)
                if isinstance(value, str) and str(out) != value.strip():
                    raise ValueError(value)
            elif t is str:
                out = str(value)
            elif isinstance(value, t):
                out = value
            else:
                raise ValueError(value)
        except ValueError:
            raise ConfigError(f"param {name}: {value!r} is not a valid {t.__name__}") from None
        if self.choices is not None and out not in self.choices:
            raise ConfigError(f"param {name}: {out!r} is not one of {list(self.choices)}")
        return out


@dataclass(frozen=True)
class StageSpec:
    """What a stage reads, writes and accepts."""

    name: str
    summary: str
    inputs: dict[str, str]
    outputs: dict[str, str]
    params: dict[str, Param] = field(default_factory=dict)
    backends: tuple[str, ...] = ("embedded",)
    optional: tuple[str, ...] = ()  # inputs a run may lack (absent from ``ctx.inputs`` then)

    def resolve_params(self, overrides: dict[str, Any]) -> dict[str, Any]:
        """Defaults updated by ``overrides``; unknown names raise ConfigError naming the stage."""
        unknown = sorted(set(overrides) - set(self.params))
        if unknown:
            raise ConfigError(f"stage {self.name}: unknown param(s) {unknown}; known: {sorted(self.params)}")
        out = {k: p.default for k, p in self.params.items()}
        for k, v in overrides.items():
            out[k] = self.params[k].coerce(f"{self.name}.{k}", v)
        return out

    def check_backend(self, backend: str) -> str:
        if backend not in self.backends:
            raise ConfigError(f"stage {self.name}: unknown backend {backend!r}; choose from {list(self.backends)}")
        return backend

    def argv(self, inputs: dict[str, Path], outputs: dict[str, Path], params: dict[str, Any], backend: str) -> list[str]:
        """The command-line arguments that run this stage with these inputs, outputs and params."""
        args: list[str] = []
        for k in self.inputs:
            if k in inputs:
                args += [f"--{_flag(k)}", str(inputs[k])]
            elif k not in self.optional:
                raise ConfigError(f"stage {self.name}: input {k} is required")
        for k in self.outputs:
            args += [f"--out-{_flag(k)}", str(outputs[k])]
        for k, v in params.items():
            args += [f"--{_flag(k)}", _format(v)]
        return args + ["--backend", backend]

    def main(self, run: Callable[[StageContext], None], argv: list[str] | None = None) -> int:
        """Parse the command line, run the stage, map errors to exit codes."""
        die_with_parent()
        parser = argparse.ArgumentParser(prog=f"python -m stages.{self.name.replace('-', '_')}", description=self.summary)
        for k, desc in self.inputs.items():
            optional = k in self.optional
            parser.add_argument(f"--{_flag(k)}", dest=f"in_{k}", type=Path, required=not optional,
                                help=f"{'optional ' if optional else ''}input: {desc}")
        for k, desc in self.outputs.items():
            parser.add_argument(f"--out-{_flag(k)}", dest=f"out_{k}", type=Path, required=True, help=f"output directory: {desc}")
        for k, p in self.params.items():
            parser.add_argument(f"--{_flag(k)}", dest=f"p_{k}", default=None, metavar=p.type.__name__.upper(),
                                help=f"{p.help} (default: {p.default!r})")
        parser.add_argument("--backend", default=self.backends[0], choices=self.backends)
        parser.add_argument("-v", "--verbose", action="store_true")
        ns = parser.parse_args(argv)
        handler = logging.StreamHandler()
        handler.setFormatter(_StageFormatter(self.name))
        logging.basicConfig(level=logging.DEBUG if ns.verbose else logging.INFO, handlers=[handler])
        log = logging.getLogger(f"humanvdm.{self.name}")
        try:
            params = self.resolve_params({k: getattr(ns, f"p_{k}") for k in self.params
                                          if getattr(ns, f"p_{k}") is not None})
            inputs = {k: getattr(ns, f"in_{k}") for k in self.inputs if getattr(ns, f"in_{k}") is not None}
            for k, path in inputs.items():
                if not path.exists():
                    raise ConfigError(f"stage {self.name}: input {k} does not exist: {path}")
            outputs = {k: getattr(ns, f"out_{k}") for k in self.outputs}
            for k, path in outputs.items():
                if path.exists() and any(path.iterdir()):
                    raise ConfigError(f"stage {self.name}: output {k} directory is not empty: {path}")
                path.mkdir(parents=True, exist_ok=True)
            ctx = StageContext(self, inputs, outputs, params, ns.backend, log)
            t0 = time.perf_counter()
            run(ctx)
            log.info("done in %.2f s", time.perf_counter() - t0)
            return EXIT_OK
        except HumanVDMError as e:
            print(f"error: {self.name}: {e}", file=sys.stderr)
            return EXIT_USER_ERROR
        except Exception as e:
            if not is_disk_full(e):
                raise
            with contextlib.suppress(OSError):  # the log may sit on the full disk
                print(f"error: {self.name}: no space left on device ({e})", file=sys.stderr)
            return EXIT_NO_SPACE


@dataclass
class StageContext:
    """What ``run`` gets: resolved inputs, empty output directories, typed params, the backend."""

    spec: StageSpec
    inputs: dict[str, Path]
    outputs: dict[str, Path]
    params: dict[str, Any]
    backend: str
    log: logging.Logger

    def progress(self, done: float, total: float | None = None, unit: str = "it", what: str = "") -> None:
        """Report progress: ``done`` of ``total`` ``unit`` in the phase ``what`` (see the module docstring)."""
        from humanvdm_core.workflow.progress import report

        report(done, total, unit, what)

    def attrs(self) -> dict[str, str]:
        """Header attributes for files this stage writes (content-determined only)."""
        return {"stage": self.spec.name, "backend": self.backend}


def _flag(name: str) -> str:
    return name.replace("_", "-")


class _StageFormatter(logging.Formatter):
    """``HH:MM:SS <stage>: <message>``; warnings read ``<stage>: warning: <message>`` so the scheduler
    can show them in its summary and keep them in the lockfile."""

    def __init__(self, stage: str):
        super().__init__(f"%(asctime)s {stage}: %(message)s", datefmt="%H:%M:%S")
        self._warning = logging.Formatter(f"%(asctime)s {stage}: warning: %(message)s", datefmt="%H:%M:%S")

    def format(self, record: logging.LogRecord) -> str:
        return (self._warning if record.levelno >= logging.WARNING else super()).format(record)


def _format(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    return repr(value) if isinstance(value, float) else str(value)

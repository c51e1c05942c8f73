"""Live progress of stage runs: the channel from a stage process to the scheduler, and what it shows.

**The channel.** For every stage run it starts, the scheduler creates an empty file
``runs/<subject>/logs/<stage>.progress`` and passes its path to the stage process in the
environment variable :data:`PROGRESS_ENV` (``HUMANVDM_PROGRESS``). A stage reports with
``ctx.progress(done, total, unit, what)`` (:meth:`humanvdm_core.workflow.stage.StageContext.progress`), and
library code that a stage calls with :func:`report` (the same call without a context); both append
one JSON line to that file::

    {"t": 1730000000.123, "done": 120, "total": 500, "unit": "it", "what": "optimise Gaussians"}

``t`` is Unix time; ``done`` and ``total`` count ``unit`` (``total`` null: unknown); ``what`` names
the phase in a few words (a new ``what``, ``unit`` or ``total`` starts a new phase: its rate and ETA
are measured afresh). Lines are appended at most every :data:`MIN_INTERVAL_S` seconds within a phase,
but the first and the last line of a phase always are. Without the variable (a stage run by hand)
reporting costs nothing and writes nothing. Readers take complete lines only. The scheduler reads
these files, never the logs' text.

**The display** (:class:`Display`, driven by the scheduler): on a terminal, a live table with one line
per active stage run (input, stage, phase, a bar, done/total, rate, ETA, elapsed) under a header
counting finished stage runs; without a terminal (a pipe, CI, a log file) plain lines: one when a run
starts (naming its log), one when it ends (ran / cached / failed / skipped), and every ``interval``
seconds one line per active run. ``quiet`` prints nothing.
"""

from __future__ import annotations

import json
import os
import sys
import threading
import time
from collections import deque
from pathlib import Path
from typing import Any

PROGRESS_ENV = "HUMANVDM_PROGRESS"
INTERVAL_ENV = "HUMANVDM_PROGRESS_INTERVAL"
MIN_INTERVAL_S = 0.2
DEFAULT_INTERVAL_S = 15.0
RATE_WINDOW_S = 30.0
MODES = ("auto", "live", "plain", "quiet")


# ---------------------------------------------------------------------------------------- stage side

class ProgressWriter:
    """Appends progress records to one file (see the module docstring); thread-safe."""

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self._lock = threading.Lock()
        self._phase: tuple | None = None
        self._last = 0.0

    def report(self, done: float, total: float | None = None, unit: str = "it", what: str = "") -> None:
        now = time.time()
        phase = (what, unit, total)
        last_of_phase = total is not None and done >= total
        with self._lock:
            if phase == self._phase and not last_of_phase and now - self._last < MIN_INTERVAL_S:
                return
            self._phase, self._last = phase, now
            rec = {"t": round(now, 3), "done": done, "total": total, "unit": unit, "what": what}
            try:
                with open(self.path, "a") as f:
                    f.write(json.dumps(rec) + "\n")
            except OSError:
                pass  # progress is a courtesy: never fail a stage for it


_writer: ProgressWriter | None = None
_writer_path: str | None = None


def report(done: float, total: float | None = None, unit: str = "it", what: str = "") -> None:
    """Report progress of the running stage (a no-op unless ``$HUMANVDM_PROGRESS`` names a file)."""
    global _writer, _writer_path
    path = os.environ.get(PROGRESS_ENV)
    if not path:
        return
    if _writer is None or path != _writer_path:
        _writer, _writer_path = ProgressWriter(path), path
    _writer.report(done, total, unit, what)


# ---------------------------------------------------------------------------------------- scheduler side

class ProgressReader:
    """Follows one progress file: the latest record, and the rate over the last ``RATE_WINDOW_S``."""

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self._offset = 0
        self._partial = b""
        self.last: dict | None = None
        self._history: deque[tuple[float, float]] = deque()

    def poll(self) -> dict | None:
        try:
            with open(self.path, "rb") as f:
                f.seek(self._offset)
                data = f.read()
        except OSError:
            return self.last
        self._offset += len(data)
        lines = (self._partial + data).split(b"\n")
        self._partial = lines.pop()
        for line in lines:
            try:
                rec = json.loads(line)
                t, done = float(rec["t"]), float(rec["done"])
            except (ValueError, KeyError, TypeError):
                continue
            if self.last is None or _phase(rec) != _phase(self.last):
                self._history.clear()
            self._history.append((t, done))
            while len(self._history) > 2 and t - self._history[0][0] > RATE_WINDOW_S:
                self._history.popleft()
            self.last = rec
        return self.last

    @property
    def rate(self) -> float | None:
        """Units per second over the recent window, or None when not yet measurable."""
        if len(self._history) < 2:
            return None
        (t0, d0), (t1, d1) = self._history[0], self._history[-1]
        if t1 - t0 < 0.5 or d1 <= d0:
            return None
        return (d1 - d0) / (t1 - t0)

    @property
    def eta_s(self) -> float | None:
        """Seconds left at the recent rate, counted from now (time since the last record is taken off)."""
        rate, rec = self.rate, self.last
        if rate is None or rec is None or rec.get("total") is None:
            return None
        left = (float(rec["total"]) - float(rec["done"])) / rate - max(0.0, time.time() - float(rec["t"]))
        return max(0.0, left)


def _phase(rec: dict) -> tuple:
    return rec.get("what"), rec.get("unit"), rec.get("total")


def fmt_duration(seconds: float | None) -> str:
    if seconds is None:
        return "?"
    s = int(round(seconds))
    h, rem = divmod(s, 3600)
    m, s = divmod(rem, 60)
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m}:{s:02d}"


def _fmt_count(x: float) -> str:
    return f"{x:.0f}" if float(x).is_integer() else f"{x:.1f}"


def _fmt_rate(rate: float | None, unit: str) -> str:
    if rate is None:
        return ""
    return f"{rate:.1f} {unit}/s" if rate >= 1 else f"{1.0 / rate:.1f} s/{unit}"


class _Active:
    def __init__(self, subject: str, stage: str, path: Path | None, log: Path | None):
        self.subject, self.stage, self.log = subject, stage, log
        self.started = time.monotonic()
        self.reader = ProgressReader(path) if path is not None else None


class Display:
    """What the scheduler shows while it runs (see the module docstring).

    ``mode``: ``auto`` (``live`` on a terminal, else ``plain``), ``live``, ``plain`` or ``quiet``;
    ``interval``: seconds between the plain mode's status lines (default ``$HUMANVDM_PROGRESS_INTERVAL``
    or :data:`DEFAULT_INTERVAL_S`)."""

    def __init__(self, mode: str = "auto", total: int = 0, interval: float | None = None, stream=None):
        if mode not in MODES:
            raise ValueError(f"progress mode {mode!r}: choose from {MODES}")
        self.stream = stream if stream is not None else sys.stderr
        if mode == "auto":
            tty = hasattr(self.stream, "isatty") and self.stream.isatty() and os.environ.get("TERM") != "dumb"
            mode = "live" if tty else "plain"
        self.mode = mode
        if interval is None:
            try:
                interval = float(os.environ.get(INTERVAL_ENV, DEFAULT_INTERVAL_S))
            except ValueError:
                interval = DEFAULT_INTERVAL_S
        self.interval = max(0.1, interval)
        self.total = total
        self.counts: dict[str, int] = {}
        self.t0 = time.monotonic()
        self._active: dict[int, _Active] = {}
        self._lock = threading.Lock()
        self._print_lock = threading.Lock()
        self._stop = threading.Event()
        self._live = None
        self._thread: threading.Thread | None = None
        if self.mode == "live" and total > 0:
            from rich.console import Console
            from rich.live import Live

            self._console = Console(file=self.stream, highlight=False)
            self._live = Live(self._render(), console=self._console, refresh_per_second=4, transient=True,
                              redirect_stdout=False, redirect_stderr=False)
            self._live.start()
        if self.mode in ("live", "plain") and total > 0:
            self._thread = threading.Thread(target=self._loop, name="humanvdm-progress", daemon=True)
            self._thread.start()

    # -- events from the scheduler

    def started(self, key: int, subject: str, stage: str, progress_file: Path | None, log: Path | None) -> None:
        with self._lock:
            self._active[key] = _Active(subject, stage, progress_file, log)
        if self.mode == "plain":
            self._print(f"{subject}/{stage}: started" + (f" (log: {log})" if log else ""))

    def finished(self, key: int, label: str, state: str, text: str) -> None:
        with self._lock:
            self._active.pop(key, None)
            self.counts[state] = self.counts.get(state, 0) + 1
        self._print(text)

    def message(self, text: str) -> None:
        self._print(text)

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
        if self._live is not None:
            self._live.stop()
            self._live = None

    # -- rendering

    def _print(self, text: str) -> None:
        if self.mode == "quiet":
            return
        if self._live is not None:
            self._live.console.print(text, markup=False, highlight=False, soft_wrap=True)
        else:
            with self._print_lock:  # one write per line: lines of parallel runs never interleave
                self.stream.write(text + "\n")
                self.stream.flush()

    def _loop(self) -> None:
        next_plain = time.monotonic() + self.interval
        tick = 0.25 if self.mode == "live" else min(1.0, self.interval)
        while not self._stop.wait(tick):
            with self._lock:
                active = list(self._active.values())
            for a in active:
                if a.reader is not None:
                    a.reader.poll()
            if self._live is not None:
                self._live.update(self._render())
            elif time.monotonic() >= next_plain:
                next_plain = time.monotonic() + self.interval
                if active:
                    self._print(f"[{fmt_duration(time.monotonic() - self.t0):>7}] {self.header(len(active))}")
                    for a in active:
                        self._print(f"[{fmt_duration(time.monotonic() - self.t0):>7}] {self.describe(a)}")

    def header(self, running: int) -> str:
        done = sum(self.counts.values())
        parts = [f"{self.counts[s]} {s}" for s in ("ran", "cached", "failed", "skipped") if self.counts.get(s)]
        return f"stage runs: {done}/{self.total} done" + (f" ({', '.join(parts)})" if parts else "") + \
            f", {running} running"

    @staticmethod
    def status(a: _Active) -> dict[str, Any]:
        """The fields of one active run's line."""
        rec = a.reader.last if a.reader is not None else None
        out: dict[str, Any] = {"input": a.subject, "stage": a.stage, "elapsed": time.monotonic() - a.started,
                               "what": "running", "done": None, "total": None, "unit": "", "rate": None,
                               "eta": None}
        if rec is not None:
            out.update(what=rec.get("what") or "running", done=rec.get("done"), total=rec.get("total"),
                       unit=rec.get("unit") or "it", rate=a.reader.rate, eta=a.reader.eta_s)
        return out

    def describe(self, a: _Active) -> str:
        s = self.status(a)
        text = f"{s['input']}/{s['stage']}: {s['what']}"
        if s["done"] is not None:
            text += f" {_fmt_count(s['done'])}"
            if s["total"]:
                text += f"/{_fmt_count(s['total'])} {s['unit']} ({100.0 * s['done'] / s['total']:.0f}%)"
            else:
                text += f" {s['unit']}"
            rate = _fmt_rate(s["rate"], s["unit"])
            if rate:
                text += f", {rate}"
            if s["eta"] is not None:
                text += f", ETA {fmt_duration(s['eta'])}"
        else:
            text += " (no progress reported yet)"
        return text + f", elapsed {fmt_duration(s['elapsed'])}"

    def _render(self):
        from rich.progress_bar import ProgressBar
        from rich.table import Table
        from rich.text import Text

        with self._lock:
            active = list(self._active.values())
        table = Table.grid(padding=(0, 1))
        table.add_row(Text(f"{self.header(len(active))} · elapsed {fmt_duration(time.monotonic() - self.t0)}",
                           style="bold"))
        rows = Table.grid(padding=(0, 1))
        for _ in range(8):
            rows.add_column(no_wrap=True)
        for a in active:
            s = self.status(a)
            total = s["total"] if s["total"] else None
            bar = ProgressBar(total=total, completed=s["done"] or 0, width=24,
                              pulse=total is None, animation_time=time.monotonic())
            count = ""
            if s["done"] is not None:
                count = f"{_fmt_count(s['done'])}" + (f"/{_fmt_count(total)}" if total else "") + f" {s['unit']}"
            rows.add_row(Text(a.subject, style="cyan"), Text(a.stage, style="bold"), Text(s["what"]), bar,
                         Text(count), Text(_fmt_rate(s["rate"], s["unit"])),
                         Text(f"ETA {fmt_duration(s['eta'])}" if s["eta"] is not None else ""),
                         Text(f"elapsed {fmt_duration(s['elapsed'])}"))
        table.add_row(rows)
        return table

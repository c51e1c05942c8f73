"""User-facing errors. A stage that raises one of these exits with a clear one-line message
(exit code 3) instead of a traceback; anything else is a bug and keeps its traceback.

:class:`HumanVDMError` is the base of every user-facing error; a project's own errors subclass it."""

from __future__ import annotations

import errno
import math
import os
from pathlib import Path

DISK_FULL_ERRNOS = (errno.ENOSPC, errno.EDQUOT)
# "No space left on device", "Disk quota exceeded", and SQLite's "database or disk is full"
DISK_FULL_TEXTS = (os.strerror(errno.ENOSPC), os.strerror(errno.EDQUOT), "database or disk is full")


class HumanVDMError(Exception):
    """An error a user can act on; its message says what is wrong and what to do."""


class InputError(HumanVDMError):
    """An input (a run's input file, or an artifact a stage reads) cannot be used as it is."""


class ConfigError(HumanVDMError):
    """pipeline.yaml, a param or a command-line setting is wrong."""


class DiskFullError(HumanVDMError):
    """The store's disk (or quota) is full. Its message is one line: where, and how much to free
    (``need_bytes``, rounded up to MB; "some space" when unknown)."""

    def __init__(self, where: str | Path, need_bytes: int = 0):
        self.where, self.need_bytes = Path(where), int(need_bytes)
        amount = f"{max(1, math.ceil(self.need_bytes / 1e6))} MB" if self.need_bytes > 0 else "some space"
        super().__init__(f"no space left on device writing {self.where}; free {amount} and rerun")


def is_disk_full(exc: BaseException | str | None) -> bool:
    """Whether an exception (or an error line) says the disk or the quota is full.

    An ``OSError`` with errno ENOSPC/EDQUOT is; so is any message holding the C library's text for
    them (libraries that wrap the error, e.g. in a RuntimeError, keep that text)."""
    if isinstance(exc, DiskFullError):
        return True
    if isinstance(exc, OSError) and exc.errno in DISK_FULL_ERRNOS:
        return True
    text = exc if isinstance(exc, str) else str(exc) if exc is not None else ""
    return any(t in text for t in DISK_FULL_TEXTS)

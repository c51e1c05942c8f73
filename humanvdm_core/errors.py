"""User-facing errors. A stage that raises one of these exits with a clear one-line message
(exit code 3) instead of a traceback; anything else is a bug and keeps its traceback."""

from __future__ import annotations

from pathlib import Path


class HumanVDMError(Exception):
    """An error a user can act on; its message says what is wrong and what to do."""


class InputError(HumanVDMError):
    """The input (photo, scan, frame set) cannot be used as it is."""


class ConfigError(HumanVDMError):
    """pipeline.yaml, a param or a command-line setting is wrong."""


class MissingWeightsError(HumanVDMError):
    """A real-model backend's local checkpoint file is missing."""

    def __init__(self, path: str | Path, what: str, where_to_get: str):
        super().__init__(
            f"missing weight file {path} ({what}). Nothing is downloaded at run time: get it from "
            f"{where_to_get} and put it at {path}, or choose another backend."
        )
        self.path = Path(path)


def require_weights(path: str | Path, what: str, where_to_get: str) -> Path:
    """Return ``path`` if the file exists, else raise :class:`MissingWeightsError`."""
    p = Path(path).expanduser()
    if not p.is_file():
        raise MissingWeightsError(p, what, where_to_get)
    return p

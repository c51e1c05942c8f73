"""User-facing errors of the reconstruction modules, on top of the engine's
(:mod:`humanvdm_core.workflow.errors`): a real-model backend's missing weight file."""

from __future__ import annotations

from pathlib import Path

from humanvdm_core.workflow.errors import HumanVDMError


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

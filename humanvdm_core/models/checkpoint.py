"""Loading official checkpoints: unwrap, strip prefixes, check keys, cache per file.

- :func:`read_state_dict` loads a ``.pth``/``.pkl`` (``torch.load(weights_only=True)``: tensors
  only, no pickled code runs) or ``.safetensors`` file, unwraps the usual containers
  (``params_ema`` first, as BasicSR's inference does, then ``params``, ``state_dict``) and strips
  a DataParallel ``module.`` prefix.  A missing file raises
  :class:`~humanvdm_core.errors.MissingWeightsError` naming it and where to get it.
- :func:`load_strict` loads a state dict into a module and raises :class:`CheckpointError`
  listing missing/unexpected keys and shape mismatches when the layout is not the expected one.
- :func:`build_strict` does both for an architecture read from the checkpoint's shapes.
- :func:`cached_model` builds a model once per (builder, file path, size, mtime) in a process.
- :func:`deterministic` makes a model's inference give the same bits for the same inputs on CUDA too.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

from humanvdm_core.errors import require_weights
from humanvdm_core.workflow.errors import HumanVDMError

_WRAPPERS = ("params_ema", "params", "state_dict", "model")
_CACHE: dict[tuple, Any] = {}


class CheckpointError(HumanVDMError):
    """A weight file exists but is not the checkpoint layout the backend expects."""


def read_state_dict(path: str | Path, what: str, where_to_get: str) -> dict:
    """The tensors of checkpoint ``path`` as a flat ``{key: tensor}`` dict (see module docstring)."""
    import torch

    p = require_weights(path, what, where_to_get)
    try:
        if p.suffix == ".safetensors":
            from safetensors.torch import load_file

            sd: Any = load_file(str(p))
        else:
            sd = torch.load(str(p), map_location="cpu", weights_only=True)
    except Exception as e:  # a truncated or foreign file: say which one
        raise CheckpointError(f"cannot read {what} checkpoint {p}: {type(e).__name__}: {e}") from None
    for key in _WRAPPERS:
        if isinstance(sd, dict) and key in sd and isinstance(sd[key], dict):
            sd = sd[key]
            break
    if not isinstance(sd, dict) or not all(hasattr(v, "shape") for v in sd.values()):
        raise CheckpointError(f"{what} checkpoint {p} is not a state dict of tensors")
    if sd and all(k.startswith("module.") for k in sd):
        sd = {k[len("module."):]: v for k, v in sd.items()}
    return sd


def load_strict(module, state_dict: dict, what: str, path: str | Path) -> None:
    """``module.load_state_dict(state_dict)`` with a readable error naming every mismatch."""
    own = module.state_dict()
    missing = sorted(set(own) - set(state_dict))
    unexpected = sorted(set(state_dict) - set(own))
    shapes = sorted(f"{k}: checkpoint {tuple(state_dict[k].shape)} vs model {tuple(own[k].shape)}"
                    for k in set(own) & set(state_dict) if tuple(own[k].shape) != tuple(state_dict[k].shape))
    if missing or unexpected or shapes:
        def show(items: list[str]) -> str:
            return ", ".join(items[:8]) + (f" (+{len(items) - 8} more)" if len(items) > 8 else "")

        parts = [f"missing keys: {show(missing)}" if missing else "",
                 f"unexpected keys: {show(unexpected)}" if unexpected else "",
                 f"shape mismatches: {show(shapes)}" if shapes else ""]
        raise CheckpointError(f"{path} is not a {what} checkpoint in the expected key layout; "
                              + "; ".join(p for p in parts if p))
    module.load_state_dict(state_dict, strict=True)


def build_strict(path: str | Path, what: str, where_to_get: str, make: Callable[[dict, Path], Any]) -> Any:
    """The module ``make(state_dict, path)`` builds for checkpoint ``path`` (architecture read from the
    tensors), its weights loaded with :func:`load_strict`, on :func:`infer_device`."""
    sd = read_state_dict(path, what, where_to_get)
    net = make(sd, Path(path))
    load_strict(net, sd, what, path)
    return net.to(infer_device())


def cached_model(builder: Callable[[Path], Any], path: str | Path) -> Any:
    """``builder(path)`` once per process for the same file (path, size, mtime); eval mode, no grad."""
    p = Path(path).expanduser()
    try:
        st = p.stat()
        key = (builder, str(p.resolve()), st.st_size, st.st_mtime_ns)
    except OSError:
        return builder(p)  # the builder raises MissingWeightsError
    if key not in _CACHE:
        model = builder(p)
        model.eval()
        for param in model.parameters():
            param.requires_grad_(False)
        _CACHE[key] = model
    return _CACHE[key]


def infer_device():
    """CUDA when available, else CPU (the tests and benchmarks here run on CPU)."""
    import torch

    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


def deterministic(fn: Callable) -> Callable:
    """Decorator: run ``fn`` with torch's deterministic algorithms when CUDA is present (reductions that
    use atomic adds on the GPU, such as PerVFI's ``index_add_`` splatting, sorted instead; cuDNN's
    deterministic convolutions; cuBLAS with a fixed workspace), so the same inputs give the same output
    bits on every run, as on the CPU; the previous settings are restored afterwards. Without CUDA it
    changes nothing."""

    @functools.wraps(fn)
    def run(*args: Any, **kwargs: Any) -> Any:
        import torch

        if not torch.cuda.is_available():
            return fn(*args, **kwargs)
        os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")  # read when cuBLAS starts
        cudnn = torch.backends.cudnn
        saved = (torch.are_deterministic_algorithms_enabled(), torch.is_deterministic_algorithms_warn_only_enabled(),
                 cudnn.deterministic, cudnn.benchmark)
        torch.use_deterministic_algorithms(True, warn_only=True)
        cudnn.deterministic, cudnn.benchmark = True, False
        try:
            return fn(*args, **kwargs)
        finally:
            torch.use_deterministic_algorithms(saved[0], warn_only=saved[1])
            cudnn.deterministic, cudnn.benchmark = saved[2], saved[3]

    return run

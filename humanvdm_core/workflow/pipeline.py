"""``pipeline.yaml``: the DAG of stages, loaded and validated before anything runs.

Format::

    schema: 1
    inputs:                       # what a run is given; a run binds one of them per subject
      photo: {kind: image, help: ...}
      scan: {kind: scan, help: ...}
    stages:
      upscale:
        module: stages.upscale                  # executable: python -m stages.upscale
        inputs: {frames: "diffuse.orbit | render-training-orbits.orbit"}
        outputs: [frames]
        params: {target_size: 1080}             # override the stage's own defaults
        backend: embedded
        resources: {num_cpus: 1, memory: 2GB}   # what one run needs (the Ray executor asks for it)

``resources`` (all optional): ``num_cpus`` (default 1), ``num_gpus`` (default 0), ``memory`` (bytes,
or a string such as ``512MB``/``8GB``/``2GiB``; default: none asked). Its ``when`` maps a setting of
the run, ``backend=NAME`` or ``PARAM=VALUE`` (as ``--set`` writes them), to resources that replace
those fields when the run's resolved backend or param has that value, in the order written::

        resources:
          num_cpus: 1
          when: {backend=sv3d_p: {num_gpus: 1, memory: 16GB}}

``--set stage.resources.num_gpus=1`` overrides the result. Resources never join a stage run's key
(they change where it runs, not what it computes); the local executor ignores them (``--jobs``
bounds what runs at once there).

An input reference is ``$name`` (a run input) or ``stage.output``; ``a | b`` lists alternatives,
the first one available in the run is used (a photo run has ``diffuse``, a scan run has
``render-training-orbits``). A trailing ``?`` makes an input optional: without it the stage still
runs (e.g. ``evaluate`` compares with a scan's ground truth only when the run has a scan). A stage whose module does not exist yet is *not implemented*: it is
shown, never run, and the stages that need it are blocked.

Validation raises :class:`ConfigError` naming the stage for: invalid YAML or duplicate keys,
unknown keys, cycles, references to unknown stages/outputs/inputs, duplicate outputs, params the
stage does not declare or of the wrong type, unknown backends, a module whose declared
inputs/outputs differ from the YAML, and resources that are unknown, negative or conditioned on an
unknown backend or param.
"""

from __future__ import annotations

import ast
import hashlib
import importlib
import importlib.util
import re
import sys
from dataclasses import dataclass, field, replace
from functools import cache
from pathlib import Path
from typing import Any

import yaml

from humanvdm_core.workflow.errors import ConfigError
from humanvdm_core.workflow.stage import StageSpec

_STAGE_KEYS = {"module", "inputs", "outputs", "params", "backend", "help", "resources"}
_MEMORY_UNITS = {"": 1, "b": 1, "kb": 10**3, "mb": 10**6, "gb": 10**9, "tb": 10**12,
                 "kib": 2**10, "mib": 2**20, "gib": 2**30, "tib": 2**40}


class _UniqueKeyLoader(yaml.SafeLoader):
    pass


def _construct_mapping(loader: yaml.SafeLoader, node: yaml.MappingNode, deep: bool = False) -> dict:
    seen = set()
    for key_node, _ in node.value:
        key = loader.construct_object(key_node, deep=deep)
        if key in seen:
            raise ConfigError(f"duplicate key {key!r} at line {key_node.start_mark.line + 1}")
        seen.add(key)
    return yaml.SafeLoader.construct_mapping(loader, node, deep)


_UniqueKeyLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)


@dataclass(frozen=True)
class Ref:
    """One input reference: a run input (``stage is None``) or a stage output."""

    stage: str | None
    name: str

    def __str__(self) -> str:
        return f"${self.name}" if self.stage is None else f"{self.stage}.{self.name}"


@dataclass(frozen=True)
class Resources:
    """What one run of a stage needs where it runs (a Ray task's resources); never part of its key."""

    num_cpus: float = 1.0
    num_gpus: float = 0.0
    memory: int | None = None  # bytes

    def updated(self, stage: str, fields: dict[str, Any]) -> Resources:
        """A copy with ``fields`` (from YAML or ``--set``) parsed and applied; ConfigError names the stage."""
        out = {}
        for key, value in fields.items():
            if key in ("num_cpus", "num_gpus"):
                try:
                    number = float(value)
                except (TypeError, ValueError):
                    number = -1.0
                if isinstance(value, bool) or not number >= 0:
                    raise ConfigError(f"stage {stage}: resources.{key} must be a number >= 0, not {value!r}")
                out[key] = number
            elif key == "memory":
                out[key] = parse_memory(stage, value)
            else:
                raise ConfigError(f"stage {stage}: unknown resource {key!r}; known: num_cpus, num_gpus, memory (and when)")
        return replace(self, **out)

    def as_dict(self) -> dict[str, Any]:
        return {"num_cpus": self.num_cpus, "num_gpus": self.num_gpus, "memory": self.memory}


def parse_memory(stage: str, value: Any) -> int | None:
    """Bytes from an int or a string like ``512MB``, ``8GB``, ``2GiB`` (None/0: not asked)."""
    if value is None:
        return None
    if isinstance(value, int) and not isinstance(value, bool) and value >= 0:
        return value or None
    m = re.fullmatch(r"\s*(\d+(?:\.\d+)?)\s*([A-Za-z]*)\s*", str(value))
    if m is None or m.group(2).lower() not in _MEMORY_UNITS or isinstance(value, bool):
        raise ConfigError(f"stage {stage}: resources.memory {value!r} is not a size (bytes, or e.g. 512MB, 8GB, 2GiB)")
    return int(float(m.group(1)) * _MEMORY_UNITS[m.group(2).lower()]) or None


@dataclass
class StageDef:
    name: str
    module: str
    inputs: dict[str, list[Ref]]
    outputs: list[str]
    params: dict[str, Any]
    backend: str
    help: str = ""
    optional: set[str] = field(default_factory=set)  # inputs marked ``?``: the stage runs without them
    spec: StageSpec | None = None  # None: module not implemented yet
    resources: Resources = field(default_factory=Resources)
    resources_when: list[tuple[str, str, dict[str, Any]]] = field(default_factory=list)  # (name, value, fields)

    @property
    def implemented(self) -> bool:
        return self.spec is not None

    def resources_for(self, params: dict[str, Any], backend: str) -> Resources:
        """The resources of a run with these resolved params and backend (``when`` applied in order)."""
        out = self.resources
        for name, value, fields in self.resources_when:
            current = backend if name == "backend" else params.get(name)
            if _setting_text(current) == value:
                out = out.updated(self.name, fields)
        return out


@dataclass
class Pipeline:
    path: Path
    inputs: dict[str, dict]
    stages: dict[str, StageDef] = field(default_factory=dict)

    def order(self) -> list[str]:
        """Stage names in a topological order (declaration order among independent stages)."""
        return _topological(self)

    def upstream(self, stage: str) -> set[str]:
        out, todo = set(), [stage]
        while todo:
            for alts in self.stages[todo.pop()].inputs.values():
                for ref in alts:
                    if ref.stage is not None and ref.stage not in out:
                        out.add(ref.stage)
                        todo.append(ref.stage)
        return out

    def resolve_params(self, stage: str, overrides: dict[str, Any] | None = None) -> dict[str, Any]:
        sd = self.stages[stage]
        merged = {**sd.params, **(overrides or {})}
        if sd.spec is None:
            return merged
        return sd.spec.resolve_params(merged)


def parse_ref(stage: str, text: str) -> tuple[list[Ref], bool]:
    """Alternatives of one input reference, and whether it is optional (a trailing ``?``)."""
    text = str(text).strip()
    optional = text.endswith("?")
    alts = []
    for part in text.rstrip("?").split("|"):
        part = part.strip()
        if part.startswith("$") and len(part) > 1:
            alts.append(Ref(None, part[1:]))
        elif part.count(".") == 1 and all(part.split(".")):
            s, o = part.split(".")
            alts.append(Ref(s, o))
        else:
            raise ConfigError(f"stage {stage}: bad input reference {part!r} (use $input or stage.output)")
    return alts, optional


def load_spec(module: str) -> StageSpec | None:
    """The ``SPEC`` of a stage module, or None when the module does not exist."""
    try:
        if importlib.util.find_spec(module) is None:
            return None
    except ModuleNotFoundError:
        return None
    mod = importlib.import_module(module)
    spec = getattr(mod, "SPEC", None)
    if not isinstance(spec, StageSpec):
        raise ConfigError(f"module {module} has no SPEC (a humanvdm_core.workflow.stage.StageSpec)")
    return spec


def load_pipeline(path: str | Path) -> Pipeline:
    """Load and validate a pipeline; its folder goes on ``sys.path`` so its stage modules import."""
    path = Path(path).resolve()
    if str(path.parent) not in sys.path:
        sys.path.insert(0, str(path.parent))
    try:
        doc = yaml.load(path.read_text(), Loader=_UniqueKeyLoader)
    except yaml.YAMLError as e:
        raise ConfigError(f"{path}: invalid YAML: {e}") from None
    except ConfigError as e:
        raise ConfigError(f"{path}: {e}") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("stages"), dict):
        raise ConfigError(f"{path}: expected a mapping with 'stages'")
    if doc.get("schema", 1) != 1:
        raise ConfigError(f"{path}: unsupported schema {doc.get('schema')}")
    unknown_top = set(doc) - {"schema", "inputs", "stages"}
    if unknown_top:
        raise ConfigError(f"{path}: unknown top-level keys {sorted(unknown_top)}")
    pipe = Pipeline(path, dict(doc.get("inputs") or {}))
    for name, body in doc["stages"].items():
        if not isinstance(body, dict):
            raise ConfigError(f"stage {name}: expected a mapping")
        extra = set(body) - _STAGE_KEYS
        if extra:
            raise ConfigError(f"stage {name}: unknown keys {sorted(extra)}; allowed: {sorted(_STAGE_KEYS)}")
        if "module" not in body:
            raise ConfigError(f"stage {name}: missing 'module'")
        outputs = list(body.get("outputs") or [])
        if len(set(outputs)) != len(outputs):
            dup = sorted({o for o in outputs if outputs.count(o) > 1})
            raise ConfigError(f"stage {name}: duplicate outputs {dup}")
        if not outputs:
            raise ConfigError(f"stage {name}: declares no outputs")
        parsed = {k: parse_ref(name, v) for k, v in (body.get("inputs") or {}).items()}
        inputs = {k: alts for k, (alts, _) in parsed.items()}
        optional = {k for k, (_, opt) in parsed.items() if opt}
        params = body.get("params") or {}
        if not isinstance(params, dict):
            raise ConfigError(f"stage {name}: params must be a mapping")
        resources, when = _parse_resources(name, body.get("resources"))
        pipe.stages[name] = StageDef(name, str(body["module"]), inputs, outputs, dict(params),
                                     str(body.get("backend", "embedded")), str(body.get("help", "")), optional,
                                     resources=resources, resources_when=when)
    _validate(pipe)
    return pipe


def _setting_text(value: Any) -> str:
    """A param value as ``--set`` and ``when`` write it (booleans lower-case)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    return str(value)


def _parse_resources(stage: str, body: Any) -> tuple[Resources, list[tuple[str, str, dict[str, Any]]]]:
    if body is None:
        return Resources(), []
    if not isinstance(body, dict):
        raise ConfigError(f"stage {stage}: resources must be a mapping (num_cpus, num_gpus, memory, when)")
    body = dict(body)
    when_body = body.pop("when", None) or {}
    resources = Resources().updated(stage, body)
    if not isinstance(when_body, dict):
        raise ConfigError(f"stage {stage}: resources.when must map NAME=VALUE to resources")
    when = []
    for cond, fields in when_body.items():
        name, sep, value = str(cond).partition("=")
        if not sep or not name.strip() or not isinstance(fields, dict):
            raise ConfigError(f"stage {stage}: resources.when: expected 'backend=NAME' or 'PARAM=VALUE' "
                              f"mapped to resources, got {cond!r}")
        resources.updated(stage, fields)  # validates the fields
        when.append((name.strip(), value.strip(), dict(fields)))
    return resources, when


def _validate(pipe: Pipeline) -> None:
    for sd in pipe.stages.values():
        for inp, alts in sd.inputs.items():
            for ref in alts:
                if ref.stage is None:
                    if ref.name not in pipe.inputs:
                        raise ConfigError(f"stage {sd.name}: input {inp} refers to unknown run input ${ref.name}")
                elif ref.stage not in pipe.stages:
                    raise ConfigError(f"stage {sd.name}: input {inp} refers to unknown stage {ref.stage!r}")
                elif ref.name not in pipe.stages[ref.stage].outputs:
                    raise ConfigError(f"stage {sd.name}: input {inp} refers to {ref}, but stage {ref.stage} "
                                      f"has outputs {pipe.stages[ref.stage].outputs}")
    _topological(pipe)  # raises on cycles
    for sd in pipe.stages.values():
        sd.spec = load_spec(sd.module)
        if sd.spec is None:
            continue
        if set(sd.spec.optional) != sd.optional:
            raise ConfigError(f"stage {sd.name}: pipeline marks inputs {sorted(sd.optional)} optional (?), "
                              f"module {sd.module} has {sorted(sd.spec.optional)}")
        if set(sd.spec.inputs) != set(sd.inputs) or list(sd.spec.outputs) != sd.outputs:
            raise ConfigError(f"stage {sd.name}: pipeline declares inputs {sorted(sd.inputs)} / outputs "
                              f"{sd.outputs}, module {sd.module} has {sorted(sd.spec.inputs)} / {list(sd.spec.outputs)}")
        sd.spec.check_backend(sd.backend)
        sd.spec.resolve_params(sd.params)
        for name, value, _ in sd.resources_when:
            if name == "backend":
                sd.spec.check_backend(value)
            elif name not in sd.spec.params:
                raise ConfigError(f"stage {sd.name}: resources.when: unknown param {name!r}; "
                                  f"known: backend, {', '.join(sorted(sd.spec.params))}")


def _topological(pipe: Pipeline) -> list[str]:
    order: list[str] = []
    state: dict[str, int] = {}

    def visit(name: str, path: list[str]) -> None:
        if state.get(name) == 2:
            return
        if state.get(name) == 1:
            cycle = path[path.index(name):] + [name]
            raise ConfigError(f"cycle in pipeline: {' -> '.join(cycle)}")
        state[name] = 1
        for alts in pipe.stages[name].inputs.values():
            for ref in alts:
                if ref.stage is not None:
                    visit(ref.stage, path + [name])
        state[name] = 2
        order.append(name)

    for name in pipe.stages:
        visit(name, [])
    return order


# ---------------------------------------------------------------------- code fingerprints

PROJECT_PACKAGE = __name__.partition(".")[0]  # the package this engine ships in: its modules are project code


def code_fingerprint(module: str, package_roots: tuple[str, ...] = (PROJECT_PACKAGE,)) -> str:
    """Hash of a stage module's source and of every project module it imports, transitively
    (modules of ``package_roots``, by default the package the engine ships in, and of the stage's
    own top-level package, e.g. ``stages``).

    Imports inside functions count (stages import heavy modules lazily). Third-party code is not
    part of the fingerprint; its versions are recorded in the lockfile instead.
    """
    sources = _project_sources(module, (*package_roots, module.split(".")[0]))
    h = hashlib.sha256()
    for name in sorted(sources):
        h.update(name.encode() + b"\0" + sources[name] + b"\n")
    return h.hexdigest()


def _project_sources(module: str, roots: tuple[str, ...]) -> dict[str, bytes]:
    seen: dict[str, bytes] = {}
    todo = [module]
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        path = _module_file(name)
        if path is None:
            continue
        src = path.read_bytes()
        seen[name] = src
        todo.extend(m for m in _imports(name, path, src) if m.split(".")[0] in roots)
    return seen


@cache
def _module_file(name: str) -> Path | None:
    """The source file of a module, found by path from its top-level package without importing
    anything below it (``find_spec`` on a submodule would run its packages' ``__init__``)."""
    top, _, rest = name.partition(".")
    try:
        spec = importlib.util.find_spec(top)
    except (ModuleNotFoundError, ValueError):
        return None
    if spec is None or spec.origin is None or not spec.origin.endswith(".py"):
        return None
    base = Path(spec.origin)
    if not rest:
        return base
    if base.name != "__init__.py":
        return None
    path = base.parent.joinpath(*rest.split("."))
    for candidate in (path.with_suffix(".py"), path / "__init__.py"):
        if candidate.is_file():
            return candidate
    return None


def _imports(name: str, path: Path, src: bytes) -> list[str]:
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = []
    for node in ast.walk(ast.parse(src)):
        if isinstance(node, ast.Import):
            out.extend(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")
                parent = ".".join(parts[: len(parts) - node.level + 1])
                base = f"{parent}.{base}" if base else parent
            out.append(base)
            out.extend(f"{base}.{a.name}" for a in node.names)  # `from pkg import module`
        # parents of a submodule run their __init__ too
    with_parents = []
    for m in out:
        parts = m.split(".")
        with_parents.extend(".".join(parts[:i]) for i in range(1, len(parts) + 1))
    return with_parents

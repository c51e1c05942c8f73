"""The engine's command line: run, explain and maintain a pipeline.

    PROG run INPUT... [--jobs N] [--force STAGE] [--until STAGE] [--set stage.param=value] [--dry-run]
                 [--executor local|ray [--address auto|HOST:PORT]]
    PROG status INPUT...        per stage: would it run, and why
    PROG dag [--params]         the stages, their inputs and outputs
    PROG params [STAGE...]      every stage's params: default, type, choices, help (names for --set)
    PROG verify                 re-hash the whole store, quarantine corrupt entries
    PROG gc                     remove artifacts that no run references
    PROG show RUN|ARTIFACT_ID   a run's lockfile summary, or an artifact's files and origin

A project makes its command from an :class:`App`: its name, how the paths given on the command
line become subjects (``discover``) and get into the store (``import_subject``), the pipeline used
where the working folder has none, verbs of its own (:class:`Verb`), and what to show under each
finished run's outputs (``show_outputs``). :func:`main` parses, dispatches, and turns a user error
(:class:`~humanvdm_core.workflow.errors.HumanVDMError`, a full disk) into one line and exit code 2.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from humanvdm_core.workflow.errors import DiskFullError, HumanVDMError, is_disk_full
from humanvdm_core.workflow.executors import EXECUTORS, make_executor
from humanvdm_core.workflow.pipeline import Pipeline, load_pipeline
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
    Subject,
    read_lockfile,
    referenced_ids,
    user_names,
)
from humanvdm_core.workflow.store import Store

RAY_JOBS = 256  # stage runs in flight on Ray by default; the cluster's resources bound what runs at once


@dataclass(frozen=True)
class Verb:
    """A subcommand of the project's own: its help line, its arguments (added after ``--store`` and
    ``--pipeline``) and its handler (returns the exit code; may raise a user error)."""

    help: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]


@dataclass(frozen=True)
class App:
    """What makes the engine's command line a project's command."""

    prog: str
    description: str
    default_pipeline: Path  # the pipeline.yaml used where the working folder has none
    discover: Callable[[list[str], str | None], list[Subject]]  # command-line paths (and --kind) -> subjects
    import_subject: Callable[[Store, Subject], object]  # put a subject's files in the store, set its input_id
    inputs_help: str = "input files or folders"
    set_example: str = "stage.param=value"  # an example of --set, shown under run, status and dag
    verbs: Mapping[str, Verb] = field(default_factory=dict)
    show_outputs: Callable[[argparse.Namespace, Store, str, Path], None] | None = None  # (args, store, run, run folder)

    @property
    def params_hint(self) -> str:
        return (f"Param names for --set STAGE.PARAM=VALUE (e.g. {self.set_example}):\n"
                f"  {self.prog} params [STAGE]   lists every stage's params with their defaults, choices and help.")


def parse_sets(items: list[str]) -> dict[str, dict[str, str]]:
    """``--set`` items as {stage: {name: value}}; the stage is what precedes the first dot (stage names
    have none), so ``stage.resources.num_gpus=1`` gives {"stage": {"resources.num_gpus": "1"}}."""
    out: dict[str, dict[str, str]] = {}
    for item in items:
        key, sep, value = item.partition("=")
        stage, dot, param = key.partition(".")
        if not sep or not dot or not stage or not param:
            raise HumanVDMError(f"--set {item!r}: expected stage.param=value")
        out.setdefault(stage, {})[param] = value
    return out


def _add_common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--store", type=Path, default=Path(os.environ.get("HUMANVDM_STORE", "artifacts")),
                   help="artifact store folder (default: ./artifacts or $HUMANVDM_STORE)")
    p.add_argument("--pipeline", type=Path, default=None, help="pipeline.yaml (default: ./pipeline.yaml, else the project's)")


def _add_selection(p: argparse.ArgumentParser, app: App) -> None:
    p.add_argument("inputs", nargs="+", help=app.inputs_help)
    p.add_argument("--kind", choices=None, default=None, help="force the input kind (one of pipeline.yaml's inputs)")
    p.add_argument("--force", action="append", default=[], metavar="STAGE", help="rerun STAGE even if cached")
    p.add_argument("--until", metavar="STAGE", help="run STAGE and what it needs, nothing after it")
    p.add_argument("--set", action="append", default=[], metavar="STAGE.PARAM=VALUE",
                   help=f"override a param; STAGE.backend=NAME chooses a backend. `{app.prog} params [STAGE]` lists "
                        "every stage's params with their defaults, choices and help")


def build_parser(app: App) -> argparse.ArgumentParser:
    """The engine's verbs, then the app's own."""
    parser = argparse.ArgumentParser(prog=app.prog, description=app.description)
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("run", help="run the pipeline on inputs (cached stages are reused)",
                       epilog=app.params_hint, formatter_class=argparse.RawDescriptionHelpFormatter)
    _add_common(p)
    _add_selection(p, app)
    p.add_argument("-j", "--jobs", type=int, default=None,
                   help="stage runs in parallel (default 1; with --executor ray: stage runs in flight, "
                        f"default {RAY_JOBS}, which Ray queues by the resources each asks for)")
    p.add_argument("--executor", choices=EXECUTORS, default="local",
                   help="where stage runs execute: this machine (default), or Ray tasks on a cluster (needs the "
                        "'cluster' extra and a store every node sees, e.g. --store /nfs/artifacts)")
    p.add_argument("--address", default=None, metavar="auto|HOST:PORT",
                   help="the Ray cluster to use with --executor ray (default: $RAY_ADDRESS, else a new local one)")
    p.add_argument("--threads", type=int, default=None, metavar="N",
                   help="compute threads per stage run (default: the cores this process may use, divided by --jobs)")
    p.add_argument("--dry-run", action="store_true", help="say what would run, run nothing")
    p.add_argument("--no-progress", action="store_true",
                   help="plain progress lines (each stage run's start and end, and every --progress-interval "
                        "seconds its phase, count, rate and ETA) instead of the live display, even on a terminal "
                        "(without a terminal that is the default)")
    p.add_argument("--progress-interval", type=float, default=None, metavar="SECONDS",
                   help="seconds between plain progress lines (default 15, or $HUMANVDM_PROGRESS_INTERVAL)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress output; only the final summary")
    p = sub.add_parser("status", help="per stage: would it run, and why", epilog=app.params_hint,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    _add_common(p)
    _add_selection(p, app)
    p = sub.add_parser("dag", help="show the pipeline's stages", epilog=app.params_hint,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    _add_common(p)
    p.add_argument("--dot", action="store_true", help="Graphviz output")
    p.add_argument("--params", action="store_true", help=f"with each stage's params (as `{app.prog} params`)")
    p = sub.add_parser("params", help="every stage's params: defaults, choices, help (names for --set)")
    _add_common(p)
    p.add_argument("stages", nargs="*", metavar="STAGE", help="only these stages (default: all)")
    p = sub.add_parser("verify", help="re-hash every artifact; quarantine corrupt ones")
    _add_common(p)
    p.add_argument("--no-quarantine", action="store_true", help="only report")
    p = sub.add_parser("gc", help="remove artifacts no run references")
    _add_common(p)
    p = sub.add_parser("show", help="a run's lockfile summary, or an artifact's files")
    _add_common(p)
    p.add_argument("what", help="run (subject) name or artifact id (prefix ok)")
    for name, verb in app.verbs.items():
        p = sub.add_parser(name, help=verb.help)
        _add_common(p)
        verb.add_arguments(p)
    return parser


def main(argv: list[str] | None, app: App) -> int:
    """Run one command of ``app``; returns the exit code."""
    args = build_parser(app).parse_args(argv)
    try:
        if args.command in app.verbs:
            return app.verbs[args.command].run(args)
        return COMMANDS[args.command](args, app)
    except HumanVDMError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except OSError as e:
        if not is_disk_full(e):
            raise
        print(f"error: {DiskFullError(Path(getattr(args, 'store', None) or e.filename or '.').resolve())}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # output piped into `head` and the like
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except KeyboardInterrupt:
        print("interrupted: running stages were stopped; the store holds only complete artifacts", file=sys.stderr)
        return 130


def _pipeline(args, app: App) -> Pipeline:
    local = Path("pipeline.yaml")
    return load_pipeline(args.pipeline or (local if local.is_file() else app.default_pipeline))


def _scheduler(args, pipe: Pipeline, store: Store, **kw) -> Scheduler:
    return Scheduler(pipe, store, overrides=parse_sets(args.set), force=set(args.force), until=args.until, **kw)


def _subjects(args, app: App, store: Store, pipe: Pipeline) -> list[Subject]:
    subjects = app.discover(args.inputs, args.kind)
    for s in subjects:
        if s.kind not in pipe.inputs:
            raise HumanVDMError(f"{s.source}: kind {s.kind!r} is not an input of {pipe.path} ({list(pipe.inputs)})")
        app.import_subject(store, s)
    return subjects


MARK = {UP_TO_DATE: "ok ", WILL_RUN: "RUN", MAY_RUN: "run?", NOT_IMPLEMENTED: "n/i", BLOCKED: "blk"}


def cmd_status(args, app: App) -> int:
    pipe = _pipeline(args, app)
    store = Store(args.store)
    runs = _scheduler(args, pipe, store).status(_subjects(args, app, store, pipe))
    _print_status(runs)
    return 0


def _print_status(runs) -> None:
    subject = None
    for r in runs:
        if r.subject.name != subject:
            subject = r.subject.name
            print(f"{subject} ({r.subject.kind}: {r.subject.source})")
        print(f"  {MARK.get(r.state, r.state):4} {r.stage:24} {r.state}: {r.reason}")


def cmd_run(args, app: App) -> int:
    pipe = _pipeline(args, app)
    store = Store(args.store)
    mode = "quiet" if args.quiet else "plain" if args.no_progress else "auto"
    executor = make_executor(args.executor, args.address)
    jobs = args.jobs if args.jobs is not None else RAY_JOBS if args.executor == "ray" else 1
    try:
        sched = _scheduler(args, pipe, store, jobs=jobs, threads=args.threads, progress=mode,
                           progress_interval=args.progress_interval, executor=executor)
        subjects = _subjects(args, app, store, pipe)
        if args.dry_run:
            _print_status(sched.status(subjects))
            return 0
        summary = sched.run(subjects)
    finally:
        executor.close()
    ran, cached = summary.count(RAN), summary.count(CACHED)
    print(f"\n{len(subjects)} input(s): {ran} stage run(s) ran, {cached} cached, "
          f"{summary.count(FAILED)} failed, {summary.count(SKIPPED)} skipped")
    missing = sorted({r.stage for r in summary.runs if r.state == NOT_IMPLEMENTED})
    if missing:
        blocked = sorted({r.stage for r in summary.runs if r.state == BLOCKED})
        print(f"not implemented yet: {', '.join(missing)}" + (f" (so not run: {', '.join(blocked)})" if blocked else ""))
    for r in summary.runs:
        for w in r.warnings:
            print(f"warning {r.label}: {user_names(r, w)}")
    for r in summary.failed:
        print(f"FAILED {r.label}: {r.reason}" + (f"\n  log: {r.log}" if r.log else ""))
    done = {r.subject.name for r in summary.runs if r.state in (RAN, CACHED)}
    for s in subjects:
        if s.name in done:
            base = store.root / "runs" / s.name
            print(f"outputs of {s.name}: {base}")
            if app.show_outputs is not None:
                app.show_outputs(args, store, s.name, base)
    return 0 if summary.ok else 1


def store_flag(args) -> str:
    """The --store option a person must repeat in later commands ('' for the default store)."""
    default = Path(os.environ.get("HUMANVDM_STORE", "artifacts"))
    return "" if Path(args.store) == default else str(args.store)


def cmd_dag(args, app: App) -> int:
    pipe = _pipeline(args, app)
    if args.dot:
        print(f"digraph {app.prog} {{")
        for name, sd in pipe.stages.items():
            style = "" if sd.implemented else ' [style=dashed, label="' + name + '\\n(not implemented)"]'
            print(f'  "{name}"{style};')
            for alts in sd.inputs.values():
                for ref in alts:
                    src = f"${ref.name}" if ref.stage is None else ref.stage
                    print(f'  "{src}" -> "{name}" [label="{ref.name}"];')
        print("}")
        return 0
    for name in pipe.order():
        sd = pipe.stages[name]
        if args.params:
            _print_params(pipe, name)
            continue
        ins = ", ".join(f"{k}<-{' | '.join(map(str, v))}{'?' if k in sd.optional else ''}"
                        for k, v in sd.inputs.items())
        flag = "" if sd.implemented else "  [not implemented yet]"
        res = sd.resources
        wants = f"num_cpus={res.num_cpus:g} num_gpus={res.num_gpus:g}" + (f" memory={res.memory / 1e9:g}GB" if res.memory else "")
        wants += "".join(f"; {name}={value}: {fields}" for name, value, fields in sd.resources_when)
        print(f"{name}{flag}\n    module: {sd.module}  backend: {sd.backend}\n    in:  {ins}\n    out: {', '.join(sd.outputs)}"
              f"\n    resources: {wants}")
    return 0


def _print_params(pipe: Pipeline, name: str) -> None:
    sd = pipe.stages[name]
    print(f"{name}" + (f": {sd.help}" if sd.help else ""))
    if sd.spec is None:
        print("    (not implemented yet)\n")
        return
    backends = ", ".join(f"{b} (default)" if b == sd.backend else b for b in sd.spec.backends)
    print(f"    backend: {backends}    --set {name}.backend=NAME")
    for pname, p in sd.spec.params.items():
        default = sd.params.get(pname, p.default)
        shown = repr(default) if not isinstance(default, str) or default else "''"
        origin = f" (pipeline.yaml; the stage's own: {p.default!r})" if pname in sd.params and sd.params[pname] != p.default else ""
        choices = f"  choices: {', '.join(map(str, p.choices))}" if p.choices else ""
        only = ""
        if p.backend is not None:
            only = f"  [backend {p.backend if isinstance(p.backend, str) else ' | '.join(p.backend)} only]"
        print(f"    {name}.{pname} = {shown}{origin}  ({p.type.__name__}){choices}{only}")
        print(f"        {p.help}")
    print()


def cmd_params(args, app: App) -> int:
    pipe = _pipeline(args, app)
    unknown = [s for s in args.stages if s not in pipe.stages]
    if unknown:
        raise HumanVDMError(f"unknown stage(s) {unknown}; stages: {list(pipe.stages)}")
    print("Set any of these with --set STAGE.PARAM=VALUE (or under the stage's params: in pipeline.yaml).\n")
    for name in pipe.order():
        if not args.stages or name in args.stages:
            _print_params(pipe, name)
    return 0


def cmd_verify(args, app: App) -> int:
    store = Store(args.store)
    report = store.verify(quarantine=not args.no_quarantine)
    print(f"checked {report.checked} artifacts: {len(report.corrupt)} corrupt")
    for artifact_id, moved in zip(report.corrupt, report.quarantined or [None] * len(report.corrupt), strict=False):
        print(f"  corrupt {artifact_id}" + (f" -> moved to {moved} (it will be recomputed)" if moved else ""))
    return 1 if report.corrupt else 0


def cmd_gc(args, app: App) -> int:
    store = Store(args.store)
    with store.exclusive_use():
        removed, freed = store.gc(referenced_ids(store))
    print(f"removed {len(removed)} unreferenced artifacts, freed {freed / 1e6:.1f} MB")
    return 0


def cmd_show(args, app: App) -> int:
    store = Store(args.store)
    lock = read_lockfile(store, args.what)
    if lock:
        print(yaml.safe_dump({"input": lock.get("input")}, sort_keys=False).rstrip())
        for stage, e in (lock.get("stages") or {}).items():
            outs = ", ".join(f"{k}={v[:12]}" for k, v in (e.get("outputs") or {}).items())
            print(f"{stage:24} {e.get('status', ''):7} {e.get('wall_s') or 0:8.2f} s "
                  f"{e.get('peak_rss_mb') or 0:8.0f} MB  {e.get('backend')}  {outs}")
        return 0
    matches = [i for i in store.all_ids() if i.startswith(args.what)]
    if len(matches) != 1:
        raise HumanVDMError(f"{args.what!r}: no run of that name and {len(matches)} artifacts with that id prefix")
    artifact_id = matches[0]
    files = store.manifest(artifact_id) or {}
    producers = [r for _, r in store.all_records() if r and artifact_id in (r.get("outputs") or {}).values()]
    print(json.dumps({"id": artifact_id, "path": str(store.object_path(artifact_id)), "files": len(files),
                      "produced_by": [{k: r.get(k) for k in ("stage", "key", "backend", "params", "wall_s")}
                                      for r in producers]}, indent=1))
    return 0


COMMANDS: dict[str, Callable[[argparse.Namespace, App], int]] = {
    "run": cmd_run, "status": cmd_status, "dag": cmd_dag, "params": cmd_params, "verify": cmd_verify, "gc": cmd_gc,
    "show": cmd_show}

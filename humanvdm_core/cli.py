"""``humanvdm``: the engine's command line (:mod:`humanvdm_core.workflow.cli`) for photos and scans.

    humanvdm run INPUT... [--jobs N] [--force STAGE] [--until STAGE] [--set stage.param=value] [--dry-run]
                 [--executor local|ray [--address auto|HOST:PORT]]
    humanvdm status INPUT...        per stage: would it run, and why
    humanvdm dag [--params]         the stages, their inputs and outputs
    humanvdm params [STAGE...]      every stage's params: default, type, choices, help (names for --set)
    humanvdm verify                 re-hash the whole store, quarantine corrupt entries
    humanvdm gc                     remove artifacts that no run references
    humanvdm show RUN|ARTIFACT_ID   a run's lockfile summary, or an artifact's files and origin
    humanvdm view RUN|PLY           an interactive 3D viewer of the result in the browser (viser)
    humanvdm report RUN             (re)write runs/RUN/report.html from the run's folder and lockfile

What this module adds to the engine's verbs: inputs are photos and scans (:mod:`humanvdm_core.inputs`),
the verbs ``view`` and ``report``, and under each finished run its report and key outputs.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from humanvdm_core.inputs import discover, import_subject
from humanvdm_core.workflow import cli as engine
from humanvdm_core.workflow.errors import HumanVDMError
from humanvdm_core.workflow.scheduler import read_lockfile
from humanvdm_core.workflow.store import Store

REPO_ROOT = Path(__file__).resolve().parent.parent
KEY_OUTPUTS = ("splat-optimize/gaussians/point_cloud.ply", "splat-optimize/gaussians/point_cloud.splat",
               "splat-optimize/gaussians/turntable.gif",
               "evaluate/report/report.html", "evaluate/report/orbit.gif", "fit-smpl/body/overlay.png")
REPORTED_STAGES = ("diffuse", "fit-smpl", "splat-optimize", "evaluate")  # runs of the reconstruction pipeline


def show_outputs(args: argparse.Namespace, store: Store, subject: str, base: Path) -> None:
    """Under a finished run's "outputs of" line: its report (written now), key outputs, the viewer."""
    report = _write_report(store, subject, args)
    if report is not None:
        print(f"  {report.relative_to(base)}   <- open this first")
    for rel in KEY_OUTPUTS:
        if (base / rel).exists():
            print(f"  {rel}")
    if (base / KEY_OUTPUTS[0]).exists():
        flag = engine.store_flag(args)
        print(f"  look around it in your browser: humanvdm view {subject}" + (f" --store {flag}" if flag else ""))


def _write_report(store: Store, subject: str, args):
    from humanvdm_core.report import write_run_report

    if not any(s in (read_lockfile(store, subject).get("stages") or {}) for s in REPORTED_STAGES):
        return None
    try:
        return write_run_report(store.root, subject, engine.store_flag(args) or None)
    except Exception as e:  # the report is a courtesy: never fail a finished run for it
        print(f"warning: could not write the report of {subject}: {type(e).__name__}: {e}", file=sys.stderr)
        return None


def _report_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("what", metavar="RUN", help="run (subject) name")


def cmd_report(args) -> int:
    store = Store(args.store)
    if not read_lockfile(store, args.what):
        raise HumanVDMError(f"{args.what!r}: no run of that name in {store.root / 'runs'}")
    path = _write_report(store, args.what, args)
    if path is None:
        return 1
    print(path)
    return 0


def _view_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("what", metavar="RUN|PLY", help="a run name, a run folder, a gaussians folder, or a .ply/.splat file")
    p.add_argument("--port", type=int, default=8080, help="local port (default 8080; the next free one if taken)")
    p.add_argument("--host", default="127.0.0.1", help="interface to serve on (default 127.0.0.1: this machine only)")
    p.add_argument("--show", default="gaussians", metavar="LAYERS",
                   help="layers visible at the start, comma-separated, of gaussians, body, proxy, cameras, grid "
                        "(default: gaussians; each is a toggle in the page)")


def cmd_view(args) -> int:
    from humanvdm_core.viewer import run_viewer

    show = tuple(s.strip() for s in args.show.split(",") if s.strip())
    return run_viewer(args.what, args.store, host=args.host, port=args.port, show=show)


APP = engine.App(
    prog="humanvdm",
    description="Single-image 3D Gaussian humans, staged and cached.",
    default_pipeline=REPO_ROOT / "pipeline.yaml",
    discover=discover,
    import_subject=import_subject,
    inputs_help="photos, scans, or folders of them",
    set_example="splat-optimize.preset=tiny",
    verbs={
        "view": engine.Verb("look around a result in the browser (3D viewer: Gaussians, body, cameras)", _view_args,
                            cmd_view),
        "report": engine.Verb("(re)write a run's report.html from its folder and lockfile", _report_args, cmd_report),
    },
    show_outputs=show_outputs,
)


def build_parser() -> argparse.ArgumentParser:
    return engine.build_parser(APP)


def main(argv: list[str] | None = None) -> int:
    return engine.main(argv, APP)


if __name__ == "__main__":
    raise SystemExit(main())

"""A throw-away project of tiny stages for scheduler tests.

Each test gets its own folder with a ``pipeline.yaml`` and a uniquely named stage package (so
module caches of earlier tests never interfere). The stages:

- ``shout``   (input ``$text``):  writes the text ``times`` times (upper-cased when ``upper``);
              fails with a user error when the text contains FAIL, with one naming the input
              file's full path when it contains BADFILE, and meets a full disk half-way through
              writing (ENOSPC) when it contains NOSPACE; sleeps ``sleep`` seconds
              (in ``steps`` steps, reporting progress after each, when ``steps`` > 0).
- ``measure`` (``shout.out``):    writes ``len(text) // bucket`` (coarse: early cutoff material).
- ``report``  (``measure.out``):  writes "size=<n>".

Every stage run appends a line to ``ledger.txt`` in the project folder (stage, subject text,
start and end time), so a test can see exactly which stages ran, and when.
"""

from __future__ import annotations

import textwrap
import uuid
from pathlib import Path

from humanvdm_core.workflow.pipeline import load_pipeline
from humanvdm_core.workflow.scheduler import Scheduler, Subject
from humanvdm_core.workflow.store import Store

STAGE_HEAD = '''
import time
from pathlib import Path

from humanvdm_core.workflow.errors import InputError
from humanvdm_core.workflow.stage import Param, StageSpec

LEDGER = Path(__file__).resolve().parents[1] / "ledger.txt"


def ledger(stage, text, t0):
    with open(LEDGER, "a") as f:
        f.write(f"{stage}\\t{text.strip()[:20]}\\t{t0}\\t{time.time()}\\n")


def read(ctx, name):
    return next(iter(sorted(ctx.inputs[name].iterdir()))).read_text()
'''

STAGES = {
    "shout": '''
SPEC = StageSpec("shout", "repeat the text", inputs={"src": "text file"}, outputs={"out": "text"},
                 params={"times": Param(1, "repetitions"), "upper": Param(False, "upper-case"),
                         "sleep": Param(0.0, "seconds to sleep"),
                         "steps": Param(0, "sleep in this many steps, reporting progress after each")})


def run(ctx):
    t0 = time.time()
    text = read(ctx, "src")
    if "FAIL" in text:
        raise InputError("this text cannot be shouted")
    if "BADFILE" in text:
        src = next(iter(sorted(ctx.inputs["src"].iterdir())))
        raise InputError(f'cannot read {src}: the file is truncated or corrupt (Failed to read "{src}")')
    if "NOSPACE" in text:
        out_dir = ctx.outputs["out"]
        (out_dir / "part.bin").write_bytes(b"x" * 300_000)
        raise OSError(28, "No space left on device", str(out_dir / "more.bin"))
    if "CRASH" in text:
        raise RuntimeError("a bug")
    steps = ctx.params["steps"]
    if steps > 0:
        for i in range(steps):
            time.sleep(ctx.params["sleep"] / steps)
            ctx.progress(i + 1, steps, "steps", "shouting")
    else:
        time.sleep(ctx.params["sleep"])
    out = text * ctx.params["times"]
    (ctx.outputs["out"] / "text.txt").write_text(out.upper() if ctx.params["upper"] else out)
    ledger("shout", text, t0)
''',
    "measure": '''
SPEC = StageSpec("measure", "coarse length", inputs={"src": "text"}, outputs={"out": "number"},
                 params={"bucket": Param(10, "bucket size")})


def run(ctx):
    t0 = time.time()
    text = read(ctx, "src")
    (ctx.outputs["out"] / "n.txt").write_text(str(len(text) // ctx.params["bucket"]))
    ledger("measure", text, t0)
''',
    "report": '''
SPEC = StageSpec("report", "final report", inputs={"src": "number"}, outputs={"out": "report"})


def run(ctx):
    t0 = time.time()
    n = read(ctx, "src")
    (ctx.outputs["out"] / "report.txt").write_text(f"size={n}")
    ledger("report", n, t0)
''',
}

PIPELINE = """
schema: 1
inputs:
  text: {{kind: text}}
stages:
  shout:
    module: {pkg}.shout
    inputs: {{src: $text}}
    outputs: [out]
  measure:
    module: {pkg}.measure
    inputs: {{src: shout.out}}
    outputs: [out]
    params: {{bucket: 10}}
  report:
    module: {pkg}.report
    inputs: {{src: measure.out}}
    outputs: [out]
"""

MAIN = '\n\nif __name__ == "__main__":\n    raise SystemExit(SPEC.main(run))\n'


class ToyProject:
    def __init__(self, root: Path, pipeline_text: str | None = None, stages: dict[str, str] | None = None):
        self.root = root
        self.pkg = f"toy_{uuid.uuid4().hex[:10]}"
        pkg_dir = root / self.pkg
        pkg_dir.mkdir(parents=True)
        (pkg_dir / "__init__.py").write_text("")
        for name, body in (stages or STAGES).items():
            self.write_stage(name, body)
        self.pipeline_path = root / "pipeline.yaml"
        self.pipeline_path.write_text(textwrap.dedent(pipeline_text or PIPELINE).format(pkg=self.pkg))
        self.store = Store(root / "artifacts")
        (root / "inputs").mkdir()

    def write_stage(self, name: str, body: str) -> None:
        (self.root / self.pkg / f"{name}.py").write_text(STAGE_HEAD + body + MAIN)

    def subject(self, name: str, text: str) -> Subject:
        src = self.root / "inputs" / f"{name}.txt"
        src.write_text(text)
        s = Subject(name, "text", src)
        s.input_id = self.store.import_path(src)
        return s

    def scheduler(self, **kw) -> Scheduler:
        return Scheduler(load_pipeline(self.pipeline_path), self.store, progress=False, **kw)

    def ledger(self) -> list[tuple[str, str, float, float]]:
        path = self.root / "ledger.txt"
        if not path.exists():
            return []
        rows = [ln.split("\t") for ln in path.read_text().splitlines()]
        return [(r[0], r[1], float(r[2]), float(r[3])) for r in rows]

    def ran(self) -> list[str]:
        """Stages that ran since the last call, in order."""
        rows = self.ledger()
        seen = getattr(self, "_seen", 0)
        self._seen = len(rows)
        return [r[0] for r in rows[seen:]]


def in_tiny_filesystem(mount: Path, size: str, script: str, timeout: float = 120):
    """Run the shell ``script`` with a fresh tmpfs of ``size`` (e.g. ``2m``) mounted at ``mount``, in a
    private mount namespace (``unshare``: root, or unprivileged user namespaces); the file system is
    gone when it ends, so ``script`` checks what it needs. Returns the CompletedProcess, or None when
    this machine cannot make such a namespace (the caller skips)."""
    import shutil
    import subprocess

    unshare = shutil.which("unshare")
    if unshare is None:
        return None
    mount.mkdir(parents=True, exist_ok=True)
    probe = subprocess.run([unshare, "--mount", "--map-root-user", "sh", "-c",
                            f"mount -t tmpfs -o size=64k none '{mount}'"], capture_output=True, timeout=30)
    if probe.returncode != 0:
        return None
    return subprocess.run([unshare, "--mount", "--map-root-user", "sh", "-c",
                           f"mount -t tmpfs -o size={size} none '{mount}' && {script}"],
                          capture_output=True, text=True, timeout=timeout)

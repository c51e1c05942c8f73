"""Shared benchmark plumbing: where results go, and what machine made them."""

from __future__ import annotations

import json
import os
import platform
import time
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"


def machine() -> dict:
    info = {"cpu_count": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version()}
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                info["cpu"] = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return info


def save_result(name: str, result: dict, command: str) -> Path:
    """Write ``benchmarks/results/<name>.json`` with the command and the machine."""
    RESULTS.mkdir(parents=True, exist_ok=True)
    path = RESULTS / f"{name}.json"
    doc = {"benchmark": name, "command": command, "date": time.strftime("%Y-%m-%d"), "machine": machine(),
           "result": result}
    path.write_text(json.dumps(doc, indent=1) + "\n")
    return path

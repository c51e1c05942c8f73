"""Headless Chromium for tests that look at what a person sees (Debian's ``chromium``; tests skip without it).

WebGL runs on SwiftShader (software), so the viewer renders without a GPU or a display.
"""

from __future__ import annotations

import shutil
import subprocess
import tempfile
from pathlib import Path

import pytest

FLAGS = ["--headless=new", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
         "--hide-scrollbars", "--disable-extensions", "--mute-audio", "--no-first-run"]


def chromium() -> str:
    """The Chromium executable, or skip the test."""
    for name in ("chromium", "chromium-browser", "google-chrome"):
        path = shutil.which(name)
        if path:
            return path
    pytest.skip("headless Chromium is not installed (Debian: apt-get install chromium)")


def _run(args: list[str], timeout: float) -> subprocess.CompletedProcess:
    with tempfile.TemporaryDirectory(prefix="chromium-") as profile:
        return subprocess.run([chromium(), *FLAGS, f"--user-data-dir={profile}", *args], capture_output=True,
                              timeout=timeout)


def dump_dom(url: str, budget_ms: int = 5000, timeout: float = 60) -> str:
    """The page's DOM after its scripts ran (``budget_ms`` of virtual time)."""
    res = _run([f"--virtual-time-budget={budget_ms}", "--dump-dom", url], timeout)
    return res.stdout.decode(errors="replace")


def require_webgl() -> None:
    """Skip unless this Chromium gives pages WebGL 2 (needed by the 3D viewer)."""
    with tempfile.TemporaryDirectory() as d:
        page = Path(d) / "probe.html"
        page.write_text("<!doctype html><title>?</title><script>document.title = "
                        "document.createElement('canvas').getContext('webgl2') ? 'webgl2' : 'none'</script>")
        if "<title>webgl2</title>" not in dump_dom(page.as_uri(), 500):
            pytest.skip("this Chromium renders no WebGL 2 (SwiftShader missing?)")


def screenshot(url: str, out: Path, size: tuple[int, int] = (1200, 800), budget_ms: int = 15000,
               timeout: float = 120):
    """A PNG of the page after ``budget_ms`` of virtual time; returns it as an (H, W, 3) uint8 array."""
    import numpy as np
    from PIL import Image

    res = _run([f"--window-size={size[0]},{size[1]}", f"--virtual-time-budget={budget_ms}",
                f"--screenshot={out}", url], timeout)
    if not Path(out).is_file():
        raise AssertionError(f"chromium wrote no screenshot: {res.stderr.decode(errors='replace')[-2000:]}")
    return np.asarray(Image.open(out).convert("RGB"))

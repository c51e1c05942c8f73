"""The run's report: ``runs/<subject>/report.html``, what a person opens after ``humanvdm run``.

It is written by ``humanvdm run`` after each input's stages (and again by ``humanvdm report RUN``) from
the run's folder and its lockfile, the one record of what ran, with which params and backends, how
long, how much memory and with which library versions. It is not an artifact: the ``evaluate``
stage's ``report/`` (metrics, grid, media) is, and this page links into it.

Top to bottom: the input (the photo; a scan's front view), the turntable of the result and the orbit
video it was fitted to (naming the backend that made that video), how to look around it (``humanvdm
view``; the PLY / ``.splat`` and their axes), the metrics, each labelled with what it measures (a fit
to the generated video is *not accuracy*; only a scan run's held-out views and geometry are), the body
fit, the view grid, then the run's details (preset, per stage: status, backend, wall time, peak
memory, params, warnings; versions). Images are referenced by relative paths into the run folder.
"""

from __future__ import annotations

import html
import json
import os
import time
from pathlib import Path
from typing import Any

from humanvdm_core.workflow.atomic import atomic_write_text
from humanvdm_core.workflow.scheduler import LOCK_NAME, read_lockfile
from humanvdm_core.workflow.store import Store

REPORT_NAME = "report.html"
ASSETS = "report_files"
INPUT_PX = 512

ORBIT_SOURCES = {
    "body-prior": ("diffuse, backend <code>body-prior</code>: the embedded stand-in, not a learned video model. "
                   "It fits a body to the photo and renders a textured proxy around it; the unseen side is "
                   "<b>made, not known</b>."),
    "sv3d_p": "diffuse, backend <code>sv3d_p</code>: SV3D_p, the paper's video diffusion model, from your checkpoint.",
    "sv3d_u": "diffuse, backend <code>sv3d_u</code>: SV3D_u (a video diffusion model) from your checkpoint.",
}


def _esc(x: Any) -> str:
    return html.escape(str(x), quote=True)


def _num(x: Any, digits: int = 2) -> str:
    if isinstance(x, bool) or x is None:
        return "n/a" if x is None else str(x)
    if isinstance(x, (int, float)):
        return f"{x:.{digits}f}" if isinstance(x, float) else str(x)
    return "n/a" if str(x).startswith("unavailable") else _esc(x)


def _img(src: str, alt: str, style: str = "max-height:360px") -> str:
    # data-loaded / data-broken mark each picture for tests and for a person reading the source
    return (f"<img src='{_esc(src)}' alt='{_esc(alt)}' style='{style}' "
            "onload=\"this.dataset.loaded='1'\" onerror=\"this.dataset.broken='1'\">")


def _rel(path: Path, base: Path) -> str:
    return Path(os.path.relpath(path, base)).as_posix()


def _input_picture(run: Path, lock: dict, store_root: Path) -> tuple[str | None, str]:
    """Write a small PNG of the run's input into ``report_files/``; (its relative path, a caption)."""
    import numpy as np
    from PIL import Image

    inp = lock.get("input") or {}
    out = run / ASSETS / "input.png"
    if "photo" in inp:
        candidates = []
        if inp["photo"].get("id"):
            folder = Store(store_root).object_path(inp["photo"]["id"])
            candidates = sorted(folder.glob("input.*")) if folder.is_dir() else []
        candidates.append(Path(inp["photo"].get("path", "")))
        for c in candidates:
            try:
                with Image.open(c) as im:
                    im.thumbnail((INPUT_PX, INPUT_PX))
                    out.parent.mkdir(parents=True, exist_ok=True)
                    im.save(out)
                return f"{ASSETS}/input.png", f"the input photo ({_esc(inp['photo'].get('path', ''))})"
            except OSError:
                continue
        return None, f"the input photo ({_esc(inp['photo'].get('path', ''))}) could not be read"
    orbit = run / "render-training-orbits" / "orbit"
    if orbit.is_dir():
        from humanvdm_core.frames import open_frame_set, read_frame

        paths, cams = open_frame_set(orbit)
        front = int(np.argmin(np.abs((np.asarray(cams.azimuth_deg) + 180) % 360 - 180)))
        rgba = read_frame(paths[front])
        bg = np.asarray(cams.extra.get("background", np.ones(3)), np.float32).reshape(3)
        rgb = rgba[..., :3] * rgba[..., 3:4] + bg * (1 - rgba[..., 3:4]) if rgba.shape[-1] == 4 else rgba[..., :3]
        im = Image.fromarray(np.clip(np.rint(rgb * 255), 0, 255).astype(np.uint8))
        im.thumbnail((INPUT_PX, INPUT_PX))
        out.parent.mkdir(parents=True, exist_ok=True)
        im.save(out)
        path = (inp.get("scan") or {}).get("path", "")
        return f"{ASSETS}/input.png", f"the input scan ({_esc(path)}), front view as rendered for the orbit"
    return None, "no input picture"


def _first(run: Path, *rels: str) -> Path | None:
    return next((run / r for r in rels if (run / r).is_file()), None)


def write_run_report(store_root: str | Path, subject: str, store_flag: str | None = None) -> Path:
    """Write ``runs/<subject>/report.html`` (see the module docstring); returns its path.
    ``store_flag``: the ``--store`` option to show in commands (None: the default store)."""
    store_root = Path(store_root)
    run = store_root / "runs" / subject
    lock = read_lockfile(Store(store_root), subject)
    stages: dict[str, dict] = lock.get("stages") or {}
    scan_run = "scan" in (lock.get("input") or {})
    metrics_path = run / "evaluate" / "report" / "metrics.json"
    metrics = json.loads(metrics_path.read_text()) if metrics_path.is_file() else None

    P: list[str] = []
    P.append("<!doctype html><html lang='en'><head><meta charset='utf-8'>"
             f"<title>Human-VDM: {_esc(subject)}</title><style>"
             "body{font-family:system-ui,sans-serif;margin:2em auto;max-width:1200px;padding:0 1em;color:#222;"
             "line-height:1.45}h1{margin-bottom:.2em}h2{margin-top:1.6em;border-bottom:1px solid #ddd}"
             "figure{margin:0}figcaption{font-size:.95em;color:#444}"
             ".row{display:grid;grid-template-columns:repeat(auto-fill,minmax(300px,1fr));gap:1.5em;"
             "align-items:start}.row img{width:100%;height:340px;object-fit:contain;background:#f6f6f6}"
             "table{border-collapse:collapse;margin:.8em 0}td,th{border:1px solid #ccc;padding:4px 9px;"
             "text-align:right}th{background:#f1f1f1}td:first-child,th:first-child{text-align:left}"
             ".warn{background:#fff3cd;border-left:5px solid #e0a800;padding:.6em .9em}"
             ".ok{background:#e8f5e9;border-left:5px solid #43a047;padding:.6em .9em}"
             "code,pre{background:#f4f4f4;padding:1px 4px;border-radius:3px}pre{padding:.6em}"
             "details{margin:.3em 0}</style></head><body>")
    created = time.strftime("%Y-%m-%d %H:%M", time.localtime((run / LOCK_NAME).stat().st_mtime)) \
        if (run / LOCK_NAME).exists() else "?"
    P.append(f"<h1>{_esc(subject)}</h1><p>Human-VDM run report · last run {created} · "
             f"<a href='{LOCK_NAME}'>lockfile</a> · <a href='logs/'>logs</a></p>")

    # -- input and result
    src, caption = _input_picture(run, lock, store_root)
    figures = []
    if src:
        figures.append(f"<figure>{_img(src, 'input')}<figcaption>{caption}</figcaption></figure>")
    turntable = _first(run, "evaluate/report/turntable.gif", "splat-optimize/gaussians/turntable.gif")
    if turntable:
        figures.append(f"<figure>{_img(_rel(turntable, run), 'turntable')}<figcaption>the 3D Gaussian human, "
                       "turning (rendered from the Gaussians)</figcaption></figure>")
    orbit_gif = _first(run, "evaluate/report/orbit.gif")
    if scan_run:
        orbit_from = "rendered from your scan (<code>render-training-orbits</code>): ground truth"
    else:
        backend = (stages.get("diffuse") or {}).get("backend", "?")
        orbit_from = ORBIT_SOURCES.get(backend, f"diffuse, backend <code>{_esc(backend)}</code>")
    if orbit_gif:
        figures.append(f"<figure>{_img(_rel(orbit_gif, run), 'orbit video')}<figcaption>the orbit video the "
                       f"Gaussians were fitted to, made by {orbit_from}</figcaption></figure>")
    P.append("<h2>Input and result</h2><div class='row'>" + "".join(figures) + "</div>")
    if not orbit_gif:
        P.append(f"<p>The orbit video was made by {orbit_from}</p>")

    # -- look around
    ply = run / "splat-optimize" / "gaussians" / "point_cloud.ply"
    splat = ply.with_suffix(".splat")
    store_opt = f" --store {store_flag}" if store_flag else ""
    axes = (stages.get("splat-optimize") or {}).get("params", {}).get("ply_axes", "y-down")
    P.append("<h2>Look around</h2>")
    if ply.is_file():
        from humanvdm_core.splat.human import PLY_AXES_COMMENT

        P.append(f"<p>In your browser, with the fitted body, the orbit cameras and their frames as toggles:</p>"
                 f"<pre>humanvdm view {_esc(subject)}{_esc(store_opt)}</pre>"
                 f"<p>then open the address it prints (http://localhost:8080). Or open "
                 f"<a href='{_rel(ply, run)}'>point_cloud.ply</a> (standard 3DGS PLY, "
                 f"{ply.stat().st_size / 1e6:.1f} MB)"
                 + (f" or <a href='{_rel(splat, run)}'>point_cloud.splat</a> (compact web format, "
                    f"{splat.stat().st_size / 1e6:.1f} MB)" if splat.is_file() else "")
                 + f" in a Gaussian-splat viewer. Axes {_esc(PLY_AXES_COMMENT.get(axes, axes).removeprefix('axes '))}"
                 "; metres. " + ("Upright in SuperSplat; gaussian-splats-3d needs <code>cameraUp: [0, -1, 0]</code> "
                                 "(or a run with <code>--set splat-optimize.ply_axes=y-up</code>)."
                                 if axes == "y-down" else "Upright in gaussian-splats-3d's default view; SuperSplat "
                                 "shows y-up files upside down.") + "</p>")
    else:
        P.append("<p>No Gaussians yet (splat-optimize has not run).</p>")

    # -- metrics
    P.append("<h2>How well it fits — and what that means</h2>")
    if metrics is None:
        P.append("<p>No metrics yet (evaluate has not run).</p>")
    else:
        basis = metrics.get("basis") or {}
        if scan_run:
            P.append("<p class='ok'>A scan run: the <b>held-out</b> views and the geometry are measured against "
                     "the scan (accuracy). The protocol views are frames the Gaussians were fitted to.</p>")
        else:
            P.append("<p class='warn'><b>Fit to the generated video — not accuracy.</b> These numbers compare renders "
                     "of the Gaussians with frames of the orbit video they were fitted to (made by "
                     f"{orbit_from.split(':')[0]}). They say how well the Gaussians reproduce that video, not how "
                     "close the result is to the real person: a photo has no ground truth for the unseen side. "
                     "Accuracy is measured on scans (<code>humanvdm run scan_folder/</code>, "
                     "<code>benchmarks/</code>).</p>")
        cols = ("psnr", "ssim", "masked_psnr", "iou", "lpips", "clip")
        for group, views in (metrics.get("views") or {}).items():
            what = basis.get(group, "")
            P.append(f"<h3>{_esc(group)} views — {_esc(what)}</h3><table><tr><th>view</th>"
                     + "".join(f"<th>{c}</th>" for c in cols) + "</tr>")
            mean = (metrics.get("mean") or {}).get(group) or {}
            for v in [*views, {"name": "mean", "metrics": mean}]:
                m = v.get("metrics") or {}
                P.append(f"<tr><td>{_esc(v['name'])}</td>" + "".join(
                    f"<td>{_num(m.get(c), 4 if c in ('ssim', 'iou', 'lpips', 'clip') else 2)}</td>" for c in cols)
                    + "</tr>")
            P.append("</table>")
        geo = metrics.get("geometry")
        if isinstance(geo, dict):
            P.append(f"<h3>Geometry — {_esc(basis.get('geometry', ''))}</h3><table>" + "".join(
                f"<tr><td>{_esc(k)}</td><td>{_num(v, 4)}</td></tr>" for k, v in geo.items()) + "</table>")
        missing = {k: v for k, v in (metrics.get("perceptual") or {}).items() if v != "ok"}
        for k, v in missing.items():
            P.append(f"<p>{_esc(k.upper())}: {_esc(v)}</p>")
        P.append("<details><summary>definitions</summary><ul>" + "".join(
            f"<li><b>{_esc(k)}</b>: {_esc(v)}</li>" for k, v in (metrics.get("definitions") or {}).items())
            + "</ul></details>")

    overlay = _first(run, "evaluate/report/fit_overlay.png", "fit-smpl/body/overlay.png")
    if overlay:
        P.append("<h2>Body fit</h2>" + _img(_rel(overlay, run), "body fit", "max-width:100%")
                 + "<p>The fitted body's outline (green) over orbit frames, detected keypoints (red), the body's "
                 "keypoints (blue).</p>")
    grid = _first(run, "evaluate/report/grid.png")
    if grid and metrics is not None:
        reference = "ground truth (rendered from the scan)" if scan_run else \
            "the generated frame it was fitted to (not ground truth)"
        names = [v["name"] for vs in (metrics.get("views") or {}).values() for v in vs]
        P.append(f"<h2>Views</h2><p>Columns: <b>{reference}</b> | <b>ours</b> | <b>|error|</b> (0 to 0.5). "
                 f"Rows, top to bottom: {_esc(', '.join(names))}.</p>" + _img(_rel(grid, run), "view grid", "max-width:100%"))

    # -- run details
    P.append("<h2>Run details</h2>")
    log_path = run / "splat-optimize" / "gaussians" / "train_log.json"
    if log_path.is_file():
        tl = json.loads(log_path.read_text())
        s = tl.get("settings") or {}
        P.append(f"<p>splat-optimize preset <b>{_esc(s.get('preset', '?'))}</b>: {tl.get('num_gaussians', '?'):,} "
                 f"Gaussians ({_esc(tl.get('template') or 'UV ' + str(s.get('uv_resolution', '?')) + '²')}), "
                 f"{s.get('iterations', '?')} iterations at "
                 f"{s.get('train_resolution', '?')}² on {_esc(tl.get('device', '?'))}; training PSNR "
                 f"{_num(tl.get('train_psnr'))} dB (against its own training frames).</p>")
    total = sum(float(e.get("wall_s") or 0) for e in stages.values())
    P.append("<table><tr><th>stage</th><th>this run</th><th>backend</th><th>wall time</th><th>peak memory</th>"
             "<th>params</th></tr>")
    for name, e in stages.items():
        status = e.get("status", "?")
        wall = e.get("wall_s")
        wall_s = f"{wall:.1f} s" if isinstance(wall, (int, float)) else "?"
        if status == "cached":
            wall_s += " (when computed)"
        mem = e.get("peak_rss_mb")
        params = e.get("params") or {}
        table = "".join(f"<tr><td>{_esc(k)}</td><td style='text-align:left'>{_esc(v)}</td></tr>"
                        for k, v in params.items())
        P.append(f"<tr><td>{_esc(name)}</td><td>{_esc(status)}</td><td>{_esc(e.get('backend'))}</td>"
                 f"<td>{wall_s}</td><td>{f'{mem:.0f} MB' if isinstance(mem, (int, float)) else '?'}</td>"
                 f"<td style='text-align:left'><details><summary>{len(params)} params</summary><table>{table}"
                 "</table></details></td></tr>")
    P.append(f"<tr><th>all</th><th></th><th></th><th>{total:.1f} s</th><th></th><th></th></tr></table>")
    warnings = [(n, w) for n, e in stages.items() for w in (e.get("warnings") or [])]
    if warnings:
        P.append("<h3>Warnings</h3><ul>" + "".join(f"<li>{_esc(n)}: {_esc(w)}</li>" for n, w in warnings) + "</ul>")
    versions: dict[str, str] = {}
    for e in stages.values():
        versions.update({k: str(v) for k, v in (e.get("versions") or {}).items()})
    if versions:
        P.append("<p>Versions: " + ", ".join(f"{_esc(k)} {_esc(v)}" for k, v in versions.items()) + ".</p>")
    P.append(f"<p>Everything above comes from <a href='{LOCK_NAME}'>{LOCK_NAME}</a> (params, backends, times, "
             "memory, versions) and the run's folders.</p></body></html>\n")
    out = run / REPORT_NAME
    atomic_write_text(out, "\n".join(P))
    return out

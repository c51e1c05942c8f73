"""Evaluation of a Gaussian human: render at the protocol (and held-out scan) views, score, report.

The contract of the ``evaluate`` stage (views, metrics, output files) is in ``stages/evaluate.py``'s
docstring; :func:`evaluate_gaussians` is that stage's work, callable without the scheduler.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

from humanvdm_core.workflow.errors import ConfigError, InputError

LOG = logging.getLogger("humanvdm.evaluate")

PROTOCOL_VIEWS = (("front", 0.0), ("back", 180.0), ("left", 90.0), ("right", 270.0))
IMAGE_METRICS = ("psnr", "ssim", "masked_psnr", "masked_ssim", "iou", "lpips", "clip")
DEFINITIONS = {
    "psnr": "10 log10(1 / MSE) over all pixels and RGB channels, images in [0, 1] (dB, higher is better)",
    "ssim": "SSIM, 11x11 Gaussian window (sigma 1.5), K1 0.01, K2 0.03, valid windows, mean over RGB",
    "masked_psnr": "PSNR over the union of the ground-truth and rendered silhouettes (alpha > 0.5)",
    "masked_ssim": "the SSIM map averaged over window centres inside that union",
    "iou": "silhouette intersection over union (alpha > 0.5)",
    "lpips": "LPIPS v0.1, AlexNet (lower is better)",
    "clip": "cosine similarity of CLIP ViT image embeddings (higher is better)",
    "p2s": "mean distance from Gaussian centres (opacity >= min_opacity) to the scan surface, world units",
    "s2p": "mean distance from uniform scan-surface samples to the nearest Gaussian centre",
    "chamfer": "(p2s + s2p) / 2; *_rel: divided by the subject height",
}


@dataclass
class EvaluateOptions:
    """The ``evaluate`` stage's params (see its SPEC for the meaning of each)."""

    resolution: int = 512
    heldout_elevations: list[float] = field(default_factory=lambda: [0.0, 25.0])
    heldout_azimuths: list[float] = field(default_factory=lambda: [45.0, 135.0, 225.0, 315.0])
    lpips_weights: str = ""
    alexnet_weights: str = ""
    clip_weights: str = ""
    geometry_samples: int = 100000
    min_opacity: float = 0.05
    cell_size: int = 256
    media_size: int = 256  # pixel size of orbit.gif (0: no orbit.gif)

    def check(self) -> None:
        """ConfigError naming the first param out of range."""
        if not 16 <= self.resolution <= 4096:
            raise ConfigError(f"evaluate.resolution must be in [16, 4096], got {self.resolution}")
        if self.geometry_samples < 100 or not 0.0 <= self.min_opacity < 1.0 or self.cell_size < 32:
            raise ConfigError("evaluate: geometry_samples must be >= 100, min_opacity in [0, 1), cell_size >= 32")


def float_list(name: str, text: str) -> list[float]:

    try:
        values = [float(t) for t in text.split(",") if t.strip()]
    except ValueError:
        values = []
    if not values:
        raise ConfigError(f"param {name}: {text!r} is not a comma-separated list of numbers")
    return values


def angle_close(a, b, atol: float = 1e-3):
    import numpy as np

    return np.isclose((np.asarray(a) - b + 180.0) % 360.0 - 180.0, 0.0, atol=atol)


def load_gaussians(path) -> dict:
    """The ``humanvdm.gaussians`` v1 arrays, validated (InputError otherwise)."""
    from pathlib import Path

    import numpy as np

    from humanvdm_core.io import read_npz

    path = Path(path)
    npz = path / "gaussians.npz" if path.is_dir() else path
    if not npz.is_file():
        raise InputError(f"no gaussians.npz in {path}: expected the output of splat-optimize")
    try:
        g = read_npz(npz, "humanvdm.gaussians", 1)
    except (ValueError, OSError) as e:
        raise InputError(f"cannot read {npz}: {e}") from None
    shapes = {"means": 3, "quats": 4, "scales": 3, "colors": 3}
    missing = [k for k in (*shapes, "opacities") if k not in g]
    if missing:
        raise InputError(f"{npz} lacks {missing}")
    n = len(g["means"])
    for k, d in shapes.items():
        if g[k].shape != (n, d):
            raise InputError(f"{npz}: {k} has shape {g[k].shape}, expected ({n}, {d})")
    g["opacities"] = g["opacities"].reshape(-1)
    if g["opacities"].shape != (n,) or n == 0:
        raise InputError(f"{npz}: {n} Gaussians, opacities of shape {g['opacities'].shape}")
    for k in (*shapes, "opacities"):
        if not np.isfinite(g[k]).all():
            raise InputError(f"{npz}: {k} holds non-finite values")
    return g


def render_gaussians(g: dict, cameras, background) -> tuple:
    """RGB (N, H, W, 3) over ``background`` and alpha (N, H, W) of the Gaussians at every camera."""
    import numpy as np
    import torch

    from humanvdm_core.splat.rasterize import rasterize_gaussians

    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")

    def t(x):
        return torch.as_tensor(np.asarray(x, dtype=np.float32), device=device)

    means, quats, scales, opac, cols = (t(g[k]) for k in ("means", "quats", "scales", "opacities", "colors"))
    bg = t(background).reshape(1, 3)
    rgbs, alphas = [], []
    with torch.no_grad():
        for i in range(len(cameras)):
            rgb, alpha, _ = rasterize_gaussians(means, quats, scales, opac, cols, t(cameras.w2c[i:i + 1]),
                                                t(cameras.K[i:i + 1]), cameras.width, cameras.height,
                                                backgrounds=bg, tile_size=16 if device.type == "cuda" else 8)
            rgbs.append(rgb[0].clamp(0, 1).cpu().numpy())
            alphas.append(alpha[0, ..., 0].clamp(0, 1).cpu().numpy())
    return np.stack(rgbs), np.stack(alphas)


def _resize(image, size: int):
    import cv2
    import numpy as np

    h, w = image.shape[:2]
    if (h, w) == (size, size):
        return image
    interp = cv2.INTER_AREA if size < min(h, w) else cv2.INTER_LINEAR
    return np.asarray(cv2.resize(image, (size, size), interpolation=interp), dtype=np.float32).reshape(
        size, size, *image.shape[2:])


class Perceptual:
    """LPIPS and CLIP loaded once; a missing file makes the metric 'unavailable: ...'."""

    def __init__(self, opts: EvaluateOptions, log):
        from humanvdm_core.errors import MissingWeightsError
        from humanvdm_core.perceptual import LPIPS, CLIPImageEncoder

        self.lpips = self.clip = None
        self.status: dict[str, str] = {}
        try:
            self.lpips = LPIPS.from_files(opts.alexnet_weights, opts.lpips_weights)
            self.status["lpips"] = "ok"
        except MissingWeightsError as e:
            self.status["lpips"] = f"unavailable: put {e.path.name} at {e.path}"
        try:
            self.clip = CLIPImageEncoder.from_file(opts.clip_weights)
            self.status["clip"] = "ok"
        except MissingWeightsError as e:
            self.status["clip"] = f"unavailable: put {e.path.name} at {e.path}"
        for k, v in self.status.items():
            log.info("%s: %s", k, v)

    def scores(self, ours, gt) -> dict:
        out = {}
        out["lpips"] = float(self.lpips.distance(ours, gt)) if self.lpips else self.status["lpips"]
        out["clip"] = float(self.clip.similarity(ours, gt)) if self.clip else self.status["clip"]
        return out


def image_metrics(ours, ours_alpha, gt, gt_alpha, perceptual: Perceptual) -> dict:
    """All image metrics of one view (numbers or 'unavailable: ...' strings)."""
    from humanvdm_core import metrics as M

    union = M.union_mask(ours_alpha, gt_alpha)
    out = {
        "psnr": float(M.psnr(ours, gt)),
        "ssim": float(M.ssim(ours, gt)),
        "masked_psnr": float(M.psnr(ours, gt, union)),
        "masked_ssim": float(M.ssim(ours, gt, union)),
        "iou": M.silhouette_iou(ours_alpha, gt_alpha),
    }
    out.update(perceptual.scores(ours, gt))
    return out


def mean_metrics(views: list[dict]) -> dict:
    """Mean of every numeric metric over the views that have one (strings pass through)."""
    import numpy as np

    out: dict = {}
    scored = [v["metrics"] for v in views if v.get("metrics")]
    for k in IMAGE_METRICS:
        vals = [m[k] for m in scored if k in m]
        nums = [x for x in vals if isinstance(x, float)]
        if nums:
            out[k] = float(np.mean(nums))
        elif vals:
            out[k] = vals[0]
    out["views"] = len(scored)
    return out


def json_safe(obj):
    from humanvdm_core.metrics import finite_or_none

    if isinstance(obj, dict):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, float):
        return finite_or_none(obj)
    return obj


def make_grid(rows: list[dict], cell: int):
    """RGB uint8 grid: per row GT | ours | |error| heatmap, labelled."""
    import cv2
    import numpy as np

    from humanvdm_core.io import to_uint8

    tiles = []
    for r in rows:
        ours = to_uint8(_resize(r["ours"], cell))
        if r["gt"] is not None:
            gt = to_uint8(_resize(r["gt"], cell))
            err = np.abs(r["ours"] - r["gt"]).mean(axis=-1)
            heat = cv2.applyColorMap(to_uint8(np.clip(_resize(err, cell) / 0.5, 0, 1)), cv2.COLORMAP_INFERNO)
            heat = cv2.cvtColor(heat, cv2.COLOR_BGR2RGB)
        else:
            gt = np.full((cell, cell, 3), 128, np.uint8)
            cv2.putText(gt, "no ground truth", (4, cell // 2), cv2.FONT_HERSHEY_SIMPLEX, cell / 700, (255, 255, 255), 1)
            heat = np.zeros((cell, cell, 3), np.uint8)
        gt = np.ascontiguousarray(gt)
        _label(gt, r["label"])
        tiles.append(np.concatenate([gt, ours, heat], axis=1))
    return np.concatenate(tiles, axis=0)


def _label(tile, text: str) -> None:
    """``text`` in white on a dark band across the top of ``tile``, sized to the tile (readable at 256 px)."""
    import cv2

    cell = tile.shape[1]
    font = cv2.FONT_HERSHEY_SIMPLEX
    scale, thick = max(0.3, cell / 330), max(1, round(cell / 128))
    (w, h), base = cv2.getTextSize(text, font, scale, thick)
    if w > cell - 8:  # long names shrink to fit
        scale *= (cell - 8) / w
        (w, h), base = cv2.getTextSize(text, font, scale, thick)
    band = h + base + 8
    tile[:band] = (tile[:band] * 0.35).astype(tile.dtype)
    cv2.putText(tile, text, (4, 4 + h), font, scale, (255, 255, 255), thick, cv2.LINE_AA)


BASIS = {
    "generated": "fit to the generated video — not accuracy",
    "training": "fit to the training views (rendered from the scan) — not held out",
    "heldout": "accuracy: against the scan, at views the Gaussians were not fitted to",
    "geometry": "accuracy: against the scan's surface",
}


def metric_basis(has_scan: bool) -> dict[str, str]:
    """What each group of numbers measures: a fit to the frames the Gaussians were trained on, or accuracy."""
    if not has_scan:
        return {"protocol": BASIS["generated"]}
    return {"protocol": BASIS["training"], "heldout": BASIS["heldout"], "geometry": BASIS["geometry"]}


def _fmt(x) -> str:
    import html

    if isinstance(x, float):
        return f"{x:.4f}" if abs(x) < 10 else f"{x:.2f}"
    if isinstance(x, str) and x.startswith("unavailable"):
        return "n/a"  # the reason is stated once, under the tables
    return html.escape(str(x))


ORBIT_GIF_FRAMES = 41  # at most this many frames of the orbit video go into orbit.gif


def write_media(out: Path, frame_paths: list[Path], background, gaussians: str | Path, body: str | Path | None,
                size: int) -> dict[str, str]:
    """The pictures a person looks at, next to the numbers (names of the files written in ``out``):
    ``orbit.gif`` (the orbit video the Gaussians were fitted to, at most :data:`ORBIT_GIF_FRAMES`
    frames at ``size``² over ``background``), ``turntable.gif`` (copied from the Gaussians artifact
    when it has one) and ``fit_overlay.png`` (the body fit's ``overlay.png`` when ``body`` is given)."""
    import shutil

    import numpy as np
    from PIL import Image

    from humanvdm_core.frames import read_frame
    from humanvdm_core.io import to_uint8

    media: dict[str, str] = {}
    if size > 0 and frame_paths:
        step = max(1, -(-len(frame_paths) // ORBIT_GIF_FRAMES))
        bg = np.asarray(background, np.float32).reshape(3)
        images = []
        for path in frame_paths[::step]:
            rgba = read_frame(path)
            rgb = rgba[..., :3] if rgba.shape[-1] < 4 else rgba[..., :3] * rgba[..., 3:4] + bg * (1 - rgba[..., 3:4])
            images.append(Image.fromarray(to_uint8(_resize(np.ascontiguousarray(rgb, np.float32), size))))
        images[0].save(out / "orbit.gif", save_all=True, append_images=images[1:], duration=80, loop=0)
        media["orbit"] = "orbit.gif"
    gdir = Path(gaussians)
    if gdir.is_dir() and (gdir / "turntable.gif").is_file():
        shutil.copyfile(gdir / "turntable.gif", out / "turntable.gif")
        media["turntable"] = "turntable.gif"
    if body is not None and (Path(body) / "overlay.png").is_file():
        shutil.copyfile(Path(body) / "overlay.png", out / "fit_overlay.png")
        media["fit_overlay"] = "fit_overlay.png"
    return media


def write_html(path, report: dict) -> None:
    import html

    from humanvdm_core.workflow.atomic import atomic_write_text

    parts = ["<!doctype html><html><head><meta charset='utf-8'><title>Human-VDM evaluation</title>",
             "<style>body{font-family:sans-serif;margin:2em}table{border-collapse:collapse;margin:1em 0}"
             "td,th{border:1px solid #ccc;padding:3px 8px;text-align:right}th{background:#eee}"
             "td:first-child{text-align:left}</style></head><body>",
             "<h1>Human-VDM evaluation</h1>",
             f"<p>{report['gaussians']['count']} Gaussians; images compared at {report['resolution']}&sup2; px.</p>"]
    basis = report.get("basis") or {}
    if "heldout" not in basis:
        parts.append("<p style='background:#fff3cd;padding:.6em;border-left:4px solid #e0a800'><b>Fit to the "
                     "generated video — not accuracy.</b> Every number here compares renders of the Gaussians with "
                     "frames of the orbit video they were fitted to; it says how well they reproduce that video, "
                     "not how close they are to the real person (that needs a scan run).</p>")
    parts.append("<p>In a run folder, the run's own report (the input, how to open the 3D viewer, the backends, "
                 "params, times, memory and versions) is <code>report.html</code> at the top of the run.</p>")
    captions = {"turntable": "the 3D Gaussian human, turning", "orbit": "the orbit video it was fitted to",
                "fit_overlay": "the fitted body over the orbit frames"}
    media = report.get("media") or {}
    if media:
        parts.append("<div style='display:flex;gap:1em;flex-wrap:wrap'>" + "".join(
            f"<figure><img src='{html.escape(media[k])}' alt='{k}' style='max-height:360px'>"
            f"<figcaption>{captions[k]}</figcaption></figure>" for k in captions if k in media) + "</div>")
    for group, views in report["views"].items():
        note = f" — {html.escape(basis[group])}" if group in basis else ""
        parts.append(f"<h2>{html.escape(group)} views{note}</h2><table><tr><th>view</th>"
                     + "".join(f"<th>{k}</th>" for k in IMAGE_METRICS) + "</tr>")
        for v in [*views, {"name": "mean", "metrics": report["mean"][group]}]:
            m = v.get("metrics") or {}
            parts.append(f"<tr><td>{html.escape(v['name'])}</td>"
                         + "".join(f"<td>{_fmt(m.get(k, '-'))}</td>" for k in IMAGE_METRICS) + "</tr>")
        parts.append("</table>")
    for name, status in report["perceptual"].items():
        if status != "ok":
            parts.append(f"<p>{name.upper()}: {html.escape(status)}</p>")
    parts.append("<h2>Geometry" + (f" — {html.escape(basis['geometry'])}" if "geometry" in basis else "") + "</h2>")
    geo = report["geometry"]
    if isinstance(geo, dict):
        parts.append("<table>" + "".join(f"<tr><td>{html.escape(k)}</td><td>{_fmt(v)}</td></tr>"
                                         for k, v in geo.items()) + "</table>")
    else:
        parts.append(f"<p>{html.escape(str(geo))}</p>")
    reference = "ground truth (scan)" if "heldout" in basis else "the generated frame it was fitted to (not ground truth)"
    parts.append(f"<h2>Views</h2><p>Columns: {reference} | ours | |error| (0 to 0.5). Rows: "
                 + ", ".join(html.escape(v["name"]) for vs in report["views"].values() for v in vs)
                 + ".</p><img src='grid.png' alt='view grid'>")
    parts.append("<h2>Definitions</h2><ul>" + "".join(f"<li><b>{k}</b>: {html.escape(v)}</li>"
                                                      for k, v in DEFINITIONS.items()) + "</ul></body></html>\n")
    atomic_write_text(path, "\n".join(parts))


def evaluate_gaussians(gaussians: str | Path, frames_dir: str | Path, scan: str | Path | None, out: Path,
                       opts: EvaluateOptions, log: logging.Logger = LOG, body: str | Path | None = None) -> dict:
    """Score the Gaussians (an artifact folder or ``gaussians.npz``) against the frame set ``frames_dir``
    (and ``scan`` when given); write metrics.json, grid.png, the media of :func:`write_media` and
    report.html into ``out``; return the report."""
    import json

    import numpy as np

    from humanvdm_core import metrics as M
    from humanvdm_core.cameras import Cameras, orbit_cameras
    from humanvdm_core.frames import open_frame_set, read_frame
    from humanvdm_core.io import write_png
    from humanvdm_core.workflow.atomic import atomic_write_text

    opts.check()
    res = opts.resolution
    g = load_gaussians(gaussians)
    paths, cams = open_frame_set(frames_dir)
    if "background" in cams.extra:
        background = np.asarray(cams.extra["background"], dtype=np.float64).reshape(3)
    elif "background" in g:
        background = np.asarray(g["background"], dtype=np.float64).reshape(3)
    else:
        background = np.ones(3)
    elevation = float(np.median(cams.elevation_deg))
    radius = float(np.median(cams.radius))
    fov = float(np.median(cams.fov_y_deg))
    log.info("%d Gaussians; orbit of %d frames (elevation %.1f, radius %.3f); scan: %s", len(g["means"]),
                 len(cams), elevation, radius, "yes" if scan is not None else "no")

    # Protocol views: the frame at that azimuth when the orbit has one.
    rows: list[dict] = []
    views: dict[str, list[dict]] = {"protocol": []}
    for name, az in PROTOCOL_VIEWS:
        hits = np.nonzero(angle_close(cams.azimuth_deg, az))[0]
        if len(hits):
            i = int(hits[0])
            cam = cams.subset([i]).scaled(res, res)
            rgba = read_frame(paths[i])
            if rgba.ndim != 3 or rgba.shape[2] != 4:
                raise InputError(f"frame {paths[i]} is not RGBA (shape {rgba.shape})")
            gt = _resize(rgba, res)
            views["protocol"].append({"name": name, "azimuth_deg": az, "elevation_deg": float(cam.elevation_deg[0]),
                                      "frame_index": i})
            rows.append({"group": "protocol", "label": name, "cam": cam, "gt": gt[..., :3], "gt_alpha": gt[..., 3]})
        else:
            cam = orbit_cameras(size=res, fov_y_deg=fov, elevation_deg=elevation, radius=radius, azimuths_deg=[az])
            views["protocol"].append({"name": name, "azimuth_deg": az, "elevation_deg": elevation,
                                      "frame_index": None, "note": "no frame at this azimuth: not scored"})
            rows.append({"group": "protocol", "label": f"{name} (no GT)", "cam": cam, "gt": None, "gt_alpha": None})

    geometry: dict | str = "unavailable: no scan input (geometry needs a run on a textured scan)"
    skipped: list[dict] = []
    if scan is not None:
        from humanvdm_core.render import render_views
        from humanvdm_core.scans import load_scan

        if "world_from_scan" not in cams.extra:
            raise InputError(f"frame set {frames_dir} carries no world_from_scan: with a scan input the frames "
                             "must come from render-training-orbits on that scan")
        mesh = load_scan(scan).transformed(np.asarray(cams.extra["world_from_scan"]))
        keep_az, keep_el = [], []
        for el in opts.heldout_elevations:
            for az in opts.heldout_azimuths:
                train = angle_close(cams.azimuth_deg, az, 1e-3) & np.isclose(cams.elevation_deg, el, atol=1e-3)
                if train.any():
                    skipped.append({"azimuth_deg": az, "elevation_deg": el, "reason": "a training view"})
                    continue
                keep_az.append(az)
                keep_el.append(el)
        views["heldout"] = []
        if keep_az:
            held = [orbit_cameras(size=res, fov_y_deg=fov, elevation_deg=el, radius=radius, azimuths_deg=[az])
                    for az, el in zip(keep_az, keep_el, strict=True)]
            hc = Cameras(np.concatenate([c.K for c in held]), np.concatenate([c.c2w for c in held]), res, res,
                         np.array(keep_az), np.array(keep_el), np.full(len(held), radius))
            truth = render_views(mesh, hc, tuple(float(c) for c in background))
            for i, (az, el) in enumerate(zip(keep_az, keep_el, strict=True)):
                name = f"az{az:g}_el{el:g}"
                views["heldout"].append({"name": name, "azimuth_deg": az, "elevation_deg": el})
                rows.append({"group": "heldout", "label": name, "cam": hc.subset([i]),
                             "gt": truth.rgba[i, ..., :3], "gt_alpha": truth.rgba[i, ..., 3]})
        keep = g["opacities"] >= opts.min_opacity
        if not keep.any():
            geometry = f"unavailable: no Gaussian has opacity >= {opts.min_opacity}"
        else:
            height = float(cams.extra["subject_height"]) if "subject_height" in cams.extra else None
            geometry = M.geometry_errors(g["means"][keep], mesh.vertices, mesh.faces, height=height,
                                         num_samples=opts.geometry_samples)
            log.info("geometry: p2s %.4f, s2p %.4f, chamfer %.4f (%.2f%% of height)", geometry["p2s"],
                         geometry["s2p"], geometry["chamfer"], 100 * geometry["chamfer_rel"])

    from humanvdm_core.workflow.progress import report as progress

    perceptual = Perceptual(opts, log)
    group_views = {k: iter(v) for k, v in views.items()}
    for n, r in enumerate(rows, start=1):
        progress(n, len(rows), "views", "render and score")
        rgb, alpha = render_gaussians(g, r["cam"], background)
        r["ours"], r["ours_alpha"] = rgb[0], alpha[0]
        v = next(group_views[r["group"]])
        if r["gt"] is not None:
            v["metrics"] = image_metrics(r["ours"], r["ours_alpha"], r["gt"], r["gt_alpha"], perceptual)
            log.info("%s %s: PSNR %.2f, SSIM %.4f, IoU %.4f", r["group"], v["name"], v["metrics"]["psnr"],
                         v["metrics"]["ssim"], v["metrics"]["iou"])

    report = {
        "schema": "humanvdm.evaluation", "version": 1,
        "gaussians": {"count": int(len(g["means"]))},
        "resolution": res,
        "background": [float(c) for c in background],
        "perceptual": perceptual.status,
        "views": views,
        "mean": {k: mean_metrics(v) for k, v in views.items()},
        "geometry": geometry,
        "skipped_heldout_views": skipped,
        "basis": metric_basis(scan is not None),
        "definitions": DEFINITIONS,
    }
    out = Path(out)
    report["media"] = write_media(out, paths, background, gaussians, body, opts.media_size)
    atomic_write_text(out / "metrics.json", json.dumps(json_safe(report), indent=2, allow_nan=False) + "\n")
    write_png(out / "grid.png", make_grid(rows, min(opts.cell_size, res)))
    write_html(out / "report.html", json_safe(report))
    return report

"""Benchmark: how far the clothed proxy's orbit gets with the scan's own depths -- what limits it.

The weight-free orbit is rendered from the clothed proxy (``humanvdm_core.clothed_proxy``): per pixel of
the input view, a front and a back sheet along the camera's ray. Its side views can be wrong because
those depths are wrong (the fitted pose, the thickness rules) or because two sheets cannot hold the
shape (legs crossing at different depths fill the space between them). This benchmark tells the two
apart on the protocol's real scans.

Per scan of ``../shared/fixtures/scans/`` (as ``bench_protocol``: turned to face +Z, rendered at azimuth 0,
elevation 10 deg, ``--photo-size``² RGBA over white):

1. ``build_body_proxy(photo)`` builds the proxy as ``diffuse`` does (every default);
2. the scan is rendered in the proxy's input view (the input view's crop and scale of the photo,
   registered by the silhouettes' boxes, at the proxy camera's focal length from farther back, so the
   scan's shape is a similarity of the proxy's world): its nearest and farthest camera depth per pixel;
3. per *case*, the proxy's front (back) sheet vertices in the case's rows (shares of the input view's
   mask height: :data:`REGIONS`) move along their rays onto the scan's nearest (farthest) surface, scaled
   by one factor per scan so the median depths agree (the fitted body's size differs from the scan's);
   the border vertices, where the two sheets meet, move to the middle of the two when both sheets move,
   else they stay; a pixel the scan does not cover (the proxy's footprint is the mask, a grid pixel
   wider), or where its depth stands more than :data:`OUTLIER` off its 5x5 median (a fingertip's far
   surface), takes the nearest other pixel's depths;
4. each proxy is scored at left / back / right (azimuth 90 / 180 / 270, the proxy's elevation, 576²)
   against the scan at the same cameras, re-framed as ``bench_protocol`` (512²): ``unseen`` (mean PSNR
   of the three), ``side_iou`` (mean of left and right), ``back_iou``.

``now`` is the proxy as built. ``all`` is its ceiling: the proxy's own silhouette and colours with the
scan's depths. A region alone shows what fixing only its depths gains; because the side views are
re-framed around the silhouette's box, one region's depths right and the rest wrong can gain nothing
(the box's front and back still come from the wrong parts).

Run:  .venv/bin/python -m benchmarks.bench_proxy_ceiling [--subjects mei eric soldier]
Writes benchmarks/results/proxy_ceiling.json.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import cv2  # noqa: E402
import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.bench_pipeline import ELEVATION, reframe, scores  # noqa: E402
from benchmarks.bench_pipeline import VIEWS as PROTOCOL_VIEWS  # noqa: E402
from benchmarks.bench_protocol import BANDS, SCANS, WHITE, YAW_DEG, find_scans  # noqa: E402
from benchmarks.common import save_result  # noqa: E402

EVAL = 512
OUTLIER = 0.05  # metres a scan depth may differ from its 5x5 median and still count
VIEWS = {v: az for v, az in PROTOCOL_VIEWS.items() if v != "front"}  # the unseen ones
REGIONS = {"head": [BANDS["head"]], "torso": [BANDS["torso"]], "legs": [BANDS["legs"]],
           "head+torso": [BANDS["head"], BANDS["torso"]], "torso+legs": [BANDS["torso"], BANDS["legs"]],
           "head+legs": [BANDS["head"], BANDS["legs"]], "all": [(0.0, 1.0)]}
CASES = [("now", None, "")] + [(name, rows, "fb") for name, rows in REGIONS.items()] + [
    ("all, front sheet only", REGIONS["all"], "f"), ("all, back sheet only", REGIONS["all"], "b")]


def scan_depths(mesh, photo_cam, photo_alpha: np.ndarray, view_mask: np.ndarray, focal: float,
                radius: float) -> tuple[np.ndarray, np.ndarray]:
    """The scan's nearest and farthest camera depth per pixel of the proxy's input view (``view_mask``),
    seen as the proxy's camera sees: ``prepare_input_view`` crops and scales the photo by one factor (found
    here from the two silhouettes' boxes), which gives the photo's camera a focal length the proxy's
    camera (``focal``) lacks; the scan is rendered at the proxy's focal length from a camera moved
    back along the same axis (the photo's ``radius`` times the focal lengths' ratio) so it fills the
    input view the same, and its shape is then a similarity of the proxy's world (a scan seen at the
    photo's focal length would come out deeper or flatter than it is)."""
    from humanvdm_core.cameras import Cameras, orbit_cameras
    from humanvdm_core.clothed_proxy import reflected_along_rays
    from humanvdm_core.image_fill import nearest_fill
    from humanvdm_core.render import render_views
    from humanvdm_core.scans import TexturedMesh

    def box(mask: np.ndarray) -> np.ndarray:
        ys, xs = np.nonzero(mask > 0.5)
        return np.array([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1], np.float64)

    b0, b1 = box(photo_alpha), box(view_mask)
    s = (b1[3] - b1[1]) / (b0[3] - b0[1])
    shift = 0.5 * (b1[:2] + b1[2:]) - s * 0.5 * (b0[:2] + b0[2:])
    ratio = focal / (s * float(photo_cam.K[0, 0, 0]))
    size = view_mask.shape[0]
    back = orbit_cameras(1, size, elevation_deg=float(photo_cam.elevation_deg[0]), radius=radius * ratio,
                         azimuths_deg=photo_cam.azimuth_deg)
    K = back.K.copy()
    K[0, 0, 0] = K[0, 1, 1] = focal
    K[0, :2, 2] = s * photo_cam.K[0, :2, 2] + shift
    cam = Cameras(K, back.c2w, size, size, back.azimuth_deg, back.elevation_deg, back.radius)
    near = render_views(mesh, cam, WHITE, samples=1).depth[0]
    moved, c = reflected_along_rays(np.asarray(mesh.vertices, np.float64), cam)
    plain = np.ones((len(moved), 3), np.float32)
    far = render_views(TexturedMesh(moved, mesh.faces, vertex_colors=plain), cam, WHITE, samples=1).depth[0]
    far = np.where(far > 0, 2.0 * c - far, 0.0)
    # a pixel far off its 5x5 neighbourhood's median (a fingertip's far depth can be a metre off) is left out
    keep = (near > 0) & (far > 0)
    for depth in (near, far):
        keep &= np.abs(depth - cv2.medianBlur(depth.astype(np.float32), 5)) <= OUTLIER
    # every other pixel (the proxy's footprint reaches a pixel beyond the scan's outline) takes the nearest kept one's
    return nearest_fill(near, keep), nearest_fill(far, keep)


def with_scan_depths(proxy, near: np.ndarray, far: np.ndarray, rows: list[tuple[float, float]] | None,
                     sheets: str) -> np.ndarray:
    """(V, 3) the proxy's vertices, those of ``sheets`` ("f", "b") in ``rows`` moved along their input-view
    rays onto the scan's ``near`` / ``far`` depth (step 3 of the module docstring)."""
    verts = np.asarray(proxy.mesh.vertices, np.float64)
    if rows is None:
        return verts
    cam = proxy.cameras.subset([proxy.front_index])
    w2c, K = cam.w2c[0], cam.K[0]
    local = verts @ w2c[:3, :3].T + w2c[:3, 3]
    z = local[:, 2]
    px = local @ K.T
    u = np.clip((px[:, 0] / z).astype(int), 0, near.shape[1] - 1)
    v = np.clip((px[:, 1] / z).astype(int), 0, near.shape[0] - 1)
    n = len(verts) // 2  # the front sheet, then the back sheet in the same pixel order
    front = np.asarray(proxy.clothed.front)
    border = np.zeros(len(verts), bool)
    border[:n] = border[n:] = np.linalg.norm(verts[:n] - verts[n:], axis=1) < 1e-6
    # the border, where the sheets meet (the outline from the side), moves to the scan's middle when both move
    target = np.where(border, 0.5 * (near[v, u] + far[v, u]), np.where(front, near[v, u], far[v, u]))
    covered = ~border | (sheets == "fb")
    mask_rows = np.nonzero((proxy.input_view.mask > 0.5).any(axis=1))[0]
    r = (v - mask_rows.min()) / max(1, np.ptp(mask_rows))
    scale = float(np.median(z[covered]) / np.median(target[covered]))
    chosen = covered & np.where(front, "f" in sheets, "b" in sheets)
    chosen &= np.logical_or.reduce([(r >= a) & (r < b) for a, b in rows])
    local[chosen] *= (scale * target[chosen] / z[chosen])[:, None]
    return (local - w2c[:3, 3]) @ w2c[:3, :3]


def measure(folder: Path, photo_size: int, tmp: Path) -> dict:
    """One scan's cases (see the module docstring)."""
    from dataclasses import replace

    from humanvdm_core.body_prior import build_body_proxy
    from humanvdm_core.cameras import orbit_cameras
    from humanvdm_core.io import write_png
    from humanvdm_core.render import render_views
    from humanvdm_core.scans import framing_radius, load_scan, normalize_scan

    mesh = normalize_scan(load_scan(folder), yaw_deg=YAW_DEG.get(folder.name, 0.0))
    photo_cam = orbit_cameras(1, photo_size, elevation_deg=ELEVATION, radius=framing_radius(),
                              azimuths_deg=np.array([0.0]))
    rgba = render_views(mesh, photo_cam, WHITE).rgba[0]
    photo = tmp / f"{folder.name}.png"
    write_png(photo, rgba)
    proxy = build_body_proxy(photo)
    front_cam = proxy.cameras.subset([proxy.front_index])
    near, far = scan_depths(mesh, photo_cam, rgba[..., 3], proxy.input_view.mask, float(front_cam.K[0, 0, 0]),
                            framing_radius())
    elevation = float(proxy.cameras.elevation_deg[0])
    cams = orbit_cameras(len(VIEWS), 576, elevation_deg=elevation, radius=framing_radius(),
                         azimuths_deg=np.array(list(VIEWS.values())))
    truth = [reframe(t[..., :3], t[..., 3], EVAL) for t in render_views(mesh, cams, WHITE).rgba]
    out = {}
    for name, rows, sheets in CASES:
        moved = replace(proxy, mesh=replace(proxy.mesh, vertices=with_scan_depths(proxy, near, far, rows, sheets)
                                            .astype(np.float32)))
        seen = moved.render(cams)
        per = {v: scores(reframe(seen[i, ..., :3], seen[i, ..., 3], EVAL), truth[i]) for i, v in enumerate(VIEWS)}
        out[name] = {"unseen": float(np.mean([p["psnr"] for p in per.values()])),
                     "side_iou": float(np.mean([per["left"]["iou"], per["right"]["iou"]])),
                     "back_iou": float(per["back"]["iou"]),
                     "views": {v: {"psnr": p["psnr"], "iou": p["iou"]} for v, p in per.items()}}
        print(f"{folder.name:32s} {name:24s} unseen {out[name]['unseen']:.2f} dB  side IoU "
              f"{out[name]['side_iou']:.3f}  back IoU {out[name]['back_iou']:.3f}", flush=True)
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--subjects", nargs="*", default=None, help="scan name fragments (default: all)")
    parser.add_argument("--photo-size", type=int, default=768)
    args = parser.parse_args()
    import torch

    torch.set_num_threads(1)
    scans = find_scans(args.subjects) if SCANS.is_dir() else []
    if not scans:
        print("no scans in ../shared/fixtures/scans: nothing to measure")
        return 0
    results = {"photo_size": args.photo_size, "eval_size": EVAL, "regions": REGIONS,
               "cases": [{"name": n, "rows": r, "sheets": s} for n, r, s in CASES], "scans": {}}
    with tempfile.TemporaryDirectory() as tmp:
        for folder in scans:
            results["scans"][folder.name] = measure(folder, args.photo_size, Path(tmp))
    command = "python -m benchmarks.bench_proxy_ceiling " + " ".join(sys.argv[1:])
    print("wrote", save_result("proxy_ceiling", results, command.strip()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

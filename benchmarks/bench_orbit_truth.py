"""The body-prior orbit against the truth on synthetic subjects posed and dressed for the hard cases.

Subjects: ``bench_pipeline``'s three (``results/pipeline.json``: subject0 seated, subject1 arms raised,
subject2 standing), ``synthetic.GARMENT_EXAMPLES`` (``gown``, ``skirt_long_hair``, ``walking_skirt``, ``long_coat``),
``a_pose`` (arms held out 45 deg to the side), ``hand_to_face`` (the right palm on the cheek), ``hands_on_head``
(both hands on the crown, elbows out), ``hands_clasped`` (the hands together before the belly), ``arms_crossed``
(the forearms folded across the lower chest) and two more seated subjects, ``seated_1`` and ``seated_5`` (seeds 1
and 5; 5 is the stability suite's), each built with
``make_subject`` (512² texture) and normalised like a scan; and headwear (:data:`HEADWEAR`: ``hat`` a wide
brim and a crown, ``afro``, ``top_bun``, ``helmet`` open at the face), shapes in one colour added around
the subject's head before normalising (:func:`with_headwear`; all closed but the helmet's open shell). The photo is the subject rendered at
azimuth 0, elevation 10°, 576² over white; ``body_prior.build_body_proxy`` (what ``diffuse``'s
body-prior backend renders its orbit from) is rendered at azimuth 0 / 90 / 180 / 270 and scored against
the subject rendered there: PSNR and silhouette IoU after re-framing (``bench_pipeline.reframe``; with
``--no-reframe`` as rendered, only resized: where the subject sits in the frame counts too), per
view; ``unseen`` = mean PSNR of 90/180/270, ``side_iou`` = mean IoU of 90/270. Also the run's warnings.
With ``--photo-azimuth A`` the photo shows the subject from azimuth A (90: in profile), and each view
is A + 0 / 90 / 180 / 270 of the subject against the proxy's 0 / 90 / 180 / 270 (``unseen`` and
``side_iou`` still name the views turned from the photo's).

Run:  .venv/bin/python -m benchmarks.bench_orbit_truth [--subjects subject0 gown] [--no-reframe] [--photo-azimuth 90]
Writes results/orbit_truth.json and results/orbit_truth.png (rows: truth, proxy; per subject), or
only results/orbit_truth_raw.json with ``--no-reframe``; ``_azA`` added to the names for a photo azimuth A.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.bench_pipeline import reframe, resized, scores  # noqa: E402
from benchmarks.common import RESULTS, save_result  # noqa: E402

AZIMUTHS = (0.0, 90.0, 180.0, 270.0)


# headwear: subject, colour, shapes around the head, each (kind, centre offset from the ears' midpoint in
# metres (x, y, z; +z the face's side), radii (x, y, z)): an ellipsoid, or a cylinder about the vertical
# (radii x / z, half-height y); "open ellipsoid" keeps the part behind a plane 0.45 of its radius before
# its centre (the face stays in view)
HEADWEAR = {
    "hat": (dict(seed=24, gender=0.4), (55, 35, 25), [("cylinder", (0.0, 0.085, 0.0), (0.2, 0.008, 0.2)),
                                                      ("cylinder", (0.0, 0.135, -0.005), (0.105, 0.05, 0.115))]),
    "afro": (dict(seed=21, gender=0.8, hair_color=(40, 28, 20)), (40, 28, 20),
             [("ellipsoid", (0.0, 0.06, -0.02), (0.16, 0.15, 0.15))]),
    "top_bun": (dict(seed=22, gender=0.9), None, [("ellipsoid", (0.0, 0.16, -0.03), (0.06, 0.05, 0.06))]),
    "helmet": (dict(seed=23, gender=0.2), (200, 200, 205),
               [("open ellipsoid", (0.0, 0.045, -0.01), (0.13, 0.14, 0.145))]),
}


def with_headwear(mesh, ears, colour, shapes):
    """``mesh`` with ``shapes`` (see :data:`HEADWEAR`) placed about ``ears`` (3,), each in one ``colour``
    (RGB 0-255), merged with :func:`humanvdm_core.scans.merge_meshes`."""
    import trimesh

    from humanvdm_core.scans import TexturedMesh, merge_meshes

    parts = [mesh]
    for kind, offset, radii in shapes:
        if kind == "cylinder":
            shape = trimesh.creation.cylinder(radius=1.0, height=2.0, sections=48)
            v, f = np.asarray(shape.vertices)[:, [0, 2, 1]], np.asarray(shape.faces)  # its axis along y
        else:
            shape = trimesh.creation.icosphere(subdivisions=4)
            v, f = np.asarray(shape.vertices), np.asarray(shape.faces)
            if kind == "open ellipsoid":
                f = f[v[f][:, :, 2].max(axis=1) < 0.45]
        v = v * np.asarray(radii) + np.asarray(ears) + np.asarray(offset)
        parts.append(TexturedMesh(v, f, vertex_colors=np.tile(np.asarray(colour, np.float32) / 255.0, (len(v), 1))))
    return merge_meshes(parts)


def specs() -> dict:
    from testdata.synthetic import GARMENT_EXAMPLES, SubjectSpec

    out = {}
    pipeline = RESULTS / "pipeline.json"
    if pipeline.is_file():
        for r in json.loads(pipeline.read_text())["result"]["subjects"]:
            out[r["subject"]] = SubjectSpec.from_dict(r["spec"])
    out.update(GARMENT_EXAMPLES)
    out["a_pose"] = SubjectSpec(pose="a-pose", gender=0.3, seed=31)  # arms held out to the side, in the body's plane
    out["hand_to_face"] = SubjectSpec(pose="hand-to-face", seed=7)  # the right palm on the cheek
    out["hands_on_head"] = SubjectSpec(pose="hands-on-head", seed=11)  # both hands on the crown, elbows out
    out["hands_clasped"] = SubjectSpec(pose="hands-clasped", seed=5)  # the hands together before the belly
    out["arms_crossed"] = SubjectSpec(pose="arms-crossed", seed=13)  # the forearms folded across the lower chest
    out.update({f"seated_{seed}": SubjectSpec(pose="seated", seed=seed) for seed in (1, 5)})  # more seated people
    out.update({name: SubjectSpec(**kw) for name, (kw, _, _) in HEADWEAR.items()})
    return out


def main() -> None:
    import cv2
    import torch

    from humanvdm_core.body_prior import build_body_proxy
    from humanvdm_core.cameras import orbit_cameras
    from humanvdm_core.io import write_png
    from humanvdm_core.render import render_views
    from humanvdm_core.scans import framing_radius, load_scan, normalize_scan
    from testdata.synthetic import make_subject

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--subjects", nargs="*", default=None)
    ap.add_argument("--no-reframe", action="store_true",
                    help="score the renders as they are (resized only); results in orbit_truth_raw.*")
    ap.add_argument("--photo-azimuth", type=float, default=0.0,
                    help="the photo shows the subject from this azimuth (90: in profile); results in *_azA.*")
    args = ap.parse_args()
    prep = resized if args.no_reframe else reframe
    label = ("orbit_truth_raw" if args.no_reframe else "orbit_truth") + (
        f"_az{args.photo_azimuth:g}" if args.photo_azimuth else "")
    torch.set_num_threads(1)
    table = specs()
    names = args.subjects or list(table)
    cams = orbit_cameras(4, 576, 33.8, 10.0, framing_radius(), azimuths_deg=np.array(AZIMUTHS))
    truth_cams = orbit_cameras(4, 576, 33.8, 10.0, framing_radius(),
                               azimuths_deg=np.array(AZIMUTHS) + args.photo_azimuth)
    result, rows = {}, []
    with tempfile.TemporaryDirectory(prefix="orbit_truth_") as tmp:
        for name in names:
            spec = table[name]
            obj = make_subject(spec, Path(tmp) / name, texture_size=512)
            mesh = load_scan(obj)
            if name in HEADWEAR:
                _, colour, shapes = HEADWEAR[name]
                ears = np.load(obj.parent / "truth.npz")["coco17"][[3, 4]].mean(axis=0)
                mesh = with_headwear(mesh, ears, spec.hair_color if colour is None else colour, shapes)
            mesh = normalize_scan(mesh)
            truth = render_views(mesh, truth_cams, (1.0, 1.0, 1.0)).rgba
            photo = Path(tmp) / f"{name}.png"
            write_png(photo, truth[0])
            proxy = build_body_proxy(photo)
            seen = proxy.render(cams)
            per = [scores(prep(seen[i, ..., :3], seen[i, ..., 3], 512), prep(truth[i, ..., :3], truth[i, ..., 3], 512))
                   for i in range(len(AZIMUTHS))]
            psnr, iou = [round(p["psnr"], 2) for p in per], [round(p["iou"], 3) for p in per]
            result[name] = {"pose": spec.pose, "dress": getattr(spec, "dress", None), "psnr": psnr, "iou": iou,
                            "mean_psnr": round(float(np.mean(psnr)), 2), "unseen": round(float(np.mean(psnr[1:])), 2),
                            "side_iou": round(float(np.mean([iou[1], iou[3]])), 3), "warnings": proxy.warnings}
            print(name, {k: v for k, v in result[name].items() if k != "warnings"}, flush=True)
            sheet = np.concatenate([np.concatenate(list(truth[..., :3]), 1), np.concatenate(list(seen[..., :3]), 1)], 0)
            rows.append(cv2.resize(sheet, None, fx=0.25, fy=0.25, interpolation=cv2.INTER_AREA))
    if not args.no_reframe:  # the sheet shows the renders as they are either way
        write_png(RESULTS / f"{label}.png", np.concatenate(rows, 0))
    cmd = "python -m benchmarks.bench_orbit_truth" + (f" --subjects {' '.join(names)}" if args.subjects else "")
    cmd += " --no-reframe" if args.no_reframe else ""
    cmd += f" --photo-azimuth {args.photo_azimuth:g}" if args.photo_azimuth else ""
    print(save_result(label, result, command=cmd))


if __name__ == "__main__":
    main()

"""Benchmark: where MediaPipe puts the 2D joints of seated and standing people, against the true joints.

Synthetic subjects (``testdata.synthetic``, ``SubjectSpec(pose=..., seed=N)``: seated seeds 1-7, standing
seeds 1-3) are rendered at azimuth 0 as one 576² photo from ``--elevations`` degrees above (seated) or
10 deg (standing), detected (``body.fit.observe_frames``), and their true COCO-17 joints projected with
the same camera. Per subject, in shares of the detected 2D torso (shoulder centre to hip centre), how far
below the true joints the detector puts the shoulders, hips, knees and ankles (mean of left and right;
negative: above), the knees against the hips and shoulders (``knees_vs_trunk``: knees minus the mean of
those two), the thighs' ``thighs_towards`` share, whether ``body.landmarks.seated`` fires and the raise
``raise_seated_knees`` applies there.
Per pose and elevation, the means. This is the measurement behind ``KNEE_RAISE_LEVEL`` and
``KNEE_RAISE_PER_DEG``: the raise should follow ``knees_vs_trunk`` for seated people and fire for no
standing one.

Run:  .venv/bin/python -m benchmarks.bench_landmarks [--elevations 10 20 30] [--seeds 1 2 3 4 5 6 7]
Writes benchmarks/results/landmarks.json.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.common import save_result  # noqa: E402

GROUPS = {"shoulders": (5, 6), "hips": (11, 12), "knees": (13, 14), "ankles": (15, 16)}


def measure(pose: str, seed: int, elevation: float, tmp: Path) -> dict:
    """One subject's 2D joint offsets (see the module docstring)."""
    import torch

    from humanvdm_core.body.fit import observe_frames, project
    from humanvdm_core.body.landmarks import (
        KNEE_RAISE_LEVEL,
        KNEE_RAISE_PER_DEG,
        seated,
        thighs_towards,
        torso_length,
    )
    from humanvdm_core.cameras import orbit_cameras
    from humanvdm_core.io import read_npz
    from humanvdm_core.render import render_views
    from humanvdm_core.scans import framing_radius, load_scan, normalize_scan
    from testdata.synthetic import SubjectSpec, make_subject

    obj = make_subject(SubjectSpec(pose=pose, seed=seed), tmp / f"{pose}{seed}", texture_size=256)
    truth = read_npz(obj.parent / "truth.npz")
    to_scan = truth["normalized_from_world"].astype(np.float64)
    joints = truth["coco17"] @ to_scan[:3, :3].T + to_scan[:3, 3]
    cam = orbit_cameras(1, 576, 33.8, elevation, framing_radius(), azimuths_deg=np.array([0.0]))
    rgba = render_views(normalize_scan(load_scan(obj)), cam, (1.0, 1.0, 1.0)).rgba
    obs, failed = observe_frames(rgba, [0])
    if failed or not obs:
        return {"pose": pose, "seed": seed, "elevation_deg": elevation, "error": "no person detected"}
    kp, conf, world = obs[0].keypoints, obs[0].confidences, obs[0].world_keypoints
    true_px = project(torch.as_tensor(joints[None]), torch.as_tensor(cam.w2c), torch.as_tensor(cam.K))[0][0].numpy()
    torso = torso_length(kp)
    below = {g: float((kp[list(j), 1] - true_px[list(j), 1]).mean() / torso) for g, j in GROUPS.items()}
    up = cam.w2c[0][:3, :3] @ np.array([0.0, 1.0, 0.0])  # the world's up in the camera's axes
    fires = seated(conf, world, up)
    return {"pose": pose, "seed": seed, "elevation_deg": elevation,
            **{k: round(v, 4) for k, v in below.items()},
            "knees_vs_trunk": round(below["knees"] - 0.5 * (below["hips"] + below["shoulders"]), 4),
            "thighs_towards": [round(float(t), 3) for t in thighs_towards(world, up)], "seated_fires": fires,
            "raise": round(max(KNEE_RAISE_LEVEL - KNEE_RAISE_PER_DEG * elevation, 0.0), 4) if fires else 0.0}


def main() -> None:
    import torch

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--elevations", type=float, nargs="*", default=[10.0, 20.0, 30.0])
    ap.add_argument("--seeds", type=int, nargs="*", default=[1, 2, 3, 4, 5, 6, 7])
    ap.add_argument("--standing-seeds", type=int, nargs="*", default=[1, 2, 3])
    args = ap.parse_args()
    torch.set_num_threads(1)
    runs = [("seated", s, e) for e in args.elevations for s in args.seeds]
    runs += [("standing", s, 10.0) for s in args.standing_seeds]
    subjects = []
    with tempfile.TemporaryDirectory(prefix="landmarks_") as tmp:
        for pose, seed, elevation in runs:
            row = measure(pose, seed, elevation, Path(tmp))
            subjects.append(row)
            print({k: v for k, v in row.items()}, flush=True)
    means = {}
    for pose, elevation in dict.fromkeys((r["pose"], r["elevation_deg"]) for r in subjects):
        rows = [r for r in subjects if r["pose"] == pose and r["elevation_deg"] == elevation and "error" not in r]
        means[f"{pose}@{elevation:g}"] = {
            **{k: round(float(np.mean([r[k] for r in rows])), 4) for k in (*GROUPS, "knees_vs_trunk", "raise")},
            "seated_fires": sum(r["seated_fires"] for r in rows), "subjects": len(rows)}
        print(f"{pose}@{elevation:g}", means[f"{pose}@{elevation:g}"], flush=True)
    cmd = "python -m benchmarks.bench_landmarks " + " ".join(sys.argv[1:])
    print(save_result("landmarks", {"means": means, "subjects": subjects}, command=cmd.strip()))


if __name__ == "__main__":
    main()

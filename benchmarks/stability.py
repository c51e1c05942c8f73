"""The stability suite of ``benchmarks.experiments``: where one photo -> 3D person breaks.

Each :class:`Case` is one failure category with a photo that carries truth: a fixture scan
(RenderPeople Mei) or a synthetic Anny subject (:mod:`testdata.synthetic`, posed and dressed
for the case) is turned so that its view from azimuth 0 is the photo, rendered at elevation 10 deg
(30 for a photo taken from above) over white and then edited in 2D where the category asks for it
(cut at the knees or past the wrists, put in a very wide frame, a second person beside it, a
cluttered background). The *truth* is
the same mesh: an orbit frame at azimuth ``a`` of the photo is compared with the mesh rendered at
that frame's camera.

A case passes when all of its checks hold:

- ``iou``: the run finished (exit 0) and the orbit's side views (the frames nearest azimuth 90 and
  270, re-framed as in ``benchmarks.bench_pipeline``) overlap the truth's silhouettes with a mean
  IoU of at least the threshold (``--side-iou-threshold``, default :data:`SIDE_IOU_PASS`);
  ``iou:X``: the same with the case's own floor X, for a photo that cuts the person off (the truth
  shows what the photo does not, so even a right orbit overlaps it less);
- ``warns:TEXT``: the run finished and printed a ``warning`` line that names the photo's file and
  contains TEXT (the run says what it had to guess);
- ``refuses:TEXT``: the run stopped (exit code not 0) with a ``FAILED`` line that names the photo and
  contains TEXT, and no Python traceback in that line (a clear refusal, not a crash).

A case whose checks fail is a result (a row with ``passed: false``), never an exception. Each case
gets a contact sheet (3 rows: truth | orbit | Gaussians; columns: input, left (az 90), back, right
(az 270)); a stage that did not run shows "not run".
"""

from __future__ import annotations

import json
import textwrap
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from benchmarks.bench_pipeline import ELEVATION, VIEWS, WHITE, reframe, scores, view_cameras
from benchmarks.bench_protocol import SCANS, nearest_frame
from benchmarks.cached_runs import PipelineRun, run_pipeline

SIDE_IOU_PASS = 0.6  # mean orbit IoU at azimuth 90/270 for an "iou" check to pass
SIDE_VIEWS = ("left", "back", "right")
MEI = "renderpeople_rp_mei_posed_001"
ERIC = "renderpeople_rp_eric_rigged_001"
CELL = 192


def synthetic_specs() -> dict:
    """The synthetic subjects the cases use, by name (built once per work folder)."""
    from testdata.synthetic import GARMENT_EXAMPLES, HAIR_COLORS, SubjectSpec

    return {
        "standing": SubjectSpec(pose="standing", seed=1),
        "seated": SubjectSpec(pose="seated", seed=5),
        "hands_on_hips": SubjectSpec(pose="hands-on-hips", seed=6),
        "gown": GARMENT_EXAMPLES["gown"],
        "long_hair": SubjectSpec(gender=0.8, hair_style="long", long_hair=True, hair_color=HAIR_COLORS["blonde"],
                                 shirt_pattern="solid", seed=21),
        "child": SubjectSpec(age=0.3, height=0.4, pose="standing", seed=22),
        "walker": SubjectSpec(gender=0.2, pose="walking", shirt_color=(30, 80, 180), seed=23),
        "long_coat": GARMENT_EXAMPLES["long_coat"],
        "hand_to_face": SubjectSpec(pose="hand-to-face", seed=7),
        "hands_on_head": SubjectSpec(pose="hands-on-head", seed=11),
        "hands_clasped": SubjectSpec(pose="hands-clasped", seed=5),
        "arms_crossed": SubjectSpec(pose="arms-crossed", seed=3),
        "head_bowed": SubjectSpec(pose="head-bowed", seed=3),
    }


@dataclass(frozen=True)
class Case:
    """One stability case: a category, where its truth comes from, how the photo is made, its checks."""

    name: str
    category: str
    source: str  # "scan:<folder>" or "synthetic:<key of synthetic_specs()>"
    checks: tuple[str, ...]  # "iou", "iou:X", "warns:TEXT", "refuses:TEXT"
    yaw_deg: float = 0.0  # the subject turned by this much first (180: the photo shows its back)
    # none | crop_knees | crop_wrists | crop_tight | far_off | wide | second_person | clutter | held_object
    edit: str = "none"
    size: int = 0  # photo size in pixels; 0: the suite's photo size
    alpha: bool = False  # keep the render's alpha (an RGBA cut-out) instead of an opaque photo
    elevation_deg: float = ELEVATION  # the photo's camera elevation (30: a photo taken from above)
    note: str = ""


CASES: tuple[Case, ...] = (
    Case("reference_front", "reference (front photo, standing)", f"scan:{MEI}", ("iou",), alpha=True,
         note="the ordinary case, for scale: the protocol's own photo of Mei (RGBA), so its runs are reused"),
    Case("seated", "seated", "synthetic:seated", ("iou",)),
    Case("gown", "loose dress / gown", "synthetic:gown", ("iou",)),
    Case("long_hair", "long hair", "synthetic:long_hair", ("iou",)),
    Case("hands_on_hips", "hands touching the body", "synthetic:hands_on_hips", ("iou",)),
    Case("hand_to_face", "a hand touching the face", "synthetic:hand_to_face", ("warns:on the head", "iou"),
         note="the right palm on the cheek, the forearm rising from an elbow before the chest"),
    Case("hands_on_head", "hands on the head", "synthetic:hands_on_head", ("warns:on the head", "iou"),
         note="both hands resting on the crown, the elbows out to the sides"),
    Case("hands_clasped", "hand-hand contact", "synthetic:hands_clasped", ("iou",),
         note="the hands held together before the lower belly"),
    Case("arms_crossed", "arms crossed before the chest", "synthetic:arms_crossed", ("iou",),
         note="each hand across the midline before the lower chest; MediaPipe leans the torso behind 13 deg back"),
    Case("head_bowed", "a head bowed (reading)", "synthetic:head_bowed", ("iou",),
         note="standing still, the neck bent 45 deg forward: the face reads bowed, so the head is not held "
         "over the shoulders"),
    Case("long_coat", "long coat", "synthetic:long_coat", ("iou",),
         note="a camel coat from the shoulders to mid-calf over dark trousers"),
    Case("child", "child proportions", "synthetic:child", ("iou",)),
    Case("from_behind", "photo from behind", f"scan:{MEI}", ("warns:from behind", "iou"), yaw_deg=180.0),
    Case("tiny_160px", "tiny photo (<= 200 px)", f"scan:{MEI}", ("iou",), size=160),
    Case("tiny_100px", "tiny photo (<= 200 px)", f"scan:{MEI}", ("refuses:too small",), size=100,
         note="below the 128 px minimum: must refuse clearly"),
    Case("two_people", "busy background: another person", "synthetic:standing", ("warns:people", "iou"),
         edit="second_person"),
    Case("clutter", "busy background: clutter", f"scan:{MEI}", ("iou",), edit="clutter"),
    Case("cropped_knees", "cropped body (cut at the knees)", f"scan:{MEI}", ("warns:cut off", "iou:0.45"),
         edit="crop_knees", note="the floor guards the legs the photo cuts off: folded behind the thighs, 0.26"),
    Case("cropped_wrists", "cropped body (arms cut at the sides)", f"scan:{ERIC}", ("warns:cut off", "iou:0.6"),
         edit="crop_wrists", note="Eric's T-pose with both hands past the photo's sides"),
    Case("cropped_to_person", "cut-out cropped to the person (no margin)", "synthetic:hands_on_head", ("iou",),
         edit="crop_tight", note="an opaque photo cut to the person's own box, the hands on the head touching its "
         "top: MediaPipe alone finds nobody in it"),
    Case("far_off", "person far off (a sixth of a 4:3 photo's height)", f"scan:{MEI}", ("warns:fills little", "iou"),
         edit="far_off", size=384, note="the 384 px render of Mei in a 2048x1536 photo: MediaPipe alone finds "
         "nobody in it"),
    Case("wide_4to1", "extreme aspect ratio (4:1)", f"scan:{MEI}", ("iou",), edit="wide"),
    Case("held_object", "held object (a box in the right hand)", "synthetic:standing", ("iou",), edit="held_object"),
    Case("from_above", "photo from above (30 deg)", f"scan:{MEI}", ("warns:taken from above", "iou"),
         elevation_deg=30.0, note="Mei photographed from 30 deg above; scored at the orbit's own (raised) cameras"),
    Case("seated_from_above", "seated, photo from above (30 deg)", "synthetic:seated",
         ("warns:taken from above", "iou"), elevation_deg=30.0,
         note="as a standing photographer sees a seated person; scored at the orbit's own (raised) cameras"),
)
QUICK_CASES = ("tiny_100px", "from_behind")
NOT_COVERED = {
    "fingers (interlaced, pointing, holding)":
        "the synthetic hands keep Anny's rest fingers and no fixture scan shows them (hands_clasped covers two "
        "hands touching, hands_on_hips, hand_to_face and hands_on_head a hand on the body)",
}


# ----------------------------------------------------------------------------- photos and truth

def subject_mesh(key: str, work: Path):
    """The synthetic subject ``key`` as a (world-frame) TexturedMesh, made once into ``work/subjects``."""
    from humanvdm_core.scans import load_scan
    from testdata.synthetic import make_subject

    spec = synthetic_specs()[key]
    folder = work / "subjects" / key
    spec_file = folder / "spec.json"
    wanted = json.dumps(spec.to_dict(), sort_keys=True)
    if not (folder / "subject.obj").exists() or not spec_file.exists() or spec_file.read_text() != wanted:
        make_subject(spec, folder, texture_size=512)
        spec_file.write_text(wanted)
    return load_scan(folder / "subject.obj"), folder


def held_box(folder: Path):
    """A 25 x 30 x 15 cm orange box at the synthetic subject's right wrist (world frame)."""
    import trimesh

    from humanvdm_core.io import read_npz
    from humanvdm_core.scans import TexturedMesh

    truth = read_npz(folder / "truth.npz")
    names = [str(n) for n in truth["coco17_names"]]
    wrist = np.asarray(truth["coco17"][names.index("right_wrist")], np.float64)
    box = trimesh.creation.box(extents=(0.25, 0.30, 0.15))
    centre = wrist + np.array([-0.06, -0.12, 0.10])  # the person's right is -X; hanging below, a bit forward
    colours = np.tile(np.array([[0.92, 0.48, 0.10]], np.float32), (len(box.vertices), 1))
    return TexturedMesh(np.asarray(box.vertices) + centre, np.asarray(box.faces), vertex_colors=colours)


def truth_mesh(case: Case, work: Path):
    """The case's truth: the mesh whose view from azimuth 0 (at the case's elevation) is the photo, normalised."""
    from humanvdm_core.scans import load_scan, merge_meshes, normalize_scan

    kind, key = case.source.split(":", 1)
    if kind == "scan":
        mesh = load_scan(SCANS / key)
    else:
        mesh, folder = subject_mesh(key, work)
        if case.edit == "held_object":
            mesh = merge_meshes([mesh, held_box(folder)])
    return normalize_scan(mesh, yaw_deg=case.yaw_deg)


def render_front(mesh, size: int, elevation_deg: float = ELEVATION) -> np.ndarray:
    """RGBA float (size, size, 4) of ``mesh`` from azimuth 0, ``elevation_deg`` (10), at the orbit framing (RGB
    over white)."""
    from humanvdm_core.cameras import orbit_cameras
    from humanvdm_core.render import render_views
    from humanvdm_core.scans import framing_radius

    cam = orbit_cameras(1, size, elevation_deg=elevation_deg, radius=framing_radius(), azimuths_deg=np.array([0.0]))
    return render_views(mesh, cam, WHITE).rgba[0]


def over(background: np.ndarray, rgba: np.ndarray, x: int, y: int) -> None:
    """Composite ``rgba`` (RGB already over white, straight alpha) onto ``background`` at (x, y), in place."""
    h, w = rgba.shape[:2]
    region = background[y:y + h, x:x + w]
    a = rgba[..., 3:4]
    # the RGB was composited over white: recover the colour where alpha > 0, then blend
    colour = np.where(a > 1e-3, (rgba[..., :3] - (1.0 - a)) / np.maximum(a, 1e-3), 0.0)
    region[...] = np.clip(colour, 0, 1) * a + region * (1.0 - a)


def clutter_background(height: int, width: int, seed: int = 7) -> np.ndarray:
    """A deterministic busy background: a grey gradient with 60 coloured boxes and 20 lines."""
    rng = np.random.default_rng(seed)
    img = np.tile(np.linspace(0.35, 0.8, width, dtype=np.float32)[None, :, None], (height, 1, 3))
    for _ in range(60):
        x0, y0 = int(rng.integers(0, width)), int(rng.integers(0, height))
        w, h = int(rng.integers(width // 20, width // 4)), int(rng.integers(height // 20, height // 3))
        cv2.rectangle(img, (x0, y0), (x0 + w, y0 + h), tuple(float(c) for c in rng.uniform(0, 1, 3)), -1)
    for _ in range(20):
        p = rng.integers(0, [width, height, width, height])
        cv2.line(img, (int(p[0]), int(p[1])), (int(p[2]), int(p[3])), tuple(float(c) for c in rng.uniform(0, 1, 3)),
                 max(1, width // 100))
    return img


def make_photo(case: Case, mesh, work: Path, photo_size: int) -> np.ndarray:
    """The case's photo, RGB float over white (opaque, as a camera gives it; RGBA with ``alpha``)."""
    size = case.size or photo_size
    rgba = render_front(mesh, size, case.elevation_deg)
    if case.edit == "none" or case.edit == "held_object":
        return rgba if case.alpha else rgba[..., :3]
    if case.edit == "crop_knees":
        ys = np.nonzero(rgba[..., 3].max(axis=1) > 0.5)[0]
        cut = int(ys.min() + 0.73 * (ys.max() - ys.min()))  # knees: ~27 % of the height above the soles
        return rgba[:cut, :, :3]
    if case.edit == "crop_wrists":
        xs = np.nonzero(rgba[..., 3].max(axis=0) > 0.5)[0]
        inset = int(0.14 * (xs.max() - xs.min()))  # past the wrists: a T-pose's hands are the outer ~12 % each side
        return rgba[:, xs.min() + inset:xs.max() - inset, :3]
    if case.edit == "crop_tight":
        ys, xs = np.nonzero(rgba[..., 3] > 0.5)
        return rgba[ys.min():ys.max() + 1, xs.min():xs.max() + 1, :3]
    if case.edit == "far_off":
        canvas = np.ones((4 * size, 16 * size // 3, 3), np.float32)
        canvas[2 * size:3 * size, 3 * size:4 * size] = rgba[..., :3]
        return canvas
    if case.edit == "wide":
        canvas = np.ones((size, 4 * size, 3), np.float32)
        canvas[:, int(1.5 * size):int(2.5 * size)] = rgba[..., :3]
        return canvas
    if case.edit == "clutter":
        canvas = clutter_background(size, size)
        over(canvas, rgba, 0, 0)
        return canvas
    if case.edit == "second_person":
        other_mesh, _ = subject_mesh("walker", work)
        from humanvdm_core.scans import normalize_scan

        other = render_front(normalize_scan(other_mesh), size)
        small = cv2.resize(other, None, fx=0.7, fy=0.7, interpolation=cv2.INTER_AREA)
        canvas = np.ones((size, int(1.75 * size), 3), np.float32)
        over(canvas, rgba, 0, 0)
        feet = int(np.nonzero(rgba[..., 3].max(axis=1) > 0.5)[0].max())
        small_feet = int(np.nonzero(small[..., 3].max(axis=1) > 0.5)[0].max())
        over(canvas, small, int(1.0 * size), max(0, feet - small_feet))
        return canvas
    raise ValueError(f"unknown edit {case.edit!r}")


# ----------------------------------------------------------------------------- scoring

def side_scores(run_dir: Path, mesh, eval_size: int) -> tuple[dict, dict]:
    """Per view (left/back/right): orbit (nearest frame) vs truth at that frame's camera; the re-framed images."""
    from humanvdm_core.frames import read_cameras, read_frames
    from humanvdm_core.render import render_views

    orbit_dir = run_dir / "diffuse" / "orbit"
    cams = read_cameras(orbit_dir)
    idx = [nearest_frame(cams.azimuth_deg, VIEWS[v]) for v in SIDE_VIEWS]
    frames = read_frames(orbit_dir, indices=idx)
    truth = render_views(mesh, cams.subset(idx), WHITE).rgba
    out, images = {}, {}
    for i, view in enumerate(SIDE_VIEWS):
        o = reframe(frames[i, ..., :3], frames[i, ..., 3], eval_size)
        t = reframe(truth[i, ..., :3], truth[i, ..., 3], eval_size)
        out[view] = {**scores(o, t), "frame_azimuth_deg": round(float(cams.azimuth_deg[idx[i]]), 2)}
        images[view] = (t[0], o[0])
    return out, images


def gaussian_side_views(run_dir: Path, mesh, eval_size: int) -> tuple[dict, dict]:
    """The final Gaussians at azimuth 90/180/270 (the orbit's elevation and framing) vs the truth there."""
    from humanvdm_core.evaluate import load_gaussians, render_gaussians
    from humanvdm_core.frames import read_cameras
    from humanvdm_core.render import render_views

    cams = view_cameras(read_cameras(run_dir / "diffuse" / "orbit"), eval_size)
    pick = [list(VIEWS).index(v) for v in SIDE_VIEWS]
    cams = cams.subset(pick)
    rgb, alpha = render_gaussians(load_gaussians(run_dir / "splat-optimize" / "gaussians"), cams, WHITE)
    truth = render_views(mesh, cams, WHITE).rgba
    out, images = {}, {}
    for i, view in enumerate(SIDE_VIEWS):
        g = reframe(rgb[i], alpha[i], eval_size)
        t = reframe(truth[i, ..., :3], truth[i, ..., 3], eval_size)
        out[view] = scores(g, t)
        images[view] = g[0]
    return out, images


def judge(case: Case, run: PipelineRun, photo_name: str, side_iou: float | None, threshold: float) -> list[dict]:
    """Each of the case's checks: what it asks, what was seen, whether it holds."""
    results = []
    for check in case.checks:
        kind, _, text = check.partition(":")
        if kind == "iou":
            floor = float(text) if text else threshold
            ok = run.returncode == 0 and side_iou is not None and side_iou >= floor
            seen = "no orbit" if side_iou is None else f"side IoU {side_iou:.3f}"
            if run.returncode:
                seen += f", run exit {run.returncode}"
            results.append({"check": f"side IoU >= {floor:.2f}", "seen": seen, "passed": bool(ok)})
        elif kind == "warns":
            hits = [w for w in run.warnings if photo_name in w and text.lower() in w.lower()]
            ok = run.returncode == 0 and bool(hits)
            results.append({"check": f"warns '{text}' naming {photo_name}", "passed": ok,
                            "seen": hits[0] if hits else f"exit {run.returncode}; warnings: {run.warnings or 'none'}"})
        elif kind == "refuses":
            hits = [e for e in run.errors if photo_name in e and text.lower() in e.lower() and "Traceback" not in e]
            ok = run.returncode != 0 and bool(hits)
            results.append({"check": f"refuses '{text}' naming {photo_name}", "passed": ok,
                            "seen": hits[0] if hits else f"exit {run.returncode}; errors: {run.errors or 'none'}"})
        else:
            raise ValueError(f"unknown check {check!r}")
    return results


# ----------------------------------------------------------------------------- contact sheet

def _cell(img: np.ndarray | None, lines: list[str]) -> np.ndarray:
    """One CELL² uint8 tile: the image letterboxed on white (or blank), with text lines at the top."""
    tile = np.full((CELL, CELL, 3), 255, np.uint8)
    if img is not None:
        img = np.clip(np.asarray(img, np.float32)[..., :3], 0, 1)  # an RGBA photo's RGB is already over white
        h, w = img.shape[:2]
        s = CELL / max(h, w)
        small = cv2.resize(img, (max(1, round(w * s)), max(1, round(h * s))), interpolation=cv2.INTER_AREA)
        y, x = (CELL - small.shape[0]) // 2, (CELL - small.shape[1]) // 2
        tile[y:y + small.shape[0], x:x + small.shape[1]] = np.rint(small * 255).astype(np.uint8)
    wrapped = [part for text in lines for part in (textwrap.wrap(text, 34) or [""])]
    for i, text in enumerate(wrapped[:12]):
        cv2.putText(tile, text, (4, 14 + 14 * i), cv2.FONT_HERSHEY_SIMPLEX, 0.38, (0, 0, 0), 1, cv2.LINE_AA)
    return tile


def truth_views(mesh, size: int) -> dict:
    """The truth at azimuth 90/180/270 (elevation 10, the orbit framing), re-framed: for a sheet without an orbit."""
    from humanvdm_core.cameras import orbit_cameras
    from humanvdm_core.render import render_views
    from humanvdm_core.scans import framing_radius

    cams = orbit_cameras(len(SIDE_VIEWS), size, elevation_deg=ELEVATION, radius=framing_radius(),
                         azimuths_deg=np.array([VIEWS[v] for v in SIDE_VIEWS]))
    rgba = render_views(mesh, cams, WHITE).rgba
    return {v: reframe(rgba[i, ..., :3], rgba[i, ..., 3], size)[0] for i, v in enumerate(SIDE_VIEWS)}


def contact_sheet(path: Path, photo: np.ndarray, row: dict, truth: dict, orbit_images: dict | None,
                  gauss_images: dict | None) -> None:
    """Rows truth | orbit | Gaussians, columns input | left | back | right (PNG)."""
    verdict = "PASS" if row["passed"] else "FAIL"
    truth_row = [_cell(photo, [f"{row['case']}: input", f"{photo.shape[1]}x{photo.shape[0]} px"])]
    orbit_row = [_cell(None, [f"{verdict}: {row['category']}", *(c["check"] for c in row["checks"])])]
    gauss_row = [_cell(None, [f"{'ok' if c['passed'] else 'NO'}: {c['seen']}" for c in row["checks"]])]
    for view in SIDE_VIEWS:
        if orbit_images is not None:
            t, o = orbit_images[view]
            iou = row["orbit"][view]["iou"]
            truth_row.append(_cell(t, [f"truth {view} (az {VIEWS[view]:.0f})"]))
            orbit_row.append(_cell(o, [f"orbit {view} IoU {iou:.2f}"]))
        else:
            truth_row.append(_cell(truth[view], [f"truth {view} (az {VIEWS[view]:.0f})"]))
            orbit_row.append(_cell(None, [f"orbit {view}: not run"]))
        if gauss_images is not None:
            gauss_row.append(_cell(gauss_images[view], [f"Gaussians {view} IoU {row['gaussians'][view]['iou']:.2f}"]))
        else:
            gauss_row.append(_cell(None, [f"Gaussians {view}: not run"]))
    sheet = np.concatenate([np.concatenate(r, axis=1) for r in (truth_row, orbit_row, gauss_row)], axis=0)
    cv2.imwrite(str(path), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR))


# ----------------------------------------------------------------------------- one case

def run_case(case: Case, work: Path, store: Path, sets: list[str], photo_size: int, eval_size: int,
             threshold: float, sheet: Path, jobs: int = 1) -> tuple[dict, PipelineRun | None]:
    """Make the photo, run the pipeline (cached), score, judge, draw the sheet; a row, never an exception
    for what the method does (an error making the photo itself is a row with ``error``)."""
    from humanvdm_core.io import write_png

    row: dict = {"case": case.name, "category": case.category, "source": case.source, "edit": case.edit,
                 "yaw_deg": case.yaw_deg, "note": case.note}
    if case.source.startswith("scan:") and not (SCANS / case.source[5:]).is_dir():
        return {**row, "passed": None, "skipped": f"no scan fixture {SCANS / case.source[5:]}"}, None
    mesh = truth_mesh(case, work)
    photo = make_photo(case, mesh, work, photo_size)
    photo_path = work / "stability" / f"{case.name}.png"
    photo_path.parent.mkdir(parents=True, exist_ok=True)
    write_png(photo_path, photo)
    row["photo"] = str(photo_path)
    row["photo_size"] = [int(photo.shape[1]), int(photo.shape[0])]

    run = run_pipeline(photo_path, store, sets, jobs=jobs)
    run_dir = store / "runs" / run.subject
    row["run"] = run.summary()
    orbit_images = gauss_images = None
    side_iou = None
    if run.ok("diffuse"):
        row["orbit"], orbit_images = side_scores(run_dir, mesh, eval_size)
        side_iou = float(np.mean([row["orbit"][v]["iou"] for v in ("left", "right")]))
        row["side_iou"] = side_iou
    if run.ok("splat-optimize") and run.ok("diffuse"):
        row["gaussians"], gauss_images = gaussian_side_views(run_dir, mesh, eval_size)
        row["gaussians_side_iou"] = float(np.mean([row["gaussians"][v]["iou"] for v in ("left", "right")]))
    row["checks"] = judge(case, run, photo_path.name, side_iou, threshold)
    row["passed"] = all(c["passed"] for c in row["checks"])
    truth = truth_views(mesh, eval_size) if orbit_images is None else {}
    contact_sheet(sheet, photo, row, truth, orbit_images, gauss_images)
    row["sheet"] = str(sheet)
    return row, run

"""Synthetic subjects (testdata.synthetic): meshes, pose semantics, texture layout, determinism,
files that load through trimesh and humanvdm_core.scans.

Needs the ``anny`` package (skipped otherwise) and its warm model cache (see humanvdm_core.body).
The module fixture builds one subject per pose (about a second each).
"""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import torch

pytestmark = pytest.mark.slow

pytest.importorskip("anny", reason="the 'anny' package is not installed (pip install --no-deps anny roma safetensors)")

from humanvdm_core.body import BodyParams  # noqa: E402
from humanvdm_core.body.model import COCO17_NAMES  # noqa: E402
from humanvdm_core.io import read_npz  # noqa: E402
from humanvdm_core.workflow.errors import ConfigError  # noqa: E402
from testdata.synthetic import (  # noqa: E402
    GARMENT_EXAMPLES,
    GARMENT_POSES,
    GARMENT_TEXTURE,
    HAIR_COLORS,
    POSES,
    RANDOM_POSES,
    SKIN_TONES,
    TEXTURE_SIZE,
    TRUTH_SCHEMA,
    TRUTH_VERSION,
    SubjectSpec,
    body_model,
    make_subject,
    random_specs,
)

KP = {name: i for i, name in enumerate(COCO17_NAMES)}
FILES = ("albedo.png", "subject.mtl", "subject.obj", "truth.npz")


def spec_for(pose: str) -> SubjectSpec:
    # blonde hair on brown skin: hair, skin, lips and the dark face features all differ by colour
    return SubjectSpec(pose=pose, hair_color=HAIR_COLORS["blonde"], skin_tone=SKIN_TONES["brown"], shirt_pattern="solid",
                       shirt_color=(30, 80, 180), lower_pattern="solid", lower_color=(40, 140, 70), seed=3)


@pytest.fixture(scope="module")
def subjects(tmp_path_factory) -> dict:
    torch.set_num_threads(1)
    root = tmp_path_factory.mktemp("synthetic")
    out = {}
    for pose in POSES:
        obj = make_subject(spec_for(pose), root / pose)
        out[pose] = (obj, read_npz(obj.parent / "truth.npz", TRUTH_SCHEMA, TRUTH_VERSION))
    return out


def load_textured(obj):
    import trimesh

    mesh = trimesh.load(str(obj), process=False)
    assert isinstance(mesh, trimesh.Trimesh)
    return mesh


def kp(truth, name: str) -> np.ndarray:
    return truth["coco17"][KP[name]]


# ----------------------------------------------------------------------------- meshes

@pytest.mark.parametrize("pose", POSES)
def test_pose_mesh_is_valid_and_grounded(subjects, pose):
    import trimesh

    obj, truth = subjects[pose]
    assert sorted(p.name for p in obj.parent.iterdir()) == sorted(FILES)
    model = body_model()
    v = np.asarray(load_textured(obj).vertices)  # split at UV seams by trimesh
    assert np.isfinite(v).all()
    verts = _obj_vertices(obj)
    assert verts.shape == (int(truth["num_vertices"]), 3) == (model.num_vertices, 3)
    raw = trimesh.Trimesh(verts, model.faces.numpy(), process=False)
    assert raw.is_watertight and raw.is_winding_consistent
    assert (raw.area_faces > 1e-10).mean() > 0.999
    assert abs(verts[:, 1].min()) < 1e-5  # feet on y = 0
    np.testing.assert_allclose(truth["bbox_min"], verts.min(0), atol=1e-5)
    np.testing.assert_allclose(truth["bbox_max"], verts.max(0), atol=1e-5)
    assert 1.0 < verts[:, 1].max() < 2.4
    assert str(truth["pose_name"]) == pose
    assert truth["joints"].shape == (model.num_joints, 3) and truth["coco17"].shape == (17, 3)
    assert np.isfinite(truth["joints"]).all() and np.isfinite(truth["coco17"]).all()


def _obj_vertices(obj) -> np.ndarray:
    return np.array([[float(c) for c in line.split()[1:4]] for line in obj.read_text().splitlines()
                     if line.startswith("v ")])


def test_truth_params_reproduce_the_mesh(subjects):
    obj, truth = subjects["walking"]
    model = body_model()
    params = BodyParams.from_numpy(truth)
    with torch.no_grad():
        out = model(params)
    np.testing.assert_allclose(out.vertices[0].numpy(), _obj_vertices(obj), atol=1e-4)
    np.testing.assert_allclose(out.joints[0].numpy(), truth["joints"], atol=1e-5)
    np.testing.assert_allclose(out.coco17[0].numpy(), truth["coco17"], atol=1e-5)
    assert list(truth["shape_names"]) == model.shape_names
    np.testing.assert_allclose(truth["shape_values"], params.shape[0].numpy())
    assert list(truth["joint_names"]) == model.joint_names


# ----------------------------------------------------------------------------- pose semantics

def test_arms_raised_wrists_above_head(subjects):
    obj, truth = subjects["arms-raised"]
    head_top = subjects["standing"][1]["bbox_max"][1]
    for side in ("left", "right"):
        assert kp(truth, f"{side}_wrist")[1] > head_top
    assert kp(truth, "left_wrist")[0] > 0 > kp(truth, "right_wrist")[0]  # person's left at +X


def test_seated_knees_at_hip_height_and_in_front(subjects):
    _, truth = subjects["seated"]
    for side in ("left", "right"):
        hip, knee, ankle = kp(truth, f"{side}_hip"), kp(truth, f"{side}_knee"), kp(truth, f"{side}_ankle")
        assert abs(knee[1] - hip[1]) < 0.12
        assert knee[2] - hip[2] > 0.3
        assert ankle[1] < knee[1] - 0.3  # shins hang down


def test_hands_on_hips(subjects):
    _, truth = subjects["hands-on-hips"]
    for side in ("left", "right"):
        wrist, hip = kp(truth, f"{side}_wrist"), kp(truth, f"{side}_hip")
        assert np.linalg.norm(wrist - hip) < 0.2
        assert abs(wrist[0]) > abs(hip[0])  # on the outside of the hip
        elbow = kp(truth, f"{side}_elbow")
        assert abs(elbow[0]) > abs(wrist[0]) + 0.05  # elbows out to the side


def test_walking_feet_apart_in_depth(subjects):
    _, truth = subjects["walking"]
    la, ra = kp(truth, "left_ankle"), kp(truth, "right_ankle")
    assert la[2] - ra[2] > 0.3  # left foot forward
    assert kp(truth, "right_wrist")[2] > kp(truth, "left_wrist")[2] + 0.2  # arms swing opposite


def test_hand_to_face_puts_the_right_palm_on_the_cheek(subjects):
    _, truth = subjects["hand-to-face"]
    wrist, ear, eye = kp(truth, "right_wrist"), kp(truth, "right_ear"), kp(truth, "right_eye")
    assert np.linalg.norm(wrist - ear) < 0.15 and wrist[1] < eye[1]  # by the cheek, below the eye
    elbow, shoulder = kp(truth, "right_elbow"), kp(truth, "right_shoulder")
    assert elbow[1] < shoulder[1] and elbow[2] > shoulder[2] + 0.1  # the elbow down, in front of the chest
    assert kp(truth, "left_wrist")[1] < kp(truth, "left_hip")[1] + 0.05  # the left arm hangs


def test_hands_on_head_rest_both_hands_on_the_crown(subjects):
    _, truth = subjects["hands-on-head"]
    eye_y = 0.5 * (kp(truth, "left_eye")[1] + kp(truth, "right_eye")[1])
    for side, s in (("left", 1.0), ("right", -1.0)):
        wrist, elbow, shoulder = (kp(truth, f"{side}_{j}") for j in ("wrist", "elbow", "shoulder"))
        assert eye_y + 0.04 < wrist[1] < eye_y + 0.15 and 0.0 < s * wrist[0] < 0.12  # on top of the head
        assert elbow[1] > shoulder[1] and s * (elbow[0] - shoulder[0]) > 0.08  # the elbows up and out


def test_hands_clasped_meet_before_the_lower_belly(subjects):
    _, truth = subjects["hands-clasped"]
    left, right = kp(truth, "left_wrist"), kp(truth, "right_wrist")
    hips = 0.5 * (kp(truth, "left_hip") + kp(truth, "right_hip"))
    assert np.linalg.norm(left - right) < 0.08  # together
    assert abs(0.5 * (left[1] + right[1]) - hips[1]) < 0.12  # at the lower belly
    assert min(left[2], right[2]) > hips[2] + 0.08  # before the body


def test_arms_crossed_fold_across_the_chest(subjects):
    _, truth = subjects["arms-crossed"]
    shoulders = 0.5 * (kp(truth, "left_shoulder") + kp(truth, "right_shoulder"))
    hips = 0.5 * (kp(truth, "left_hip") + kp(truth, "right_hip"))
    for side, s in (("left", 1.0), ("right", -1.0)):
        wrist, elbow = kp(truth, f"{side}_wrist"), kp(truth, f"{side}_elbow")
        assert s * wrist[0] < -0.03  # across the midline
        assert hips[1] + 0.2 < wrist[1] < shoulders[1] and wrist[2] > shoulders[2] + 0.12  # before the chest
        assert elbow[1] < wrist[1] and s * elbow[0] > 0.1  # the elbow down, beside the body
    assert kp(truth, "right_wrist")[2] > kp(truth, "left_wrist")[2]  # the right forearm over the left


def test_a_bowed_head_hangs_before_the_shoulders(subjects):
    _, bowed = subjects["head-bowed"]
    _, stand = subjects["standing"]

    def ears_ahead(truth) -> float:
        return float(0.5 * (kp(truth, "left_ear") + kp(truth, "right_ear"))[2]
                     - 0.5 * (kp(truth, "left_shoulder") + kp(truth, "right_shoulder"))[2])

    assert ears_ahead(bowed) > ears_ahead(stand) + 0.04  # the head before the shoulders
    assert kp(bowed, "nose")[1] < kp(stand, "nose")[1] - 0.03  # and lower: looking down
    for side in ("left", "right"):  # the rest as standing
        np.testing.assert_allclose(kp(bowed, f"{side}_wrist"), kp(stand, f"{side}_wrist"), atol=1e-6)


def test_standing_and_a_pose_arms(subjects):
    _, stand = subjects["standing"]
    _, apose = subjects["a-pose"]
    for side in ("left", "right"):
        assert kp(stand, f"{side}_wrist")[1] < kp(stand, f"{side}_hip")[1] + 0.05  # arms down
        assert abs(kp(stand, f"{side}_wrist")[0]) < 0.35
        assert abs(kp(apose, f"{side}_wrist")[0]) > 0.45  # arms out
        assert kp(apose, f"{side}_hip")[1] < kp(apose, f"{side}_wrist")[1] < kp(apose, f"{side}_shoulder")[1]


# ----------------------------------------------------------------------------- texture

def _face_samples(mesh, face_mask: np.ndarray) -> np.ndarray:
    """RGB (0-255) of the texture at 7 barycentric points of each selected face."""
    tex = np.asarray(mesh.visual.material.image.convert("RGB"))
    uv = np.asarray(mesh.visual.uv)[mesh.faces[face_mask]]  # (n, 3, 2)
    w = np.array([[1, 1, 1], [4, 1, 1], [1, 4, 1], [1, 1, 4], [2, 2, 1], [2, 1, 2], [1, 2, 2]], float)
    w /= w.sum(1, keepdims=True)
    pts = np.einsum("bk,nkd->nbd", w, uv).reshape(-1, 2)
    h, wd = tex.shape[:2]
    col = np.clip((pts[:, 0] * wd).astype(int), 0, wd - 1)
    row = np.clip(((1.0 - pts[:, 1]) * h).astype(int), 0, h - 1)
    return tex[row, col].astype(np.float64)


def _near(samples: np.ndarray, rgb, tol: float) -> np.ndarray:
    return np.linalg.norm(samples - np.asarray(rgb, float), axis=1) < tol


def _region(mesh, centre, radius, axis: int, sign: float, min_dot: float = 0.6, cell: float = 0.02,
            slack: float = 0.03) -> np.ndarray:
    """Faces within ``radius`` of ``centre`` facing ``sign`` * ``axis`` that lie within ``slack`` of the
    outermost such face along that direction in their ``cell``-sized grid square (a coarse depth
    test: inner surfaces such as the mouth cavity drop out)."""
    c = mesh.triangles_center
    n = mesh.face_normals
    cand = np.flatnonzero((np.linalg.norm(c - np.asarray(centre), axis=1) < radius) & (sign * n[:, axis] > min_dot))
    other = [a for a in range(3) if a != axis]
    keys = np.floor(c[cand][:, other] / cell).astype(np.int64)
    _, cell_id = np.unique(keys, axis=0, return_inverse=True)
    depth = sign * c[cand, axis]
    best = np.full(cell_id.max() + 1, -np.inf)
    np.maximum.at(best, cell_id, depth)
    out = np.zeros(len(c), dtype=bool)
    out[cand[depth >= best[cell_id] - slack]] = True
    return out


def test_face_on_the_front_of_the_head_only(subjects):
    obj, truth = subjects["standing"]
    spec = spec_for("standing")
    mesh = load_textured(obj)
    head = truth["joints"][list(truth["joint_names"]).index("head")] + np.array([0.0, 0.06, 0.0])
    x, z = mesh.triangles_center[:, 0], mesh.triangles_center[:, 2]
    front = _face_samples(mesh, _region(mesh, head, 0.14, 2, +1.0) & (z > head[2]))
    # the back of the skull: not the nape, not the backs of the ears (skin)
    back = _face_samples(mesh, _region(mesh, head, 0.10, 2, -1.0) & (z < head[2]) & (np.abs(x) < 0.06))
    assert len(front) > 500 and len(back) > 500

    def dark(samples):  # eye liner, pupils (the hair is blonde here)
        return samples.mean(axis=1) < 45

    def lips(samples):
        return (samples[:, 0] - samples[:, 1] > 60) & (samples[:, 0] - samples[:, 2] > 50)

    assert dark(front).mean() > 0.01 and lips(front).mean() > 0.003
    assert dark(back).mean() < 0.002 and lips(back).mean() < 0.001
    assert _near(front, spec.skin_tone, 40).mean() > 0.4
    assert _near(back, spec.hair_color, 70).mean() > 0.85
    assert _near(back, spec.skin_tone, 25).mean() < 0.05


def _front_point(mesh, x: float, y: float) -> np.ndarray:
    """The frontmost (largest z) face centre within 2 cm of (x, y) in the XY plane."""
    c = mesh.triangles_center
    near = np.flatnonzero(np.hypot(c[:, 0] - x, c[:, 1] - y) < 0.02)
    return c[near[np.argmax(c[near, 2])]]


def test_clothing_colours_differ_from_skin(subjects):
    obj, truth = subjects["standing"]
    spec = spec_for("standing")
    mesh = load_textured(obj)
    J = {n: truth["joints"][i] for i, n in enumerate(truth["joint_names"])}
    belly = _front_point(mesh, 0.0, J["spine03"][1])
    shirt = np.median(_face_samples(mesh, _region(mesh, belly, 0.06, 2, +1.0)), axis=0)
    thigh = _front_point(mesh, *(0.5 * (J["upperleg02.L"] + J["lowerleg01.L"]))[:2])
    trousers = np.median(_face_samples(mesh, _region(mesh, thigh, 0.08, 2, +1.0, 0.5)), axis=0)
    shoes = np.median(_face_samples(mesh, _region(mesh, J["toe3-1.L"] + [0, 0.02, 0], 0.05, 1, +1.0, 0.3)), axis=0)
    skin = np.asarray(spec.skin_tone, float)
    for colour, expected in ((shirt, spec.shirt_color), (trousers, spec.lower_color), (shoes, spec.shoe_color)):
        assert np.linalg.norm(colour - skin) > 60
        assert np.linalg.norm(colour - np.asarray(expected, float)) < 30
    forearm = 0.5 * (J["lowerarm01.L"] + J["wrist.L"])
    arm = np.median(_face_samples(mesh, _region(mesh, forearm, 0.05, 0, +1.0, 0.3)), axis=0)
    assert np.linalg.norm(arm - skin) < 30  # short sleeves: bare forearms


def test_texture_is_in_the_anny_uv_layout(subjects):
    obj, _ = subjects["a-pose"]
    mesh = load_textured(obj)
    assert mesh.visual.kind == "texture"
    assert mesh.visual.material.image.size == (TEXTURE_SIZE, TEXTURE_SIZE)
    model = body_model()
    vt = np.array([[float(c) for c in line.split()[1:3]] for line in obj.read_text().splitlines()
                   if line.startswith("vt ")])
    np.testing.assert_allclose(vt, model.uvs.numpy(), atol=1e-6)


def test_loads_through_scans_with_matching_normalisation(subjects):
    scans = pytest.importorskip("humanvdm_core.scans")
    obj, truth = subjects["seated"]
    mesh = scans.load_scan(obj.parent)
    assert mesh.texture is not None and mesh.texture.shape == (TEXTURE_SIZE, TEXTURE_SIZE, 3)
    np.testing.assert_allclose(scans.normalization_transform(mesh), truth["normalized_from_world"], atol=1e-5)
    norm = truth["normalized_from_world"]
    joints_n = truth["joints"] @ norm[:3, :3].T + norm[:3, 3]
    lo, hi = scans.normalize_scan(mesh).bounds
    assert np.all(joints_n >= lo - 1e-3) and np.all(joints_n <= hi + 1e-3)
    assert hi[1] - lo[1] == pytest.approx(scans.DEFAULT_SUBJECT_HEIGHT, abs=1e-4)


# ----------------------------------------------------------------------------- determinism, specs

def test_same_spec_gives_identical_files(subjects, tmp_path):
    obj, _ = subjects["hands-on-hips"]
    again = make_subject(spec_for("hands-on-hips"), tmp_path / "again")
    for name in FILES:
        assert (obj.parent / name).read_bytes() == (again.parent / name).read_bytes(), name


def test_random_specs_are_varied_and_reproducible():
    specs = random_specs(12, seed=5)
    assert specs == random_specs(12, seed=5)
    assert specs != random_specs(12, seed=6)
    assert {s.pose for s in specs} == set(RANDOM_POSES)
    assert len({s.skin_tone for s in specs}) >= 6
    assert min(s.gender for s in specs) < 0.4 < 0.6 < max(s.gender for s in specs)
    assert len({s.seed for s in specs}) == 12
    for s in specs:
        assert SubjectSpec.from_dict(s.to_dict()) == s


def test_spec_validation():
    with pytest.raises(ConfigError, match="pose"):
        SubjectSpec(pose="cartwheel")
    with pytest.raises(ConfigError, match="age"):
        SubjectSpec(age=1.5)
    with pytest.raises(ConfigError, match="skin_tone"):
        SubjectSpec(skin_tone=(300, 0, 0))
    with pytest.raises(ConfigError, match="unknown"):
        SubjectSpec.from_dict({"colour": 1})


# ----------------------------------------------------------------------------- garment meshes

GARMENT_TEXTURE_SIZE = 128  # small: these tests look at geometry and silhouettes


def body_only(spec: SubjectSpec) -> SubjectSpec:
    return replace(spec, dress="none", long_hair=False)


@pytest.fixture(scope="module")
def garments(tmp_path_factory) -> dict:
    """name -> (obj, truth) for two garment examples and their body-only twins ("<name>/body")."""
    torch.set_num_threads(1)
    root = tmp_path_factory.mktemp("garments")
    out = {}
    for name in ("skirt_long_hair", "gown"):
        for key, spec in ((name, GARMENT_EXAMPLES[name]), (f"{name}/body", body_only(GARMENT_EXAMPLES[name]))):
            obj = make_subject(spec, root / key.replace("/", "_"), texture_size=GARMENT_TEXTURE_SIZE)
            out[key] = (obj, read_npz(obj.parent / "truth.npz", TRUTH_SCHEMA, TRUTH_VERSION))
    return out


def test_garment_spec_fields():
    assert not set(SubjectSpec().to_dict()) & {"dress", "dress_flare", "dress_color", "dress_color2",
                                               "dress_pattern", "long_hair"}
    assert {s.pose for s in random_specs(12, seed=5)} == set(RANDOM_POSES)
    assert not any(s.has_garments for s in random_specs(12, seed=5))
    for spec in GARMENT_EXAMPLES.values():
        assert spec.has_garments and SubjectSpec.from_dict(spec.to_dict()) == spec
        assert SubjectSpec.from_dict(json.loads(json.dumps(spec.to_dict()))) == spec
    assert set(GARMENT_POSES) == set(POSES) - {"seated"}
    with pytest.raises(ConfigError, match="dress"):
        SubjectSpec(dress="cape")
    with pytest.raises(ConfigError, match="upright"):
        SubjectSpec(dress="skirt", pose="seated")
    with pytest.raises(ConfigError, match="dress_flare"):
        SubjectSpec(dress="long", dress_flare=2.0)
    with pytest.raises(ConfigError, match="dress_pattern"):
        SubjectSpec(dress="long", dress_pattern="paisley")
    assert SubjectSpec(long_hair=True, pose="seated").has_garments  # hair goes with any pose


def _obj_objects(obj) -> list[str]:
    return [line.split()[1] for line in obj.read_text().splitlines() if line.startswith("o ")]


def test_garment_files_and_meshes(garments, tmp_path):
    import trimesh

    scans = pytest.importorskip("humanvdm_core.scans")
    model = body_model()
    for name in ("skirt_long_hair", "gown"):
        obj, truth = garments[name]
        body_obj, body_truth = garments[f"{name}/body"]
        assert sorted(p.name for p in obj.parent.iterdir()) == sorted((*FILES, GARMENT_TEXTURE))
        assert sorted(p.name for p in body_obj.parent.iterdir()) == sorted(FILES)
        assert _obj_objects(obj) == ["subject", "dress", "hair"] and _obj_objects(body_obj) == ["subject"]
        assert list(truth["garments"]) == ["dress", "hair"]
        # the body is the body-only twin's, byte for byte: OBJ lines, albedo, parameters
        text, body_text = obj.read_text(), body_obj.read_text()
        assert text.startswith(body_text) and text[len(body_text):].startswith("o dress\n")
        assert (obj.parent / "albedo.png").read_bytes() == (body_obj.parent / "albedo.png").read_bytes()
        for key in ("pose", "shape", "transl", "joints", "coco17", "num_vertices", "num_faces"):
            np.testing.assert_array_equal(truth[key], body_truth[key])
        # the OBJ's garment vertices are the truth's, after the body's
        verts = _obj_vertices(obj)
        nb, nd = model.num_vertices, len(truth["dress_vertices"])
        assert len(verts) == nb + nd + len(truth["hair_vertices"])
        np.testing.assert_allclose(verts[nb:nb + nd], truth["dress_vertices"], atol=1e-5)
        np.testing.assert_allclose(verts[nb + nd:], truth["hair_vertices"], atol=1e-5)
        np.testing.assert_allclose(truth["bbox_min"], verts.min(0), atol=1e-5)
        np.testing.assert_allclose(truth["bbox_max"], verts.max(0), atol=1e-5)
        assert abs(verts[:, 1].min()) < 1e-5  # still standing on y = 0
        for part in ("dress", "hair"):
            mesh = trimesh.Trimesh(truth[f"{part}_vertices"], truth[f"{part}_faces"], process=False)
            assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0, part
        # load_scan merges both materials (two textures -> one atlas); normalisation as recorded
        scan = scans.load_scan(obj.parent)
        assert len(scan.vertices) >= len(verts) and scan.texture is not None
        np.testing.assert_allclose(scans.normalization_transform(scan), truth["normalized_from_world"], atol=1e-5)
        # the dress reaches from the waist to the knee / ankle
        knee, ankle = (np.mean([kp(truth, f"{s}_{j}")[1] for s in ("left", "right")]) for j in ("knee", "ankle"))
        hips = np.mean([kp(truth, f"{s}_hip")[1] for s in ("left", "right")])
        assert hips < truth["dress_top_y"] < hips + 0.25
        assert truth["dress_knee_half_width"] > 0.2 and truth["dress_knee_half_depth"] > 0.15
    _, skirt = garments["skirt_long_hair"]
    _, gown = garments["gown"]
    knee = np.mean([kp(skirt, f"{s}_knee")[1] for s in ("left", "right")])
    assert knee - 0.12 < skirt["dress_hem_y"] < knee
    assert 0.0 < gown["dress_hem_y"] < 0.1
    assert gown["dress_hem_half_width"] == pytest.approx(GARMENT_EXAMPLES["gown"].dress_flare, abs=0.04)
    assert gown["hair_bottom_y"] < kp(gown, "left_shoulder")[1] - 0.1  # down to the shoulder blades
    # deterministic
    again = make_subject(GARMENT_EXAMPLES["gown"], tmp_path / "again", texture_size=GARMENT_TEXTURE_SIZE)
    for name in (*FILES, GARMENT_TEXTURE):
        assert (garments["gown"][0].parent / name).read_bytes() == (again.parent / name).read_bytes(), name


def _section_points(vertices: np.ndarray, faces: np.ndarray, y: float) -> np.ndarray:
    """Where a mesh's edges cross the horizontal plane at height ``y``."""
    tri = vertices.astype(np.float64)[faces]
    out = []
    for i, j in ((0, 1), (1, 2), (2, 0)):
        a, b = tri[:, i], tri[:, j]
        da, db = a[:, 1] - y, b[:, 1] - y
        m = da * db < 0
        out.append(a[m] + (da[m] / (da[m] - db[m]))[:, None] * (b[m] - a[m]))
    return np.concatenate(out)


def _render(obj, azimuths, size: int = 384):
    from humanvdm_core.cameras import orbit_cameras
    from humanvdm_core.render import render_views
    from humanvdm_core.scans import framing_radius, load_scan, normalize_scan

    cams = orbit_cameras(len(azimuths), size, elevation_deg=0.0, radius=framing_radius(),
                         azimuths_deg=np.asarray(azimuths, dtype=float))
    return cams, render_views(normalize_scan(load_scan(obj)), cams, (1.0, 1.0, 1.0)).rgba


def _project(cams, i: int, truth, points: np.ndarray) -> np.ndarray:
    """(N, 2) pixel (u, v) of world points, through the subject's normalisation and camera ``i``."""
    N = truth["normalized_from_world"].astype(np.float64)
    p = points @ N[:3, :3].T + N[:3, 3]
    c = p @ cams.w2c[i][:3, :3].T + cams.w2c[i][:3, 3]
    uv = c @ cams.K[i].T
    return uv[:, :2] / uv[:, 2:]


def _silhouette_span(alpha: np.ndarray, row: int) -> tuple[int, int]:
    cols = np.flatnonzero(alpha[row] > 0.5)
    return int(cols.min()), int(cols.max()) + 1


@pytest.mark.parametrize("name", ["skirt_long_hair", "gown"])
def test_dress_widens_the_silhouette_at_knee_height(garments, name):
    model = body_model()
    widths = {}
    for key in (name, f"{name}/body"):
        obj, truth = garments[key]
        cams, rgba = _render(obj, [0.0, 90.0])
        body_v = _obj_vertices(obj)[:model.num_vertices]
        knee_y = float(np.mean([kp(truth, f"{s}_knee")[1] for s in ("left", "right")]))
        legs = _section_points(body_v, model.faces.numpy(), knee_y)
        for i, view in enumerate(("front", "side")):
            row = int(np.floor(_project(cams, i, truth, legs)[:, 1].mean()))
            lo, hi = _silhouette_span(rgba[i, ..., 3], row)
            widths[key, view] = hi - lo
            uv = _project(cams, i, truth, legs)
            widths[key, view, "legs"] = uv[:, 0].max() - uv[:, 0].min()
            if key == name:
                dress = _project(cams, i, truth, _section_points(truth["dress_vertices"], truth["dress_faces"], knee_y))
                widths[key, view, "dress"] = dress[:, 0].max() - dress[:, 0].min()
                # truth's half-width / half-depth at the knee describe that cross-section
                extent = truth["dress_knee_half_width" if view == "front" else "dress_knee_half_depth"] * 2
                scale = abs(truth["normalized_from_world"][0, 0]) * cams.K[i][0, 0] / cams.radius[i]
                assert widths[key, view, "dress"] == pytest.approx(extent * scale, rel=0.1)
    for view in ("front", "side"):
        dressed, bare = widths[name, view], widths[f"{name}/body", view]
        assert bare == pytest.approx(widths[f"{name}/body", view, "legs"], abs=4)  # the legs
        assert dressed == pytest.approx(widths[name, view, "dress"], abs=4)  # the dress
        assert dressed > 1.25 * bare  # the legs are inside
        # wider by about the dress's width less the legs'
        assert dressed - bare == pytest.approx(widths[name, view, "dress"] - widths[f"{name}/body", view, "legs"],
                                               abs=6)


def test_a_long_coat_hangs_from_the_shoulders_to_mid_calf(tmp_path):
    import trimesh

    torch.set_num_threads(1)
    obj = make_subject(GARMENT_EXAMPLES["long_coat"], tmp_path / "coat", texture_size=GARMENT_TEXTURE_SIZE)
    truth = read_npz(obj.parent / "truth.npz", TRUTH_SCHEMA, TRUTH_VERSION)
    assert str(truth["dress_kind"]) == "coat" and list(truth["garments"]) == ["dress"]
    coat = trimesh.Trimesh(truth["dress_vertices"], truth["dress_faces"], process=False)
    assert coat.is_watertight and coat.is_winding_consistent and coat.volume > 0
    shoulder = np.mean([kp(truth, f"{s}_shoulder")[1] for s in ("left", "right")])
    knee, ankle = (np.mean([kp(truth, f"{s}_{j}")[1] for s in ("left", "right")]) for j in ("knee", "ankle"))
    assert shoulder - 0.06 < truth["dress_top_y"] < shoulder + 0.02
    assert ankle + 0.3 * (knee - ankle) < truth["dress_hem_y"] < knee - 0.3 * (knee - ankle)
    # it hangs: no narrower at the waist than at the chest, and wider than the thighs at the knees
    hips = np.mean([kp(truth, f"{s}_hip")[1] for s in ("left", "right")])
    width = {}
    for name, y in (("chest", shoulder - 0.15), ("waist", 0.5 * (shoulder + hips) - 0.05)):
        x = _section_points(truth["dress_vertices"], truth["dress_faces"], y)[:, 0]
        width[name] = x.max() - x.min()
    assert width["waist"] >= width["chest"] - 0.005
    assert 2 * truth["dress_knee_half_width"] > 0.3 and 2 * truth["dress_knee_half_depth"] > 0.25


def test_long_hair_hangs_below_the_neck_at_the_back(garments):
    obj, truth = garments["skirt_long_hair"]
    bare_obj, bare_truth = garments["skirt_long_hair/body"]
    spec = GARMENT_EXAMPLES["skirt_long_hair"]
    J = {n: truth["joints"][i] for i, n in enumerate(truth["joint_names"])}
    neck_y, bottom = float(J["neck01"][1]), float(truth["hair_bottom_y"])
    assert bottom < neck_y - 0.12
    ys = np.linspace(neck_y - 0.02, bottom + 0.02, 6)
    hair_rgb = np.asarray(spec.hair_color, float) / 255.0
    backs = {}
    for key, t in (("hair", truth), ("bare", bare_truth)):
        cams, rgba = _render(obj if key == "hair" else bare_obj, [180.0, 90.0])
        # back view: the spine's line below the neck is hair-coloured with hair, shirt-coloured without
        points = np.stack([np.zeros_like(ys), ys, np.full_like(ys, float(truth["hair_back_z"]))], axis=1)
        uv = np.floor(_project(cams, 0, t, points)).astype(int)
        colours = rgba[0, uv[:, 1], uv[:, 0], :3]
        near_hair = np.linalg.norm(colours - hair_rgb, axis=1) < 0.15
        assert near_hair.all() if key == "hair" else not near_hair.any(), (key, colours)
        # side view (from the person's left, image right = the back): the outline reaches further back
        backs[key] = []
        for y in ys:
            row = int(np.floor(_project(cams, 1, t, np.array([[0.0, y, 0.0]]))[0, 1]))
            backs[key].append(_silhouette_span(rgba[1, ..., 3], row)[1] - _project(cams, 1, t, np.zeros((1, 3)))[0, 0])
    scale = abs(truth["normalized_from_world"][0, 0]) * cams.K[1][0, 0] / cams.radius[1]  # px per metre (about)
    assert np.all(np.asarray(backs["hair"]) > np.asarray(backs["bare"]) + 0.01 * scale)

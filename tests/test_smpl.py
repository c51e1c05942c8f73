"""SMPL / SMPL-X backend on tiny synthetic model files (tests/smpl_tiny.py; the real files are non-free).

Checks loading (chumpy pickles without chumpy, .npz), the missing-file errors, the project's conventions,
LBS consistency, gradients, batching, COCO-17 order, UV layouts, and, when the ``smplx`` package is
installed, that the vertices and joints equal ``smplx``'s own forward pass.
"""

from __future__ import annotations

import math
import pickle
import sys

import numpy as np
import pytest
import torch

from humanvdm_core.body import (
    COCO17_NAMES,
    BodyParams,
    UVPositionMap,
    axis_angle_to_matrix,
    lbs,
    load_body_model,
)
from humanvdm_core.body.smpl_model import SMPL_JOINT_NAMES, SMPLX_JOINT_NAMES, SMPLBody, load_model_file
from humanvdm_core.errors import MissingWeightsError
from humanvdm_core.workflow.errors import ConfigError
from tests import smpl_tiny

NOSE, L_EYE, R_EYE, L_EAR, R_EAR = 0, 1, 2, 3, 4
L_SHOULDER, L_WRIST, R_WRIST, L_HIP, L_ANKLE, R_HIP, R_ANKLE = 5, 9, 10, 11, 15, 12, 16


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """Folders with the tiny models: ``pkl`` (chumpy pickle SMPL + SMPL-X npz), ``npz`` (SMPL npz)."""
    torch.set_num_threads(1)
    smpl, smplx_data = smpl_tiny.smpl_arrays(), smpl_tiny.smplx_arrays()
    pkl_root, npz_root = tmp_path_factory.mktemp("pkl"), tmp_path_factory.mktemp("npz")
    smpl_tiny.write_smpl_pkl(pkl_root, data=smpl)
    smpl_tiny.write_smplx_npz(pkl_root, data=smplx_data)
    smpl_tiny.write_smpl_npz(npz_root, data=smpl)
    return {"pkl": pkl_root, "npz": npz_root, "smpl": smpl, "smplx": smplx_data}


def make(tiny, kind: str = "smpl", root: str = "pkl", **kw) -> SMPLBody:
    face_ids = tiny[kind]["face_vertex_ids"].tolist()
    return SMPLBody(tiny[root], kind=kind, face_vertex_ids=face_ids, **kw)


@pytest.fixture(scope="module")
def body(tiny) -> SMPLBody:
    return make(tiny)


@pytest.fixture(scope="module")
def body_x(tiny) -> SMPLBody:
    return make(tiny, "smplx")


def random_params(model: SMPLBody, batch: int, seed: int = 0, pose_std: float = 0.3) -> BodyParams:
    g = torch.Generator().manual_seed(seed)
    p = model.zero_params(batch)
    p.pose = pose_std * torch.randn(p.pose.shape, generator=g)
    p.shape = torch.randn(p.shape.shape, generator=g)
    p.global_orient = torch.randn(batch, 3, generator=g)
    p.transl = torch.randn(batch, 3, generator=g)
    p.scale = 0.7 + 0.6 * torch.rand(batch, 1, generator=g)
    return p


# ----------------------------------------------------------------------------- files

def test_chumpy_pickle_loads_without_chumpy(tiny):
    before = set(sys.modules)
    data = load_model_file(tiny["pkl"] / "smpl" / "SMPL_NEUTRAL.pkl")
    new = {m.split(".")[0] for m in set(sys.modules) - before}
    assert "chumpy" not in sys.modules and "scipy" not in new
    ref = tiny["smpl"]
    for key in ("v_template", "shapedirs", "weights", "J_regressor", "posedirs", "kintree_table", "f"):
        assert isinstance(data[key], np.ndarray), key
        assert np.allclose(data[key], ref[key]), key
    assert data["bs_style"] == "lbs"


def test_text_protocol_pickle(tiny, tmp_path):
    path = smpl_tiny.write_smpl_pkl(tmp_path, data=tiny["smpl"], protocol=0)
    assert b"cnumpy.core.multiarray\n_reconstruct" in path.read_bytes()
    data = load_model_file(path)
    assert np.allclose(data["shapedirs"], tiny["smpl"]["shapedirs"])
    assert np.allclose(data["J_regressor"], tiny["smpl"]["J_regressor"])


def test_npz_object_arrays_skipped(tiny):
    data = load_model_file(tiny["pkl"] / "smplx" / "SMPLX_NEUTRAL.npz")
    assert "joint2num" not in data and data["v_template"].shape == tiny["smplx"]["v_template"].shape


def test_unpickler_refuses_other_globals(tmp_path):
    path = tmp_path / "SMPL_NEUTRAL.pkl"
    path.write_bytes(pickle.dumps({"v_template": print}, protocol=2))  # any non-allowed global
    with pytest.raises(pickle.UnpicklingError, match="refusing"):
        load_model_file(path)


def test_pkl_and_npz_agree(tiny, body):
    from_npz = make(tiny, root="npz")
    assert from_npz.model_file.suffix == ".npz" and body.model_file.suffix == ".pkl"
    p = random_params(body, 2, seed=1)
    a, b = body(p), from_npz(p)
    assert torch.allclose(a.vertices, b.vertices, atol=1e-6)
    assert torch.equal(body.faces, from_npz.faces)


def test_model_file_may_be_given_directly(tiny):
    path = tiny["npz"] / "smpl" / "SMPL_NEUTRAL.npz"
    model = SMPLBody(path, face_vertex_ids=tiny["smpl"]["face_vertex_ids"])
    assert model.num_vertices == len(tiny["smpl"]["v_template"])


@pytest.mark.parametrize("kind,gender,expected", [
    ("smpl", "neutral", "smpl/SMPL_NEUTRAL.pkl"), ("smpl", "female", "smpl/SMPL_FEMALE.pkl"),
    ("smplx", "neutral", "smplx/SMPLX_NEUTRAL.npz"), ("smplx", "male", "smplx/SMPLX_MALE.npz"),
])
def test_missing_model_file(tmp_path, kind, gender, expected):
    with pytest.raises(MissingWeightsError, match=expected) as info:
        SMPLBody(tmp_path, kind=kind, gender=gender)
    assert info.value.path == tmp_path / expected
    assert ("smpl-x.is.tue.mpg.de" if kind == "smplx" else "smpl.is.tue.mpg.de") in str(info.value)
    with pytest.raises(MissingWeightsError, match=expected):
        load_body_model(kind, model_dir=tmp_path, gender=gender)


def test_bad_arguments(tiny, tmp_path):
    with pytest.raises(ConfigError, match="unknown"):
        SMPLBody(tmp_path, kind="smplh")
    with pytest.raises(ConfigError, match="gender"):
        SMPLBody(tmp_path, gender="other")
    with pytest.raises(ConfigError, match="face_vertex_ids"):  # a non-standard vertex count
        SMPLBody(tiny["pkl"])
    with pytest.raises(ConfigError, match="num_betas"):
        make(tiny, num_betas=11)
    with pytest.raises(ConfigError, match="unknown body model backend"):
        load_body_model("smplh")
    with pytest.raises(ConfigError, match="model_dir"):
        load_body_model("smpl")


def test_factory(tiny):
    model = load_body_model("smplx", model_dir=tiny["pkl"], face_vertex_ids=tiny["smplx"]["face_vertex_ids"],
                            num_betas=5, num_expression_coeffs=3)
    assert isinstance(model, SMPLBody) and model.name == "smplx:neutral"
    assert model.shape_names == [f"beta{i}" for i in range(5)] + [f"expression{i}" for i in range(3)]


# ----------------------------------------------------------------------------- model

@pytest.mark.parametrize("kind", ["smpl", "smplx"])
def test_shapes(tiny, body, body_x, kind):
    model = body if kind == "smpl" else body_x
    V, J = model.num_vertices, model.num_joints
    names = SMPL_JOINT_NAMES if kind == "smpl" else SMPLX_JOINT_NAMES
    assert J == len(names) and model.joint_names == list(names) and len(model.pose_joint_names) == J - 1
    assert len(model.shape_names) == (10 if kind == "smpl" else 20)
    assert model.faces.dtype == torch.int64 and model.faces.shape[1] == 3 and int(model.faces.max()) < V
    assert model.skinning_weights.shape == (V, J)
    assert torch.allclose(model.skinning_weights.sum(1), torch.ones(V), atol=1e-5)
    out = model(random_params(model, 3))
    assert out.vertices.shape == out.rest_vertices.shape == (3, V, 3)
    assert out.joints.shape == (3, J, 3) and out.bone_transforms.shape == (3, J, 4, 4)
    assert out.coco17.shape == (3, len(COCO17_NAMES), 3) and out.vertices.dtype == torch.float32
    assert torch.isfinite(out.vertices).all()


def test_batch_equals_single(body_x):
    p = random_params(body_x, 3, seed=2)
    batch = body_x(p)
    for i in range(3):
        one = BodyParams(**{name: getattr(p, name)[i:i + 1]
                            for name in ("pose", "shape", "global_orient", "transl", "scale")})
        assert torch.allclose(body_x(one).vertices[0], batch.vertices[i], atol=1e-5)


def test_gradients_reach_every_parameter(body_x):
    p = random_params(body_x, 2, seed=3).requires_grad_()
    out = body_x(p)
    (out.vertices.square().sum() + out.coco17.square().sum()).backward()
    for name in ("pose", "shape", "global_orient", "transl", "scale"):
        grad = getattr(p, name).grad
        assert grad is not None and torch.isfinite(grad).all() and grad.abs().sum() > 0, name


@pytest.mark.parametrize("kind", ["smpl", "smplx"])
def test_world_conventions(body, body_x, kind):
    model = body if kind == "smpl" else body_x
    out = model(model.zero_params())
    k, joints = out.coco17[0], out.joints[0]
    assert torch.allclose(joints[0], torch.zeros(3), atol=1e-6)  # root at the origin
    assert torch.allclose(out.bone_transforms[0], torch.eye(4).expand_as(out.bone_transforms[0]), atol=1e-6)
    assert k[NOSE, 1] > k[L_SHOULDER, 1] > k[L_HIP, 1] > k[L_ANKLE, 1]  # head above feet
    assert k[NOSE, 2] > 0.5 * (k[L_EAR, 2] + k[R_EAR, 2]) + 0.05  # facing +Z
    assert k[L_WRIST, 0] > 0.2 and k[R_WRIST, 0] < -0.2 and k[L_EYE, 0] > k[R_EYE, 0]  # left at +X
    assert torch.allclose(k[L_WRIST] * torch.tensor([-1.0, 1.0, 1.0]), k[R_WRIST], atol=1e-5)


def test_coco17_order(body, tiny):
    out = body(random_params(body, 2, seed=4))
    face_ids = tiny["smpl"]["face_vertex_ids"]
    assert torch.equal(out.coco17[:, :5], out.vertices[:, face_ids])
    for i, name in enumerate(COCO17_NAMES[5:], start=5):
        assert torch.equal(out.coco17[:, i], out.joints[:, body.joint_names.index(name)]), name


def test_global_params(body):
    base = body(body.zero_params())
    p = body.zero_params()
    p.global_orient[0] = torch.tensor([0.0, math.pi / 2, 0.0])  # turn to face +X
    p.scale[0] = 2.0
    p.transl[0] = torch.tensor([0.1, 0.2, 0.3])
    out = body(p)
    R = axis_angle_to_matrix(p.global_orient[0])
    assert torch.allclose(out.vertices[0], 2.0 * base.vertices[0] @ R.T + p.transl[0], atol=1e-5)
    nose, ears = out.coco17[0, NOSE], 0.5 * (out.coco17[0, L_EAR] + out.coco17[0, R_EAR])
    assert nose[0] > ears[0] + 0.1


def test_pose_axes_are_world_axes(body):
    # A T-posed left arm (along +X) rotated by -0.5 rad about +Z at the shoulder swings down.
    zero = body(body.zero_params())
    p = body.zero_params()
    p.pose[0, body.pose_index("left_shoulder")] = torch.tensor([0.0, 0.0, -0.5])
    w0, w1 = zero.coco17[0, L_WRIST], body(p).coco17[0, L_WRIST]
    assert w1[1] < w0[1] - 0.1 and w1[0] < w0[0] - 0.02 and abs(float(w1[2] - w0[2])) < 0.02


@pytest.mark.parametrize("kind", ["smpl", "smplx"])
def test_canonical_da_pose(body, body_x, kind):
    model = body if kind == "smpl" else body_x
    k = model(model.canonical_params()).coco17[0]
    for hip, ankle, sign in ((L_HIP, L_ANKLE, 1.0), (R_HIP, R_ANKLE, -1.0)):
        d = k[ankle] - k[hip]
        assert 25.0 <= math.degrees(math.atan2(sign * float(d[0]), -float(d[1]))) <= 35.0
    assert k[L_WRIST, 1] < k[L_SHOULDER, 1] - 0.1 and k[L_WRIST, 0] > k[L_HIP, 0] + 0.1


@pytest.mark.parametrize("kind", ["smpl", "smplx"])
def test_lbs_reproduces_model(body, body_x, kind):
    model = body if kind == "smpl" else body_x
    out = model(random_params(model, 3, seed=5))
    posed = lbs(out.rest_vertices, model.skinning_weights, out.bone_transforms)
    assert (posed - out.vertices).abs().max() < 1e-5


def test_lbs_from_canonical(tiny, body):
    plain = make(tiny, pose_correctives=False)
    p = random_params(body, 2, seed=6)
    for model, tol in ((plain, 1e-4), (body, 0.05)):
        canonical = model.canonical_params(2)
        canonical.shape = p.shape.clone()
        can, tgt = model(canonical), model(p)
        posed = lbs(can.vertices, model.skinning_weights, tgt.bone_transforms,
                    source_transforms=can.bone_transforms)
        assert (posed - tgt.vertices).abs().max() < tol
    # without correctives the rest mesh is the shaped template, whatever the pose
    assert torch.allclose(plain(p).rest_vertices, plain(canonical).rest_vertices, atol=1e-6)


def test_shape_changes_height(body):
    p = body.zero_params()
    p.shape[0, 0] = 3.0
    tall, base = body(p).vertices[0, :, 1], body(body.zero_params()).vertices[0, :, 1]
    assert float(tall.max() - tall.min()) > float(base.max() - base.min()) + 0.05


# ----------------------------------------------------------------------------- UV layout

def test_without_uv_file(body):
    assert body.uvs is None and body.uv_faces is None and body.uv_file is None
    with pytest.raises(MissingWeightsError, match="smpl_uv.obj"):
        body.require_uv_layout()
    with pytest.raises(MissingWeightsError, match="smpl_uv.obj"):
        UVPositionMap.from_model(body, 32)


def test_uv_obj(tiny, tmp_path):
    smpl_tiny.write_smpl_npz(tmp_path, data=tiny["smpl"])
    obj = smpl_tiny.write_uv_obj(tmp_path / "smpl" / "smpl_uv.obj", tiny["smpl"])
    model = SMPLBody(tmp_path, face_vertex_ids=tiny["smpl"]["face_vertex_ids"])
    model.require_uv_layout()
    assert model.uv_file == obj and model.uv_faces.shape == model.faces.shape
    F = len(model.faces)
    # write_uv_obj gives face i the texture coordinates 3i, 3i+1, 3i+2 (listed reordered, corners rotated)
    assert torch.equal(model.uv_faces, torch.arange(3 * F).reshape(F, 3))
    uvmap = UVPositionMap.from_model(model, 64)
    assert uvmap.num_samples > 0


# ----------------------------------------------------------------------------- against smplx

def test_matches_smplx_smpl(body):
    smplx = pytest.importorskip("smplx", reason="the smplx package is not installed")
    from smplx.utils import Struct

    B = 3
    p = random_params(body, B, seed=7, pose_std=0.5)
    p.scale = torch.ones(B, 1)
    out = body(p)
    ids = dict.fromkeys(smplx.vertex_ids.vertex_ids["smplh"], 0)  # the tiny mesh has no such vertices
    ref = smplx.SMPL(str(body.model_file.parent), data_struct=Struct(**load_model_file(body.model_file)),
                     vertex_ids=ids, num_betas=10, batch_size=B)
    with torch.no_grad():
        o = ref(betas=p.shape, body_pose=p.pose.reshape(B, -1), global_orient=p.global_orient,
                transl=p.transl - body.pelvis_offset(p.shape))
    assert (o.vertices - out.vertices).abs().max() < 1e-5
    assert (o.joints[:, :24] - out.joints).abs().max() < 1e-5


def test_matches_smplx_smplx(body_x, monkeypatch):
    smplx = pytest.importorskip("smplx", reason="the smplx package is not installed")
    from smplx import body_models

    # SMPLX always picks the standard topology's extra vertices; the tiny mesh has none of them.
    monkeypatch.setitem(body_models.VERTEX_IDS, "smplx", dict.fromkeys(body_models.VERTEX_IDS["smplx"], 0))
    B = 2
    p = random_params(body_x, B, seed=8, pose_std=0.5)
    p.scale = torch.ones(B, 1)
    out = body_x(p)
    ref = smplx.SMPLX(str(body_x.model_file.parent), use_pca=False, flat_hand_mean=True, num_betas=10,
                      num_expression_coeffs=10, batch_size=B)
    q = p.pose
    with torch.no_grad():
        o = ref(betas=p.shape[:, :10], expression=p.shape[:, 10:], global_orient=p.global_orient,
                body_pose=q[:, :21].reshape(B, -1), jaw_pose=q[:, 21], leye_pose=q[:, 22], reye_pose=q[:, 23],
                left_hand_pose=q[:, 24:39].reshape(B, -1), right_hand_pose=q[:, 39:].reshape(B, -1),
                transl=p.transl - body_x.pelvis_offset(p.shape))
    assert (o.vertices - out.vertices).abs().max() < 1e-5
    assert (o.joints[:, :55] - out.joints).abs().max() < 1e-5

"""Body model interface, the Anny backend and UV position maps.

Needs the ``anny`` package (skipped otherwise). The first Anny build writes its cache (about a
minute, see humanvdm_core.body.anny_model); with a warm cache this module runs in seconds.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

pytestmark = pytest.mark.slow

pytest.importorskip("anny", reason="the 'anny' package is not installed (pip install --no-deps anny roma safetensors)")

from humanvdm_core.body import (  # noqa: E402
    COCO17_NAMES,
    AnnyBody,
    BodyParams,
    UVPositionMap,
    anny_cache_dir,
    axis_angle_to_matrix,
    lbs,
)
from humanvdm_core.workflow.errors import ConfigError  # noqa: E402

NOSE, L_EAR, R_EAR = 0, 3, 4
L_SHOULDER, R_SHOULDER, L_WRIST, R_WRIST = 5, 6, 9, 10
L_HIP, R_HIP, L_ANKLE, R_ANKLE = 11, 12, 15, 16


@pytest.fixture(scope="module")
def body() -> AnnyBody:
    torch.set_num_threads(1)
    return AnnyBody()


def random_params(body: AnnyBody, batch: int, seed: int = 0, pose_std: float = 0.3) -> BodyParams:
    g = torch.Generator().manual_seed(seed)
    p = body.zero_params(batch)
    p.pose = pose_std * torch.randn(p.pose.shape, generator=g)
    p.shape = torch.rand(p.shape.shape, generator=g)
    p.global_orient = torch.randn(batch, 3, generator=g)
    p.transl = torch.randn(batch, 3, generator=g)
    p.scale = 0.7 + 0.6 * torch.rand(batch, 1, generator=g)
    return p


# ----------------------------------------------------------------------------- model

def test_cache_dir_env_override(monkeypatch, tmp_path):
    monkeypatch.setenv("HUMANVDM_CACHE", str(tmp_path))
    assert anny_cache_dir() == tmp_path / "anny"


def test_unknown_or_nonfree_topology_refused():
    with pytest.raises(ConfigError, match="non-free"):
        AnnyBody(topology="smplx")
    with pytest.raises(ConfigError, match="unknown"):
        AnnyBody(topology="nope")


def test_shapes(body):
    V, J = body.num_vertices, body.num_joints
    assert V == 13718 and J == 104 and len(body.pose_joint_names) == J - 1
    assert body.faces.dtype == torch.int64 and body.faces.shape[1] == 3
    assert int(body.faces.min()) >= 0 and int(body.faces.max()) < V
    assert body.uv_faces.shape == body.faces.shape and body.uvs.shape[1] == 2
    assert float(body.uvs.min()) >= 0.0 and float(body.uvs.max()) <= 1.0
    assert body.skinning_weights.shape == (V, J)
    assert torch.allclose(body.skinning_weights.sum(1), torch.ones(V), atol=1e-5)
    out = body(random_params(body, 2))
    assert out.vertices.shape == (2, V, 3)
    assert out.rest_vertices.shape == (2, V, 3)
    assert out.joints.shape == (2, J, 3)
    assert out.coco17.shape == (2, len(COCO17_NAMES), 3)
    assert out.bone_transforms.shape == (2, J, 4, 4)
    assert out.vertices.dtype == torch.float32
    assert torch.isfinite(out.vertices).all()


def test_gradients_reach_every_parameter(body):
    p = random_params(body, 2, seed=1).requires_grad_()
    out = body(p)
    (out.vertices.square().sum() + out.coco17.square().sum()).backward()
    for name in ("pose", "shape", "global_orient", "transl", "scale"):
        grad = getattr(p, name).grad
        assert grad is not None and torch.isfinite(grad).all(), name
        assert grad.abs().sum() > 0, name


def test_world_conventions(body):
    out = body(body.zero_params())
    v, k = out.vertices[0], out.coco17[0]
    height = float(v[:, 1].max() - v[:, 1].min())
    assert 1.4 < height < 2.0
    # head above feet, root (pelvis) at the origin
    assert k[NOSE, 1] > k[L_SHOULDER, 1] > k[L_HIP, 1] > k[L_ANKLE, 1]
    assert torch.allclose(out.joints[0, 0], torch.zeros(3), atol=1e-5)
    # facing +Z: the nose is in front of the ears
    assert k[NOSE, 2] > 0.5 * (k[L_EAR, 2] + k[R_EAR, 2]) + 0.05
    # the person's left at +X
    assert k[L_WRIST, 0] > 0.2 and k[R_WRIST, 0] < -0.2
    assert out.joints[0, body.joint_names.index("wrist.L"), 0] > 0.2
    # symmetric: left and right keypoints mirror each other across x = 0
    assert torch.allclose(k[L_WRIST] * torch.tensor([-1.0, 1.0, 1.0]), k[R_WRIST], atol=2e-3)


def test_global_params(body):
    base = body(body.zero_params())
    p = body.zero_params()
    p.global_orient[0] = torch.tensor([0.0, math.pi / 2, 0.0])  # turn to face +X
    p.scale[0] = 2.0
    p.transl[0] = torch.tensor([0.1, 0.2, 0.3])
    out = body(p)
    R = axis_angle_to_matrix(p.global_orient[0])
    expected = 2.0 * base.vertices[0] @ R.T + p.transl[0]
    assert torch.allclose(out.vertices[0], expected, atol=1e-5)
    nose, ears = out.coco17[0, NOSE], 0.5 * (out.coco17[0, L_EAR] + out.coco17[0, R_EAR])
    assert nose[0] > ears[0] + 0.1  # now facing +X


def test_pose_axes_are_world_axes(body):
    # Rotating the left shoulder joint by -90 degrees about world +Z swings the A-posed left arm
    # down and towards the body (clockwise seen from the front): the wrist drops and moves inward.
    zero = body(body.zero_params())
    p = body.zero_params()
    p.pose[0, body.pose_index("upperarm01.L")] = torch.tensor([0.0, 0.0, -0.5])
    out = body(p)
    w0, w1 = zero.coco17[0, L_WRIST], out.coco17[0, L_WRIST]
    assert w1[1] < w0[1] - 0.05 and w1[0] < w0[0] - 0.05
    assert abs(float(w1[2] - w0[2])) < 0.05  # a rotation about Z keeps the wrist's depth


def test_canonical_da_pose(body):
    out = body(body.canonical_params())
    k = out.coco17[0]
    for hip, ankle, sign in ((L_HIP, L_ANKLE, 1.0), (R_HIP, R_ANKLE, -1.0)):
        d = k[ankle] - k[hip]
        angle = math.degrees(math.atan2(sign * float(d[0]), -float(d[1])))
        assert 25.0 <= angle <= 35.0
    # arms relaxed: wrists below the shoulders, away from the hips
    assert k[L_WRIST, 1] < k[L_SHOULDER, 1] - 0.1 and k[L_WRIST, 0] > k[L_HIP, 0] + 0.1


def test_lbs_reproduces_model(body):
    p = random_params(body, 3, seed=2)
    out = body(p)
    posed = lbs(out.rest_vertices, body.skinning_weights, out.bone_transforms)
    assert (posed - out.vertices).abs().max() < 1e-4


def test_lbs_from_canonical(body):
    # Points on the canonical body follow the body into any pose (the Gaussians' use of lbs).
    p = random_params(body, 2, seed=3)
    canonical = body.canonical_params(2)
    canonical.shape = p.shape.clone()
    can = body(canonical)
    tgt = body(p)
    posed = lbs(can.vertices, body.skinning_weights, tgt.bone_transforms, source_transforms=can.bone_transforms)
    assert (posed - tgt.vertices).abs().max() < 1e-3


def test_forward_deterministic(body):
    p = random_params(body, 2, seed=4)
    a, b = body(p), body(p)
    assert torch.equal(a.vertices, b.vertices) and torch.equal(a.bone_transforms, b.bone_transforms)


def test_params_numpy_roundtrip(body):
    p = random_params(body, 2, seed=5)
    q = BodyParams.from_numpy(p.to_numpy())
    assert all(torch.equal(getattr(p, n), getattr(q, n)) for n in ("pose", "shape", "global_orient", "transl", "scale"))


def test_low_resolution_topology(body):
    pytest.importorskip("warp", reason="building a retopology the first time needs warp-lang")
    low = AnnyBody(topology="notoes_collapse10pc")
    assert low.num_vertices == 1229 and low.num_joints == body.num_joints and low.uvs is None
    p = random_params(body, 2, seed=6)
    full_out, low_out = body(p), low(p)
    # same skeleton, keypoints transferred from the full mesh within a few centimetres (times scale)
    assert torch.allclose(full_out.joints, low_out.joints, atol=1e-4)
    assert (full_out.coco17 - low_out.coco17).norm(dim=-1).max() < 0.025
    with pytest.raises(ValueError, match="no UV layout"):
        UVPositionMap.from_model(low, 64)


# ----------------------------------------------------------------------------- UV position map

@pytest.fixture(scope="module")
def uvmaps(body) -> dict[int, UVPositionMap]:
    return {r: UVPositionMap.from_model(body, r) for r in (128, 256, 512)}


def test_uvmap_counts_scale_with_area(body, uvmaps):
    counts = {r: m.num_samples for r, m in uvmaps.items()}
    assert 3.8 < counts[256] / counts[128] < 4.2 and 3.8 < counts[512] / counts[256] < 4.2
    tri = body.uvs.double().numpy()[body.uv_faces.numpy()]
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    area = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]).sum()
    for r, m in uvmaps.items():
        assert abs(m.num_samples - area * r * r) < 0.01 * area * r * r
        assert m.mask.shape == (r, r) and int(m.mask.sum()) == m.num_samples


def test_uvmap_samples_valid(body, uvmaps):
    m = uvmaps[256]
    assert m.face_ids.min() >= 0 and m.face_ids.max() < len(body.faces)
    assert (m.barycentrics >= 0).all() and np.allclose(m.barycentrics.sum(1), 1.0)
    texel = m.rows * m.resolution + m.cols
    assert (np.diff(texel) > 0).all()  # row-major, each texel once
    # each texel's centre is where its face's UV triangle puts the barycentric point
    uv = body.uvs.double().numpy()[body.uv_faces.numpy()[m.face_ids]]
    uv_at = (uv * m.barycentrics[:, :, None]).sum(1)
    centre = np.stack([(m.cols + 0.5) / m.resolution, 1.0 - (m.rows + 0.5) / m.resolution], 1)
    assert np.abs(uv_at - centre).max() < 1e-6


def test_uvmap_positions_on_surface(body, uvmaps):
    import trimesh
    import trimesh.proximity

    m = uvmaps[128]
    out = body(random_params(body, 1, seed=7))
    points = m.positions(out.vertices)[0].numpy().astype(np.float64)
    assert points.shape == (m.num_samples, 3)
    mesh = trimesh.Trimesh(out.vertices[0].numpy().astype(np.float64), body.faces.numpy(), process=False)
    sample = points[np.random.default_rng(0).choice(len(points), 200, replace=False)]
    _, dist, _ = trimesh.proximity.closest_point_naive(mesh, sample)
    assert dist.max() < 1e-5
    # numpy in, numpy out; torch stays differentiable
    assert np.allclose(m.positions(out.vertices[0].numpy()), points, atol=1e-5)
    w = m.weights(body.skinning_weights)
    assert w.shape == (m.num_samples, body.num_joints) and torch.allclose(w.sum(1), torch.ones(len(w)), atol=1e-5)
    # UV samples posed by lbs with interpolated weights stay on the posed surface samples, up to
    # LBS's non-linearity inside a triangle (about a millimetre here)
    posed = lbs(m.positions(out.rest_vertices), w, out.bone_transforms)
    assert (posed[0] - torch.as_tensor(points, dtype=posed.dtype)).norm(dim=-1).max() < 5e-3


def test_uvmap_deterministic_and_roundtrip(body, uvmaps, tmp_path):
    again = UVPositionMap.from_model(body, 256)
    ref = uvmaps[256]
    for name in ("face_ids", "barycentrics", "rows", "cols"):
        assert np.array_equal(getattr(ref, name), getattr(again, name))
    ref.save(tmp_path / "a.npz")
    ref.save(tmp_path / "b.npz")
    assert (tmp_path / "a.npz").read_bytes() == (tmp_path / "b.npz").read_bytes()
    loaded = UVPositionMap.load(tmp_path / "a.npz")
    assert np.array_equal(loaded.barycentrics, ref.barycentrics) and loaded.resolution == 256
    image = ref.to_image(ref.positions(body(body.zero_params()).vertices[0]))
    assert image.shape == (256, 256, 3) and bool((image[~torch.as_tensor(ref.mask)] == 0).all())

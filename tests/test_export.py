"""The exported Gaussians, read by a third-party reader (plyfile): 3DGS property order and types, axes, .splat."""

from __future__ import annotations

import numpy as np
import pytest

from humanvdm_core.splat import human as H

plyfile = pytest.importorskip("plyfile")

HEAD, FEET, NOSE = 0, 1, 2


def _person(n_extra: int = 40, seed: int = 0):
    """Gaussians in our world (y up, facing +z): a head at y 1.7, feet at y 0, a nose in front of the head,
    then random anisotropic ones."""
    rng = np.random.default_rng(seed)
    means = np.concatenate([[[0.0, 1.7, 0.0], [0.0, 0.0, 0.0], [0.0, 1.65, 0.12]],
                            rng.uniform(-0.3, 0.3, (n_extra, 3)) + [0, 0.9, 0]]).astype(np.float32)
    n = len(means)
    q = rng.normal(size=(n, 4))
    quats = (q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32)
    scales = rng.uniform(0.005, 0.05, (n, 3)).astype(np.float32)
    opac = rng.uniform(0.1, 1.0, n).astype(np.float32)
    colors = rng.uniform(0, 1, (n, 3)).astype(np.float32)
    return means, quats, scales, opac, colors


def _cov(quats: np.ndarray, scales: np.ndarray) -> np.ndarray:
    import torch

    R = H.quat_to_matrix(torch.as_tensor(np.asarray(quats, np.float64))).numpy()
    return R @ (np.asarray(scales, np.float64)[:, :, None] ** 2 * np.swapaxes(R, 1, 2))


def test_ply_in_3dgs_axes_read_by_plyfile(tmp_path):
    means, quats, scales, opac, colors = _person()
    path = tmp_path / "point_cloud.ply"
    H.write_ply(path, means, quats, scales, opac, colors)  # the default: 3DGS/COLMAP axes
    ply = plyfile.PlyData.read(str(path))
    assert ply.byte_order == "<" and not ply.text
    assert [e.name for e in ply.elements] == ["vertex"]
    vertex = ply["vertex"]
    assert [p.name for p in vertex.properties] == list(H.PLY_PROPERTIES)
    assert [p.name for p in vertex.properties][:9] == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    assert [p.name for p in vertex.properties][-8:] == ["opacity", "scale_0", "scale_1", "scale_2",
                                                       "rot_0", "rot_1", "rot_2", "rot_3"]
    assert {p.val_dtype for p in vertex.properties} == {"f4"} and vertex.count == len(means)
    assert any("y-down" in c for c in ply.comments) and any("metres" in c for c in ply.comments)

    xyz = np.stack([vertex[a] for a in "xyz"], axis=1).astype(np.float64)
    # y down: the head is above the feet, so at a smaller y; the subject faces -z (the nose is at smaller z)
    assert xyz[HEAD, 1] < xyz[FEET, 1] - 1.5
    assert xyz[NOSE, 2] < xyz[HEAD, 2] - 0.1
    np.testing.assert_allclose(xyz, means * [1, -1, -1], atol=1e-6)
    # the Gaussians' shapes turned with the points: cov_file = R cov R^T, R = diag(1, -1, -1)
    q_file = np.stack([vertex[f"rot_{i}"] for i in range(4)], axis=1)
    s_file = np.exp(np.stack([vertex[f"scale_{i}"] for i in range(3)], axis=1))
    R = np.diag([1.0, -1.0, -1.0])
    np.testing.assert_allclose(_cov(q_file, s_file), R @ _cov(quats, scales) @ R, atol=1e-7)
    np.testing.assert_allclose(1 / (1 + np.exp(-vertex["opacity"])), np.clip(opac, 1e-6, 1 - 1e-6), atol=1e-5)
    np.testing.assert_allclose(0.5 + H.SH_C0 * vertex["f_dc_1"], colors[:, 1], atol=1e-6)
    assert np.all(vertex["f_rest_44"] == 0) and np.all(vertex["nx"] == 0)

    back = H.read_ply(path)  # our reader: back into our world
    np.testing.assert_allclose(back["means"], means, atol=1e-6)
    np.testing.assert_allclose(back["quats"], quats, atol=1e-6)
    assert str(back["axes"]) == "y-down"


def test_ply_y_up_option_keeps_our_axes(tmp_path):
    means, quats, scales, opac, colors = _person(5)
    path = tmp_path / "up.ply"
    H.write_ply(path, means, quats, scales, opac, colors, axes="y-up")
    vertex = plyfile.PlyData.read(str(path))["vertex"]
    assert vertex["y"][HEAD] > vertex["y"][FEET] + 1.5 and vertex["z"][NOSE] > vertex["z"][HEAD]
    np.testing.assert_allclose(H.read_ply(path)["quats"], quats, atol=1e-6)


def test_splat_file_matches_the_ply(tmp_path):
    means, quats, scales, opac, colors = _person()
    H.write_splat(tmp_path / "g.splat", means, quats, scales, opac, colors)
    raw = (tmp_path / "g.splat").read_bytes()
    assert len(raw) == 32 * len(means)
    s = H.read_splat(tmp_path / "g.splat")
    importance = np.prod(s["scales"], axis=1) * s["opacities"]
    assert np.all(np.diff(importance) <= 0.05 * importance[:-1])  # largest, most opaque first (8-bit opacity)
    order = np.argsort(-(np.prod(scales.astype(np.float64), axis=1) * opac), kind="stable")
    np.testing.assert_allclose(s["means"], (means * [1, -1, -1])[order], atol=1e-6)  # same axes as the PLY
    np.testing.assert_allclose(s["colors"], colors[order], atol=0.5 / 255 + 1e-6)
    np.testing.assert_allclose(s["opacities"], opac[order], atol=0.5 / 255 + 1e-6)
    R = np.diag([1.0, -1.0, -1.0])
    cov = _cov(s["quats"], s["scales"])
    want = R @ _cov(quats[order], scales[order]) @ R
    np.testing.assert_allclose(cov, want, atol=0.05 * np.abs(want).max())  # 8-bit rotations

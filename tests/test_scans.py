"""Scan loading and normalisation: OBJ/GLB fixtures, the THuman2.0 layout, atlases, bad inputs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from humanvdm_core.scans import (
    TexturedMesh,
    find_mesh_file,
    framing_radius,
    load_scan,
    merge_meshes,
    normalization_transform,
    normalize_scan,
    save_obj,
)
from humanvdm_core.workflow.errors import InputError
from testdata.procedural import make_person, write_person

SCANS = Path(__file__).resolve().parents[1].parent / "shared" / "fixtures" / "scans"
RENDERPEOPLE = SCANS / "renderpeople_rp_mei_posed_001"
SOLDIER = SCANS / "threejs_soldier" / "Soldier.glb"


def need(path: Path) -> Path:
    if not path.exists():
        pytest.skip(f"fixture not present: {path}")
    return path


def extent(mesh: TexturedMesh) -> np.ndarray:
    lo, hi = mesh.bounds
    return hi - lo


@pytest.mark.fixtures
def test_renderpeople_obj_loads_and_normalises():
    folder = need(RENDERPEOPLE)
    mesh = load_scan(folder)
    assert mesh.num_faces == 30004 and len(mesh.vertices) == 17368
    assert mesh.texture.shape == (2048, 2048, 3) and mesh.texture.dtype == np.uint8
    assert mesh.uvs.min() >= 0.0 and mesh.uvs.max() <= 1.0
    assert 165 < extent(mesh)[1] < 175  # centimetres, Y up
    by_file = load_scan(folder / "rp_mei_posed_001_30k.obj")
    np.testing.assert_array_equal(by_file.vertices, mesh.vertices)

    norm = normalize_scan(mesh, height=1.7)
    np.testing.assert_allclose(extent(norm)[1], 1.7, rtol=1e-5)
    np.testing.assert_allclose(norm.bounds.mean(axis=0), 0.0, atol=1e-5)
    assert extent(norm)[0] < 1.0 and extent(norm)[2] < 1.0


@pytest.mark.fixtures
def test_soldier_glb_merges_meshes_in_bind_pose_and_normalises():
    mesh = load_scan(need(SOLDIER))
    assert mesh.num_faces == 11376  # body + visor
    assert mesh.texture.shape == (1024, 1024, 3)  # both materials share one image: no atlas
    raw = extent(mesh)
    assert raw[1] > 3 * raw[2], "skinned meshes must stay in their Y-up bind pose"
    norm = normalize_scan(mesh, height=1.7)
    size = extent(norm)
    np.testing.assert_allclose(size[1], 1.7, rtol=1e-5)
    assert 1.2 < size[0] < 2.2  # T-pose arm span about the height
    assert size[2] < 0.6
    np.testing.assert_allclose(norm.bounds.mean(axis=0), 0.0, atol=1e-5)


def test_thuman_layout_and_parent_folder(tmp_path):
    person = make_person(segments=12)
    scan_dir = tmp_path / "0001"
    save_obj(person, scan_dir, "0001", texture_name="material0.jpeg", mtl_name="material0.mtl")
    for path in (scan_dir, tmp_path, scan_dir / "0001.obj"):
        mesh = load_scan(path)
        assert mesh.num_faces == person.num_faces
        np.testing.assert_allclose(mesh.vertices, person.vertices, atol=1e-5)
        assert mesh.texture.shape == person.texture.shape
        assert np.abs(mesh.texture.astype(int) - person.texture).mean() < 4  # JPEG
    # another mesh in the folder: the one named like its folder (NNNN/NNNN.obj) wins
    save_obj(person, scan_dir, "extra")
    assert find_mesh_file(scan_dir) == scan_dir / "0001.obj"


def test_procedural_obj_round_trip(tmp_path):
    person = make_person(segments=16)
    obj = write_person(tmp_path, segments=16)
    assert {p.name for p in tmp_path.iterdir()} == {"person.obj", "person.mtl", "person.png"}
    mesh = load_scan(obj)
    np.testing.assert_allclose(mesh.vertices, person.vertices, atol=1e-5)
    np.testing.assert_allclose(mesh.uvs, person.uvs, atol=1e-5)
    np.testing.assert_array_equal(mesh.texture, person.texture)
    np.testing.assert_allclose(extent(person)[1], 1.705, atol=0.01)


def test_vertex_colour_scan_round_trip(tmp_path):
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=1)
    colors = np.tile(np.array([[0.2, 0.6, 0.8]], np.float32), (len(sphere.vertices), 1))
    save_obj(TexturedMesh(sphere.vertices, sphere.faces, vertex_colors=colors), tmp_path, "ball")
    mesh = load_scan(tmp_path)
    assert mesh.texture is None and mesh.num_faces == len(sphere.faces)
    np.testing.assert_allclose(mesh.vertex_colors, colors, atol=1 / 255)


def _sample_nearest(texture: np.ndarray, uv: np.ndarray) -> np.ndarray:
    h, w = texture.shape[:2]
    col = np.clip((uv[:, 0] * w).astype(int), 0, w - 1)
    row = np.clip(((1.0 - uv[:, 1]) * h).astype(int), 0, h - 1)
    return texture[row, col]


def test_merge_packs_distinct_textures_into_an_atlas():
    rng = np.random.default_rng(3)
    quad_v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float32)
    quad_f = np.array([[0, 1, 2], [0, 2, 3]])
    parts, uvs = [], []
    for _ in range(2):
        tex = rng.integers(0, 255, (32, 32, 3), dtype=np.uint8)
        uv = rng.uniform(0.05, 0.95, (4, 2)).astype(np.float32)
        parts.append(TexturedMesh(quad_v, quad_f, uvs=uv, texture=tex))
        uvs.append(uv)
    parts.append(TexturedMesh(quad_v + 2, quad_f, vertex_colors=np.full((4, 3), 0.5, np.float32)))
    merged = merge_meshes(parts)
    assert merged.num_faces == 6 and len(merged.vertices) == 12
    for i in range(2):  # textured parts sample the same texels as before
        np.testing.assert_array_equal(_sample_nearest(merged.texture, merged.uvs[4 * i:4 * i + 4]),
                                      _sample_nearest(parts[i].texture, uvs[i]))
    # the colour-only part points at a white tile and keeps its colour
    np.testing.assert_array_equal(_sample_nearest(merged.texture, merged.uvs[8:]), 255)
    np.testing.assert_allclose(merged.vertex_colors[8:], 0.5)
    np.testing.assert_allclose(merged.vertex_colors[:8], 1.0)


def test_normalization_transform_and_framing_radius():
    person = make_person(segments=8)
    m = normalization_transform(person, height=2.0, yaw_deg=90.0)
    turned = person.transformed(m)
    np.testing.assert_allclose(extent(turned)[1], 2.0, rtol=1e-6)
    np.testing.assert_allclose(extent(turned)[[2, 0]], extent(person)[[0, 2]] * 2.0 / extent(person)[1], rtol=1e-5)
    r = framing_radius(1.7, 33.8, 0.85)
    np.testing.assert_allclose(2 * r * np.tan(np.radians(33.8 / 2)) * 0.85, 1.7)


@pytest.mark.parametrize("content, name, message", [
    (None, None, "no mesh"),
    (b"just some text\n", "notes.txt", "not a mesh file"),
    (b"hello world\n", "scan.obj", "no triangle mesh"),
    (b"v 0 0 0\nv 1 0 0\n", "points.obj", "no triangle mesh"),
    (b"glTF garbage bytes", "scan.glb", "cannot read mesh"),
])
def test_bad_inputs_raise_input_error(tmp_path, content, name, message):
    target = tmp_path
    if content is not None:
        target = tmp_path / name
        target.write_bytes(content)
    with pytest.raises(InputError, match=message):
        load_scan(target)
    with pytest.raises(InputError, match="does not exist"):
        load_scan(tmp_path / "missing")


def test_two_meshes_in_a_folder_is_an_error(tmp_path):
    person = make_person(segments=8)
    save_obj(person, tmp_path, "a")
    save_obj(person, tmp_path, "b")
    with pytest.raises(InputError, match="2 meshes"):
        load_scan(tmp_path)

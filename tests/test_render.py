"""The rasterizer's camera convention, depth/normal layers, the SV3D orbit, and the render stage."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from humanvdm_core.cameras import Cameras, look_at, orbit_cameras
from humanvdm_core.render import render_views
from humanvdm_core.scans import TexturedMesh, framing_radius, load_scan, normalization_transform
from testdata.procedural import (
    BACK_TORSO_COLORS,
    FRONT_TORSO_COLORS,
    LEFT_ARM,
    make_person,
    write_person,
)

REPO = Path(__file__).resolve().parents[1]
SOLDIER = REPO.parent / "shared" / "fixtures" / "scans" / "threejs_soldier" / "Soldier.glb"


def project(cameras: Cameras, i: int, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (u, v) and camera z of world points: K @ (w2c @ X)."""
    cam = points @ cameras.w2c[i][:3, :3].T + cameras.w2c[i][:3, 3]
    uvw = cam @ cameras.K[i].T
    return uvw[:, :2] / uvw[:, 2:], cam[:, 2]


def one_camera(K: np.ndarray, eye, width: int, height: int) -> Cameras:
    return Cameras(K[None], look_at(np.asarray(eye, float))[None], width, height,
                   np.zeros(1), np.zeros(1), np.ones(1))


def test_triangle_projects_where_K_and_w2c_say():
    """Coverage area and centroid, depth and normals of one triangle match the analytic projection."""
    K = np.array([[150.0, 0.0, 70.3], [0.0, 140.0, 55.7], [0.0, 0.0, 1.0]])  # off-centre, fx != fy
    cams = one_camera(K, (0.4, 0.3, 2.5), 160, 120)
    tri = np.array([[-0.5, -0.3, 0.1], [0.6, -0.2, -0.2], [0.1, 0.5, 0.0]])
    mesh = TexturedMesh(tri, [[0, 1, 2]], vertex_colors=np.ones((3, 3)))
    res = render_views(mesh, cams, background=(0.0, 0.0, 0.0))
    alpha, depth, normals = res.alpha[0], res.depth[0], res.normals[0]

    uv, _ = project(cams, 0, tri)
    (x0, y0), (x1, y1), (x2, y2) = uv
    area = 0.5 * abs((x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0))
    rows, cols = np.mgrid[0:120, 0:160]
    centres = np.stack([cols + 0.5, rows + 0.5], axis=-1)  # pixel centres at integer + 0.5
    assert area > 1000
    np.testing.assert_allclose(alpha.sum(), area, rtol=0.01)
    centroid = (alpha[..., None] * centres).sum(axis=(0, 1)) / alpha.sum()
    np.testing.assert_allclose(centroid, uv.mean(axis=0), atol=0.05)  # a half-pixel slip would be 0.5

    # depth: the triangle's plane hit by each full pixel's centre ray
    w2c = cams.w2c[0]
    cam_tri = tri @ w2c[:3, :3].T + w2c[:3, 3]
    n_cam = np.cross(cam_tri[1] - cam_tri[0], cam_tri[2] - cam_tri[0])
    rays = np.concatenate([centres, np.ones((120, 160, 1))], axis=-1) @ np.linalg.inv(K).T  # z = 1
    z_true = n_cam.dot(cam_tri[0]) / (rays @ n_cam)
    full = alpha == 1.0
    assert full.sum() > 800
    np.testing.assert_allclose(depth[full], z_true[full], rtol=1e-4)
    assert (depth[alpha == 0] == 0).all() and (normals[alpha == 0] == 0).all()

    # normals: the face normal in world space, turned towards the camera
    n_world = np.cross(tri[1] - tri[0], tri[2] - tri[0])
    n_world /= np.linalg.norm(n_world)
    if n_world.dot(cams.c2w[0][:3, 3] - tri[0]) < 0:
        n_world = -n_world
    np.testing.assert_allclose(normals[full], np.broadcast_to(n_world, normals[full].shape), atol=1e-4)
    assert ((alpha > 0) & (alpha < 1)).any(), "antialiased edges"


def test_texture_orientation_front_quad():
    """UV (0, 1) is the image's top-left; the front camera sees +X on the image's right."""
    quadrants = np.array([[[255, 0, 0], [0, 255, 0]], [[0, 0, 255], [255, 255, 255]]], dtype=np.uint8)
    texture = np.repeat(np.repeat(quadrants, 16, axis=0), 16, axis=1)  # 32x32, 16x16 blocks
    verts = np.array([[-0.5, -0.5, 0.0], [0.5, -0.5, 0.0], [0.5, 0.5, 0.0], [-0.5, 0.5, 0.0]])
    uvs = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    mesh = TexturedMesh(verts, [[0, 1, 2], [0, 2, 3]], uvs=uvs, texture=texture)
    cams = orbit_cameras(num_frames=1, size=64, elevation_deg=0.0, radius=2.0)  # azimuth 0: on +Z
    rgb = render_views(mesh, cams).rgba[0, ..., :3]
    for world, colour in [((-0.25, 0.25), (1, 0, 0)), ((0.25, 0.25), (0, 1, 0)),
                          ((-0.25, -0.25), (0, 0, 1)), ((0.25, -0.25), (1, 1, 1))]:
        (u, v), = project(cams, 0, np.array([[*world, 0.0]]))[0]
        np.testing.assert_allclose(rgb[int(v), int(u)], colour, atol=0.02, err_msg=f"at world {world}")


def test_sphere_depth_and_normals_are_consistent():
    import trimesh

    ball = trimesh.creation.icosphere(subdivisions=4, radius=0.5)
    mesh = TexturedMesh(ball.vertices, ball.faces, vertex_colors=np.full((len(ball.vertices), 3), 0.3))
    cams = orbit_cameras(num_frames=3, size=96, radius=2.0)
    bg = (0.1, 0.7, 0.2)
    res = render_views(mesh, cams, background=bg)
    for i in range(len(cams)):
        alpha, depth, normals = res.alpha[i], res.depth[i], res.normals[i]
        empty, full = alpha == 0, alpha == 1
        np.testing.assert_allclose(res.rgba[i][empty][:, :3], np.broadcast_to(bg, (empty.sum(), 3)), atol=1e-6)
        assert (depth[empty] == 0).all() and (normals[empty] == 0).all()
        np.testing.assert_allclose(np.linalg.norm(normals[full], axis=-1), 1.0, atol=1e-4)
        assert 1.49 < depth[full].min() < 1.52 and depth[full].max() < 2.0
        # back-project each full pixel with its depth: the point lies on the sphere, its normal radial
        # (away from the silhouette: there a pixel's depth averages a steep slope)
        inner = full.copy()
        for _ in range(2):
            inner[1:-1, 1:-1] &= inner[:-2, 1:-1] & inner[2:, 1:-1] & inner[1:-1, :-2] & inner[1:-1, 2:]
        v, u = np.nonzero(inner)
        rays = np.stack([u + 0.5, v + 0.5, np.ones_like(u, float)], axis=1) @ np.linalg.inv(cams.K[i]).T
        cam_pts = rays * depth[inner][:, None]
        world = cam_pts @ cams.c2w[i][:3, :3].T + cams.c2w[i][:3, 3]
        np.testing.assert_allclose(np.linalg.norm(world, axis=1), 0.5, atol=0.003)
        cos = (normals[inner] * world / np.linalg.norm(world, axis=1, keepdims=True)).sum(axis=1)
        assert cos.min() > 0.995
        assert ((alpha > 0) & (alpha < 1)).sum() > 50  # soft silhouette


def _colour_fraction(patch: np.ndarray, colour) -> float:
    return float((np.abs(patch * 255.0 - np.asarray(colour)).max(axis=-1) < 40).mean())


def test_procedural_person_in_the_sv3d_orbit():
    """21 frames at 576^2; the last (azimuth 0) is the front view, frame 10 (azimuth 188.6) about the back."""
    person = make_person()
    world_from_scan = normalization_transform(person)
    mesh = person.transformed(world_from_scan)
    cams = orbit_cameras(radius=framing_radius())
    assert len(cams) == 21 and cams.width == cams.height == 576
    assert cams.azimuth_deg[-1] == 0.0 and abs(cams.azimuth_deg[10] - 180.0) < 10.0
    res = render_views(mesh, cams, background=(0.5, 0.5, 0.5))
    assert res.rgba.shape == (21, 576, 576, 4) and res.rgba.dtype == np.float32

    def patch(frame: int, raw_point, half: int = 12) -> np.ndarray:
        world = world_from_scan[:3, :3] @ np.asarray(raw_point) + world_from_scan[:3, 3]
        (u, v), = project(cams, frame, world[None])[0]
        return res.rgba[frame, int(v) - half:int(v) + half, int(u) - half:int(u) + half, :3]

    chest = (0.0, 1.15, 0.11)
    front, back = patch(20, chest), patch(10, (0.0, 1.15, -0.11))
    assert _colour_fraction(front, FRONT_TORSO_COLORS[0]) > 0.2 and _colour_fraction(front, FRONT_TORSO_COLORS[1]) > 0.2
    assert _colour_fraction(front, BACK_TORSO_COLORS[0]) == 0.0
    assert _colour_fraction(back, BACK_TORSO_COLORS[0]) > 0.2 and _colour_fraction(back, FRONT_TORSO_COLORS[0]) == 0.0
    # the subject's left arm (+X) is green and on the image's right in the front view
    arm_raw = np.array([0.25, 1.1, 0.015])
    assert _colour_fraction(patch(20, arm_raw, half=3), LEFT_ARM) > 0.5
    arm_world = world_from_scan[:3, :3] @ arm_raw + world_from_scan[:3, 3]
    assert project(cams, 20, arm_world[None])[0][0, 0] > 288
    # eyes: dark pixels on the face in the front view only
    eyes_front, eyes_back = patch(20, (0.0, 1.6, 0.1), half=20), patch(10, (0.0, 1.6, -0.1), half=20)
    assert (eyes_front.max(axis=-1) < 0.15).sum() > 20 and (eyes_back.max(axis=-1) < 0.15).sum() == 0
    # framing: the subject spans about `fill` of the frame height at the front view
    rows = np.nonzero(res.alpha[20].max(axis=1) > 0)[0]
    assert 0.8 * 576 < rows.max() - rows.min() + 1 < 0.95 * 576
    # every vertex lands on covered pixels, at or behind the visible surface (pixel-averaged depth)
    for frame in (0, 20):
        uv, z = project(cams, frame, mesh.vertices.astype(np.float64))
        cols, rows_ = uv[:, 0].astype(int), uv[:, 1].astype(int)
        assert (res.alpha[frame][rows_, cols] > 0).mean() > 0.99
        seen = res.alpha[frame][rows_, cols] == 1
        excess = res.depth[frame][rows_, cols][seen] - z[seen]  # > 0 only from averaging a steep pixel
        assert excess.max() < 0.03 and (excess < 0.005).mean() > 0.98


def test_yaw_turns_the_scan():
    person = make_person(segments=16)
    cams = orbit_cameras(num_frames=2, size=64, radius=framing_radius())  # azimuths 180, 0
    plain = render_views(person.transformed(normalization_transform(person)), cams)
    turned = render_views(person.transformed(normalization_transform(person, yaw_deg=180.0)), cams)
    assert np.abs(turned.rgba[1] - plain.rgba[0]).mean() < 2e-3
    assert np.abs(turned.rgba[0] - plain.rgba[0]).mean() > 2e-2


@pytest.mark.fixtures
def test_soldier_renders_upright():
    if not SOLDIER.exists():
        pytest.skip(f"fixture not present: {SOLDIER}")
    scan = load_scan(SOLDIER)
    mesh = scan.transformed(normalization_transform(scan, yaw_deg=180.0))  # it faces -Z
    res = render_views(mesh, orbit_cameras(num_frames=1, size=96, radius=framing_radius()))
    alpha = res.alpha[0]
    rows, cols = np.nonzero(alpha > 0)
    assert rows.max() - rows.min() > 0.8 * 96 and cols.max() - cols.min() > 0.6 * 96  # T-pose
    assert 0.1 < alpha.mean() < 0.5


# ----------------------------------------------------------------------------- the stage

def run_stage(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "stages.render_training_orbits", *args],
                          cwd=REPO, capture_output=True, text=True, timeout=120)


@pytest.fixture(scope="module")
def person_dir(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("scan")
    write_person(folder, segments=24)
    return folder


def test_stage_writes_the_frame_set_deterministically(tmp_path, person_dir):
    from humanvdm_core.frames import read_cameras, read_frames
    from humanvdm_core.io import read_exr

    args = ["--scan", str(person_dir), "--resolution", "48", "--num-frames", "3", "--seed", "7"]
    a, b = tmp_path / "a", tmp_path / "b"
    for out in (a, b):
        proc = run_stage(*args, "--out-orbit", str(out))
        assert proc.returncode == 0, proc.stderr
    files = sorted(p.relative_to(a).as_posix() for p in a.rglob("*") if p.is_file())
    assert files == ["cameras.npz"] + [f"{layer}/{i:04d}.exr" for layer in ("depth", "frames", "normals")
                                       for i in range(3)]
    for name in files:
        assert (a / name).read_bytes() == (b / name).read_bytes(), f"{name} differs between identical runs"

    cams = read_cameras(a)
    np.testing.assert_allclose(cams.azimuth_deg, [120.0, 240.0, 0.0])
    assert cams.width == 48 and cams.K.shape == (3, 3, 3)
    expected_bg = np.random.default_rng(7).uniform(0.0, 1.0, 3)
    np.testing.assert_allclose(cams.extra["background"], expected_bg)
    assert cams.extra["world_from_scan"].shape == (4, 4)
    frames = read_frames(a)
    assert frames.shape == (3, 48, 48, 4)
    empty = frames[..., 3] == 0
    np.testing.assert_allclose(frames[empty][:, :3], np.broadcast_to(expected_bg, (empty.sum(), 3)), atol=2e-3)
    assert read_frames(a, "depth").shape == (3, 48, 48, 1) and read_frames(a, "normals").shape == (3, 48, 48, 3)
    _, attrs = read_exr(a / "frames" / "0000.exr", with_attrs=True)
    assert attrs["humanvdm:stage"] == "render-training-orbits" and attrs["channels"] == ["R", "G", "B", "A"]


def test_stage_accepts_a_mesh_file_and_a_named_background(tmp_path, person_dir):
    from humanvdm_core.frames import read_cameras

    proc = run_stage("--scan", str(person_dir / "person.obj"), "--out-orbit", str(tmp_path / "o"),
                     "--resolution", "32", "--num-frames", "1", "--background", "white")
    assert proc.returncode == 0, proc.stderr
    np.testing.assert_allclose(read_cameras(tmp_path / "o").extra["background"], [1.0, 1.0, 1.0])


@pytest.mark.parametrize("make_input, extra, message", [
    (lambda d: d, [], "no mesh"),
    (lambda d: (d / "notes.txt", (d / "notes.txt").write_text("hi"))[0], [], "not a mesh file"),
    (lambda d: (d / "scan.obj", (d / "scan.obj").write_text("hello\n"))[0], [], "no triangle mesh"),
    (lambda d: d, ["--background", "purple"], "param background"),
])
def test_stage_bad_inputs_exit_3(tmp_path, make_input, extra, message):
    scan = tmp_path / "scan"
    scan.mkdir()
    proc = run_stage("--scan", str(make_input(scan)), "--out-orbit", str(tmp_path / "out"), *extra)
    assert proc.returncode == 3, proc.stderr
    assert message in proc.stderr and "Traceback" not in proc.stderr


def test_renderers_coexist_and_are_deterministic():
    from humanvdm_core.render import Renderer

    mesh = make_person(segments=12)
    mesh = mesh.transformed(normalization_transform(mesh))
    cams = orbit_cameras(num_frames=2, size=40, radius=framing_radius())
    first = Renderer()
    before = first.render(mesh, cams)
    other = Renderer(samples=2)
    two = other.render(mesh, cams)
    other.release()  # must not disturb the first renderer's context
    after = first.render(mesh, cams)
    first.release()
    np.testing.assert_array_equal(before.rgba, after.rgba)
    np.testing.assert_array_equal(before.depth, after.depth)
    assert set(np.unique(two.alpha)) <= {0.0, 0.5, 1.0}

"""``humanvdm view RUN|PLY``: look around a result in a browser (an interactive 3D viewer built on viser).

What it shows, in our world's axes (y up, the subject facing +z, metres), each a toggle:

- the Gaussians (``splat-optimize/gaussians/gaussians.npz``, or a ``point_cloud.ply`` / ``.splat`` in the
  axes its header states, 3DGS's y-down when it states none);
- the fitted body (``fit-smpl/body/body.npz``: ``vertices``, ``faces``);
- the clothed proxy the ``body-prior`` orbit was rendered from (``diffuse/orbit/proxy.npz``), when there is one;
- the orbit cameras (``diffuse/orbit`` or ``render-training-orbits/orbit``) as frustums showing their frames.

``RUN`` is a run's name in the store (``artifacts/runs/<name>``), a run folder, a ``gaussians`` artifact
folder or a PLY / ``.splat`` file (the run around a PLY inside a run folder is found too). The viewer is
viser (nerfstudio's; ``pip install 'humanvdm[viewer]'``): it renders the Gaussians itself with WebGL in
the browser, sorted per frame; nothing here draws pixels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from humanvdm_core.workflow.errors import HumanVDMError, InputError

ORBIT_FOLDERS = ("diffuse/orbit", "render-training-orbits/orbit")
THUMB_PX = 128


@dataclass
class ViewScene:
    """What the viewer shows (arrays in our world's axes)."""

    title: str
    means: np.ndarray
    quats: np.ndarray  # wxyz
    scales: np.ndarray
    opacities: np.ndarray
    colors: np.ndarray  # sRGB [0, 1]
    body: tuple[np.ndarray, np.ndarray] | None = None  # vertices, faces
    proxy: tuple[np.ndarray, np.ndarray, np.ndarray | None] | None = None  # vertices, faces, vertex colours
    cameras: object | None = None  # humanvdm_core.cameras.Cameras
    thumbnails: list[np.ndarray] = field(default_factory=list)
    sources: dict[str, str] = field(default_factory=dict)

    @property
    def centre(self) -> np.ndarray:
        """The middle of the Gaussians' extent (robust to a few strays)."""
        lo, hi = np.percentile(self.means, [0.5, 99.5], axis=0)
        return (lo + hi) / 2

    @property
    def height(self) -> float:
        lo, hi = np.percentile(self.means[:, 1], [0.5, 99.5])
        return float(max(hi - lo, 1e-3))


def resolve(target: str, store_root: Path) -> tuple[Path | None, Path | None, Path | None]:
    """(run folder, gaussians folder, splat file) for ``target`` (see the module docstring)."""
    path = Path(target).expanduser()
    if path.is_file():
        if path.suffix.lower() not in (".ply", ".splat"):
            raise InputError(f"{path}: expected a .ply or .splat file, a run folder or a run name")
        run = path.parent.parent.parent if path.parent.parent.name == "splat-optimize" else None
        return run, None, path
    if path.is_dir():
        if (path / "gaussians.npz").is_file():
            run = path.parent.parent if path.parent.name == "splat-optimize" else None
            return run, path, None
        if (path / "splat-optimize" / "gaussians").is_dir():
            return path, path / "splat-optimize" / "gaussians", None
        raise InputError(f"{path}: no Gaussians here (no gaussians.npz, no splat-optimize/gaussians)")
    run = store_root / "runs" / str(target)
    if (run / "splat-optimize" / "gaussians").is_dir():
        return run, run / "splat-optimize" / "gaussians", None
    runs = sorted(p.parent.parent.name for p in (store_root / "runs").glob("*/splat-optimize/gaussians"))
    raise HumanVDMError(f"{target!r}: not a file, a folder or a run with Gaussians in {store_root / 'runs'}"
                        + (f" (runs with Gaussians: {', '.join(runs)})" if runs else " (none has Gaussians yet)"))


def load_scene(target: str, store_root: Path) -> ViewScene:
    from humanvdm_core.splat import human as H

    run, gdir, file = resolve(target, store_root)
    if gdir is not None and not (gdir / "gaussians.npz").is_file() and (gdir / "point_cloud.ply").is_file():
        gdir, file = None, gdir / "point_cloud.ply"
    sources: dict[str, str] = {}
    if file is not None:
        if file.suffix.lower() == ".splat":  # stored in the 3DGS axes, like the PLY by default
            g = H.read_splat(file)
            g["means"], g["quats"] = H.to_axes(g["means"], g["quats"], "y-down", inverse=True)
        else:
            g = H.read_ply(file)
        sources["gaussians"] = str(file)
    else:
        from humanvdm_core.evaluate import load_gaussians

        g = load_gaussians(gdir)
        sources["gaussians"] = str(gdir / "gaussians.npz")
    scene = ViewScene(title=(run.name if run is not None else (file or gdir).name),
                      means=np.asarray(g["means"], np.float32), quats=np.asarray(g["quats"], np.float32),
                      scales=np.asarray(g["scales"], np.float32),
                      opacities=np.asarray(g["opacities"], np.float32).reshape(-1),
                      colors=np.clip(np.asarray(g["colors"], np.float32), 0, 1), sources=sources)
    if run is None:
        return scene
    body = run / "fit-smpl" / "body" / "body.npz"
    if body.is_file():
        with np.load(body, allow_pickle=False) as z:
            if "vertices" in z.files and "faces" in z.files:
                scene.body = (z["vertices"].astype(np.float32), z["faces"].astype(np.int32))
                sources["body"] = str(body)
    for rel in ORBIT_FOLDERS:
        orbit = run / rel
        if not (orbit / "cameras.npz").is_file():
            continue
        proxy = orbit / "proxy.npz"
        if proxy.is_file():
            with np.load(proxy, allow_pickle=False) as z:
                colors = z["vertex_colors"] if "vertex_colors" in z.files else None
                scene.proxy = (z["vertices"].astype(np.float32), z["faces"].astype(np.int32), colors)
            sources["proxy"] = str(proxy)
        scene.cameras, scene.thumbnails = _orbit(orbit)
        sources["orbit"] = str(orbit)
        break
    return scene


def _orbit(root: Path):
    import cv2

    from humanvdm_core.frames import open_frame_set, read_frame

    paths, cams = open_frame_set(root)
    bg = np.asarray(cams.extra.get("background", np.ones(3)), np.float32).reshape(3)
    thumbs = []
    for p in paths:
        rgba = read_frame(p)
        rgb = rgba[..., :3] * rgba[..., 3:4] + bg * (1 - rgba[..., 3:4]) if rgba.shape[-1] == 4 else rgba[..., :3]
        s = THUMB_PX / max(rgb.shape[:2])
        small = cv2.resize(np.ascontiguousarray(rgb, np.float32), (max(1, round(rgb.shape[1] * s)),
                                                                    max(1, round(rgb.shape[0] * s))),
                           interpolation=cv2.INTER_AREA)
        thumbs.append(np.clip(np.rint(small * 255), 0, 255).astype(np.uint8))
    return cams, thumbs


def covariances(quats: np.ndarray, scales: np.ndarray) -> np.ndarray:
    """(M, 3, 3) ``R diag(s^2) R^T`` from unit wxyz quaternions and linear scales."""
    q = np.asarray(quats, np.float64)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    R = np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], 1)
    s2 = np.asarray(scales, np.float64) ** 2
    return (R * s2[:, None, :]) @ np.swapaxes(R, 1, 2)


def _rot_to_wxyz(R: np.ndarray) -> np.ndarray:
    import viser.transforms as vtf

    return vtf.SO3.from_matrix(np.asarray(R, np.float64)).wxyz


LAYERS = ("gaussians", "body", "proxy", "cameras", "grid")


def serve(scene: ViewScene, host: str = "127.0.0.1", port: int = 8080, show: tuple[str, ...] = ("gaussians",)):
    """Start the viser server with ``scene``, the layers in ``show`` visible (:data:`LAYERS`); returns it
    (the caller keeps the process alive)."""
    unknown = set(show) - set(LAYERS)
    if unknown:
        raise HumanVDMError(f"--show: unknown layer(s) {sorted(unknown)}; choose from {list(LAYERS)}")
    try:
        import trimesh
        import viser
    except ImportError as e:
        raise HumanVDMError(f"the viewer needs viser ({e.name} is missing): pip install 'humanvdm[viewer]'") from None

    server = viser.ViserServer(host=host, port=port, label=f"Human-VDM: {scene.title}", verbose=False)
    server.scene.set_up_direction("+y")
    handles: dict[str, list] = {"gaussians": [], "body": [], "proxy": [], "cameras": [], "grid": []}
    handles["gaussians"].append(server.scene.add_gaussian_splats(
        "/gaussians", centers=scene.means, covariances=covariances(scene.quats, scene.scales).astype(np.float32),
        rgbs=scene.colors, opacities=scene.opacities[:, None], visible="gaussians" in show))
    centre, height = scene.centre, scene.height
    floor = float(np.percentile(scene.means[:, 1], 0.5))
    handles["grid"].append(server.scene.add_grid("/grid", width=4 * height, height=4 * height, plane="xz",
                                                 position=(float(centre[0]), floor, float(centre[2])),
                                                 cell_size=0.1 * height, section_size=0.5 * height,
                                                 visible="grid" in show))
    if scene.body is not None:
        handles["body"].append(server.scene.add_mesh_simple(
            "/body", scene.body[0], scene.body[1], color=(120, 170, 235), opacity=0.7, visible="body" in show))
    if scene.proxy is not None:
        v, f, c = scene.proxy
        colors = None
        if c is not None:
            c = np.asarray(c)
            colors = c if c.dtype == np.uint8 else np.clip(np.rint(c * 255), 0, 255).astype(np.uint8)
        handles["proxy"].append(server.scene.add_mesh_trimesh(
            "/proxy", trimesh.Trimesh(v, f, vertex_colors=colors, process=False), visible="proxy" in show))
    cams = scene.cameras
    if cams is not None:
        for i in range(len(cams)):
            K, c2w = cams.K[i], cams.c2w[i]
            fov = 2 * math.atan(0.5 * cams.height / K[1, 1])
            thumb = scene.thumbnails[i] if i < len(scene.thumbnails) else None
            handles["cameras"].append(server.scene.add_camera_frustum(
                f"/cameras/{i:03d}", fov=fov, aspect=cams.width / cams.height, scale=0.09 * height,
                image=thumb, wxyz=_rot_to_wxyz(c2w[:3, :3]), position=c2w[:3, 3], color=(230, 120, 30),
                visible="cameras" in show))

    with server.gui.add_folder("Show"):
        for key, label in (("gaussians", "Gaussians"), ("body", "fitted body"), ("proxy", "clothed proxy"),
                           ("cameras", "orbit cameras + frames"), ("grid", "floor grid")):
            box = server.gui.add_checkbox(label, initial_value=key in show and bool(handles[key]),
                                          disabled=not handles[key])

            @box.on_update
            def _(event, key=key, box=box) -> None:
                for h in handles[key]:
                    h.visible = box.value
    server.gui.add_markdown(f"**{scene.title}**: {len(scene.means):,} Gaussians. Axes: y up, metres. "
                            "Drag to orbit, scroll to zoom, right-drag to pan.")

    # start in front of the subject, as the orbit's input view (azimuth 0) sees it
    fov, elevation = math.radians(33.8), 0.0
    distance = 1.5 * height / (2 * math.tan(fov / 2))
    if cams is not None:
        front = int(np.argmin(np.abs((np.asarray(cams.azimuth_deg) + 180) % 360 - 180)))
        fov = 2 * math.atan(0.5 * cams.height / cams.K[front][1, 1])
        elevation = math.radians(float(cams.elevation_deg[front]))
        distance = max(distance, float(np.linalg.norm(cams.c2w[front][:3, 3] - centre)))
    server.initial_camera.fov = fov
    server.initial_camera.look_at = tuple(float(v) for v in centre)
    server.initial_camera.position = (float(centre[0]), float(centre[1] + distance * math.sin(elevation)),
                                      float(centre[2] + distance * math.cos(elevation)))
    server.initial_camera.up = (0.0, 1.0, 0.0)
    return server


def run_viewer(target: str, store_root: Path, host: str = "127.0.0.1", port: int = 8080,
               show: tuple[str, ...] = ("gaussians",)) -> int:
    """``humanvdm view``: serve until Ctrl-C."""
    import time

    scene = load_scene(target, store_root)
    server = serve(scene, host, port, show)
    actual = server.get_port()
    shown = "localhost" if host in ("127.0.0.1", "0.0.0.0", "localhost") else host
    print(f"viewer of {scene.title}: http://{shown}:{actual}   (Ctrl-C to stop)")
    for k, v in scene.sources.items():
        print(f"  {k}: {v}")
    missing = [k for k in ("body", "orbit") if k not in scene.sources]
    if missing:
        print(f"  (not found: {', '.join(missing)})")
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        pass
    finally:
        server.stop()
    return 0

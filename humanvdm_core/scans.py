"""Textured scans: load OBJ / glTF / GLB / PLY scans into one :class:`TexturedMesh`, normalise them.

Contract:

- :class:`TexturedMesh` is one triangle mesh with one texture. Surface colour (unlit albedo,
  sRGB-encoded values used as they are) = ``texture(uv) * vertex_colors``; either factor may be
  absent (= white). ``uvs`` follow the OBJ/OpenGL convention (origin at the bottom-left of the
  image, v up); ``texture`` rows are stored top row first, as images are.
- :func:`load_scan` accepts an OBJ (+MTL + texture), GLB/glTF, or PLY file, or a folder holding
  exactly one of them anywhere below it (the THuman2.0 layout ``NNNN/NNNN.obj`` + ``material0.mtl``
  + ``material0.jpeg`` is one such folder; when a folder holds several meshes, the one named like
  its own folder wins). All meshes of a file are merged with their scene transforms; several
  textures are packed into one atlas. Skinned glTF meshes are taken in their bind pose (glTF
  ignores a skinned mesh node's transform). Colour factors (OBJ ``Kd``, glTF ``baseColorFactor``)
  are ignored when a texture is present and used as the colour when there is none; texture alpha
  is ignored; a mesh with neither texture nor colours gets :data:`UNCOLORED_GRAY`.
  Unusable input raises :class:`humanvdm_core.workflow.errors.InputError`.
- :func:`normalize_scan` centres the bounding box at the origin and scales the vertical (Y)
  extent to ``height`` world units (default :data:`DEFAULT_SUBJECT_HEIGHT` = 1.7, about a
  person's height in metres, so body models fit at their natural scale). Scans are expected Y up,
  facing +Z (the orbit-camera convention of :mod:`humanvdm_core.cameras`); ``yaw_deg`` turns one
  that faces elsewhere (e.g. 180 for the three.js Soldier, which faces -Z).
  :func:`normalization_transform` gives the same mapping as a 4x4 ``world_from_scan`` matrix.
- :func:`framing_radius` is the orbit radius at which a subject of that height spans ``fill`` of
  the frame height at elevation 0: ``radius = height / (2 * fill * tan(fov_y / 2))`` (the subject's
  depth makes it appear slightly larger than ``fill``; the default 0.85 leaves room for that).
"""

from __future__ import annotations

import hashlib
import json
import logging
import struct
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from humanvdm_core.io import write_png
from humanvdm_core.workflow.atomic import atomic_write_bytes, atomic_write_text
from humanvdm_core.workflow.errors import InputError

MESH_SUFFIXES = (".obj", ".glb", ".gltf", ".ply")
DEFAULT_SUBJECT_HEIGHT = 1.7
DEFAULT_FILL = 0.85
ATLAS_MAX_SIZE = 8192
UNCOLORED_GRAY = 0.7  # albedo of a mesh with neither texture nor colours
_ATLAS_PAD = 4

log = logging.getLogger("humanvdm.scans")


@dataclass
class TexturedMesh:
    """A triangle mesh with per-vertex UVs into one RGB texture and/or per-vertex colours."""

    vertices: np.ndarray  # (V, 3) float32
    faces: np.ndarray  # (F, 3) int32
    uvs: np.ndarray | None = None  # (V, 2) float32, origin bottom-left of the image
    texture: np.ndarray | None = None  # (H, W, 3) uint8 RGB, top row first
    vertex_colors: np.ndarray | None = None  # (V, 3) float32 in [0, 1], multiplies the texture

    def __post_init__(self) -> None:
        self.vertices = np.ascontiguousarray(self.vertices, dtype=np.float32)
        self.faces = np.ascontiguousarray(self.faces, dtype=np.int32)
        n = len(self.vertices)
        if self.vertices.ndim != 2 or self.vertices.shape[1] != 3:
            raise ValueError(f"vertices must be (V, 3), got {self.vertices.shape}")
        if self.faces.ndim != 2 or self.faces.shape[1] != 3:
            raise ValueError(f"faces must be (F, 3), got {self.faces.shape}")
        if self.faces.size and (self.faces.min() < 0 or self.faces.max() >= n):
            raise ValueError("faces index vertices out of range")
        if (self.uvs is None) != (self.texture is None):
            raise ValueError("uvs and texture come together")
        if self.uvs is not None:
            self.uvs = np.ascontiguousarray(self.uvs, dtype=np.float32)
            if self.uvs.shape != (n, 2):
                raise ValueError(f"uvs must be ({n}, 2), got {self.uvs.shape}")
            self.texture = np.ascontiguousarray(self.texture, dtype=np.uint8)
            if self.texture.ndim != 3 or self.texture.shape[2] != 3:
                raise ValueError(f"texture must be (H, W, 3) uint8, got {self.texture.shape}")
        if self.vertex_colors is not None:
            self.vertex_colors = np.ascontiguousarray(self.vertex_colors, dtype=np.float32)
            if self.vertex_colors.shape != (n, 3):
                raise ValueError(f"vertex_colors must be ({n}, 3), got {self.vertex_colors.shape}")

    @property
    def num_faces(self) -> int:
        return len(self.faces)

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3): min and max corner of the bounding box."""
        return np.stack([self.vertices.min(axis=0), self.vertices.max(axis=0)])

    def transformed(self, matrix: np.ndarray) -> TexturedMesh:
        """A copy with vertices mapped by a 4x4 affine ``matrix``: ``v' = matrix[:3, :3] @ v + matrix[:3, 3]``."""
        m = np.asarray(matrix, dtype=np.float64)
        v = self.vertices.astype(np.float64) @ m[:3, :3].T + m[:3, 3]
        return replace(self, vertices=v.astype(np.float32))


# ----------------------------------------------------------------------------- normalisation

def yaw_matrix(yaw_deg: float) -> np.ndarray:
    """4x4 rotation about +Y by ``yaw_deg`` (right-handed: +Z turns towards +X)."""
    a = np.radians(yaw_deg)
    m = np.eye(4)
    m[0, 0], m[0, 2], m[2, 0], m[2, 2] = np.cos(a), np.sin(a), -np.sin(a), np.cos(a)
    return m


def normalization_transform(mesh: TexturedMesh, height: float = DEFAULT_SUBJECT_HEIGHT,
                            yaw_deg: float = 0.0) -> np.ndarray:
    """4x4 ``world_from_scan``: turn by ``yaw_deg`` about +Y, move the bounding-box centre to the
    origin, scale uniformly so the vertical (Y) extent is ``height``."""
    rot = yaw_matrix(yaw_deg)
    v = mesh.vertices.astype(np.float64) @ rot[:3, :3].T
    lo, hi = v.min(axis=0), v.max(axis=0)
    extent = hi[1] - lo[1]
    if not np.isfinite(extent) or extent <= 0:
        raise InputError(f"scan has no vertical extent (bounds {lo.tolist()} .. {hi.tolist()}); is it Y up?")
    scale = height / extent
    shift = np.eye(4)
    shift[:3, 3] = -(lo + hi) / 2.0
    return np.diag([scale, scale, scale, 1.0]) @ shift @ rot


def normalize_scan(mesh: TexturedMesh, height: float = DEFAULT_SUBJECT_HEIGHT, yaw_deg: float = 0.0) -> TexturedMesh:
    """Bounding-box centre at the origin, vertical (Y) extent = ``height`` world units (after turning
    the scan by ``yaw_deg`` about +Y, for scans that do not face +Z)."""
    return mesh.transformed(normalization_transform(mesh, height, yaw_deg))


def framing_radius(height: float = DEFAULT_SUBJECT_HEIGHT, fov_y_deg: float = 33.8, fill: float = DEFAULT_FILL) -> float:
    """Orbit radius at which a subject ``height`` tall spans ``fill`` of the frame height."""
    if not 0.0 < fill <= 2.0:
        raise ValueError(f"fill must be in (0, 2], got {fill}")
    return float(height / (2.0 * fill * np.tan(np.radians(fov_y_deg) / 2.0)))


# ----------------------------------------------------------------------------- loading

def find_mesh_file(path: str | Path) -> Path:
    """The mesh file a scan path names: the file itself, or the one mesh file in a folder."""
    path = Path(path)
    if path.is_file():
        if path.suffix.lower() not in MESH_SUFFIXES:
            raise InputError(f"{path} is not a mesh file: expected one of {', '.join(MESH_SUFFIXES)}")
        return path
    if not path.is_dir():
        raise InputError(f"scan {path} does not exist")
    found = sorted(p for p in path.rglob("*") if p.is_file() and p.suffix.lower() in MESH_SUFFIXES
                   and not any(part.startswith(".") for part in p.relative_to(path).parts))
    if not found:
        raise InputError(f"no mesh ({', '.join(MESH_SUFFIXES)}) found in {path}")
    if len(found) == 1:
        return found[0]
    named = [p for p in found if p.stem == p.parent.name]  # THuman2.0: NNNN/NNNN.obj
    if len(named) == 1:
        return named[0]
    listed = ", ".join(str(p.relative_to(path)) for p in found[:6])
    raise InputError(f"{len(found)} meshes in {path} ({listed}{', ...' if len(found) > 6 else ''}): "
                     "pass one mesh file or a folder holding exactly one")


def load_scan(path: str | Path) -> TexturedMesh:
    """Load a scan file or folder (see the module docstring) as one :class:`TexturedMesh`."""
    import trimesh

    mesh_path = find_mesh_file(path)
    try:
        scene = trimesh.load(str(mesh_path), force="scene", process=False)
    except Exception as e:  # trimesh raises many types for corrupt files
        raise InputError(f"cannot read mesh {mesh_path}: {type(e).__name__}: {e}") from None
    skinned = _skinned_node_names(mesh_path)
    parts: list[TexturedMesh] = []
    for node in scene.graph.nodes_geometry:
        transform, geom_name = scene.graph[node]
        geom = scene.geometry[geom_name]
        if not isinstance(geom, trimesh.Trimesh) or len(geom.faces) == 0:
            continue
        part = _part_from_trimesh(geom, mesh_path)
        # a mesh with several primitives hangs them under its node: check the parent too
        if node not in skinned and scene.graph.transforms.parents.get(node) not in skinned:
            part = part.transformed(transform)
        parts.append(part)
    if not parts:
        raise InputError(f"{mesh_path} holds no triangle mesh with faces")
    merged = merge_meshes(parts)
    if not np.isfinite(merged.vertices).all():
        raise InputError(f"{mesh_path} has non-finite vertex coordinates")
    return merged


def _part_from_trimesh(geom, source: Path) -> TexturedMesh:
    """One trimesh geometry as a TexturedMesh (texture, else material colour, else vertex colours)."""
    visual = geom.visual
    n = len(geom.vertices)
    if visual.kind == "texture":
        material = getattr(visual, "material", None)
        image = getattr(material, "image", None)
        if image is None:
            image = getattr(material, "baseColorTexture", None)
        uv = getattr(visual, "uv", None)
        if image is not None and uv is not None and len(uv) == n:
            texture = np.asarray(image.convert("RGB"), dtype=np.uint8)
            return TexturedMesh(geom.vertices, geom.faces, uvs=uv, texture=texture)
        vertex_colors = geom.vertex_attributes.get("color")
        if vertex_colors is not None and len(vertex_colors) == n:  # OBJ "v x y z r g b" beside an MTL
            return TexturedMesh(geom.vertices, geom.faces, vertex_colors=_unit_colors(vertex_colors))
        if source.suffix.lower() == ".obj":
            log.warning("%s: material has no readable texture image; using its flat colour", source)
        color = np.asarray(getattr(material, "main_color", (180, 180, 180, 255)), dtype=np.float32)[:3] / 255.0
        return TexturedMesh(geom.vertices, geom.faces, vertex_colors=np.tile(color, (n, 1)))
    colors = np.full((n, 3), UNCOLORED_GRAY, dtype=np.float32)
    if visual.kind == "vertex":
        colors = _unit_colors(visual.vertex_colors)
    elif visual.kind == "face":  # spread face colours to vertices (last face wins; scans rarely do this)
        colors = np.zeros((n, 3), dtype=np.float32)
        colors[geom.faces.reshape(-1)] = np.repeat(np.asarray(visual.face_colors)[:, :3] / 255.0, 3, axis=0)
    return TexturedMesh(geom.vertices, geom.faces, vertex_colors=colors)


def _unit_colors(colors) -> np.ndarray:
    """RGB(A) colours as float32 (N, 3) in [0, 1] (uint8 inputs are divided by 255)."""
    c = np.asarray(colors)
    rgb = c[:, :3].astype(np.float32)
    return rgb / 255.0 if c.dtype == np.uint8 or rgb.max(initial=0.0) > 1.0 else rgb


def _skinned_node_names(path: Path) -> set[str]:
    """Names of glTF nodes that carry a skin (their node transform must be ignored)."""
    suffix = path.suffix.lower()
    try:
        if suffix == ".gltf":
            doc = json.loads(path.read_text(encoding="utf-8"))
        elif suffix == ".glb":
            with open(path, "rb") as f:
                header = f.read(20)
                length, kind = struct.unpack("<II", header[12:20])
                if kind != 0x4E4F534A:  # 'JSON'
                    return set()
                doc = json.loads(f.read(length))
        else:
            return set()
    except (OSError, ValueError, struct.error):
        return set()
    # trimesh names scene-graph nodes after the glTF node name, or its index when it has none
    return {str(n.get("name", i)) for i, n in enumerate(doc.get("nodes", [])) if "skin" in n and "mesh" in n}


def merge_meshes(parts: list[TexturedMesh]) -> TexturedMesh:
    """Concatenate meshes; several distinct textures are packed into one atlas."""
    if len(parts) == 1:
        return parts[0]
    textures: list[np.ndarray] = []
    keys: list[str] = []
    tex_index: list[int | None] = []
    for p in parts:
        if p.texture is None:
            tex_index.append(None)
            continue
        key = hashlib.sha1(p.texture.tobytes()).hexdigest()
        if key not in keys:
            keys.append(key)
            textures.append(p.texture)
        tex_index.append(keys.index(key))
    any_vc = any(p.vertex_colors is not None for p in parts)
    if textures and any(i is None for i in tex_index):
        textures.append(np.full((8, 8, 3), 255, dtype=np.uint8))  # white tile for colour-only parts
    atlas, rects = (textures[0], [(0.0, 0.0, 1.0, 1.0)]) if len(textures) == 1 else pack_atlas(textures)

    verts, faces, uvs, colors = [], [], [], []
    offset = 0
    for p, ti in zip(parts, tex_index, strict=True):
        v, f, uv = p.vertices, p.faces, p.uvs
        if textures:
            if ti is None:  # point into the white tile
                uv = np.full((len(v), 2), 0.5, dtype=np.float32)
                ti = len(textures) - 1
            elif len(textures) > 1:
                v, f, uv, c = _wrap_uvs(p)
                p = replace(p, vertices=v, faces=f, uvs=uv, vertex_colors=c)
            u0, v0, u1, v1 = rects[ti]
            uvs.append(np.stack([u0 + uv[:, 0] * (u1 - u0), v0 + uv[:, 1] * (v1 - v0)], axis=1))
        if any_vc:
            colors.append(p.vertex_colors if p.vertex_colors is not None else np.ones((len(v), 3), np.float32))
        verts.append(v)
        faces.append(f + offset)
        offset += len(v)
    return TexturedMesh(
        np.concatenate(verts), np.concatenate(faces),
        uvs=np.concatenate(uvs) if textures else None, texture=atlas if textures else None,
        vertex_colors=np.concatenate(colors) if any_vc else None,
    )


def _wrap_uvs(p: TexturedMesh) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """Bring UVs into [0, 1] for atlas packing (repeat wrapping cannot work inside an atlas).

    When every UV is already in [0, 1] nothing changes; otherwise faces get their own vertices and
    each face is shifted by whole tiles so its centre lies in [0, 1], then clipped.
    """
    uv = p.uvs
    if uv.min() >= -1e-4 and uv.max() <= 1 + 1e-4:
        return p.vertices, p.faces, np.clip(uv, 0.0, 1.0), p.vertex_colors
    corners = p.faces.reshape(-1)
    face_uv = uv[p.faces]  # (F, 3, 2)
    shift = np.floor(face_uv.mean(axis=1, keepdims=True))
    new_uv = np.clip(face_uv - shift, 0.0, 1.0).reshape(-1, 2)
    colors = None if p.vertex_colors is None else p.vertex_colors[corners]
    return p.vertices[corners], np.arange(len(corners), dtype=np.int32).reshape(-1, 3), new_uv, colors


def pack_atlas(textures: list[np.ndarray]) -> tuple[np.ndarray, list[tuple[float, float, float, float]]]:
    """Pack textures into a grid atlas; returns it and each texture's UV rectangle (u0, v0, u1, v1).

    Every cell has the largest texture's size (smaller ones are resized) with a replicated border
    of a few pixels so filtering does not bleed between cells; the atlas is scaled down to at most
    :data:`ATLAS_MAX_SIZE` pixels a side.
    """
    import cv2

    n = len(textures)
    cols = int(np.ceil(np.sqrt(n)))
    rows = int(np.ceil(n / cols))
    cw = max(t.shape[1] for t in textures) + 2 * _ATLAS_PAD
    ch = max(t.shape[0] for t in textures) + 2 * _ATLAS_PAD
    shrink = min(1.0, ATLAS_MAX_SIZE / (cols * cw), ATLAS_MAX_SIZE / (rows * ch))
    cw, ch = int(cw * shrink), int(ch * shrink)
    atlas = np.zeros((rows * ch, cols * cw, 3), dtype=np.uint8)
    aw, ah = atlas.shape[1], atlas.shape[0]
    rects = []
    for i, tex in enumerate(textures):
        r, c = divmod(i, cols)
        inner = cv2.resize(tex, (cw - 2 * _ATLAS_PAD, ch - 2 * _ATLAS_PAD), interpolation=cv2.INTER_AREA)
        cell = cv2.copyMakeBorder(inner, _ATLAS_PAD, _ATLAS_PAD, _ATLAS_PAD, _ATLAS_PAD, cv2.BORDER_REPLICATE)
        atlas[r * ch:(r + 1) * ch, c * cw:(c + 1) * cw] = cell
        x0, x1 = c * cw + _ATLAS_PAD, (c + 1) * cw - _ATLAS_PAD
        top, bottom = r * ch + _ATLAS_PAD, (r + 1) * ch - _ATLAS_PAD  # image rows
        rects.append((x0 / aw, 1.0 - bottom / ah, x1 / aw, 1.0 - top / ah))
    return atlas, rects


# ----------------------------------------------------------------------------- writing

def save_obj(mesh: TexturedMesh, folder: str | Path, name: str = "mesh", texture_name: str | None = None,
             mtl_name: str | None = None) -> Path:
    """Write ``name.obj`` + an MTL (+ the texture, PNG or JPEG by its suffix) into ``folder``.

    Returns the OBJ path. Vertex colours are written as OBJ ``v x y z r g b`` extensions when there
    is no texture.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    mtl_name = mtl_name or f"{name}.mtl"
    lines = [f"mtllib {mtl_name}", "usemtl material0"]
    vc = mesh.vertex_colors if mesh.texture is None else None
    for i, v in enumerate(mesh.vertices):
        colour = "" if vc is None else " {:.6f} {:.6f} {:.6f}".format(*vc[i])
        lines.append(f"v {v[0]:.6f} {v[1]:.6f} {v[2]:.6f}{colour}")
    f1 = mesh.faces + 1
    if mesh.texture is not None:
        lines += [f"vt {u:.6f} {v:.6f}" for u, v in mesh.uvs]
        lines += [f"f {a}/{a} {b}/{b} {c}/{c}" for a, b, c in f1]
    else:
        lines += [f"f {a} {b} {c}" for a, b, c in f1]
    mtl = ["newmtl material0", "Kd 1 1 1", "illum 0"]
    if mesh.texture is not None:
        texture_name = texture_name or f"{name}.png"
        _write_texture(folder / texture_name, mesh.texture)
        mtl.append(f"map_Kd {texture_name}")
    atomic_write_text(folder / mtl_name, "\n".join(mtl) + "\n")
    obj_path = folder / f"{name}.obj"
    atomic_write_text(obj_path, "\n".join(lines) + "\n")
    return obj_path


def _write_texture(path: Path, texture: np.ndarray) -> None:
    if path.suffix.lower() == ".png":
        write_png(path, texture)
        return
    import cv2

    ok, data = cv2.imencode(path.suffix, cv2.cvtColor(texture, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 95])
    if not ok:
        raise OSError(f"cannot encode texture {path}")
    atomic_write_bytes(path, data.tobytes())

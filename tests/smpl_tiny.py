"""Tiny synthetic SMPL / SMPL-X model files (the real files are non-free) for tests.

The bodies are made of tubes (two rings of vertices per bone) around a plausible rest skeleton in SMPL's
native frame (metres, Y up, facing +Z, the person's left at +X, the pelvis near y = -0.22 as in SMPL), with
the real kinematic trees (24 and 55 joints), a joint regressor averaging the rings next to each joint,
skinning weights on the bone's parent joint (blended near joints), random small shape and pose blend
shapes, and five face vertices (nose, eyes, ears: :data:`FACE_VERTEX_IDS` of the generated mesh).

Files written (the layouts of the official files, under ``<root>/smpl`` and ``<root>/smplx``):

- :func:`write_smpl_pkl`: ``SMPL_<GENDER>.pkl``, a protocol-2 (or 0) pickle like the official SMPL files:
  ``v_template``, ``shapedirs``, ``weights``, ``J`` are ``chumpy.ch.Ch`` objects and ``J_regressor`` is a
  ``scipy.sparse.csc.csc_matrix``; written with fake ``chumpy``/``scipy`` classes, so reading it needs
  the loader's stand-ins (neither package is imported).
- :func:`write_smpl_npz`: the same model as ``SMPL_<GENDER>.npz`` with plain arrays.
- :func:`write_smplx_npz`: ``SMPLX_<GENDER>.npz`` with the arrays ``smplx.SMPLX`` reads (10 shape + 10
  expression components, hand PCA, face landmarks), plus ``joint2num`` as an object array (as the real
  file has) to check it is skipped.
- :func:`write_uv_obj`: ``smpl_uv.obj`` (a per-triangle UV layout, faces listed in another order).
"""

from __future__ import annotations

import contextlib
import pickle
import sys
import types
from pathlib import Path

import numpy as np

SMPL_PARENTS = [-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21]
SMPLX_PARENTS = [-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 15, 15, 15,
                 20, 25, 26, 20, 28, 29, 20, 31, 32, 20, 34, 35, 20, 37, 38,
                 21, 40, 41, 21, 43, 44, 21, 46, 47, 21, 49, 50, 21, 52, 53]
ROOT_SENTINEL = 4294967295  # the root's parent in the official kintree_tables (uint32 -1)

# Left-side and central rest joints (SMPL order); right-side ones mirror across x = 0.
_BODY = {
    0: (0.0, -0.22, 0.02), 1: (0.06, -0.31, 0.01), 3: (0.0, -0.11, 0.0), 4: (0.10, -0.69, 0.01),
    6: (0.0, 0.03, 0.03), 7: (0.09, -1.09, -0.03), 9: (0.0, 0.08, 0.03), 10: (0.12, -1.15, 0.09),
    12: (0.0, 0.29, 0.0), 13: (0.08, 0.19, 0.01), 15: (0.0, 0.36, 0.05), 16: (0.19, 0.23, -0.01),
    18: (0.44, 0.22, -0.03), 20: (0.70, 0.22, -0.03), 22: (0.78, 0.21, -0.04),
}
_MIRROR = {2: 1, 5: 4, 8: 7, 11: 10, 14: 13, 17: 16, 19: 18, 21: 20, 23: 22}
_RING = 6  # vertices per ring
FACE_VERTEX_OFFSETS = ((0.0, 0.03, 0.11), (0.035, 0.07, 0.09), (-0.035, 0.07, 0.09), (0.08, 0.04, 0.0),
                       (-0.08, 0.04, 0.0))  # nose, left eye, right eye, left ear, right ear, from the head


def _mirror(p) -> np.ndarray:
    return np.array([-p[0], p[1], p[2]])


def smpl_joints() -> np.ndarray:
    J = np.zeros((24, 3))
    for j, p in _BODY.items():
        J[j] = p
    for j, src in _MIRROR.items():
        J[j] = _mirror(_BODY[src])
    return J


def smplx_joints() -> np.ndarray:
    J = np.zeros((55, 3))
    J[:22] = smpl_joints()[:22]
    J[22] = (0.0, 0.33, 0.07)  # jaw
    J[23], J[24] = (0.03, 0.42, 0.09), (-0.03, 0.42, 0.09)  # eyes
    bases = {"index": (0.09, 0.0, 0.025), "middle": (0.095, 0.0, 0.005), "pinky": (0.08, 0.0, -0.035),
             "ring": (0.09, 0.0, -0.015), "thumb": (0.03, -0.01, 0.04)}
    for side, wrist, first in ((1.0, 20, 25), (-1.0, 21, 40)):
        for k, (bx, by, bz) in enumerate(bases.values()):
            for i in range(3):
                J[first + 3 * k + i] = J[wrist] + np.array([side * (bx + 0.025 * i), by, bz])
    return J


def _tip(J: np.ndarray, parents: list[int], j: int) -> np.ndarray:
    """An end point past a joint with no children (or the head's top)."""
    if j == 15:
        return J[15] + np.array([0.0, 0.22, -0.03])
    if j in (10, 11):
        return J[j] + np.array([0.0, -0.02, 0.08])
    if j in (23, 24):
        return J[j] + np.array([0.0, 0.0, 0.02])
    if j == 22 and len(parents) == 55:
        return J[j] + np.array([0.0, -0.05, 0.05])
    d = J[j] - J[parents[j]]
    return J[j] + 0.6 * d


def _radius(j: int, n_joints: int) -> float:
    if n_joints == 55 and j >= 22:
        return 0.008 if j >= 25 else 0.01
    if j in (0, 3, 6, 9, 13, 14):
        return 0.09
    if j in (12, 15):
        return 0.06
    if j in (1, 2, 4, 5, 7, 8, 10, 11):
        return 0.055
    return 0.04


def make_body(parents: list[int], J: np.ndarray, num_shape: int, seed: int = 0) -> dict[str, np.ndarray]:
    """Arrays of a tube body: v_template, f, weights, J_regressor, shapedirs (V,3,num_shape),
    posedirs (V,3,9(J-1)), kintree_table, J; and ``face_vertex_ids``."""
    rng = np.random.default_rng(seed)
    n = len(parents)
    children: dict[int, list[int]] = {j: [] for j in range(n)}
    for j in range(1, n):
        children[parents[j]].append(j)
    segments: list[tuple[int, np.ndarray, np.ndarray, int | None]] = []  # (driving joint, a, b, child)
    for j in range(1, n):
        segments.append((parents[j], J[parents[j]], J[j], j))
    for j in range(n):
        if not children[j] or j == 15:
            segments.append((j, J[j], _tip(J, parents, j), None))

    verts, faces = [], []
    weights = []
    near_rings: dict[int, list[int]] = {j: [] for j in range(n)}  # ring vertices around each joint
    for drive, a, b, child in segments:
        d = b - a
        d = d / max(np.linalg.norm(d), 1e-9)
        helper = np.array([0.0, 0.0, 1.0]) if abs(d[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
        u = np.cross(d, helper)
        u /= np.linalg.norm(u)
        w = np.cross(d, u)
        r = _radius(drive, n)
        ring_ids = []
        for t in (0.25, 0.75):
            centre = a + t * (b - a)
            start = len(verts)
            for k in range(_RING):
                ang = 2 * np.pi * k / _RING
                verts.append(centre + r * (np.cos(ang) * u + np.sin(ang) * w))
                row = np.zeros(n)
                grand = parents[drive]
                if t == 0.25 and grand >= 0:
                    row[drive], row[grand] = 0.8, 0.2
                else:
                    row[drive] = 1.0
                weights.append(row)
            ring_ids.append(list(range(start, start + _RING)))
        near_rings[drive].extend(ring_ids[0])
        if child is not None:
            near_rings[child].extend(ring_ids[1])
        r0, r1 = ring_ids
        for k in range(_RING):
            k1 = (k + 1) % _RING
            faces.append([r0[k], r0[k1], r1[k1]])
            faces.append([r0[k], r1[k1], r1[k]])
    face_ids = []
    for off in FACE_VERTEX_OFFSETS:
        face_ids.append(len(verts))
        verts.append(J[15] + np.array(off))
        row = np.zeros(n)
        row[15] = 1.0
        weights.append(row)
    nose, leye, reye, lear, rear = face_ids
    faces += [[nose, leye, reye], [lear, leye, nose], [rear, nose, reye]]

    V = len(verts)
    v_template = np.asarray(verts)
    J_regressor = np.zeros((n, V))
    for j in range(n):
        J_regressor[j, near_rings[j]] = 1.0 / len(near_rings[j])
    height = (v_template[:, 1] - v_template[:, 1].min())[:, None]
    shapedirs = 0.004 * rng.standard_normal((V, 3, num_shape))
    shapedirs[:, 1, 0] += 0.03 * height[:, 0]  # the first component makes the body taller
    posedirs = (0.003 * rng.standard_normal((V, 3, 9 * (n - 1)))).astype(np.float32)
    kintree = np.array([[ROOT_SENTINEL] + parents[1:], list(range(n))], dtype=np.int64)
    return {
        "v_template": v_template, "f": np.asarray(faces, dtype=np.uint32), "weights": np.asarray(weights),
        "J_regressor": J_regressor, "shapedirs": shapedirs, "posedirs": posedirs, "kintree_table": kintree,
        "J": J_regressor @ v_template, "face_vertex_ids": np.asarray(face_ids),
    }


def smpl_arrays(seed: int = 0) -> dict[str, np.ndarray]:
    return make_body(SMPL_PARENTS, smpl_joints(), num_shape=10, seed=seed)


def smplx_arrays(seed: int = 1) -> dict[str, np.ndarray]:
    data = make_body(SMPLX_PARENTS, smplx_joints(), num_shape=20, seed=seed)
    rng = np.random.default_rng(seed + 100)
    for side in ("l", "r"):
        data[f"hands_components{side}"] = np.linalg.qr(rng.standard_normal((45, 45)))[0]
        data[f"hands_mean{side}"] = 0.1 * rng.standard_normal(45)
    F = len(data["f"])
    data["lmk_faces_idx"] = rng.integers(0, F, 51)
    bary = rng.random((51, 3))
    data["lmk_bary_coords"] = bary / bary.sum(1, keepdims=True)
    return data


# ----------------------------------------------------------------------------- fake chumpy / scipy pickles

class _FakeCh:
    """Pickles like ``chumpy.ch.Ch``: state is its ``__dict__`` with the value under ``x``."""

    def __init__(self, x: np.ndarray):
        self.x = np.asarray(x, dtype=np.float64)
        self._dirty_vars = set()
        self._itr = None
        self._depends_on_deps = {}
        self._make_dense = False
        self._make_sparse = False


class _FakeCSC:
    """Pickles like an old ``scipy.sparse.csc.csc_matrix``."""

    def __init__(self, dense: np.ndarray):
        dense = np.asarray(dense)
        col_of, row_of = np.nonzero(dense.T)  # nonzeros in column-major order
        self._shape = dense.shape
        self.maxprint = 50
        self.indices = row_of.astype(np.int32)
        counts = np.bincount(col_of, minlength=dense.shape[1])
        self.indptr = np.concatenate([[0], np.cumsum(counts)]).astype(np.int32)
        self.data = dense.T[col_of, row_of]


@contextlib.contextmanager
def _fake_modules():
    """Make ``_FakeCh``/``_FakeCSC`` picklable as ``chumpy.ch.Ch``/``scipy.sparse.csc.csc_matrix``."""
    names = {"chumpy": None, "chumpy.ch": ("Ch", _FakeCh), "scipy": None, "scipy.sparse": None,
             "scipy.sparse.csc": ("csc_matrix", _FakeCSC)}
    saved = {name: sys.modules.get(name) for name in names}
    originals = {cls: (cls.__module__, cls.__qualname__, cls.__name__) for cls in (_FakeCh, _FakeCSC)}
    try:
        for name, entry in names.items():
            mod = types.ModuleType(name)
            if entry is not None:
                attr, cls = entry
                setattr(mod, attr, cls)
                cls.__module__, cls.__qualname__, cls.__name__ = name, attr, attr
            sys.modules[name] = mod
        yield
    finally:
        for name, mod in saved.items():
            if mod is None:
                sys.modules.pop(name, None)
            else:
                sys.modules[name] = mod
        for cls, (module, qualname, name) in originals.items():
            cls.__module__, cls.__qualname__, cls.__name__ = module, qualname, name


def write_smpl_pkl(root: Path, gender: str = "neutral", data: dict | None = None, protocol: int = 2) -> Path:
    """Protocol 2 (binary) or 0 (text), both used by Python 2's pickle; numpy's module named ``numpy.core``
    as in files written before numpy 2."""
    data = smpl_arrays() if data is None else data
    payload = {
        "v_template": _FakeCh(data["v_template"]), "shapedirs": _FakeCh(data["shapedirs"]),
        "weights": _FakeCh(data["weights"]), "J": _FakeCh(data["J"]),
        "J_regressor": _FakeCSC(data["J_regressor"]), "J_regressor_prior": _FakeCSC(data["J_regressor"]),
        "posedirs": data["posedirs"], "f": data["f"], "kintree_table": data["kintree_table"],
        "bs_type": "lrotmin", "bs_style": "lbs", "vert_sym_idxs": np.arange(len(data["v_template"])),
    }
    path = Path(root) / "smpl" / f"SMPL_{gender.upper()}.pkl"
    path.parent.mkdir(parents=True, exist_ok=True)
    with _fake_modules():
        blob = pickle.dumps(payload, protocol=protocol)
    assert b"chumpy.ch" in blob and b"scipy.sparse.csc" in blob
    blob = blob.replace(b"cnumpy._core.multiarray\n", b"cnumpy.core.multiarray\n")  # GLOBAL opcodes
    path.write_bytes(blob)
    return path


def _model_arrays(data: dict) -> dict[str, np.ndarray]:
    return {k: v for k, v in data.items() if k != "face_vertex_ids"}


def write_smpl_npz(root: Path, gender: str = "neutral", data: dict | None = None) -> Path:
    data = smpl_arrays() if data is None else data
    path = Path(root) / "smpl" / f"SMPL_{gender.upper()}.npz"
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, **_model_arrays(data))
    return path


def write_smplx_npz(root: Path, gender: str = "neutral", data: dict | None = None) -> Path:
    data = smplx_arrays() if data is None else data
    path = Path(root) / "smplx" / f"SMPLX_{gender.upper()}.npz"
    path.parent.mkdir(parents=True, exist_ok=True)
    joint2num = np.empty((), dtype=object)
    joint2num[()] = {"pelvis": 0}
    np.savez(path, joint2num=joint2num, **_model_arrays(data))
    return path


def write_uv_obj(path: Path, data: dict) -> Path:
    """A UV layout with each triangle in its own grid cell; faces listed in reverse order, corners rotated."""
    faces = np.asarray(data["f"], np.int64)
    F = len(faces)
    cells = int(np.ceil(np.sqrt(F)))
    lines = [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in data["v_template"]]
    for i in range(F):
        cu, cv = (i % cells) / cells, (i // cells) / cells
        s = 0.8 / cells
        lines += [f"vt {cu + 0.1 / cells:.6f} {cv + 0.1 / cells:.6f}", f"vt {cu + 0.1 / cells + s:.6f} "
                  f"{cv + 0.1 / cells:.6f}", f"vt {cu + 0.1 / cells:.6f} {cv + 0.1 / cells + s:.6f}"]
    for i in reversed(range(F)):
        a, b, c = faces[i]
        ta, tb, tc = 3 * i + 1, 3 * i + 2, 3 * i + 3
        lines.append(f"f {b + 1}/{tb} {c + 1}/{tc} {a + 1}/{ta}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")
    return path

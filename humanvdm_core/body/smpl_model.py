"""SMPL / SMPL-X body model backend, from model files the user supplies (non-free: never shipped/downloaded).

:class:`SMPLBody` implements :class:`~humanvdm_core.body.model.BodyModel` for SMPL (24 joints) and SMPL-X
(55 joints). It reads the model file itself and runs its own forward pass (the same blend-shape + LBS
computation as the ``smplx`` package, whose output it matches to float precision; see tests/test_smpl.py),
because the project needs the bone transforms and the bind-pose mesh, which ``smplx``'s forward does not
return. The ``smplx`` package is therefore not needed at run time; the tests compare against it when it
is installed.

Model files (the ``smplx`` package's folder convention):

- ``<model_dir>/smpl/SMPL_{NEUTRAL,MALE,FEMALE}.pkl`` (or ``.npz``), from https://smpl.is.tue.mpg.de
  (rename e.g. ``basicmodel_neutral_lbs_10_207_0_v1.1.0.pkl`` to ``SMPL_NEUTRAL.pkl``);
- ``<model_dir>/smplx/SMPLX_{NEUTRAL,MALE,FEMALE}.npz`` (or ``.pkl``), from https://smpl-x.is.tue.mpg.de.

``model_dir`` may also be the ``smpl``/``smplx`` folder itself, or the model file. A missing file raises
:class:`~humanvdm_core.errors.MissingWeightsError` naming the file expected.

Loading: ``.npz`` files are read with ``allow_pickle=False`` (object arrays such as ``joint2num`` are
skipped). ``.pkl`` files (SMPL's official files hold ``chumpy`` arrays and ``scipy.sparse`` matrices) are
read by :func:`load_model_file` with a restricted unpickler: only numpy's array/dtype/scalar
reconstructors, ``set``/``frozenset``/``object``/``slice``/``complex``, ``copyreg._reconstructor``,
``_codecs.encode`` (bytes in Python 3 protocol-2 pickles) and stand-ins for every ``chumpy.*`` class and
for ``scipy.sparse`` CSC/CSR matrices may be referenced; anything else is refused. A chumpy stand-in
yields its value array ``x``, a sparse stand-in its dense matrix. Neither chumpy nor scipy is needed.

Conventions. SMPL's native frame is already the project's world frame (metres, Y up, facing +Z, the
person's left at +X), so no axis change is applied. Differences from ``smplx``'s parameters:

- ``pose`` (B, P, 3) is SMPL's per-joint axis-angle for joints 1..J-1 in the model's joint order
  (SMPL: P = 23, ``body_pose`` reshaped; SMPL-X: P = 54 = 21 body + jaw + left eye + right eye + 15 left
  hand + 15 right hand joints, i.e. ``smplx``'s ``full_pose`` without the root, hands as full axis-angle,
  no PCA, zero = flat hand (``flat_hand_mean=True``)). Each joint's rest frame is world-aligned, so the
  axes are world axes of the zero pose as the interface requires.
- ``shape`` (B, S): SMPL's ``betas`` (``num_betas``), for SMPL-X followed by the ``expression``
  coefficients (``num_expression_coeffs``). The default shape is zeros (the mean shape).
- The root joint (pelvis) is at the origin: ``transl`` here = ``smplx``'s ``transl`` + the rest pelvis
  position :meth:`SMPLBody.pelvis_offset` (at ``scale`` 1).
- ``rest_vertices`` is SMPL's shaped template *plus the pose-corrective blend shapes of the given pose*
  (with the root at the origin), so ``vertices == lbs(rest_vertices, skinning_weights, bone_transforms)``
  holds exactly. With ``pose_correctives=False`` the pose blend shapes are left out (the model is then
  pure LBS of the shaped template, and lbs() from the canonical pose to any pose is exact; with them,
  points carried from the canonical pose miss the difference of the two poses' correctives, whose size
  depends on the poses; it has not been measured on a real model here).
- ``bone_transforms`` are the identity at zero pose and parameters (the bind pose is the zero pose).

``coco17``: shoulders, elbows, wrists, hips, knees and ankles are SMPL's joints (SMPL's hip joints sit
higher and more inside than COCO's annotated hips, a known offset a fitting loss should tolerate); nose,
eyes and ears are single mesh vertices, by default the widely used vertex ids of the standard topologies
(:data:`FACE_VERTEX_IDS`; SMPL: nose 332, eyes 2800/6260, ears 583/4071; SMPL-X: nose 9120, eyes
9448/9929, ears 6/616). A model with another vertex count needs ``face_vertex_ids``.

UV layout: SMPL's comes from a separate ``smpl_uv.obj`` (distributed on the SMPL website); SMPL-X's from
the model file's ``vt``/``ft`` arrays when present, else ``smplx_uv.obj``. The OBJ is looked for next to
the model file. Without one, ``uvs`` and ``uv_faces`` are None and :meth:`SMPLBody.require_uv_layout`
raises :class:`~humanvdm_core.errors.MissingWeightsError` naming the file.
"""

from __future__ import annotations

import io
import pickle
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from humanvdm_core.body.model import (
    COCO17_NAMES,
    BodyModel,
    BodyOutput,
    BodyParams,
    axis_angle_to_matrix,
    global_transform,
    transform_points,
)
from humanvdm_core.errors import MissingWeightsError
from humanvdm_core.workflow.errors import ConfigError, InputError

KINDS = ("smpl", "smplx")
GENDERS = ("neutral", "male", "female")
WHERE_TO_GET = {
    "smpl": "https://smpl.is.tue.mpg.de (register, download the SMPL model for Python; rename e.g. "
            "basicmodel_neutral_lbs_10_207_0_v1.1.0.pkl to SMPL_NEUTRAL.pkl)",
    "smplx": "https://smpl-x.is.tue.mpg.de (register, download the SMPL-X model, .npz files)",
}
UV_FILES = {"smpl": "smpl_uv.obj", "smplx": "smplx_uv.obj"}
UV_WHERE_TO_GET = {
    "smpl": "https://smpl.is.tue.mpg.de (the 'UV map' download)",
    "smplx": "https://smpl-x.is.tue.mpg.de (the 'UV map' download)",
}

SMPL_JOINT_NAMES: tuple[str, ...] = (
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2", "left_ankle",
    "right_ankle", "spine3", "left_foot", "right_foot", "neck", "left_collar", "right_collar", "head",
    "left_shoulder", "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist",
    "left_hand", "right_hand",
)
_FINGERS = ("index", "middle", "pinky", "ring", "thumb")
SMPLX_JOINT_NAMES: tuple[str, ...] = (
    SMPL_JOINT_NAMES[:22] + ("jaw", "left_eye", "right_eye")
    + tuple(f"left_{f}{i}" for f in _FINGERS for i in (1, 2, 3))
    + tuple(f"right_{f}{i}" for f in _FINGERS for i in (1, 2, 3))
)
# Standard vertex counts and the face keypoint vertices (COCO order: nose, left eye, right eye, left ear,
# right ear) of the official topologies.
NUM_VERTICES = {"smpl": 6890, "smplx": 10475}
FACE_VERTEX_IDS = {"smpl": (332, 2800, 6260, 583, 4071), "smplx": (9120, 9448, 9929, 6, 616)}
# COCO-17 keypoints 5..16 are the SMPL joints of the same names (the same indices in SMPL and SMPL-X).
COCO_BODY_JOINTS: tuple[str, ...] = COCO17_NAMES[5:]

# The canonical da-pose: each hip rotated outward about the forward axis (SMPL's zero-pose legs are
# almost parallel, so the legs end up about this far from vertical), and the T-pose arms lowered by
# CANONICAL_ARM_DROP_DEG at the shoulders (an A-pose, "arms relaxed" as the interface asks).
CANONICAL_LEG_SPREAD_DEG = 27.0
CANONICAL_ARM_DROP_DEG = 45.0


# ----------------------------------------------------------------------------- model files

class _ChumpyStandIn:
    """Takes the place of any ``chumpy`` class while unpickling; its value is the ``x`` array."""

    def __new__(cls, *args, **kwargs):
        return object.__new__(cls)

    def __init__(self, *args, **kwargs):
        pass

    def __setstate__(self, state) -> None:
        if isinstance(state, tuple) and len(state) == 2:  # (dict, slots)
            state = {**(state[0] or {}), **(state[1] or {})}
        self.__dict__.update(state if isinstance(state, dict) else {})

    def value(self) -> np.ndarray:
        x = self.__dict__.get("x")
        if x is None:
            raise InputError(
                f"the model file holds a chumpy expression ({type(self).__name__}), not a plain array; "
                f"re-save the model with plain numpy arrays (e.g. as .npz)"
            )
        return np.asarray(_plain(x))


class _SparseStandIn:
    """Takes the place of ``scipy.sparse`` CSC/CSR matrices while unpickling; :meth:`dense` rebuilds them."""

    fmt = "csc"

    def __new__(cls, *args, **kwargs):
        return object.__new__(cls)

    def __init__(self, *args, **kwargs):
        pass

    def __setstate__(self, state) -> None:
        if isinstance(state, tuple) and len(state) == 2:
            state = {**(state[0] or {}), **(state[1] or {})}
        self.__dict__.update(state if isinstance(state, dict) else {})

    def dense(self) -> np.ndarray:
        d = self.__dict__
        shape = d.get("_shape", d.get("shape"))
        data, indices, indptr = (np.asarray(d[k]) for k in ("data", "indices", "indptr"))
        rows, cols = (int(s) for s in shape)
        out = np.zeros((rows, cols), dtype=data.dtype)
        major = np.repeat(np.arange(len(indptr) - 1), np.diff(indptr))
        if self.fmt == "csc":
            np.add.at(out, (indices, major), data)
        else:
            np.add.at(out, (major, indices), data)
        return out


class _CSRStandIn(_SparseStandIn):
    fmt = "csr"


def _numpy_module(name: str):
    """numpy's ``core`` modules under either name (``numpy.core`` before 2.0, ``numpy._core`` after)."""
    import importlib

    rest = name.split(".", 2)[2] if name.count(".") >= 2 else ""
    for base in ("numpy._core", "numpy.core"):
        try:
            return importlib.import_module(f"{base}.{rest}" if rest else base)
        except ImportError:
            continue
    raise ImportError(name)


class _ModelUnpickler(pickle.Unpickler):
    """Unpickles SMPL model files, allowing only the globals listed in the module docstring."""

    _NUMPY = {("multiarray", "_reconstruct"), ("multiarray", "scalar"), ("numeric", "_frombuffer")}
    _BUILTINS = {"set", "frozenset", "object", "slice", "complex"}
    _stand_ins: dict[str, type] = {}

    def find_class(self, module: str, name: str):
        if module == "chumpy" or module.startswith("chumpy."):
            key = f"{module}.{name}"
            if key not in self._stand_ins:
                self._stand_ins[key] = type(name, (_ChumpyStandIn,), {"__module__": __name__})
            return self._stand_ins[key]
        if module == "scipy.sparse" or module.startswith("scipy.sparse."):
            if name in ("csc_matrix", "csc_array"):
                return _SparseStandIn
            if name in ("csr_matrix", "csr_array"):
                return _CSRStandIn
        if module in ("numpy.core.multiarray", "numpy._core.multiarray", "numpy.core.numeric",
                      "numpy._core.numeric") and (module.rsplit(".", 1)[1], name) in self._NUMPY:
            return getattr(_numpy_module(module), name)
        if module == "numpy" and name in ("ndarray", "dtype"):
            return getattr(np, name)
        if module.startswith("numpy.dtypes") and name.endswith("DType"):
            import numpy.dtypes

            return getattr(numpy.dtypes, name)
        if module in ("builtins", "__builtin__") and name in self._BUILTINS:
            return super().find_class("builtins", name)
        if module == "_codecs" and name == "encode":  # how Python 3 protocol-2 pickles hold bytes
            return super().find_class(module, name)
        if module in ("copyreg", "copy_reg") and name == "_reconstructor":
            return super().find_class("copyreg", name)
        raise pickle.UnpicklingError(
            f"refusing to load {module}.{name} from a body model file (only numpy arrays, chumpy arrays and "
            f"scipy sparse matrices are expected)"
        )


def _plain(value):
    """chumpy / sparse stand-ins -> numpy arrays; anything else unchanged."""
    if isinstance(value, _ChumpyStandIn):
        return value.value()
    if isinstance(value, _SparseStandIn):
        return value.dense()
    return value


def load_model_file(path: str | Path) -> dict[str, object]:
    """Read an SMPL-family model file (.pkl, chumpy or not, or .npz) into plain numpy arrays (and the
    pickle's other plain values), without chumpy or scipy and without running arbitrary pickled code."""
    path = Path(path)
    if path.suffix == ".npz":
        out: dict[str, object] = {}
        with np.load(path, allow_pickle=False) as data:
            for key in data.files:
                try:
                    out[key] = data[key]
                except ValueError:  # an object array (e.g. joint2num); not needed
                    continue
        return out
    with open(path, "rb") as fh:
        raw = _ModelUnpickler(io.BytesIO(fh.read()), encoding="latin1").load()
    if not isinstance(raw, dict):
        raise InputError(f"{path} is not an SMPL model file (unpickled a {type(raw).__name__}, not a dict)")
    return {str(k): _plain(v) for k, v in raw.items()}


def model_file_names(kind: str, gender: str) -> list[str]:
    """File names looked for, preferred first (``smplx``'s convention)."""
    stem = f"{'SMPL' if kind == 'smpl' else 'SMPLX'}_{gender.upper()}"
    exts = (".pkl", ".npz") if kind == "smpl" else (".npz", ".pkl")
    return [stem + ext for ext in exts]


def find_model_file(model_dir: str | Path, kind: str = "smpl", gender: str = "neutral") -> Path:
    """The model file for ``kind``/``gender``: ``model_dir`` itself if it is a file, else the first of
    :func:`model_file_names` in ``model_dir/<kind>/`` then ``model_dir/``; raises MissingWeightsError."""
    _check_kind_gender(kind, gender)
    root = Path(model_dir).expanduser()
    if root.is_file():
        return root
    names = model_file_names(kind, gender)
    for folder in (root / kind, root):
        for name in names:
            if (folder / name).is_file():
                return folder / name
    label = {"smpl": "SMPL", "smplx": "SMPL-X"}[kind]
    raise MissingWeightsError(
        root / kind / names[0],
        f"{label} {gender} body model; {names[1]} is accepted too, also directly under {root}",
        WHERE_TO_GET[kind],
    )


def read_obj_uvs(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(vt (T, 2), face vertex indices (F, 3), face texture indices (F, 3)), 0-based, from a triangle OBJ."""
    vts: list[list[float]] = []
    faces: list[list[int]] = []
    tex: list[list[int]] = []
    with open(path, encoding="utf-8", errors="replace") as fh:
        for line in fh:
            parts = line.split()
            if not parts:
                continue
            if parts[0] == "vt":
                vts.append([float(parts[1]), float(parts[2])])
            elif parts[0] == "f":
                corners = [c.split("/") for c in parts[1:]]
                if len(corners) != 3 or any(len(c) < 2 or not c[1] for c in corners):
                    raise InputError(f"{path}: expected textured triangles (f v/vt v/vt v/vt), got {line!r}")
                faces.append([int(c[0]) - 1 for c in corners])
                tex.append([int(c[1]) - 1 for c in corners])
    if not faces or not vts:
        raise InputError(f"{path}: no textured faces found")
    return np.asarray(vts, np.float64), np.asarray(faces, np.int64), np.asarray(tex, np.int64)


def _match_uv_faces(faces: np.ndarray, obj_faces: np.ndarray, obj_tex: np.ndarray, path: Path) -> np.ndarray:
    """Texture indices per model face: the OBJ's faces may be listed in another order, each triangle's
    corners possibly rotated, but they must be the model's triangles."""
    if obj_faces.shape == faces.shape and np.array_equal(obj_faces, faces):
        return obj_tex
    lookup: dict[tuple[int, ...], dict[int, int]] = {}
    for fv, ft in zip(obj_faces.tolist(), obj_tex.tolist(), strict=True):
        lookup[tuple(sorted(fv))] = dict(zip(fv, ft, strict=True))
    out = np.empty_like(faces)
    for i, fv in enumerate(faces.tolist()):
        corner = lookup.get(tuple(sorted(fv)))
        if corner is None:
            raise InputError(f"{path} does not match the body model's mesh (face {i} {fv} is not in it)")
        out[i] = [corner[v] for v in fv]
    return out


def _check_kind_gender(kind: str, gender: str) -> None:
    if kind not in KINDS:
        raise ConfigError(f"unknown SMPL model kind {kind!r}; choose one of {list(KINDS)}")
    if gender not in GENDERS:
        raise ConfigError(f"unknown gender {gender!r}; choose one of {list(GENDERS)}")


# ----------------------------------------------------------------------------- the model

class SMPLBody(BodyModel):
    """SMPL or SMPL-X from user-supplied model files, in the project's conventions (module docstring).

    Args:
        model_dir: folder holding ``smpl/``/``smplx/`` (or the model files), or the model file itself.
        kind: ``"smpl"`` or ``"smplx"``.
        gender: ``"neutral"``, ``"male"`` or ``"female"``.
        num_betas: shape coefficients used (at most what the file has).
        num_expression_coeffs: SMPL-X expression coefficients appended to ``shape`` (ignored for SMPL).
        pose_correctives: apply SMPL's pose-dependent blend shapes (True, as ``smplx`` does).
        face_vertex_ids: vertex ids of nose, left eye, right eye, left ear, right ear; needed only for a
            model whose vertex count is not the standard topology's.
    """

    def __init__(self, model_dir: str | Path, kind: str = "smpl", gender: str = "neutral",
                 num_betas: int = 10, num_expression_coeffs: int = 10, pose_correctives: bool = True,
                 face_vertex_ids: Sequence[int] | None = None, dtype: torch.dtype = torch.float32,
                 device: torch.device | str = "cpu"):
        super().__init__()
        _check_kind_gender(kind, gender)
        self.kind = kind
        self.gender = gender
        self.name = f"{kind}:{gender}"
        self.model_file = find_model_file(model_dir, kind, gender)
        self.pose_correctives = bool(pose_correctives)
        data = load_model_file(self.model_file)
        missing = [k for k in ("v_template", "f", "shapedirs", "posedirs", "J_regressor", "weights",
                               "kintree_table") if k not in data]
        if missing:
            raise InputError(f"{self.model_file} is not an SMPL-family model file: missing {missing}")

        v_template = np.asarray(data["v_template"], np.float64)
        V = len(v_template)
        parents = np.asarray(data["kintree_table"], np.int64)[0].copy()
        J = len(parents)
        names = SMPL_JOINT_NAMES if kind == "smpl" else SMPLX_JOINT_NAMES
        if J != len(names):
            raise InputError(f"{self.model_file} has {J} joints; a {kind} model has {len(names)}")
        parents[0] = -1
        if any(not 0 <= parents[j] < j for j in range(1, J)):
            raise InputError(f"{self.model_file}: the kinematic tree is not ordered parents first")

        shapedirs = np.asarray(data["shapedirs"], np.float64)
        if shapedirs.ndim == 2:
            shapedirs = shapedirs[:, :, None]
        shape_cols, expr_cols = self._shape_columns(shapedirs.shape[-1], num_betas, num_expression_coeffs)
        shape_basis = shapedirs[:, :, shape_cols]  # (V, 3, S)
        posedirs = np.asarray(data["posedirs"], np.float64).reshape(V * 3, -1)
        if posedirs.shape[1] != 9 * (J - 1):
            raise InputError(f"{self.model_file}: posedirs has {posedirs.shape[1]} columns, not {9 * J - 9}")
        weights = np.asarray(data["weights"], np.float64)
        J_regressor = np.asarray(data["J_regressor"], np.float64)
        if weights.shape != (V, J) or J_regressor.shape != (J, V):
            raise InputError(f"{self.model_file}: weights {weights.shape} / J_regressor {J_regressor.shape} "
                             f"do not fit {V} vertices and {J} joints")
        faces = np.asarray(data["f"]).astype(np.int64)

        if face_vertex_ids is None:
            if V != NUM_VERTICES[kind]:
                raise ConfigError(
                    f"{self.model_file} has {V} vertices, not the standard {kind} topology's "
                    f"{NUM_VERTICES[kind]}: pass face_vertex_ids (nose, left/right eye, left/right ear)"
                )
            face_vertex_ids = FACE_VERTEX_IDS[kind]
        face_ids = np.asarray(list(face_vertex_ids), np.int64)
        if face_ids.shape != (5,) or face_ids.min() < 0 or face_ids.max() >= V:
            raise ConfigError(f"face_vertex_ids must be 5 vertex ids below {V}, got {list(face_vertex_ids)}")

        self.joint_names = list(names)
        self.pose_joint_names = self.joint_names[1:]
        self.num_betas = len(shape_cols) - len(expr_cols)
        self.shape_names = [f"beta{i}" for i in range(self.num_betas)] + \
            [f"expression{i}" for i in range(len(expr_cols))]
        self.parents = parents.tolist()

        def buf(name: str, value: np.ndarray, dt: torch.dtype = dtype) -> None:
            tensor = torch.as_tensor(np.ascontiguousarray(value), dtype=dt)
            self.register_buffer(name, tensor, persistent=False)

        buf("v_template", v_template)
        buf("shape_basis", shape_basis)
        buf("pose_basis", posedirs.T)  # (9 (J-1), 3 V)
        buf("J_regressor", J_regressor)
        buf("skinning_weights", weights)
        buf("faces", faces, torch.int64)
        buf("face_vertex_ids", face_ids, torch.int64)
        buf("coco_joint_ids", np.asarray([self.joint_names.index(n) for n in COCO_BODY_JOINTS]), torch.int64)

        self.uv_file: Path | None = None
        uvs, uv_faces = self._uv_layout(data, faces)
        if uvs is not None:
            buf("uvs", uvs)
            buf("uv_faces", uv_faces, torch.int64)
        else:
            self.uvs = None
            self.uv_faces = None
        self.to(device)

    def _shape_columns(self, available: int, num_betas: int, num_expr: int) -> tuple[list[int], list[int]]:
        """Columns of the file's shapedirs used as betas (then expressions, SMPL-X)."""
        if self.kind == "smpl":
            body_dim, expr_start, expr_dim = available, available, 0
        elif available >= 400:  # SMPL-X v1.1: 300 shape + 100 expression components
            body_dim, expr_start, expr_dim = 300, 300, available - 300
        else:  # SMPL-X v1.0: 10 shape + 10 expression components
            body_dim, expr_start, expr_dim = min(10, available), min(10, available), max(available - 10, 0)
        if not 0 < num_betas <= body_dim:
            raise ConfigError(f"num_betas={num_betas}: {self.model_file} has {body_dim} shape components")
        if self.kind == "smpl":
            num_expr = 0
        elif not 0 <= num_expr <= expr_dim:
            raise ConfigError(f"num_expression_coeffs={num_expr}: {self.model_file} has {expr_dim} "
                              f"expression components")
        expr = list(range(expr_start, expr_start + num_expr))
        return list(range(num_betas)) + expr, expr

    def _uv_layout(self, data: dict, faces: np.ndarray) -> tuple[np.ndarray | None, np.ndarray | None]:
        if "vt" in data and "ft" in data and np.asarray(data["ft"]).shape == faces.shape:
            self.uv_file = self.model_file
            return np.asarray(data["vt"], np.float64)[:, :2], np.asarray(data["ft"]).astype(np.int64)
        obj = self.model_file.parent / UV_FILES[self.kind]
        if not obj.is_file():
            return None, None
        vt, obj_faces, obj_tex = read_obj_uvs(obj)
        self.uv_file = obj
        return vt, _match_uv_faces(faces, obj_faces, obj_tex, obj)

    def require_uv_layout(self) -> None:
        """Raise MissingWeightsError naming the UV file when the model has no UV layout."""
        if self.uvs is None:
            raise MissingWeightsError(
                self.model_file.parent / UV_FILES[self.kind],
                f"{self.kind} UV layout (an OBJ of the {self.kind} mesh with texture coordinates), "
                f"needed for UV position maps",
                UV_WHERE_TO_GET[self.kind],
            )

    # ------------------------------------------------------------------ parameters

    def default_shape(self, batch: int = 1) -> torch.Tensor:
        return torch.zeros(batch, len(self.shape_names), dtype=self.dtype, device=self.device)

    def canonical_params(self, batch: int = 1) -> BodyParams:
        params = self.zero_params(batch)
        legs, arms = np.radians(CANONICAL_LEG_SPREAD_DEG), np.radians(CANONICAL_ARM_DROP_DEG)
        # A rotation about +Z (forward) by +a swings a downward left leg towards +X (outward) and a
        # left arm pointing +X downwards when a < 0; the right side mirrors.
        params.pose[:, self.pose_index("left_hip"), 2] = legs
        params.pose[:, self.pose_index("right_hip"), 2] = -legs
        params.pose[:, self.pose_index("left_shoulder"), 2] = -arms
        params.pose[:, self.pose_index("right_shoulder"), 2] = arms
        return params

    def shaped_template(self, shape: torch.Tensor) -> torch.Tensor:
        """(B, V, 3) the template with shape (and expression) blend shapes, native position."""
        return self.v_template + torch.einsum("vds,bs->bvd", self.shape_basis, shape.to(self.dtype))

    def pelvis_offset(self, shape: torch.Tensor) -> torch.Tensor:
        """(B, 3) the rest pelvis (root joint) position in the model file's frame. At ``scale`` 1,
        ``smplx``'s ``transl`` is ``BodyParams.transl - pelvis_offset(shape)`` for any global orientation
        (both rotate the body about the pelvis)."""
        return torch.einsum("v,bvd->bd", self.J_regressor[0], self.shaped_template(shape))

    # ------------------------------------------------------------------ forward

    def forward(self, params: BodyParams) -> BodyOutput:
        B, J, S = params.batch_size, self.num_joints, len(self.shape_names)
        if params.pose.shape[1:] != (J - 1, 3) or params.shape.shape[1:] != (S,):
            raise ValueError(f"{self.name}: pose must be (B, {J - 1}, 3) and shape (B, {S}); "
                             f"got {tuple(params.pose.shape)} and {tuple(params.shape.shape)}")
        v_shaped = self.shaped_template(params.shape)  # (B, V, 3)
        joints_rest = torch.einsum("jv,bvd->bjd", self.J_regressor, v_shaped)  # (B, J, 3)
        root = joints_rest[:, :1]
        rot = axis_angle_to_matrix(params.pose.to(self.dtype))  # (B, J-1, 3, 3)
        rest = v_shaped - root
        if self.pose_correctives:
            eye = torch.eye(3, dtype=rot.dtype, device=rot.device)
            feature = (rot - eye).reshape(B, -1)
            rest = rest + (feature @ self.pose_basis).reshape(B, -1, 3)
        joints_local = joints_rest - root  # rest joints, root at the origin

        # Forward kinematics in the root-centred frame; the root's own rotation is global_orient's.
        eye4 = torch.eye(4, dtype=rot.dtype, device=rot.device).expand(B, 4, 4)
        world = [eye4]
        for j in range(1, J):
            p = self.parents[j]
            local = torch.cat([
                torch.cat([rot[:, j - 1], (joints_local[:, j] - joints_local[:, p])[:, :, None]], dim=2),
                eye4[:, 3:],
            ], dim=1)
            world.append(world[p] @ local)
        frames = torch.stack(world, dim=1)  # (B, J, 4, 4) posed joint frames
        posed_joints = frames[:, :, :3, 3]
        # bone transform = frame @ translate(-rest joint): maps a rest point to its posed position
        offset = posed_joints - (frames[:, :, :3, :3] @ joints_local[..., None])[..., 0]
        bones = torch.cat([torch.cat([frames[:, :, :3, :3], offset[..., None]], dim=3), frames[:, :, 3:]],
                          dim=2)

        G = global_transform(params)  # (B, 4, 4)
        bone_transforms = G[:, None] @ bones
        blended = torch.einsum("vj,bjkl->bvkl", self.skinning_weights, bone_transforms)
        vertices = transform_points(blended, rest)
        joints = transform_points(G[:, None], posed_joints)
        face = vertices[:, self.face_vertex_ids]  # nose, left eye, right eye, left ear, right ear
        coco17 = torch.cat([face, joints[:, self.coco_joint_ids]], dim=1)
        return BodyOutput(vertices=vertices, joints=joints, coco17=coco17, bone_transforms=bone_transforms,
                          rest_vertices=rest)


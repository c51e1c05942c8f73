"""Orbit cameras in the SV3D_p convention, with OpenCV axes.

World frame: Y up, the subject centred at the origin and facing +Z. A camera at azimuth ``az`` and
elevation ``el`` (degrees) sits at ``radius * (sin az cos el, sin el, cos az cos el)`` and looks at
the origin, so azimuth 0 is the front view and azimuth 90 sees the subject's left side.

Camera axes are OpenCV's: x right, y down, z forward. ``c2w`` maps camera to world coordinates;
``w2c`` is its inverse. ``K`` is the pixel intrinsic matrix with the principal point at the image
centre (pixel centres at integer + 0.5, as gsplat and OpenCV use).

:func:`project_points` and :func:`sample_bilinear` are the projection and the image lookup that
follow that pixel convention.

The SV3D_p orbit has 21 frames at ``linspace(0, 360, 22)[1:] % 360``: the last frame (azimuth 0)
is the input view.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from humanvdm_core.io import read_npz, write_npz

SV3D_FRAMES = 21
SV3D_SIZE = 576
SV3D_FOV_DEG = 33.8
DEFAULT_ELEVATION_DEG = 10.0
CAMERAS_SCHEMA = "humanvdm.cameras"
CAMERAS_VERSION = 1


def orbit_azimuths(num_frames: int = SV3D_FRAMES) -> np.ndarray:
    """Azimuths (degrees) of the SV3D_p orbit: evenly spaced, ending at 0 (the input view)."""
    return np.linspace(0.0, 360.0, num_frames + 1)[1:] % 360.0


def intrinsics(fov_y_deg: float, width: int, height: int) -> np.ndarray:
    """3x3 K for a vertical field of view, square pixels, principal point at the image centre."""
    fy = 0.5 * height / np.tan(np.radians(fov_y_deg) / 2.0)
    return np.array([[fy, 0.0, width / 2.0], [0.0, fy, height / 2.0], [0.0, 0.0, 1.0]])


def orbit_position(azimuth_deg, elevation_deg, radius) -> np.ndarray:
    az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    return np.stack([np.sin(az) * np.cos(el), np.sin(el), np.cos(az) * np.cos(el)], axis=-1) * np.asarray(
        radius
    )[..., None]


def look_at(eye: np.ndarray, target: np.ndarray | None = None, up: np.ndarray | None = None) -> np.ndarray:
    """Camera-to-world 4x4 (OpenCV axes) for a camera at ``eye`` looking at ``target`` (default: the
    origin) with ``up`` (default +Y) pointing up in the image."""
    eye = np.asarray(eye, dtype=np.float64)
    target = np.zeros(3) if target is None else np.asarray(target, dtype=np.float64)
    up = np.array([0.0, 1.0, 0.0]) if up is None else np.asarray(up, dtype=np.float64)
    forward = target - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, down, forward, eye
    return c2w


@dataclass
class Cameras:
    """N pinhole cameras of one frame set. Arrays are float64; ``c2w`` uses OpenCV axes."""

    K: np.ndarray  # (N, 3, 3)
    c2w: np.ndarray  # (N, 4, 4)
    width: int
    height: int
    azimuth_deg: np.ndarray  # (N,)
    elevation_deg: np.ndarray  # (N,)
    radius: np.ndarray  # (N,)
    extra: dict[str, np.ndarray] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.c2w)

    @property
    def w2c(self) -> np.ndarray:
        return np.linalg.inv(self.c2w)

    @property
    def fov_y_deg(self) -> np.ndarray:
        return np.degrees(2.0 * np.arctan(0.5 * self.height / self.K[:, 1, 1]))

    def scaled(self, width: int, height: int) -> Cameras:
        """The same cameras for images resampled to ``width`` x ``height``."""
        K = self.K.copy()
        K[:, 0, :] *= width / self.width
        K[:, 1, :] *= height / self.height
        return Cameras(K, self.c2w.copy(), width, height, self.azimuth_deg.copy(),
                       self.elevation_deg.copy(), self.radius.copy(), dict(self.extra))

    def subset(self, index) -> Cameras:
        idx = np.asarray(index)
        return Cameras(self.K[idx], self.c2w[idx], self.width, self.height, self.azimuth_deg[idx],
                       self.elevation_deg[idx], self.radius[idx], dict(self.extra))

    def save(self, path: str | Path) -> None:
        arrays = {
            "K": self.K, "c2w": self.c2w, "w2c": self.w2c,
            "width": np.int64(self.width), "height": np.int64(self.height),
            "azimuth_deg": self.azimuth_deg, "elevation_deg": self.elevation_deg, "radius": self.radius,
        }
        arrays.update({f"extra_{k}": v for k, v in self.extra.items()})
        write_npz(path, arrays, CAMERAS_SCHEMA, CAMERAS_VERSION)

    @classmethod
    def load(cls, path: str | Path) -> Cameras:
        d = read_npz(path, CAMERAS_SCHEMA, CAMERAS_VERSION)
        extra = {k[len("extra_"):]: v for k, v in d.items() if k.startswith("extra_")}
        return cls(d["K"], d["c2w"], int(d["width"]), int(d["height"]), d["azimuth_deg"],
                   d["elevation_deg"], d["radius"], extra)


def orbit_cameras(
    num_frames: int = SV3D_FRAMES,
    size: int = SV3D_SIZE,
    fov_y_deg: float = SV3D_FOV_DEG,
    elevation_deg: float = DEFAULT_ELEVATION_DEG,
    radius: float = 2.0,
    azimuths_deg: np.ndarray | None = None,
) -> Cameras:
    """A static orbit around the origin (SV3D_p azimuths unless ``azimuths_deg`` is given)."""
    az = orbit_azimuths(num_frames) if azimuths_deg is None else np.asarray(azimuths_deg, dtype=np.float64)
    n = len(az)
    el = np.full(n, float(elevation_deg))
    r = np.full(n, float(radius))
    eyes = orbit_position(az, el, r)
    c2w = np.stack([look_at(e) for e in eyes])
    K = np.repeat(intrinsics(fov_y_deg, size, size)[None], n, axis=0)
    return Cameras(K, c2w, size, size, az, el, r)


def _quat_from_matrix(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a rotation matrix."""
    m = R
    t = np.trace(m)
    if t > 0:
        s = np.sqrt(t + 1.0) * 2
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif m[1, 1] > m[2, 2]:
        s = np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    q = np.array(q)
    return q / np.linalg.norm(q)


def _matrix_from_quat(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def slerp(q0: np.ndarray, q1: np.ndarray, t: float) -> np.ndarray:
    dot = float(np.dot(q0, q1))
    if dot < 0:
        q1, dot = -q1, -dot
    if dot > 0.9995:
        q = q0 + t * (q1 - q0)
        return q / np.linalg.norm(q)
    theta = np.arccos(dot)
    return (np.sin((1 - t) * theta) * q0 + np.sin(t * theta) * q1) / np.sin(theta)


def interpolate_cameras(cams: Cameras, i: int, t: float) -> tuple[np.ndarray, np.ndarray, float, float, float]:
    """Camera between frames ``i`` and ``i + 1`` at fraction ``t``.

    Rotation by quaternion slerp; position on the orbit (azimuth along the shorter arc, elevation
    and radius linearly), so in-between cameras stay on the circle instead of cutting its chord.
    Returns (K, c2w, azimuth_deg, elevation_deg, radius).
    """
    j = i + 1
    d_az = (cams.azimuth_deg[j] - cams.azimuth_deg[i] + 180.0) % 360.0 - 180.0
    az = (cams.azimuth_deg[i] + t * d_az) % 360.0
    el = (1 - t) * cams.elevation_deg[i] + t * cams.elevation_deg[j]
    r = (1 - t) * cams.radius[i] + t * cams.radius[j]
    q = slerp(_quat_from_matrix(cams.c2w[i, :3, :3]), _quat_from_matrix(cams.c2w[j, :3, :3]), t)
    c2w = np.eye(4)
    c2w[:3, :3] = _matrix_from_quat(q)
    # Orbit centre: the point the two cameras' positions are measured from (origin for our orbits).
    centre_i = cams.c2w[i, :3, 3] - orbit_position(cams.azimuth_deg[i], cams.elevation_deg[i], cams.radius[i])
    centre_j = cams.c2w[j, :3, 3] - orbit_position(cams.azimuth_deg[j], cams.elevation_deg[j], cams.radius[j])
    c2w[:3, 3] = (1 - t) * centre_i + t * centre_j + orbit_position(az, el, r)
    K = (1 - t) * cams.K[i] + t * cams.K[j]
    return K, c2w, float(az), float(el), float(r)


def upsample_cameras(cams: Cameras, factor: int) -> Cameras:
    """Insert ``factor - 1`` interpolated cameras between consecutive frames (N -> (N-1)*factor+1)."""
    Ks, c2ws, azs, els, rs = [], [], [], [], []
    for i in range(len(cams) - 1):
        for k in range(factor):
            if k == 0:  # keep the original camera exactly
                K, c2w = cams.K[i], cams.c2w[i]
                az, el, r = cams.azimuth_deg[i], cams.elevation_deg[i], cams.radius[i]
            else:
                K, c2w, az, el, r = interpolate_cameras(cams, i, k / factor)
            Ks.append(K), c2ws.append(c2w), azs.append(az), els.append(el), rs.append(r)
    last = len(cams) - 1
    Ks.append(cams.K[last]), c2ws.append(cams.c2w[last])
    azs.append(cams.azimuth_deg[last]), els.append(cams.elevation_deg[last]), rs.append(cams.radius[last])
    return Cameras(np.stack(Ks), np.stack(c2ws), cams.width, cams.height, np.array(azs), np.array(els),
                   np.array(rs), dict(cams.extra))


def project_points(points: np.ndarray, w2c: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World points (P, 3) in one camera (``w2c`` 4x4, ``K`` 3x3): pixel coordinates (P, 2) and camera
    depths (P,) (points behind the camera divide by 1e-6)."""
    cam = points @ w2c[:3, :3].T + w2c[:3, 3]
    z = cam[:, 2]
    px = cam[:, :2] / np.maximum(z, 1e-6)[:, None] * np.array([K[0, 0], K[1, 1]]) + K[:2, 2]
    return px, z


def sample_bilinear(image: np.ndarray, px: np.ndarray) -> np.ndarray:
    """Bilinear samples (P, C) of ``image`` (H, W, C) at pixel coordinates ``px`` (P, 2), pixel centres at
    +0.5, the border replicated outside."""
    import cv2

    image = np.ascontiguousarray(image, dtype=np.float32)
    mx = (px[:, 0] - 0.5).astype(np.float32).reshape(-1, 1)
    my = (px[:, 1] - 0.5).astype(np.float32).reshape(-1, 1)
    chunk = 32000  # cv2.remap's maps hold fewer than SHRT_MAX (32767) rows
    out = [cv2.remap(image, mx[i:i + chunk], my[i:i + chunk], interpolation=cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE).reshape(min(chunk, len(px) - i), -1)
           for i in range(0, len(px), chunk)]
    return np.concatenate(out) if out else np.zeros((0, image.shape[2] if image.ndim == 3 else 1), np.float32)

"""Camera maths. Conventions: OpenCV camera axes (x right, y down, z forward); poses are
world-to-camera (W2C) 4x4 float64; the world is right-handed with +z up; radians inside.
"""

from __future__ import annotations

import numpy as np

WORLD_UP = np.array([0.0, 0.0, 1.0])


def intrinsics(width: int, height: int, fov_deg: float) -> np.ndarray:
    """Pinhole K (3x3, pixels) for a horizontal field of view; pixel centres at +0.5, so cx = W/2."""
    fx = 0.5 * width / np.tan(0.5 * np.radians(fov_deg))
    return np.array([[fx, 0.0, width / 2.0], [0.0, fx, height / 2.0], [0.0, 0.0, 1.0]])


def se3(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """4x4 rigid transform from a rotation and a translation."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def invert_se3(T: np.ndarray) -> np.ndarray:
    """Inverse of one (4,4) or a stack (N,4,4) of rigid transforms."""
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    out = np.zeros_like(T, dtype=np.float64)
    Rt = np.swapaxes(R, -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    out[..., 3, 3] = 1.0
    return out


def camera_centers(w2c: np.ndarray) -> np.ndarray:
    """Camera centres in world coordinates, (N,3), from W2C poses (N,4,4): c = -R^T t."""
    R = w2c[..., :3, :3]
    t = w2c[..., :3, 3]
    return -np.einsum("...ji,...j->...i", R, t)


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = WORLD_UP) -> np.ndarray:
    """W2C pose of a camera at `eye` looking at `target`, with image-up along `up` (no roll)."""
    eye = np.asarray(eye, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, dtype=np.float64))
    if np.linalg.norm(x) < 1e-9:
        raise ValueError("look_at: viewing direction is parallel to up")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])  # rows: camera axes expressed in world coordinates
    return se3(R, -R @ eye)

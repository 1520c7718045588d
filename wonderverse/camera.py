"""Camera maths. Conventions: OpenCV camera axes (x right, y down, z forward); poses are
world-to-camera (W2C) 4x4 float64; the world is right-handed with +z up; radians inside.

Rotations act on column vectors (`p' = R @ p`). Quaternions are Hamilton, scalar first (w, x, y, z),
the same rotation as `scipy.spatial.transform.Rotation.from_quat([x, y, z, w])`. Functions accept
stacks over leading axes where that is natural (`(..., 3)`, `(..., 3, 3)`, `(..., 4)`, `(..., 4, 4)`).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

DEFAULT_FOV_DEG = 60.0  # horizontal field of view of a video whose camera nobody stated

WORLD_UP = np.array([0.0, 0.0, 1.0])

# Relative size of the second singular value below which a point set counts as collinear (or coincident).
UMEYAMA_DEGENERATE_RTOL = 1e-10
# Horizontal length of a unit forward vector below which the camera counts as looking straight up/down.
VERTICAL_VIEW_TOL = 1e-9
# Points closer together than this, relative to their coordinates' size (at least 1), count as one point.
STILL_REL_TOL = 1e-9


def intrinsics(width: int, height: int, fov_deg: float) -> np.ndarray:
    """Pinhole K (3x3, pixels) for a horizontal field of view; pixel centres at +0.5, so cx = W/2."""
    fx = 0.5 * width / np.tan(0.5 * np.radians(fov_deg))
    return np.array([[fx, 0.0, width / 2.0], [0.0, fx, height / 2.0], [0.0, 0.0, 1.0]])


def fit_intrinsics(width: int, height: int, K: np.ndarray, max_side_px: int) -> tuple[int, int, np.ndarray]:
    """(w, h, K') of an image of width x height with K (3,3) or (T,3,3) resized so that its longer side is
    at most `max_side_px` (never enlarged): each side rounded (at least 1 pixel), K's rows scaled by the
    side's exact ratio (pixel centres stay at +0.5). A copy of K (float64) even when nothing changes."""
    s = min(1.0, max_side_px / max(width, height))
    w, h = max(1, round(width * s)), max(1, round(height * s))
    Ks = np.asarray(K, np.float64).copy()
    Ks[..., 0, :] *= w / width
    Ks[..., 1, :] *= h / height
    return w, h, Ks


@dataclass(frozen=True, eq=False)
class CameraPrior:
    """What is known of a video's intrinsics before SfM: K (3,3, pixels of its frames) and where it came from.
    source "given": the camera's own (the renderer's K, or a clip whose field of view the user gave); "guessed":
    an assumed field of view (`DEFAULT_FOV_DEG` for a clip nobody described). No prior at all is None where a
    CameraPrior is expected. K is kept as a float64 copy; ValueError for a K that is not finite (3,3) with
    positive focal lengths, or another source."""

    K: np.ndarray
    source: Literal["given", "guessed"]

    def __post_init__(self) -> None:
        K = np.array(self.K, dtype=np.float64)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise ValueError(f"a camera prior's K must be finite (3,3) with positive focal lengths, got {self.K!r}")
        if self.source not in ("given", "guessed"):
            raise ValueError(f"a camera prior's source is 'given' or 'guessed', got {self.source!r}")
        K.flags.writeable = False  # frozen means frozen: the matrix too
        object.__setattr__(self, "K", K)

    @property
    def given(self) -> bool:
        """The camera's own K, not a guess."""
        return self.source == "given"


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


def pixels_to_world(u: np.ndarray, v: np.ndarray, z: np.ndarray, K: np.ndarray, w2c: np.ndarray) -> np.ndarray:
    """World points (..., 3) float64 of pixel positions u, v (pixel centres at +0.5) at camera z `z` (arrays of one
    shape), seen through K (3,3) from W2C (4,4): R^T (x_cam - t)."""
    z = np.asarray(z, np.float64)
    cam = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], axis=-1)
    w2c = np.asarray(w2c, np.float64)
    return (cam - w2c[:3, 3]) @ w2c[:3, :3]


def world_to_pixels(
    points: np.ndarray, K: np.ndarray, w2c: np.ndarray, h: int, w: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The inverse of `pixels_to_world`: pixel positions u, v (centres at +0.5) and camera z of world points (M,3)
    seen through K (3,3) from W2C (4,4), and whether each lies in front of the camera inside an h×w image
    ((M,) float64 ×3, (M,) bool; u and v are inf or NaN where z is 0)."""
    cam = np.asarray(points, np.float64) @ w2c[:3, :3].T + w2c[:3, 3]
    z = cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u, v = K[0, 0] * cam[:, 0] / z + K[0, 2], K[1, 1] * cam[:, 1] / z + K[1, 2]
    framed = (z > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    return u, v, z, framed


def camera_radius(w2c: np.ndarray) -> float:
    """Largest distance (world units) of a camera centre from the centres' mean, for finite W2C poses
    (N,4,4); 0 for none. What the splats' normalisation and their training scale are relative to."""
    centres = camera_centers(np.asarray(w2c, dtype=np.float64).reshape(-1, 4, 4))
    return float(np.max(np.linalg.norm(centres - centres.mean(axis=0), axis=1))) if len(centres) else 0.0


def span(points: np.ndarray) -> float:
    """Bounding-box diagonal of points (M,3) (world units); 0 when they coincide up to rounding
    (closer than `STILL_REL_TOL` of their coordinates' size, at least 1) or when there are none."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if not len(points):
        return 0.0
    e = float(np.linalg.norm(points.max(0) - points.min(0)))
    return 0.0 if e <= STILL_REL_TOL * max(1.0, float(np.abs(points).max())) else e


def scene_extent(w2c: np.ndarray, depths: Iterable[np.ndarray] | None = None) -> float:
    """The scene's size in world units: the bounding-box diagonal of the finite cameras' centres (W2C
    (N,4,4); `span`, so 0 for a camera that only turns), plus, when `depths` (camera z maps) are given,
    2 x the median of all their valid values (finite, > 0): how far the cameras see, the median keeping a
    few far pixels (distant terrain) from inflating it. With depths the result is positive: 1.0 when
    nothing is valid. Lengths of the fly-through and novel-view paths and of the TSDF mesh are fractions
    of it."""
    w2c = np.asarray(w2c, np.float64).reshape(-1, 4, 4)
    extent = span(camera_centers(w2c[np.isfinite(w2c).all(axis=(1, 2))]))
    if depths is None:
        return extent
    valid = [d[np.isfinite(d) & (d > 0)] for d in (np.asarray(x, np.float32) for x in depths)]
    allz = np.concatenate(valid) if valid else np.zeros(0, np.float32)
    extent = extent + 2.0 * float(np.median(allz)) if allz.size else extent
    return extent if extent > 0 and np.isfinite(extent) else 1.0


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


# ----------------------------------------------------------------------------------------------- SO(3)


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices (..., 3, 3) of vectors (..., 3): skew(a) @ b == cross(a, b)."""
    v = np.asarray(v, dtype=np.float64)
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    o = np.zeros_like(x)
    return np.stack([np.stack([o, -z, y], -1), np.stack([z, o, -x], -1), np.stack([-y, x, o], -1)], -2)


def _vee(A: np.ndarray) -> np.ndarray:
    """Axial vector (..., 3) of the antisymmetric part of (..., 3, 3) matrices: vee((A - A^T) / 2)."""
    return 0.5 * np.stack([A[..., 2, 1] - A[..., 1, 2], A[..., 0, 2] - A[..., 2, 0], A[..., 1, 0] - A[..., 0, 1]], -1)


def _sinc(x: np.ndarray) -> np.ndarray:
    """sin(x)/x, exact at 0 and free of cancellation near it (numpy's sinc is normalised by pi)."""
    return np.sinc(np.asarray(x) / np.pi)


def so3_exp(omega: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of rotation vectors (..., 3) (axis * angle, radians; Rodrigues).

    R = I + sinc(θ) [ω]x + ½ sinc²(θ/2) [ω]x², which has no division by θ, so it is exact at and near 0.
    """
    omega = np.asarray(omega, dtype=np.float64)
    theta = np.linalg.norm(omega, axis=-1)[..., None, None]
    K = skew(omega)
    a = _sinc(theta)
    b = 0.5 * _sinc(0.5 * theta) ** 2  # (1 - cos θ) / θ² without cancellation
    return np.eye(3) + a * K + b * (K @ K)


def _angle_and_sin_axis(R: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(θ, sinθ·axis, cosθ) of rotations (..., 3, 3); θ from atan2 so it is accurate at 0 and at π."""
    v = _vee(R)
    c = 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0)
    return np.arctan2(np.linalg.norm(v, axis=-1), c), v, c


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation vectors (..., 3) (axis * angle, angle in [0, π]) of rotation matrices (..., 3, 3).

    The angle comes from atan2(|sin part|, cos part). The axis comes from the antisymmetric part when
    cos θ >= 0 and from the symmetric part R + R^T = 2cosθ I + 2(1 - cosθ) a a^T otherwise, which stays
    accurate as θ -> π (where the antisymmetric part vanishes). At exactly π either sign is returned;
    both re-exponentiate to R.
    """
    R = np.asarray(R, dtype=np.float64)
    theta, v, c = _angle_and_sin_axis(R)
    sin_norm = np.linalg.norm(v, axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        # Small/medium angles: ω = v · θ / sinθ, with the ratio -> 1 at the identity.
        ratio = np.where(sin_norm > 0.0, theta / np.where(sin_norm > 0.0, sin_norm, 1.0), 1.0)
        small = v * ratio[..., None]
        # Large angles: a a^T = (sym(R) - cosθ I) / (1 - cosθ); take the column with the largest diagonal.
        one_minus_c = np.where(c < 0.0, 1.0 - c, 1.0)
        M = (0.5 * (R + np.swapaxes(R, -1, -2)) - c[..., None, None] * np.eye(3)) / one_minus_c[..., None, None]
        diag = np.diagonal(M, axis1=-2, axis2=-1)
        k = np.argmax(diag, axis=-1)
        col = np.take_along_axis(M, k[..., None, None], axis=-1)[..., 0]
        dk = np.take_along_axis(diag, k[..., None], axis=-1)
        axis = col / np.sqrt(np.maximum(dk, 1e-300))
        axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
        # The symmetric part fixes the axis up to sign; the antisymmetric part (sinθ·a) gives the sign.
        sign = np.where(np.sum(axis * v, axis=-1) < 0.0, -1.0, 1.0)
        large = axis * (sign * theta)[..., None]
    return np.where((c < 0.0)[..., None], large, small)


def geodesic_angle(R0: np.ndarray, R1: np.ndarray) -> np.ndarray:
    """Angle (radians, in [0, π]) of the rotation R0^T R1 between rotations (..., 3, 3); atan2-based."""
    rel = np.swapaxes(np.asarray(R0, dtype=np.float64), -1, -2) @ np.asarray(R1, dtype=np.float64)
    return _angle_and_sin_axis(rel)[0]


# ----------------------------------------------------------------------------------------- quaternions


def quat_from_matrix(R: np.ndarray) -> np.ndarray:
    """Unit quaternions (..., 4), wxyz with w >= 0, of rotation matrices (..., 3, 3). For a rotation by π
    (w = 0 up to rounding, where q and -q are equally canonical) either sign may come out; both give R.

    Shepperd's method: of the four ways to recover the quaternion, use the one dividing by the largest
    component, so nothing is divided by a small number.
    """
    R = np.asarray(R, dtype=np.float64)
    r00, r01, r02 = R[..., 0, 0], R[..., 0, 1], R[..., 0, 2]
    r10, r11, r12 = R[..., 1, 0], R[..., 1, 1], R[..., 1, 2]
    r20, r21, r22 = R[..., 2, 0], R[..., 2, 1], R[..., 2, 2]
    # Rows: 4 * q * q_k for k = w, x, y, z; row k is the best conditioned when q_k is the largest.
    cands = np.stack(
        [
            np.stack([1.0 + r00 + r11 + r22, r21 - r12, r02 - r20, r10 - r01], -1),
            np.stack([r21 - r12, 1.0 + r00 - r11 - r22, r01 + r10, r02 + r20], -1),
            np.stack([r02 - r20, r01 + r10, 1.0 - r00 + r11 - r22, r12 + r21], -1),
            np.stack([r10 - r01, r02 + r20, r12 + r21, 1.0 - r00 - r11 + r22], -1),
        ],
        -2,
    )
    diag = np.stack([1.0 + r00 + r11 + r22, 1.0 + r00 - r11 - r22, 1.0 - r00 + r11 - r22, 1.0 - r00 - r11 + r22], -1)
    k = np.argmax(diag, axis=-1)
    q = np.take_along_axis(cands, k[..., None, None], axis=-2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0.0, -q, q)


def quat_matrix_entries(w: Any, x: Any, y: Any, z: Any) -> list[Any]:
    """The nine entries, row by row, of the rotation matrix of the unit quaternion (w, x, y, z).

    Plain arithmetic, so the components may be NumPy arrays or torch tensors (the one formula behind
    `matrix_from_quat` and the Gaussians' differentiable `splats.model.quat_to_rotmat`).
    """
    return [
        1 - 2 * (y * y + z * z),
        2 * (x * y - w * z),
        2 * (x * z + w * y),
        2 * (x * y + w * z),
        1 - 2 * (x * x + z * z),
        2 * (y * z - w * x),
        2 * (x * z - w * y),
        2 * (y * z + w * x),
        1 - 2 * (x * x + y * y),
    ]


def matrix_from_quat(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of quaternions (..., 4), wxyz; normalises first, so q and -q (and
    any positive multiple) give the same matrix.

    Raises ValueError if any quaternion is zero or not finite (a camera has no such rotation; the
    Gaussians' convention, zero = identity, is `splats.model.quat_to_rotmat`'s).
    """
    q = np.asarray(q, dtype=np.float64)
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    if not np.all(np.isfinite(q)) or np.any(n == 0.0):
        raise ValueError("matrix_from_quat: quaternion is zero or not finite")
    entries = quat_matrix_entries(*np.moveaxis(q / n, -1, 0))
    return np.stack(entries, -1).reshape(*q.shape[:-1], 3, 3)


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a*b of wxyz quaternions (..., 4), broadcasting over leading axes: the rotation
    of b followed by that of a (`matrix_from_quat(a * b) == matrix_from_quat(a) @ matrix_from_quat(b)`)."""
    aw, ax, ay, az = np.moveaxis(np.asarray(a), -1, 0)
    bw, bx, by, bz = np.moveaxis(np.asarray(b), -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def quat_slerp(q0: np.ndarray, q1: np.ndarray, t: np.ndarray | float) -> np.ndarray:
    """Spherical linear interpolation of unit quaternions (wxyz) along the shortest arc.

    q0, q1: (..., 4); t: scalar or array, broadcast against their leading axes (t = 0 -> q0, 1 -> q1).
    Returns unit quaternions (..., 4) turning at constant angular velocity in t. q1 and -q1 give the
    same rotations. The weights sin((1-t)Ω)/sinΩ are written with sinc, so (nearly) equal quaternions
    need no special case.
    """
    q0 = np.asarray(q0, dtype=np.float64)
    q1 = np.asarray(q1, dtype=np.float64)
    q0 = q0 / np.linalg.norm(q0, axis=-1, keepdims=True)
    q1 = q1 / np.linalg.norm(q1, axis=-1, keepdims=True)
    q1 = np.where(np.sum(q0 * q1, axis=-1, keepdims=True) < 0.0, -q1, q1)  # shortest path
    t = np.asarray(t, dtype=np.float64)[..., None]
    # Angle between the quaternions (half the rotation angle), in [0, π/2]; atan2 form is accurate near 0.
    omega = 2.0 * np.arctan2(
        np.linalg.norm(q1 - q0, axis=-1, keepdims=True), np.linalg.norm(q1 + q0, axis=-1, keepdims=True)
    )
    s = _sinc(omega)
    w0 = (1.0 - t) * _sinc((1.0 - t) * omega) / s
    w1 = t * _sinc(t * omega) / s
    q = w0 * q0 + w1 * q1
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


# ----------------------------------------------------------------------------------------------- Sim(3)


@dataclass(frozen=True, eq=False)
class Sim3:
    """Similarity transform x -> s * R @ (x - center) + t (s > 0, R a rotation). Arrays are stored read-only.

    `center` is zero for a plain similarity (`Sim3(s, R, t)`). A similarity about a point, such as the
    splats' scene normalisation (move the cameras' mean `center` to the origin, then scale), keeps it
    instead of folding it into t = -s R center: subtracting first keeps far-off coordinates exact.
    """

    s: float
    R: np.ndarray
    t: np.ndarray
    center: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        s = float(self.s)
        R = np.array(self.R, dtype=np.float64)
        t = np.array(self.t, dtype=np.float64)
        c = np.array(self.center, dtype=np.float64)
        if R.shape != (3, 3) or t.shape != (3,) or c.shape != (3,):
            raise ValueError(f"Sim3: R must be (3,3), t and center (3,), got {R.shape}, {t.shape} and {c.shape}")
        if not (np.isfinite(s) and s > 0.0):
            raise ValueError(f"Sim3: scale must be finite and positive, got {s}")
        for a in (R, t, c):
            a.setflags(write=False)
        object.__setattr__(self, "s", s)
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "center", c)

    @classmethod
    def identity(cls) -> Sim3:
        """The identity transform."""
        return cls(1.0, np.eye(3), np.zeros(3))

    @property
    def translation(self) -> np.ndarray:
        """The translation of the matrix form x -> s R x + translation: t - s R center."""
        return self.t - self.s * (self.R @ self.center)

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Transformed points (..., 3): s * R @ (p - center) + t."""
        return self.s * ((np.asarray(points, dtype=np.float64) - self.center) @ self.R.T) + self.t

    def apply_inverse(self, points: np.ndarray) -> np.ndarray:
        """Points (..., 3) mapped back: R^T (p - t) / s + center (`inverse().apply` up to rounding)."""
        return (np.asarray(points, dtype=np.float64) - self.t) @ self.R / self.s + self.center

    def matrix(self) -> np.ndarray:
        """4x4 homogeneous matrix [[s R, translation], [0, 1]]."""
        M = np.eye(4)
        M[:3, :3] = self.s * self.R
        M[:3, 3] = self.translation
        return M

    def inverse(self) -> Sim3:
        """The inverse transform: p -> R^T (p - t) / s + center (a similarity about t)."""
        return Sim3(1.0 / self.s, self.R.T, self.center, center=self.t)

    def compose(self, other: Sim3) -> Sim3:
        """self ∘ other: `a.compose(b).apply(p) == a.apply(b.apply(p))`."""
        t = self.s * (self.R @ (other.t - self.center)) + self.t
        return Sim3(self.s * other.s, self.R @ other.R, t, center=other.center)

    def transform_w2c(self, w2c: np.ndarray) -> np.ndarray:
        """W2C poses (..., 4, 4) expressed in the new world, where new_point = s R (old_point - center) + t.

        The scene (and the camera centres) move by this Sim3; camera rotations become R_c R^T; the result
        is again rigid (unit-scale rotation), so camera-space coordinates and depths scale by s:
        t_c' = s (t_c + R_c center) - R_c R^T t. Non-finite poses stay non-finite.
        """
        w2c = np.asarray(w2c, dtype=np.float64)
        Rw = w2c[..., :3, :3]
        Rc = Rw @ self.R.T
        tc = self.s * (np.einsum("...ij,j->...i", Rw, self.center) + w2c[..., :3, 3])
        tc = tc - np.einsum("...ij,j->...i", Rc, self.t)
        out = np.zeros_like(w2c)
        out[..., :3, :3] = Rc
        out[..., :3, 3] = tc
        out[..., 3, 3] = 1.0
        return out

    def inverse_transform_w2c(self, w2c: np.ndarray) -> np.ndarray:
        """W2C poses (..., 4, 4) of the new world back in the old one (`transform_w2c` undone)."""
        w2c = np.asarray(w2c, dtype=np.float64)
        Rc = w2c[..., :3, :3] @ self.R
        tc = (w2c[..., :3, 3] + np.einsum("...ij,j->...i", w2c[..., :3, :3], self.t)) / self.s
        tc = tc - np.einsum("...ij,j->...i", Rc, self.center)
        out = np.zeros_like(w2c)
        out[..., :3, :3] = Rc
        out[..., :3, 3] = tc
        out[..., 3, 3] = 1.0
        return out

    def to_dict(self) -> dict[str, Any]:
        """JSON-able {"s", "R", "t"} (and "center" when it is not zero); `from_dict` reads it back."""
        d: dict[str, Any] = {"s": float(self.s), "R": self.R.tolist(), "t": self.t.tolist()}
        if self.center.any():
            d["center"] = self.center.tolist()
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Sim3:
        """The Sim3 of `to_dict`'s {"s", "R", "t"[, "center"]}."""
        return cls(d["s"], d["R"], d["t"], center=d.get("center", np.zeros(3)))


def _degenerate(points_centred: np.ndarray) -> bool:
    """True when centred points (N,3) span fewer than 2 dimensions (coincident or collinear)."""
    sv = np.linalg.svd(points_centred, compute_uv=False)
    return bool(sv[0] == 0.0 or sv[1] <= UMEYAMA_DEGENERATE_RTOL * sv[0])


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = True, allow_degenerate: bool = False) -> Sim3:
    """Least-squares Sim3 (or SE3 when with_scale=False, s = 1) minimising sum ||dst - (s R src + t)||².

    src, dst: (N, 3) corresponding points. Umeyama (1991) with the reflection fix, so R is always a
    proper rotation. Raises ValueError for N < 3, mismatched shapes, non-finite points, or (unless
    allow_degenerate) collinear/coincident point sets, for which R is not unique. With
    allow_degenerate=True collinear sets return one of the equally good minimisers (useful for residual
    metrics such as ATE); coincident src still raises when with_scale (the scale is undefined).
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.ndim != 2 or src.shape[1] != 3 or src.shape != dst.shape:
        raise ValueError(f"umeyama: src and dst must both be (N,3), got {src.shape} and {dst.shape}")
    if src.shape[0] < 3:
        raise ValueError(f"umeyama: need at least 3 point pairs, got {src.shape[0]}")
    if not (np.all(np.isfinite(src)) and np.all(np.isfinite(dst))):
        raise ValueError("umeyama: points must be finite (drop NaN/inf rows first)")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d  # centring first keeps large coordinates (1e5) accurate
    if not allow_degenerate:
        for name, pts in (("src", xs), ("dst", xd)):
            if _degenerate(pts):
                raise ValueError(f"umeyama: {name} points are collinear or coincident; the rotation is not unique")
    n = src.shape[0]
    cov = xd.T @ xs / n
    U, D, Vt = np.linalg.svd(cov)
    if not allow_degenerate and D[1] <= UMEYAMA_DEGENERATE_RTOL * D[0]:
        raise ValueError("umeyama: cross-covariance has rank < 2; the rotation is not unique")
    S = np.ones(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0.0:
        S[2] = -1.0  # best proper rotation instead of a reflection
    R = U @ np.diag(S) @ Vt
    if with_scale:
        var_s = np.sum(xs * xs) / n
        if var_s == 0.0:
            raise ValueError("umeyama: src points coincide; the scale is undefined")
        s = float(np.sum(D * S) / var_s)
        if not s > 0.0:
            raise ValueError("umeyama: dst points coincide or are uncorrelated with src; scale is not positive")
    else:
        s = 1.0
    return Sim3(s, R, mu_d - s * (R @ mu_s))


# ---------------------------------------------------------------------------------------- trajectories


def _smoothstep(u: np.ndarray) -> np.ndarray:
    """3u² - 2u³: 0 -> 0, 1 -> 1, zero velocity at both ends."""
    return u * u * (3.0 - 2.0 * u)


def _w2c_from(R: np.ndarray, centers: np.ndarray) -> np.ndarray:
    """W2C poses (..., 4, 4) from rotations (..., 3, 3) and camera centres (..., 3): t = -R c."""
    out = np.zeros((*R.shape[:-2], 4, 4))
    out[..., :3, :3] = R
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", R, centers)
    out[..., 3, 3] = 1.0
    return out


def interpolate_poses(key_w2c: np.ndarray, key_times: np.ndarray, times: np.ndarray, ease: bool = True) -> np.ndarray:
    """W2C poses (N, 4, 4) at `times` between key poses (K, 4, 4) at strictly increasing `key_times` (K,).

    Between two keys the rotation follows the slerp (shortest arc) and the camera centre the straight
    line, both driven by the same parameter u in [0, 1] so they stay in step; with ease, u is
    smoothstepped (the camera slows to rest at every key). Times outside the keys clamp to the end keys.
    """
    key_w2c = np.asarray(key_w2c, dtype=np.float64)
    key_times = np.asarray(key_times, dtype=np.float64)
    times = np.asarray(times, dtype=np.float64)
    K = key_w2c.shape[0]
    if key_w2c.shape[1:] != (4, 4) or key_times.shape != (K,) or K == 0:
        raise ValueError(
            f"interpolate_poses: need key_w2c (K,4,4) and key_times (K,), K >= 1; got "
            f"{key_w2c.shape} and {key_times.shape}"
        )
    if K > 1 and not np.all(np.diff(key_times) > 0.0):
        raise ValueError("interpolate_poses: key_times must be strictly increasing")
    if K == 1:
        return np.repeat(key_w2c, times.shape[0], axis=0)
    i = np.clip(np.searchsorted(key_times, times, side="right") - 1, 0, K - 2)
    u = np.clip((times - key_times[i]) / (key_times[i + 1] - key_times[i]), 0.0, 1.0)
    if ease:
        u = _smoothstep(u)
    q = quat_from_matrix(key_w2c[:, :3, :3])
    R = matrix_from_quat(quat_slerp(q[i], q[i + 1], u))
    c = camera_centers(key_w2c)
    centers = (1.0 - u)[:, None] * c[i] + u[:, None] * c[i + 1]
    return _w2c_from(R, centers)


def rot_z(a: np.ndarray | float) -> np.ndarray:
    """Rotations (..., 3, 3) by angles `a` (radians, any shape) about +z, counter-clockwise seen from above."""
    a = np.asarray(a, dtype=np.float64)
    c, s = np.cos(a), np.sin(a)
    o, one = np.zeros_like(a), np.ones_like(a)
    return np.stack([np.stack([c, -s, o], -1), np.stack([s, c, o], -1), np.stack([o, o, one], -1)], -2)


def rot_x(a: np.ndarray | float) -> np.ndarray:
    """Rotations (..., 3, 3) by angles `a` (radians, any shape) about +x (y towards z)."""
    a = np.asarray(a, dtype=np.float64)
    c, s = np.cos(a), np.sin(a)
    o, one = np.zeros_like(a), np.ones_like(a)
    return np.stack([np.stack([one, o, o], -1), np.stack([o, c, -s], -1), np.stack([o, s, c], -1)], -2)


def _horizontal_heading(R_w2c: np.ndarray) -> np.ndarray:
    """Unit horizontal forward direction (3,) of a camera: its optical axis projected on the ground plane.

    For a camera looking straight up or down, the direction is taken from its x axis (left = -x).
    """
    f = R_w2c[2].copy()
    f[2] = 0.0
    n = np.linalg.norm(f)
    if n > VERTICAL_VIEW_TOL:
        return f / n
    left = -R_w2c[0].copy()
    left[2] = 0.0
    left /= np.linalg.norm(left)
    return np.cross(left, WORLD_UP)


def move_path(
    start_w2c: np.ndarray,
    yaw_rad: float,
    pitch_rad: float,
    forward_m: float,
    strafe_m: float,
    n_frames: int,
    ease: bool = False,
) -> np.ndarray:
    """W2C poses (n_frames, 4, 4) of a camera move starting exactly at `start_w2c` (frame 0).

    Frame k has progress u = k / (n_frames - 1) (smoothstepped when ease). At progress u:
    - heading turned by u * yaw_rad about the world up axis +z; positive = turn LEFT (counter-clockwise
      seen from above);
    - pitch changed by u * pitch_rad about the camera's own x axis; positive = look UP;
    - centre = start centre + u * forward_m * h + u * strafe_m * l, where h is the start optical axis
      projected on the horizontal plane (unit) and l = z × h the horizontal left direction (positive
      strafe = left, negative = right, negative forward = back).
    Yaw (left-multiplied, world z) and pitch (right-multiplied, camera x) commute, and neither adds roll:
    a camera with a horizontal x axis keeps it. A paper move "left 30, up 10, forward 2" is
    yaw_rad=radians(30), pitch_rad=radians(10), forward_m=2, strafe_m=0.
    """
    start = np.asarray(start_w2c, dtype=np.float64)
    if start.shape != (4, 4):
        raise ValueError(f"move_path: start_w2c must be (4,4), got {start.shape}")
    if n_frames < 1:
        raise ValueError(f"move_path: n_frames must be >= 1, got {n_frames}")
    u = np.linspace(0.0, 1.0, n_frames) if n_frames > 1 else np.zeros(1)
    if ease:
        u = _smoothstep(u)
    R0 = start[:3, :3]
    h = _horizontal_heading(R0)
    left = np.cross(WORLD_UP, h)
    c0 = camera_centers(start)
    centers = c0 + (u * forward_m)[:, None] * h + (u * strafe_m)[:, None] * left
    # C2W rotation R^T: world yaw on the left, camera-frame pitch on the right.
    c2w = rot_z(u * yaw_rad) @ R0.T @ rot_x(u * pitch_rad)
    out = _w2c_from(np.swapaxes(c2w, -1, -2), centers)
    out[0] = start  # exactly, not up to the rounding of t -> c -> t
    return out


def heading_pitch(w2c: np.ndarray) -> tuple[np.ndarray | float, np.ndarray | float]:
    """(yaw, pitch) in radians of W2C cameras (..., 4, 4), from their optical axis in world coordinates.

    yaw: counter-clockwise from world +x about +z, in (-π, π]; pitch: elevation above the horizontal
    plane, in [-π/2, π/2] (positive = looking up). Floats for one pose, arrays for a stack.
    """
    f = np.asarray(w2c, dtype=np.float64)[..., 2, :3]
    yaw = np.arctan2(f[..., 1], f[..., 0])
    pitch = np.arctan2(f[..., 2], np.hypot(f[..., 0], f[..., 1]))
    if yaw.ndim == 0:
        return float(yaw), float(pitch)
    return yaw, pitch


def relative_motion_steps(w2c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-step motion between consecutive W2C poses (N, 4, 4): (trans_steps (N-1,), rot_steps_rad (N-1,)).

    trans_steps: distance between consecutive camera centres (world units); rot_steps_rad: geodesic angle
    between consecutive rotations. A step touching a NaN pose is NaN.
    """
    w2c = np.asarray(w2c, dtype=np.float64)
    c = camera_centers(w2c)
    trans = np.linalg.norm(np.diff(c, axis=0), axis=-1)
    R = w2c[:, :3, :3]
    with np.errstate(invalid="ignore"):
        rot = geodesic_angle(R[:-1], R[1:])
    bad = ~np.all(np.isfinite(w2c), axis=(-2, -1))
    bad_step = bad[:-1] | bad[1:]
    trans[bad_step] = np.nan
    rot[bad_step] = np.nan
    return trans, rot

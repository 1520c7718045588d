"""A gravity-aligned world frame for a scene whose frame is arbitrary (SfM's): which way is up, from the
cameras and from the ground or floor in the points.

Evidence:
1. **Camera x axes.** People and drones hold cameras level (no roll): every camera's x axis (image right) is
   horizontal whatever its pitch, so up is the direction most nearly perpendicular to all of them (the
   eigenvector of Σ xᵢxᵢᵀ with the smallest eigenvalue; COLMAP's `model_orientation_aligner` uses the same
   idea). Its sign: the side the image-up vectors (−y) lean to, or, when every camera looks straight down or
   up, the opposite of where they look (a nadir drone). Cameras that all share one heading leave a plane of
   candidates (every direction perpendicular to the one x axis); the image-up mean projected on it is then
   off by the cameras' mean pitch. Cameras on their side (a phone's landscape shots among portrait ones, turned
   to the others' shape when read) are left out of this (`on_their_side`).
2. **The ground plane.** A RANSAC plane in the points (the SfM points, the fused mesh) whose normal lies within
   `plane_max_angle_deg` of the camera estimate (with one heading: perpendicular to the shared x axis and
   within `ambiguous_max_angle_deg` of the image-up mean, so a wall facing the cameras is not taken for the
   floor), with every camera above it; the largest such plane, refitted by least squares on its inliers,
   when it holds at least `plane_min_support_frac` of the points.

Which decides (`estimate_gravity`) was measured on the procedural worlds, whose cameras are level: the x axes
gave the true up to 0.00° wherever the headings spread, the ground plane 0.05° indoors but up to 3.2°
outdoors, where the terrain slopes; with one heading the image-up mean was 8–10° off (the cameras' pitch),
the floor 0.1° and the outdoor terrain 1.6–2.1°. So the x axes decide when the headings spread and the x axes
are level (rms tilt at most `max_level_tilt_deg`); otherwise the ground plane when there is one (with one
heading, its normal made perpendicular to the shared x axis); otherwise the cameras alone.

The frame: the smallest rotation taking the estimated up to +Z (a scene that is already upright stays as it
is), the origin on the ground plane below the cameras' centroid (the centroid itself when no ground plane
was found), scale unchanged. Inputs: W2C poses (N,4,4) in OpenCV camera axes (NaN rows skipped), points
(P,3) in the same frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from wonderverse.camera import Sim3, camera_centers

Z_UP = np.array([0.0, 0.0, 1.0])


class GravityParams(BaseModel):
    """How the up direction is estimated. Lengths are fractions of the points' extent."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    method: Literal["auto", "cameras"] = Field("auto", description="auto: cameras and ground plane; cameras: alone")
    # Level cameras (x axes this close to horizontal, rms) with spread headings decide alone.
    max_level_tilt_deg: float = Field(3.0, ge=0, le=90)
    # Two camera headings this far apart (sin² of half the angle) resolve up from the x axes alone.
    min_heading_spread: float = Field(0.002, gt=0, lt=0.5, description="second eigenvalue of Σ x xᵀ / N")
    # |mean image-up · up| below this: the cameras look (nearly) straight down or up; sign from the view axes
    min_image_up_lean: float = Field(0.1, gt=0, lt=1)
    plane_max_angle_deg: float = Field(20.0, gt=0, lt=90, description="ground normal within this of camera up")
    # With one camera heading, the ground normal is any direction perpendicular to the shared x axis within this
    # of the image-up mean (a mean pitch within it of level): a wall facing the cameras is not the floor.
    ambiguous_max_angle_deg: float = Field(45.0, gt=0, lt=90)
    plane_inlier_frac: float = Field(0.002, gt=0, lt=0.5, description="RANSAC inlier distance / points' extent")
    plane_min_support_frac: float = Field(0.05, gt=0, le=1, description="ground plane's share of the points")
    plane_min_points: int = Field(30, ge=3, description="fewer points: no plane is sought")
    plane_max_points: int = Field(20_000, ge=3, le=10_000_000, description="points subsampled to this many for RANSAC")
    ransac_iterations: int = Field(400, ge=1, le=100_000)
    seed: int = 0


@dataclass(frozen=True)
class GravityFrame:
    """world_from_input: the rigid transform (Sim3 with s = 1) into the gravity-aligned world (+Z up);
    up: the estimated up direction (3,) in the input frame; evidence: what decided it (JSON-able)."""

    world_from_input: Sim3
    up: np.ndarray
    evidence: dict[str, Any]


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def rotation_to_z(up: np.ndarray) -> np.ndarray:
    """The smallest rotation R (3,3) with R @ up = +Z (up need not be unit length)."""
    u = _unit(np.asarray(up, np.float64))
    c = float(u @ Z_UP)
    axis = np.cross(u, Z_UP)
    s = float(np.linalg.norm(axis))
    if s < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])  # up = -Z: half a turn about x
    k = axis / s
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + s * K + (1.0 - c) * (K @ K)


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle in degrees between two directions (3,)."""
    return float(np.degrees(np.arccos(np.clip(_unit(a) @ _unit(b), -1.0, 1.0))))


def _valid(w2c: np.ndarray) -> np.ndarray:
    w2c = np.asarray(w2c, np.float64).reshape(-1, 4, 4)
    ok = w2c[np.isfinite(w2c).all(axis=(1, 2))]
    if len(ok) == 0:
        raise ValueError("no finite camera pose: the up direction needs cameras")
    return ok


def camera_up(w2c: np.ndarray, params: GravityParams | None = None) -> tuple[np.ndarray, np.ndarray | None, dict]:
    """Up from the cameras' orientations: (up (3,), the x axis that leaves it ambiguous or None, evidence).

    The second value is the cameras' shared x axis when their headings do not spread (up is then only known
    to be perpendicular to it, and the returned up assumes a level mean pitch), else None.
    """
    p = params or GravityParams()
    R_all = _valid(w2c)[:, :3, :3]
    side = on_their_side(R_all)
    R = R_all[~side]
    x, img_up, fwd = R[:, 0], -R[:, 1], R[:, 2]
    evals, evecs = np.linalg.eigh(x.T @ x / len(x))  # ascending
    mean_up = img_up.mean(0)
    ambiguous_axis = None
    if evals[1] >= p.min_heading_spread:
        up = evecs[:, 0]
        mode = "x axes"
    else:  # one heading: any direction perpendicular to the shared x axis; take the image-up mean's
        ambiguous_axis = evecs[:, 2]
        up = mean_up - (mean_up @ ambiguous_axis) * ambiguous_axis
        mode = "image up, one heading"
        if np.linalg.norm(up) < 1e-9:  # image ups cancel: use where the cameras look instead
            up = -(fwd.mean(0) - (fwd.mean(0) @ ambiguous_axis) * ambiguous_axis)
        if np.linalg.norm(up) < 1e-9:
            up = evecs[:, 0]
    up = _unit(up)
    lean = float(img_up.mean(0) @ up)
    if abs(lean) >= p.min_image_up_lean:
        sign_from = "image up"
        up = up if lean > 0 else -up
    else:  # every camera looks (nearly) straight down or up: assume down, as a drone's nadir camera
        sign_from = "view axes (looking down)"
        look = float(fwd.mean(0) @ up)
        up = -up if look > 0 else up
    evidence = {
        "mode": mode,
        "sign_from": sign_from,
        "x_axis_eigenvalues": [float(e) for e in evals],
        "cameras": len(R),
        "cameras_on_their_side": int(side.sum()),
    }
    return up, ambiguous_axis, evidence


SIDE_MIN_IMAGE_UP = 0.5  # |mean image-up| at least this: most cameras upright, their mean a fair first up
SIDE_MAX_SHARE = 1.0 / 3.0  # more cameras than this "on their side" is a rolled rig, not a few turned shots
SIDE_MIN_X_UP = 0.7071  # |x · first up| over this (x within 45° of up): the camera is on its side


def on_their_side(R: np.ndarray) -> np.ndarray:
    """(N,) bool: cameras (W2C rotations (N,3,3)) on their side, whose x axis points nearer up than level: a
    phone's landscape shot among portrait ones, turned a quarter to their shape when read (`video.files`). Their
    x axes would pull the up estimate toward the horizon (on a 20° orbit with 2 of 14 such shots, 79° off), so
    `camera_up` leaves them out. Up here is the image-up mean, used only when most cameras are upright (its norm
    at least SIDE_MIN_IMAGE_UP) and at most SIDE_MAX_SHARE of them would be left out; else none is."""
    side = np.zeros(len(R), bool)
    mean_up = (-R[:, 1]).mean(0)
    if np.linalg.norm(mean_up) < SIDE_MIN_IMAGE_UP:
        return side
    side = np.abs(R[:, 0] @ (mean_up / np.linalg.norm(mean_up))) > SIDE_MIN_X_UP
    return side if side.sum() <= SIDE_MAX_SHARE * len(R) else np.zeros(len(R), bool)


def ground_plane(
    points: np.ndarray,
    centres: np.ndarray,
    up0: np.ndarray,
    ambiguous_axis: np.ndarray | None = None,
    params: GravityParams | None = None,
) -> dict[str, Any] | None:
    """The largest plane in `points` (P,3) that could be the ground: its normal within plane_max_angle_deg of
    `up0` (of the plane perpendicular to `ambiguous_axis` when given), every camera centre (M,3) above it.
    Returns {"normal" (3,) unit, pointing to the cameras, "point" (3,) on the plane, "support_frac",
    "inlier_dist", "points"} or None (too few points, or no plane with plane_min_support_frac of them)."""
    p = params or GravityParams()
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    if len(pts) < p.plane_min_points:
        return None
    rng = np.random.default_rng(p.seed)
    if len(pts) > p.plane_max_points:
        pts = pts[rng.choice(len(pts), p.plane_max_points, replace=False)]
    lo, hi = np.percentile(pts, [2.0, 98.0], axis=0)
    extent = float(np.linalg.norm(hi - lo))
    if not extent > 0:
        return None
    tol = p.plane_inlier_frac * extent
    cos_max = np.cos(np.radians(p.plane_max_angle_deg))
    sin_max = np.sin(np.radians(p.plane_max_angle_deg))
    up0 = _unit(np.asarray(up0, np.float64))
    cos_loose = np.cos(np.radians(p.ambiguous_max_angle_deg))

    def admissible(n: np.ndarray) -> bool:
        if ambiguous_axis is not None:
            return abs(float(n @ ambiguous_axis)) <= sin_max and abs(float(n @ up0)) >= cos_loose
        return abs(float(n @ up0)) >= cos_max

    def oriented(n: np.ndarray, q: np.ndarray) -> np.ndarray | None:
        """n pointing to the cameras, or None when the cameras are not all above the plane."""
        h = (centres - q) @ n
        if np.all(h > tol):
            return n
        if np.all(h < -tol):
            return -n
        return None

    best: tuple[int, np.ndarray, np.ndarray] | None = None
    for _ in range(p.ransac_iterations):
        a, b, c = pts[rng.choice(len(pts), 3, replace=False)]
        n = np.cross(b - a, c - a)
        norm = np.linalg.norm(n)
        if norm < 1e-12 * extent * extent:
            continue
        n = n / norm
        if not admissible(n):
            continue
        count = int(np.count_nonzero(np.abs((pts - a) @ n) < tol))
        if best is None or count > best[0]:
            n_o = oriented(n, a)
            if n_o is not None:
                best = (count, n_o, a)
    if best is None:
        return None
    _, n, q = best
    for _ in range(3):  # least-squares refit on the inliers
        inl = pts[np.abs((pts - q) @ n) < tol]
        q = inl.mean(0)
        n_fit = np.linalg.svd(inl - q, full_matrices=False)[2][2]
        n = n_fit if n_fit @ n > 0 else -n_fit
    support = int(np.count_nonzero(np.abs((pts - q) @ n) < tol))
    frac = support / len(pts)
    if frac < p.plane_min_support_frac or not admissible(n) or oriented(n, q) is None:
        return None
    return {"normal": n, "point": q, "support_frac": frac, "inlier_dist": tol, "points": len(pts)}


def given_frame(reason: str) -> GravityFrame:
    """The input frame kept as it is, for a world that is gravity-aligned by construction (a video backend's
    own world, where the conditioning paths were planned with +Z up): the identity, with `reason` as the
    evidence's source."""
    return GravityFrame(
        Sim3.identity(),
        Z_UP.copy(),
        {"source": reason, "origin": "the world's own origin", "up_in_input": Z_UP.tolist(), "plane": None},
    )


def estimate_gravity(
    w2c: np.ndarray, points: np.ndarray | None = None, params: GravityParams | None = None
) -> GravityFrame:
    """The gravity-aligned frame (module docstring: the evidence, which decides, the origin) of cameras W2C
    (N,4,4) and points (P,3) (None or empty: cameras only) in the input frame. Raises ValueError when no
    camera pose is finite."""
    p = params or GravityParams()
    centres = camera_centers(_valid(w2c))
    cam_up, axis, cam_ev = camera_up(w2c, p)
    tilt = float(np.degrees(np.arcsin(min(1.0, np.sqrt(max(cam_ev["x_axis_eigenvalues"][0], 0.0))))))
    cam_ev["x_axis_tilt_rms_deg"] = tilt
    plane = None
    if p.method == "auto" and points is not None and len(points):
        plane = ground_plane(points, centres, cam_up, axis, p)
    cameras_decide = axis is None and tilt <= p.max_level_tilt_deg
    if plane is not None and not cameras_decide:
        up = plane["normal"] if axis is None else _unit(plane["normal"] - (plane["normal"] @ axis) * axis)
        source = "ground plane" if axis is None else "ground plane, perpendicular to the cameras' x axis"
    else:
        up, source = cam_up, "cameras"
    R = rotation_to_z(up)
    centroid = centres.mean(0)
    if plane is not None:  # where the vertical through the cameras' centroid meets the ground plane
        n = plane["normal"]
        origin = centroid - ((centroid - plane["point"]) @ n) / (up @ n) * up
    else:
        origin = centroid
    evidence: dict[str, Any] = {
        "source": source,
        "up_in_input": up.tolist(),
        "camera_up": cam_up.tolist(),
        "camera": cam_ev,
        "origin": "on the ground plane below the cameras' centroid" if plane is not None else "the cameras' centroid",
        "origin_in_input": origin.tolist(),
        "plane": None,
    }
    if plane is not None:
        evidence["plane"] = {
            "normal_in_input": plane["normal"].tolist(),
            "support_frac": plane["support_frac"],
            "inlier_dist": plane["inlier_dist"],
            "points": plane["points"],
            "angle_to_camera_up_deg": angle_deg(plane["normal"], cam_up),
        }
    return GravityFrame(Sim3(1.0, R, np.zeros(3), center=origin), up, evidence)

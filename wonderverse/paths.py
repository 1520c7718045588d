"""Camera paths for rendering a trained scene: a smooth fly-through along the training cameras, and novel
views that leave the training trajectory (a parallel track beside/above it, or an orbit).

All poses are W2C (N,4,4) float64 in OpenCV camera axes (x right, y down, z forward); the world must be
right-handed with +z up, since the novel track and the orbit move and aim their cameras by it (in SfM's own
frame, whose up is anywhere, the video comes out rolled: the outputs step passes its gravity-aligned frame,
`wonderverse.gravity`). Input poses that are not finite (NaN: not registered) are skipped. The scene
extent used for offsets is `camera.scene_extent` of the training cameras (their centres' bounding-box diagonal).
"""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from wonderverse.camera import (
    STILL_REL_TOL,
    WORLD_UP,
    _horizontal_heading,
    camera_centers,
    look_at,
    matrix_from_quat,
    quat_from_matrix,
    scene_extent,
    span,
)

# Below this length of (view direction × up) a camera counts as looking straight up/down for look_at,
# whose roll is then taken from the fly-through camera instead of the world up axis.
NEAR_VERTICAL_SIN = 1e-3
# Weight of the camera heading against the horizontal velocity (in typical steps) when choosing "sideways".
HEADING_WEIGHT = 0.01


class FlythroughParams(BaseModel):
    """How the training trajectory is smoothed and resampled."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    # Gaussian smoothing of the camera centres and rotations, sigma in input poses (0 = none).
    smooth_sigma_poses: float = Field(3.0, ge=0.0)
    # Path length that one radian of turning counts as, a fraction of the scene extent: turns on the spot
    # get screen time instead of flashing by, and translation-free trajectories still advance.
    turn_length_frac_per_rad: float = Field(0.25, ge=0.0)


class NovelViewParams(BaseModel):
    """A track parallel to the fly-through, shifted across it, looking at what the training cameras looked at."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    # Direction of the shift in the plane across the track: 0 = horizontal left of the direction of travel,
    # 90 = world up, 180 = right, -90 = down.
    offset_direction_deg: float = 30.0
    # Distance ahead of each training camera at which it is taken to look, when the caller gives none;
    # a fraction of the scene extent.
    look_distance_frac: float = Field(0.5, gt=0.0)
    flythrough: FlythroughParams = FlythroughParams()


class OrbitParams(BaseModel):
    """A circle around the point the training cameras looked at."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    arc_deg: float = Field(360.0, gt=0.0, le=360.0)  # counter-clockwise seen from above
    # Orbit radius relative to the median horizontal distance of the training cameras from the centre.
    radius_scale: float = Field(1.0, gt=0.0)
    # Height above the median training camera height, a fraction of the scene extent.
    height_frac: float = 0.1
    look_distance_frac: float = Field(0.5, gt=0.0)


def _valid_poses(w2c: np.ndarray) -> np.ndarray:
    """The finite poses (M,4,4) of (N,4,4), in order; ValueError when none is."""
    w2c = np.asarray(w2c, dtype=np.float64)
    if w2c.ndim != 3 or w2c.shape[1:] != (4, 4):
        raise ValueError(f"w2c must be (N,4,4), got {w2c.shape}")
    valid = w2c[np.all(np.isfinite(w2c), axis=(1, 2))]
    if len(valid) == 0:
        raise ValueError("no finite camera pose to build a path from")
    return valid


def _odd_padded_smooth(x: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian smoothing of rows (M,D) along axis 0 with point-reflected (odd) padding at both ends.

    Odd padding (x0 - (x_k - x0)) keeps the end values exactly and does not bend straight segments, where
    plain padding would pull the ends of the path towards its middle.
    """
    from scipy.ndimage import gaussian_filter1d

    m = len(x)
    if int(4.0 * sigma + 0.5) == 0 or m < 3:  # scipy's kernel radius: 0 means no smoothing (and tiny sigma fails)
        return x.copy()
    p = min(m - 1, int(np.ceil(4.0 * sigma)))
    left = 2.0 * x[0] - x[1 : p + 1][::-1]
    right = 2.0 * x[-1] - x[-p - 1 : -1][::-1]
    xp = np.concatenate([left, x, right])
    return gaussian_filter1d(xp, sigma, axis=0, mode="nearest")[p : p + m]


def _continuous_quats(R: np.ndarray) -> np.ndarray:
    """Quaternions (M,4) of rotations (M,3,3), signs flipped so that neighbours lie in the same hemisphere."""
    q = quat_from_matrix(R)
    for i in range(1, len(q)):
        if np.dot(q[i], q[i - 1]) < 0.0:
            q[i] = -q[i]
    return q


def _poses(R: np.ndarray, centers: np.ndarray) -> np.ndarray:
    """W2C (N,4,4) from rotations (N,3,3) and camera centres (N,3)."""
    out = np.zeros((len(R), 4, 4))
    out[:, :3, :3] = R
    out[:, :3, 3] = -np.einsum("nij,nj->ni", R, centers)
    out[:, 3, 3] = 1.0
    return out


def flythrough_path(w2c: np.ndarray, n_frames: int, params: FlythroughParams | None = None) -> np.ndarray:
    """W2C poses (n_frames, 4, 4) of a smooth path along the training cameras (N,4,4), in the given order.

    The finite poses are smoothed (centres and sign-aligned quaternions, Gaussian in pose index with
    end-preserving padding), then resampled at equal steps of a path length that counts translation plus
    `turn_length_frac_per_rad * extent` per radian of turning, through a natural cubic spline (C2: no
    jumps in velocity or acceleration). Frame 0 is the first finite training camera and the last frame
    the last one (exactly, up to rounding, when there are more than 4·sigma poses).
    """
    if n_frames < 1:
        raise ValueError(f"n_frames must be >= 1, got {n_frames}")
    from scipy.interpolate import CubicSpline

    params = params or FlythroughParams()
    poses = _valid_poses(w2c)
    c = _odd_padded_smooth(camera_centers(poses), params.smooth_sigma_poses)
    q = _odd_padded_smooth(_continuous_quats(poses[:, :3, :3]), params.smooth_sigma_poses)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    if len(poses) == 1:
        return np.repeat(_poses(matrix_from_quat(q), c), n_frames, axis=0)

    extent = span(c)
    # A camera that only turns: its path length is the turning alone, its centre one point.
    turn_len = params.turn_length_frac_per_rad * extent if extent > 0.0 else 1.0
    if extent == 0.0:
        c = np.broadcast_to(c.mean(0), c.shape).copy()
    dtheta = 2.0 * np.arctan2(np.linalg.norm(np.diff(q, axis=0), axis=1), np.linalg.norm(q[1:] + q[:-1], axis=1))
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(c, axis=0), axis=1) + turn_len * dtheta)])
    if s[-1] <= 0.0:
        return np.repeat(_poses(matrix_from_quat(q[:1]), c[:1]), n_frames, axis=0)
    # Knots must increase strictly: drop poses that do not advance (a paused camera), keep the last one.
    tol = STILL_REL_TOL * s[-1]
    keep = [0]
    for i in range(1, len(s)):
        if s[i] - s[keep[-1]] > tol:
            keep.append(i)
    keep[-1] = len(s) - 1
    if len(keep) < 2:
        keep = [0, len(s) - 1]
    knots = s[keep]
    u = np.linspace(0.0, s[-1], n_frames) if n_frames > 1 else np.zeros(1)
    centres = CubicSpline(knots, c[keep], axis=0, bc_type="natural")(u)
    quats = CubicSpline(knots, q[keep], axis=0, bc_type="natural")(u)
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    return _poses(matrix_from_quat(quats), centres)


def _aim(eye: np.ndarray, target: np.ndarray, fallback_R: np.ndarray) -> np.ndarray:
    """look_at with world up, or with the image-up of `fallback_R` (W2C rotation) when looking near vertically."""
    z = target - eye
    z = z / np.linalg.norm(z)
    if np.linalg.norm(np.cross(z, WORLD_UP)) >= NEAR_VERTICAL_SIN:
        return look_at(eye, target)
    return look_at(eye, target, up=-fallback_R[1])


def _look_distance(extent: float, look_distance: float | None, frac: float) -> float:
    d = frac * extent if look_distance is None else float(look_distance)
    if not (np.isfinite(d) and d > 0.0):
        raise ValueError(
            f"look distance must be positive (got {d}); pass look_distance when the cameras do not move (extent 0)"
        )
    return d


def novel_view_path(
    w2c: np.ndarray,
    n_frames: int,
    offset_frac: float = 0.15,
    look_distance: float | None = None,
    params: NovelViewParams | None = None,
) -> np.ndarray:
    """W2C poses (n_frames, 4, 4) of a track parallel to the fly-through, off the training trajectory.

    Each fly-through centre moves by offset_frac × S, where S = max(scene extent, look distance), along the
    direction at `offset_direction_deg` from the horizontal left of the direction of travel (of the camera
    heading where the path does not move horizontally) towards world up; the camera
    then looks at the point the fly-through camera looked at: `look_distance` (world units; default
    look_distance_frac × extent, e.g. pass the median scene depth) ahead along its optical axis. No roll
    (image up towards world +z) unless looking straight up or down.
    """
    params = params or NovelViewParams()
    base = flythrough_path(w2c, n_frames, params.flythrough)
    extent = scene_extent(w2c)
    d_look = _look_distance(extent, look_distance, params.look_distance_frac)
    shift = offset_frac * max(extent, d_look)
    a = np.radians(params.offset_direction_deg)
    centres = camera_centers(base)
    # Direction of travel on the ground plane, leaning on the camera heading where the path barely moves
    # horizontally (a weight, not a switch, so the direction never jumps).
    vel = np.gradient(centres, axis=0) if len(base) > 1 else np.zeros_like(centres)
    typical = float(np.median(np.linalg.norm(vel, axis=1)))
    if typical <= STILL_REL_TOL * max(1.0, float(np.abs(centres).max())):
        typical = 0.0  # no motion beyond rounding
    out = np.empty_like(base)
    for k, pose in enumerate(base):
        R = pose[:3, :3]
        heading = _horizontal_heading(R)
        travel = heading if typical == 0.0 else vel[k] / typical + HEADING_WEIGHT * heading
        travel[2] = 0.0
        travel /= np.linalg.norm(travel)
        left = np.cross(WORLD_UP, travel)
        eye = centres[k] + shift * (np.cos(a) * left + np.sin(a) * WORLD_UP)
        out[k] = _aim(eye, centres[k] + d_look * R[2], R)
    return out


def orbit_path(
    w2c: np.ndarray,
    n_frames: int,
    look_distance: float | None = None,
    params: OrbitParams | None = None,
) -> np.ndarray:
    """W2C poses (n_frames, 4, 4) circling the scene's look-at centre counter-clockwise (seen from above).

    The centre is the mean of the points the finite training cameras looked at (`look_distance` ahead
    along each optical axis; default look_distance_frac × extent). The circle starts at the first camera's
    azimuth around the centre, has radius radius_scale × the cameras' median horizontal distance from the
    centre (the look distance if that is zero), lies at the cameras' median height + height_frac × extent,
    and spans arc_deg (a full circle does not repeat its first pose). Every camera looks at the centre.
    """
    if n_frames < 1:
        raise ValueError(f"n_frames must be >= 1, got {n_frames}")
    params = params or OrbitParams()
    poses = _valid_poses(w2c)
    extent = scene_extent(poses)
    d_look = _look_distance(extent, look_distance, params.look_distance_frac)
    c = camera_centers(poses)
    centre = np.mean(c + d_look * poses[:, 2, :3], axis=0)
    rel = c[:, :2] - centre[:2]
    radius = float(np.median(np.linalg.norm(rel, axis=1)))
    radius = params.radius_scale * (radius if radius > 1e-9 * max(extent, d_look) else d_look)
    if np.linalg.norm(rel[0]) > 0.0:
        start = np.arctan2(rel[0, 1], rel[0, 0])
    else:  # first camera above the centre: start behind it, as seen along its heading
        h = _horizontal_heading(poses[0, :3, :3])
        start = np.arctan2(-h[1], -h[0])
    arc = np.radians(params.arc_deg)
    ang = start + np.linspace(0.0, arc, n_frames, endpoint=params.arc_deg < 360.0)
    z = float(np.median(c[:, 2])) + params.height_frac * extent
    eyes = np.stack([centre[0] + radius * np.cos(ang), centre[1] + radius * np.sin(ang), np.full_like(ang, z)], -1)
    return np.stack([look_at(e, centre) for e in eyes])

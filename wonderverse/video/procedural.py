"""The default video model: ray-cast renders of a procedural world, with exact ground truth and faults.

Every frame is a pure function of (world, pose, K): surfaces carry a solid 3D texture evaluated at
the hit point, so what SIFT finds on a surface stays put when the camera moves. Like a real video
model, a generation attempt sometimes goes wrong (`fault_probability`): the camera teleports or
snaps round, objects move, frames freeze, or the camera ignores its instruction and takes another smooth
path; `GroundTruth.faults` says what and where. The defects of real AI video (`ProceduralOptions.defects`:
texture-poor surfaces, exposure and white-balance drift, flickering detail, geometric drift, blur,
compression, low parallax; see defects.py) are off by default; ground truth stays the truth under them.
"""

from __future__ import annotations

import functools
import os
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any

import numpy as np

from wonderverse.camera import camera_centers, geodesic_angle, heading_pitch, intrinsics, look_at, rot_x, rot_z
from wonderverse.video.base import GroundTruth, Guide, Video
from wonderverse.video.content import WorldContent, segment_words
from wonderverse.video.defects import (
    DriftField,
    FrameLook,
    SurfaceLook,
    degrade_frames,
    plan_segment,
    scale_parallax,
    surface_look,
)
from wonderverse.video.procedural_options import FaultType, ProceduralOptions, resolved_defects
from wonderverse.video.shadows import build_cascades
from wonderverse.video.texture import (
    Noise,
    Sunlight,
    part_tables,
    rotate,
    rowdot,
    sky_colour,
    surface_colour,
)
from wonderverse.video.world import World, build_world, make_scene

# Separates the fault stream from any other use of (scene_seed, seed).
FAULT_STREAM = 0xFA017
DEMO_PROMPT = "a quiet village with houses and trees"


# ---------------------------------------------------------------- faults


@dataclass(frozen=True)
class FaultPlan:
    """One drawn fault. frame: first affected frame k (1 for ignore); magnitude in metres (teleport, morph),
    degrees (rotation; ignore: the turn a camera told to stay still makes instead) or frames (freeze);
    detail_seed seeds the remaining choices (directions, objects, the wrong path)."""

    type: FaultType
    frame: int
    magnitude: float
    detail_seed: int

    def frames(self, n_frames: int) -> list[int]:
        """Frames where the video departs from the path: k for a jump, k..k+F-1 for a freeze, 1..T-1 when
        the instruction is ignored (frame 0 is the reference the segment continues from)."""
        if self.type == "freeze":
            return list(range(self.frame, min(n_frames, self.frame + int(self.magnitude))))
        if self.type == "ignore":
            return list(range(1, n_frames))
        return [self.frame]


def draw_fault(scene_seed: int, seed: int, n_frames: int, opts: ProceduralOptions) -> FaultPlan | None:
    """The fault of one generation attempt, or None for a clean one; no rendering.

    Drawn from a generator seeded by SeedSequence([FAULT_STREAM, scene_seed, seed]): the same inputs
    always give the same answer, a new seed an independent draw. A segment of fewer than 2 frames
    cannot hold a fault (raises ValueError when one is forced).
    """
    rng = np.random.default_rng(np.random.SeedSequence([FAULT_STREAM, scene_seed, seed]))
    hit = rng.random() < opts.fault_probability
    pick = opts.fault_types[int(rng.integers(len(opts.fault_types)))]
    kind = opts.force_fault or (pick if hit else None)
    if kind is None:
        return None
    if n_frames < 2:
        if opts.force_fault:
            raise ValueError(f"force_fault={opts.force_fault!r} needs a path of at least 2 frames, got {n_frames}")
        return None
    lo = max(1, int(np.floor(opts.fault_window[0] * n_frames)))
    hi = min(n_frames, max(lo + 1, int(np.ceil(opts.fault_window[1] * n_frames))))
    k = int(rng.integers(lo, hi))
    if kind == "teleport":
        magnitude = float(rng.uniform(*opts.teleport_m))
    elif kind == "rotation":
        magnitude = float(rng.uniform(*opts.sudden_rotation_deg))
    elif kind == "morph":
        magnitude = float(rng.uniform(*opts.morph_m))
    elif kind == "ignore":  # the whole segment takes the wrong path
        k, magnitude = 1, float(rng.uniform(*opts.ignore_turn_deg))
    else:  # freeze frames k..k+F-1; short clips move k earlier so the whole freeze fits
        span = min(opts.freeze_frames, n_frames)
        k = min(k, n_frames - span)
        magnitude = float(span)
    return FaultPlan(kind, k, magnitude, int(rng.integers(2**32)))


def apply_pose_fault(path: np.ndarray, plan: FaultPlan | None, opts: ProceduralOptions) -> tuple[np.ndarray, dict]:
    """W2C poses (T,4,4) the camera really renders under `plan`, and the fault record (morph details
    are added by `build_morph`)."""
    poses = np.array(path, dtype=np.float64, copy=True)
    if plan is None:
        return poses, {}
    T = len(poses)
    rng = np.random.default_rng(plan.detail_seed)
    record: dict[str, Any] = {"type": plan.type, "frames": plan.frames(T), "magnitude": plan.magnitude}
    k = plan.frame
    if plan.type == "teleport":
        d = rng.normal(size=3) * [1.0, 1.0, opts.teleport_vertical_share]
        d[2] = abs(d[2])  # a video model loses its place, it does not dive under the ground
        offset = plan.magnitude * d / np.linalg.norm(d)
        R = poses[k:, :3, :3]
        poses[k:, :3, 3] -= np.einsum("tij,j->ti", R, offset)  # centre c -> c + offset
        record |= {"unit": "m", "offset_m": [float(x) for x in offset]}
    elif plan.type == "rotation":
        phi = rng.uniform(0, 2 * np.pi)
        yaw, pitch = np.radians(plan.magnitude) * np.cos(phi), np.radians(plan.magnitude) * np.sin(phi)
        centres = camera_centers(poses[k:])
        # yaw about the world's up axis, pitch about the camera's own x axis, centre kept
        R = np.einsum("ij,tjk,kl->til", rot_x(pitch).T, poses[k:, :3, :3], rot_z(yaw).T)
        poses[k:, :3, :3] = R
        poses[k:, :3, 3] = -np.einsum("tij,tj->ti", R, centres)
        rel = R[0] @ path[k, :3, :3].T
        angle = float(np.degrees(np.arccos(np.clip((np.trace(rel) - 1) / 2, -1.0, 1.0))))
        record |= {"unit": "deg", "magnitude": angle}
        record |= {"yaw_deg": float(np.degrees(yaw)), "pitch_deg": float(np.degrees(pitch))}
    elif plan.type == "freeze":
        frames = record["frames"]
        poses[frames] = poses[frames[0]]
        record["unit"] = "frames"
    elif plan.type == "ignore":
        poses, mode = ignored_path(poses, plan.magnitude, rng, opts)
        del record["magnitude"]
        record |= ignore_details(path, poses, mode)
    else:
        record["unit"] = "m"
    return poses, record


def ignored_path(
    path: np.ndarray, turn_deg: float, rng: np.random.Generator, opts: ProceduralOptions
) -> tuple[np.ndarray, str]:
    """A smooth, plausible but wrong path (T,4,4) W2C in place of `path`, starting at its first pose, and its
    mode in words. Modes, one drawn (rng) among those that differ from the plan:
    - "reverse_turn" (a plan that turns by >= ignore_min_turn_deg): heading and pitch change the other way,
      centres as planned;
    - "no_turn" (same plans): no rotation at all; the centre goes straight along the start's level heading,
      as far per frame as the plan's centre did;
    - "turned_move" (a plan that moves >= ignore_min_move_m): the centre's displacement turned about the world
      up by ±ignore_move_turn_deg, rotations as planned;
    - "unplanned_turn" (a still plan): a steady yaw of ±turn_deg over the segment.
    Every mode keeps the plan's step sizes (or, still, an even turn), so nothing jumps."""
    T = len(path)
    R, c = path[:, :3, :3], camera_centers(path)
    c2w = np.swapaxes(R, 1, 2)
    rot_deg = float(np.degrees(geodesic_angle(R[0], R)).max())
    move = float(np.linalg.norm(c - c[0], axis=1).max())
    modes = (["reverse_turn", "no_turn"] if rot_deg >= opts.ignore_min_turn_deg else []) + (
        ["turned_move"] if move >= opts.ignore_min_move_m else []
    )
    mode = modes[int(rng.integers(len(modes)))] if modes else "unplanned_turn"
    u = np.linspace(0.0, 1.0, T)
    if mode == "reverse_turn":
        yaw = np.atleast_1d(heading_pitch(path)[0])
        dpsi = np.unwrap(yaw) - yaw[0]
        # planned c2w_i = rot_z(dpsi_i) R0^T Q_i, with Q_i the rotation left in the first camera's frame (pitch)
        Q = R[0] @ rot_z(-dpsi) @ c2w
        c2w = rot_z(-dpsi) @ R[0].T @ np.swapaxes(Q, 1, 2)
    elif mode == "no_turn":
        f = R[0, 2].copy()
        f[2] = 0.0
        heading = f / max(float(np.linalg.norm(f)), 1e-12)
        along = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(c, axis=0), axis=1))])
        c2w = np.broadcast_to(R[0].T, (T, 3, 3))
        c = c[0] + along[:, None] * heading
    elif mode == "turned_move":
        theta = np.radians(rng.uniform(*opts.ignore_move_turn_deg)) * rng.choice([-1.0, 1.0])
        c = c[0] + (c - c[0]) @ rot_z(theta).T
    else:
        c2w = rot_z(np.radians(turn_deg) * rng.choice([-1.0, 1.0]) * u) @ c2w
    out = np.zeros_like(path)
    out[:, :3, :3] = np.swapaxes(c2w, 1, 2)
    out[:, :3, 3] = -np.einsum("tij,tj->ti", out[:, :3, :3], c)
    out[:, 3, 3] = 1.0
    out[0] = path[0]  # exactly: the segment continues from its reference
    return out, mode


def describe_move(poses: np.ndarray) -> dict[str, Any]:
    """A camera path (T,4,4 W2C) from its first to its last pose, in figures and words: turn_left_deg (heading
    change about the world up, positive = left), look_up_deg (pitch change), rotation_deg (geodesic angle),
    forward_m, left_m, up_m (the centre's displacement along the first camera's level heading, its left and
    the world up, in the path's units), path_m (summed centre steps), words ("turn right 20 deg, move
    forward 1")."""
    yaw, pitch = heading_pitch(poses)
    yaw, pitch = np.atleast_1d(yaw), np.atleast_1d(pitch)
    turn = float(np.degrees(np.unwrap(yaw)[-1] - yaw[0]))
    look_up = float(np.degrees(pitch[-1] - pitch[0]))
    rotation = float(np.degrees(geodesic_angle(poses[0, :3, :3], poses[-1, :3, :3])))
    c = camera_centers(poses)
    f = poses[0, 2, :3].copy()
    f[2] = 0.0
    heading = f / max(float(np.linalg.norm(f)), 1e-12)
    left = np.cross([0.0, 0.0, 1.0], heading)
    d = c[-1] - c[0]
    fwd, lft, up = float(d @ heading), float(d @ left), float(d[2])
    path_m = float(np.linalg.norm(np.diff(c, axis=0), axis=1).sum())
    words = []
    if abs(turn) >= 0.5:
        words.append(f"turn {'left' if turn > 0 else 'right'} {abs(turn):.0f} deg")
    if abs(look_up) >= 0.5:
        words.append(f"look {'up' if look_up > 0 else 'down'} {abs(look_up):.0f} deg")
    big = max(abs(fwd), abs(lft), abs(up))
    parts = [
        f"{name} {abs(x):.3g}"
        for x, name in ((fwd, "forward" if fwd > 0 else "back"), (lft, "left" if lft > 0 else "right"),
                        (up, "up" if up > 0 else "down"))
        if big > 0 and abs(x) >= 0.1 * big
    ]  # fmt: skip
    if parts:
        words.append("move " + " and ".join(parts))
    return {
        "turn_left_deg": turn,
        "look_up_deg": look_up,
        "rotation_deg": rotation,
        "forward_m": fwd,
        "left_m": lft,
        "up_m": up,
        "path_m": path_m,
        "words": ", ".join(words) or "stay still",
    }


def ignore_details(planned: np.ndarray, rendered: np.ndarray, mode: str) -> dict[str, Any]:
    """The record of an ignored instruction: mode, the planned and the rendered move (`describe_move`, in the
    paths' units) and a summary in words."""
    a, b = describe_move(planned), describe_move(rendered)
    return {
        "mode": mode,
        "planned": a,
        "rendered": b,
        "summary": f"asked to {a['words']}; rendered: {b['words']}",
    }


# ---------------------------------------------------------------- rendering


@lru_cache(maxsize=8)
def _camera_rays(width: int, height: int, k_key: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Camera-space ray directions through pixel centres (+0.5), row-major: their x and y (2,H*W)
    float32 (z = 1), and their lengths (H*W,). Read-only: they are shared between calls."""
    K = np.array(k_key, dtype=np.float64).reshape(3, 3)
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    x = (u.ravel() - K[0, 2] - K[0, 1] * (v.ravel() - K[1, 2]) / K[1, 1]) / K[0, 0]
    y = (v.ravel() - K[1, 2]) / K[1, 1]
    xy = np.stack([x, y]).astype(np.float32)
    length = np.sqrt(x * x + y * y + 1.0).astype(np.float32)
    xy.setflags(write=False)
    length.setflags(write=False)
    return xy, length


def world_directions(K: np.ndarray, w2c: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """The camera centre (3,) float32 in the world and every pixel's world ray direction (3,H*W)
    float32, row-major; each direction has camera z = 1, so a hit's ray parameter is its depth."""
    xy, _ = _camera_rays(width, height, tuple(np.asarray(K, dtype=np.float64).ravel()))
    centre, M = _camera_frame(w2c)
    return centre, _directions(xy, M)


def _camera_frame(w2c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The camera centre (3,) and the camera-to-world rotation R^T (3,3), both float32."""
    R = np.asarray(w2c[:3, :3], dtype=np.float64)
    return (-R.T @ w2c[:3, 3]).astype(np.float32), R.T.astype(np.float32)


def _directions(xy: np.ndarray, M: np.ndarray) -> np.ndarray:
    """World directions (3,n) float32 M (x, y, 1) of camera directions xy (2,n)."""
    dirs = np.empty((3, xy.shape[1]), dtype=np.float32)
    for j in range(3):
        np.multiply(xy[0], M[j, 0], out=dirs[j])
        dirs[j] += xy[1] * M[j, 1]
        dirs[j] += M[j, 2]
    return dirs


def _pack_rays(origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """(n,6) float32 rays [origin, direction] as Open3D takes them, from origins (3,n) or (3,) and
    directions (3,n) or (3,)."""
    n = dirs.shape[1] if np.ndim(dirs) == 2 else origins.shape[1]
    rays = np.empty((n, 6), dtype=np.float32)
    for j in range(3):  # column by column: broadcasting a 3-vector over (n,3) is ten times slower
        rays[:, j] = origins[j]
        rays[:, 3 + j] = dirs[j]
    return rays


def world_rays(K: np.ndarray, w2c: np.ndarray, width: int, height: int) -> np.ndarray:
    """(H*W,6) float32 rays [origin, direction] in the world for every pixel; each direction has camera
    z = 1, so a hit's ray parameter is its depth."""
    return _pack_rays(*world_directions(K, w2c, width, height))


@lru_cache(maxsize=4)
def _noise(seed: int) -> Noise:
    return Noise(seed)


@dataclass
class Morph:
    """Objects moved by a morph fault: the morphed world's scene and, per object id, how texture
    coordinates map back to where the surface was built (p_tex = (p - new_pivot) / scale + old_pivot)."""

    scene: Any
    vertices: np.ndarray  # (V,3) float32 morphed mesh
    moved: np.ndarray  # (n_objects+1,) bool
    scale: np.ndarray  # (n_objects+1,) float32
    new_pivot: np.ndarray  # (n_objects+1,3) float32
    old_pivot: np.ndarray  # (n_objects+1,3) float32
    cache: dict[Any, Any] = field(default_factory=dict)


def cast(scene: Any, rays: np.ndarray, nthreads: int = 0, uvs: bool = False) -> dict[str, np.ndarray]:
    """Open3D first hits of rays (n,6) [origin, direction]: t_hit (inf on a miss) in units of the
    direction's length, primitive_ids, primitive_normals (world, by winding), and with `uvs`
    primitive_uvs (n,2) (the hit is (1-u-v) v0 + u v1 + v v2). nthreads: Open3D's threads (0: all cores)."""
    import open3d as o3d

    rays = o3d.core.Tensor.from_numpy(np.ascontiguousarray(rays, dtype=np.float32))
    ans = scene.cast_rays(rays, nthreads=nthreads)
    keys = ("t_hit", "primitive_ids", "primitive_normals") + (("primitive_uvs",) if uvs else ())
    # copies: the arrays then own their memory, whatever Open3D does with its tensors
    return {k: np.array(ans[k].numpy()) for k in keys}


def render_view(
    world: World,
    K: np.ndarray,
    w2c: np.ndarray,
    width: int,
    height: int,
    opts: ProceduralOptions,
    morph: Morph | None = None,
    look: SurfaceLook | None = None,
    frame: FrameLook | None = None,
    drift: Drift | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Render one view with a real ray caster. Returns rgb (H,W,3) uint8, depth (H,W) float32 camera z
    in metres (+inf for sky) and normals (H,W,3) float32 unit, camera space (OpenCV axes), facing the
    camera, 0 for sky. look, frame, drift: the defects of this view (see `_view_chunks`), None for none."""
    rgb = np.empty((height, width, 3), dtype=np.uint8)
    depth = np.empty((height, width), dtype=np.float32)
    normals = np.zeros((height, width, 3), dtype=np.float32)
    out = (rgb, depth, normals)
    _run(_view_chunks(world, K, w2c, width, height, opts, morph, out, look, frame, drift), opts.shading_threads)
    return rgb, depth, normals


@dataclass(frozen=True)
class Drift:
    """The world deformed by the geometric drift for one frame: the deformed mesh's scene (what the frame
    shows) and the undeformed vertices (V,3) float32, where a hit's barycentric coordinates find the point
    the surface had before the deformation."""

    scene: Any
    vertices: np.ndarray


def drifted(world: World, morph: Morph | None, field: DriftField, amount_m: float) -> Drift:
    """The world (morphed, if a morph fault is on) with every vertex moved by the drift field at `amount_m`."""
    verts = world.vertices if morph is None else morph.vertices
    moved = verts + field.displacement(np.ascontiguousarray(verts.T), amount_m).T
    return Drift(make_scene(moved, world.triangles), verts)


def _undeformed(drift: Drift, triangles: np.ndarray, tri: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(3,n) float32 points of the undeformed surface at the hits on triangles tri (n,) with barycentric
    coordinates uv (n,2) on the deformed one."""
    corners = triangles.take(tri, axis=0)  # (n,3) vertex ids
    u, v = uv[:, 0], uv[:, 1]
    w = np.float32(1.0) - u - v
    out = np.empty((3, len(tri)), dtype=np.float32)
    for j in range(3):
        col = drift.vertices[:, j]
        out[j] = w * col.take(corners[:, 0]) + u * col.take(corners[:, 1]) + v * col.take(corners[:, 2])
    return out


def _view_chunks(
    world: World,
    K: np.ndarray,
    w2c: np.ndarray,
    width: int,
    height: int,
    opts: ProceduralOptions,
    morph: Morph | None,
    out: tuple[np.ndarray, np.ndarray, np.ndarray],
    look: SurfaceLook | None = None,
    frame: FrameLook | None = None,
    drift: Drift | None = None,
) -> list[Callable[[], None]]:
    """The work of `render_view` as independent pixel chunks, each writing its own rows of
    out = (rgb (H,W,3) uint8, depth (H,W) float32, normals (H,W,3) float32 zeroed beforehand). Chunks
    of several views can run together, so no thread waits for the end of each frame.

    Defects (None: none): look, the texture-poor surfaces; frame, this frame's colour gain and flickering
    detail; drift, the deformed world the colours are cast against (depth and normals are still cast
    against the undeformed world: ground truth; texture and shadows are read where the hit was before the
    deformation: the same triangle at the same barycentric coordinates)."""
    if not all(a.flags.c_contiguous for a in out):
        raise ValueError("_view_chunks writes into its outputs: they must be C-contiguous")
    fx = float(K[0, 0])
    xy, dnorm = _camera_rays(width, height, tuple(np.asarray(K, dtype=np.float64).ravel()))
    centre, c2w = _camera_frame(w2c)
    Rf = np.asarray(w2c[:3, :3], dtype=np.float32)
    scene = world.scene if morph is None else morph.scene
    origin = centre[:, None]
    noise, sky_noise = _noise(opts.noise_seed), _noise(opts.noise_seed + 1)
    sunlight = _sunlight(world, opts, morph)
    gain = None if frame is None else frame.gain
    flickers = frame is not None and frame.flicker is not None

    part_tables(world, opts, noise)  # build shared caches before the chunks run in parallel
    n_pix = width * height
    rgb, depth, normals = out[0].reshape(n_pix, 3), out[1].reshape(n_pix), out[2].reshape(n_pix, 3)

    def shade(sl: slice) -> None:
        """Ray-cast and shade pixels `sl`: disjoint slices of the outputs, so chunks may run concurrently
        (numpy releases the GIL). Vectors are (3,n) here (see texture.py); outputs are (n,3)."""
        dworld = _directions(xy[:, sl], c2w)
        # Open3D holds the GIL while it casts, stalling the other chunks' threads: let it use every core
        rays = _pack_rays(centre, dworld)
        ans = cast(scene if drift is None else drift.scene, rays, nthreads=0, uvs=drift is not None)
        t_all = ans["t_hit"]  # camera z = 1 along every ray, so the ray parameter is the depth
        if drift is None:
            depth[sl] = t_all
        else:  # ground truth: the undeformed world
            _write_truth(cast(scene, rays, nthreads=0), dworld, Rf, depth[sl], normals[sl])
        prim_ids, prim_normals = ans["primitive_ids"], ans["primitive_normals"]
        hit_mask = np.isfinite(t_all)
        hit = np.flatnonzero(hit_mask)
        all_hit = len(hit) == len(t_all)
        col = np.empty((3, len(t_all)), dtype=np.float32)
        if len(hit):
            if all_hit:  # no sky in this chunk (the usual case): views, no gathers
                t, d, n_geo = t_all, dworld, np.ascontiguousarray(prim_normals.T)
                tri, ray_len = prim_ids, dnorm[sl]
            else:
                t, d, n_geo = t_all.take(hit), dworld.take(hit, axis=1), prim_normals.T.take(hit, axis=1)
                tri, ray_len = prim_ids.take(hit), dnorm[sl].take(hit)
            n_dot_d = rowdot(n_geo, d)
            n_face = n_geo * np.where(n_dot_d > 0, np.float32(-1.0), np.float32(1.0))  # exact: a sign flip
            if drift is None:
                n_cam = rotate(n_face, Rf)
                for c in range(3):
                    if all_hit:
                        normals[sl, c] = n_cam[c]
                    else:
                        normals[sl, c][hit] = n_cam[c]
                points = origin + t * d
            else:  # where the hit was before the deformation (same triangle, same barycentric coordinates)
                uv = ans["primitive_uvs"] if all_hit else ans["primitive_uvs"].take(hit, axis=0)
                points = _undeformed(drift, world.triangles, tri, uv)
            tex = _texture_points(world, points, tri, morph)
            dist = t * ray_len
            cos_inc = np.abs(n_dot_d) * t / dist
            footprint = t * np.float32(1.0 / fx) / np.maximum(cos_inc, np.float32(opts.min_cos_incidence))
            detail = None
            if flickers:
                assert frame is not None
                idx = np.arange(sl.start, sl.stop) if all_hit else hit + sl.start
                pu = (idx % width).astype(np.float32) + np.float32(0.5)
                pv = (idx // width).astype(np.float32) + np.float32(0.5)
                detail = frame.detail(pu, pv, opts.texture_octaves, opts.octave_gain)
            surf = surface_colour(
                world, opts, noise, sunlight, points, tex, n_geo, n_face, dist, footprint, tri, look, detail
            )
            if all_hit:
                col = surf
            else:
                for c in range(3):
                    col[c][hit] = surf[c]
        if not all_hit:
            miss = np.flatnonzero(~hit_mask)
            sky = sky_colour(world, opts, sky_noise, dworld.take(miss, axis=1), fx)
            for c in range(3):
                col[c][miss] = sky[c]
        if gain is not None:  # exposure and white balance of this frame
            for c in range(3):
                col[c] *= gain[c]
        np.clip(col, 0.0, 1.0, out=col)
        col *= np.float32(255.0)
        col += np.float32(0.5)
        for c in range(3):
            rgb[sl, c] = col[c]

    # Chunk bounds are part of the picture: fbm normalises by the octaves that its chunk needs
    return [functools.partial(shade, slice(s, min(n_pix, s + opts.chunk_px))) for s in range(0, n_pix, opts.chunk_px)]


def _write_truth(
    ans: dict[str, np.ndarray], dworld: np.ndarray, Rf: np.ndarray, depth: np.ndarray, normals: np.ndarray
) -> None:
    """Write one chunk's depth (n,) and camera-space normals (n,3) (facing the camera, left 0 for sky) from a
    cast `ans` of rays whose world directions are dworld (3,n) (camera z = 1), W2C rotation Rf."""
    t_all = ans["t_hit"]
    depth[:] = t_all
    hit = np.flatnonzero(np.isfinite(t_all))
    if not len(hit):
        return
    n_geo = ans["primitive_normals"].T.take(hit, axis=1)
    n_dot_d = rowdot(n_geo, dworld.take(hit, axis=1))
    n_face = n_geo * np.where(n_dot_d > 0, np.float32(-1.0), np.float32(1.0))
    n_cam = rotate(n_face, Rf)
    for c in range(3):
        normals[hit, c] = n_cam[c]


def _run(chunks: list[Callable[[], None]], n_threads: int) -> None:
    """Run the chunks on the shading pool (in order, so a view's chunks finish close together)."""
    if n_threads > 1 and len(chunks) > 1:
        for f in [_pool(n_threads).submit(c) for c in chunks]:
            f.result()
    else:
        for c in chunks:
            c()


def _pool(n_threads: int) -> ThreadPoolExecutor:
    # keyed by process id: a forked child inherits the pool object but not its threads
    return _pool_of(n_threads, os.getpid())


@lru_cache(maxsize=4)
def _pool_of(n_threads: int, pid: int) -> ThreadPoolExecutor:
    return ThreadPoolExecutor(max_workers=n_threads, thread_name_prefix=f"wonderverse-shade-{pid}")


def _sunlight(world: World, opts: ProceduralOptions, morph: Morph | None) -> Sunlight | None:
    """The share of the sun reaching surface points, or None without shadows."""
    if not opts.shadows or world.kind != "outdoor":
        return None
    scene = world.scene if morph is None else morph.scene
    sun = world.sky.sun_dir.astype(np.float32)
    if opts.shadow_method == "rays":

        def by_rays(points: np.ndarray, normals: np.ndarray) -> np.ndarray:
            import open3d as o3d

            origins = points + normals * np.float32(opts.shadow_bias_m)
            blocked = scene.test_occlusions(o3d.core.Tensor.from_numpy(_pack_rays(origins, sun))).numpy()
            return np.where(blocked.astype(bool), np.float32(0.0), np.float32(1.0))

        return Sunlight(by_rays, cheap=False)
    cache = world.cache if morph is None else morph.cache
    key = ("shadow", opts.shadow_map_px, opts.shadow_near_m)
    if key not in cache:
        verts = world.vertices if morph is None else morph.vertices
        cache[key] = build_cascades(scene, sun, verts, opts.shadow_near_m, opts.shadow_map_px)
    cascades = cache[key]
    return Sunlight(lambda points, normals: cascades.light(points, normals, opts.shadow_bias_texels), cheap=True)


def _texture_points(world: World, points: np.ndarray, tri: np.ndarray, morph: Morph | None) -> np.ndarray:
    """Where the solid texture is read for each hit (3,n), from world points (3,n): the point where the
    surface was built (morphed objects carry their texture along), shifted by the world's texture offset."""
    offset = world.texture_offset[:, None]
    tex = points + offset
    if morph is not None:
        obj = world.tri_object.take(tri)
        sel = np.flatnonzero(morph.moved.take(obj))
        if len(sel):
            o = obj.take(sel)
            back = (points.take(sel, axis=1) - morph.new_pivot.take(o, axis=0).T) / morph.scale.take(o)
            tex[:, sel] = back + morph.old_pivot.take(o, axis=0).T + offset
    return tex


# ---------------------------------------------------------------- morph fault


def build_morph(
    world: World,
    K: np.ndarray,
    w2c: np.ndarray,
    width: int,
    height: int,
    plan: FaultPlan,
    opts: ProceduralOptions,
) -> tuple[Morph, dict[str, Any]]:
    """Move and resize up to `morph_objects` objects seen from pose `w2c`; returns the morphed world's
    scene with its texture mapping, and the record's details (object ids, scales, offset)."""
    rng = np.random.default_rng(plan.detail_seed)
    s = opts.morph_probe_stride_px
    rays = world_rays(K, w2c, width, height).reshape(height, width, 6)[s // 2 :: s, s // 2 :: s].reshape(-1, 6)
    centre = rays[0, :3]
    ans = cast(world.scene, rays)
    seen = ans["primitive_ids"][np.isfinite(ans["t_hit"])].astype(np.int64)
    ids, counts = np.unique(world.tri_object[seen], return_counts=True)
    keep = ids > 0
    ids, counts = ids[keep], counts[keep]
    if len(ids) == 0:  # nothing but ground in view: take the objects nearest the camera
        pivots = np.array([o.pivot for o in world.objects])
        ids = np.argsort(np.linalg.norm(pivots - centre, axis=1))[: opts.morph_objects] + 1
        counts = np.ones(len(ids))
    n_pick = min(opts.morph_objects, len(ids))
    chosen = np.sort(rng.choice(ids, size=n_pick, replace=False, p=counts / counts.sum()))
    n_obj = len(world.objects) + 1
    moved = np.zeros(n_obj, dtype=bool)
    scale = np.ones(n_obj, dtype=np.float32)
    old_pivot = np.zeros((n_obj, 3), dtype=np.float32)
    new_pivot = np.zeros((n_obj, 3), dtype=np.float32)
    a = rng.uniform(0, 2 * np.pi)
    offset = plan.magnitude * np.array([np.cos(a), np.sin(a), 0.0])
    verts = world.vertices.copy()
    scales = []
    for oid in chosen:
        pivot = np.array(world.objects[oid - 1].pivot, dtype=np.float32)
        sc = float(rng.uniform(*opts.morph_scale))
        sel = world.vert_object == oid
        verts[sel] = pivot + offset.astype(np.float32) + sc * (verts[sel] - pivot)
        moved[oid], scale[oid], old_pivot[oid], new_pivot[oid] = True, sc, pivot, pivot + offset
        scales.append(sc)
    morph = Morph(make_scene(verts, world.triangles), verts, moved, scale, new_pivot, old_pivot)
    details = {"objects": [int(i) for i in chosen], "scales": scales, "offset_m": [float(x) for x in offset]}
    return morph, details


# ---------------------------------------------------------------- the video model


def validate_path(path: np.ndarray) -> np.ndarray:
    """The path as (T,4,4) float64 W2C rigid transforms; ValueError with the reason otherwise."""
    arr = np.asarray(path, dtype=np.float64)
    if arr.ndim != 3 or arr.shape[1:] != (4, 4):
        raise ValueError(f"camera path must have shape (T, 4, 4), got {arr.shape}")
    if len(arr) == 0:
        raise ValueError("camera path has 0 frames; at least 1 is needed")
    bad = ~np.isfinite(arr).all(axis=(1, 2))
    if bad.any():
        raise ValueError(f"camera path has NaN/inf entries at frames {np.flatnonzero(bad).tolist()}")
    if not np.allclose(arr[:, 3], [0.0, 0.0, 0.0, 1.0], atol=1e-6):
        raise ValueError("camera path poses must have a last row of [0, 0, 0, 1]")
    R = arr[:, :3, :3]
    err = np.abs(R @ np.swapaxes(R, 1, 2) - np.eye(3)).max(axis=(1, 2))
    if (err > 1e-4).any() or (np.linalg.det(R) < 0).any():
        raise ValueError(
            f"camera path rotations are not proper rotations at frames {np.flatnonzero(err > 1e-4).tolist()}"
        )
    return arr


def _rescaled(poses: np.ndarray, factor: float) -> np.ndarray:
    """W2C poses (T,4,4) of the same cameras in a world scaled by `factor` (translations times it);
    the poses themselves when factor is 1, so scale 1 is bit for bit what it always was."""
    if factor == 1.0:
        return poses
    out = np.array(poses, dtype=np.float64, copy=True)
    out[:, :3, 3] *= factor
    return out


def _rescaled_record(record: dict[str, Any], factor: float) -> dict[str, Any]:
    """A fault record with its distances (teleport, morph: magnitude and offset_m) in scaled units."""
    if record.get("unit") != "m":
        return record
    out = dict(record, magnitude=record["magnitude"] * factor)
    if "offset_m" in out:
        out["offset_m"] = [x * factor for x in out["offset_m"]]
    return out


class ProceduralVideo:
    """VideoModel over a procedural world chosen by (scene_prompt, scene_seed), shared by all segments."""

    def __init__(
        self,
        scene_prompt: str,
        scene_seed: int,
        width: int,
        height: int,
        fov_deg: float,
        options: dict[str, Any] | ProceduralOptions | None = None,
    ) -> None:
        if width < 8 or height < 8:
            raise ValueError(f"frame size {width}x{height} is too small; at least 8x8")
        if not 5.0 < fov_deg < 170.0:
            raise ValueError(f"fov_deg={fov_deg} must lie in (5, 170)")
        if scene_seed < 0:
            raise ValueError(f"scene_seed must be >= 0, got {scene_seed}")
        self.scene_prompt = scene_prompt
        self.scene_seed = int(scene_seed)
        self.width, self.height, self.fov_deg = int(width), int(height), float(fov_deg)
        self.options = (
            options if isinstance(options, ProceduralOptions) else ProceduralOptions.model_validate(options or {})
        )
        self.K = intrinsics(self.width, self.height, self.fov_deg)
        self._world: World | None = None
        self.content = WorldContent()  # what the segments' words placed (video/content.py)

    @property
    def world(self) -> World:
        """The scene's world (built on first use), with the content the words of earlier calls placed."""
        if self._world is None:
            self._world = build_world(self.scene_prompt, self.scene_seed, self.options)
        placed = self.content.world
        return self._world if placed is None else placed

    def _content_world(self, prompt: str, end_w2c: np.ndarray) -> tuple[World, np.ndarray, dict[int, str]]:
        """The world this generation renders: the scene's, with what the user's words in `prompt` (after the scene
        prompt: `segment_words`) name placed in front of the path's last pose `end_w2c` (native metres), and all
        content placed before. Returns it with object_label (object id -> label id, -1 none) and label names, one
        consistent snapshot (another thread may add content meanwhile)."""
        base = self.world if self.content.world is None else self._world
        assert base is not None
        words = segment_words(prompt, self.scene_prompt)
        if words:
            self.content.add(base, words, end_w2c, self.K, (self.width, self.height), self.scene_seed)
        world, object_label, names = self.content.snapshot()
        return (base if world is None else world), object_label, names

    def place_content(self, prompt: str, path: np.ndarray) -> None:
        """Place what a segment's words name (as `generate` does with `prompt` and `path`, scene units) without
        rendering: a fresh video model (another step, a later `extend`) replays the scene's segments with this, so
        the world keeps the content earlier segments placed. Placement depends only on the scene seed, the words
        and the path's last pose, so the order of replays does not matter."""
        self._content_world(prompt, _rescaled(validate_path(path), 1.0 / self.options.scene_scale)[-1])

    @property
    def takes_guide(self) -> bool:
        """Whether `generate` reads a guide (`options.accept_guide`); otherwise a guide is ignored."""
        return self.options.accept_guide

    def _keep_known(self, guide: Guide, frames: np.ndarray, depth: np.ndarray) -> tuple[np.ndarray, dict[str, float]]:
        """What a guided model does with `guide`: the known pixels (mask False) are the guide's, the rest the
        rendered truth `frames`. Returns those frames and the guide's errors against the truth (`guide_errors`
        on `frames` and camera-z `depth`, scene units). WonderError when the guide does not fit the video."""
        from wonderverse.guide import guide_errors, validate_guide

        validate_guide(guide, *depth.shape)
        errors = guide_errors(guide, frames, depth)
        return np.where(guide.mask[..., None], frames, guide.frames).astype(np.uint8), errors

    def surface_look(self) -> SurfaceLook | None:
        """The scene's texture-poor surfaces (`defects.texture_poor_share`), None for none."""
        return surface_look(self.world, self.scene_seed, resolved_defects(self.options))

    def render(self, w2c: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One clean frame at a W2C pose in scene units: rgb (H,W,3) uint8, depth (H,W) f32 scene units,
        normals (H,W,3) f32. Of the defects only the world's own look (texture-poor surfaces) applies; the
        per-attempt ones (drifts, flicker, blur, compression, parallax) do not."""
        s = self.options.scene_scale
        native = _rescaled(validate_path(w2c[None]), 1.0 / s)[0]
        rgb, depth, normals = render_view(
            self.world, self.K, native, self.width, self.height, self.options, look=self.surface_look()
        )
        if s != 1.0:
            depth *= np.float32(s)
        return rgb, depth, normals

    def _draw_movers(
        self, world: World, poses: np.ndarray, frames: np.ndarray, depth: np.ndarray, seed: int, frozen: set[int]
    ) -> np.ndarray | None:
        """Composite `options.movers` moving people and vehicles (`video.movers`) into the rendered `frames` (T,H,W,3)
        in place, occluded by the world's camera-z `depth` (native metres) at W2C `poses` (native). Returns their
        masks (T,H,W) bool (frozen frames are filled by the caller), or None without movers. Before the defects, which
        then blur and compress movers and world alike."""
        if not self.options.movers:
            return None
        from wonderverse.video.movers import composite_movers, plan_movers

        movers = plan_movers(world, poses, self.K, self.width, self.options.movers, self.scene_seed, seed)
        masks = np.zeros(depth.shape, dtype=bool)
        for i in range(len(poses)):
            if i not in frozen:
                origin, dirs = world_directions(self.K, poses[i], self.width, self.height)
                masks[i] = composite_movers(frames[i], depth[i], movers, i, origin, dirs, world.sky.sun_dir)
        return masks

    def generate(
        self,
        prompt: str,
        path: np.ndarray,
        seed: int,
        reference: np.ndarray | None,
        guide: Guide | None = None,
    ) -> Video:
        """Render `path` (T,4,4 W2C, scene units). The world comes from the scene prompt; what the user's words at
        the end of `prompt` name (video/content.py) is placed in front of the path's last pose and stays in the
        world for every later call, with per-pixel labels in gt.labels. `seed` (>= 0) decides the attempt's fault
        and its defects. `guide` (what is known along the path, for guided extensions) is ignored unless
        `options.accept_guide`: then the frames keep the guide's known pixels and show the rendered truth
        elsewhere, and gt.guide holds the guide's errors against it.
        Returns frames (T,H,W,3) uint8, K and GroundTruth (poses, depth and fault distances in scene units:
        native metres times `scene_scale`).

        With defects (`options.defects`) the frames show them; gt.poses are the poses really rendered (after
        `parallax_scale` and any fault), gt.depth and gt.normals those of the world's own undeformed mesh at
        those poses (the geometric drift shows in the frames only). With `options.movers` the frames show moving
        people and vehicles (`video.movers`) and gt.movers their masks; depth, normals and labels stay the static
        world's."""
        path = validate_path(path)
        if seed < 0:
            raise ValueError(f"seed must be >= 0, got {seed}")
        shape = (self.height, self.width, 3)
        if reference is not None and np.shape(reference) != shape:
            raise ValueError(f"reference frame has shape {np.shape(reference)}, this video renders {shape}")
        params = resolved_defects(self.options)
        clean = params.is_clean()
        plan = draw_fault(self.scene_seed, seed, len(path), self.options)
        s = self.options.scene_scale
        native = _rescaled(path, 1.0 / s)  # the world renders in native metres whatever the scale
        world, object_label, label_names = self._content_world(prompt, native[-1])
        asked = native if clean else scale_parallax(native, params.parallax_scale)
        poses, record = apply_pose_fault(asked, plan, self.options)
        morph = None
        if plan is not None and plan.type == "morph":
            w2c_k = poses[plan.frame]
            morph, details = build_morph(world, self.K, w2c_k, self.width, self.height, plan, self.options)
            record |= details
        T = len(poses)
        segment = None if clean else plan_segment(params, self.scene_seed, seed, T)
        look = None if clean else surface_look(world, self.scene_seed, params)
        frames = np.empty((T, *shape), dtype=np.uint8)
        depth = np.empty((T, self.height, self.width), dtype=np.float32)
        normals = np.zeros((T, self.height, self.width, 3), dtype=np.float32)
        frozen = set(record["frames"][1:]) if record.get("type") == "freeze" else set()
        chunks = []
        for i in range(T):
            if i not in frozen:
                m = morph if morph is not None and plan is not None and i >= plan.frame else None
                out = (frames[i], depth[i], normals[i])
                frame = None if segment is None else segment.frames[i]
                drift = None
                if segment is not None and segment.drift is not None and segment.frames[i].drift_m > 0:
                    drift = drifted(world, m, segment.drift, segment.frames[i].drift_m)
                view = _view_chunks(
                    world, self.K, poses[i], self.width, self.height, self.options, m, out, look, frame, drift
                )
                if drift is None:
                    chunks += view
                else:  # its own deformed scene: render it now and let the scene go
                    _run(view, self.options.shading_threads)
        _run(chunks, self.options.shading_threads)  # all frames at once: threads never wait at a frame's end
        mover_masks = self._draw_movers(world, poses, frames, depth, seed, frozen)
        for i in sorted(frozen):  # the video holds the previous frame
            frames[i], depth[i], normals[i] = frames[i - 1], depth[i - 1], normals[i - 1]
            if mover_masks is not None:
                mover_masks[i] = mover_masks[i - 1]
        labels = None
        if label_names:  # what of the placed content each pixel shows, cast as depth was
            at = plan.frame if morph is not None and plan is not None else T
            labels = content_labels(world, object_label, self.K, poses, self.width, self.height, morph, at, frozen)
        if not clean:
            frames = degrade_frames(frames, depth, poses, self.K, params)
        if s != 1.0:  # report in scene units; frames the fault left alone keep the path exactly
            moved = ~(poses == native).all(axis=(1, 2))
            poses, record = np.where(moved[:, None, None], _rescaled(poses, s), path), _rescaled_record(record, s)
            depth *= np.float32(s)
        if record.get("type") == "ignore":  # in scene units, and against the path as asked
            record |= ignore_details(path, poses, record["mode"])
        guided = None
        if guide is not None and self.options.accept_guide:  # a guided model keeps the known, invents the rest
            frames, guided = self._keep_known(guide, frames, depth)
        truth = GroundTruth(poses, depth, normals, record, guide=guided, labels=labels, label_names=label_names)
        truth.movers = mover_masks
        return Video(frames=frames, K=self.K.copy(), gt=truth, k_is_guess=False)


def content_labels(
    world: World,
    object_label: np.ndarray,
    K: np.ndarray,
    poses: np.ndarray,
    width: int,
    height: int,
    morph: Morph | None = None,
    morph_from: int = 0,
    frozen: set[int] | frozenset[int] = frozenset(),
) -> np.ndarray:
    """(T,H,W) int16 label of the placed content each pixel shows (object_label of the hit triangle's object,
    -1 for none or sky), cast like the depth: the same rays against the world (the morphed one from frame
    `morph_from` on), frozen frames holding the previous frame. poses: (T,4,4) W2C in native metres."""
    tri_label = object_label.take(world.tri_object)
    labels = np.full((len(poses), height, width), -1, dtype=np.int16)
    for i, w2c in enumerate(poses):
        if i in frozen:
            labels[i] = labels[i - 1]
            continue
        scene = morph.scene if morph is not None and i >= morph_from else world.scene
        ans = cast(scene, world_rays(K, w2c, width, height))
        hit = np.flatnonzero(np.isfinite(ans["t_hit"]))
        labels[i].reshape(-1)[hit] = tri_label.take(ans["primitive_ids"].take(hit).astype(np.int64))
    return labels


def demo_path(start: np.ndarray, n_frames: int, yaw_deg: float = 30.0, forward_m: float = 2.0) -> np.ndarray:
    """(T,4,4) W2C path from `start`: turn right by yaw_deg while moving forward_m along the start's
    view direction (kept level); a stand-in for the planner in tests and benchmarks."""
    c0 = camera_centers(start[None])[0]
    fwd = start[2, :3].copy()
    level = np.array([fwd[0], fwd[1], 0.0]) / max(np.hypot(fwd[0], fwd[1]), 1e-9)
    out = []
    for s in np.linspace(0.0, 1.0, n_frames):
        yaw = -np.radians(yaw_deg) * s  # negative about +z turns a +y-looking camera towards +x (right)
        view = rot_z(yaw) @ fwd
        eye = c0 + forward_m * s * level
        out.append(look_at(eye, eye + view))
    return np.stack(out)


def render_fps(width: int = 480, height: int = 320, frames: int = 25, prompt: str = DEMO_PROMPT) -> float:
    """Frames per second of clean rendering at width x height (world build and warm-up excluded)."""
    video = ProceduralVideo(prompt, 0, width, height, 60.0, {"fault_probability": 0.0})
    path = demo_path(video.world.start_pose(), frames)
    video.generate(prompt, path[:2], 0, None)  # builds the scene and caches the ray grid
    t0 = time.perf_counter()
    video.generate(prompt, path, 0, None)
    return frames / (time.perf_counter() - t0)

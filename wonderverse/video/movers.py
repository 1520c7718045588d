"""Moving people and vehicles for the procedural world: transient objects with exact masks.

Real footage (and AI video) shows things that move while the camera does: a walking person, a passing car. A
static reconstruction cannot explain them, so they are the ground truth a robust loss is measured against
(`benchmarks.transients`). Each mover is a few coloured boxes (legs, torso and head; a car's body and cabin) that
walks or drives in a straight line across the view during a segment, standing on the ground. Movers are ray-cast
analytically per pixel and composited into the rendered frame where they are nearer than the world's own surface
(the true depth), so the world occludes them correctly and they occlude it. They cast no shadows and leave the world
untouched, so a frame rendered with movers differs from the same frame without them exactly on the mover mask:
the clip rendered with `movers: 0` is the static ground truth of every frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from wonderverse.video.world import World

MOVER_STREAM = 0x30E5  # separates the movers' draws from any other use of (scene_seed, seed)
VEHICLE_SHARE = 0.35  # share of movers that are vehicles (the rest are people)
PERSON_SPEED_M_PER_FRAME = 0.15  # 1.5 m/s, frames 0.1 s apart (a clip subsampled for training)
VEHICLE_SPEED_M_PER_FRAME = 0.6  # 6 m/s (22 km/h), frames 0.1 s apart
PERSON_DISTANCE_M = (3.5, 9.0)  # distance of a person from the camera at the segment's middle frame
VEHICLE_DISTANCE_M = (8.0, 16.0)  # likewise of a vehicle (they keep to the road, further off)
SCREEN_SPREAD_FRAC = 0.7  # share of the image width a mover's middle-frame position is drawn across
HEADING_JITTER_DEG = 30.0  # movers cross the view, give or take this much
AMBIENT = 0.45  # share of a mover's colour lit by the sky alone; the rest follows the sun (Lambert)

# (centre, half size) in metres of a mover's boxes: x along its heading, y to its left, z up from the ground
_PERSON = (((0.0, 0.0, 0.42), (0.12, 0.2, 0.42)), ((0.0, 0.0, 1.15), (0.14, 0.23, 0.32)), ((0, 0, 1.6), (0.11,) * 3))
_VEHICLE = (((0.0, 0.0, 0.75), (2.1, 0.9, 0.45)), ((-0.2, 0.0, 1.5), (1.1, 0.8, 0.3)))
_CLOTHES = np.array([[0.75, 0.1, 0.1], [0.1, 0.2, 0.7], [0.9, 0.75, 0.1], [0.15, 0.15, 0.15], [0.95, 0.95, 0.95]])
_SKIN = np.array([[0.9, 0.7, 0.55], [0.55, 0.38, 0.26], [0.35, 0.22, 0.15]])
_PAINT = np.array([[0.8, 0.05, 0.05], [0.05, 0.3, 0.8], [0.9, 0.9, 0.9], [0.1, 0.1, 0.12], [0.95, 0.6, 0.05]])
_GLASS = np.array([0.12, 0.16, 0.2])


@dataclass(frozen=True)
class Mover:
    """One moving object: its kind, boxes (centre (B,3) and half sizes (B,3) in its own frame, colours (B,3) in
    [0,1]), heading (radians about +z, world) and ground point per frame (T,3) native metres."""

    kind: str
    centres: np.ndarray
    halves: np.ndarray
    colours: np.ndarray
    heading: float
    positions: np.ndarray


def _ground_z(world: World, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Height of the ground under (x, y): the terrain outdoors, the floor (z = 0) indoors."""
    if world.terrain is None:
        return np.zeros_like(np.asarray(x, dtype=np.float64))
    return np.asarray(world.terrain.height(x, y), dtype=np.float64)


def _one_mover(rng: np.random.Generator, world: World, w2c: np.ndarray, K: np.ndarray, width: int, t: np.ndarray):
    """A mover whose ground point is in view at frame offset 0 of the camera `w2c`, at frame offsets `t` (T,)."""
    vehicle = rng.random() < VEHICLE_SHARE
    R = w2c[:3, :3]
    centre = -R.T @ w2c[:3, 3]
    fwd = R[2].copy()
    fwd[2] = 0.0
    fwd /= max(np.linalg.norm(fwd), 1e-9)
    left = np.array([-fwd[1], fwd[0], 0.0])
    half_fov = np.arctan(width / (2.0 * K[0, 0]))
    angle = np.arctan(rng.uniform(-0.5, 0.5) * SCREEN_SPREAD_FRAC * 2 * np.tan(half_fov))
    dist = rng.uniform(*(VEHICLE_DISTANCE_M if vehicle else PERSON_DISTANCE_M))
    mid = centre[:2] + dist * (np.cos(angle) * fwd[:2] - np.sin(angle) * left[:2])
    across = np.radians(rng.uniform(-HEADING_JITTER_DEG, HEADING_JITTER_DEG)) + (0.0 if rng.random() < 0.5 else np.pi)
    heading = float(np.arctan2(left[1], left[0]) + across)
    speed = VEHICLE_SPEED_M_PER_FRAME if vehicle else PERSON_SPEED_M_PER_FRAME
    xy = mid[None] + np.outer(t * speed, [np.cos(heading), np.sin(heading)])
    positions = np.column_stack([xy, _ground_z(world, xy[:, 0], xy[:, 1])])
    boxes = _VEHICLE if vehicle else _PERSON
    if vehicle:
        colours = np.stack([_PAINT[rng.integers(len(_PAINT))], _GLASS])
    else:
        colours = np.stack([_CLOTHES[rng.integers(len(_CLOTHES))], _CLOTHES[rng.integers(len(_CLOTHES))]])
        colours = np.vstack([colours, _SKIN[rng.integers(len(_SKIN))]])
    c, h = (np.array([b[i] for b in boxes], dtype=np.float64) for i in (0, 1))
    return Mover("vehicle" if vehicle else "person", c, h, colours, heading, positions)


def plan_movers(
    world: World, poses: np.ndarray, K: np.ndarray, width: int, count: int, scene_seed: int, seed: int
) -> list[Mover]:
    """`count` movers for a segment rendered at W2C `poses` (T,4,4, native metres): each in view at the middle
    frame, crossing it. Drawn from SeedSequence([MOVER_STREAM, scene_seed, seed]): the same inputs give the same
    movers; the world's own draws are untouched."""
    rng = np.random.default_rng(np.random.SeedSequence([MOVER_STREAM, scene_seed, seed]))
    mid = len(poses) // 2
    t = np.arange(len(poses), dtype=np.float64) - mid
    return [_one_mover(rng, world, np.asarray(poses[mid], np.float64), K, width, t) for _ in range(count)]


def _hit_boxes(mover: Mover, k: int, origin: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ray parameter of the first hit (n,) (inf for none) and the world normal there (n,3) of rays from `origin`
    (3,) along `dirs` (n,3) with mover `mover`'s boxes at frame k (slab test in each box's frame)."""
    c, s = np.cos(mover.heading), np.sin(mover.heading)
    to_local = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])  # world -> mover axes
    o = to_local @ (origin - mover.positions[k])
    d = dirs @ to_local.T
    best = np.full(len(d), np.inf)
    normal = np.zeros((len(d), 3))
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        for centre, half in zip(mover.centres, mover.halves, strict=True):
            t1, t2 = (centre - half - o) * inv, (centre + half - o) * inv
            near, far = np.minimum(t1, t2), np.maximum(t1, t2)
            axis = np.argmax(near, axis=1)
            t_in = near.max(axis=1)
            hit = (t_in <= far.min(axis=1)) & (t_in > 0) & (t_in < best)
            best = np.where(hit, t_in, best)
            n_local = np.zeros_like(d)
            rows = np.arange(len(d))
            n_local[rows, axis] = -np.sign(d[rows, axis])
            normal = np.where(hit[:, None], n_local @ to_local, normal)  # back to world axes
    return best, normal


def render_movers(
    movers: list[Mover], k: int, origin: np.ndarray, dirs: np.ndarray, depth: np.ndarray, sun_dir: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The movers at frame k over a frame whose rays start at `origin` (3,) along `dirs` (n,3) (camera z = 1, so a
    ray parameter is a depth) and whose world surface lies at camera z `depth` (n,) (inf: sky). Returns the
    movers' colours (n,3) in [0,1] and the mask (n,) of pixels where a mover is in front of the world."""
    colour = np.zeros((len(dirs), 3))
    nearest = np.asarray(depth, dtype=np.float64).copy()
    mask = np.zeros(len(dirs), dtype=bool)
    sun = np.asarray(sun_dir, dtype=np.float64)
    for mover in movers:
        for b in range(len(mover.centres)):  # one box at a time: each has its own colour
            one = Mover(mover.kind, mover.centres[b : b + 1], mover.halves[b : b + 1], mover.colours[b : b + 1],
                        mover.heading, mover.positions)  # fmt: skip
            t, n = _hit_boxes(one, k, origin, dirs)
            front = t < nearest
            lit = AMBIENT + (1.0 - AMBIENT) * np.clip(n @ sun, 0.0, 1.0)
            colour = np.where(front[:, None], mover.colours[b][None] * lit[:, None], colour)
            nearest = np.where(front, t, nearest)
            mask |= front
    return np.clip(colour, 0.0, 1.0), mask


def composite_movers(
    frame: np.ndarray, depth: np.ndarray, movers: list[Mover], k: int, origin: np.ndarray, dirs: np.ndarray,
    sun_dir: np.ndarray,
) -> np.ndarray:  # fmt: skip
    """Draw the movers at frame k into `frame` (H,W,3) uint8 in place, occluded by the world's camera-z `depth`
    (H,W); rays `origin` (3,) and `dirs` (3,H*W) as `procedural.world_directions` gives them. Returns the mover
    mask (H,W) bool: exactly the pixels that changed."""
    h, w = depth.shape
    colour, mask = render_movers(movers, k, origin.astype(np.float64), dirs.T.astype(np.float64), depth.ravel(),
                                 sun_dir)  # fmt: skip
    flat = frame.reshape(-1, 3)
    flat[mask] = np.clip(colour[mask] * 255.0 + 0.5, 0, 255).astype(np.uint8)
    return mask.reshape(h, w)

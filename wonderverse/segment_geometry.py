"""A checked segment's geometry in the plan's world frame, and the guide its extensions are rendered from.

A segment's frames come from a video model; the check's SfM of its accepted attempt gives their poses in a
world of its own (arbitrary scale, position and rotation) and a few 3D points. What an extension needs is
that segment's content in the *plan's* world frame, where the extension's planned path lives:

1. the depth model's prediction for each frame, aligned per frame (scale and shift, `align_frames`) to the
   SfM points projected into it (depth in SfM units);
2. the Sim(3) taking the SfM world onto the plan's (`sfm_to_plan`), fitted to the attempt's registered
   cameras against its planned path;
3. poses and depth mapped through it (camera z scales by the Sim(3)'s scale).

4. each frame's depth fused with its neighbours' (`fuse_depth`): the per-pixel median of its own depth and
   theirs reprojected into it. A monocular network's errors (its warp, its noise) are largely independent from
   frame to frame, so the median removes much of them: on a 160x112, 9-frame procedural segment with the
   "realistic" oracle prior, the guides rendered from it gained 1-2 dB PSNR.

`guide_from_geometry` then lifts the registered frames by that depth and renders them along an extension's
planned path (`wonderverse.guide.guide_from_frames`), the frame the extension continues from lifted last
(whole), so the nearest frames win. The geometry is first moved rigidly so that the reference frame's pose is
the extension's first planned pose exactly: the extension starts from that frame by construction, and the
Sim(3) fit's residual at that frame (a few centimetres, a fraction of a degree) would otherwise shift the whole
guide (it cost 2 dB on a right turn continuing from a segment's last frame).

Why the Sim(3)'s rotation comes from the cameras' orientations rather than Umeyama on their centres: a
planned segment often moves its camera along a straight line (the initial forward move, a strafe), and the
rotation about that line is then undetermined by the centres alone. The orientations fix it whatever the path;
scale and translation then come from the centres by least squares with that rotation held.

Conventions: OpenCV camera axes, W2C poses (4,4) float64, K in pixels with centres at +0.5, depth = camera z.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from wonderverse.camera import Sim3, camera_centers, invert_se3
from wonderverse.guide import GuideParams, guide_from_frames, lift_frames, render_points
from wonderverse.priors.base import DepthKind
from wonderverse.priors.params import AlignParams
from wonderverse.video.base import Guide

# Relative spread of the SfM camera centres below which the camera counts as not moving: the scale between the
# SfM world and the plan's is then undefined.
STILL_SPREAD_REL = 1e-9


class GeometryParams(BaseModel):
    """How a segment's frames are placed in the plan's world."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    fuse_neighbour_frames: int = Field(
        4,
        ge=0,
        le=32,
        description="a frame's depth is the per-pixel median of its own and that of up to this many registered "
        "frames on either side, reprojected into it; 0 = each frame's own depth",
    )
    max_fit_rms_rel: float = Field(
        0.2,
        gt=0,
        description="a segment whose SfM camera centres end farther than this share of its planned path's length "
        "(RMS) from the plan, after the best Sim(3), is not placed: its SfM is too far from the plan to trust",
    )


@dataclass
class SegmentGeometry:
    """A segment's frames placed in the plan's world.

    depth: (T,H,W) float32 camera z in plan units (+inf = sky; NaN for frames SfM did not register).
    poses: (T,4,4) float64 W2C in the plan's world (NaN where not registered). K: (3,3) the intrinsics SfM used.
    registered: (T,) bool. aligned: (T,) bool, the frame's depth alignment to the SfM points held (else a
    fallback scale, see `wonderverse.priors.align`). to_plan: the Sim(3) SfM world -> plan world.
    fit_rms: RMS distance (plan units) between the mapped SfM camera centres and the planned ones; fit_rms_rel:
    the same relative to the planned path's length (NaN when the plan does not move). reasons: the frames whose
    alignment failed, in words.
    """

    depth: np.ndarray
    poses: np.ndarray
    K: np.ndarray
    registered: np.ndarray
    aligned: np.ndarray
    to_plan: Sim3
    fit_rms: float
    fit_rms_rel: float
    reasons: list[str] = field(default_factory=list)


def _nearest_rotation(M: np.ndarray) -> np.ndarray:
    """The rotation closest (Frobenius) to a 3x3 matrix."""
    U, _, Vt = np.linalg.svd(M)
    S = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt)) or 1.0])
    return U @ S @ Vt


def path_length(w2c: np.ndarray) -> float:
    """Summed distance between consecutive camera centres of finite W2C poses (N,4,4)."""
    c = camera_centers(np.asarray(w2c, np.float64))
    return float(np.linalg.norm(np.diff(c, axis=0), axis=1).sum()) if len(c) > 1 else 0.0


def sfm_to_plan(sfm_w2c: np.ndarray, planned_w2c: np.ndarray, registered: np.ndarray) -> tuple[Sim3, float]:
    """The Sim(3) taking the SfM world onto the plan's, from the registered frames' cameras, and the RMS of the
    camera centres' residuals after it (plan units).

    Rotation R: the rotation nearest to the mean of R_plan^T R_sfm over the registered frames (a world Sim(3)
    turns each camera rotation R_c into R_c R^T). Scale s and translation t: least squares of planned centres
    against s R (SfM centres) + t. ValueError (in words) for fewer than two registered frames, a camera SfM saw
    standing still (no scale), or a scale that is not positive (the estimated motion runs against the plan)."""
    sfm_w2c = np.asarray(sfm_w2c, np.float64)
    planned_w2c = np.asarray(planned_w2c, np.float64)
    reg = np.asarray(registered, bool) & np.isfinite(sfm_w2c).all(axis=(1, 2))
    reg &= np.isfinite(planned_w2c).all(axis=(1, 2))
    if reg.sum() < 2:
        raise ValueError(f"SfM registered {int(reg.sum())} of its {len(reg)} frames; at least 2 are needed")
    Rs, Rp = sfm_w2c[reg, :3, :3], planned_w2c[reg, :3, :3]
    R = _nearest_rotation(np.einsum("nji,njk->ik", Rp, Rs))  # sum over frames of Rp^T Rs
    a = camera_centers(sfm_w2c[reg]) @ R.T
    b = camera_centers(planned_w2c[reg])
    a0, b0 = a - a.mean(0), b - b.mean(0)
    var = float((a0**2).sum())
    if var <= (STILL_SPREAD_REL * max(1.0, float(np.abs(a).max()))) ** 2:
        raise ValueError("the SfM camera does not move, so its scale in the plan's world is undefined")
    s = float((a0 * b0).sum() / var)
    if not s > 0:
        raise ValueError("the SfM camera moves against its planned path (negative scale)")
    t = b.mean(0) - s * a.mean(0)
    rms = float(np.sqrt(np.mean(np.sum((s * a + t - b) ** 2, axis=1))))
    return Sim3(s, R, t), rms


def place_segment(
    raw_depth: np.ndarray,
    kind: DepthKind,
    sfm_w2c: np.ndarray,
    registered: np.ndarray,
    points: np.ndarray,
    K: np.ndarray,
    planned_w2c: np.ndarray,
    align: AlignParams,
    sky_beyond_ref: float,
    params: GeometryParams | None = None,
) -> SegmentGeometry:
    """The geometry of a segment's frames in the plan's world.

    raw_depth: (T,H,W) the depth model's output in `kind` space; sfm_w2c (T,4,4) and registered (T,) the
    attempt's SfM poses (NaN where not registered), points (N,3) its SfM points, K (3,3) the intrinsics SfM
    used; planned_w2c (T,4,4) the segment's planned path. Depth is aligned per frame to the points it sees
    (`align_frames`, sky beyond `sky_beyond_ref` times the farthest point), everything is mapped by
    `sfm_to_plan`, and each frame's depth is fused with its neighbours' (`fuse_depth`). ValueError (in words)
    when the SfM cannot be placed (see `sfm_to_plan`) or fits the plan worse than `max_fit_rms_rel`."""
    p = params or GeometryParams()
    from wonderverse.priors import align_frames

    sfm_w2c = np.asarray(sfm_w2c, np.float64)
    registered = np.asarray(registered, bool) & np.isfinite(sfm_w2c).all(axis=(1, 2))
    to_plan, rms = sfm_to_plan(sfm_w2c, planned_w2c, registered)
    length = path_length(planned_w2c)
    if length > 0 and rms > p.max_fit_rms_rel * length:
        raise ValueError(
            f"its SfM path is {rms / length:.0%} of the planned path's length (RMS) away from the plan after the "
            f"best similarity (at most {p.max_fit_rms_rel:.0%})"
        )
    points = np.asarray(points, np.float64).reshape(-1, 3)
    aligned = align_frames(raw_depth, kind, sfm_w2c, points, K, align, sky_beyond_ref)
    depth = (aligned.depth * np.float32(to_plan.s)).astype(np.float32)
    depth[~registered] = np.nan
    poses = to_plan.transform_w2c(sfm_w2c)
    poses[~registered] = np.nan
    depth = fuse_depth(depth, poses, K, registered, p.fuse_neighbour_frames)
    return SegmentGeometry(
        depth=depth,
        poses=poses,
        K=np.asarray(K, np.float64),
        registered=registered,
        aligned=aligned.ok & registered,
        to_plan=to_plan,
        fit_rms=rms,
        fit_rms_rel=rms / length if length > 0 else float("nan"),
        reasons=aligned.reasons,
    )


def fuse_depth(
    depth: np.ndarray, w2c: np.ndarray, K: np.ndarray, registered: np.ndarray, neighbours: int
) -> np.ndarray:
    """Each registered frame's depth (T,H,W camera z; +inf sky) as the per-pixel median of its own and that of
    the registered frames up to `neighbours` before and after it, each lifted alone and rendered into it
    (`wonderverse.guide`, nearest surface per pixel). Sky pixels of a frame stay sky; a pixel no neighbour sees
    keeps its own depth; unregistered frames are returned as they are. Returns float32 (T,H,W)."""
    depth = np.asarray(depth, np.float32)
    idx = np.flatnonzero(np.asarray(registered, bool))
    if neighbours <= 0 or len(idx) < 2:
        return depth.copy()
    H, W = depth.shape[1:]
    blank = np.zeros((1, H, W, 3), np.uint8)  # colours are not needed, only the rendered depth
    solo = GuideParams(frame_stride=1, dedup_lifted=False, sky_as_directions=False)
    views: dict[int, list[np.ndarray]] = {int(t): [depth[t]] for t in idx}
    for j, src in enumerate(idx):
        targets = [int(t) for t in idx[max(0, j - neighbours) : j + neighbours + 1] if t != src]
        if not targets:
            continue
        points = lift_frames(blank, depth[src : src + 1], K, w2c[src : src + 1], solo)
        rendered = render_points(points, w2c[targets], K, W, H, solo)
        for n, t in enumerate(targets):
            seen = ~rendered.mask[n] & np.isfinite(rendered.depth[n])
            views[t].append(np.where(seen, rendered.depth[n], np.nan).astype(np.float32))
    out = depth.copy()
    for t, stack in views.items():
        own = depth[t]
        solid = np.where(np.isfinite(own), own, np.nan)
        with warnings.catch_warnings():  # a pixel no view sees: NaN, handled below
            warnings.simplefilter("ignore", RuntimeWarning)
            med = np.nanmedian(np.stack([solid, *stack[1:]]), axis=0)
        out[t] = np.where(np.isfinite(own) & np.isfinite(med), med, own)
    return out


def anchored(w2c: np.ndarray, reference_frame: int, start_w2c: np.ndarray) -> np.ndarray:
    """Poses (T,4,4 W2C) moved rigidly (the same world motion for all) so that frame `reference_frame`'s pose
    becomes `start_w2c`: W2C_t' = W2C_t inv(W2C_ref) start. Unchanged when that frame's pose is not finite."""
    ref = np.asarray(w2c[reference_frame], np.float64)
    if not np.isfinite(ref).all():
        return np.asarray(w2c, np.float64)
    return np.asarray(w2c, np.float64) @ invert_se3(ref) @ np.asarray(start_w2c, np.float64)


def lift_order(registered: np.ndarray, reference_frame: int) -> np.ndarray:
    """Indices of the registered frames, farthest from `reference_frame` first, so that the frame an extension
    continues from (or the registered frame nearest it) comes last: `guide_from_frames` lifts the last frame
    whole and earlier ones only where it holds nothing."""
    idx = np.flatnonzero(np.asarray(registered, bool))
    return idx[np.argsort(-np.abs(idx - int(reference_frame)), kind="stable")]


def guide_from_geometry(
    frames: np.ndarray,
    depth: np.ndarray,
    poses: np.ndarray,
    K: np.ndarray,
    registered: np.ndarray,
    reference_frame: int,
    path: np.ndarray,
    K_out: np.ndarray,
    width: int,
    height: int,
    params: GuideParams | None = None,
) -> Guide:
    """The guide of an extension: a segment's frames (T,H,W,3) uint8 with their placed `depth` (T,H,W) and
    `poses` (T,4,4) in the plan's world (a `SegmentGeometry`), anchored so that the extension's `reference_frame`
    sits at the start of its planned `path` (N,4,4 W2C; `anchored`), lifted from the registered frames (the
    reference frame last) and rendered along `path` with K_out at width x height. ValueError when no frame is
    registered."""
    order = lift_order(registered, reference_frame)
    if not len(order):
        raise ValueError("none of its frames is registered")
    poses = anchored(poses, reference_frame, np.asarray(path)[0])
    return guide_from_frames(frames[order], depth[order], K, poses[order], path, K_out, width, height, params)

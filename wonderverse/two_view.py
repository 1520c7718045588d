"""A segment's camera motion from two-view geometry alone: each looked-at frame against the first.

Why: SfM's path can be wrong in a way its own gates do not see. Where one plane carries most of the matches
(the ground of an outdoor scene, seen over a short baseline), the motion between two calibrated views has two
solutions (the planar ambiguity: Longuet-Higgins 1986, Faugeras & Lustman 1988): (R, t, n) and a twin whose
translation points along the plane's normal n and whose plane's normal points along t. COLMAP's verification
called 44-54 of the 54 matched pairs of every clip looked at "planar or panoramic" (a homography explains at
least 80 % of what an essential matrix does), in clips SfM got right as in those it got wrong. On the
plan-following benchmark (48 procedural 17-frame 320x208 segments, turns of 20-45 deg with and without forward
travel) SfM's path took the twin on 7 clean turn-and-travel segments: its dominant plane was perpendicular to
the true travel (|n . t| >= 0.96) instead of level, and the path turned 13-27 deg up and travelled mostly
downwards, at a reprojection error of 0.5 px, so the plan-following test rejected segments that had followed
their plan.

The essential matrix fitted by RANSAC to all of a pair's matches is not fooled as long as some matches lie off
the plane: the twin explains only those on it, the true motion all of them. On the same segments the pairs
(first frame, frame j) gave the rotation within 0.5 deg and the direction of travel within 6 deg of the truth
where SfM was 20-27 deg and 80-99 deg off. So `two_view_path` looks at a few frames (`TwoViewParams.frames`,
spread over the segment), matches each with the first and with the next looked-at one (SIFT, mutual nearest
neighbours with Lowe's ratio test) and, with K known, fits
- the essential matrix (COLMAP's LO-RANSAC on the calibrated rays, `pycolmap.estimate_relative_pose`), and
- a rotation alone (x2 ~ R x1, two-point RANSAC on the rays, same threshold).
Where the rotation alone explains more than `travel_max_rotation_only_share` of the essential matrix's inliers,
too few matches show parallax to measure the travel: the pair is read as a rotation (the essential matrix's
rotation, coupled to a translation that is noise, was 1.3 deg off on a rendered 3 deg pair; the rotation alone
0.2 deg), and the frame's travel is "not measured" (not "none": the plan-following test then judges the travel
on the frames that measured it). A pair enters the path only when a loop through a neighbouring looked-at
frame closes (first -> k -> j against first -> j, within `cycle_tol_deg`): a pair settled in a wrong solution
disagrees with its neighbours. Over the benchmark's 96 renderings (clean and ignoring their instruction,
half AI-like) 19 of 667 pairs failed their loop; the 648 kept had rotation errors of 0.16 deg (median), 1.0
(90th percentile), 4.9 at most, and the 384 that measured travel a direction error of 2.8 deg (median), 15
(90th percentile), 17 of them beyond 45 deg (short or weak pairs of AI-like video).
Each pair's translation has its own unknown scale; the baselines are brought to one by the depths of the first
frame's features that two pairs both triangulate (one point has one depth: b_j z_j = b_k z_k, least squares in
log space). The result is a path (W2C, the first camera at the origin with the identity rotation, NaN for
frames not looked at or left out), which `plan_following` compares with SfM's and judges where SfM's is
contradicted (`plan_following.choose_path`).

Limits: on AI-like video (non-rigid drift, blur, JPEG) the travel of short pairs is often not measurable (read
as a rotation, as above), and a direction of travel can still come out wrong on a weak pair that passes its
loop. Cost: SIFT on `frames` frames and 2 (frames - 1) - 1 pair fits, 2.7 s per 17-frame 320x208 segment on
the shared 2-core machine (one thread). pycolmap is imported inside the functions (importing this module for
`TwoViewParams` stays cheap).
"""

from __future__ import annotations

import itertools
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field


class TwoViewParams(BaseModel):
    """Step `check`: the two-view look at a segment's motion (`two_view_path`), against which the plan-following
    test checks SfM's path and which it judges instead where SfM's path is contradicted or failed its gates."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    frames: int = Field(9, ge=2, le=1000, description="frames looked at, spread from the first to the last")
    max_num_features: int = Field(2048, ge=64, le=65536, description="SIFT features per frame")
    max_image_size_px: int = Field(1024, ge=64, le=8192, description="SIFT runs on frames downscaled to this")
    match_max_ratio: float = Field(0.8, gt=0, le=1, description="Lowe's ratio test (COLMAP's default)")
    match_max_angle_rad: float = Field(0.7, gt=0, le=3.2, description="largest descriptor angle (COLMAP's)")
    max_error_px: float = Field(1.0, gt=0, description="RANSAC inlier threshold of both models (px)")
    min_inliers: int = Field(
        50, ge=8, description="a pair with fewer essential-matrix inliers is left out (SfM's init_min_num_inliers)"
    )
    travel_max_rotation_only_share: float = Field(
        0.4,
        gt=0,
        le=1,
        description="the travel is measured only where a rotation alone explains at most this share of E's "
        "inliers (the rest show parallax above max_error_px)",
    )
    cycle_tol_deg: float = Field(
        3.0, gt=0, description="a pair with the first frame is kept when a loop through a neighbour closes to this"
    )
    rotation_trials: int = Field(300, ge=1, le=100000, description="RANSAC trials of the rotation-only model")
    random_seed: int = Field(0, ge=0, lt=2**31, description="seed of both RANSAC estimators")
    num_threads: int = Field(1, ge=1, le=256, description="threads of SIFT extraction and RANSAC")


@dataclass
class PairMotion:
    """Frame j against the first frame. matches; inliers (essential matrix); rotation_only_inliers (of those,
    explained by a rotation alone); travel: the pair measures the direction of travel (parallax); cycle_deg:
    the smaller loop error through the neighbouring looked-at frames (NaN: no loop); tri_angle_deg: median
    triangulation angle of the inliers (NaN without travel); rotation_deg: the rotation's angle; baseline: the
    travel in the path's units (NaN when not measured); used: the frame is in the path; why: why not."""

    j: int
    matches: int
    inliers: int = 0
    rotation_only_inliers: int = 0
    travel: bool = False
    cycle_deg: float = float("nan")
    tri_angle_deg: float = float("nan")
    rotation_deg: float = float("nan")
    baseline: float = float("nan")
    used: bool = False
    why: str = ""


@dataclass
class TwoViewPath:
    """What `two_view_path` found. poses: (T,4,4) W2C, frame 0 the identity, translations in units of the longest
    measured travel (0 where the travel was not measured); registered: (T,) bool, the frames in the path (their
    rotation known); travel_known: (T,) bool, those whose travel is measured too (frame 0 always); pairs: one
    PairMotion per looked-at frame after the first; seconds: wall time."""

    poses: np.ndarray
    registered: np.ndarray
    travel_known: np.ndarray
    pairs: list[PairMotion]
    seconds: float

    @property
    def notes(self) -> list[str]:
        """Frames left out and why, in words."""
        return [f"frame {p.j}: {p.why}" for p in self.pairs if not p.used]

    def to_attrs(self) -> dict[str, Any]:
        """JSON-ready summary (NaN -> None) for store attributes."""

        def clean(v: Any) -> Any:
            return None if isinstance(v, float) and not np.isfinite(v) else v

        return {
            "frames": [int(i) for i in np.flatnonzero(self.registered)],
            "travel_frames": [int(i) for i in np.flatnonzero(self.travel_known)],
            "pairs": [{k: clean(v) for k, v in asdict(p).items()} for p in self.pairs],
            "seconds": float(self.seconds),
        }


# ---------------------------------------------------------------- features and matches


def _features(frame: np.ndarray, extractor: Any) -> tuple[np.ndarray, np.ndarray]:
    """SIFT of one (H,W,3) uint8 frame: keypoints (N,2) pixels (centres at +0.5) and unit descriptors (N,128)."""
    grey = np.clip(np.round(frame.astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32)), 0, 255)
    kp, desc = extractor.extract_from_uint8_array(np.ascontiguousarray(grey.astype(np.uint8)))
    xy = np.array([[k.x, k.y] for k in kp], dtype=np.float64).reshape(-1, 2)
    d = np.asarray(desc.data, dtype=np.float32).reshape(len(xy), 128)
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    return xy, d


def match_descriptors(d1: np.ndarray, d2: np.ndarray, max_ratio: float, max_angle: float) -> np.ndarray:
    """Mutual nearest neighbours of unit descriptors (N,D), (M,D) passing Lowe's ratio test and a bound on the
    angle between them (radians; COLMAP's SIFT matching rules): (K,2) int index pairs."""
    if len(d1) < 2 or len(d2) < 2:
        return np.zeros((0, 2), dtype=np.int64)
    angle = np.arccos(np.clip(d1 @ d2.T, -1.0, 1.0))
    nn12 = np.argmin(angle, axis=1)
    nn21 = np.argmin(angle, axis=0)
    two = np.partition(angle, 1, axis=1)[:, :2]
    i = np.arange(len(d1))
    keep = (nn21[nn12] == i) & (two[:, 0] <= max_ratio * two[:, 1]) & (two[:, 0] <= max_angle)
    return np.stack([i[keep], nn12[keep]], axis=1)


# ---------------------------------------------------------------- models


def rays(p: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Unit viewing rays (N,3) in camera coordinates of pixels p (N,2) (centres at +0.5) under K (3,3)."""
    r = np.c_[p, np.ones(len(p))] @ np.linalg.inv(K).T
    return r / np.linalg.norm(r, axis=1, keepdims=True)


def _kabsch(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The rotation R minimising sum |R a_k - b_k|^2 over the rows of a, b (k,3)."""
    U, _, Vt = np.linalg.svd(b.T @ a)
    return U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt


def rotation_only(r1: np.ndarray, r2: np.ndarray, max_angle: float, trials: int, seed: int) -> tuple[np.ndarray, int]:
    """The rotation R with r2 ~ R r1 (unit rays (N,3)) by two-point RANSAC (inliers: angle below `max_angle`
    radians), refined on its inliers: (R, number of inliers)."""
    n = len(r1)
    if n < 2:
        return np.eye(3), 0
    rng = np.random.default_rng(seed)
    k = np.stack([rng.choice(n, 2, replace=False) for _ in range(trials)])
    U, _, Vt = np.linalg.svd(np.einsum("tki,tkj->tij", r2[k], r1[k]))
    D = np.ones((trials, 3))
    D[:, 2] = np.sign(np.linalg.det(U @ Vt))
    Rs = U @ (D[:, :, None] * Vt)
    cos_max = np.cos(max_angle)
    counts = np.count_nonzero(np.einsum("tij,nj,ni->tn", Rs, r1, r2) >= cos_max, axis=1)
    R = Rs[int(np.argmax(counts))]
    for _ in range(2):  # refine on the inliers
        inl = np.sum((r1 @ R.T) * r2, axis=1) >= cos_max
        if inl.sum() < 2:
            break
        R = _kabsch(r1[inl], r2[inl])
    return R, int(np.count_nonzero(np.sum((r1 @ R.T) * r2, axis=1) >= cos_max))


def triangulated_depths(r1: np.ndarray, r2: np.ndarray, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Midpoint triangulation of rays r1 (camera 1) and r2 (camera 2) under x2 = R x1 + t: (depth along z in
    camera 1, NaN behind either camera; triangulation angle in degrees, 0 there), each (N,)."""
    d2 = r2 @ R  # R^T r2: the second rays in camera 1's frame
    c2 = -R.T @ t
    b = np.sum(r1 * d2, axis=1)
    d = r1 @ -c2
    e = d2 @ -c2
    den = np.maximum(1.0 - b * b, 1e-12)
    s = (b * e - d) / den
    u = (e - b * d) / den
    X = 0.5 * (s[:, None] * r1 + c2 + u[:, None] * d2)
    v1 = X / np.maximum(np.linalg.norm(X, axis=1, keepdims=True), 1e-300)
    v2 = X - c2
    v2 /= np.maximum(np.linalg.norm(v2, axis=1, keepdims=True), 1e-300)
    angle = np.degrees(np.arccos(np.clip(np.sum(v1 * v2, axis=1), -1.0, 1.0)))
    front = (s > 0) & (u > 0)
    return np.where(front, X[:, 2], np.nan), np.where(front, angle, 0.0)


def angle_deg(R: np.ndarray) -> float:
    """Rotation angle of R (3,3), degrees."""
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))


@dataclass
class _Edge:
    """Frames a < b matched: R (cam_b from cam_a), unit t (None: the travel is not measured), the frame-a feature
    ids and both rays of E's inliers, counts."""

    R: np.ndarray
    t: np.ndarray | None
    ids: np.ndarray
    r1: np.ndarray
    r2: np.ndarray
    matches: int
    inliers: int
    rotation_only_inliers: int


def _edge(fa: Any, fb: Any, camera: Any, ransac: Any, K: np.ndarray, p: TwoViewParams) -> _Edge | int:
    """Two-view geometry of two frames' features (keypoints, descriptors); the number of matches when fewer
    than `min_inliers` matches or essential-matrix inliers."""
    import pycolmap

    m = match_descriptors(fa[1], fb[1], p.match_max_ratio, p.match_max_angle_rad)
    if len(m) < p.min_inliers:
        return len(m)
    est = pycolmap.estimate_relative_pose(camera, fa[0][m[:, 0]], camera, fb[0][m[:, 1]], ransac)
    if est is None or int(est["num_inliers"]) < p.min_inliers:
        return len(m)
    inl = np.asarray(est["inlier_mask"], dtype=bool)
    r1, r2 = rays(fa[0][m[inl, 0]], K), rays(fb[0][m[inl, 1]], K)
    f_px = 0.5 * (K[0, 0] + K[1, 1])
    R_rot, n_rot = rotation_only(r1, r2, p.max_error_px / f_px, p.rotation_trials, p.random_seed)
    n = len(r1)
    if n_rot > p.travel_max_rotation_only_share * n:
        # Too little parallax to measure the travel: E's translation is noise, and its rotation, coupled to
        # that translation, is off too (1.3° on a 3° pair of a rendered turn); the pair is read as a rotation.
        return _Edge(R_rot, None, m[inl, 0], r1, r2, len(m), n, n_rot)
    pose = est["cam2_from_cam1"]
    t = np.asarray(pose.translation, dtype=np.float64)
    return _Edge(pose.rotation.matrix(), t / np.linalg.norm(t), m[inl, 0], r1, r2, len(m), n, n_rot)


# ---------------------------------------------------------------- the path


def _subset(n_frames: int, n: int) -> list[int]:
    return [int(i) for i in np.unique(np.round(np.linspace(0, n_frames - 1, min(n, n_frames))).astype(int))]


def two_view_path(frames: np.ndarray, K: np.ndarray, params: TwoViewParams | None = None) -> TwoViewPath:
    """The segment's motion from two-view geometry against its first frame (module doc).

    frames: (T,H,W,3) uint8; K: (3,3) pixels, known (the check's K). Returns a TwoViewPath; a looked-at frame
    is left out (its PairMotion says why) when its pair with the first frame matches too little, or when no loop
    through a neighbouring looked-at frame closes (the pair settled in a wrong solution). Never raises on
    content (no texture: nothing but frame 0 registered); ValueError for wrong shapes or a bad K."""
    import time

    import pycolmap

    params = params or TwoViewParams()
    t0 = time.perf_counter()
    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.dtype != np.uint8 or len(frames) < 1:
        raise ValueError(f"frames must be (T,H,W,3) uint8 with T >= 1, got {frames.dtype} {frames.shape}")
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError(f"K must be a finite (3,3) matrix with positive focal lengths, got {K!r}")
    T, H, W = frames.shape[:3]
    idx = _subset(T, params.frames)
    options = pycolmap.FeatureExtractionOptions()
    options.num_threads = params.num_threads
    options.use_gpu = False
    options.max_image_size = params.max_image_size_px
    options.sift.max_num_features = params.max_num_features
    extractor = pycolmap.FeatureExtractor.create(options, pycolmap.Device.cpu)
    feats = {i: _features(frames[i], extractor) for i in idx}
    camera = pycolmap.Camera(model="PINHOLE", width=W, height=H, params=[K[0, 0], K[1, 1], K[0, 2], K[1, 2]])
    ransac = pycolmap.RANSACOptions()
    ransac.max_error = params.max_error_px
    ransac.random_seed = params.random_seed
    ransac.num_threads = params.num_threads
    first = {j: _edge(feats[idx[0]], feats[j], camera, ransac, K, params) for j in idx[1:]}
    chain = {(a, b): _edge(feats[a], feats[b], camera, ransac, K, params) for a, b in itertools.pairwise(idx[1:])}
    pairs = [_judge_pair(j, first, chain, idx, params) for j in idx[1:]]
    kept = {p.j: e for p in pairs if p.used and isinstance(e := first[p.j], _Edge)}
    depths = {j: (e.ids, triangulated_depths(e.r1, e.r2, e.R, e.t)[0]) for j, e in kept.items() if e.t is not None}
    scales = _baselines(depths, {p.j: p.tri_angle_deg for p in pairs})
    poses = np.full((T, 4, 4), np.nan)
    poses[idx[0]] = np.eye(4)
    travel_known = np.zeros(T, dtype=bool)
    travel_known[idx[0]] = True
    for p in pairs:
        if not p.used:
            continue
        e = kept[p.j]
        poses[p.j] = np.eye(4)
        poses[p.j, :3, :3] = e.R
        if e.t is not None and p.j in scales:
            p.baseline = scales[p.j]
            poses[p.j, :3, 3] = e.t * p.baseline
            travel_known[p.j] = True
    registered = np.all(np.isfinite(poses.reshape(T, -1)), axis=1)
    return TwoViewPath(poses, registered, travel_known, pairs, time.perf_counter() - t0)


def _judge_pair(
    j: int, first: dict[int, _Edge | int], chain: dict[tuple[int, int], _Edge | int], idx: list[int], p: TwoViewParams
) -> PairMotion:
    """Whether frame j's pair with the first frame enters the path (PairMotion.used, .why)."""
    e = first[j]
    if not isinstance(e, _Edge):
        why = f"{e} matches or essential-matrix inliers with the first frame (need {p.min_inliers})"
        return PairMotion(j, e, why=why)
    out = PairMotion(j, e.matches, e.inliers, e.rotation_only_inliers, e.t is not None, rotation_deg=angle_deg(e.R))
    if e.t is not None:
        out.tri_angle_deg = float(np.median(triangulated_depths(e.r1, e.r2, e.R, e.t)[1]))
    # Loops first -> k -> j through the looked-at neighbours k of j, against first -> j.
    k = idx.index(j)
    loops = []
    for nb in (idx[k - 1] if k > 1 else None, idx[k + 1] if k + 1 < len(idx) else None):
        if nb is None:
            continue
        via, short = first.get(nb), chain.get((min(nb, j), max(nb, j)))
        if isinstance(via, _Edge) and isinstance(short, _Edge):
            nb_to_j = short.R if nb < j else short.R.T
            loops.append(angle_deg(nb_to_j @ via.R @ e.R.T))
    out.cycle_deg = min(loops) if loops else float("nan")
    if not loops:
        out.why = "no loop through a neighbouring looked-at frame to check it against"
    elif out.cycle_deg > p.cycle_tol_deg:
        out.why = f"its loops through the neighbouring frames close to {out.cycle_deg:.1f}° at best (a wrong solution)"
    else:
        out.used = True
    return out


MIN_COMMON_POINTS = 8  # points two pairs both triangulate, to carry the scale from one to the other


def _baselines(depth_of: dict[int, tuple[np.ndarray, np.ndarray]], tri: dict[int, float]) -> dict[int, float]:
    """Each pair's baseline, the largest 1: from the depths of the first frame's features that two pairs both
    triangulate (one point, one depth: b_j z_j = b_k z_k), solved in log space (least squares, weighted by the
    square root of the points shared) over every two pairs sharing at least MIN_COMMON_POINTS, on the connected
    group holding the pair of widest triangulation angle. Pairs outside that group are left out."""
    js = sorted(depth_of)
    if not js:
        return {}
    rows: list[tuple[int, int, float, int]] = []
    for a in range(len(js)):
        for b in range(a + 1, len(js)):
            ids_a, z_a = depth_of[js[a]]
            ids_b, z_b = depth_of[js[b]]
            ok_a, ok_b = np.isfinite(z_a) & (z_a > 0), np.isfinite(z_b) & (z_b > 0)
            _, ia, ib = np.intersect1d(ids_a[ok_a], ids_b[ok_b], return_indices=True)
            if len(ia) >= MIN_COMMON_POINTS:  # log b_a - log b_b = median log(z_b / z_a)
                rows.append((a, b, float(np.median(np.log(z_b[ok_b][ib] / z_a[ok_a][ia]))), len(ia)))
    ref = max(range(len(js)), key=lambda a: tri.get(js[a], 0.0))
    group, grew = {ref}, True
    while grew:
        grew = False
        for a, b, _, _ in rows:
            if (a in group) != (b in group):
                group |= {a, b}
                grew = True
    members = sorted(group)
    col = {a: c for c, a in enumerate(members)}
    A, y, w = [], [], []
    for a, b, v, n in rows:
        if a in group and b in group:
            r = np.zeros(len(members))
            r[col[a]], r[col[b]] = 1.0, -1.0
            A.append(r)
            y.append(v)
            w.append(np.sqrt(n))
    gauge = np.zeros(len(members))
    gauge[col[ref]] = 1.0
    A.append(gauge)
    y.append(0.0)
    w.append(1.0)
    W = np.array(w)
    log_b = np.linalg.lstsq(np.array(A) * W[:, None], np.array(y) * W, rcond=None)[0]
    b = np.exp(log_b - log_b.max())
    return {js[a]: float(b[col[a]]) for a in members}

"""Step `poses`: one camera path in one world frame for every frame of the stitched video.

`source: sfm` runs one reconstruction over the accepted frames in stitched order (every
`frame_stride`-th frame; sequential matching links the segments across their seams) and fills the
frames in between by interpolation; `source: conditioning` uses the path the video backend was
conditioned on (exact for the procedural world, guidance for real video models)."""

from __future__ import annotations

from typing import Any

import numpy as np

from tasks.base import Step
from tasks.segments import stitched
from wonderverse.config import RunConfig
from wonderverse.errors import WonderError
from wonderverse.store import SceneStore, write_array


def _params(cfg: RunConfig) -> dict[str, Any]:
    return {"poses": cfg.steps.poses}


def _fill(poses: np.ndarray, known: np.ndarray) -> np.ndarray:
    """Interpolate (slerp + linear centre) the poses of frames not in `known` from their neighbours."""
    from wonderverse.camera import interpolate_poses

    idx = np.flatnonzero(known)
    if len(idx) < 2:
        return poses
    out = poses.copy()
    missing = np.flatnonzero(~known & (np.arange(len(poses)) > idx[0]) & (np.arange(len(poses)) < idx[-1]))
    if len(missing):
        out[missing] = interpolate_poses(poses[idx], idx.astype(float), missing.astype(float), ease=False)
    return out


def _keep_previous_frame(
    store: SceneStore, frame_index: np.ndarray, segs: list[str], poses: np.ndarray, points: np.ndarray
) -> tuple[np.ndarray, np.ndarray, dict[str, Any] | None]:
    """A new reconstruction mapped into the world frame of the previous one (Sim(3) of the camera centres of
    the frames both posed), so an extended scene keeps its frame and its splats stay where they were. SfM's
    frame is arbitrary; without a previous reconstruction (or < 3 shared frames) nothing changes."""
    from wonderverse.camera import camera_centers, umeyama

    if store.attrs("sfm").get("complete") is not True or store.attrs("sfm").get("source") != "sfm":
        return poses, points, None
    old_segs = store.attrs("sfm")["segments"]
    old_index, old_poses = store.array("sfm/frame_index"), store.array("sfm/poses")
    old = {(old_segs[a], int(i)): pose for (a, i), pose in zip(old_index, old_poses, strict=True)}
    pairs = [(pose, old.get((segs[a], int(i)))) for (a, i), pose in zip(frame_index, poses, strict=True)]
    pairs = [(n, o) for n, o in pairs if o is not None and np.isfinite(n).all() and np.isfinite(o).all()]
    if len(pairs) < 3:
        return poses, points, None
    sim = umeyama(camera_centers(np.stack([n for n, _ in pairs])), camera_centers(np.stack([o for _, o in pairs])))
    fin = np.isfinite(poses).all(axis=(1, 2))
    out = poses.copy()
    out[fin] = sim.transform_w2c(poses[fin])
    return out, sim.apply(points) if len(points) else points, {"shared_frames": len(pairs), "scale": float(sim.s)}


def run(store: SceneStore, cfg: RunConfig, key: str) -> str:
    p = cfg.steps.poses
    frames, index = stitched(store)
    if len(frames) == 0:
        raise WonderError("no accepted frames to pose (every segment was dropped)")
    segs = sorted({s for s, _ in index})
    K = store.array(f"segments/{index[0][0]}/K")
    n = len(frames)
    frame_index = np.array([(segs.index(s), i) for s, i in index], dtype=np.int32)
    points = np.zeros((0, 3))
    colors = np.zeros((0, 3), np.uint8)
    attrs: dict[str, Any] = {"source": p.source, "segments": segs}
    if p.source == "conditioning":
        paths = {s: store.array(f"segments/{s}/path") for s in segs}
        poses = np.stack([paths[s][i] for s, i in index])
        registered = np.ones(n, bool)
    else:
        from wonderverse.sfm import reconstruct

        sel = np.unique(np.r_[np.arange(0, n, p.frame_stride), n - 1])
        res = reconstruct(frames[sel], p.sfm, K_prior=K)
        if not res.registered.any():
            raise WonderError(f"global SfM registered no frame: {'; '.join(res.problems)}")
        poses = np.full((n, 4, 4), np.nan)
        poses[sel] = res.poses
        registered = np.zeros(n, bool)
        registered[sel] = res.registered
        poses = _fill(poses, registered)
        points, colors, K = res.points, res.colors, res.K
        attrs |= {
            "mapper": res.mapper,
            "reproj_error_px": res.reproj_error_px,
            "problems": res.problems,
            "timings": res.timings,
            "frames_used": len(sel),
        }
    if p.source == "sfm":
        poses, points, attrs["kept_frame"] = _keep_previous_frame(store, frame_index, segs, poses, points)
    with store.staged("sfm", key, **attrs) as g:
        write_array(g, "poses", poses, chunks=poses.shape)
        write_array(g, "registered", registered, chunks=registered.shape)
        write_array(g, "K", np.asarray(K, np.float64), chunks=(3, 3))
        write_array(g, "frame_index", frame_index, chunks=frame_index.shape)
        write_array(g, "points3d", points.reshape(-1, 3), chunks=(max(1, len(points)), 3))
        write_array(g, "colors", colors.reshape(-1, 3), chunks=(max(1, len(points)), 3))
    posed = int(np.isfinite(poses[:, 0, 0]).sum())
    return f"{posed}/{n} frames posed ({p.source}), {len(points)} points"


STEP = Step("poses", 1, ("check",), _params, run, "one camera path for the stitched video", group="sfm")

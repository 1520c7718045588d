"""Step `poses`: one camera path in one world frame for every frame of the stitched video.

`source: sfm` runs one reconstruction over the accepted frames in stitched order (per segment every
`frame_stride`-th frame and its ends; sequential matching links the segments across their seams) and fills
the frames in between by interpolation; `source: conditioning` uses the path the video backend was
conditioned on (exact for the procedural world, guidance for real video models).

The `sfm` group keeps the COLMAP workspace (`colmap_database`, `colmap_model/<file>`, image names from
`image_names`) and, in its attrs, what it was made from (`segment_sources`, `workspace_key`)
and the Sim(3) from the COLMAP model to the world frame (`model_to_world`). When a re-run only adds
segments (an extension), their frames are registered into that reconstruction with the old poses and
intrinsics held fixed (`solve: incremental`, see `wonderverse.sfm_extend`): the old frames keep their exact
poses, so there is nothing to map back. Anything else, or an extension that fails its gates
(`incremental_problems`), re-solves every frame (`solve: full`) and maps the result into the previous
world frame. A full solve is checked against each segment's own SfM from the check step
(`segment_disagreement`) and re-solved with the next seeds while a segment disagrees (`solves`, `seed_offset`).
The global solve does not hold a known K the way the check does (see `wonderverse.sfm`'s notes)."""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Any

import numpy as np

from tasks.base import Step
from tasks.progress import advance
from tasks.segments import accepted_attempt, attempt_path, stitched
from wonderverse.camera import Sim3
from wonderverse.config import PosesParams, RunConfig
from wonderverse.errors import WonderError
from wonderverse.progress import ProgressFn
from wonderverse.store import SceneStore, cache_key, write_array

if TYPE_CHECKING:
    from wonderverse.sfm import SfmResult, SfmWorkspace

log = logging.getLogger("wonderverse.poses")
UNIT = "SfM stages"


def _report(prefix: str) -> ProgressFn:
    """The SfM's progress as this step's, its notes led by `prefix` ("solve 2 of 3: matching features")."""
    return lambda done, total, note: advance(done, total, UNIT, f"{prefix}{note}", eta=False)  # stages: no pace


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
    store: SceneStore, index: list[tuple[str, int]], poses: np.ndarray, points: np.ndarray
) -> tuple[np.ndarray, np.ndarray, dict[str, Any] | None, Sim3]:
    """A new reconstruction mapped into the world frame of the previous one (Sim(3) of the camera centres of
    the frames both posed), so an extended scene keeps its frame and its splats stay where they were. SfM's
    frame is arbitrary; without a previous reconstruction (or < 3 shared frames) nothing changes.
    Returns (poses, points, info for the attrs or None, the Sim(3) from the SfM model to the world)."""
    from wonderverse.camera import camera_centers, umeyama

    if store.attrs("sfm").get("complete") is not True or store.attrs("sfm").get("source") != "sfm":
        return poses, points, None, Sim3.identity()
    old = _previous_poses(store)
    pairs = [(pose, old.get(key)) for key, pose in zip(index, poses, strict=True)]
    pairs = [(n, o) for n, o in pairs if o is not None and np.isfinite(n).all() and np.isfinite(o).all()]
    if len(pairs) < 3:
        return poses, points, None, Sim3.identity()
    sim = umeyama(camera_centers(np.stack([n for n, _ in pairs])), camera_centers(np.stack([o for _, o in pairs])))
    fin = np.isfinite(poses).all(axis=(1, 2))
    out = poses.copy()
    out[fin] = sim.transform_w2c(poses[fin])
    info = {"shared_frames": len(pairs), "scale": float(sim.s)}
    return out, sim.apply(points) if len(points) else points, info, sim


def _previous_poses(store: SceneStore) -> dict[tuple[str, int], np.ndarray]:
    """(segment, generation-order index) -> W2C pose of the previous `sfm` group, in its stored order."""
    old_segs = store.attrs("sfm")["segments"]
    old_index, old_poses = store.array("sfm/frame_index"), store.array("sfm/poses")
    return {(old_segs[a], int(i)): pose for (a, i), pose in zip(old_index, old_poses, strict=True)}


def _selection(index: list[tuple[str, int]], stride: int) -> np.ndarray:
    """Stitched positions SfM uses: per segment, the frames whose generation index is a multiple of `stride`
    and the segment's first and last stitched frames (they link it across its seams). The choice depends on
    the segment alone, so a left extension prepended to the video leaves the old segments' selection (and
    with it an extensible reconstruction) unchanged."""
    n = len(index)
    seg = [s for s, _ in index]
    keep = [
        i % stride == 0 or k == 0 or k == n - 1 or seg[k - 1] != seg[k] or seg[k + 1] != seg[k]
        for k, (_, i) in enumerate(index)
    ]
    return np.flatnonzero(keep)


def _workspace_key(p: PosesParams) -> str:
    """What must not change for a reconstruction to be extended rather than re-solved."""
    # 2: image names sort in stitched order (`image_names`)
    return cache_key("sfm_workspace", 2, {"sfm": p.sfm, "frame_stride": p.frame_stride})


def image_names(store: SceneStore, keys: list[tuple[str, int]]) -> list[str]:
    """COLMAP image names for stitched frames (segment, generation-order index): unique, stable when the scene
    is extended at either end, and sorting in stitched order. COLMAP numbers images by sorted name, and the
    global mapper depends on that order: on the flows benchmark's 3-segment scene, names sorting by segment
    id (a left extension's reversed frames out of place) made it fail its gates in 3 of 4 runs and the
    incremental fallback end 10.8 % of the path off; names in stitched order gave 0.1 % in 4 of 4.
    `<lane><frame>_<segment>_<index>.png`: lane = 5000 + the segment's place in the playback order relative
    to the first segment that is not a left extension (lefts are prepended, the rest appended), frame = the
    index, or 9999 - index for a segment played reversed."""
    order = store.attrs("segments").get("order") or sorted({seg for seg, _ in keys})
    roles = {seg: store.attrs(f"segments/{seg}") for seg in order}
    anchor = next((k for k, seg in enumerate(order) if roles[seg].get("role") != "left"), 0)
    lane = {seg: 5000 + k - anchor for k, seg in enumerate(order)}
    return [f"{lane[seg]:04d}{9999 - i if roles[seg].get('reversed') else i:04d}_{seg}_{i:04d}.png" for seg, i in keys]


def _sources(store: SceneStore, segs: list[str]) -> dict[str, dict[str, Any]]:
    """Per segment, what its frames are: the segment's cache key and its accepted attempt."""
    return {s: {"key": store.cache_key_of(f"segments/{s}"), "attempt": accepted_attempt(store, s)} for s in segs}


def _extensible(
    store: SceneStore, p: PosesParams, names: list[str], name_seg: dict[str, str], sources: dict[str, Any]
) -> dict[str, Any] | None:
    """The previous `sfm` attrs when this run only adds segments to a reconstruction whose COLMAP workspace
    is stored (same SfM settings, every previously posed segment still there with the same frames, at least
    one new segment, the previous frames a subset of this run's); else None (full solve)."""
    prev = store.attrs("sfm")
    if prev.get("complete") is not True or prev.get("source") != "sfm" or not store.exists("sfm/colmap_model"):
        return None
    old_sources = prev.get("segment_sources") or {}
    if prev.get("workspace_key") != _workspace_key(p) or not old_sources:
        return None
    if any(sources.get(s) != v for s, v in old_sources.items()) or set(sources) == set(old_sources):
        return None
    old_names = set(prev.get("sfm_names") or [])
    if not old_names <= set(names) or any(name_seg[n] in old_sources for n in names if n not in old_names):
        return None
    return prev


def _load_workspace(store: SceneStore) -> SfmWorkspace:
    from wonderverse.sfm import SfmWorkspace

    model = {f: store.array(f"sfm/colmap_model/{f}").tobytes() for f in store.children("sfm/colmap_model")}
    return SfmWorkspace(database=store.array("sfm/colmap_database").tobytes(), model=model)


def _write_workspace(g: Any, ws: SfmWorkspace) -> None:
    """The COLMAP database and model files as uint8 arrays (`colmap_database`, `colmap_model/<file>`)."""

    def blob(group: Any, name: str, data: bytes) -> None:
        a = np.frombuffer(data, np.uint8)
        write_array(group, name, a, chunks=(max(1, min(len(a), 1 << 24)),))

    blob(g, "colmap_database", ws.database)
    model = g.create_group("colmap_model")
    for name, data in ws.model.items():
        blob(model, name, data)


def _incremental_poses(
    store: SceneStore, prev: dict[str, Any], res: SfmResult, sel: np.ndarray, index: list[tuple[str, int]]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Poses (N,4,4) W2C world, registered (N,) and points of an extension registered into the stored
    reconstruction: new frames through the stored model-to-world Sim(3); old frames keep exactly the poses
    later steps already used (interpolated ones included); frames in between are interpolated."""
    m = prev["model_to_world"]
    sim = Sim3(m["s"], np.array(m["R"]), np.array(m["t"]))
    n = len(index)
    poses = np.full((n, 4, 4), np.nan)
    registered = np.zeros(n, bool)
    poses[sel[res.registered]] = sim.transform_w2c(res.poses[res.registered])
    registered[sel] = res.registered
    old = _previous_poses(store)
    old_registered = {key for key, r in zip(old, store.array("sfm/registered"), strict=True) if r}
    for k, key in enumerate(index):  # the frames SfM posed before stay anchors, with their stored poses
        if key in old_registered:
            poses[k], registered[k] = old[key], True
    poses = _fill(poses, registered)
    for k, key in enumerate(index):
        if key in old and np.isfinite(old[key]).all():
            poses[k] = old[key]
    return poses, registered, sim.apply(res.points) if len(res.points) else res.points


def segment_disagreement(store: SceneStore, poses: np.ndarray, keys: list[tuple[str, int]]) -> dict[str, float]:
    """Per segment: how far the global solve's poses of its frames (`poses`, one per `keys` entry) are from
    the segment's own SfM in the check (an independent solve of fewer frames), as the ATE after a Sim(3)
    alignment, a share of that path's length. Segments with fewer than 3 frames posed by both, or whose check
    did not pass, are left out."""
    from wonderverse.metrics import ate

    rows: dict[str, list[tuple[int, int]]] = {}
    for k, (seg, i) in enumerate(keys):
        rows.setdefault(seg, []).append((k, i))
    out = {}
    for seg, pairs in rows.items():
        ap = attempt_path(store, seg)
        own_path = f"{ap}/sfm/poses"
        if not store.exists(own_path) or store.attrs(f"{ap}/check").get("accepted") is not True:
            continue  # a segment kept although its check failed has no trustworthy path of its own
        ks, own = [k for k, _ in pairs], store.array(own_path)[[i for _, i in pairs]]
        both = np.isfinite(poses[ks]).all(axis=(1, 2)) & np.isfinite(own).all(axis=(1, 2))
        if both.sum() >= 3:
            frac = ate(poses[ks], own)["rmse_frac"]
            if np.isfinite(frac):
                out[seg] = float(frac)
    return out


def _full_solve(
    store: SceneStore, p: PosesParams, frames: np.ndarray, names: list[str], keys: list[tuple[str, int]], K: np.ndarray
) -> tuple[SfmResult, dict[str, Any]]:
    """Every selected frame solved at once, re-solved with the next seeds (up to `p.disagreement_retries`)
    while some segment disagrees with its own SfM by more than `p.max_segment_disagreement_frac`: global
    SfM over a stitched video can pass every gate with a segment bent out of shape (measured: 10 % of the
    path off, on a turn the segment's own solve got right). Returns the least disagreeing solve and attrs."""
    from wonderverse.sfm import reconstruct

    tried = []
    for retry in range(p.disagreement_retries + 1):
        sfm = p.sfm.model_copy(update={"random_seed": p.sfm.random_seed + retry})
        solve = f"solve {retry + 1} of up to {p.disagreement_retries + 1}: " if retry else ""
        res = reconstruct(frames, sfm, K_prior=K, names=names, keep_workspace=True, progress=_report(solve))
        posed = bool(res.registered.any())
        worst = segment_disagreement(store, res.poses, keys) if posed else {}
        tried.append((posed, -max(worst.values(), default=0.0), retry, res, worst))
        if max(worst.values(), default=0.0) <= p.max_segment_disagreement_frac:  # also: nothing to compare
            break
    _, _, retry, res, worst = max(tried, key=lambda t: t[:2])
    if len(tried) > 1:
        log.warning("global SfM: %d solve(s), kept seed +%d (segment disagreement %s)", len(tried), retry, worst)
    return res, {"segment_disagreement": worst, "solves": len(tried), "seed_offset": retry}


def _sfm_poses(
    store: SceneStore, p: PosesParams, frames: np.ndarray, index: list[tuple[str, int]], segs: list[str], K: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, SfmResult, dict[str, Any]]:
    """Global SfM over the selected stitched frames: registered into the stored reconstruction when this
    run only adds segments to it (old frames keep their exact poses), else solved from scratch and mapped
    into the previous world frame. Returns poses (N,4,4) W2C world, registered (N,), points (world), the
    SfM result (colours, K, and the COLMAP workspace to store) and the attrs."""
    from wonderverse.sfm_extend import extend_reconstruction

    sel = _selection(index, p.frame_stride)
    names = image_names(store, [index[k] for k in sel])
    name_seg = {name: index[k][0] for name, k in zip(names, sel, strict=True)}
    sources = _sources(store, segs)
    attrs: dict[str, Any] = {}
    prev = _extensible(store, p, names, name_seg, sources)
    if prev is not None:
        old_names = set(prev["sfm_names"])
        new_frames = {name: frames[k] for name, k in zip(names, sel, strict=True) if name not in old_names}
        res, _ = extend_reconstruction(  # the workspace is also in res.workspace
            _load_workspace(store), names, new_frames, p.sfm, progress=_report("extension: ")
        )
        if res.gates_passed:
            poses, registered, points = _incremental_poses(store, prev, res, sel, index)
            sim_attrs = {"model_to_world": prev["model_to_world"], "kept_frame": prev.get("kept_frame")}
            attrs |= {"solve": "incremental", "new_frames": len(new_frames), **sim_attrs}
        else:  # fall back to the full solve, and say why
            attrs |= {"incremental_problems": res.problems, "incremental_timings": res.timings}
    if "solve" not in attrs:
        res, more = _full_solve(store, p, frames[sel], names, [index[k] for k in sel], K)
        attrs |= more
        if not res.registered.any() or res.workspace is None:
            raise WonderError(f"global SfM registered no frame: {'; '.join(res.problems)}")
        poses = np.full((len(frames), 4, 4), np.nan)
        poses[sel] = res.poses
        registered = np.zeros(len(frames), bool)
        registered[sel] = res.registered
        poses = _fill(poses, registered)
        poses, points, kept, sim = _keep_previous_frame(store, index, poses, res.points)
        model_to_world = {"s": float(sim.s), "R": sim.R.tolist(), "t": sim.t.tolist()}
        attrs |= {"solve": "full", "kept_frame": kept, "model_to_world": model_to_world}
    attrs |= {
        "mapper": res.mapper,
        "reproj_error_px": res.reproj_error_px,
        "problems": res.problems,
        "timings": res.timings,
        "frames_used": len(sel),
        "sfm_names": names,
        "segment_sources": sources,
        "workspace_key": _workspace_key(p),
    }
    return poses, registered, points, res, attrs


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
    workspace: SfmWorkspace | None = None
    if p.source == "conditioning":
        paths = {s: store.array(f"segments/{s}/path") for s in segs}
        poses = np.stack([paths[s][i] for s, i in index])
        registered = np.ones(n, bool)
    else:
        poses, registered, points, res, more = _sfm_poses(store, p, frames, index, segs, K)
        colors, K, workspace = res.colors, res.K, res.workspace
        attrs |= more
    with store.staged("sfm", key, **attrs) as g:
        write_array(g, "poses", poses, chunks=poses.shape)
        write_array(g, "registered", registered, chunks=registered.shape)
        write_array(g, "K", np.asarray(K, np.float64), chunks=(3, 3))
        write_array(g, "frame_index", frame_index, chunks=frame_index.shape)
        write_array(g, "points3d", points.reshape(-1, 3), chunks=(max(1, len(points)), 3))
        write_array(g, "colors", colors.reshape(-1, 3), chunks=(max(1, len(points)), 3))
        if workspace is not None:
            _write_workspace(g, workspace)
    posed = int(np.isfinite(poses[:, 0, 0]).sum())
    how = f", {attrs['solve']} solve" if "solve" in attrs else ""
    return f"{posed}/{n} frames posed ({p.source}{how}), {len(points)} points"


# 2: the group keeps the COLMAP workspace (extensions register only their new frames); frames selected per segment
# 3: image names in stitched order; full solves checked against each segment's own SfM
STEP = Step("poses", 3, ("check",), _params, run, "one camera path for the stitched video", group="sfm")

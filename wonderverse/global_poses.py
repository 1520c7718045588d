"""Global poses: one camera path in one world frame for every frame of the stitched video.

One SfM reconstruction over the accepted frames in stitched order (per segment every `frame_stride`-th frame and its
ends, `select_frames`; sequential matching links the segments across their seams); the frames in between are
interpolated (`fill_poses`). When a solve only adds segments to a previous one whose COLMAP workspace is kept (an
extension), their frames are registered into it with the old poses and intrinsics held fixed
(`wonderverse.sfm_extend`), and the old frames keep their exact poses (`merge_incremental`). Anything else, or an
extension that fails its gates, re-solves every frame (`solve_consistent`: re-solved with the next seeds while a
segment disagrees with its own SfM, `segment_disagreement`, or with the turn its check read, `segment_turn_error`)
and maps the result into the previous world frame (`map_into_previous`), so an extended scene keeps its frame and
its splats stay where they were.

The `K` attrs say where the solve's intrinsics came from (`wonderverse.sfm.k_record`).

Frames are keyed by (segment id, generation-order index). Poses are W2C (N,4,4) float64, NaN where unknown.
Knows nothing of the store: `solve_global_poses` takes arrays and what the previous solve left
(`PreviousSolve`), and returns arrays and the attrs to keep.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from wonderverse.camera import CameraPrior, Sim3
from wonderverse.errors import WonderError
from wonderverse.progress import ProgressFn

if TYPE_CHECKING:
    from wonderverse.config import PosesParams
    from wonderverse.sfm import SfmResult, SfmWorkspace

Key = tuple[str, int]  # (segment id, generation-order index) of a stitched frame
log = logging.getLogger("wonderverse.poses")  # the poses step's logger: its warnings read as the step's


@dataclass
class PreviousSolve:
    """What the previous global solve left, as the next one needs it.

    poses: every frame's W2C pose in the world frame, in stored order (NaN where unknown); registered:
    the frames SfM posed (the others were interpolated); names: the COLMAP image names of its SfM frames;
    sources: per segment, what its frames were (compared for equality only); workspace_key: the settings
    its COLMAP workspace was made with; model_to_world: the Sim(3) from that COLMAP model to the world;
    kept_frame: how it was itself mapped into the solve before it; load_workspace: reads the stored COLMAP
    workspace (None when none is stored)."""

    poses: dict[Key, np.ndarray]
    registered: set[Key]
    names: list[str]
    sources: dict[str, Any]
    workspace_key: str | None = None
    model_to_world: Sim3 | None = None
    kept_frame: dict[str, Any] | None = None
    load_workspace: Callable[[], SfmWorkspace] | None = None


@dataclass
class GlobalPoses:
    """poses (N,4,4) W2C world frame, NaN where unknown; registered (N,) bool, posed by SfM (the rest
    interpolated); points (P,3) world and colors (P,3) uint8 of the sparse model; K (3,3) the solve's
    intrinsics; workspace: the COLMAP workspace to keep; attrs: how the solve went (JSON-able)."""

    poses: np.ndarray
    registered: np.ndarray
    points: np.ndarray
    colors: np.ndarray
    K: np.ndarray
    workspace: SfmWorkspace | None
    attrs: dict[str, Any]


def fill_poses(poses: np.ndarray, known: np.ndarray) -> np.ndarray:
    """`poses` (N,4,4) with the frames between the first and last `known` (N,) ones that are not known
    interpolated (slerp + linear centre) from their neighbours; frames outside stay as they are."""
    from wonderverse.camera import interpolate_poses

    idx = np.flatnonzero(known)
    if len(idx) < 2:
        return poses
    out = poses.copy()
    missing = np.flatnonzero(~known & (np.arange(len(poses)) > idx[0]) & (np.arange(len(poses)) < idx[-1]))
    if len(missing):
        out[missing] = interpolate_poses(poses[idx], idx.astype(float), missing.astype(float), ease=False)
    return out


def select_frames(index: Sequence[Key], stride: int) -> np.ndarray:
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


def image_names(keys: Sequence[Key], order: Sequence[str], left: set[str], reversed_: set[str]) -> list[str]:
    """COLMAP image names for stitched frames: unique, stable when the scene is extended at either end, and
    sorting in stitched order. `order`: the segments in playback-lane order (lefts are prepended, the rest
    appended); `left`: the segments that are left extensions; `reversed_`: those played reversed.

    COLMAP numbers images by sorted name, and the global mapper depends on that order: on the flows
    benchmark's 3-segment scene, names sorting by segment id (a left extension's reversed frames out of
    place) made it fail its gates in 3 of 4 runs and the incremental fallback end 10.8 % of the path off;
    names in stitched order gave 0.1 % in 4 of 4. `<lane><frame>_<segment>_<index>.png`: lane = 5000 + the
    segment's place in `order` relative to the first segment that is not a left extension, frame = the
    index, or 9999 - index for a segment played reversed."""
    anchor = next((k for k, seg in enumerate(order) if seg not in left), 0)
    lane = {seg: 5000 + k - anchor for k, seg in enumerate(order)}
    return [f"{lane[seg]:04d}{9999 - i if seg in reversed_ else i:04d}_{seg}_{i:04d}.png" for seg, i in keys]


def map_into_previous(
    index: Sequence[Key], poses: np.ndarray, points: np.ndarray, previous: Mapping[Key, np.ndarray] | None
) -> tuple[np.ndarray, np.ndarray, dict[str, Any] | None, Sim3]:
    """A new reconstruction mapped into the world frame of the previous one: the Sim(3) (Umeyama) taking
    the camera centres of the frames both posed (finite in both) onto the previous ones. SfM's frame is
    arbitrary; without a previous solve (or < 3 shared frames) nothing changes.
    Returns (poses (N,4,4) W2C, points (P,3), {"shared_frames", "scale"} or None, the Sim(3) applied)."""
    from wonderverse.camera import camera_centers, umeyama

    if previous is None:
        return poses, points, None, Sim3.identity()
    pairs = [(pose, previous.get(key)) for key, pose in zip(index, poses, strict=True)]
    pairs = [(n, o) for n, o in pairs if o is not None and np.isfinite(n).all() and np.isfinite(o).all()]
    if len(pairs) < 3:
        return poses, points, None, Sim3.identity()
    sim = umeyama(camera_centers(np.stack([n for n, _ in pairs])), camera_centers(np.stack([o for _, o in pairs])))
    fin = np.isfinite(poses).all(axis=(1, 2))
    out = poses.copy()
    out[fin] = sim.transform_w2c(poses[fin])
    info = {"shared_frames": len(pairs), "scale": float(sim.s)}
    return out, sim.apply(points) if len(points) else points, info, sim


def merge_incremental(
    index: Sequence[Key], sel: np.ndarray, res: SfmResult, model_to_world: Sim3, previous: PreviousSolve
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Poses (N,4,4) W2C world, registered (N,) and points (P,3) world of an extension registered into the
    previous reconstruction (`res`: the solve of the frames at stitched positions `sel`): new frames go
    through the model-to-world Sim(3); old frames keep exactly the poses later steps already used
    (interpolated ones included), and those SfM posed before stay anchors of the interpolation of the
    frames in between."""
    n = len(index)
    poses = np.full((n, 4, 4), np.nan)
    registered = np.zeros(n, bool)
    poses[sel[res.registered]] = model_to_world.transform_w2c(res.poses[res.registered])
    registered[sel] = res.registered
    old = previous.poses
    for k, key in enumerate(index):
        if key in previous.registered:
            poses[k], registered[k] = old[key], True
    poses = fill_poses(poses, registered)
    for k, key in enumerate(index):
        if key in old and np.isfinite(old[key]).all():
            poses[k] = old[key]
    return poses, registered, model_to_world.apply(res.points) if len(res.points) else res.points


def _by_segment(keys: Sequence[Key]) -> dict[str, list[tuple[int, int]]]:
    """Per segment, (row in `keys`, generation-order index) of each of its frames."""
    rows: dict[str, list[tuple[int, int]]] = {}
    for k, (seg, i) in enumerate(keys):
        rows.setdefault(seg, []).append((k, i))
    return rows


def segment_disagreement(poses: np.ndarray, keys: Sequence[Key], own: Mapping[str, np.ndarray]) -> dict[str, float]:
    """Per segment: how far a global solve's poses of its frames (`poses`, one per `keys` entry) are from
    the segment's own SfM (`own[seg]`: its W2C poses in generation order, an independent solve of fewer
    frames), as the ATE after a Sim(3) alignment, a share of that path's length. Segments missing from
    `own` (no trustworthy path of their own) or with fewer than 3 frames posed by both are left out."""
    from wonderverse.metrics import ate

    out = {}
    for seg, pairs in _by_segment(keys).items():
        if seg not in own:
            continue
        ks, own_poses = [k for k, _ in pairs], own[seg][[i for _, i in pairs]]
        both = np.isfinite(poses[ks]).all(axis=(1, 2)) & np.isfinite(own_poses).all(axis=(1, 2))
        if both.sum() >= 3:
            frac = ate(poses[ks], own_poses)["rmse_frac"]
            if np.isfinite(frac):
                out[seg] = float(frac)
    return out


def segment_turn_error(
    poses: np.ndarray, keys: Sequence[Key], turns: Mapping[str, tuple[np.ndarray, np.ndarray]]
) -> dict[str, float]:
    """Per segment whose check read its turn (`turns[seg]`: its planned W2C path (T,4,4) and the check's reading,
    (yaw, pitch, roll) of the path it trusted minus the plan's, degrees, first to last judged frame): degrees
    between that reading and the same difference for a solve's poses of its frames (`poses`, one per `keys`
    entry). Camera centres miss what this catches: a global solve that settled one segment in the planar twin
    of its motion (measured: a 30° turn solved with 27° of pitch drift, its centres within 2.3 % of the check's
    SfM, which sat in the same twin) against the check's two-view reading; a generator that turned otherwise
    than planned is no error, the check read that too. Segments with fewer than 2 frames posed are left out."""
    from wonderverse.plan_following import compare_to_plan

    out = {}
    for seg, pairs in _by_segment(keys).items():
        if seg not in turns:
            continue
        plan, reading = turns[seg]
        est = np.full(np.shape(plan), np.nan)
        for k, i in pairs:
            est[i] = poses[k]
        v = compare_to_plan(est, plan)
        if v.estimated is not None and v.planned is not None:
            out[seg] = float(np.linalg.norm(turn_angles(v.estimated) - turn_angles(v.planned) - reading))
    return out


def turn_angles(motion: Any) -> np.ndarray:
    """(yaw left, pitch up, roll left) degrees of a `plan_following.Motion` or its attrs dict."""
    names = ("yaw_left_deg", "pitch_up_deg", "roll_left_deg")
    get = motion.get if isinstance(motion, dict) else lambda n: getattr(motion, n)
    return np.array([get(n) for n in names], dtype=np.float64)


def mappers_after_check(check_mapper: tuple[str, bool] | None) -> dict[str, Any]:
    """SfmParams updates for the global solve of a one-segment video whose check mapped it (with the same
    intrinsics handling: a guessed K) with `check_mapper`
    (the mapper's name, whether its model passed the gates): that mapper goes first, and alone when no mapper
    passed in the check, so the same frames never go through the whole mapper chain twice (measured before
    the parallax look: a near-static 49-frame clip ran three mappers in the check and three again here)."""
    if check_mapper is None or not check_mapper[0]:
        return {}
    kind = "global" if check_mapper[0] == "global" else "incremental"  # the prior-focal run is an incremental one
    if not check_mapper[1]:
        return {"mapper": kind}
    return {"auto_order": (kind, "incremental" if kind == "global" else "global")}


def solve_consistent(
    solve: Callable[[int, str], SfmResult],
    measures: Mapping[str, tuple[Callable[[np.ndarray], dict[str, float]], float]],
    retries: int,
) -> tuple[SfmResult, dict[str, Any]]:
    """`solve(seed_offset, note)` re-run with the next seeds (up to `retries` more times) while some segment's poses
    are further from what the check knew of it than a measure allows (`measures`: name -> (per-segment figures of a
    solve's poses, limit); `segment_disagreement` against its own SfM, `segment_turn_error_deg` against its turn):
    global SfM over a stitched video can pass every gate with a segment bent out of shape (measured: 10 % of the
    path off, on a turn the segment's own solve got right). `note` is "" for the first solve, else "solve k of up
    to n: ". Returns the solve that posed something and went least past its limits (the worst figure over its
    limit; the earliest of equals), and attrs {each measure's name: its figures, "solves", "seed_offset"}."""
    tried = []
    for retry in range(retries + 1):
        res = solve(retry, f"solve {retry + 1} of up to {retries + 1}: " if retry else "")
        posed = bool(res.registered.any())
        figures = {name: fn(res.poses) if posed else {} for name, (fn, _) in measures.items()}
        worst = max((v / measures[name][1] for name, f in figures.items() for v in f.values()), default=0.0)
        tried.append((posed, -worst, retry, res, figures))
        if worst <= 1.0:  # also: nothing to compare
            break
    _, _, retry, res, figures = max(tried, key=lambda t: t[:2])
    if len(tried) > 1:
        log.warning("global SfM: %d solve(s), kept seed +%d (%s)", len(tried), retry, figures)
    return res, {**figures, "solves": len(tried), "seed_offset": retry}


def can_extend(
    previous: PreviousSolve | None,
    workspace_key: str,
    names: Sequence[str],
    name_seg: Mapping[str, str],
    sources: Mapping[str, Any],
) -> bool:
    """Whether this solve only adds segments to `previous`, so its new frames can be registered into the
    stored reconstruction: same SfM settings (`workspace_key`), its workspace stored, every previously posed
    segment still there with the same frames, at least one new segment, the previous frames' names a subset
    of this solve's `names` and every new name a new segment's (`name_seg`: name -> segment)."""
    if previous is None or previous.load_workspace is None or previous.model_to_world is None:
        return False
    old_sources = previous.sources
    if previous.workspace_key != workspace_key or not old_sources:
        return False
    if any(sources.get(s) != v for s, v in old_sources.items()) or set(sources) == set(old_sources):
        return False
    old_names = set(previous.names)
    return old_names <= set(names) and not any(name_seg[n] in old_sources for n in names if n not in old_names)


def _prefixed(progress: ProgressFn, prefix: str) -> ProgressFn:
    """`progress` with every note led by `prefix` ("solve 2 of 3: matching features")."""
    return lambda done, total, note: progress(done, total, f"{prefix}{note}")


def solve_global_poses(
    frames: np.ndarray,
    index: Sequence[Key],
    prior: CameraPrior,
    params: PosesParams,
    *,
    names: Sequence[str],
    sources: Mapping[str, Any],
    workspace_key: str,
    own: Mapping[str, np.ndarray],
    turns: Mapping[str, tuple[np.ndarray, np.ndarray]],
    previous: PreviousSolve | None,
    progress: ProgressFn,
    check_mapper: tuple[str, bool] | None = None,
    hold_given: bool = False,
) -> GlobalPoses:
    """Global SfM over the stitched video: registered into the previous reconstruction when this solve only
    adds segments to it (old frames keep their exact poses, `can_extend`), else solved from scratch (and again
    while a segment disagrees with `own`, its own SfM, or with `turns`, its turn); mapped into the previous world
    frame.

    frames (N,H,W,3) uint8 and index (N keys) in stitched order; prior: the video's intrinsics, a guess (self-
    calibrated, `wonderverse.sfm.reconstruct`) or given: held fixed with `hold_given` (the user's camera: the
    returned K is then the prior's, exactly), else refined from (a generated video's: over a stitched video refining
    was right where holding was not, `wonderverse.sfm` module notes); names: the COLMAP image name of each frame
    `select_frames(index, params.frame_stride)` picks; sources: per segment, what its frames are; workspace_key:
    what must not change for a reconstruction to be extended; own: per segment whose check passed on SfM's path, its
    own SfM poses (generation order); turns: per segment whose check judged its plan-following, its planned path and
    the check's reading of its turn (`segment_turn_error`); previous: the last solve or None; check_mapper: when the
    video is one segment, the mapper its check's SfM kept and whether that model passed its gates
    (`mappers_after_check`; only where the check handled K as this solve does: a guess, or a held K).
    Raises WonderError when no frame could be posed."""
    from wonderverse.sfm import k_record, reconstruct
    from wonderverse.sfm_extend import extend_reconstruction

    p = params
    sel = select_frames(index, p.frame_stride)
    name_seg = {name: index[k][0] for name, k in zip(names, sel, strict=True)}
    attrs: dict[str, Any] = {}
    if can_extend(previous, workspace_key, names, name_seg, sources):
        assert previous is not None and previous.load_workspace is not None and previous.model_to_world is not None
        old_names = set(previous.names)
        new_frames = {name: frames[k] for name, k in zip(names, sel, strict=True) if name not in old_names}
        res, _ = extend_reconstruction(  # the workspace is also in res.workspace
            previous.load_workspace(), list(names), new_frames, p.sfm, progress=_prefixed(progress, "extension: ")
        )
        problems, turn = list(res.problems), {}
        if res.gates_passed:
            poses, registered, points = merge_incremental(index, sel, res, previous.model_to_world, previous)
            new_segs = {name_seg[name] for name in new_frames}
            turn = segment_turn_error(poses, index, {s: t for s, t in turns.items() if s in new_segs})
            limit = p.max_segment_turn_error_deg
            problems = [f"segment {s} turned {e:.1f}° off what its check read" for s, e in turn.items() if e > limit]
        if res.gates_passed and not problems:
            sim_attrs = {"model_to_world": previous.model_to_world.to_dict(), "kept_frame": previous.kept_frame}
            attrs |= {
                "solve": "incremental",
                "new_frames": len(new_frames),
                "segment_turn_error_deg": turn,
                **sim_attrs,
            }
        else:  # fall back to the full solve, and say why
            attrs |= {"incremental_problems": problems, "incremental_timings": res.timings}
    if "solve" not in attrs:
        keys = [index[k] for k in sel]

        order = mappers_after_check(check_mapper)

        def solve(seed_offset: int, note: str) -> SfmResult:
            seed = p.sfm.random_seed + seed_offset
            sfm = p.sfm.model_copy(update={"random_seed": seed, "hold_known_intrinsics": hold_given, **order})
            return reconstruct(
                frames[sel],
                sfm,
                prior,
                names=list(names),
                keep_workspace=True,
                progress=_prefixed(progress, note),
            )

        measures = {
            "segment_disagreement": (
                lambda poses: segment_disagreement(poses, keys, own),
                p.max_segment_disagreement_frac,
            ),
            "segment_turn_error_deg": (
                lambda poses: segment_turn_error(poses, keys, turns),
                p.max_segment_turn_error_deg,
            ),
        }
        res, more = solve_consistent(solve, measures, p.disagreement_retries)
        attrs |= more
        if res.stopped:
            raise WonderError(f"global SfM did not map the video: {res.stopped}")
        if not res.registered.any() or res.workspace is None:
            raise WonderError(f"global SfM registered no frame: {'; '.join(res.problems)}")
        poses = np.full((len(frames), 4, 4), np.nan)
        poses[sel] = res.poses
        registered = np.zeros(len(frames), bool)
        registered[sel] = res.registered
        poses = fill_poses(poses, registered)
        poses, points, kept, sim = map_into_previous(
            index, poses, res.points, None if previous is None else previous.poses
        )
        attrs |= {"solve": "full", "kept_frame": kept, "model_to_world": sim.to_dict()}
    held = hold_given and prior.given
    if attrs["solve"] == "incremental":  # the kept camera: the full solve that made the workspace held or refined it
        res.k_source = "given" if held else "estimated"  # (whether it held K is part of the workspace key)
    attrs |= k_record(res, prior)
    K = prior.K.copy() if held and res.k_source == "given" else res.K  # held: the K given, not COLMAP's copy of it
    attrs |= {
        "mapper": res.mapper,
        "reproj_error_px": res.reproj_error_px,
        "problems": res.problems,
        "timings": res.timings,
        "frames_used": len(sel),
        "sfm_names": list(names),
        "segment_sources": dict(sources),
        "workspace_key": workspace_key,
    }
    return GlobalPoses(poses, registered, points, res.colors, K, res.workspace, attrs)

"""How good a scene's result is, read from the store: the global camera poses against the quality gates, the
splats' PSNR/SSIM (called held-out only where views were held out), and per clip how many frames the check's SfM
and the global solve registered. `inspect --json` (`quality`), the report, and the closing line of `generate` and
`reconstruct` (`gate_line`; `--strict` makes it an error, exit 2) read it.

The quality gates on the final poses (docs/usage.md, "Quality gates"), for poses from SfM (poses taken from the
conditioning path have no SfM to judge): the global solve registered at least `MIN_POSED_VIEWS` views, at least
the poses step's own `sfm.min_registered_frac` of the frames it was given (0.8 by default), and kept at least its
`sfm.min_points` 3D points (100 by default): the same share and point count the SfM gates ask of one clip, plus
a floor of views, since a handful of photos can pass a share and still leave nothing to train the splats on (a
6-photo set registering 5 views from 25 points made a scene of 12.7 dB training PSNR). ATE needs a ground-truth
path: the procedural world's; for anything else it is not available, and `ate_note` says so.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict

from tasks.segments import accepted_attempt
from wonderverse.schema import ATTEMPT, SFM, SPLATS
from wonderverse.store import DamagedData, SceneStore

MIN_POSED_VIEWS = 8  # views the global solve must register, whatever the share
DEFAULT_MIN_REGISTERED_FRAC = 0.8  # SfmParams' defaults, where no configuration is stored
DEFAULT_MIN_POINTS = 100


class Record(BaseModel):
    model_config = ConfigDict(frozen=True)


class PoseGates(Record):
    """The gates the final poses are held to."""

    min_views: int = MIN_POSED_VIEWS
    min_registered_frac: float = DEFAULT_MIN_REGISTERED_FRAC
    min_points: int = DEFAULT_MIN_POINTS


class PoseQuality(Record):
    """The global camera path: where it came from, frames registered by SfM of those it was given (`registered` of
    `frames_used`), frames with a pose (`posed` of `frames`: SfM's and those interpolated between them), 3D points,
    mean reprojection error, ATE (share of the path's length, after a Sim(3)) when a ground truth exists (else None,
    `ate_note` says why), the gates, what failed them (empty: passed) and `passed` (None: no SfM to judge)."""

    source: str
    registered: int
    frames_used: int
    posed: int
    frames: int
    points: int
    reproj_error_px: float | None
    ate_frac: float | None
    ate_note: str
    gates: PoseGates
    problems: list[str]
    passed: bool | None


class SplatQuality(Record):
    """The splats' figures: views held out (never trained on) and trained on; PSNR (dB) and SSIM on the held-out
    views (None when none was held out) and on (up to 8 of) the training views; `psnr_label` names the PSNR to quote:
    "held-out" only where views were held out, else "training"."""

    held_out_views: int
    training_views: int
    held_out_psnr_db: float | None
    held_out_ssim: float | None
    training_psnr_db: float | None
    training_ssim: float | None
    psnr_label: str

    @property
    def psnr_db(self) -> float | None:
        """The PSNR `psnr_label` names."""
        return self.held_out_psnr_db if self.psnr_label == "held-out" else self.training_psnr_db


class Quality(Record):
    """`inspect --json`'s `quality`: the poses' and the splats' figures (None: that step has not run)."""

    poses: PoseQuality | None
    splats: SplatQuality | None


def _finite(x: Any) -> float | None:
    return float(x) if isinstance(x, int | float) and math.isfinite(x) else None


def gates_of(cfg: Any | None) -> PoseGates:
    """The gates under a RunConfig (its poses step's SfM gates), or the defaults without one."""
    if cfg is None:
        return PoseGates()
    sfm = cfg.steps.poses.sfm
    return PoseGates(min_registered_frac=sfm.min_registered_frac, min_points=sfm.min_points)


def ground_truth_path(store: SceneStore) -> tuple[np.ndarray, np.ndarray] | None:
    """(global poses, ground-truth poses of the same stitched frames) when every segment has a ground truth (the
    procedural world's), else None."""
    sfm = store.meta(SFM.path)
    if sfm is None:
        return None
    gts = {}
    for seg in sfm.segments:
        k = accepted_attempt(store, seg)
        path = ATTEMPT.at(seg=seg, attempt=k).gt.poses if k is not None else None
        if path is None or not store.exists(path):
            return None
        gts[seg] = store.array(path)
    index = store.array(SFM.frame_index)
    gt = np.stack([gts[sfm.segments[a]][i] for a, i in index]) if len(index) else np.zeros((0, 4, 4))
    return store.array(SFM.poses), gt


def pose_problems(registered: int, frames_used: int, points: int, gates: PoseGates) -> list[str]:
    """What fails the gates, in words naming the figures (empty: every gate holds)."""
    out = []
    share = registered / frames_used if frames_used else 0.0
    if registered < gates.min_views or share < gates.min_registered_frac:
        out.append(
            f"{registered} of {frames_used} views registered (at least {gates.min_views} and "
            f"{100 * gates.min_registered_frac:.0f} % needed)"
        )
    if points < gates.min_points:
        out.append(f"{points} 3D points (at least {gates.min_points} needed)")
    return out


def pose_quality(store: SceneStore, gates: PoseGates | None = None) -> PoseQuality | None:
    """The global poses' figures and gates (None: the poses step has not completed, or its data is damaged: the
    damage is listed with the store's damaged groups and the poses step rebuilds it on the next run)."""
    from wonderverse.metrics import ate

    sfm = store.meta(SFM.path)
    if sfm is None:
        return None
    gates = gates or PoseGates()
    try:
        poses = store.array(SFM.poses)
        registered = int(store.array(SFM.registered).sum())
        points = int(store.open_array(SFM.points3d).shape[0])
    except DamagedData:
        return None
    posed = int(np.isfinite(poses).all(axis=(1, 2)).sum())
    used = int(sfm.frames_used) if sfm.frames_used is not None else len(poses)
    ate_frac, note = None, "not available: no ground-truth camera path (only the procedural world has one)"
    pair = ground_truth_path(store)
    if pair is not None:
        try:
            ate_frac = _finite(ate(*pair)["rmse_frac"])
            note = "against the procedural world's ground truth, Sim(3)-aligned, share of the path's length"
        except ValueError as e:
            note = f"not available: {e}"
    if sfm.source == "conditioning":
        problems, passed = [], None
    else:
        problems = pose_problems(registered, used, points, gates)
        passed = not problems
    return PoseQuality(
        source=sfm.source,
        registered=registered,
        frames_used=used,
        posed=posed,
        frames=len(poses),
        points=points,
        reproj_error_px=_finite(sfm.reproj_error_px),
        ate_frac=ate_frac,
        ate_note=note,
        gates=gates,
        problems=problems,
        passed=passed,
    )


def splat_quality(store: SceneStore) -> SplatQuality | None:
    """The splats' PSNR/SSIM, held-out and training (None: the splats step has not completed)."""
    splats = store.meta(SPLATS.path)
    if splats is None:
        return None
    m = splats.metrics
    held = len(m.test_views)
    return SplatQuality(
        held_out_views=held,
        training_views=len(m.train_views),
        held_out_psnr_db=_finite(m.test_psnr) if held else None,
        held_out_ssim=_finite(m.test_ssim) if held else None,
        training_psnr_db=_finite(m.train_psnr),
        training_ssim=_finite(m.train_ssim),
        psnr_label="held-out" if held and _finite(m.test_psnr) is not None else "training",
    )


def quality(store: SceneStore, gates: PoseGates | None = None) -> Quality:
    return Quality(poses=pose_quality(store, gates), splats=splat_quality(store))


def registration(store: SceneStore, seg: str) -> tuple[tuple[int, int] | None, tuple[int, int] | None]:
    """Frames of a segment registered (of those SfM was given) by its check's SfM and by the global solve (None
    where that solve has not run, or, for the global one, did not include the segment)."""
    k = accepted_attempt(store, seg)
    check = None
    if k is not None:
        path = ATTEMPT.at(seg=seg, attempt=k).sfm.registered
        if store.exists(path):
            r = store.array(path)
            check = (int(r.sum()), len(r))
    sfm = store.meta(SFM.path)
    if sfm is None or sfm.source != "sfm" or seg not in sfm.segments:
        return check, None
    mine = store.array(SFM.frame_index)[:, 0] == sfm.segments.index(seg)
    registered = int(store.array(SFM.registered)[mine].sum())
    # the frames SfM was given: their image names carry the segment (`global_poses.image_names`)
    used = sum(f"_{seg}_" in name for name in sfm.sfm_names) or int(mine.sum())
    return check, (registered, used)


def gate_line(q: PoseQuality | None) -> str | None:
    """The closing line's words when the final poses fail the gates (None: they pass, or nothing to judge)."""
    if q is None or q.passed is not False:
        return None
    return (
        "the final camera poses fail the quality gates: "
        + "; ".join(q.problems)
        + ": the scene is likely unusable (more frames with more overlap, or --fov-deg, may help)"
    )

"""Does a segment go where the words say? The plan-following check, guided extensions and named content.

1. Plan-following test (`wonderverse.plan_following.judge_segment`). N segments (--quick: 8 at 224x144, 13
   frames; else 48 at the preview preset's 320x208, 17 frames), each a planned move from the procedural world's
   start pose (`camera.move_path`): a turn left, right, up or down of 20-45 deg, half of them with forward travel
   of 0.5-2 m, half without; a left/right turn also travels sideways `plan.strafe_m_per_deg` per degree as the
   pipeline's paths do (`planning.paths.conditioning_paths`), so only up/down turns without travel are pure rotations.
   Half are rendered with the `ai_like` defects (real generated video is like that), half without. Each is
   rendered twice: clean (`fault_probability` 0) and with `force_fault: "ignore"` (the camera takes a smooth,
   plausible, wrong path: the turn reversed or left out, the travel turned by 90-180 deg; `gt.faults["mode"]`).
   Each rendering is posed exactly as the check poses an attempt (`sfm.reconstruct` with `cfg.steps.check.sfm`
   of the preview preset, K known), looked at with two-view geometry (`two_view.two_view_path`, the check's
   `plan_following.two_view`) and judged as `tasks.check` judges it (`plan_following.judge_segment`: SfM's
   path unless two-view geometry contradicts its rotations by more than `sfm_rotation_tol_deg`, or SfM's model
   failed its gates and cannot be confirmed; then the two-view path). Sweeps (SfM and the two-view look run
   once per rendering, only the judgement is repeated): `rotation_tol_deg`, `rotation_tol_share` and
   `translation_direction_tol_deg` scaled together by `SWEEP_FACTORS` (1 = the shipped
   `PlanFollowingParams()`), then the two rotation tolerances alone and the direction tolerance alone, each
   row also with SfM's path alone (the test before the two-view look); and `sfm_rotation_tol_deg` over
   `DISAGREEMENT_TOLS_DEG`. "Not judged": neither path registered 2 frames (ok is None); left out of recall
   and FPR, and counted. Diagnostics: the same test on the path really rendered (gt.poses: what the test does
   with perfect poses), and "SfM off": the SfM path fails the test against the path really rendered (the
   error is SfM's, not the video's). Also: what the whole check does (`check_trajectory`, plus the
   plan-following test as `tasks.check` adds it), over all segments.
2. Named content (`wonderverse.video.content`): extend requests (`CONTENT_REQUESTS`, --quick: the first 4 at
   160x104, 9 frames; else all 10 at 320x208, 17 frames). The rule planner's extension for the words after the
   initial segment (`planning.rules.plan_extension`), its path as `planning.paths.conditioning_paths` makes it,
   rendered after the initial segment by the same procedural model with the segment prompt carrying the words
   (`video.prompts.segment_prompt`). A hit when every named kind's ground-truth labels cover more than
   `CONTENT_MIN_SHARE` of the pixels of the segment's last `CONTENT_LAST_FRAMES` frames. Column `column`: the
   labelled pixels' mean column as a share of the width (< 0.5: left of centre).
3. Guided extensions (procedural `accept_guide`): a 5-segment scene (initial + 2 rounds of left and right;
   "a small house decorated for Christmas", `ai_like` defects, no faults; --quick: 224x144, 13 frames, splats
   at 160 px for 150 iterations; else the preview preset) through the real pipeline up to `splats`, guided and
   unguided (otherwise the same config). Per extension generated from a guide (an extension whose parent could
   not be placed in the plan's world is generated unguided, and is left out): the guide's coverage (share of
   known pixels), colour PSNR and depth AbsRel against the truth over known pixels (recorded by the procedural
   backend in its accepted attempt's gt attrs `guide`, `guide.guide_errors`). Seam quality: PSNR of the
   extension's first `SEAM_FRAMES` frames after its reference frame (frame 0 repeats the parent's) against the
   final splats rendered at those frames' global SfM poses (video size, the learnt background): the scene
   re-rendered where the segment joins it, guided vs unguided on the same segments. Branch speed-up: wall time
   to `check` of the guided scene (in a guided flow `generate_segments` renders, checks and places wave by
   wave; that is where the branches run side by side) with `execution.segment_workers` and `generate_workers`
   1 (serial) over 2 (a Dask LocalCluster of 2 processes per wave), fresh scene folders, after the two scenes
   above warmed the process up. The machine's cores bound it (2 here, shared).

Last-line keys:
- `ignored_recall`, `ignored_fpr`: at the shipped defaults, share of judged "ignore" renderings with ok False,
  and of judged clean renderings with ok False (targets >= 0.95, <= 0.05).
- `ignored_not_judged`, `clean_not_judged`: renderings SfM could not register (counts); `segments`: N.
- `check_recall`, `check_fpr`: the whole check (trajectory rules + plan following) rejecting "ignore" / clean
  renderings, over all N each (a segment SfM cannot register is rejected by the trajectory rules).
- `true_path_recall`, `true_path_fpr`: the test at the defaults on the paths really rendered (perfect poses).
- `clean_sfm_off`: clean renderings whose SfM path fails the test against the path really rendered (count).
- `best_factor`: the factor of the "all three" sweep with the highest recall among those with FPR <= 0.05 (NaN
  if none).
- `sfm_s_per_segment`: mean SfM seconds per rendering.
- `sfm_only_recall`, `sfm_only_fpr`: the same on SfM's path alone (the test before the two-view look).
- `judged_on_two_view`: renderings judged on the two-view path at the defaults (count, of 2 N);
  `two_view_s_per_segment`: mean seconds of the two-view look per rendering.
- `content_hit_rate`: share of extend requests whose named content is visible (NaN: no content module).
- `guide_coverage`, `guide_psnr_db`, `guide_depth_absrel`: means over the guided extensions; `guided_extensions`:
  how many of the 4 were generated from a guide.
- `seam_psnr_guided`, `seam_psnr_unguided`: mean seam PSNR (dB) over those extensions, in each scene.
- `branch_speedup`: `branch_serial_s` ÷ `branch_parallel_s` (seconds to `check` of the guided scene).
- `seconds`: the whole benchmark.
The guided keys are NaN when the installed procedural options have no `accept_guide` or a scene fails (a note
line says which). `--only plan|content|guided` (repeatable) runs only those parts; the last line then holds
their keys (and `seconds`).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from benchmarks.common import report, table
from benchmarks.detection import PROMPTS  # the same six worlds
from wonderverse.plan_following import PlanFollowingParams

DIRECTIONS = ("left", "right", "up", "down")
TURN_DEG = (20.0, 45.0)
FORWARD_M = (0.5, 2.0)
SWEEP_FACTORS = (0.5, 0.75, 1.0, 1.25, 1.5, 2.0)
SCALED = ("rotation_tol_deg", "rotation_tol_share", "translation_direction_tol_deg")
# What each sweep scales: all three together, then the rotation and the direction tolerances alone.
SWEEPS = {"all": SCALED, "rotation": SCALED[:2], "direction": SCALED[2:]}
TARGET_RECALL, TARGET_FPR = 0.95, 0.05


@dataclass(frozen=True)
class Case:
    """One planned segment: world (prompt, scene seed), move (direction, degrees, forward metres), defects."""

    index: int
    prompt: str
    scene_seed: int
    direction: str
    turn_deg: float
    forward_m: float
    defects: str

    @property
    def move(self) -> str:
        travel = f" + forward {self.forward_m:.1f}" if self.forward_m else ""
        return f"{self.direction} {self.turn_deg:.0f}{travel}"


@dataclass
class Outcome:
    """One rendering of a case posed by the check's SfM: estimated W2C poses (T,4,4, NaN where unregistered),
    registered mask, planned W2C path, the path really rendered (gt.poses), whether it ignored its instruction
    (and how), and the trajectory rules' verdict on it (True: accepted) with their reasons; the two-view look at
    its frames (`two_view.TwoViewPath`, None: not taken), whether SfM's model passed its gates, and the seconds
    of SfM and of the two-view look."""

    case: Case
    ignored: bool
    mode: str
    poses: np.ndarray
    registered: np.ndarray
    planned: np.ndarray
    true_poses: np.ndarray
    trajectory_ok: bool
    trajectory_reasons: list[str]
    sfm_s: float
    two_view: Any = None
    gates_passed: bool = True
    two_view_s: float = 0.0


def cases(n: int) -> list[Case]:
    """N cases: direction cycles, travel every other group of 4, `ai_like` defects on a pattern that crosses both."""
    out = []
    for i in range(n):
        rng = np.random.default_rng([23, i])
        travel = (i // len(DIRECTIONS)) % 2 == 1
        out.append(
            Case(
                index=i,
                prompt=PROMPTS[i % len(PROMPTS)],
                scene_seed=i,
                direction=DIRECTIONS[i % len(DIRECTIONS)],
                turn_deg=float(rng.uniform(*TURN_DEG)),
                forward_m=float(rng.uniform(*FORWARD_M)) if travel else 0.0,
                defects="ai_like" if (i + i // len(DIRECTIONS)) % 2 else "none",
            )
        )
    return out


def planned_path(case: Case, start_w2c: np.ndarray, frames: int, strafe_m_per_deg: float) -> np.ndarray:
    """(T,4,4) W2C path of the case's move from `start_w2c` as `planning.paths.conditioning_paths` builds it:
    `camera.move_path` (yaw + = left, pitch + = up) with the planner's sideways travel per degree of yaw."""
    from wonderverse.camera import move_path

    sign = 1.0 if case.direction in ("left", "up") else -1.0
    yaw_deg, pitch_deg = (
        (sign * case.turn_deg, 0.0) if case.direction in ("left", "right") else (0.0, sign * case.turn_deg)
    )
    return move_path(
        start_w2c, math.radians(yaw_deg), math.radians(pitch_deg), case.forward_m, strafe_m_per_deg * yaw_deg, frames
    )


def render_and_pose(case: Case, ignored: bool, width: int, height: int, frames: int) -> Outcome:
    """Render the case (clean or ignoring its instruction) and pose it with the check's SfM (see module doc)."""
    from wonderverse.camera import CameraPrior
    from wonderverse.check import check_trajectory
    from wonderverse.config import build_config
    from wonderverse.sfm import reconstruct
    from wonderverse.two_view import two_view_path
    from wonderverse.video import initial_pose
    from wonderverse.video.procedural import ProceduralVideo

    cfg = build_config(case.prompt, preset="preview")
    opts: dict[str, Any] = {"fault_probability": 0.0, "defects": case.defects}
    if ignored:
        opts["force_fault"] = "ignore"
    model = ProceduralVideo(case.prompt, case.scene_seed, width, height, cfg.scene.video.fov_deg, opts)
    path = planned_path(case, initial_pose(model), frames, cfg.steps.plan.strafe_m_per_deg)
    video = model.generate(case.prompt, path, seed=(2000 if ignored else 1000) + case.index, reference=None)
    t = time.perf_counter()
    sfm = reconstruct(video.frames, cfg.steps.check.sfm, CameraPrior(video.K, "given"))
    seconds = time.perf_counter() - t
    rules = check_trajectory(
        sfm.poses, sfm.registered, cfg.steps.check.rules, sfm.problems, points=sfm.points, stopped=sfm.stopped
    )
    look, two_view_s = None, 0.0
    pf = cfg.steps.check.plan_following
    if pf is not None and pf.two_view is not None:
        t = time.perf_counter()
        look = two_view_path(video.frames, video.K, pf.two_view)
        two_view_s = time.perf_counter() - t
    return Outcome(
        case=case,
        ignored=ignored,
        mode=str(video.gt.faults.get("mode", "clean")) if video.gt is not None else "clean",
        poses=sfm.poses,
        registered=sfm.registered,
        planned=path,
        true_poses=video.gt.poses,
        trajectory_ok=bool(rules.accepted),
        trajectory_reasons=list(rules.reasons),
        sfm_s=seconds,
        two_view=look,
        gates_passed=bool(sfm.gates_passed),
        two_view_s=two_view_s,
    )


def scaled(params: PlanFollowingParams, factor: float, names: tuple[str, ...] = SCALED) -> PlanFollowingParams:
    """`params` with the tolerances `names` multiplied by `factor` (the direction tolerance capped at 180)."""
    new = {name: getattr(params, name) * factor for name in names}
    if "translation_direction_tol_deg" in new:
        new["translation_direction_tol_deg"] = min(new["translation_direction_tol_deg"], 180.0)
    return params.model_copy(update=new)


def judged(o: Outcome, params: PlanFollowingParams, truth: bool = False, sfm_only: bool = False) -> Any:
    """The plan-following verdict on the outcome as `tasks.check` reaches it (`plan_following.judge_segment`:
    SfM's path checked against the two-view look, `choose_path`); `sfm_only`: compare_to_plan of SfM's path
    alone (the test before the two-view look); `truth`: compare_to_plan of the path really rendered."""
    from wonderverse.plan_following import choose_path, compare_to_plan

    if truth:
        return compare_to_plan(o.true_poses, o.planned, params)
    sfm = compare_to_plan(o.poses, o.planned, params, registered=o.registered)
    if sfm_only or params.two_view is None or o.two_view is None:
        return sfm
    return choose_path(sfm, o.poses, o.registered, o.gates_passed, o.two_view, o.planned, params)


def verdict(o: Outcome, params: PlanFollowingParams, truth: bool = False, sfm_only: bool = False) -> bool | None:
    """`judged`'s ok on the outcome: True followed, False ignored, None not judged."""
    return judged(o, params, truth, sfm_only).ok


def sfm_off(o: Outcome, params: PlanFollowingParams) -> bool:
    """Whether the SfM path itself fails the test against the path really rendered (SfM, not the video, is off)."""
    from wonderverse.plan_following import compare_to_plan

    return compare_to_plan(o.poses, o.true_poses, params, registered=o.registered).ok is False


def rates(flagged: list[bool | None], ignored: list[bool]) -> dict[str, Any]:
    """Recall (ignored renderings flagged), FPR (clean ones flagged), over judged renderings only, and counts.

    flagged[i]: True (the test rejected rendering i), False (accepted), None (not judged). Rates are NaN when
    nothing of their kind was judged."""
    if len(flagged) != len(ignored):
        raise ValueError(f"{len(flagged)} verdicts for {len(ignored)} renderings")
    pos = [f for f, ig in zip(flagged, ignored, strict=True) if ig and f is not None]
    neg = [f for f, ig in zip(flagged, ignored, strict=True) if not ig and f is not None]
    return {
        "recall": float(np.mean(pos)) if pos else float("nan"),
        "fpr": float(np.mean(neg)) if neg else float("nan"),
        "ignored_judged": len(pos),
        "clean_judged": len(neg),
        "ignored_not_judged": sum(ig for ig in ignored) - len(pos),
        "clean_not_judged": sum(not ig for ig in ignored) - len(neg),
    }


def flagged_by(
    outcomes: list[Outcome], params: PlanFollowingParams, truth: bool = False, sfm_only: bool = False
) -> list[bool | None]:
    """Per outcome: True when the plan-following test rejects it, False when it passes, None when not judged
    (`truth`: judged on the path really rendered instead; `sfm_only`: on SfM's path alone)."""
    out: list[bool | None] = []
    for o in outcomes:
        ok = verdict(o, params, truth, sfm_only)
        out.append(None if ok is None else not ok)
    return out


def sweep_rows(
    outcomes: list[Outcome],
    base: PlanFollowingParams,
    factors: tuple[float, ...],
    sweeps: dict[str, tuple[str, ...]] | None = None,
) -> list[dict[str, Any]]:
    """One row per (sweep, factor): the scaled tolerances, recall and FPR over judged renderings and the judged
    counts; recall and FPR on the paths really rendered too (what the test does with perfect poses). `sweeps`:
    name -> tolerances scaled (default SWEEPS; factor 1 is given once, in the first sweep)."""
    sweeps = SWEEPS if sweeps is None else sweeps
    ignored = [o.ignored for o in outcomes]
    rows = []
    for k, (name, names) in enumerate(sweeps.items()):
        for f in factors:
            if f == 1.0 and k > 0:
                continue
            p = scaled(base, f, names)
            r = rates(flagged_by(outcomes, p), ignored)
            t = rates(flagged_by(outcomes, p, truth=True), ignored)
            alone = rates(flagged_by(outcomes, p, sfm_only=True), ignored)
            rows.append(
                {
                    "scaled": name,
                    "factor": f,
                    "rot_tol_deg": p.rotation_tol_deg,
                    "rot_tol_share": p.rotation_tol_share,
                    "dir_tol_deg": p.translation_direction_tol_deg,
                    "recall": r["recall"],
                    "fpr": r["fpr"],
                    "ignored judged": r["ignored_judged"],
                    "clean judged": r["clean_judged"],
                    "recall (true path)": t["recall"],
                    "fpr (true path)": t["fpr"],
                    "recall (SfM only)": alone["recall"],
                    "fpr (SfM only)": alone["fpr"],
                }
            )
    return rows


DISAGREEMENT_TOLS_DEG = (2.0, 3.0, 4.0, 6.0, 8.0, 12.0, 20.0)


def disagreement_rows(
    outcomes: list[Outcome], base: PlanFollowingParams, tols_deg: tuple[float, ...] = DISAGREEMENT_TOLS_DEG
) -> list[dict[str, Any]]:
    """One row per `sfm_rotation_tol_deg` (the rotation disagreement beyond which two-view geometry overrules
    SfM's path): recall, FPR, judged counts and how many renderings were judged on the two-view path."""
    ignored = [o.ignored for o in outcomes]
    rows = []
    for tol in tols_deg:
        p = base.model_copy(update={"sfm_rotation_tol_deg": tol})
        verdicts = [judged(o, p) for o in outcomes]
        r = rates([None if v.ok is None else not v.ok for v in verdicts], ignored)
        rows.append(
            {
                "sfm_rotation_tol_deg": tol,
                "recall": r["recall"],
                "fpr": r["fpr"],
                "ignored judged": r["ignored_judged"],
                "clean judged": r["clean_judged"],
                "judged on two-view": sum(v.source == "two_view" for v in verdicts),
            }
        )
    return rows


def best_factor(rows: list[dict[str, Any]], max_fpr: float = TARGET_FPR, sweep: str = "all") -> float:
    """The factor of the row of `sweep` (rows without a "scaled" entry count as its) with the highest recall among
    rows with FPR <= max_fpr (the larger factor on a tie: the looser, the fewer false positives on unseen data);
    NaN when no row qualifies."""
    good = [r for r in rows if r.get("scaled", sweep) == sweep and r["fpr"] <= max_fpr and math.isfinite(r["recall"])]
    if not good:
        return float("nan")
    return float(max(good, key=lambda r: (r["recall"], r["factor"]))["factor"])


def breakdown_rows(outcomes: list[Outcome], params: PlanFollowingParams) -> list[dict[str, Any]]:
    """At `params`: per (rendering kind, move kind, defects) group, how many were flagged, passed, not judged,
    judged on the two-view path, flagged by SfM's path alone, flagged on the path really rendered, whose SfM
    path fails the test against that path (`sfm_off`), and what the whole check did (rejected by the trajectory
    rules or the plan-following test)."""
    verdicts = [judged(o, params) for o in outcomes]
    flagged = [None if v.ok is None else not v.ok for v in verdicts]
    alone = flagged_by(outcomes, params, sfm_only=True)
    on_truth = flagged_by(outcomes, params, truth=True)
    groups: dict[tuple[str, str, str], list[int]] = {}
    for i, o in enumerate(outcomes):
        move = "turn+travel" if o.case.forward_m else "turn"
        groups.setdefault((o.mode, move, o.case.defects), []).append(i)
    rows = []
    for (mode, move, defects), idx in sorted(groups.items()):
        rows.append(
            {
                "rendering": mode,
                "move": move,
                "defects": defects,
                "n": len(idx),
                "flagged": sum(flagged[i] is True for i in idx),
                "passed": sum(flagged[i] is False for i in idx),
                "not judged": sum(flagged[i] is None for i in idx),
                "on two-view": sum(verdicts[i].source == "two_view" for i in idx),
                "flagged (SfM only)": sum(alone[i] is True for i in idx),
                "flagged (true path)": sum(on_truth[i] is True for i in idx),
                "SfM off": sum(sfm_off(outcomes[i], params) for i in idx),
                "check rejects": sum(_check_rejects(outcomes[i], flagged[i]) for i in idx),
            }
        )
    return rows


def _check_rejects(o: Outcome, flagged: bool | None) -> bool:
    """The whole check's verdict: the trajectory rules reject, or the plan-following test does (`tasks.check`)."""
    return (not o.trajectory_ok) or flagged is True


def plan_following_part(n: int, width: int, height: int, frames: int) -> tuple[list[Outcome], dict[str, Any]]:
    """Render, pose and judge N cases twice each; print the sweep and the breakdown; return the headline part."""
    outcomes = []
    for case in cases(n):
        for ignored in (False, True):
            o = render_and_pose(case, ignored, width, height, frames)
            outcomes.append(o)
            pf = judged(o, PlanFollowingParams())
            word = {None: "not judged", True: "passed", False: "FLAGGED"}[pf.ok]
            word += f" ({'; '.join(pf.reasons)})" if pf.ok is False else ""
            word += f" [{pf.source}, SfM vs two-view {pf.sfm_disagreement_deg:.1f}°]"
            rules = "" if o.trajectory_ok else f"; trajectory rules reject: {'; '.join(o.trajectory_reasons)}"
            print(
                f"case {case.index} {case.move} [{case.defects}] {o.mode}: {word}{rules}", file=sys.stderr, flush=True
            )
    base = PlanFollowingParams()
    rows = sweep_rows(outcomes, base, SWEEP_FACTORS)
    table(breakdown_rows(outcomes, base), "plan following at the shipped defaults, per group")
    table(disagreement_rows(outcomes, base), "SfM's path overruled by two-view geometry beyond a rotation disagreement")
    ignored = [o.ignored for o in outcomes]
    verdicts = [judged(o, base) for o in outcomes]
    flagged = [None if v.ok is None else not v.ok for v in verdicts]
    at_default = rates(flagged, ignored)
    on_truth = rates(flagged_by(outcomes, base, truth=True), ignored)
    alone = rates(flagged_by(outcomes, base, sfm_only=True), ignored)
    check = [_check_rejects(o, f) for o, f in zip(outcomes, flagged, strict=True)]
    head = {
        "ignored_recall": round(at_default["recall"], 3),
        "ignored_fpr": round(at_default["fpr"], 3),
        "ignored_not_judged": at_default["ignored_not_judged"],
        "clean_not_judged": at_default["clean_not_judged"],
        "segments": n,
        "check_recall": round(float(np.mean([c for c, o in zip(check, outcomes, strict=True) if o.ignored])), 3),
        "check_fpr": round(float(np.mean([c for c, o in zip(check, outcomes, strict=True) if not o.ignored])), 3),
        "true_path_recall": round(on_truth["recall"], 3),
        "true_path_fpr": round(on_truth["fpr"], 3),
        "clean_sfm_off": sum(sfm_off(o, base) for o in outcomes if not o.ignored),
        "best_factor": best_factor(rows),
        "sfm_s_per_segment": round(float(np.mean([o.sfm_s for o in outcomes])), 2),
        "sfm_only_recall": round(alone["recall"], 3),
        "sfm_only_fpr": round(alone["fpr"], 3),
        "judged_on_two_view": sum(v.source == "two_view" for v in verdicts),
        "two_view_s_per_segment": round(float(np.mean([o.two_view_s for o in outcomes])), 2),
    }
    return outcomes, {"rows": rows, "head": head}


# ---------------------------------------------------------------- 2. named content

CONTENT_REQUESTS = (  # (scene prompt, the user's extend words)
    ("a small house decorated for Christmas", "a frozen lake on the left"),
    ("a small house decorated for Christmas", "a tall tower on the right"),
    ("a cosy living room with bookshelves", "a sofa on the left"),
    ("a quiet forest lake in autumn", "some pine trees on the right"),
    ("a desert village at noon", "a fountain on the left"),
    ("a desert village at noon", "a car on the right"),
    ("a snowy mountain cabin", "a snowman on the left"),
    ("a snowy mountain cabin", "some rocks on the right"),
    ("a quiet forest lake in autumn", "a stone statue on the left"),
    ("a cosy living room with bookshelves", "a tall plant on the right"),
)
CONTENT_MIN_SHARE = 0.005  # named content is visible when its labels cover more than this share of the pixels ...
CONTENT_LAST_FRAMES = 3  # ... of the segment's last frames


def content_request(scene_prompt: str, words: str, width: int, height: int, frames: int) -> dict[str, Any]:
    """One extend request: the rule planner's extension for `words` after the initial segment
    (`planning.rules.plan_extension`), its path as `planning.paths.conditioning_paths` makes it, rendered (after the
    initial segment, by the same model) with the segment prompt carrying the words. Returns a table row: the
    named kinds, their label share over the last frames, the mean column of their pixels (share of the width:
    < 0.5 left of centre) and whether all are visible."""
    from wonderverse.config import build_config
    from wonderverse.planning.paths import conditioning_paths
    from wonderverse.planning.rules import initial_segment, plan_extension
    from wonderverse.planning.segments import Plan
    from wonderverse.video import initial_pose, make_video_model
    from wonderverse.video.content import label_share, parse_content
    from wonderverse.video.prompts import segment_prompt

    video = {"width": width, "height": height, "frames_per_segment": frames, "options": {"fault_probability": 0.0}}
    cfg = build_config(scene_prompt, preset="preview", overrides={"scene": {"video": video}})
    fov = cfg.scene.video.fov_deg
    plan = Plan(segments=(initial_segment(cfg.steps.plan, fov),), planner="rules")
    ext = plan_extension(scene_prompt, words, plan, cfg.steps.plan, fov_deg=fov)
    plan = plan.extended(ext)
    model = make_video_model(cfg.scene.video_source)
    paths = conditioning_paths(plan, initial_pose(model), frames, cfg.steps.plan.strafe_m_per_deg)
    init = model.generate(segment_prompt(scene_prompt, "init", ""), paths["s000"].path, 1, None)
    e = paths[ext.id]
    ref = init.frames[e.ref_idx]
    v = model.generate(segment_prompt(scene_prompt, ext.role, ext.intent), e.path, 2, ref)
    kinds = sorted({item.kind for item in parse_content(words).items})
    last = slice(-CONTENT_LAST_FRAMES, None)
    labels, names = v.gt.labels, v.gt.label_names
    shares = [label_share(labels, names, k, last) for k in kinds]
    column = float("nan")
    if labels is not None:
        ids = [i for i, n in names.items() if n.split(" (")[0] in kinds]
        cols = np.nonzero(np.isin(labels[last], ids))[2]
        column = float(cols.mean() + 0.5) / width if cols.size else float("nan")
    return {
        "scene": scene_prompt,
        "words": words,
        "move": ext.move.to_paper(),
        "named": ", ".join(kinds) or "-",
        "share": min(shares) if shares else 0.0,
        "column": column,
        "visible": bool(shares) and min(shares) > CONTENT_MIN_SHARE,
    }


def content_part(n: int, width: int, height: int, frames: int) -> tuple[list[dict[str, Any]], float, str]:
    """The first n CONTENT_REQUESTS: rows, hit rate, and a note (why it is NaN, when it is)."""
    try:
        import wonderverse.video.content  # noqa: F401
    except ImportError:
        return [], float("nan"), "no wonderverse.video.content in this tree"
    rows = []
    for scene_prompt, words in CONTENT_REQUESTS[:n]:
        row = content_request(scene_prompt, words, width, height, frames)
        print(f"content {words!r} in {scene_prompt!r}: share {row['share']:.4f}", file=sys.stderr, flush=True)
        rows.append(row)
    return rows, float(np.mean([r["visible"] for r in rows])), ""


# ---------------------------------------------------------------- 3. guided extensions

SEAM_FRAMES = 3  # an extension's first frames after its reference frame (frame 0 repeats the parent's frame)
GUIDED_PROMPT = "a small house decorated for Christmas"


def guided_config(guided: bool, workers: int, quick: bool) -> Any:
    """Preview config of the 5-segment scene (initial + 2 rounds of left and right) with the `ai_like` defects,
    no faults, guided (`accept_guide`) or not, with `workers` segment and generation workers. Raises ValueError
    (pydantic's) or WonderError when this tree's procedural options do not know `accept_guide`."""
    from wonderverse.config import build_config

    options: dict[str, Any] = {"fault_probability": 0.0, "defects": "ai_like"}
    if guided:
        options["accept_guide"] = True
    video: dict[str, Any] = {"options": options}
    splats: dict[str, Any] = {}
    if quick:
        video |= {"width": 224, "height": 144, "frames_per_segment": 13}  # smaller: SfM cannot place the parents
        splats = {"max_side_px": 160, "train": {"iterations": 150}}
    overrides = {
        "scene": {"video": video, "extensions": {"rounds": 2, "directions": ["left", "right"]}},
        "steps": {"check": {"sfm": {"num_threads": 1}}, "splats": splats},
        "execution": {"segment_workers": workers, "generate_workers": workers},
    }
    return build_config(GUIDED_PROMPT, preset="preview", overrides=overrides)


def guide_records(scene_dir: Any) -> list[dict[str, Any]]:
    """Per extension segment: the guide record of its accepted attempt (gt `guide`: coverage, psnr_db,
    depth_absrel, depth_off_share); segments without one are left out."""
    from tasks.segments import attempt_path, segment_ids, segment_meta
    from wonderverse.store import SceneStore

    store = SceneStore.open(scene_dir)
    out = []
    for seg in segment_ids(store):
        if segment_meta(store, seg).role == "init":
            continue
        try:
            truth = store.meta(attempt_path(store, seg).gt, complete=False)
        except KeyError:  # dropped by the check
            continue
        rec = truth.guide if truth is not None else None
        if rec is not None:
            figures = rec.model_dump()
            out.append({"segment": seg} | {k: (float("nan") if v is None else v) for k, v in figures.items()})
    return out


def seam_psnr(scene_dir: Any) -> dict[str, float]:
    """Per extension segment: PSNR (dB) of its first SEAM_FRAMES frames after the reference frame against the
    final splats rendered at those frames' global SfM poses (video size, the splats' learnt background)."""
    from tasks.output_scene import posed_frames
    from tasks.segments import segment_meta
    from tasks.splats import stored_sky
    from wonderverse.metrics import psnr
    from wonderverse.schema import SFM, SPLATS
    from wonderverse.splats.model import GaussianModel, normalization_from_dict
    from wonderverse.splats.renderer import make_renderer
    from wonderverse.splats.views import render_views
    from wonderverse.store import SceneStore

    store = SceneStore.open(scene_dir)
    frames, w2c, names = posed_frames(store)
    norm = normalization_from_dict(store.meta(SPLATS.path).normalization)
    arrays = {name: store.array(getattr(SPLATS, name)) for name in GaussianModel.PARAM_NAMES}
    background = stored_sky(store)
    K = store.array(SFM.K)
    h, w = frames.shape[1:3]
    by_seg: dict[str, list[tuple[int, int]]] = {}
    for row, name in enumerate(names):
        seg, idx = name.rsplit("_", 1)
        if int(idx) >= 1 and segment_meta(store, seg).role != "init":
            by_seg.setdefault(seg, []).append((int(idx), row))
    out = {}
    renderer = make_renderer("torch")
    for seg, items in sorted(by_seg.items()):
        rows = [r for _, r in sorted(items)[:SEAM_FRAMES]]
        views = render_views(arrays, norm, w2c[rows], K, w, h, renderer, background=background)
        values = [psnr(v.rgb, frames[r].astype(np.float64) / 255.0) for v, r in zip(views, rows, strict=True)]
        out[seg] = float(np.mean(values))
    return out


def guided_part(quick: bool) -> tuple[list[dict[str, Any]], dict[str, float], str]:
    """Guided vs unguided 5-segment scenes (see the module doc): rows, headline figures, a note when NaN."""
    import tempfile
    from pathlib import Path

    from flows.pipeline import execute
    from wonderverse.errors import WonderError

    nan = float("nan")
    keys = ("guide_coverage", "guide_psnr_db", "guide_depth_absrel", "guided_extensions", "seam_psnr_guided")
    keys += ("seam_psnr_unguided", "branch_speedup", "branch_serial_s", "branch_parallel_s")
    empty = dict.fromkeys(keys, nan)
    try:
        scenes = {"guided": guided_config(True, 2, quick), "unguided": guided_config(False, 2, quick)}
        timed = {1: guided_config(True, 1, quick), 2: scenes["guided"]}
    except (ValueError, WonderError) as e:
        return [], empty, f"no guided procedural option in this tree: {str(e).splitlines()[0]}"
    seconds: dict[int, float] = {}
    seams: dict[str, dict[str, float]] = {}
    records: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="wv_plan_following_") as tmp:
        try:
            for name, cfg in scenes.items():  # the first also warms the process up for the timed runs
                t = time.perf_counter()
                execute(Path(tmp) / name, cfg, until="splats")
                print(f"scene {name}: to splats in {time.perf_counter() - t:.0f} s", file=sys.stderr, flush=True)
                seams[name] = seam_psnr(Path(tmp) / name)
            records = guide_records(Path(tmp) / "guided")
            for workers, cfg in timed.items():
                t = time.perf_counter()
                execute(Path(tmp) / f"timed_{workers}", cfg, until="check")
                seconds[workers] = time.perf_counter() - t
                print(f"guided scene, {workers} worker(s): to check in {seconds[workers]:.0f} s", file=sys.stderr)
        except WonderError as e:
            return [], empty, f"a 5-segment scene failed: {e}"
    rows = [
        {
            "segment": rec["segment"],
            "coverage": rec.get("coverage", nan),
            "guide psnr_db": rec.get("psnr_db", nan),
            "depth absrel": rec.get("depth_absrel", nan),
            "depth off share": rec.get("depth_off_share", nan),
            "seam psnr guided": seams["guided"].get(rec["segment"], nan),
            "seam psnr unguided": seams["unguided"].get(rec["segment"], nan),
        }
        for rec in records
    ]

    def mean(values: list[float]) -> float:
        v = [x for x in values if math.isfinite(x)]
        return round(float(np.mean(v)), 4) if v else nan

    head = {
        "guide_coverage": mean([r["coverage"] for r in rows]),
        "guide_psnr_db": mean([r["guide psnr_db"] for r in rows]),
        "guide_depth_absrel": mean([r["depth absrel"] for r in rows]),
        "guided_extensions": len(rows),
        "seam_psnr_guided": mean([r["seam psnr guided"] for r in rows]),
        "seam_psnr_unguided": mean([r["seam psnr unguided"] for r in rows]),
        "branch_speedup": round(seconds[1] / seconds[2], 3),
        "branch_serial_s": round(seconds[1], 1),
        "branch_parallel_s": round(seconds[2], 1),
    }
    note = "" if records else "the guided scene recorded no guide (gt `guide`) on any extension"
    return rows, head, note


PARTS = ("plan", "content", "guided")


def parse(argv: list[str] | None = None) -> argparse.Namespace:
    """--quick (smaller workload), --only PART (repeatable; default all of PARTS)."""
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--quick", action="store_true", help="smaller workload (CI-sized)")
    p.add_argument("--only", action="append", choices=PARTS, help="run only this part (repeatable)")
    return p.parse_args(argv)


def main() -> None:
    args = parse()
    parts = set(args.only or PARTS)
    t0 = time.perf_counter()
    if args.quick:
        n, width, height, frames = 8, 224, 144, 13
        n_content, content_size = 4, (160, 104, 9)
    else:
        n, width, height, frames = 48, 320, 208, 17  # the preview preset's frames
        n_content, content_size = len(CONTENT_REQUESTS), (320, 208, 17)
    notes = []
    headline: dict[str, Any] = {}
    rows: list[dict[str, Any]] = []
    if "content" in parts:
        content_rows, hit_rate, note = content_part(n_content, *content_size)
        if content_rows:
            table(content_rows, "named content: extend requests, label share over the last frames")
        if note:
            notes.append(f"content_hit_rate NaN: {note}")
        headline["content_hit_rate"] = round(hit_rate, 3)
    if "guided" in parts:
        guided_rows, guided_head, note = guided_part(args.quick)
        if guided_rows:
            table(guided_rows, "guided extensions: guide vs truth, seam PSNR vs the final splats (dB)")
        if note:
            notes.append(f"guided figures NaN: {note}")
        headline |= guided_head
    if "plan" in parts:
        _, part1 = plan_following_part(n, width, height, frames)
        rows = part1["rows"]
        headline = part1["head"] | headline
    for line in notes:
        print(f"note: {line}", flush=True)
    headline["seconds"] = round(time.perf_counter() - t0, 1)
    if rows:
        report("plan following: tolerance sweep (recall of 'ignore', FPR on clean; judged only)", rows, headline)
    else:
        print(json.dumps(headline), flush=True)


if __name__ == "__main__":
    main()

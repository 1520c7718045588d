"""benchmarks.plan_following: recall / FPR and the tolerance sweep on constructed paths (no rendering, no SfM)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from benchmarks.plan_following import (
    Case,
    Outcome,
    best_factor,
    breakdown_rows,
    cases,
    disagreement_rows,
    parse,
    planned_path,
    rates,
    scaled,
    sweep_rows,
)
from wonderverse.camera import camera_centers, look_at, move_path, so3_exp
from wonderverse.plan_following import PlanFollowingParams
from wonderverse.two_view import TwoViewPath

START = look_at(np.array([0.0, 0.0, 3.0]), np.array([0.0, 10.0, 2.0]))  # level-ish, looking along +y
T = 13


def _similar(w2c: np.ndarray, seed: int) -> np.ndarray:
    """The same camera path in another world frame and scale (what SfM returns): C' = s R C + t."""
    rng = np.random.default_rng(seed)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    R = q * np.sign(np.linalg.det(q))
    s, t = float(rng.uniform(0.2, 5.0)), rng.normal(size=3)
    out = np.zeros_like(w2c)
    out[:, :3, :3] = w2c[:, :3, :3] @ R.T
    c = s * camera_centers(w2c) @ R.T + t
    out[:, :3, 3] = -np.einsum("tij,tj->ti", out[:, :3, :3], c)
    out[:, 3, 3] = 1.0
    return out


def _outcome(
    planned: np.ndarray,
    rendered: np.ndarray,
    ignored: bool,
    seed: int,
    registered: bool = True,
    sfm_path: np.ndarray | None = None,
    two_view: bool = False,
) -> Outcome:
    """An outcome whose SfM path is `sfm_path` (default: the rendered path) in another frame and scale, and,
    with `two_view`, a two-view look that saw the rendered path exactly at every other frame."""
    case = Case(seed, "test", 0, "left", 40.0, 1.0, "none")
    seen = rendered if sfm_path is None else sfm_path
    poses = _similar(seen, seed) if registered else np.full_like(rendered, np.nan)
    reg = np.full(len(planned), registered)
    mode = "reverse_turn" if ignored else "clean"
    tv = _two_view(rendered) if two_view else None
    return Outcome(case, ignored, mode, poses, reg, planned, rendered, True, [], 0.0, tv, True, 0.0)


def _two_view(w2c: np.ndarray) -> TwoViewPath:
    """The two-view look at a path known exactly: every other frame, relative to frame 0, travel measured."""
    n = len(w2c)
    rel = w2c @ np.linalg.inv(w2c[0])
    poses = np.full((n, 4, 4), np.nan)
    poses[::2] = rel[::2]
    reg = np.zeros(n, dtype=bool)
    reg[::2] = True
    return TwoViewPath(poses, reg, reg.copy(), [], 0.0)


def _twin(w2c: np.ndarray, pitch_deg: float) -> np.ndarray:
    """A wrong SfM path like the planar twin: pitch up growing to `pitch_deg`, travel turned downwards."""
    out = w2c.copy()
    c = camera_centers(w2c)
    for j in range(len(w2c)):
        u = j / (len(w2c) - 1)
        out[j, :3, :3] = so3_exp(np.array([np.radians(pitch_deg) * u, 0.0, 0.0])) @ w2c[j, :3, :3]
        d = c[j] - c[0]
        out[j, :3, 3] = -out[j, :3, :3] @ (c[0] + 0.4 * d - [0.0, 0.0, 0.9 * float(np.linalg.norm(d))])
    return out


def test_rates_count_judged_only() -> None:
    flagged = [True, False, None, True, False, False, None]
    ignored = [True, True, True, False, False, False, False]
    r = rates(flagged, ignored)
    assert r["recall"] == pytest.approx(0.5)
    assert r["fpr"] == pytest.approx(1 / 3)
    assert (r["ignored_judged"], r["clean_judged"], r["ignored_not_judged"], r["clean_not_judged"]) == (2, 3, 1, 1)
    assert math.isnan(rates([None], [True])["recall"])
    with pytest.raises(ValueError):
        rates([True], [True, False])


def test_sweep_on_constructed_paths() -> None:
    planned = move_path(START, math.radians(40), 0.0, 1.0, 0.0, T)  # left 40 + forward 1
    half = move_path(START, math.radians(20), 0.0, 1.0, 0.0, T)  # a half-done turn: followed loosely
    wrong = move_path(START, math.radians(-40), 0.0, 1.0, 0.0, T)  # turned right instead
    outcomes = [
        _outcome(planned, planned, False, 1),
        _outcome(planned, half, False, 2),
        _outcome(planned, wrong, True, 3),
        _outcome(planned, wrong, True, 4, registered=False),  # SfM failed: not judged
    ]
    all_rows = sweep_rows(outcomes, PlanFollowingParams(), (0.5, 1.0))
    rows = {(r["scaled"], r["factor"]): r for r in all_rows}
    assert set(rows) == {("all", 0.5), ("all", 1.0), ("rotation", 0.5), ("direction", 0.5)}  # factor 1 once
    # left 40 planned, 20 done: error 20 deg; tolerance 8 + 0.6 * 40 = 32 at the defaults, 16 at half of them
    assert rows[("all", 1.0)]["recall"] == 1.0 and rows[("all", 1.0)]["fpr"] == 0.0
    assert rows[("all", 0.5)]["recall"] == 1.0 and rows[("all", 0.5)]["fpr"] == 0.5
    assert rows[("rotation", 0.5)]["fpr"] == 0.5  # the rotation tolerance alone flags the half-done turn ...
    assert rows[("direction", 0.5)]["fpr"] == 0.0  # ... the direction tolerance alone does not (same travel)
    assert rows[("direction", 0.5)]["dir_tol_deg"] == pytest.approx(40.0)
    assert rows[("direction", 0.5)]["rot_tol_deg"] == pytest.approx(8.0)
    assert all(r["ignored judged"] == 1 and r["clean judged"] == 2 for r in all_rows)
    # on the true paths the unregistered "ignore" rendering is judged too (and flagged)
    assert all(r["recall (true path)"] == 1.0 for r in all_rows)
    assert best_factor(all_rows) == 1.0


def test_best_factor_and_scaling() -> None:
    rows = [
        {"factor": 0.5, "recall": 1.0, "fpr": 0.2},
        {"factor": 1.0, "recall": 0.9, "fpr": 0.05},
        {"factor": 1.5, "recall": 0.9, "fpr": 0.0},
        {"factor": 2.0, "recall": 0.5, "fpr": 0.0},
    ]
    assert best_factor(rows) == 1.5  # the loosest of the best recalls within the FPR target
    assert math.isnan(best_factor(rows[:1]))
    p = scaled(PlanFollowingParams(), 3.0)
    assert p.translation_direction_tol_deg == 180.0  # capped: the model's bound
    assert p.rotation_tol_deg == pytest.approx(3 * PlanFollowingParams().rotation_tol_deg)
    assert p.min_rotation_deg == PlanFollowingParams().min_rotation_deg  # not scaled


def test_cases_cover_every_kind_and_paths_turn_as_named() -> None:
    cs = cases(8)
    assert {c.direction for c in cs} == {"left", "right", "up", "down"}
    assert {(c.forward_m > 0, c.defects) for c in cs} == {(a, d) for a in (False, True) for d in ("none", "ai_like")}
    for c in cs:
        path = planned_path(c, START, T, strafe_m_per_deg=0.04)
        fwd0, fwd1 = path[0, 2, :3], path[-1, 2, :3]  # optical axes in world coordinates
        yaw = math.degrees(math.atan2(np.cross(fwd0[:2], fwd1[:2]), fwd0[:2] @ fwd1[:2]))
        pitch = math.degrees(math.asin(fwd1[2]) - math.asin(fwd0[2]))
        sign = 1 if c.direction in ("left", "up") else -1
        turned = yaw if c.direction in ("left", "right") else pitch
        assert turned == pytest.approx(sign * c.turn_deg, abs=1e-6)
        assert 20 <= c.turn_deg <= 45


def test_two_view_look_in_the_sweep_and_the_breakdown() -> None:
    """A clean rendering whose SfM path is twin-like (flagged by SfM alone) and a reversed turn: with the two-view
    look the clean one passes (judged on two-view geometry), the reversed one is still caught."""
    planned = move_path(START, math.radians(-24), 0.0, 1.8, -24 * 0.04, T)
    wrong = move_path(START, math.radians(24), 0.0, 1.8, -24 * 0.04, T)
    outcomes = [
        _outcome(planned, planned, False, 1, sfm_path=_twin(planned, 30.0), two_view=True),
        _outcome(planned, wrong, True, 2, two_view=True),
    ]
    rows = {(r["scaled"], r["factor"]): r for r in sweep_rows(outcomes, PlanFollowingParams(), (1.0,))}
    row = rows[("all", 1.0)]
    assert (row["recall"], row["fpr"]) == (1.0, 0.0)
    assert (row["recall (SfM only)"], row["fpr (SfM only)"]) == (1.0, 1.0)
    tols = disagreement_rows(outcomes, PlanFollowingParams(), (4.0, 45.0))
    assert [(r["fpr"], r["judged on two-view"]) for r in tols] == [(0.0, 1), (1.0, 0)]  # 30° > 4°, < 45°
    groups = breakdown_rows(outcomes, PlanFollowingParams())
    clean = next(g for g in groups if g["rendering"] == "clean")
    assert (clean["flagged"], clean["on two-view"], clean["flagged (SfM only)"]) == (0, 1, 1)
    # without the two-view look (params or outcome), the verdict is SfM's alone
    assert sweep_rows(outcomes, PlanFollowingParams(two_view=None), (1.0,))[0]["fpr"] == 1.0


def test_only_option() -> None:
    assert parse([]).only is None
    assert parse(["--only", "plan"]).only == ["plan"]
    assert parse(["--only", "plan", "--only", "content", "--quick"]).only == ["plan", "content"]
    with pytest.raises(SystemExit):
        parse(["--only", "everything"])

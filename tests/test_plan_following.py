"""The plan-following check: a segment's estimated path (the planned one seen through an arbitrary
similarity, as SfM gives it, plus noise) against its plan. Ground truth: paths built with `move_path`
from the move each test states, so what the camera did is known by construction."""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError
from scipy.spatial.transform import Rotation

from wonderverse.camera import Sim3, camera_centers, look_at, move_path, se3, so3_exp
from wonderverse.plan_following import (
    PlanFollowingParams,
    choose_path,
    compare_to_plan,
    judge_segment,
    rotation_disagreement,
)
from wonderverse.two_view import TwoViewPath

T = 25
START = look_at(np.array([1.0, 2.0, 1.5]), np.array([5.0, 3.0, 1.0]))  # looking slightly down
STRAFE_M_PER_DEG = 0.04  # as the planner adds to a turn (wonderverse/planning/paths.py)
FAST = settings(max_examples=150, deadline=None)


def path(yaw_deg: float, pitch_deg: float = 0.0, forward: float = 0.0, strafe: float = 0.0, **kw) -> np.ndarray:
    start = kw.pop("start", START)
    return move_path(start, math.radians(yaw_deg), math.radians(pitch_deg), forward, strafe, kw.pop("n", T), **kw)


def turn(yaw_deg: float, pitch_deg: float = 0.0, forward: float = 0.0) -> np.ndarray:
    """A planned move as the planner makes it: a turn also strafes toward its side."""
    return path(yaw_deg, pitch_deg, forward, STRAFE_M_PER_DEG * yaw_deg)


def noisy(w2c: np.ndarray, rot_deg: float, trans: float, seed: int = 0) -> np.ndarray:
    """Poses with each rotation perturbed by ~rot_deg and each centre by ~trans (world units)."""
    rng = np.random.default_rng(seed)
    R = so3_exp(rng.normal(0.0, math.radians(rot_deg), (len(w2c), 3))) @ w2c[:, :3, :3]
    c = camera_centers(w2c) + rng.normal(0.0, trans, (len(w2c), 3))
    out = np.stack([se3(r, -r @ ci) for r, ci in zip(R, c, strict=True)])
    out[0] = w2c[0]
    return out


def similarity(seed: int, scale: float, offset: float = 1e5) -> Sim3:
    rng = np.random.default_rng(seed)
    return Sim3(scale, Rotation.random(random_state=seed).as_matrix(), rng.uniform(-offset, offset, 3))


def as_sfm(w2c: np.ndarray, sim: Sim3) -> np.ndarray:
    return sim.transform_w2c(w2c)


# --------------------------------------------------------------------------------------------- followed

MOVES = [(30, 0, 2), (-30, 0, 0), (0, 0, 2), (0, 0, -1.5), (30, 10, 2), (-45, -15, 1), (0, 20, 0), (90, 0, 3)]


@pytest.mark.parametrize("scale", [1e-3, 1.0, 1e3])
@pytest.mark.parametrize("move", MOVES)
def test_the_plan_seen_through_any_similarity_with_noise_is_followed(move: tuple, scale: float) -> None:
    plan = turn(*move)
    est = as_sfm(noisy(plan, rot_deg=0.3, trans=0.01, seed=MOVES.index(move)), similarity(7, scale))
    for s in (None, 1 / scale):
        r = compare_to_plan(est, plan, scale=s)
        assert r.ok is True, r.reasons
        assert r.reasons == []
        assert r.estimated is not None and r.planned is not None
        assert r.planned.yaw_left_deg == pytest.approx(move[0], abs=1e-6)
        assert r.planned.pitch_up_deg == pytest.approx(move[1], abs=1e-6)
        assert r.estimated.yaw_left_deg == pytest.approx(move[0], abs=1.5)
        assert r.rotation_error_deg < 2.0
        if r.planned.travel > 0.05:
            assert r.translation_direction_error_deg < 5.0
        if s is not None and r.planned.travel > 0.05:
            assert r.size_ratio == pytest.approx(1.0, abs=0.05)
        if s is None:
            assert math.isnan(r.size_ratio)


def test_eased_timing_and_an_arc_instead_of_a_straight_line_still_follow() -> None:
    """Video models ease in and out and travel along their current heading while turning; neither is an
    ignored instruction."""
    plan = turn(30, 0, 2)
    eased = path(30, 0, 2, STRAFE_M_PER_DEG * 30, ease=True)
    assert compare_to_plan(as_sfm(eased, similarity(1, 0.01)), plan).ok is True
    # An arc: each step goes forward along the camera's current heading while it turns.
    steps = [START]
    for _ in range(T - 1):
        steps.append(move_path(steps[-1], math.radians(30 / (T - 1)), 0.0, 2 / (T - 1), 0.05, 2)[-1])
    arc = np.stack(steps)
    r = compare_to_plan(as_sfm(arc, similarity(2, 300.0)), plan)
    assert r.ok is True, r.reasons
    assert 5.0 < r.translation_direction_error_deg < 30.0  # the chord bends by about half the turn


# ------------------------------------------------------------------------------------------ not followed

WRONG = [
    # (plan, what the segment did, words the reason must contain)
    ((30, 0, 0), (-28, 0, 0), "turned right 28° where the plan said left 30°"),
    ((30, 0, 0), (0, 0, 0), "did not turn (0°) where the plan said left 30°"),
    ((30, 0, 0), (0, 30, 0), "turned up 30° where the plan said left 30°"),
    ((-25, 0, 1), (0, 0, 1), "did not turn (0°) where the plan said right 25°"),
    ((0, 0, 2), (0, 0, -2), "moved backward where the plan said forward 2"),
    ((0, 15, 0), (0, -15, 0), "turned down 15° where the plan said up 15°"),
]


@pytest.mark.parametrize("scale", [1e-3, 1e3])
@pytest.mark.parametrize(("planned", "done", "words"), WRONG)
def test_an_ignored_instruction_is_caught_and_said_in_words(
    planned: tuple, done: tuple, words: str, scale: float
) -> None:
    plan, est = turn(*planned), turn(*done)
    r = compare_to_plan(as_sfm(noisy(est, 0.2, 0.005, seed=3), similarity(11, scale)), plan)
    assert r.ok is False
    assert any(words in reason for reason in r.reasons), r.reasons


# Tighter than the defaults (which allow for SfM of short, small clips), to reach the wording of small errors.
TIGHT = PlanFollowingParams(rotation_tol_deg=5.0, rotation_tol_share=0.4, translation_direction_tol_deg=50.0)


def test_a_wrong_small_angle_beside_a_right_large_one_is_named() -> None:
    r = compare_to_plan(path(30, -10), path(30, 10), TIGHT)
    assert r.reasons == ["turned left 30°, down 10° where the plan said left 30°, up 10°"]
    r = compare_to_plan(path(30, 0), path(30, 20), TIGHT)
    assert r.reasons == ["turned left 30° where the plan said left 30°, up 20°"]


def test_forward_instead_of_turning() -> None:
    """The planned turn strafes toward its side (the planner's move); a segment that went straight ahead
    did not turn and travelled the wrong way; with a known scale its travel is measured too."""
    plan = turn(30)
    est = as_sfm(path(0, 0, 2), similarity(5, 0.02))
    r = compare_to_plan(est, plan)
    assert r.ok is False
    assert "did not turn (0°) where the plan said left 30°" in r.reasons
    assert "moved forward where the plan said left 1.2" in r.reasons
    pure_turn = path(30)
    r = compare_to_plan(est, pure_turn, scale=50.0)
    assert "moved forward 2 where the plan said no travel" in r.reasons
    r = compare_to_plan(est, pure_turn)  # without a scale a travel's size is unknown: only the turn is judged
    assert r.reasons == ["did not turn (0°) where the plan said left 30°"]


def test_a_path_that_ends_right_but_went_the_wrong_way_first_is_caught() -> None:
    first = path(-40, n=13)
    wander = np.concatenate([first, path(70, start=first[-1], n=13)[1:]])  # right 40, then left 70: net left 30
    r = compare_to_plan(as_sfm(wander, similarity(3, 1e-3)), path(30))
    assert r.ok is False
    assert r.estimated is not None and r.estimated.yaw_left_deg == pytest.approx(30.0, abs=1e-6)
    assert r.reasons == ["turned right 40° on the way where the plan said left 30°"]
    back = path(0, 0, -1.0, n=13)
    there = np.concatenate([back, path(0, 0, 3.0, start=back[-1], n=13)[1:]])  # back 1, then forward 3: net +2
    r = compare_to_plan(as_sfm(there, similarity(4, 1e3)), path(0, 0, 2))
    assert r.ok is False
    assert r.translation_direction_error_deg == pytest.approx(0.0, abs=1e-6)
    assert r.reasons == ["moved backward on the way where the plan said forward 2"]


def test_a_half_turn_the_other_way_round_is_not_the_same_turn() -> None:
    """Left 180 and right 180 end in the same orientation; the path tells them apart."""
    r = compare_to_plan(path(-180), path(180))
    assert r.ok is False
    assert r.reasons == ["turned right 180° where the plan said left 180°"]
    assert compare_to_plan(noisy(path(180), 0.3, 0.0), path(180)).ok is True


def test_roll_is_named() -> None:
    plan = path(30, 0, 1)
    # Roll each camera about its own optical axis, growing to 25°: +z-rotation in camera space drops its
    # right side (y is down), a roll to the right.
    rolled = plan.copy()
    for k, a in enumerate(np.linspace(0.0, math.radians(25), T)):
        rolled[k] = se3(so3_exp(np.array([0.0, 0.0, -a])), np.zeros(3)) @ plan[k]
    r = compare_to_plan(rolled, plan, TIGHT)
    assert r.estimated is not None and r.estimated.roll_left_deg == pytest.approx(-25.0, abs=0.5)
    assert r.ok is False
    assert any(reason.startswith("turned left 30° and rolled right 25°") for reason in r.reasons), r.reasons


# ------------------------------------------------------------------------------------------- tolerances


def test_rotation_tolerance_is_absolute_plus_a_share_of_the_plan() -> None:
    params = PlanFollowingParams()
    tol = params.rotation_tol_deg + params.rotation_tol_share * 30  # 17° for left 30
    plan = path(30)
    assert compare_to_plan(path(30 - tol + 1), plan).ok is True
    assert compare_to_plan(path(30 + tol - 1), plan).ok is True
    r = compare_to_plan(path(30 - tol - 1), plan)
    assert r.ok is False and r.rotation_tol_deg == pytest.approx(tol)
    strict = PlanFollowingParams(rotation_tol_deg=2.0, rotation_tol_share=0.0)
    assert compare_to_plan(path(27), plan, strict).ok is False
    assert compare_to_plan(path(29), plan, strict).ok is True


def test_no_turn_planned_allows_a_wobble_below_the_still_limit() -> None:
    plan = path(0, 0, 2)
    assert compare_to_plan(path(8, 0, 2), plan).ok is True
    r = compare_to_plan(path(12, 0, 2), plan)
    assert r.reasons == ["turned left 12° where the plan said no turn"]
    # A planned 0.5° turn counts as none: a turn of 5° the other way is within the wobble.
    assert compare_to_plan(path(-5, 0, 2), path(0.5, 0, 2)).ok is True
    out_and_back = np.concatenate([path(20, 0, 1, n=13), path(-20, 0, 1, start=path(20, 0, 1, n=13)[-1], n=13)[1:]])
    r = compare_to_plan(out_and_back, path(0, 0, 2))
    assert r.reasons == ["turned left 20° on the way where the plan said no turn"]


def test_translation_direction_and_size_tolerances() -> None:
    params = TIGHT
    plan = path(0, 0, 2)
    ok_side = path(0, 0, 2 * math.cos(math.radians(40)), 2 * math.sin(math.radians(40)))  # 40° off
    off_side = path(0, 0, 2 * math.cos(math.radians(60)), 2 * math.sin(math.radians(60)))  # 60° off
    r = compare_to_plan(ok_side, plan, params)
    assert r.ok is True and r.translation_direction_error_deg == pytest.approx(40.0, abs=1e-6)
    r = compare_to_plan(off_side, plan, params)
    assert r.ok is False and r.reasons == ["moved forward and left where the plan said forward 2"]
    r = compare_to_plan(path(0, 0, 0.1, 2.0), plan, params)  # 87° off: only the main direction is named
    assert r.reasons == ["moved left where the plan said forward 2"]
    assert params.size_ratio_min == 0.5 and params.size_ratio_max == 2.0
    sfm = similarity(9, 0.1)
    assert compare_to_plan(as_sfm(path(0, 0, 1.2), sfm), plan, params, scale=10.0).ok is True
    r = compare_to_plan(as_sfm(path(0, 0, 0.6), sfm), plan, params, scale=10.0)
    assert r.size_ratio == pytest.approx(0.3)
    assert r.reasons == ["moved forward 0.6 where the plan said forward 2"]
    r = compare_to_plan(as_sfm(path(0, 0, 5.0), sfm), plan, params, scale=10.0)
    assert r.reasons == ["moved forward 5 where the plan said forward 2"]
    assert compare_to_plan(as_sfm(path(0, 0, 5.0), sfm), plan, params).ok is True  # no scale: direction only


def test_a_pure_rotation_plan_does_not_judge_the_direction_of_travel() -> None:
    plan = path(-30)
    est = as_sfm(noisy(plan, 0.2, 0.02, seed=8), similarity(6, 1e-3))  # centres move only by noise
    r = compare_to_plan(est, plan)
    assert r.ok is True
    assert math.isnan(r.translation_direction_error_deg)
    assert "no travel planned: the direction of travel is not judged" in r.notes


def test_a_planned_move_with_no_estimated_travel_did_not_move() -> None:
    r = compare_to_plan(as_sfm(path(0), similarity(2, 1e3)), path(0, 0, 2))
    assert r.reasons == ["did not move where the plan said forward 2"]


# ------------------------------------------------------------------------------------------- degenerate


def test_unregistered_frames_are_left_out() -> None:
    plan = turn(30, 0, 2)
    est = as_sfm(plan, similarity(12, 1e-3))
    est[[0, 1, 7, 8, 24]] = np.nan
    r = compare_to_plan(est, plan)
    assert r.ok is True, r.reasons
    assert r.frames == [2, 3, 4, 5, 6, *range(9, 24)]
    assert r.notes[0] == "judged on the 20 registered frames of 25 (frames 2-23)"
    # The plan is read over the same frames: from frame 2 to 23 it turns 21 of the 30 degrees.
    assert r.planned is not None and r.planned.yaw_left_deg == pytest.approx(30 * 21 / 24)
    wrong = as_sfm(turn(-30, 0, 2), similarity(12, 1e-3))
    wrong[[0, 1, 7, 8, 24]] = np.nan
    assert compare_to_plan(wrong, plan).ok is False
    mask = np.ones(T, bool)
    mask[:3] = False
    assert compare_to_plan(as_sfm(plan, similarity(12, 1.0)), plan, registered=mask).frames[0] == 3


def test_too_few_registered_frames_or_no_plan_is_not_judged() -> None:
    plan = turn(30)
    est = np.full_like(plan, np.nan)
    est[5] = plan[5]
    r = compare_to_plan(est, plan)
    assert r.ok is None
    assert r.reasons == ["not judged: only 1 frame(s) registered; at least 2 are needed"]
    r = compare_to_plan(plan, np.full_like(plan, np.nan))  # a user's clip has no planned path
    assert r.ok is None and r.reasons == ["not judged: the segment has no planned camera path"]
    assert json.dumps(r.to_attrs(), allow_nan=False)


def test_bad_input_raises() -> None:
    plan = turn(30)
    with pytest.raises(ValueError, match="both be"):
        compare_to_plan(plan[:-1], plan)
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="scale"):
            compare_to_plan(plan, plan, scale=bad)
    with pytest.raises(ValidationError):
        PlanFollowingParams(rotation_tol_degrees=3)  # type: ignore[call-arg]
    with pytest.raises(ValidationError):
        PlanFollowingParams().rotation_tol_deg = 1.0  # type: ignore[misc]
    with pytest.raises(ValidationError, match="size_ratio_min"):
        PlanFollowingParams(size_ratio_min=3.0)


def test_to_attrs_is_json() -> None:
    r = compare_to_plan(as_sfm(turn(-28), similarity(1, 1.0)), turn(30), scale=1.0)
    attrs = json.loads(json.dumps(r.to_attrs(), allow_nan=False))
    assert attrs["ok"] is False
    assert attrs["reasons"] == r.reasons
    assert attrs["planned"]["yaw_left_deg"] == pytest.approx(30.0)
    assert attrs["estimated"]["yaw_left_deg"] == pytest.approx(-28.0)
    assert attrs["size_ratio"] == pytest.approx(28 / 30)


# ------------------------------------------------------------------------------------------- properties

quats = st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(lambda q: np.linalg.norm(q) > 0.1)
sims = st.builds(
    lambda q, log_s, t: Sim3(10.0**log_s, Rotation.from_quat(q).as_matrix(), np.array(t)),
    quats,
    st.floats(-3, 3),
    st.lists(st.floats(-1e5, 1e5), min_size=3, max_size=3),
)
moves = st.tuples(st.floats(-150, 150), st.floats(-40, 40), st.floats(-3, 3))


@FAST
@given(sims, moves, st.integers(0, 2**16))
def test_property_the_plan_through_any_similarity_is_followed(sim: Sim3, move: tuple, seed: int) -> None:
    plan = turn(*move)
    travel = np.linalg.norm(camera_centers(plan[-1:]) - camera_centers(plan[:1]))
    est = as_sfm(noisy(plan, 0.2, 0.005 * max(float(travel), 0.01), seed), sim)
    for s in (None, 1.0 / sim.s):
        r = compare_to_plan(est, plan, scale=s)
        assert r.ok is True, (move, r.reasons)
        assert r.rotation_error_deg < 2.0


@FAST
@given(sims, st.floats(15, 150), st.floats(-3, 3), st.booleans())
def test_property_a_reversed_turn_is_caught_in_any_frame(sim: Sim3, yaw: float, fwd: float, left: bool) -> None:
    yaw = yaw if left else -yaw
    plan, wrong = turn(yaw, 0, fwd), turn(-yaw, 0, fwd)
    seen = compare_to_plan(as_sfm(wrong, sim), plan)
    direct = compare_to_plan(wrong, plan)
    assert seen.ok is False and direct.ok is False
    said = "right" if left else "left"
    assert seen.reasons[0].startswith(f"turned {said} ")
    digits = re.compile(r"\d+(\.\d+)?")
    assert [digits.sub("#", x) for x in seen.reasons] == [digits.sub("#", x) for x in direct.reasons]
    assert seen.rotation_error_deg == pytest.approx(2 * abs(yaw), abs=1e-6)


@FAST
@given(sims, st.floats(0.5, 3), st.floats(-20, 20))
def test_property_backward_instead_of_forward_is_caught_in_any_frame(sim: Sim3, fwd: float, yaw: float) -> None:
    plan, wrong = path(yaw, 0, fwd), path(yaw, 0, -fwd)
    r = compare_to_plan(as_sfm(wrong, sim), plan)
    assert r.ok is False
    assert r.translation_direction_error_deg == pytest.approx(180.0, abs=1e-4)
    assert r.reasons[-1].startswith("moved backward where the plan said forward")


# ------------------------------------------------------------------ SfM's path checked against two-view geometry


def as_two_view(w2c: np.ndarray, frames: list[int], travel_frames: list[int]) -> TwoViewPath:
    """What `two_view_path` returns for a camera path known exactly: frame 0 the identity, the other looked-at
    frames relative to it (translations scaled so that the longest is 1, zero where travel is not measured)."""
    T = len(w2c)
    rel = w2c @ np.linalg.inv(w2c[0])
    longest = max(float(np.linalg.norm(rel[j, :3, 3])) for j in travel_frames) if travel_frames else 1.0
    poses = np.full((T, 4, 4), np.nan)
    for j in frames:
        poses[j] = rel[j]
        poses[j, :3, 3] = rel[j, :3, 3] / longest if j in travel_frames else 0.0
    poses[0] = np.eye(4)
    registered = np.all(np.isfinite(poses.reshape(T, -1)), axis=1)
    known = np.zeros(T, dtype=bool)
    known[[0, *travel_frames]] = True
    return TwoViewPath(poses, registered, known & registered, [], 0.0)


def planar_twin_like(w2c: np.ndarray, pitch_deg: float) -> np.ndarray:
    """The wrong path SfM settled in on the benchmark's turn-and-travel clips (the planar twin): the turn as it
    was, plus a pitch up growing to `pitch_deg`, and the travel turned to point mostly downwards."""
    T = len(w2c)
    out = w2c.copy()
    c = camera_centers(w2c)
    down = -np.array([0.0, 0.0, 1.0])
    for j in range(T):
        u = j / (T - 1)
        out[j, :3, :3] = so3_exp(np.array([math.radians(pitch_deg) * u, 0.0, 0.0])) @ w2c[j, :3, :3]
        d = c[j] - c[0]
        moved = c[0] + 0.4 * d + 0.9 * np.linalg.norm(d) * down
        out[j, :3, 3] = -out[j, :3, :3] @ moved
    return out


EVERY_OTHER = list(range(0, T, 2))


def test_travel_known_judges_the_translation_on_measured_frames_only() -> None:
    plan = turn(30, 0, 2)
    back = path(30, 0, -2, -STRAFE_M_PER_DEG * 30)  # the turn as planned, the travel reversed
    late = list(range(T // 2, T))
    # travel reversed, but measured only where it was right: the travel judged on those frames passes
    mixed = plan.copy()
    mixed[: T // 2] = back[: T // 2]
    known = np.zeros(T, dtype=bool)
    known[[0, *late]] = True
    r = compare_to_plan(mixed, plan, travel_known=known)
    assert r.ok is True, r.reasons
    assert any(n.startswith(f"travel measured at frames 0, {T // 2},") for n in r.notes)
    # the same frames measured on the reversed path: caught
    r = compare_to_plan(back, plan, travel_known=known)
    assert r.ok is False and r.reasons[-1].startswith("moved backward")
    # nothing but the first frame measured: the translation is not judged, the rotation is
    none = np.zeros(T, dtype=bool)
    none[0] = True
    r = compare_to_plan(back, plan, travel_known=none)
    assert r.ok is True
    assert "the travel was not measured (too little parallax): the translation is not judged" in r.notes
    assert r.estimated is not None and math.isnan(r.estimated.forward)
    assert r.estimated.yaw_left_deg == pytest.approx(30.0, abs=1e-6)
    r = compare_to_plan(turn(-30, 0, 2), plan, travel_known=none)
    assert r.ok is False and r.reasons[0].startswith("turned right 30°")
    with pytest.raises(ValueError, match="travel_known"):
        compare_to_plan(plan, plan, travel_known=np.ones(3, dtype=bool))


def test_rotation_disagreement_between_two_paths() -> None:
    truth = turn(-24, 0, 1.8)
    seen = as_sfm(truth, similarity(3, 0.01))
    reg = np.ones(T, dtype=bool)
    dis, _ = rotation_disagreement(seen, reg, truth, reg)
    assert dis < 1e-6
    off = seen.copy()
    off[-1, :3, :3] = so3_exp(np.radians([10.0, 0.0, 0.0])) @ off[-1, :3, :3]
    dis, frame = rotation_disagreement(off, reg, truth, reg)
    assert dis == pytest.approx(10.0, abs=1e-6) and frame == T - 1
    # relative to the first common frame: a path missing frame 0 is compared from frame 1
    late = reg.copy()
    late[0] = False
    dis, frame = rotation_disagreement(off, late, truth, reg)
    assert dis == pytest.approx(10.0, abs=1e-6) and frame == T - 1
    one = np.zeros(T, dtype=bool)
    one[5] = True
    assert math.isnan(rotation_disagreement(off, one, truth, reg)[0])


def _choose(sfm_w2c: np.ndarray, plan: np.ndarray, tv: TwoViewPath, gates: bool = True, reg=None):
    reg = np.ones(T, dtype=bool) if reg is None else reg
    sfm = compare_to_plan(sfm_w2c, plan, registered=reg)
    return sfm, choose_path(sfm, sfm_w2c, reg, gates, tv, plan, PlanFollowingParams())


def test_sfm_in_the_planar_twin_is_overruled_by_two_view_geometry() -> None:
    """A clean turn and travel whose SfM path is the twin: SfM alone flags it, two-view geometry clears it."""
    plan = turn(-24, 0, 1.8)
    twin = as_sfm(planar_twin_like(plan, 26.0), similarity(4, 3.0))
    alone, r = _choose(twin, plan, as_two_view(plan, EVERY_OTHER, EVERY_OTHER[4:]))
    assert alone.ok is False  # the false positive the two-view look removes
    assert r.ok is True and r.source == "two_view"
    assert r.sfm_disagreement_deg == pytest.approx(26.0, abs=0.5)
    assert r.notes[0].startswith("judged on two-view geometry: SfM's path is contradicted by two-view geometry")
    assert r.frames == EVERY_OTHER
    attrs = json.loads(json.dumps(r.to_attrs(), allow_nan=False))
    assert attrs["source"] == "two_view" and attrs["two_view"]["frames"] == EVERY_OTHER


def test_a_fault_sfm_passes_is_caught_on_two_view_geometry() -> None:
    """The camera went straight on (no turn) but SfM's path follows the plan: two-view geometry sees the
    straight path, disagrees with SfM by the whole turn, and the verdict on it flags the segment."""
    plan = turn(-24, 0, 1.8)
    straight = path(0, 0, float(np.linalg.norm(camera_centers(plan)[-1] - camera_centers(plan)[0])))
    alone, r = _choose(as_sfm(plan, similarity(5, 2.0)), plan, as_two_view(straight, EVERY_OTHER, EVERY_OTHER[2:]))
    assert alone.ok is True
    assert r.ok is False and r.source == "two_view"
    assert r.reasons[0].startswith("did not turn")
    assert r.sfm_disagreement_deg == pytest.approx(24.0, abs=0.5)


def test_sfm_confirmed_by_two_view_geometry_keeps_its_verdict() -> None:
    plan = turn(30, 0, 2)
    reversed_turn = turn(-30, 0, 2)
    seen = as_sfm(noisy(reversed_turn, 0.3, 0.01), similarity(6, 0.5))
    alone, r = _choose(seen, plan, as_two_view(reversed_turn, EVERY_OTHER, EVERY_OTHER[3:]))
    assert alone.ok is False
    assert r.ok is False and r.source == "sfm" and r.reasons == alone.reasons
    assert r.sfm_disagreement_deg < 2.0
    assert r.notes[-1].startswith("two-view geometry agrees with SfM's rotations to")


def test_sfm_that_failed_its_gates_is_used_only_when_confirmed() -> None:
    plan = turn(30, 0, 2)
    wrong = as_sfm(planar_twin_like(plan, 20.0), similarity(7, 1.0))
    # gates failed, no frame in common to confirm it: the two-view path is judged
    reg = np.zeros(T, dtype=bool)
    reg[[7, 9, 15]] = True
    tv = as_two_view(plan, [0, 2, 4, 6], [0, 4, 6])
    _, r = _choose(wrong, plan, tv, gates=False, reg=reg)
    assert r.source == "two_view" and r.ok is True
    assert "failed its quality gates and shares fewer than 2 frames" in r.notes[0]
    # the same SfM path with its gates passed and nothing to compare: SfM's verdict stands
    _, r = _choose(wrong, plan, tv, gates=True, reg=reg)
    assert r.source == "sfm" and math.isnan(r.sfm_disagreement_deg)
    # gates failed but confirmed by two-view geometry: SfM's verdict
    good = as_sfm(plan, similarity(8, 1.0))
    _, r = _choose(good, plan, as_two_view(plan, EVERY_OTHER, EVERY_OTHER[2:]), gates=False)
    assert r.source == "sfm" and r.ok is True


def test_neither_path_judged_is_not_judged() -> None:
    plan = turn(30, 0, 2)
    nothing = as_two_view(plan, [0], [0])
    twin = planar_twin_like(plan, 35.0)
    reg = np.zeros(T, dtype=bool)
    _, r = _choose(np.full_like(plan, np.nan), plan, nothing, reg=reg)
    assert r.ok is None
    assert r.reasons == [
        "not judged: SfM's path could not be judged; two-view geometry: only 1 frame(s) registered; at least 2 "
        "are needed"
    ]
    # SfM contradicted (nothing to contradict with here: one frame) keeps SfM's verdict
    _, r = _choose(twin, plan, nothing)
    assert r.source == "sfm" and r.ok is False
    # SfM registered nothing, two-view geometry did: judged on it
    _, r = _choose(np.full_like(plan, np.nan), plan, as_two_view(plan, EVERY_OTHER, EVERY_OTHER), reg=reg)
    assert r.ok is True and r.source == "two_view"


def test_judge_segment_without_frames_or_plan() -> None:
    plan = turn(30, 0, 2)
    seen = as_sfm(plan, similarity(9, 1.0))
    reg = np.ones(T, dtype=bool)
    r = judge_segment(plan, seen, reg)  # no frames: SfM's path alone
    assert r.ok is True and r.source == "sfm" and r.two_view is None
    frames = np.zeros((T, 8, 8, 3), dtype=np.uint8)
    r = judge_segment(np.full_like(plan, np.nan), seen, reg, frames, np.eye(3))  # a user's clip: no plan
    assert r.ok is None and r.two_view is None
    r = judge_segment(plan, seen, reg, frames, np.eye(3), PlanFollowingParams(two_view=None))
    assert r.ok is True and r.two_view is None


@pytest.mark.e2e
@pytest.mark.parametrize("ignored", [False, True])
def test_a_rendered_turn_and_travel_is_judged_as_the_check_judges_it(ignored: bool) -> None:
    """Right 24° with 1.8 m forward over the forest lake's ground (benchmarks.plan_following case 13), rendered
    clean and ignoring its instruction, posed by the check's SfM and judged with the two-view look: the clean
    one passes (where SfM's own path took the planar twin, on two-view geometry), the ignoring one does not."""
    from wonderverse.camera import CameraPrior
    from wonderverse.config import build_config
    from wonderverse.sfm import reconstruct
    from wonderverse.video import initial_pose
    from wonderverse.video.procedural import ProceduralVideo

    prompt = "a quiet forest lake in autumn"
    cfg = build_config(prompt, preset="preview")
    opts = {"fault_probability": 0.0} | ({"force_fault": "ignore"} if ignored else {})
    model = ProceduralVideo(prompt, 13, 320, 208, cfg.scene.video.fov_deg, opts)
    plan = move_path(initial_pose(model), math.radians(-24), 0.0, 1.8, -24 * STRAFE_M_PER_DEG, 17)
    video = model.generate(prompt, plan, seed=2013 if ignored else 1013, reference=None)
    sfm = reconstruct(video.frames, cfg.steps.check.sfm, CameraPrior(video.K, "given"))
    p = cfg.steps.check.plan_following
    r = judge_segment(plan, sfm.poses, sfm.registered, video.frames, video.K, p, sfm_gates_passed=sfm.gates_passed)
    assert compare_to_plan(video.gt.poses, plan, p).ok is (not ignored)  # the truth, for reference
    assert r.ok is (not ignored), (r.reasons, r.notes)
    if compare_to_plan(sfm.poses, plan, p, registered=sfm.registered).ok is not r.ok:
        assert r.source == "two_view" and r.sfm_disagreement_deg > p.sfm_rotation_tol_deg
    assert r.two_view is not None and len(r.two_view["frames"]) >= 6

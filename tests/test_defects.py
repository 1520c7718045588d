"""The defects of real AI video in the procedural backend (`ProceduralOptions.defects`) and the fault that
ignores the camera instruction.

Each defect is measured against what it claims, with a clean render of the same world and poses (defects
"none") or the path as asked as the reference; ground truth must stay the truth: depth and normals of the
world's own mesh at the poses really rendered.
"""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError
from scipy.ndimage import gaussian_filter, laplace, map_coordinates

from wonderverse.camera import camera_centers, geodesic_angle, look_at
from wonderverse.video.base import Guide
from wonderverse.video.defects import DriftField, motion_blur, plan_segment
from wonderverse.video.procedural import (
    ProceduralOptions,
    ProceduralVideo,
    apply_pose_fault,
    demo_path,
    draw_fault,
)
from wonderverse.video.procedural_options import DEFECT_LEVELS, DefectParams, resolved_defects
from wonderverse.video.texture import Noise

OUTDOOR = "a quiet village with houses and trees"
INDOOR = "a cozy living room with a sofa"
W, H = 96, 64
FAST = {"fault_probability": 0.0, "shadow_map_px": 256}  # coarse shadow maps: a world's first frame in 50 ms


def video(prompt: str = OUTDOOR, width: int = W, height: int = H, **opts: object) -> ProceduralVideo:
    return ProceduralVideo(prompt, 3, width, height, 60.0, {**FAST, **opts})


def grey(frames: np.ndarray) -> np.ndarray:
    return frames.astype(np.float64) @ np.array([0.299, 0.587, 0.114])


def same_truth(a: object, b: object) -> bool:
    return (
        np.array_equal(a.gt.depth, b.gt.depth)
        and np.array_equal(a.gt.normals, b.gt.normals)
        and np.array_equal(a.gt.poses, b.gt.poses)
    )


def still_path(v: ProceduralVideo, n: int) -> np.ndarray:
    return np.repeat(v.world.start_pose()[None], n, axis=0)


# ---------------------------------------------------------------- options


def test_levels_validate_and_a_wrong_name_lists_the_valid_ones() -> None:
    assert ProceduralOptions().defects == "none" and resolved_defects(ProceduralOptions()).is_clean()
    assert {"none", "texture_poor", "ai_like"} <= set(DEFECT_LEVELS)
    tp = resolved_defects(ProceduralOptions(defects="texture_poor"))
    assert tp.texture_poor_share == 0.5 and tp == DefectParams(texture_poor_share=0.5)
    assert not resolved_defects(ProceduralOptions(defects="ai_like")).is_clean()
    explicit = ProceduralOptions(defects={"blur_sigma_px": 1.0})
    assert resolved_defects(explicit) == DefectParams(blur_sigma_px=1.0)
    with pytest.raises(ValidationError, match="none, texture_poor, ai_like"):
        ProceduralOptions(defects="cinematic")
    with pytest.raises(ValidationError):
        ProceduralOptions(defects={"blur_px": 1.0})  # extra fields are refused
    with pytest.raises(ValidationError):
        ProceduralOptions(defects={"parallax_scale": 0.0})
    with pytest.raises(ValidationError):
        DefectParams(jpeg_quality=0)
    assert "ignore" not in ProceduralOptions().fault_types, "the default faults are today's"


def test_defects_none_is_byte_identical_to_no_defects_and_the_guide_is_ignored() -> None:
    def full(**opts: object) -> ProceduralVideo:  # today's default options, shadow maps included
        return ProceduralVideo(OUTDOOR, 3, W, H, 60.0, {"fault_probability": 0.0, **opts})

    plain, named, empty = full(), full(defects="none"), full(defects={})
    path = demo_path(plain.world.start_pose(), 3)
    a = plain.generate("", path, 0, None)
    for other in (named, empty):
        b = other.generate("", path, 0, None)
        assert np.array_equal(a.frames, b.frames) and same_truth(a, b)
    guide = Guide(np.zeros_like(a.frames), np.ones(a.frames.shape[:3], bool), np.full(a.gt.depth.shape, np.inf))
    assert np.array_equal(plain.generate("", path, 0, None, guide=guide).frames, a.frames)


def test_ai_like_is_deterministic_per_attempt_and_differs_between_attempts() -> None:
    v = video(defects="ai_like")
    path = demo_path(v.world.start_pose(), 4)
    a, b, c = v.generate("", path, 1, None), video(defects="ai_like").generate("", path, 1, None), None
    assert np.array_equal(a.frames, b.frames) and same_truth(a, b)
    c = v.generate("", path, 2, None)
    assert not np.array_equal(a.frames[1:], c.frames[1:])
    clean = video().generate("", path, 1, None)
    assert not np.array_equal(a.frames, clean.frames)


def test_frames_under_defects_are_the_same_at_any_scene_scale() -> None:
    base, small = video(defects="ai_like"), video(defects="ai_like", scene_scale=1e-3)
    path = demo_path(base.world.start_pose(), 3)
    spath = path.copy()
    spath[:, :3, 3] *= 1e-3
    a, b = base.generate("", path, 0, None), small.generate("", spath, 0, None)
    assert np.array_equal(a.frames, b.frames)
    np.testing.assert_allclose(camera_centers(b.gt.poses), 1e-3 * camera_centers(a.gt.poses), atol=1e-9)


# ---------------------------------------------------------------- texture-poor surfaces


@pytest.mark.parametrize("prompt", [OUTDOOR, INDOOR])
def test_texture_poor_surfaces_flatten_the_image_and_keep_the_depth(prompt: str) -> None:
    path = demo_path(video(prompt).world.start_pose(), 2, yaw_deg=30.0, forward_m=0.5)
    shares = (0.0, 0.25, 0.75, 1.0)
    out = {s: video(prompt, defects={"texture_poor_share": s}).generate("", path, 0, None) for s in shares}
    hit = np.isfinite(out[0.0].gt.depth)

    def flat_share(frames: np.ndarray) -> float:
        g = grey(frames)
        grad = np.maximum(np.abs(np.diff(g, axis=2))[:, :-1], np.abs(np.diff(g, axis=1))[:, :, :-1])
        return float(np.mean(grad[hit[:, :-1, :-1]] < 2.0))

    flat = {s: flat_share(out[s].frames) for s in shares}
    assert flat[1.0] > flat[0.0] + 0.25, flat
    assert flat[0.0] <= flat[0.25] <= flat[0.75] <= flat[1.0], flat
    for s in shares:
        assert same_truth(out[s], out[0.0]), "texture-poor surfaces keep the geometry"
    # a surface plain at one share is plain at every larger one; a share in between is in between
    differ = (out[0.0].frames != out[1.0].frames).any(axis=-1)
    plain = {s: (out[s].frames == out[1.0].frames).all(axis=-1) & differ for s in (0.25, 0.75)}
    assert (plain[0.25] <= plain[0.75]).mean() > 0.995
    assert 0.05 < plain[0.25].sum() / differ.sum() < min(0.8, plain[0.75].sum() / differ.sum())


def test_the_texture_poor_level_leaves_the_sky_alone_and_render_shows_it() -> None:
    v, clean = video(defects="texture_poor"), video()
    pose = v.world.start_pose()
    rgb, depth, _ = v.render(pose)
    rgb0, depth0, _ = clean.render(pose)
    sky = ~np.isfinite(depth)
    assert np.array_equal(depth, depth0) and sky.any()
    assert np.array_equal(rgb[sky], rgb0[sky])
    assert not np.array_equal(rgb[~sky], rgb0[~sky])


# ---------------------------------------------------------------- exposure and white balance


def test_exposure_and_white_balance_drift_smoothly_and_leave_the_truth_alone() -> None:
    T, stops, wb = 25, 0.3, 0.05
    v = video(width=48, height=32)
    path = demo_path(v.world.start_pose(), T, yaw_deg=20.0, forward_m=1.0)
    clean = v.generate("", path, 0, None)
    params = {"exposure_drift_stops": stops, "white_balance_drift_frac": wb}
    drifted = video(width=48, height=32, defects=params).generate("", path, 0, None)
    assert same_truth(drifted, clean)
    a, b = clean.frames.astype(np.float64), drifted.frames.astype(np.float64)
    ok = ((a > 30) & (a < 180)).all(axis=-1) & (b < 250).all(axis=-1)  # no clipping either side
    ratio = np.array([[b[i][ok[i]][:, c].sum() / a[i][ok[i]][:, c].sum() for c in range(3)] for i in range(T)])
    log2 = np.log2(ratio)
    exposure = log2.mean(axis=1)  # white balance keeps the product of the gains
    balance = np.exp2(log2 - exposure[:, None]) - 1.0
    assert np.abs(log2[0]).max() < 0.01, "the first frame is the reference's look"
    assert 0.5 * stops < np.abs(exposure).max() < stops + 0.02
    assert 0.5 * wb < np.abs(balance).max() < wb + 0.01
    steps = np.abs(np.diff(log2, axis=0)).max()
    assert steps < (stops + np.log2(1 + wb)) * 4 * np.pi / (T - 1), "no jumps"
    turns = np.sum(np.diff(np.sign(np.diff(exposure))) != 0)
    assert turns <= 4, "a slow drift, not noise"
    # the drawn curves the frames were given, the same draw
    seg = plan_segment(DefectParams(**params), 3, 0, T)
    np.testing.assert_allclose(exposure, seg.exposure_stops, atol=0.01)


# ---------------------------------------------------------------- flickering detail


def test_flicker_changes_fine_detail_between_frames_but_not_the_blurred_image() -> None:
    v = video(defects={"detail_flicker_contrast": 0.3})
    still = still_path(v, 3)
    clean = video().generate("", still, 0, None)
    out = v.generate("", still, 0, None)
    assert same_truth(out, clean)
    assert np.array_equal(clean.frames[0], clean.frames[2]), "the same pose renders the same frame"
    a, b = grey(out.frames[0]), grey(out.frames[2])
    hit = np.isfinite(out.gt.depth[0])
    raw = np.abs(a - b)[hit].mean()
    blurred = np.abs(gaussian_filter(a, 4) - gaussian_filter(b, 4))[hit].mean()
    assert raw > 4.0, raw
    # value noise of 3 px cells keeps some coarse power (independent cells): a 4 px blur leaves about 1/sqrt(11)
    assert blurred < 0.4 * raw, (raw, blurred)
    exposure = video(defects={"exposure_drift_stops": 0.5}).generate("", demo_path(still[0], 3, 0.0, 0.0), 0, None)
    c, d = grey(exposure.frames[0]), grey(exposure.frames[2])
    coarse = np.abs(gaussian_filter(c, 4) - gaussian_filter(d, 4))[hit].mean() / np.abs(c - d)[hit].mean()
    assert coarse > 0.8, "a coarse change survives the blur: the flicker's does not"
    sky = ~hit
    assert np.array_equal(out.frames[0][sky], out.frames[2][sky]), "the sky does not flicker"


# ---------------------------------------------------------------- geometric drift


def test_geometric_drift_deforms_the_frames_slightly_and_not_the_ground_truth() -> None:
    T = 4
    v = video()
    path = demo_path(v.world.start_pose(), T, yaw_deg=10.0, forward_m=0.5)
    clean = v.generate("", path, 0, None)
    small = video(defects={"geometric_drift_m": 0.05}).generate("", path, 0, None)
    large = video(defects={"geometric_drift_m": 1.0}).generate("", path, 0, None)
    assert same_truth(small, clean) and same_truth(large, clean), "ground truth is the undeformed world"
    assert np.array_equal(small.frames[0], clean.frames[0]), "no drift at the first frame"

    def changed(a: np.ndarray, b: np.ndarray) -> float:
        return float(np.mean(np.abs(a.astype(int) - b.astype(int)).max(axis=-1) > 40))

    end_small, end_large = changed(small.frames[-1], clean.frames[-1]), changed(large.frames[-1], clean.frames[-1])
    assert 0.0 < end_small < 0.05 and end_small < end_large, (end_small, end_large)
    assert changed(small.frames[1], clean.frames[1]) <= end_small + 0.01, "it grows over the segment"


def test_the_drift_field_is_smooth_and_bounded_by_its_amplitude() -> None:
    field = DriftField(Noise(5), 1.0 / 15.0, np.array([[0, 0, 0], [100, 0, 0], [0, 100, 0]], np.float32))
    p = np.random.default_rng(0).uniform(-60, 60, (3, 20000)).astype(np.float32)
    d = field.displacement(p, 0.05)
    assert np.abs(d).max() <= 0.05 + 1e-7 and np.abs(d).max() > 0.025
    near = field.displacement(p + np.float32(0.1), 0.05)  # 10 cm away: at most ~cm/m of change
    assert np.abs(near - d).max() < 0.05 * 0.1 * 1.0


# ---------------------------------------------------------------- blur and compression


def high_frequency(frames: np.ndarray) -> float:
    return float(np.mean([np.mean(laplace(grey(f)) ** 2) for f in frames]))


@pytest.mark.parametrize(
    ("params", "max_ratio"),
    [({"blur_sigma_px": 1.0}, 0.4), ({"jpeg_quality": 15}, 0.8), ({"motion_blur_shutter": 1.0}, 0.6)],
)
def test_blur_and_compression_take_out_high_frequencies(params: dict, max_ratio: float) -> None:
    v = video()
    path = demo_path(v.world.start_pose(), 3, yaw_deg=30.0, forward_m=0.5)  # about 10 px per frame
    clean = v.generate("", path, 0, None)
    out = video(defects=params).generate("", path, 0, None)
    assert same_truth(out, clean)
    ratio = high_frequency(out.frames) / high_frequency(clean.frames)
    assert ratio < max_ratio, ratio
    assert np.abs(grey(out.frames).mean() - grey(clean.frames).mean()) < 3.0, "the picture's brightness is kept"


def test_motion_blur_follows_the_motion_a_still_camera_stays_sharp() -> None:
    v = video(defects={"motion_blur_shutter": 1.0})
    still = still_path(v, 3)
    assert np.array_equal(v.generate("", still, 0, None).frames, video().generate("", still, 0, None).frames)
    # a pan: vertical edges smear, horizontal ones do not
    eye = camera_centers(still[:1])[0]
    pan = np.stack([look_at(eye, eye + np.array([np.sin(a), np.cos(a), -0.1])) for a in np.radians([0.0, 6.0, 12.0])])
    clean, out = video().generate("", pan, 0, None), v.generate("", pan, 0, None)
    g0, g1 = grey(clean.frames[1]), grey(out.frames[1])
    across = np.mean(np.diff(g1, axis=1) ** 2) / np.mean(np.diff(g0, axis=1) ** 2)
    along = np.mean(np.diff(g1, axis=0) ** 2) / np.mean(np.diff(g0, axis=0) ** 2)
    assert across < 0.5 * along, (across, along)


def test_motion_blur_averages_bilinear_samples_along_the_smear() -> None:
    rng = np.random.default_rng(0)
    frame = rng.integers(0, 256, (20, 30, 3)).astype(np.uint8)
    flow = rng.normal(0.0, 6.0, (20, 30, 2)).astype(np.float32)
    flow[0, 0] = [400.0, 0.0]  # capped at max_px
    out = motion_blur(frame, flow, 0.5, 5, 8.0)
    smear = flow * 0.5
    length = np.linalg.norm(smear, axis=-1, keepdims=True)
    smear = np.where(length > 8.0, smear * 8.0 / length, smear)
    assert np.allclose(smear[0, 0], [8.0, 0.0])
    rows, cols = np.meshgrid(np.arange(20.0), np.arange(30.0), indexing="ij")
    ref = np.zeros((20, 30, 3))
    for s in np.linspace(-0.5, 0.5, 5):
        at = np.stack([np.clip(rows + s * smear[..., 1], 0, 19), np.clip(cols + s * smear[..., 0], 0, 29)])
        for c in range(3):
            ref[..., c] += map_coordinates(frame[..., c].astype(float), at, order=1) / 5
    np.testing.assert_allclose(out, ref, atol=2e-3)
    assert np.array_equal(motion_blur(frame, np.zeros_like(flow), 1.0, 5, 8.0), frame.astype(np.float32))


# ---------------------------------------------------------------- low parallax


@pytest.mark.parametrize("scale", [0.3, 0.7])
def test_parallax_scale_moves_the_camera_that_share_of_the_way_and_keeps_rotations(scale: float) -> None:
    v = video(defects={"parallax_scale": scale})
    path = demo_path(v.world.start_pose(), 4, yaw_deg=20.0, forward_m=2.0)
    out = v.generate("", path, 0, None)
    c, asked = camera_centers(out.gt.poses), camera_centers(path)
    np.testing.assert_allclose(c - c[0], scale * (asked - asked[0]), atol=1e-9)
    np.testing.assert_allclose(out.gt.poses[:, :3, :3], path[:, :3, :3], atol=1e-12)
    # the ground truth is that of the poses really rendered
    truth = video().generate("", out.gt.poses, 0, None)
    assert np.array_equal(out.gt.depth, truth.gt.depth) and np.array_equal(out.frames, truth.frames)


# ---------------------------------------------------------------- the ignored instruction


def steps(poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    c = camera_centers(poses)
    return np.linalg.norm(np.diff(c, axis=0), axis=1), geodesic_angle(poses[:-1, :3, :3], poses[1:, :3, :3])


def test_ignore_takes_a_smooth_wrong_path_in_every_mode() -> None:
    opts = ProceduralOptions(force_fault="ignore")
    start = video().world.start_pose()
    path = demo_path(start, 9, yaw_deg=-20.0, forward_m=1.0)  # turn left 20 deg, forward 1 m
    plan_trans, plan_rot = steps(path)
    modes = set()
    for seed in range(40):
        plan = draw_fault(3, seed, len(path), opts)
        assert plan is not None and plan.type == "ignore"
        poses, record = apply_pose_fault(path, plan, opts)
        modes.add(record["mode"])
        assert record["type"] == "ignore" and record["frames"] == list(range(1, 9))
        assert np.array_equal(poses[0], path[0])
        trans, rot = steps(poses)
        assert trans.max() <= 1.01 * plan_trans.max() + 1e-9 and rot.max() <= 1.01 * plan_rot.max() + 1e-9
        end_rot = np.degrees(geodesic_angle(poses[-1, :3, :3], path[-1, :3, :3]))
        d_plan, d_real = (
            camera_centers(path)[-1] - camera_centers(path)[0],
            camera_centers(poses)[-1] - camera_centers(poses)[0],
        )
        cos = d_plan @ d_real / (np.linalg.norm(d_plan) * np.linalg.norm(d_real))
        assert end_rot > 15.0 or cos < 0.1, (record["mode"], end_rot, cos)
        assert np.linalg.norm(d_real) == pytest.approx(np.linalg.norm(d_plan)), "same overall speed"
        planned, rendered = record["planned"], record["rendered"]
        assert planned["turn_left_deg"] == pytest.approx(20.0) and planned["forward_m"] == pytest.approx(1.0)
        if record["mode"] == "reverse_turn":
            assert rendered["turn_left_deg"] == pytest.approx(-20.0) and "turn right 20" in rendered["words"]
        elif record["mode"] == "no_turn":
            assert rendered["rotation_deg"] == pytest.approx(0.0, abs=1e-6)
        assert "asked to turn left 20 deg" in record["summary"]
    assert modes == {"reverse_turn", "no_turn", "turned_move"}, modes


def test_a_camera_told_to_stay_still_turns_instead() -> None:
    opts = ProceduralOptions(force_fault="ignore")
    still = np.repeat(video().world.start_pose()[None], 6, axis=0)
    poses, record = apply_pose_fault(still, draw_fault(3, 0, 6, opts), opts)
    assert record["mode"] == "unplanned_turn" and record["planned"]["words"] == "stay still"
    assert 15.0 - 1e-6 <= abs(record["rendered"]["turn_left_deg"]) <= 30.0 + 1e-6
    _, rot = steps(poses)
    assert np.ptp(rot) < 1e-9, "an even turn"


def test_ignore_renders_the_wrong_path_and_records_it_in_scene_units() -> None:
    v = video(force_fault="ignore")
    path = demo_path(v.world.start_pose(), 5, yaw_deg=20.0, forward_m=1.0)
    out = v.generate("", path, 0, None)
    f = out.gt.faults
    assert f["type"] == "ignore" and f["frames"] == [1, 2, 3, 4]
    assert not np.allclose(out.gt.poses[1:], path[1:])
    truth = video().generate("", out.gt.poses, 0, None)
    assert np.array_equal(out.frames, truth.frames) and same_truth(out, truth)
    scale = 1e-3
    spath = path.copy()
    spath[:, :3, 3] *= scale
    small = video(force_fault="ignore", scene_scale=scale).generate("", spath, 0, None).gt
    np.testing.assert_allclose(camera_centers(small.poses), scale * camera_centers(out.gt.poses), atol=1e-12)
    for key in ("planned", "rendered"):
        assert small.faults[key]["forward_m"] == pytest.approx(scale * f[key]["forward_m"], abs=1e-12)
        assert small.faults[key]["path_m"] == pytest.approx(scale * f[key]["path_m"])
        assert small.faults[key]["turn_left_deg"] == pytest.approx(f[key]["turn_left_deg"])
    assert small.faults["mode"] == f["mode"]


def test_ignore_is_drawn_when_listed_and_never_by_default() -> None:
    listed = ProceduralOptions(fault_probability=1.0, fault_types=("ignore", "teleport"))
    kinds = {draw_fault(3, seed, 9, listed).type for seed in range(40)}
    assert kinds == {"ignore", "teleport"}
    default = ProceduralOptions(fault_probability=1.0)
    assert all(draw_fault(3, seed, 9, default).type != "ignore" for seed in range(200))

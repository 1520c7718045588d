"""benchmarks.enhancement: the parallax bound (which world points triangulation can place within a tolerance),
which points the aligned prior places, merging runs, and changing a condition's defects."""

import numpy as np

from benchmarks.enhancement import MATCH_SIGMA_PX, determinable, placed_by_prior
from wonderverse.camera import look_at

F_PX, W, H = 200.0, 320, 240
K = np.array([[F_PX, 0.0, W / 2], [0.0, F_PX, H / 2], [0.0, 0.0, 1.0]])


def test_points_are_determinable_up_to_the_depth_where_triangulation_error_reaches_the_tolerance():
    """Two cameras 1 m apart looking along +y at points straight ahead: triangulation's depth error is about
    z² σ / (f b) (σ the match error in pixels), so points are determinable up to z = sqrt(tol f b / σ)."""
    baseline = 1.0
    up = np.array([0.0, 0.0, 1.0])
    cams = np.stack([look_at(np.array([x, 0.0, 0.0]), np.array([x, 10.0, 0.0]), up) for x in (-0.5, 0.5)])
    z = np.linspace(2.0, 60.0, 400)
    points = np.stack([np.zeros_like(z), z, np.zeros_like(z)], axis=1)
    for edge in (10.0, 25.0):
        tol = edge**2 * MATCH_SIGMA_PX / (F_PX * baseline)
        sub, ok = determinable(points, K, cams, tol, H, W)
        depth = sub[:, 1]
        assert len(sub) == len(points)
        assert ok[depth < 0.95 * edge].all() and (depth < 0.95 * edge).sum() > 10
        assert not ok[depth > 1.05 * edge].any() and (depth > 1.05 * edge).sum() > 10


def test_a_point_one_camera_alone_frames_is_not_determinable():
    cams = np.stack([look_at(np.zeros(3), np.array([0.0, 10.0, 0.0]), np.array([0.0, 0.0, 1.0]))] * 2)
    _, ok = determinable(np.array([[0.0, 5.0, 0.0], [0.0, -5.0, 0.0]]), K, cams, 1.0, H, W)
    assert not ok.any()  # no baseline in front, nothing framed behind


def test_the_prior_places_points_where_its_depth_is_within_the_tolerance_along_the_ray():
    """A plane 10 m ahead seen by one camera; its prior is exact on the left third, 0.3 m off in the middle
    and an occluder 5 m ahead on the right; one point lies behind the camera."""
    cam = look_at(np.zeros(3), np.array([0.0, 10.0, 0.0]), np.array([0.0, 0.0, 1.0]))[None]
    prior = np.full((1, H, W), 10.0)
    prior[0, :, W // 3 : 2 * W // 3] = 10.3
    prior[0, :, 2 * W // 3 :] = 5.0
    xs = np.array([-4.0, 0.0, 4.0])  # pixel columns 80, 160, 240 at f = 200
    points = np.concatenate([np.stack([xs, np.full(3, 10.0), np.zeros(3)], 1), [[0.0, -10.0, 0.0]]])
    assert placed_by_prior(points, K, cam, prior, 0.2).tolist() == [True, False, False, False]
    assert placed_by_prior(points, K, cam, prior, 0.4).tolist() == [True, True, False, False]


def test_merging_runs_puts_a_later_rows_variant_in_place_of_the_earlier_one():
    from benchmarks.enhancement import merge_rows

    def row(world: str, condition: str, variant: str, f1: float) -> dict:
        return {"world": world, "condition": condition, "variant": variant, "f1": f1}

    first = [
        row("outdoor", "clean", "both", 0.5),
        row("outdoor", "clean", "rgb", 0.3),
        row("indoor", "clean", "both", 0.8),
    ]
    merged = merge_rows([first, [row("outdoor", "clean", "both", 0.6)]])
    got = {(r["world"], r["variant"]): r["f1"] for r in merged}
    assert got == {("outdoor", "both"): 0.6, ("outdoor", "rgb"): 0.3, ("indoor", "both"): 0.8}


def test_turning_every_defect_of_a_condition_off_gives_the_clean_frames():
    from benchmarks.enhancement import prepare
    from wonderverse.config import build_config

    small = {
        "scene": {"video": {"width": 64, "height": 48, "frames_per_segment": 3}},
        "steps": {"splats": {"max_side_px": 64}},
    }
    cfg = build_config("benchmark", preset="preview", overrides=small)
    off = dict(texture_poor_share=0, exposure_drift_stops=0, white_balance_drift_frac=0, detail_flicker_contrast=0)
    off |= dict(geometric_drift_m=0, blur_sigma_px=0, motion_blur_shutter=0, jpeg_quality=None, parallax_scale=1)
    clean = prepare("indoor", "clean", cfg)["views"].frames
    ai_like = prepare("indoor", "ai_like", cfg)["views"].frames
    all_off = prepare("indoor", "ai_like", cfg, defect_update=off)["views"].frames
    one_on = prepare("indoor", "ai_like", cfg, defect_update=off | {"blur_sigma_px": 0.5})["views"].frames
    assert np.array_equal(all_off, clean)
    assert not np.array_equal(ai_like, clean) and not np.array_equal(one_on, clean)


def test_a_world_fixed_prior_error_makes_the_aligned_prior_worse_and_keeps_the_sky():
    from benchmarks.enhancement import prepare
    from wonderverse.config import build_config
    from wonderverse.metrics import depth_errors

    small = {
        "scene": {"video": {"width": 96, "height": 64, "frames_per_segment": 4}},
        "steps": {"splats": {"max_side_px": 96}},
    }
    cfg = build_config("benchmark", preset="preview", overrides=small)
    plain = prepare("outdoor", "clean", cfg)
    fixed = prepare("outdoor", "clean", cfg, prior_update={"world_warp_log_amp": 0.1})
    truth = plain["gt_depth"]
    ok = np.isfinite(truth)

    def absrel(data: dict) -> float:
        return depth_errors(data["views"].prior_depth, truth, mask=ok)["absrel"]

    assert absrel(fixed) > 1.2 * absrel(plain)
    assert np.array_equal(np.isinf(fixed["views"].prior_depth), ~ok)

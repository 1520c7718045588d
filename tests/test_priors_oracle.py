"""The ORACLE priors on an analytic scene (ground plane, a wall, sky): exact at level "none", degraded like
a monocular network otherwise (unknown scale/shift that alignment removes), seeded, batch-independent."""

from __future__ import annotations

import numpy as np
import pytest

from wonderverse.camera import intrinsics
from wonderverse.priors import (
    ORACLE_LEVELS,
    PriorsParams,
    align_scale_shift,
    make_depth_model,
    make_normal_model,
)
from wonderverse.priors.oracle import OracleDepth, OracleNormals
from wonderverse.video.base import GroundTruth

T, H, W = 4, 48, 64
K = intrinsics(W, H, 70.0)


def analytic_scene() -> tuple[np.ndarray, np.ndarray]:
    """(T,H,W) camera z with +inf sky and (T,H,W,3) unit normals facing the camera (0 for sky).

    Camera 1.5 m above a ground plane (OpenCV y down: ground at Y = +1.5, normal (0,-1,0)) and a
    fronto-parallel wall (normal (0,0,-1)) 6..6.6 m away that covers the middle of the view; sky above.
    """
    u = np.arange(W) + 0.5
    v = np.arange(H) + 0.5
    a = np.broadcast_to((u[None, :] - K[0, 2]) / K[0, 0], (H, W))
    b = np.broadcast_to((v[:, None] - K[1, 2]) / K[1, 1], (H, W))
    depth = np.full((T, H, W), np.inf, dtype=np.float32)
    normals = np.zeros((T, H, W, 3), dtype=np.float32)
    with np.errstate(divide="ignore"):
        z_ground = np.where(b > 0, 1.5 / b, np.inf)
    for t in range(T):
        z_wall = 6.0 + 0.2 * t
        wall = (np.abs(a * z_wall) < 2.0) & (b * z_wall > -2.0) & (z_wall < z_ground)
        ground = np.isfinite(z_ground) & ~wall
        depth[t][ground] = z_ground[ground]
        depth[t][wall] = z_wall
        normals[t][ground] = (0.0, -1.0, 0.0)
        normals[t][wall] = (0.0, 0.0, -1.0)
    return depth, normals


GT_DEPTH, GT_NORMALS = analytic_scene()
FRAMES = np.zeros((T, H, W, 3), dtype=np.uint8)
SKY = ~np.isfinite(GT_DEPTH)


def test_scene_has_ground_wall_and_sky() -> None:
    assert SKY.any() and (~SKY).sum() > 0.4 * SKY.size
    assert (GT_NORMALS[..., 2] == -1).any() and (GT_NORMALS[..., 1] == -1).any()


@pytest.mark.parametrize("space", ["depth", "inverse_depth"])
def test_level_none_is_exact_with_sky_at_a_far_constant(space: str) -> None:
    pred = OracleDepth(GT_DEPTH, level="none", space=space).predict(FRAMES)
    assert pred.kind == space and pred.depth.dtype == np.float32 and np.isfinite(pred.depth).all()
    expected = GT_DEPTH if space == "depth" else 1.0 / GT_DEPTH
    np.testing.assert_allclose(pred.depth[~SKY], expected[~SKY], rtol=1e-6)
    for t in range(T):
        far = 3.0 * GT_DEPTH[t][~SKY[t]].max()
        np.testing.assert_allclose(pred.depth[t][SKY[t]], far if space == "depth" else 1.0 / far, rtol=1e-6)
    normals = OracleNormals(GT_NORMALS, level="none").predict(FRAMES).normals
    np.testing.assert_allclose(normals, GT_NORMALS, atol=1e-6)


def abs_rel_after_alignment(level: str, seed: int = 0) -> tuple[float, list[float]]:
    pred = OracleDepth(GT_DEPTH, level=level, space="inverse_depth", seed=seed).predict(FRAMES)
    errs, scales = [], []
    for t in range(T):
        r = align_scale_shift(pred.depth[t], GT_DEPTH[t], mask=~SKY[t], space="inverse_depth", method="lstsq")
        assert r.ok
        e = np.abs(r.aligned_depth[~SKY[t]] - GT_DEPTH[t][~SKY[t]]) / GT_DEPTH[t][~SKY[t]]
        errs.append(float(np.mean(e)))
        scales.append(r.scale)
    return float(np.mean(errs)), scales


def test_degradation_is_realistic_and_monotone_in_level() -> None:
    err = {lvl: abs_rel_after_alignment(lvl)[0] for lvl in ("none", "mild", "realistic", "harsh")}
    assert err["none"] < 1e-5
    assert 0.0 < err["mild"] < err["realistic"] < err["harsh"]
    assert 0.005 < err["realistic"] < 0.15  # a few % AbsRel, like a good monocular network after alignment
    # the unknown per-frame scale is really there (and different per frame)
    _, scales = abs_rel_after_alignment("realistic")
    assert max(scales) / min(scales) > 1.2


def test_unaligned_prediction_is_not_the_truth() -> None:
    pred = OracleDepth(GT_DEPTH, level="realistic", space="depth").predict(FRAMES)
    assert pred.kind == "depth"
    ratio = pred.depth[~SKY] / GT_DEPTH[~SKY]
    assert np.abs(np.median(ratio) - 1.0) > 0.05 or np.std(ratio) > 0.05


def test_seeded_and_independent_of_batching() -> None:
    o = OracleDepth(GT_DEPTH, level="realistic", seed=3)
    full = o.predict(FRAMES).depth
    np.testing.assert_array_equal(full, OracleDepth(GT_DEPTH, level="realistic", seed=3).predict(FRAMES).depth)
    part = o.predict(FRAMES[:2], indices=np.array([2, 0])).depth
    np.testing.assert_array_equal(part[0], full[2])
    np.testing.assert_array_equal(part[1], full[0])
    other = OracleDepth(GT_DEPTH, level="realistic", seed=4).predict(FRAMES).depth
    assert not np.array_equal(full, other)
    with pytest.raises(ValueError):
        o.predict(FRAMES[:2])  # which frames? indices are required for a partial batch
    with pytest.raises(ValueError):
        o.predict(FRAMES[:1], indices=np.array([T]))

    n = OracleNormals(GT_NORMALS, level="realistic", seed=3)
    nf = n.predict(FRAMES).normals
    np.testing.assert_array_equal(n.predict(FRAMES[:1], indices=np.array([3])).normals[0], nf[3])


def test_normals_are_degraded_unit_and_zero_for_sky() -> None:
    errs = {}
    for level in ("mild", "realistic", "harsh"):
        pred = OracleNormals(GT_NORMALS, level=level).predict(FRAMES, K=K)
        n = pred.normals
        assert n.dtype == np.float32 and np.isfinite(n).all()
        assert (n[SKY] == 0).all()
        np.testing.assert_allclose(np.linalg.norm(n[~SKY], axis=-1), 1.0, atol=1e-5)
        cos = np.clip((n[~SKY] * GT_NORMALS[~SKY]).sum(-1), -1, 1)
        errs[level] = float(np.degrees(np.arccos(cos)).mean())
    assert 0.5 < errs["mild"] < errs["realistic"] < errs["harsh"]
    assert 3.0 < errs["realistic"] < 25.0


def test_all_sky_frames_stay_finite() -> None:
    sky = np.full((2, H, W), np.inf, dtype=np.float32)
    for space in ("depth", "inverse_depth"):
        d = OracleDepth(sky, level="harsh", space=space).predict(FRAMES[:2]).depth
        assert np.isfinite(d).all()
    n = OracleNormals(np.zeros((2, H, W, 3), np.float32), level="harsh").predict(FRAMES[:2]).normals
    assert np.isfinite(n).all() and (n == 0).all()


def test_labelled_as_oracle_and_only_built_with_ground_truth() -> None:
    assert "benchmarks only" in (OracleDepth.__doc__ or "") and "never the default" in (OracleDepth.__doc__ or "")
    assert "benchmarks only" in (OracleNormals.__doc__ or "")
    assert set(ORACLE_LEVELS) == {"none", "mild", "realistic", "harsh"}
    p = PriorsParams(depth_backend="oracle", normal_backend="oracle", oracle_level="mild")
    assert PriorsParams().depth_backend != "oracle" and PriorsParams().normal_backend != "oracle"
    from wonderverse.errors import WonderError

    with pytest.raises(WonderError):
        make_depth_model(p)
    with pytest.raises(WonderError):
        make_normal_model(p)
    gt = GroundTruth(poses=np.tile(np.eye(4), (T, 1, 1)), depth=GT_DEPTH, normals=GT_NORMALS.astype(np.float16))
    dm = make_depth_model(p, gt)
    nm = make_normal_model(p, gt)
    assert isinstance(dm, OracleDepth) and isinstance(nm, OracleNormals)
    assert dm.predict(FRAMES).depth.shape == (T, H, W)
    assert nm.predict(FRAMES).normals.shape == (T, H, W, 3)


def _shifted_pair(z: float, offset: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A fronto-parallel wall at camera z `z` seen by two cameras at `offset`, the second moved right by one
    pixel's footprint on the wall: pixel column u of the first sees what column u - 1 of the second sees."""
    depth = np.full((2, H, W), z, dtype=np.float32)
    w2c = np.tile(np.eye(4), (2, 1, 1))
    step = z / K[0, 0]
    for i, centre in enumerate((offset, offset + np.array([step, 0.0, 0.0]))):
        w2c[i, :3, 3] = -centre  # identity rotation: t = -C
    return depth, w2c


@pytest.mark.parametrize("offset", [0.0, 1e6])
def test_world_fixed_error_is_the_same_on_a_surface_in_every_frame(offset: float) -> None:
    level = ORACLE_LEVELS["none"].model_copy(update={"world_warp_log_amp": 0.1})
    depth, w2c = _shifted_pair(5.0, np.array([offset, -offset, offset]))
    pred = OracleDepth(depth, level, "depth", seed=2, K=K, w2c=w2c).predict(FRAMES[:2]).depth
    sky_far = OracleDepth(depth, "none", "depth").predict(FRAMES[:2]).depth
    log_err = np.log(pred / sky_far)
    assert np.isfinite(log_err).all() and log_err.std() > 0.02  # an error, and not a constant one
    np.testing.assert_allclose(log_err[0][:, 1:], log_err[1][:, :-1], atol=2e-3 if offset else 1e-5)
    # the per-frame warp of the named levels is different in each frame: the same comparison fails for it
    warped = OracleDepth(depth, ORACLE_LEVELS["none"].model_copy(update={"warp_log_amp": 0.1}), "depth", seed=2)
    w_err = np.log(warped.predict(FRAMES[:2]).depth / sky_far)
    assert np.abs(w_err[0][:, 1:] - w_err[1][:, :-1]).max() > 0.02


def test_world_fixed_error_has_the_std_it_is_given_and_leaves_the_sky() -> None:
    depth = np.full((1, H, W), 80.0, dtype=np.float32)  # a wall ~150 m wide: many wavelengths of 1-4 m
    depth[0, :8] = np.inf
    level = ORACLE_LEVELS["none"].model_copy(update={"world_warp_log_amp": 0.05})
    pred = OracleDepth(depth, level, "depth", seed=5, K=K, w2c=np.eye(4)[None]).predict(FRAMES[:1]).depth[0]
    exact = OracleDepth(depth, "none", "depth").predict(FRAMES[:1]).depth[0]
    assert np.log(pred[8:] / exact[8:]).std() == pytest.approx(0.05, rel=0.3)
    np.testing.assert_array_equal(pred[:8], exact[:8])


def test_world_fixed_error_needs_the_cameras() -> None:
    level = ORACLE_LEVELS["realistic"].model_copy(update={"world_warp_log_amp": 0.05})
    with pytest.raises(ValueError, match="needs K"):
        OracleDepth(GT_DEPTH, level)
    with pytest.raises(ValueError, match="needs K"):
        OracleDepth(GT_DEPTH, level, K=K, w2c=np.eye(4)[None])
    with pytest.raises(ValueError, match="wavelengths"):
        level.model_validate(level.model_dump() | {"world_warp_wavelength_m": (2.0, 1.0)})

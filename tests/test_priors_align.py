"""align_scale_shift: exact recovery of known scale/shift (with outliers, in both spaces, dense or (u,v,z)
references) and fallbacks in words. Extremes (float16, 1e-3..1e4, constant and all-sky priors, never NaN) are
in test_extremes.py, which imports the helpers here."""

from __future__ import annotations

import numpy as np
import pytest

from wonderverse.priors import AlignParams, align_scale_shift, reference_samples

H, W = 40, 60


def scene_depth(rng: np.random.Generator, lo: float = 1.0, hi: float = 20.0) -> np.ndarray:
    """(H,W) camera z, log-uniform in [lo, hi]."""
    return np.exp(rng.uniform(np.log(lo), np.log(hi), (H, W)))


def sparse_reference(z: np.ndarray, rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """A dense map with NaN except at n random pixels, and the same points as (u, v, z) samples."""
    idx = rng.choice(z.size, n, replace=False)
    rows, cols = np.unravel_index(idx, z.shape)
    dense = np.full(z.shape, np.nan)
    dense[rows, cols] = z[rows, cols]
    uvz = np.stack([cols + rng.uniform(0, 1, n), rows + rng.uniform(0, 1, n), z[rows, cols]], axis=1)
    return dense, uvz


def add_outliers(ref: np.ndarray, rng: np.random.Generator, frac: float) -> np.ndarray:
    out = ref.copy()
    known = np.flatnonzero(np.isfinite(out))
    bad = rng.choice(known, int(frac * known.size), replace=False)
    out.flat[bad] *= rng.uniform(2.0, 5.0, bad.size)  # gross errors, all too far
    return out


def test_lstsq_recovers_scale_and_shift_in_depth_space() -> None:
    rng = np.random.default_rng(0)
    z = scene_depth(rng)
    a, b = 2.5, 0.7
    prior = (z - b) / a
    dense, _ = sparse_reference(z, rng, 300)
    r = align_scale_shift(prior, dense, space="depth", method="lstsq")
    assert r.ok and r.reason == ""
    assert r.scale == pytest.approx(a, rel=1e-9) and r.shift == pytest.approx(b, rel=1e-9)
    assert r.n_used == 300 and r.residual < 1e-6  # float32 output
    assert r.aligned_depth.dtype == np.float32 and r.aligned_depth.shape == (H, W)
    np.testing.assert_allclose(r.aligned_depth, z, rtol=1e-6)


@pytest.mark.parametrize("method", ["trimmed", "ransac"])
@pytest.mark.parametrize("space", ["depth", "inverse_depth"])
def test_robust_methods_ignore_outliers(method: str, space: str) -> None:
    rng = np.random.default_rng(1)
    z = scene_depth(rng)
    a, b = (3.0, -0.2) if space == "depth" else (0.8, 0.05)
    target = z if space == "depth" else 1.0 / z
    prior = (target - b) / a
    dense, _ = sparse_reference(z, rng, 400)
    noisy = add_outliers(dense, rng, 0.2)
    plain = align_scale_shift(prior, noisy, space=space, method="lstsq")
    r = align_scale_shift(prior, noisy, space=space, method=method, params=AlignParams(trim_fraction=0.3))
    assert r.ok
    assert r.scale == pytest.approx(a, rel=1e-6)
    assert r.shift == pytest.approx(b, rel=1e-6, abs=1e-9)
    np.testing.assert_allclose(r.aligned_depth, z, rtol=1e-5)
    assert r.residual < 1e-6 and plain.residual > 1e-3  # the outliers do hurt plain least squares
    assert 0.6 * 400 <= r.n_used <= 0.8 * 400 + 1


def test_dense_and_uvz_references_agree() -> None:
    rng = np.random.default_rng(2)
    z = scene_depth(rng)
    prior = 1.0 / z * 3.0 + 0.1
    dense, uvz = sparse_reference(z, rng, 200)
    r1 = align_scale_shift(prior, dense, space="inverse_depth", method="lstsq")
    r2 = align_scale_shift(prior, uvz, space="inverse_depth", method="lstsq")
    assert r1.ok and r2.ok and r1.n_used == r2.n_used == 200
    assert r1.scale == pytest.approx(r2.scale, rel=1e-12) and r1.shift == pytest.approx(r2.shift, abs=1e-12)
    np.testing.assert_allclose(r1.aligned_depth, z, rtol=1e-5)
    # samples off the image or without a positive depth are dropped
    junk = np.array([[-1.0, 5.0, 2.0], [W + 0.5, 5.0, 2.0], [3.2, 4.7, np.nan], [3.2, 4.7, -1.0], [3.2, 4.7, 0.0]])
    rows, _, _ = reference_samples(np.vstack([uvz, junk]), (H, W))
    assert rows.size == 200
    rows1, cols1, _ = reference_samples(uvz[:1], (H, W))
    assert (rows1[0], cols1[0]) == (int(uvz[0, 1]), int(uvz[0, 0]))


def test_mask_excludes_pixels_from_the_fit() -> None:
    rng = np.random.default_rng(3)
    z = scene_depth(rng)
    prior = z / 4.0
    ref = z.copy()
    ref[:, :10] *= 3.0  # wrong reference where the mask says "do not use" (e.g. sky, moving objects)
    mask = np.ones((H, W), dtype=bool)
    mask[:, :10] = False
    r = align_scale_shift(prior, ref, mask=mask, method="lstsq")
    assert r.ok and r.scale == pytest.approx(4.0, rel=1e-9) and r.shift == pytest.approx(0.0, abs=1e-9)
    assert r.n_used == H * (W - 10)
    np.testing.assert_allclose(r.aligned_depth, z, rtol=1e-6)  # masked pixels are still aligned


def test_too_few_points_falls_back_to_median_ratio() -> None:
    rng = np.random.default_rng(6)
    z = scene_depth(rng)
    prior = z / 2.0
    dense, _ = sparse_reference(z, rng, 5)
    r = align_scale_shift(prior, dense, params=AlignParams(min_points=20))
    assert not r.ok and "5 usable reference points" in r.reason
    assert r.scale == pytest.approx(2.0, rel=1e-9) and r.shift == 0.0
    assert np.isfinite(r.aligned_depth).all() and (r.aligned_depth > 0).all()


def test_negative_scale_is_refused() -> None:
    rng = np.random.default_rng(9)
    z = scene_depth(rng)
    prior = -z + 30.0  # anti-correlated: a depth map handed over as if it were disparity
    r = align_scale_shift(prior, z, space="depth", method="lstsq")
    assert not r.ok and "negative scale" in r.reason
    assert r.scale > 0 and r.shift == 0.0
    assert np.isfinite(r.aligned_depth).all() and (r.aligned_depth > 0).all()


def test_non_positive_inverse_depth_goes_to_the_far_clamp() -> None:
    rng = np.random.default_rng(10)
    z = scene_depth(rng, 2.0, 10.0)
    prior = 1.0 / z
    prior[:5] = -0.3  # sky region that the fit maps to negative disparity
    ref = z.copy()
    ref[:5] = np.nan
    r = align_scale_shift(prior, ref, space="inverse_depth", method="lstsq")
    assert r.ok
    far = z[5:].max() * AlignParams().depth_clamp_ratio
    np.testing.assert_allclose(r.aligned_depth[:5], far, rtol=1e-6)
    assert r.n_clamped >= 5 * W
    np.testing.assert_allclose(r.aligned_depth[5:], z[5:], rtol=1e-5)


def test_bad_arguments() -> None:
    with pytest.raises(ValueError):
        align_scale_shift(np.ones((H, W)), np.ones((H, W)), space="disparity")  # type: ignore[arg-type]
    with pytest.raises(ValueError):
        align_scale_shift(np.ones((H, W)), np.ones((H + 1, W + 1)))
    with pytest.raises(ValueError):
        align_scale_shift(np.ones((H, W)), np.ones((H, W)), mask=np.ones((3, 3), bool))


def test_project_points_gives_pixels_and_depth_in_front_only() -> None:
    from wonderverse.camera import look_at
    from wonderverse.priors import project_points

    K = np.array([[50.0, 0, W / 2], [0, 50.0, H / 2], [0, 0, 1]])
    w2c = look_at(np.array([0.0, 0, 1]), np.array([0.0, 5, 1]))  # looking along world +y, image up = +z
    pts = np.array([[0.0, 4, 1], [1.0, 2, 1], [0.0, -3, 1], [0.0, 2, 2]])  # the third is behind the camera
    uvz = project_points(pts, w2c, K)
    np.testing.assert_allclose(uvz, [[W / 2, H / 2, 4], [W / 2 + 25, H / 2, 2], [W / 2, H / 2 - 25, 2]], atol=1e-12)


def test_align_frames_recovers_each_frames_scale_and_shift_and_marks_sky() -> None:
    from wonderverse.camera import invert_se3, look_at
    from wonderverse.priors import align_frames

    rng = np.random.default_rng(3)
    K = np.array([[50.0, 0, W / 2], [0, 50.0, H / 2], [0, 0, 1]])
    z = 2.0 + 0.05 * np.arange(H)[:, None] + 0.02 * np.arange(W)[None, :]  # a slanted wall, camera z
    pose = look_at(np.array([1.0, -2, 1]), np.array([1.5, 3, 1.2]))
    rows, cols = rng.integers(8, H, 200), rng.integers(0, W, 200)  # SfM points below the sky band
    cam = np.stack([(cols + 0.5 - K[0, 2]) / K[0, 0], (rows + 0.5 - K[1, 2]) / K[1, 1], np.ones(200)], -1)
    cam *= z[rows, cols, None]
    points = cam @ invert_se3(pose)[:3, :3].T + invert_se3(pose)[:3, 3]
    a, b = np.array([0.5, 2.0, 1.0]), np.array([0.3, -0.1, 0.0])
    prior = (z[None] - b[:, None, None]) / a[:, None, None]  # a * prior + b = z in depth space
    prior[:, :5] = (100.0 - b[:, None, None]) / a[:, None, None]  # the top rows: far beyond every point (sky)
    poses = np.stack([pose, pose, np.full((4, 4), np.nan)])  # frame 2 has no global pose
    out = align_frames(prior, "depth", poses, points, K, AlignParams(), sky_beyond_ref=4.0)
    np.testing.assert_allclose(out.scale[:2], a[:2], rtol=1e-9)
    np.testing.assert_allclose(out.shift[:2], b[:2], atol=1e-9)
    np.testing.assert_allclose(out.depth[:2, 5:], np.broadcast_to(z[5:], (2, H - 5, W)), rtol=1e-5)
    assert np.isposinf(out.depth[:2, :5]).all()  # sky: beyond 4 x the farthest point seen
    assert out.ok.tolist() == [True, True, False] and out.depth.dtype == np.float32
    assert len(out.reasons) == 1 and out.reasons[0].startswith("frame 2: ")
    np.testing.assert_allclose(out.depth[2], prior[2], rtol=1e-6)  # no reference: the prior as depth, no sky rule


def test_the_default_sky_rule_finds_the_realistic_oracles_sky_in_procedural_frames() -> None:
    """The priors step's sky rule against the procedural truth: the realistic oracle (like a monocular network)
    puts the sky far away, not at infinity; SfM points come from corner features, as SIFT's would. With the
    default `sky_beyond_ref` most true sky becomes +inf and no true surface does; at the former default (4)
    most of the sky stayed a far surface, which the splats then painted and the mesh fused."""
    from benchmarks.enhancement import FEATURE_SHARE, corner_mask
    from wonderverse.config import PriorsStepParams
    from wonderverse.priors import align_frames
    from wonderverse.priors.oracle import OracleDepth
    from wonderverse.video.procedural import ProceduralVideo, demo_path

    video = ProceduralVideo("a small house decorated for Christmas", 0, 160, 112, 60.0, {"fault_probability": 0.0})
    path = demo_path(video.world.start_pose(), 6, yaw_deg=20.0, forward_m=1.0)
    vid = video.generate("", path, 0, None)
    depth, K = vid.gt.depth, vid.K
    points = []
    for t in range(len(depth)):
        v, u = np.nonzero(corner_mask(vid.frames[t], FEATURE_SHARE) & np.isfinite(depth[t]))
        z = depth[t, v, u].astype(np.float64)
        cam = np.stack([(u + 0.5 - K[0, 2]) / K[0, 0] * z, (v + 0.5 - K[1, 2]) / K[1, 1] * z, z], -1)
        points.append((cam - path[t, :3, 3]) @ path[t, :3, :3])
    points = np.concatenate(points)
    pred = OracleDepth(depth, "realistic", "inverse_depth", seed=1).predict(vid.frames)
    sky = np.isinf(depth)
    assert 0.05 < sky.mean() < 0.5  # the scene shows sky

    def marked(k: float) -> tuple[float, float]:
        out = align_frames(pred.depth, pred.kind, path, points, K, AlignParams(), sky_beyond_ref=k)
        return float(np.isinf(out.depth[sky]).mean()), float(np.isinf(out.depth[~sky]).mean())

    recall, wrong = marked(PriorsStepParams().sky_beyond_ref)
    before = marked(4.0)[0]  # the former default
    # seen: 66 % of the sky marked, 0.01 % of the surfaces; 5 % of the sky at 4
    assert recall > 0.6 and wrong < 0.005 and recall > 3 * before, (recall, wrong, before)

"""GaussianModel, initialisation, SH evaluation and scene normalisation."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from wonderverse.camera import look_at, quat_from_matrix, quat_multiply
from wonderverse.splats.model import (
    SH_C0,
    GaussianModel,
    eval_sh,
    init_from_points,
    normalization_from_cameras,
    num_sh_bases,
    quat_to_rotmat,
    sh_basis,
    sh_colors,
    sh_rotation_matrices,
    sh_to_rgb,
    voxel_downsample,
)


def fibonacci_sphere(n: int) -> np.ndarray:
    i = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * i / n)
    theta = math.pi * (1 + 5**0.5) * i
    return np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], axis=1)


def test_sh_basis_is_orthonormal_on_the_sphere() -> None:
    # Independent check of every constant and sign-free shape: the real SH basis up to degree 3 must be
    # orthonormal under the uniform measure (integral over the sphere = 4*pi * mean over a uniform grid).
    d = torch.from_numpy(fibonacci_sphere(40000))
    Y = sh_basis(3, d).numpy()
    gram = 4 * math.pi * (Y.T @ Y) / len(Y)
    np.testing.assert_allclose(gram, np.eye(16), atol=2e-3)


def test_sh_degree1_signs_follow_inria() -> None:
    # INRIA: result = C0*sh0 - C1*y*sh1 + C1*z*sh2 - C1*x*sh3.
    coeffs = torch.zeros(4, 3)
    coeffs[1:, 0] = torch.tensor([1.0, 2.0, 3.0])
    d = torch.tensor([0.2, -0.3, 0.5])
    val = eval_sh(1, coeffs, d)
    u = d / d.norm()
    expect = 0.4886025119029199 * (-u[1] * 1.0 + u[2] * 2.0 - u[0] * 3.0)
    assert val[0].item() == pytest.approx(expect.item(), rel=1e-6)
    assert val[1].item() == 0.0


def test_sh_colors_dc_and_clamp() -> None:
    coeffs = torch.zeros(2, 16, 3)
    coeffs[0, 0] = torch.tensor([0.3, -0.5, 1.0]) / SH_C0
    coeffs[1, 0] = -5.0
    rgb = sh_colors(3, coeffs, torch.randn(2, 3))
    np.testing.assert_allclose(rgb[0].numpy(), [0.8, 0.0, 1.5], atol=1e-6)
    assert torch.all(rgb[1] == 0.0)
    # A lower active degree ignores the higher coefficients.
    coeffs[0, 5:] = 7.0
    np.testing.assert_allclose(sh_colors(1, coeffs, torch.randn(2, 3))[0].numpy(), [0.8, 0.0, 1.5], atol=1e-6)
    with pytest.raises(ValueError):
        eval_sh(2, torch.zeros(3, 4, 3), torch.randn(3, 3))
    assert torch.isfinite(eval_sh(3, coeffs, torch.zeros(2, 3))).all()


def test_quaternions_match_scipy_and_zero_is_identity() -> None:
    q = torch.randn(50, 4, dtype=torch.float64) * 3
    R = quat_to_rotmat(q).numpy()
    qn = q.numpy() / np.linalg.norm(q.numpy(), axis=1, keepdims=True)
    ref = Rotation.from_quat(qn[:, [1, 2, 3, 0]]).as_matrix()
    np.testing.assert_allclose(R, ref, atol=1e-12)
    np.testing.assert_allclose(quat_to_rotmat(torch.zeros(1, 4)).numpy()[0], np.eye(3))
    for Rm in ref[:10]:
        np.testing.assert_allclose(quat_to_rotmat(torch.from_numpy(quat_from_matrix(Rm))).numpy(), Rm, atol=1e-12)
    a, b = Rotation.random(2, random_state=3)
    qa, qb = (r.as_quat()[[3, 0, 1, 2]] for r in (a, b))
    qab = torch.from_numpy(quat_multiply(qa, qb))
    np.testing.assert_allclose(quat_to_rotmat(qab).numpy(), (a * b).as_matrix(), atol=1e-12)


def test_sh_rotation_rotates_the_radiance_function() -> None:
    R = Rotation.random(random_state=7).as_matrix()
    rng = np.random.default_rng(0)
    c = rng.normal(size=(16,))
    mats = sh_rotation_matrices(R, 3)
    c_rot = c.copy()
    for band, D in enumerate(mats, start=1):
        sl = slice(band * band, (band + 1) ** 2)
        c_rot[sl] = D @ c[sl]
    d = fibonacci_sphere(200)
    f_rot = sh_basis(3, torch.from_numpy(d)).numpy() @ c_rot
    f_ref = sh_basis(3, torch.from_numpy(d @ R)).numpy() @ c  # f(R^T d)
    np.testing.assert_allclose(f_rot, f_ref, atol=1e-10)


def test_init_from_points_grid() -> None:
    g = np.stack(np.meshgrid(*[np.arange(6) * 0.1] * 3, indexing="ij"), -1).reshape(-1, 3)
    cols = np.tile(np.array([[255, 0, 128]], dtype=np.uint8), (len(g), 1))
    m = init_from_points(g, cols, sh_degree=2)
    assert m.num_gaussians == 216 and m.shN.shape == (216, 8, 3) and m.means.dtype == torch.float32
    interior = np.all((g > 0.05) & (g < 0.45), axis=1)
    np.testing.assert_allclose(m.scales.detach().numpy()[interior], 0.1, rtol=1e-5)
    np.testing.assert_allclose(m.opacities.detach().numpy(), 0.1, rtol=1e-5)
    np.testing.assert_allclose(sh_to_rgb(m.sh0[:, 0]).detach().numpy()[0], [1.0, 0.0, 128 / 255], atol=1e-6)
    np.testing.assert_array_equal(quat_to_rotmat(m.quats).detach().numpy()[0], np.eye(3))
    assert torch.all(m.shN == 0)


def test_init_scales_count_the_neighbours_they_join() -> None:
    # two seeds 1 apart, each 0.01 from an existing Gaussian: sized by the existing ones, not by each other
    seeds = np.array([[0.0, 0, 0], [1.0, 0, 0]])
    old = seeds + np.array([0.0, 0.01, 0.0])
    alone = init_from_points(seeds, np.zeros((2, 3)), sh_degree=0, knn_k=1)
    joined = init_from_points(seeds, np.zeros((2, 3)), sh_degree=0, knn_k=1, neighbours=old)
    np.testing.assert_allclose(alone.scales.detach().numpy(), 1.0, rtol=1e-6)
    np.testing.assert_allclose(joined.scales.detach().numpy(), 0.01, rtol=1e-4)
    one = init_from_points(seeds[:1], np.zeros((1, 3)), sh_degree=0, neighbours=old[:1], knn_k=3)
    np.testing.assert_allclose(one.scales.detach().numpy(), 0.01, rtol=1e-4)  # a lone seed with a neighbour


def test_voxel_downsample_averages_per_voxel() -> None:
    pts = np.array([[0.1, 0.1, 0.1], [0.3, 0.3, 0.3], [1.2, 0.1, 0.1], [1.4, 0.1, 0.1], [-0.5, 0, 0]])
    cols = np.array([[0, 0, 0], [1, 1, 1], [0, 0, 0], [0, 0, 1], [1, 0, 0]], float)
    p, c = voxel_downsample(pts, cols, 1.0)
    np.testing.assert_allclose(p, [[0.2, 0.2, 0.2], [1.3, 0.1, 0.1], [-0.5, 0, 0]])
    np.testing.assert_allclose(c, [[0.5, 0.5, 0.5], [0, 0, 0.5], [1, 0, 0]])
    same, _ = voxel_downsample(pts, None, 0.0)
    np.testing.assert_array_equal(same, pts)


def test_model_shapes_and_numpy_roundtrip() -> None:
    m = init_from_points(np.random.default_rng(0).normal(size=(30, 3)), np.full((30, 3), 0.2), sh_degree=3)
    arrays = m.to_numpy()
    assert {k: v.dtype for k, v in arrays.items()} == {k: np.float32 for k in GaussianModel.PARAM_NAMES}
    back = GaussianModel.from_numpy(arrays)
    assert back.sh_degree == 3
    for k in GaussianModel.PARAM_NAMES:
        assert torch.equal(getattr(back, k), getattr(m, k))
    with pytest.raises(ValueError):
        z = torch.zeros
        GaussianModel(z(3, 3), z(2, 4), z(3, 3), z(3), z(3, 1, 3), z(3, 0, 3), 0)
    assert GaussianModel.empty(2).shN.shape == (0, num_sh_bases(2) - 1, 3)


def test_normalization_single_camera_uses_points() -> None:
    w2c = look_at(np.array([10.0, 0, 0]), np.array([20.0, 0, 0]))[None]
    pts = np.array([[12.0, 0, 0], [14.0, 0, 0], [18.0, 0, 0]])
    norm = normalization_from_cameras(w2c, pts)
    assert norm.s == pytest.approx(1 / 4.0)
    assert normalization_from_cameras(w2c).s == 1.0

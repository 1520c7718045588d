"""The torch rasteriser against an independent brute-force float64 reference, plus conventions. Extremes (tiny
and huge scales, far coordinates, near plane, zero quaternions, saturated opacity) are in test_extremes.py."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from wonderverse.camera import intrinsics, look_at
from wonderverse.splats.model import sh_colors
from wonderverse.splats.render_torch import render

W, H = 64, 48


@pytest.fixture(autouse=True)
def one_thread():
    # On a shared 2-core machine two OpenMP threads spin-wait for each other: tiny images run much faster
    # on one thread.
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


# ------------------------------------------------------------------------------------------- reference


def reference_render(
    means: np.ndarray,
    quats: np.ndarray,
    scales: np.ndarray,
    opac: np.ndarray,
    colors: np.ndarray,
    viewmat: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    near: float = 0.01,
    far: float = 1e10,
    background: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """gsplat 1.5.3 semantics written out directly: no tiles, no boxes, every Gaussian at every pixel.

    Float64 NumPy; rotations via scipy; Gaussians composited one at a time front to back over all
    pixels at once. Returns rgb (H,W,3), depth (H,W,1) = Σ w z, alpha (H,W,1), normals (H,W,3).
    """
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    Rv, tv = viewmat[:3, :3], viewmat[:3, 3]
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    rgb = np.zeros((height, width, 3))
    depth = np.zeros((height, width, 1))
    nrm = np.zeros((height, width, 3))
    T = np.ones((height, width))
    done = np.zeros((height, width), bool)
    mc_all = means @ Rv.T + tv
    for i in np.argsort(mc_all[:, 2], kind="stable"):
        x, y, z = mc_all[i]
        if not near <= z <= far:
            continue
        q = quats[i] / np.linalg.norm(quats[i]) if np.linalg.norm(quats[i]) > 0 else np.array([1.0, 0, 0, 0])
        Rg = Rotation.from_quat(q[[1, 2, 3, 0]]).as_matrix()
        cov_c = Rv @ Rg @ np.diag(scales[i] ** 2) @ Rg.T @ Rv.T
        limx_p, limx_n = (width - cx) / fx + 0.3 * width / (2 * fx), cx / fx + 0.3 * width / (2 * fx)
        limy_p, limy_n = (height - cy) / fy + 0.3 * height / (2 * fy), cy / fy + 0.3 * height / (2 * fy)
        xc = z * np.clip(x / z, -limx_n, limx_p)
        yc = z * np.clip(y / z, -limy_n, limy_p)
        J = np.array([[fx / z, 0, -fx * xc / z**2], [0, fy / z, -fy * yc / z**2]])
        cov2 = J @ cov_c @ J.T + 0.3 * np.eye(2)
        if np.linalg.det(cov2) <= 0:
            continue
        P = np.linalg.inv(cov2)
        dx = fx * x / z + cx - u
        dy = fy * y / z + cy - v
        sigma = 0.5 * (P[0, 0] * dx * dx + P[1, 1] * dy * dy) + P[0, 1] * dx * dy
        a = np.minimum(0.999, opac[i] * np.exp(-sigma))
        n = Rv @ Rg[:, np.argmin(scales[i])]
        n = -n if n @ mc_all[i] > 0 else n
        live = (a >= 1 / 255) & (sigma >= 0) & ~done
        next_T = T * (1 - a)
        stop = live & (next_T <= 1e-4)
        done |= stop
        draw = live & ~stop
        w = np.where(draw, a * T, 0.0)
        rgb += w[..., None] * colors[i]
        depth += w[..., None] * z
        nrm += w[..., None] * n
        T = np.where(draw, next_T, T)
    if background is not None:
        rgb += T[..., None] * background
    return rgb, depth, (1 - T)[..., None], nrm


def random_scene(n: int, seed: int, dtype: torch.dtype = torch.float64, sigma_px: float = 3.0) -> dict:
    """n Gaussians in front of a camera at the origin looking down +z, image-filling, random shapes."""
    g = torch.Generator().manual_seed(seed)
    K = torch.tensor(intrinsics(W, H, 60.0), dtype=dtype)
    fx = float(K[0, 0])
    z = torch.rand(n, generator=g, dtype=dtype) * 4 + 2
    x = (torch.rand(n, generator=g, dtype=dtype) * 2.4 - 1.2) * z * (W / 2) / fx
    y = (torch.rand(n, generator=g, dtype=dtype) * 2.4 - 1.2) * z * (H / 2) / fx
    return {
        "means": torch.stack([x, y, z], 1),
        "quats": torch.randn(n, 4, generator=g, dtype=dtype),
        "scales": z[:, None] * sigma_px / fx * torch.exp(0.6 * torch.randn(n, 3, generator=g, dtype=dtype)),
        "opacities": torch.rand(n, generator=g, dtype=dtype) * 0.9 + 0.05,
        "colors": torch.rand(n, 3, generator=g, dtype=dtype),
        "viewmat": torch.eye(4, dtype=dtype),
        "K": K,
    }


def run_torch(scene: dict, **kw) -> tuple[torch.Tensor, ...]:
    s = scene
    return render(s["means"], s["quats"], s["scales"], s["opacities"], s["colors"], s["viewmat"], s["K"], W, H, **kw)


def run_reference(scene: dict, **kw) -> tuple[np.ndarray, ...]:
    s = {k: v.detach().double().numpy() for k, v in scene.items()}
    return reference_render(
        s["means"], s["quats"], s["scales"], s["opacities"], s["colors"], s["viewmat"], s["K"], W, H, **kw
    )


# ------------------------------------------------------------------------------------------- forward


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_forward_matches_brute_force_reference(dtype: torch.dtype) -> None:
    scene = random_scene(300, seed=1, dtype=dtype)
    bg = np.array([0.1, 0.5, 0.9])
    rgb, depth, alpha, normals, info = run_torch(scene, background=torch.tensor(bg, dtype=dtype))
    ref = run_reference(scene, background=bg)
    tol = 1e-9 if dtype == torch.float64 else 2e-4
    for out, r, name in zip((rgb, depth, alpha, normals), ref, ("rgb", "depth", "alpha", "normals"), strict=True):
        assert out.shape == r.shape, name
        np.testing.assert_allclose(out.detach().double().numpy(), r, atol=tol * max(1.0, np.abs(r).max()), err_msg=name)
    # The scene is dense enough to exercise the stop rule and many overlaps per pixel.
    assert alpha.min() > 0.5 and info["n_pairs"] > 5 * W * H
    assert info["radii"].shape == (300, 2) and info["radii"].dtype == torch.int32
    assert info["visible"].sum() > 200


def test_rendering_without_autograd_gives_the_same_image() -> None:
    # Outside autograd the compositing keeps nothing for a backward pass; the image must not change.
    scene = random_scene(300, seed=3)
    scene["means"].requires_grad_(True)
    with_grad = run_torch(scene)
    with torch.no_grad():
        without = run_torch(scene)
    assert with_grad[0].requires_grad and not without[0].requires_grad
    for a, b in zip(with_grad[:4], without[:4], strict=True):
        assert torch.equal(a.detach(), b)
    assert with_grad[4]["n_pairs"] == without[4]["n_pairs"] > 0


@pytest.mark.parametrize("tile_size", [4, 8, 16, 32])
def test_tile_size_does_not_change_the_image(tile_size: int) -> None:
    scene = random_scene(200, seed=2)
    base = run_torch(scene, tile_size=16)
    out = run_torch(scene, tile_size=tile_size)
    for a, b in zip(base[:4], out[:4], strict=True):
        np.testing.assert_allclose(a.numpy(), b.numpy(), atol=1e-12)


def test_pixel_centres_at_half_integers() -> None:
    # Principal point at (20.5, 13.5), the centre of pixel (20, 13); a small isotropic Gaussian on the
    # optical axis projects there (and its Jacobian has no off-axis terms).
    K = torch.tensor([[50.0, 0, 20.5], [0, 50.0, 13.5], [0, 0, 1]], dtype=torch.float64)
    z = 3.0
    scene = {
        "means": torch.tensor([[0.0, 0.0, z]], dtype=torch.float64),
        "quats": torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64),
        "scales": torch.full((1, 3), 1.2 * z / 50.0, dtype=torch.float64),
        "opacities": torch.tensor([0.9], dtype=torch.float64),
        "colors": torch.ones(1, 3, dtype=torch.float64),
        "viewmat": torch.eye(4, dtype=torch.float64),
        "K": K,
    }
    _, _, alpha, _, info = run_torch(scene)
    a = alpha[..., 0]
    assert tuple(np.unravel_index(int(a.argmax()), a.shape)) == (13, 20)
    np.testing.assert_allclose(info["means2d"][0, 0].detach().numpy(), [20.5, 13.5], atol=1e-12)
    # Peak alpha = opacity; one pixel away the 2D variance is 1.2^2 px^2 plus eps2d = 0.3 px^2.
    assert a[13, 20].item() == pytest.approx(0.9, rel=1e-12)
    for v, u in ((13, 19), (13, 21), (12, 20), (14, 20)):
        assert a[v, u].item() == pytest.approx(0.9 * np.exp(-0.5 / (1.44 + 0.3)), rel=1e-12)
    assert a[14, 21].item() == pytest.approx(0.9 * np.exp(-1.0 / (1.44 + 0.3)), rel=1e-12)


def test_depth_and_normals_of_a_flat_wall() -> None:
    # A grid of flat, opaque discs on the plane z = 4 (normals along -z once facing the camera).
    gx, gy = np.meshgrid(np.linspace(-4, 4, 33), np.linspace(-3, 3, 25))
    n = gx.size
    rot = Rotation.from_euler("x", 180, degrees=True).as_quat()[[3, 0, 1, 2]]  # flips the disc's axis
    scene = {
        "means": torch.tensor(np.stack([gx.ravel(), gy.ravel(), np.full(n, 4.0)], 1)),
        "quats": torch.tensor(np.tile(rot, (n, 1))),
        "scales": torch.tensor(np.tile([0.25, 0.25, 1e-4], (n, 1))),
        "opacities": torch.full((n,), 0.99, dtype=torch.float64),
        "colors": torch.full((n, 3), 0.5, dtype=torch.float64),
        "viewmat": torch.eye(4, dtype=torch.float64),
        "K": torch.tensor(intrinsics(W, H, 60.0)),
    }
    _, depth, alpha, normals, _ = run_torch(scene)
    assert alpha.min().item() > 0.999
    np.testing.assert_allclose((depth / alpha).numpy(), 4.0, atol=1e-9)
    np.testing.assert_allclose((normals / alpha).numpy(), np.broadcast_to([0, 0, -1.0], normals.shape), atol=1e-9)


def test_sh_colors_follow_view_direction() -> None:
    scene = random_scene(100, seed=3)
    g = torch.Generator().manual_seed(5)
    sh = torch.randn(100, 16, 3, generator=g, dtype=torch.float64) * 0.3
    pose = torch.tensor(look_at(np.array([0.3, -0.2, -1.0]), np.array([0.0, 0.0, 4.0])))
    scene["viewmat"] = pose
    campos = -pose[:3, :3].T @ pose[:3, 3]
    rgb_sh = render(
        scene["means"], scene["quats"], scene["scales"], scene["opacities"], sh, pose, scene["K"], W, H, sh_degree=3
    )[0]
    scene["colors"] = sh_colors(3, sh, scene["means"] - campos)
    np.testing.assert_allclose(rgb_sh.numpy(), run_torch(scene)[0].numpy(), atol=1e-12)
    np.testing.assert_allclose(rgb_sh.numpy(), run_reference(scene)[0], atol=1e-9)


# ------------------------------------------------------------------------------------------- gradients


def _loss_weights(seed: int) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [rng.normal(size=(H, W, c)) for c in (3, 1, 1, 3)]


def test_gradients_match_finite_differences_of_the_reference() -> None:
    scene = random_scene(60, seed=4, sigma_px=4.0)
    weights = _loss_weights(0)
    bg = np.array([0.2, 0.3, 0.4])
    params = {k: scene[k].clone().requires_grad_() for k in ("means", "quats", "scales", "opacities", "colors")}
    out = render(**params, viewmat=scene["viewmat"], K=scene["K"], width=W, height=H, background=torch.tensor(bg))[:4]
    info = render(**params, viewmat=scene["viewmat"], K=scene["K"], width=W, height=H)[4]
    loss = sum((o * torch.from_numpy(w)).sum() for o, w in zip(out, weights, strict=True))
    loss.backward()

    def ref_loss(s: dict) -> float:
        outs = run_reference(s, background=bg)
        return float(sum((o * w).sum() for o, w in zip(outs, weights, strict=True)))

    # Gaussians that are drawn, and one coordinate of each parameter kind (central differences).
    visible = torch.nonzero(info["visible"])[:, 0][:6].tolist()
    checked = 0
    for i in visible:
        for name, j in (("means", 0), ("means", 2), ("quats", 1), ("scales", 0), ("opacities", None), ("colors", 2)):
            idx = (i,) if j is None else (i, j)
            eps = 1e-6 * max(1.0, abs(scene[name][idx].item()))
            plus = {k: v.clone() for k, v in scene.items()}
            minus = {k: v.clone() for k, v in scene.items()}
            plus[name][idx] += eps
            minus[name][idx] -= eps
            fd = (ref_loss(plus) - ref_loss(minus)) / (2 * eps)
            an = params[name].grad[idx].item()
            assert an == pytest.approx(fd, rel=1e-4, abs=1e-5), (name, idx)
            checked += 1
    assert checked == 36


def test_gradcheck_on_a_tiny_scene() -> None:
    scene = random_scene(6, seed=6, sigma_px=6.0)
    vm, K = scene["viewmat"], scene["K"]

    def f(means, quats, scales, opacities, colors):
        rgb, depth, alpha, normals, _ = render(
            means,
            quats,
            scales,
            opacities,
            colors,
            vm,
            K,
            24,
            16,
            background=torch.tensor([0.3, 0.2, 0.1], dtype=torch.float64),
        )
        return rgb, depth, alpha, normals

    # Move the Gaussians into the 24x16 image.
    scene["means"][:, :2] *= 0.3
    inputs = tuple(scene[k].clone().requires_grad_() for k in ("means", "quats", "scales", "opacities", "colors"))
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=True)


def test_means2d_gradient_is_exposed() -> None:
    scene = random_scene(50, seed=7, dtype=torch.float32)
    means = scene["means"].clone().requires_grad_()
    rgb, *_, info = render(
        means, scene["quats"], scene["scales"], scene["opacities"], scene["colors"], scene["viewmat"], scene["K"], W, H
    )
    info["means2d"].retain_grad()
    rgb.sum().backward()
    assert info["means2d"].grad is not None and info["means2d"].grad.shape == (1, 50, 2)
    g2d = info["means2d"].grad[0]
    assert (g2d[info["visible"]].abs().sum(1) > 0).float().mean() > 0.8
    assert torch.all(g2d[~info["visible"]] == 0)


# ------------------------------------------------------------------------------------------- extremes


def _finite(*ts: torch.Tensor) -> bool:
    return all(bool(torch.isfinite(t).all()) for t in ts)


def _render_and_grad(means, quats, scales, opacities, colors, viewmat, K, **kw):
    params = [t.clone().requires_grad_() for t in (means, quats, scales, opacities, colors)]
    rgb, depth, alpha, normals, info = render(*params, viewmat, K, W, H, **kw)
    (rgb.sum() + depth.sum() + alpha.sum() + normals.sum()).backward()
    grads = [p.grad if p.grad is not None else torch.zeros_like(p) for p in params]
    return (rgb, depth, alpha, normals), grads, info


def test_no_gaussians_renders_the_background() -> None:
    z = torch.zeros
    bg = torch.tensor([0.2, 0.4, 0.6])
    (rgb, depth, alpha, normals), grads, info = _render_and_grad(
        z(0, 3), z(0, 4), z(0, 3), z(0), z(0, 3), torch.eye(4), torch.tensor(intrinsics(W, H, 60.0)), background=bg
    )
    assert torch.allclose(rgb, bg.expand(H, W, 3)) and torch.all(alpha == 0) and torch.all(depth == 0)
    assert torch.all(normals == 0) and info["radii"].shape == (0, 2)
    assert all(g.numel() == 0 for g in grads)


def test_make_renderer_backends_on_the_cpu() -> None:
    from wonderverse.errors import WonderError
    from wonderverse.splats.renderer import make_renderer

    assert make_renderer("torch").name == "torch"
    if not torch.cuda.is_available():
        assert make_renderer("auto").name == "torch"
        with pytest.raises(WonderError, match="gsplat"):
            make_renderer("gsplat")
    with pytest.raises(WonderError):
        make_renderer("vulkan")  # type: ignore[arg-type]


def test_gsplat_backends_hand_written_normals_match_autograd_of_the_torch_normals() -> None:
    # The gsplat backend's normals (a custom autograd function, here on the CPU) against
    # `gaussian_normals` differentiated by autograd, including zero and near-zero quaternions.
    from wonderverse.splats.render_gsplat import _CameraNormals
    from wonderverse.splats.render_torch import gaussian_normals

    g = torch.Generator().manual_seed(0)
    n = 400
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    quats[0] = 0.0
    quats[1] = torch.tensor([1e-7, 0.0, 0.0, 0.0])
    scales = torch.rand(n, 3, generator=g, dtype=torch.float64)
    means = torch.randn(n, 3, generator=g, dtype=torch.float64) * 2 + torch.tensor([0.0, 0.0, 4.0])
    viewmat = torch.tensor(look_at([0.1, -0.1, -0.2], [0.0, 0.0, 4.0]))
    weights = torch.randn(n, 3, generator=g, dtype=torch.float64)
    q_ours, q_ref = quats.clone().requires_grad_(), quats.clone().requires_grad_()
    ours = _CameraNormals.apply(q_ours, scales, means, viewmat)
    means_c = means @ viewmat[:3, :3].T + viewmat[:3, 3]
    ref = gaussian_normals(q_ref, scales, viewmat, means_c)
    (ours * weights).sum().backward()
    (ref * weights).sum().backward()
    torch.testing.assert_close(ours, ref, rtol=0, atol=1e-12)
    torch.testing.assert_close(q_ours.grad, q_ref.grad, rtol=0, atol=1e-12)
    assert torch.equal(q_ours.grad[0], torch.zeros(4))  # the zero quaternion: identity, no gradient
    assert ((ours * means_c).sum(-1) <= 0).all()  # every normal faces its camera
    assert torch.autograd.gradcheck(
        lambda q: _CameraNormals.apply(q, scales[2:30], means[2:30], viewmat), (quats[2:30].clone().requires_grad_(),)
    )

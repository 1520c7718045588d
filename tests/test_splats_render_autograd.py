"""The rasteriser's hand-written compositing backward against autograd through a plain compositor.

`render` composites with a custom autograd Function (chunked, analytic backward). Here the same projection
feeds a straightforward differentiable compositor (every Gaussian at every pixel, front to back, gsplat's
rules written with torch.where), and autograd's gradients of a random loss are the ground truth. Both
compositors are compared: the C++ kernel and the vectorised torch one, whose chunking and dropping of undrawn
pairs are forced on and off so every path is compared.
"""

from __future__ import annotations

import pytest
import torch

from wonderverse.camera import intrinsics
from wonderverse.splats import native_raster, render_torch
from wonderverse.splats.model import quat_to_rotmat
from wonderverse.splats.render_torch import gaussian_normals, project_gaussians, render

W, H = 40, 28


@pytest.fixture(autouse=True)
def one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def autograd_render(means, quats, scales, opacities, colors, viewmat, K, background):
    """gsplat 1.5.3 compositing written out with differentiable torch ops (float64, no tiles, no boxes)."""
    proj = project_gaussians(means, quats, scales, opacities, viewmat, K, W, H)
    normals = gaussian_normals(quats, scales, viewmat, proj.means_c)
    feats = torch.cat([colors, proj.depths[:, None], normals], 1)
    u, v = torch.meshgrid(
        torch.arange(W, dtype=means.dtype) + 0.5, torch.arange(H, dtype=means.dtype) + 0.5, indexing="xy"
    )
    acc = torch.zeros(H, W, feats.shape[1], dtype=means.dtype)
    T = torch.ones(H, W, dtype=means.dtype)
    done = torch.zeros(H, W, dtype=torch.bool)
    for i in torch.argsort(proj.depths.detach(), stable=True).tolist():
        if not bool(proj.visible[i]):
            continue
        a, b, c = proj.conics[i]
        dx = proj.means2d[i, 0] - u
        dy = proj.means2d[i, 1] - v
        sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
        alpha = torch.clamp_max(opacities[i] * torch.exp(-sigma), 0.999)
        live = (alpha >= 1 / 255) & (sigma >= 0) & ~done
        next_T = T * (1 - alpha)
        stop = live & (next_T <= 1e-4)
        done = done | stop
        draw = live & ~stop
        acc = acc + torch.where(draw, alpha * T, 0.0)[..., None] * feats[i]
        T = torch.where(draw, next_T, T)
    rgb = acc[..., :3] + T[..., None] * background
    return rgb, acc[..., 3:4], (1 - T)[..., None], acc[..., 4:7]


def scene(kind: str) -> dict:
    g = torch.Generator().manual_seed(11)
    K = torch.tensor(intrinsics(W, H, 60.0), dtype=torch.float64)
    fx = float(K[0, 0])
    n = 70
    z = torch.rand(n, generator=g, dtype=torch.float64) * 3 + 2
    x = (torch.rand(n, generator=g, dtype=torch.float64) * 2.2 - 1.1) * z * (W / 2) / fx
    y = (torch.rand(n, generator=g, dtype=torch.float64) * 2.2 - 1.1) * z * (H / 2) / fx
    sigma_px = 3.0 if kind == "random" else 8.0
    opac = torch.rand(n, generator=g, dtype=torch.float64) * 0.9 + 0.05
    if kind == "opaque_layers":
        opac = torch.where(torch.arange(n) % 2 == 0, torch.ones(n, dtype=torch.float64), opac * 0.2 + 0.8)
    return {
        "means": torch.stack([x, y, z], 1),
        "quats": torch.randn(n, 4, generator=g, dtype=torch.float64),
        "scales": z[:, None] * sigma_px / fx * torch.exp(0.5 * torch.randn(n, 3, generator=g, dtype=torch.float64)),
        "opacities": opac,
        "colors": torch.rand(n, 3, generator=g, dtype=torch.float64),
    }


def use_compositor(name: str, monkeypatch) -> None:
    """Composite with the C++ kernel ("native", which must build here) or the vectorised torch code."""
    if name == "native":
        assert native_raster.library() is not None, "the C++ compositing kernel did not build"
    else:
        monkeypatch.setattr(native_raster, "usable", lambda features: False)


@pytest.mark.parametrize(
    ("kind", "compositor", "chunk_pairs", "compact_below"),
    [
        ("random", "native", 1 << 16, 0.75),
        ("opaque_layers", "native", 1 << 16, 0.75),
        ("random", "torch", 1 << 16, 0.0),  # one chunk, nothing dropped
        ("random", "torch", 97, 2.0),  # many chunks, every chunk keeps only its drawn pairs
        ("opaque_layers", "torch", 1 << 16, 0.75),  # the default rule: most pairs lie behind opaque surfaces
        ("opaque_layers", "torch", 61, 0.0),
    ],
)
def test_gradients_match_autograd(kind: str, compositor: str, chunk_pairs: int, compact_below: float, monkeypatch):
    use_compositor(compositor, monkeypatch)
    monkeypatch.setattr(render_torch, "CHUNK_PAIRS", chunk_pairs)
    monkeypatch.setattr(render_torch, "COMPACT_BELOW", compact_below)
    s = scene(kind)
    vm = torch.eye(4, dtype=torch.float64)
    vm[:3, :3] = quat_to_rotmat(torch.tensor([0.99, 0.05, -0.08, 0.02], dtype=torch.float64))
    vm[:3, 3] = torch.tensor([0.1, -0.05, 0.2], dtype=torch.float64)
    s["means"] = s["means"] @ vm[:3, :3] - vm[:3, :3].T @ vm[:3, 3]  # the same camera-space points
    K = torch.tensor(intrinsics(W, H, 60.0), dtype=torch.float64)
    bg = torch.tensor([0.2, 0.5, 0.7], dtype=torch.float64)
    g = torch.Generator().manual_seed(3)
    weights = [torch.randn(H, W, c, generator=g, dtype=torch.float64) for c in (3, 1, 1, 3)]

    def loss_and_grads(fn):
        params = {k: v.clone().requires_grad_() for k, v in s.items()}
        outs = fn(params["means"], params["quats"], params["scales"], params["opacities"], params["colors"])
        loss = sum((o * w).sum() for o, w in zip(outs, weights, strict=True))
        loss.backward()
        return [o.detach() for o in outs], {k: p.grad for k, p in params.items()}

    outs, grads = loss_and_grads(lambda *p: render(*p, vm, K, W, H, background=bg)[:4])
    ref_outs, ref_grads = loss_and_grads(lambda *p: autograd_render(*p, vm, K, bg))

    if kind == "opaque_layers":
        # Most pixels are saturated: the stop rule ends them early and most of their pairs are not drawn.
        assert float((ref_outs[2] > 0.999).double().mean()) > 0.8
    for o, r in zip(outs, ref_outs, strict=True):
        torch.testing.assert_close(o, r, rtol=0, atol=1e-10)
    for name, ref in ref_grads.items():
        assert float(ref.abs().max()) > 1e-3, name  # the loss depends on every kind of parameter
        torch.testing.assert_close(grads[name], ref, rtol=1e-8, atol=1e-9 * float(ref.abs().max()), msg=name)


@pytest.mark.parametrize("threads", [1, 3])
def test_the_two_compositors_agree_in_float32(threads: int, monkeypatch) -> None:
    """A float32 scene of 3000 Gaussians, as training renders it: images and gradients of the C++ kernel (split
    among `threads`) and of the torch compositor agree to float32 rounding, and the kernel repeats itself exactly."""
    g = torch.Generator().manual_seed(5)
    n, w, h = 3000, 96, 64
    K = torch.tensor(intrinsics(w, h, 60.0), dtype=torch.float32)
    z = torch.rand(n, generator=g) * 4 + 1
    xy = (torch.rand(n, 2, generator=g) * 2.2 - 1.1) * z[:, None] * torch.tensor([w / 2, h / 2]) / float(K[0, 0])
    s = {
        "means": torch.cat([xy, z[:, None]], 1),
        "quats": torch.randn(n, 4, generator=g),
        "scales": z[:, None] * 2.5 / float(K[0, 0]) * torch.exp(0.5 * torch.randn(n, 3, generator=g)),
        "opacities": torch.rand(n, generator=g) * 0.9 + 0.05,
        "colors": torch.rand(n, 3, generator=g),
    }
    weights = [torch.randn(h, w, c, generator=g) for c in (3, 1, 1, 3)]
    torch.set_num_threads(threads)

    def run() -> tuple[list[torch.Tensor], dict[str, torch.Tensor]]:
        params = {k: v.clone().requires_grad_() for k, v in s.items()}
        outs = render(*params.values(), torch.eye(4), K, w, h, background=torch.tensor([0.3, 0.4, 0.5]))[:4]
        sum((o * wt).sum() for o, wt in zip(outs, weights, strict=True)).backward()
        return [o.detach() for o in outs], {k: p.grad for k, p in params.items()}

    use_compositor("native", monkeypatch)
    native_outs, native_grads = run()
    again_outs, again_grads = run()
    use_compositor("torch", monkeypatch)
    torch_outs, torch_grads = run()
    assert float(torch_outs[2].mean()) > 0.5  # mostly covered, with layers to composite
    for a, b, c in zip(native_outs, again_outs, torch_outs, strict=True):
        assert torch.equal(a, b)
        torch.testing.assert_close(a, c, rtol=1e-4, atol=1e-5)
    for name, ref in torch_grads.items():
        assert torch.equal(native_grads[name], again_grads[name]), name
        scale = float(ref.abs().max())
        torch.testing.assert_close(native_grads[name], ref, rtol=1e-3, atol=1e-4 * scale, msg=name)


@pytest.mark.parametrize(("w", "h", "tile_size"), [(96, 64, 16), (37, 23, 16), (50, 41, 8)])
def test_the_kernel_lists_the_same_pairs_as_torch(w: int, h: int, tile_size: int, monkeypatch) -> None:
    """Every pixel's candidate Gaussians, front to back, from the C++ kernel and from the torch code: the same
    lists, on images whose sides are no multiple of the tile, with Gaussians reaching past the borders, huge
    ones, needles and faint ones."""
    g = torch.Generator().manual_seed(9)
    n = 2500
    K = torch.tensor(intrinsics(w, h, 70.0), dtype=torch.float32)
    z = torch.rand(n, generator=g) * 5 + 0.5
    xy = (torch.rand(n, 2, generator=g) * 3 - 1.5) * z[:, None] * torch.tensor([w / 2, h / 2]) / float(K[0, 0])
    scales = z[:, None] * 2.0 / float(K[0, 0]) * torch.exp(1.5 * torch.randn(n, 3, generator=g))
    scales[::50, :2] *= 1e-4  # needles
    opac = torch.rand(n, generator=g)
    opac[::7] = 0.005  # faint: chords of a pixel or none
    proj = project_gaussians(
        torch.cat([xy, z[:, None]], 1), torch.randn(n, 4, generator=g), scales, opac, torch.eye(4), K, w, h
    )
    tiles_x, tiles_y = (w + tile_size - 1) // tile_size, (h + tile_size - 1) // tile_size
    gid, tile = render_torch._tile_intersections(proj.means2d, proj.radii, proj.depths, tile_size, tiles_x, tiles_y)

    def lists() -> dict[int, list[int]]:
        p = render_torch._candidate_pairs(
            proj.means2d.detach(), proj.conics.detach(), opac, gid, tile, tile_size, tiles_x, w, h
        )
        bounds = p.crow.tolist()
        gids = p.gid.tolist()
        out = {}
        for k, pixel in enumerate(p.seg_pixel.tolist()):
            assert pixel not in out and 0 <= pixel < w * h
            out[pixel] = gids[bounds[k] : bounds[k + 1]]
        return out

    use_compositor("native", monkeypatch)
    native = lists()
    use_compositor("torch", monkeypatch)
    reference = lists()
    assert len(reference) > 0.8 * w * h and sum(map(len, reference.values())) > 20 * w * h
    assert native == reference

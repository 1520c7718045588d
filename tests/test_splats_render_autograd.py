"""The rasteriser's hand-written compositing backward against autograd through a plain compositor.

`render` composites with a custom autograd Function (chunked, analytic backward). Here the same projection
feeds a straightforward differentiable compositor (every Gaussian at every pixel, front to back, gsplat's
rules written with torch.where), and autograd's gradients of a random loss are the ground truth. Chunking
and the dropping of undrawn pairs are forced on and off so every path is compared.
"""

from __future__ import annotations

import pytest
import torch

from wonderverse.camera import intrinsics
from wonderverse.splats import render_torch
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


@pytest.mark.parametrize(
    ("kind", "chunk_pairs", "compact_below"),
    [
        ("random", 1 << 16, 0.0),  # one chunk, nothing dropped
        ("random", 97, 2.0),  # many chunks, every chunk keeps only its drawn pairs
        ("opaque_layers", 1 << 16, 0.75),  # the default rule: most pairs lie behind opaque surfaces
        ("opaque_layers", 61, 0.0),
    ],
)
def test_gradients_match_autograd(kind: str, chunk_pairs: int, compact_below: float, monkeypatch) -> None:
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

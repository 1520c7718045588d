"""Small Triton kernels for the CUDA training step, where each replaces ~10-20 small PyTorch
operations: on the GPU machine each such operation cost ~30 µs of host time (docs/benchmarks.md,
2026-11-23), and the step is host-bound.

* `camera_normals(quats, scales, means, viewmat)`: the gsplat backend's per-Gaussian camera-space
  normals, the same function as `render_torch.gaussian_normals`: each Gaussian's shortest axis, column
  k = argmin(scale) of R(q / |q|) (first index on ties, as torch.argmin), rotated by the viewmat and
  flipped to face the camera (n . mean_c <= 0); only the quaternions get a gradient. One launch each
  way; the backward recomputes what it needs from the inputs instead of saving it.
* `accumulate_grad2d(grad, radii, grad2d, count, ndc_x, ndc_y)`: the densification statistics of one
  step, in place (`strategy._accumulate_grad2d` is the same in torch).

Both need CUDA float32 tensors and Triton (shipped with PyTorch's CUDA wheels); `available()` says
whether Triton imports. Tested against their torch versions by tests/test_splats_gpu.py.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

try:
    import triton
    import triton.language as tl
except ImportError:  # pragma: no cover - depends on the machine
    triton = None

_BLOCK = 256


def available() -> bool:
    return triton is not None


if triton is not None:

    @triton.jit
    def _geometry(q_ptr, s_ptr, m_ptr, v_ptr, i, ok):
        """Unit quaternion, shortest-axis masks, the axis a in the world, the camera normal n and its sign."""
        qw = tl.load(q_ptr + 4 * i, mask=ok, other=1.0)
        qx = tl.load(q_ptr + 4 * i + 1, mask=ok, other=0.0)
        qy = tl.load(q_ptr + 4 * i + 2, mask=ok, other=0.0)
        qz = tl.load(q_ptr + 4 * i + 3, mask=ok, other=0.0)
        norm = tl.maximum(tl.sqrt(qw * qw + qx * qx + qy * qy + qz * qz), 1e-12)
        w, x, y, z = qw / norm, qx / norm, qy / norm, qz / norm
        s0 = tl.load(s_ptr + 3 * i, mask=ok, other=0.0)
        s1 = tl.load(s_ptr + 3 * i + 1, mask=ok, other=0.0)
        s2 = tl.load(s_ptr + 3 * i + 2, mask=ok, other=0.0)
        k0 = (s0 <= s1) & (s0 <= s2)
        k1 = (s1 < s0) & (s1 <= s2)  # ties go to the lower index
        # column k of R(q)
        a0 = tl.where(k0, 1 - 2 * (y * y + z * z), tl.where(k1, 2 * (x * y - w * z), 2 * (x * z + w * y)))
        a1 = tl.where(k0, 2 * (x * y + w * z), tl.where(k1, 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)))
        a2 = tl.where(k0, 2 * (x * z - w * y), tl.where(k1, 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)))
        r00, r01, r02, t0 = tl.load(v_ptr), tl.load(v_ptr + 1), tl.load(v_ptr + 2), tl.load(v_ptr + 3)
        r10, r11, r12, t1 = tl.load(v_ptr + 4), tl.load(v_ptr + 5), tl.load(v_ptr + 6), tl.load(v_ptr + 7)
        r20, r21, r22, t2 = tl.load(v_ptr + 8), tl.load(v_ptr + 9), tl.load(v_ptr + 10), tl.load(v_ptr + 11)
        n0 = r00 * a0 + r01 * a1 + r02 * a2
        n1 = r10 * a0 + r11 * a1 + r12 * a2
        n2 = r20 * a0 + r21 * a1 + r22 * a2
        m0 = tl.load(m_ptr + 3 * i, mask=ok, other=0.0)
        m1 = tl.load(m_ptr + 3 * i + 1, mask=ok, other=0.0)
        m2 = tl.load(m_ptr + 3 * i + 2, mask=ok, other=0.0)
        c0 = r00 * m0 + r01 * m1 + r02 * m2 + t0
        c1 = r10 * m0 + r11 * m1 + r12 * m2 + t1
        c2 = r20 * m0 + r21 * m1 + r22 * m2 + t2
        sign = tl.where(n0 * c0 + n1 * c1 + n2 * c2 > 0, -1.0, 1.0)
        return w, x, y, z, norm, k0, k1, n0, n1, n2, sign

    @triton.jit
    def _forward(q_ptr, s_ptr, m_ptr, v_ptr, out_ptr, n, BLOCK: tl.constexpr):
        i = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
        ok = i < n
        _, _, _, _, _, _, _, n0, n1, n2, sign = _geometry(q_ptr, s_ptr, m_ptr, v_ptr, i, ok)
        tl.store(out_ptr + 3 * i, sign * n0, mask=ok)
        tl.store(out_ptr + 3 * i + 1, sign * n1, mask=ok)
        tl.store(out_ptr + 3 * i + 2, sign * n2, mask=ok)

    @triton.jit
    def _backward(q_ptr, s_ptr, m_ptr, v_ptr, g_ptr, out_ptr, n, BLOCK: tl.constexpr):
        i = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
        ok = i < n
        w, x, y, z, norm, k0, k1, _, _, _, sign = _geometry(q_ptr, s_ptr, m_ptr, v_ptr, i, ok)
        g0 = sign * tl.load(g_ptr + 3 * i, mask=ok, other=0.0)
        g1 = sign * tl.load(g_ptr + 3 * i + 1, mask=ok, other=0.0)
        g2 = sign * tl.load(g_ptr + 3 * i + 2, mask=ok, other=0.0)
        # d/da = R^T g
        b0 = tl.load(v_ptr) * g0 + tl.load(v_ptr + 4) * g1 + tl.load(v_ptr + 8) * g2
        b1 = tl.load(v_ptr + 1) * g0 + tl.load(v_ptr + 5) * g1 + tl.load(v_ptr + 9) * g2
        b2 = tl.load(v_ptr + 2) * g0 + tl.load(v_ptr + 6) * g1 + tl.load(v_ptr + 10) * g2
        # the Jacobian of column k of R(q) with respect to (w, x, y, z), transposed, times d/da
        gw = 2 * tl.where(k0, z * b1 - y * b2, tl.where(k1, x * b2 - z * b0, y * b0 - x * b1))
        gx = 2 * tl.where(k0, y * b1 + z * b2, tl.where(k1, y * b0 - 2 * x * b1 + w * b2, z * b0 - w * b1 - 2 * x * b2))
        gy = 2 * tl.where(
            k0, -2 * y * b0 + x * b1 - w * b2, tl.where(k1, x * b0 + z * b2, w * b0 + z * b1 - 2 * y * b2)
        )
        gz = 2 * tl.where(
            k0, -2 * z * b0 + w * b1 + x * b2, tl.where(k1, -w * b0 - 2 * z * b1 + y * b2, x * b0 + y * b1)
        )
        # through q / |q|
        d = w * gw + x * gx + y * gy + z * gz
        tl.store(out_ptr + 4 * i, (gw - w * d) / norm, mask=ok)
        tl.store(out_ptr + 4 * i + 1, (gx - x * d) / norm, mask=ok)
        tl.store(out_ptr + 4 * i + 2, (gy - y * d) / norm, mask=ok)
        tl.store(out_ptr + 4 * i + 3, (gz - z * d) / norm, mask=ok)

    @triton.jit
    def _accumulate(g_ptr, r_ptr, sum_ptr, count_ptr, n, ndc_x, ndc_y, BLOCK: tl.constexpr):
        i = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
        ok = i < n
        gx = tl.load(g_ptr + 2 * i, mask=ok, other=0.0) * ndc_x
        gy = tl.load(g_ptr + 2 * i + 1, mask=ok, other=0.0) * ndc_y
        norm = tl.sqrt(gx * gx + gy * gy)
        seen = (tl.load(r_ptr + 2 * i, mask=ok, other=0) > 0) & (tl.load(r_ptr + 2 * i + 1, mask=ok, other=0) > 0)
        counted = seen & (norm < 3.0e38)  # visible, with a finite gradient (NaN compares false)
        total = tl.load(sum_ptr + i, mask=ok, other=0.0)
        tl.store(sum_ptr + i, total + tl.where(counted, norm, 0.0), mask=ok)
        tl.store(count_ptr + i, tl.load(count_ptr + i, mask=ok, other=0.0) + tl.where(counted, 1.0, 0.0), mask=ok)


class _CameraNormals(torch.autograd.Function):
    @staticmethod
    def forward(ctx: Any, quats: Tensor, scales: Tensor, means: Tensor, viewmat: Tensor) -> Tensor:
        args = [t.detach().contiguous() for t in (quats, scales, means, viewmat)]
        out = torch.empty_like(args[2])
        n = len(out)
        if n:
            _forward[(triton.cdiv(n, _BLOCK),)](*args, out, n, BLOCK=_BLOCK)
        ctx.save_for_backward(*args)
        return out

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor, None, None, None]:
        args = ctx.saved_tensors
        out = torch.empty_like(args[0])
        n = len(out)
        if n:
            _backward[(triton.cdiv(n, _BLOCK),)](*args, grad.contiguous(), out, n, BLOCK=_BLOCK)
        return out, None, None, None


def camera_normals(quats: Tensor, scales: Tensor, means: Tensor, viewmat: Tensor) -> Tensor:
    """Camera-space unit normals (N,3) of the Gaussians for the 4x4 world-to-camera `viewmat`."""
    return _CameraNormals.apply(quats, scales, means, viewmat)


def accumulate_grad2d(
    grad: Tensor, radii: Tensor, grad2d: Tensor, count: Tensor, ndc_x: float, ndc_y: float
) -> tuple[Tensor, Tensor]:
    """Add |(grad_x ndc_x, grad_y ndc_y)| of the visible Gaussians (radii > 0) with a finite gradient to
    `grad2d` and 1 to their `count`, in place; returns (grad2d, count). grad (N,2) float32, radii (N,2)
    int32, grad2d and count (N,) float32 and contiguous (they are updated), all on one CUDA device."""
    n = len(grad2d)
    if n:
        grad, radii = grad.contiguous(), radii.contiguous()
        _accumulate[(triton.cdiv(n, _BLOCK),)](grad, radii, grad2d, count, n, ndc_x, ndc_y, BLOCK=_BLOCK)
    return grad2d, count

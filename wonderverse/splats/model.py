"""The Gaussian-splat scene model, its initialisation from points, scene normalisation and SH colour.

Conventions (the same as gsplat 1.5.3 and the INRIA 3DGS code):
  means (N,3) world coordinates (the *normalised* frame while training, see `normalization_from_cameras`);
  quats (N,4) w,x,y,z, unnormalised (normalised wherever they are used; a zero quaternion means identity);
  log_scales (N,3) natural log of the per-axis standard deviations;
  logit_opacities (N,) logit of the opacity in (0,1);
  sh0 (N,1,3) and shN (N,K,3) real spherical-harmonic coefficients, K = (degree+1)^2 - 1,
  colour = max(SH(dir) + 0.5, 0) with dir = mean - camera centre.
All tensors are float32.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor, nn

if TYPE_CHECKING:
    from wonderverse.camera import Sim3

# Real SH constants of the INRIA 3DGS code (utils/sh_utils.py), used by gsplat too.
SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (
    1.0925484305920792,
    -1.0925484305920792,
    0.31539156525252005,
    -1.0925484305920792,
    0.5462742152960396,
)
SH_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)
MAX_SH_DEGREE = 3


def num_sh_bases(degree: int) -> int:
    """Number of SH coefficients per channel up to and including `degree`: (degree+1)^2."""
    if not 0 <= degree <= MAX_SH_DEGREE:
        raise ValueError(f"SH degree must be in 0..{MAX_SH_DEGREE}, got {degree}")
    return (degree + 1) ** 2


def rgb_to_sh(rgb: Tensor) -> Tensor:
    """DC coefficient giving colour `rgb` (in [0,1]): (rgb - 0.5) / C0."""
    return (rgb - 0.5) / SH_C0


def sh_to_rgb(sh0: Tensor) -> Tensor:
    """Colour of the DC term alone: sh0 * C0 + 0.5 (not clamped)."""
    return sh0 * SH_C0 + 0.5


def sh_basis(degree: int, dirs: Tensor) -> Tensor:
    """Real SH basis (..., (degree+1)^2) at unit directions `dirs` (..., 3); INRIA ordering and signs."""
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [
            SH_C2[0] * xy,
            SH_C2[1] * yz,
            SH_C2[2] * (2.0 * zz - xx - yy),
            SH_C2[3] * xz,
            SH_C2[4] * (xx - yy),
        ]
    if degree >= 3:
        out += [
            SH_C3[0] * y * (3.0 * xx - yy),
            SH_C3[1] * xy * z,
            SH_C3[2] * y * (4.0 * zz - xx - yy),
            SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
            SH_C3[4] * x * (4.0 * zz - xx - yy),
            SH_C3[5] * z * (xx - yy),
            SH_C3[6] * x * (xx - 3.0 * yy),
        ]
    return torch.stack(out, dim=-1)


def eval_sh(degree: int, sh_coeffs: Tensor, dirs: Tensor) -> Tensor:
    """Raw SH value (..., 3) of coefficients (..., K>=(degree+1)^2, 3) in directions (..., 3).

    Only the first (degree+1)^2 coefficients are used (so a lower active degree can be evaluated on a
    model that stores more). `dirs` need not be unit length: they are normalised here, and a zero
    direction evaluates the DC term only. Add 0.5 and clamp at 0 for a colour (`sh_colors`).
    """
    n = num_sh_bases(degree)
    if sh_coeffs.shape[-2] < n:
        raise ValueError(f"degree {degree} needs {n} SH coefficients, got {sh_coeffs.shape[-2]}")
    norm = dirs.norm(dim=-1, keepdim=True)
    unit = dirs / norm.clamp_min(1e-12)
    basis = sh_basis(degree, unit)  # (..., n)
    return (basis.unsqueeze(-1) * sh_coeffs[..., :n, :]).sum(dim=-2)


def sh_colors(degree: int, sh_coeffs: Tensor, dirs: Tensor) -> Tensor:
    """RGB (..., 3) = max(eval_sh + 0.5, 0), the 3DGS/gsplat colour convention (no upper clamp)."""
    return torch.clamp_min(eval_sh(degree, sh_coeffs, dirs) + 0.5, 0.0)


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """Rotation matrices (...,3,3) of w,x,y,z quaternions (...,4); normalised here, zero -> identity (the
    Gaussians' convention, as gsplat's; `camera.matrix_from_quat` is the same formula over NumPy)."""
    from wonderverse.camera import quat_matrix_entries

    norm = quats.norm(dim=-1, keepdim=True)
    # A zero quaternion is mapped to the identity instead of dividing by zero.
    identity = torch.zeros_like(quats)
    identity[..., 0] = 1.0
    q = torch.where(norm > 1e-12, quats / norm.clamp_min(1e-12), identity)
    R = torch.stack(quat_matrix_entries(*q.unbind(-1)), dim=-1)
    return R.reshape(*quats.shape[:-1], 3, 3)


def sh_rotation_matrices(R: np.ndarray, degree: int) -> list[np.ndarray]:
    """Per-band matrices D_l ((2l+1)x(2l+1), l = 1..degree) rotating SH coefficients with the scene.

    A radiance function f rotated by R is f'(d) = f(R^T d); band l is closed under rotation, so the
    coefficients map linearly, c'_l = D_l c_l. D_l is solved exactly (up to rounding) from basis values at
    random directions: Y_l(d) D_l = Y_l(R^T d).
    """
    rng = np.random.default_rng(0)
    d = rng.normal(size=(64, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    dt = torch.from_numpy(d)
    rd = torch.from_numpy(d @ np.asarray(R, dtype=np.float64))  # rows: R^T d
    Y = sh_basis(degree, dt).numpy()
    Yr = sh_basis(degree, rd).numpy()
    mats = []
    for band in range(1, degree + 1):
        sl = slice(band * band, (band + 1) * (band + 1))
        D, *_ = np.linalg.lstsq(Y[:, sl], Yr[:, sl], rcond=None)
        mats.append(D)  # Y D = Y_r, so for coefficient column vectors c' = D c
    return mats


def normalization_from_cameras(w2c: np.ndarray, points: np.ndarray | None = None, target_radius: float = 1.0) -> Sim3:
    """The similarity from the world to the training frame, x_n = scale (x - center) (a `Sim3` about
    `center`, no rotation, t = 0): centre = mean camera centre; scale so the farthest camera lies at
    `target_radius`.

    Training in a frame centred on the cameras with unit extent keeps learning rates and the densification
    thresholds scene-independent. The scale is dimensionless (normalised units per world unit); depths in
    the normalised frame are `scale` times world depths. With one camera (or all at one place) the extent
    comes from `points` (their median distance to the centre) instead; with neither, scale = 1. Stored with
    the splats (`normalization_to_dict`) so that exports are in the original world frame.
    """
    from wonderverse.camera import Sim3, camera_centers, camera_radius

    w2c = np.asarray(w2c, dtype=np.float64).reshape(-1, 4, 4)
    center = camera_centers(w2c).mean(axis=0)
    extent = camera_radius(w2c)
    if not extent > 1e-9 and points is not None and len(points):
        extent = float(np.median(np.linalg.norm(np.asarray(points, np.float64) - center, axis=1)))
    scale = target_radius / extent if extent > 1e-9 and np.isfinite(extent) else 1.0
    return Sim3(scale, np.eye(3), np.zeros(3), center=center)


def normalization_to_dict(norm: Sim3) -> dict[str, list[float] | float]:
    """How the splats group stores its normalisation x_n = scale rotation (x - center): {center, scale,
    rotation}. Only a similarity about a point (t = 0) has this form."""
    if norm.t.any():
        raise ValueError("a scene normalisation has t = 0 (x_n = scale rotation (x - center))")
    return {"center": norm.center.tolist(), "scale": float(norm.s), "rotation": norm.R.tolist()}


def normalization_from_dict(d: dict) -> Sim3:
    """The `Sim3` of `normalization_to_dict`'s {center, scale, rotation} (rotation optional: identity)."""
    from wonderverse.camera import Sim3

    return Sim3(d["scale"], d.get("rotation", np.eye(3)), np.zeros(3), center=d["center"])


class GaussianModel(nn.Module):
    """Trainable Gaussians (see the module docstring for each tensor's convention).

    `sh_degree` is the largest degree the model stores; the renderer may use a lower active degree.
    """

    def __init__(
        self,
        means: Tensor,
        quats: Tensor,
        log_scales: Tensor,
        logit_opacities: Tensor,
        sh0: Tensor,
        shN: Tensor,
        sh_degree: int,
    ) -> None:
        super().__init__()
        n = means.shape[0]
        k = num_sh_bases(sh_degree) - 1
        shapes = {
            "means": (means, (n, 3)),
            "quats": (quats, (n, 4)),
            "log_scales": (log_scales, (n, 3)),
            "logit_opacities": (logit_opacities, (n,)),
            "sh0": (sh0, (n, 1, 3)),
            "shN": (shN, (n, k, 3)),
        }
        for name, (t, shape) in shapes.items():
            if tuple(t.shape) != shape:
                raise ValueError(f"{name}: expected shape {shape}, got {tuple(t.shape)}")
            setattr(self, name, nn.Parameter(t.detach().to(torch.float32).clone()))
        self.sh_degree = sh_degree

    PARAM_NAMES = ("means", "quats", "log_scales", "logit_opacities", "sh0", "shN")

    @property
    def num_gaussians(self) -> int:
        return int(self.means.shape[0])

    @property
    def scales(self) -> Tensor:
        return torch.exp(self.log_scales)

    @property
    def opacities(self) -> Tensor:
        return torch.sigmoid(self.logit_opacities)

    @property
    def sh_coeffs(self) -> Tensor:
        """All SH coefficients (N, (sh_degree+1)^2, 3)."""
        return torch.cat([self.sh0, self.shN], dim=1)

    def param_dict(self) -> dict[str, nn.Parameter]:
        """The trainable tensors by name (what optimisers and strategies operate on)."""
        return {name: getattr(self, name) for name in self.PARAM_NAMES}

    def replace_params(self, params: dict[str, Tensor]) -> None:
        """Install new tensors (e.g. after densification changed N); they become this model's Parameters."""
        for name in self.PARAM_NAMES:
            p = params[name]
            setattr(self, name, p if isinstance(p, nn.Parameter) else nn.Parameter(p))

    def to_numpy(self) -> dict[str, np.ndarray]:
        """float32 arrays by parameter name (for the scene store)."""
        return {name: getattr(self, name).detach().cpu().numpy().astype(np.float32) for name in self.PARAM_NAMES}

    @staticmethod
    def from_numpy(arrays: dict[str, np.ndarray], sh_degree: int | None = None) -> GaussianModel:
        """Inverse of `to_numpy`; the SH degree is inferred from shN when not given."""
        if sh_degree is None:
            sh_degree = round(math.sqrt(arrays["shN"].shape[1] + 1)) - 1
        t = {k: torch.from_numpy(np.asarray(v, dtype=np.float32)) for k, v in arrays.items()}
        return GaussianModel(sh_degree=sh_degree, **{k: t[k] for k in GaussianModel.PARAM_NAMES})

    @staticmethod
    def empty(sh_degree: int = 0) -> GaussianModel:
        k = num_sh_bases(sh_degree) - 1
        z = torch.zeros
        return GaussianModel(z(0, 3), z(0, 4), z(0, 3), z(0), z(0, 1, 3), z(0, k, 3), sh_degree)


def voxel_downsample(
    points: np.ndarray, colors: np.ndarray | None, voxel_size: float
) -> tuple[np.ndarray, np.ndarray | None]:
    """Average points (and colours) per cubic voxel of edge `voxel_size` (same units as the points).

    Returns (M,3) float64 centroids and (M,3) float64 mean colours (None when colours are None), in
    order of first occurrence of each voxel. voxel_size <= 0 returns the input unchanged.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    cols = None if colors is None else np.asarray(colors, dtype=np.float64).reshape(-1, 3)
    if voxel_size <= 0 or len(points) == 0:
        return points, cols
    keys = np.floor(points / voxel_size).astype(np.int64)
    _, first, inverse, counts = np.unique(keys, axis=0, return_index=True, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    order = np.argsort(first)  # keep first-occurrence order so the result does not depend on np.unique's sort
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    inv = rank[inverse]
    m = len(first)
    sums = np.zeros((m, 3))
    np.add.at(sums, inv, points)
    cnt = counts[order][:, None].astype(np.float64)
    out_cols = None
    if cols is not None:
        csum = np.zeros((m, 3))
        np.add.at(csum, inv, cols)
        out_cols = csum / cnt
    return sums / cnt, out_cols


def knn_mean_distance(points: np.ndarray, k: int = 3, others: np.ndarray | None = None) -> np.ndarray:
    """Mean Euclidean distance (P,) from each point to its `k` nearest other points (scipy cKDTree), the
    neighbours taken among `points` and `others` (Q,3) together.

    Fewer than k+1 points use all the others; a single point gets NaN (callers substitute a default).
    """
    from scipy.spatial import cKDTree

    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    every = points if others is None else np.concatenate([points, np.asarray(others, np.float64).reshape(-1, 3)])
    if len(every) <= 1:
        return np.full(len(points), np.nan)
    kk = min(k, len(every) - 1)
    dist, _ = cKDTree(every).query(points, k=kk + 1)
    return dist[:, 1:].reshape(len(points), -1).mean(axis=1)


def init_from_points(
    points: np.ndarray,
    colors: np.ndarray,
    sh_degree: int,
    init_opacity: float = 0.1,
    knn_k: int = 3,
    scale_multiplier: float = 1.0,
    min_scale: float = 1e-7,
    default_scale: float = 0.01,
    neighbours: np.ndarray | None = None,
) -> GaussianModel:
    """Isotropic Gaussians at `points` (P,3) coloured `colors` (P,3; uint8 0..255 or float 0..1).

    Scale = scale_multiplier * mean distance to the `knn_k` nearest neighbours among the points and
    `neighbours` (Q,3; e.g. the Gaussians a new batch joins), clamped below at `min_scale` (duplicate
    points stay finite), `default_scale` when there is a single point;
    rotation identity; opacity `init_opacity`; DC SH from the colour, higher bands zero.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    colors = np.asarray(colors)
    rgb = colors.astype(np.float64) / 255.0 if colors.dtype == np.uint8 else colors.astype(np.float64)
    rgb = np.clip(rgb.reshape(-1, 3), 0.0, 1.0)
    if len(rgb) != len(points):
        raise ValueError(f"{len(points)} points but {len(rgb)} colours")
    if not 0.0 < init_opacity < 1.0:
        raise ValueError(f"init_opacity must be in (0,1), got {init_opacity}")
    n = len(points)
    dist = knn_mean_distance(points, knn_k, neighbours)
    dist = np.where(np.isfinite(dist), dist, default_scale)
    scales = np.maximum(dist * scale_multiplier, min_scale)
    k = num_sh_bases(sh_degree) - 1
    quats = torch.zeros(n, 4)
    quats[:, 0] = 1.0
    logit = math.log(init_opacity / (1.0 - init_opacity))
    return GaussianModel(
        means=torch.from_numpy(points).float(),
        quats=quats,
        log_scales=torch.from_numpy(np.log(scales)).float()[:, None].repeat(1, 3),
        logit_opacities=torch.full((n,), logit),
        sh0=rgb_to_sh(torch.from_numpy(rgb).float())[:, None, :],
        shN=torch.zeros(n, k, 3),
        sh_degree=sh_degree,
    )

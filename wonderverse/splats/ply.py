"""splats.ply in the INRIA 3DGS layout, the format 3DGS viewers (SIBR, SuperSplat, antimatter15, gsplat's
exporter) read: one `vertex` element, binary little-endian, all properties float32, in this order

    x y z  nx ny nz  f_dc_0..2  f_rest_0..(3K-1)  opacity  scale_0..2  rot_0..3

with nx..nz = 0, f_dc the DC SH coefficient per channel (R, G, B), f_rest the K = (degree+1)^2 - 1 higher
coefficients channel-major (all of R's K coefficients, then G's, then B's: INRIA's
`features_rest.transpose(1, 2).flatten(1)`), opacity as a logit, scale_* as natural logs, rot_* a w,x,y,z
quaternion (not necessarily unit length).

The file is written in the original world frame: the inverse of the training normalisation (a
`camera.Sim3`, x_n = s R (x - c) + t) is applied: means x = R^T x_n / s + c, log-scales shifted by -log(s), rotations
composed as q_world = q(R^T) * q_n, and SH bands of degree >= 1 rotated with R^T (identity when R = I).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from wonderverse.camera import Sim3, quat_from_matrix, quat_multiply
from wonderverse.splats.model import MAX_SH_DEGREE, num_sh_bases, sh_rotation_matrices


def ply_property_names(sh_degree: int) -> list[str]:
    """The INRIA property names, in file order, for SH degree `sh_degree`."""
    k = num_sh_bases(sh_degree) - 1
    return (
        ["x", "y", "z", "nx", "ny", "nz"]
        + [f"f_dc_{i}" for i in range(3)]
        + [f"f_rest_{i}" for i in range(3 * k)]
        + ["opacity"]
        + [f"scale_{i}" for i in range(3)]
        + [f"rot_{i}" for i in range(4)]
    )


def to_world(arrays: dict[str, np.ndarray], normalization: Sim3) -> dict[str, np.ndarray]:
    """Gaussian arrays (GaussianModel.to_numpy names) mapped from the training frame to the world frame."""
    s, R = normalization.s, normalization.R
    out = {k: np.asarray(v, dtype=np.float64).copy() for k, v in arrays.items()}
    out["means"] = normalization.apply_inverse(out["means"])
    out["log_scales"] = out["log_scales"] - math.log(s)
    if not np.allclose(R, np.eye(3), atol=1e-12):
        q_rt = quat_from_matrix(R.T)
        out["quats"] = quat_multiply(np.broadcast_to(q_rt, out["quats"].shape), out["quats"])
        sh_n = out["shN"]
        degree = round(math.sqrt(sh_n.shape[1] + 1)) - 1
        for band, D in enumerate(sh_rotation_matrices(R.T, degree), start=1):
            sl = slice(band * band - 1, (band + 1) ** 2 - 1)  # shN omits the DC coefficient
            sh_n[:, sl, :] = np.einsum("ij,njc->nic", D, sh_n[:, sl, :])
    return out


def to_training_frame(arrays: dict[str, np.ndarray], normalization: Sim3) -> dict[str, np.ndarray]:
    """Inverse of `to_world`: world-frame Gaussian arrays into the normalised training frame."""
    turn = Sim3(1.0 / normalization.s, normalization.R.T, np.zeros(3))
    # to_world with (1/s, R^T) maps x -> R x * s, log-scales + log s, q -> q(R) q, SH rotated by R.
    out = to_world({**arrays, "means": np.asarray(arrays["means"], np.float64) - normalization.center}, turn)
    out["means"] = out["means"] + normalization.t
    return out


def write_ply(
    path: str | Path,
    arrays: dict[str, np.ndarray],
    normalization: Sim3 | None = None,
) -> Path:
    """Write Gaussians (GaussianModel.to_numpy() arrays, training frame) as an INRIA splats.ply in the world
    frame (`normalization` inverted; None = already in the world frame). Returns the path."""
    from plyfile import PlyData, PlyElement

    if normalization is not None:
        arrays = to_world(arrays, normalization)
    n = len(arrays["means"])
    shn = np.asarray(arrays["shN"], dtype=np.float32)
    shn = shn.reshape(n, shn.shape[1] if shn.ndim == 3 else shn.size // max(3 * n, 1), 3)
    degree = round(math.sqrt(shn.shape[1] + 1)) - 1
    if num_sh_bases(degree) - 1 != shn.shape[1] or degree > MAX_SH_DEGREE:
        raise ValueError(f"shN has {shn.shape[1]} coefficients per channel, not (d+1)^2 - 1 for d <= 3")
    columns = np.concatenate(
        [
            np.asarray(arrays["means"], dtype=np.float32).reshape(n, 3),
            np.zeros((n, 3), dtype=np.float32),
            np.asarray(arrays["sh0"], dtype=np.float32).reshape(n, 3),
            shn.transpose(0, 2, 1).reshape(n, 3 * shn.shape[1]),  # channel-major, as INRIA
            np.asarray(arrays["logit_opacities"], dtype=np.float32).reshape(n, 1),
            np.asarray(arrays["log_scales"], dtype=np.float32).reshape(n, 3),
            np.asarray(arrays["quats"], dtype=np.float32).reshape(n, 4),
        ],
        axis=1,
    )
    names = ply_property_names(degree)
    vertex = np.empty(n, dtype=[(name, "<f4") for name in names])
    for i, name in enumerate(names):
        vertex[name] = columns[:, i]
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    PlyData([PlyElement.describe(vertex, "vertex")], text=False, byte_order="<").write(str(path))
    return path


def read_ply(path: str | Path, normalization: Sim3 | None = None) -> dict[str, np.ndarray]:
    """Read an INRIA splats.ply into GaussianModel.from_numpy() arrays (float32): world frame, or the
    training frame of `normalization` when given. The SH degree follows the number of f_rest fields."""
    from plyfile import PlyData

    v = PlyData.read(str(path))["vertex"].data
    names = v.dtype.names or ()
    n_rest = sum(1 for name in names if name.startswith("f_rest_"))
    if n_rest % 3:
        raise ValueError(f"{path}: {n_rest} f_rest fields is not a multiple of 3")
    k = n_rest // 3
    n = len(v)

    def cols(fields: list[str]) -> np.ndarray:
        return np.stack([np.asarray(v[f], dtype=np.float64) for f in fields], axis=1) if fields else np.zeros((n, 0))

    arrays = {
        "means": cols(["x", "y", "z"]),
        "quats": cols([f"rot_{i}" for i in range(4)]),
        "log_scales": cols([f"scale_{i}" for i in range(3)]),
        "logit_opacities": np.asarray(v["opacity"], dtype=np.float64),
        "sh0": cols([f"f_dc_{i}" for i in range(3)]).reshape(n, 1, 3),
        "shN": cols([f"f_rest_{i}" for i in range(n_rest)]).reshape(n, 3, k).transpose(0, 2, 1),
    }
    if normalization is not None:
        arrays = to_training_frame(arrays, normalization)
    return {name: np.ascontiguousarray(a, dtype=np.float32) for name, a in arrays.items()}

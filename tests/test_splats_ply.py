"""INRIA splats.ply export: layout, round trip, and the inverse scene normalisation."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from plyfile import PlyData
from scipy.spatial.transform import Rotation

from wonderverse.camera import Sim3, intrinsics, look_at
from wonderverse.splats.model import GaussianModel
from wonderverse.splats.ply import ply_property_names, read_ply, to_world, write_ply
from wonderverse.splats.render_torch import render

INRIA_DEGREE3 = (
    ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    + [f"f_rest_{i}" for i in range(45)]
    + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
)


def _arrays(n: int, degree: int, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    k = (degree + 1) ** 2 - 1
    return {
        "means": rng.normal(size=(n, 3)).astype(np.float32),
        "quats": rng.normal(size=(n, 4)).astype(np.float32),
        "log_scales": rng.normal(-3, 0.5, size=(n, 3)).astype(np.float32),
        "logit_opacities": rng.normal(size=n).astype(np.float32),
        "sh0": rng.normal(size=(n, 1, 3)).astype(np.float32),
        "shN": rng.normal(size=(n, k, 3)).astype(np.float32),
    }


def test_layout_is_what_3dgs_viewers_expect(tmp_path: Path) -> None:
    a = _arrays(7, 3)
    path = write_ply(tmp_path / "splats.ply", a)
    ply = PlyData.read(str(path))
    assert ply.byte_order == "<" and not ply.text
    assert [e.name for e in ply.elements] == ["vertex"]
    v = ply["vertex"]
    assert [p.name for p in v.properties] == INRIA_DEGREE3 == ply_property_names(3)
    assert all(v.data.dtype[name] == np.dtype("<f4") for name in INRIA_DEGREE3)
    assert len(v.data) == 7
    # Channel-major f_rest: f_rest_0..14 are red's 15 coefficients, 15..29 green's, 30..44 blue's.
    assert v["f_rest_0"][2] == a["shN"][2, 0, 0] and v["f_rest_14"][2] == a["shN"][2, 14, 0]
    assert v["f_rest_15"][2] == a["shN"][2, 0, 1] and v["f_rest_44"][2] == a["shN"][2, 14, 2]
    assert v["f_dc_1"][3] == a["sh0"][3, 0, 1] and v["rot_0"][4] == a["quats"][4, 0]
    assert v["opacity"][5] == a["logit_opacities"][5] and v["scale_2"][6] == a["log_scales"][6, 2]
    assert np.all(v["nx"] == 0) and np.all(v["nz"] == 0)
    # Header as text, property for property.
    header = path.read_bytes().split(b"end_header")[0].decode()
    assert "format binary_little_endian 1.0" in header and "element vertex 7" in header
    assert header.count("property float ") == 62


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_roundtrip_without_normalization(tmp_path: Path, degree: int) -> None:
    a = _arrays(11, degree, seed=degree)
    back = read_ply(write_ply(tmp_path / "s.ply", a))
    assert set(back) == set(a)
    for k in a:
        assert back[k].dtype == np.float32 and back[k].shape == a[k].shape
        np.testing.assert_array_equal(back[k], a[k])
    model = GaussianModel.from_numpy(back)
    assert model.sh_degree == degree


def test_empty_model(tmp_path: Path) -> None:
    a = GaussianModel.empty(2).to_numpy()
    back = read_ply(write_ply(tmp_path / "e.ply", a))
    assert back["means"].shape == (0, 3) and back["shN"].shape == (0, 8, 3)


def test_export_undoes_the_normalization_exactly_as_rendered(tmp_path: Path) -> None:
    # Render the training-frame model with training-frame poses, and the exported world-frame model with
    # world poses: colour (with view-dependent SH), alpha and normals agree; depth scales by 1/s.
    rng = np.random.default_rng(3)
    n, degree = 120, 3
    world_pts = np.array([1e4, -2e4, 30.0]) + rng.normal(size=(n, 3)) * np.array([8.0, 8.0, 3.0])
    eye = np.array([1e4 - 25.0, -2e4 + 3.0, 32.0])
    w2c_world = look_at(eye, np.array([1e4, -2e4, 30.0]))
    norm = Sim3(0.05, Rotation.random(random_state=4).as_matrix(), np.zeros(3), center=[1e4 - 5.0, -2e4, 29.0])
    a = _arrays(n, degree, seed=5)
    a["means"] = norm.apply(world_pts).astype(np.float32)
    a["log_scales"] = np.log(rng.uniform(0.3, 1.5, size=(n, 3)) * norm.s).astype(np.float32)
    a["logit_opacities"] = np.full(n, 1.0, np.float32)
    a["shN"] *= 0.3
    path = write_ply(tmp_path / "splats.ply", a, norm)
    world = read_ply(path)
    np.testing.assert_allclose(world["means"], world_pts, rtol=1e-6)
    back = read_ply(path, norm)  # into the training frame again
    for k in ("means", "log_scales", "sh0", "shN", "logit_opacities"):
        np.testing.assert_allclose(back[k], a[k], atol=2e-4, err_msg=k)
    q_back = back["quats"] / np.linalg.norm(back["quats"], axis=1, keepdims=True)
    q_a = a["quats"] / np.linalg.norm(a["quats"], axis=1, keepdims=True)
    np.testing.assert_allclose(np.abs(np.sum(q_back * q_a, axis=1)), 1.0, atol=1e-5)

    W, H = 64, 48
    K = torch.tensor(intrinsics(W, H, 70.0))

    def draw(arr: dict[str, np.ndarray], w2c: np.ndarray) -> tuple[torch.Tensor, ...]:
        t = {k: torch.from_numpy(v.astype(np.float64)) for k, v in arr.items()}
        # The world frame is far from the origin: draw it relative to the camera (same maths, exact).
        return render(
            t["means"],
            t["quats"],
            t["log_scales"].exp(),
            torch.sigmoid(t["logit_opacities"]),
            torch.cat([t["sh0"], t["shN"]], dim=1),
            torch.from_numpy(w2c),
            K,
            W,
            H,
            sh_degree=degree,
        )

    # The file holds float32 world coordinates near 1e4 (quantised to ~1e-3); the transform itself is
    # checked in float64, and the file against the float64 transform.
    world64 = to_world(a, norm)
    for k in world64:
        np.testing.assert_allclose(world[k], world64[k], rtol=1e-6, atol=1e-6, err_msg=k)
    rgb_n, depth_n, alpha_n, normals_n, _ = draw(a, norm.transform_w2c(w2c_world))
    world64["means"] = world64["means"] - eye  # translate the scene and camera together
    w2c_shift = w2c_world.copy()
    w2c_shift[:3, 3] = w2c_world[:3, :3] @ eye + w2c_world[:3, 3]
    rgb_w, depth_w, alpha_w, normals_w, _ = draw(world64, w2c_shift)
    assert alpha_n.mean() > 0.3
    np.testing.assert_allclose(rgb_w.numpy(), rgb_n.numpy(), atol=1e-8)
    np.testing.assert_allclose(alpha_w.numpy(), alpha_n.numpy(), atol=1e-8)
    np.testing.assert_allclose(normals_w.numpy(), normals_n.numpy(), atol=1e-8)
    np.testing.assert_allclose(norm.s * depth_w.numpy(), depth_n.numpy(), atol=1e-8 * depth_n.numpy().max())

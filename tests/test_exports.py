"""Exports for other tools: COLMAP text model (read back by pycolmap), nerfstudio transforms.json, camera path."""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image
from scipy.spatial.transform import Rotation

from wonderverse.camera import camera_centers, intrinsics, look_at
from wonderverse.exports import (
    read_camera_path,
    read_colmap_poses,
    read_nerfstudio_poses,
    write_camera_path,
    write_colmap_text,
    write_nerfstudio,
)

W, H = 64, 48


def _poses(n: int, seed: int = 0) -> np.ndarray:
    """Random rigid W2C poses with translations of a few metres."""
    rng = np.random.default_rng(seed)
    out = np.tile(np.eye(4), (n, 1, 1))
    out[:, :3, :3] = Rotation.random(n, random_state=seed).as_matrix()
    out[:, :3, 3] = rng.uniform(-5.0, 5.0, (n, 3))
    return out


def _assert_same_poses(a: np.ndarray, b: np.ndarray) -> None:
    np.testing.assert_allclose(a[:, :3, :3], b[:, :3, :3], rtol=0, atol=1e-9)
    np.testing.assert_allclose(a[:, :3, 3], b[:, :3, 3], rtol=0, atol=1e-9)


# ------------------------------------------------------------------------------------------------ COLMAP


def test_colmap_text_round_trip_through_pycolmap(tmp_path: Path) -> None:
    w2c = _poses(8)
    w2c[[2, 5]] = np.nan
    names = [f"frame_{i:05d}.png" for i in range(8)]
    K = intrinsics(W, H, 70.0)
    rng = np.random.default_rng(1)
    pts = rng.uniform(-3, 3, (20, 3))
    cols = rng.integers(0, 256, (20, 3), dtype=np.uint8)
    write_colmap_text(tmp_path, K, w2c, W, H, names, pts, cols)
    back = read_colmap_poses(tmp_path)
    keep = [0, 1, 3, 4, 6, 7]
    assert back.names == [names[i] for i in keep]
    _assert_same_poses(back.w2c, w2c[keep])
    np.testing.assert_allclose(back.K, np.broadcast_to(K, (6, 3, 3)), rtol=0, atol=1e-12)
    assert (back.width, back.height) == (W, H)
    rec = pycolmap.Reconstruction(str(tmp_path))
    assert len(rec.cameras) == 1 and rec.cameras[1].model.name == "PINHOLE"
    assert sorted(rec.images) == [i + 1 for i in keep]  # ids are input index + 1
    xyz = np.array([rec.points3D[j + 1].xyz for j in range(20)])
    rgb = np.array([rec.points3D[j + 1].color for j in range(20)])
    np.testing.assert_allclose(xyz, pts, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(rgb, cols)


def test_colmap_pose_convention_projects_like_ours(tmp_path: Path) -> None:
    # A camera at a known place looking at a known point: pycolmap must put that point at the principal point
    # and a point to the camera's right (world) at larger u, below it at larger v.
    eye, target = np.array([1.0, -4.0, 2.0]), np.array([0.5, 1.0, 1.0])
    w2c = look_at(eye, target)[None]
    K = intrinsics(W, H, 60.0)
    write_colmap_text(tmp_path, K, w2c, W, H, ["a.png"])
    rec = pycolmap.Reconstruction(str(tmp_path))
    im, cam = rec.images[1], rec.cameras[1]
    np.testing.assert_allclose(im.projection_center(), eye, atol=1e-12)
    np.testing.assert_allclose(cam.img_from_cam(im.cam_from_world() * target), [W / 2, H / 2], atol=1e-9)
    right = w2c[0, 0, :3]  # camera x axis in world coordinates
    below = w2c[0, 1, :3]
    u, v = cam.img_from_cam(im.cam_from_world() * (target + 0.1 * right))
    assert u > W / 2 + 1 and abs(v - H / 2) < 1e-9
    u, v = cam.img_from_cam(im.cam_from_world() * (target + 0.1 * below))
    assert v > H / 2 + 1 and abs(u - W / 2) < 1e-9
    # The quaternion in images.txt is scalar-first, as COLMAP defines it.
    line = next(s for s in (tmp_path / "images.txt").read_text().splitlines() if s and not s.startswith("#"))
    q = np.array([float(v) for v in line.split()[1:5]])
    xyzw = Rotation.from_matrix(w2c[0, :3, :3]).as_quat()
    np.testing.assert_allclose(np.abs(q @ np.r_[xyzw[3], xyzw[:3]]), 1.0, atol=1e-12)


def test_colmap_per_image_intrinsics_and_no_points(tmp_path: Path) -> None:
    w2c = _poses(3, seed=4)
    Ks = np.stack([intrinsics(W, H, f) for f in (50.0, 60.0, 70.0)])
    write_colmap_text(tmp_path, Ks, w2c, W, H, ["a.png", "b.png", "c.png"])
    back = read_colmap_poses(tmp_path)
    _assert_same_poses(back.w2c, w2c)
    np.testing.assert_allclose(back.K, Ks, rtol=0, atol=1e-12)
    assert len(pycolmap.Reconstruction(str(tmp_path)).points3D) == 0


def test_colmap_rejects_bad_input(tmp_path: Path) -> None:
    K = intrinsics(W, H, 60.0)
    with pytest.raises(ValueError, match="unique"):
        write_colmap_text(tmp_path, K, _poses(2), W, H, ["a.png", "a.png"])
    with pytest.raises(ValueError, match="whitespace"):
        write_colmap_text(tmp_path, K, _poses(1), W, H, ["a b.png"])
    with pytest.raises(ValueError, match="one name per pose"):
        write_colmap_text(tmp_path, K, _poses(2), W, H, ["a.png"])
    skewed = K.copy()
    skewed[0, 1] = 1.0
    with pytest.raises(ValueError, match="skew"):
        write_colmap_text(tmp_path, skewed, _poses(1), W, H, ["a.png"])


@settings(max_examples=25, deadline=None)
@given(
    quat=st.lists(st.floats(-1.0, 1.0), min_size=4, max_size=4).filter(lambda q: np.linalg.norm(q) > 1e-3),
    t=st.lists(st.floats(-1e3, 1e3), min_size=3, max_size=3),
)
def test_colmap_round_trip_any_pose(quat: list[float], t: list[float]) -> None:
    w2c = np.eye(4)[None].copy()
    w2c[0, :3, :3] = Rotation.from_quat(quat).as_matrix()
    w2c[0, :3, 3] = t
    with tempfile.TemporaryDirectory() as d:
        write_colmap_text(Path(d), intrinsics(W, H, 60.0), w2c, W, H, ["x.png"])
        back = read_colmap_poses(Path(d))
    _assert_same_poses(back.w2c, w2c)


# -------------------------------------------------------------------------------------------- nerfstudio


def test_nerfstudio_round_trip_and_images(tmp_path: Path) -> None:
    rng = np.random.default_rng(2)
    frames = rng.integers(0, 256, (5, H, W, 3), dtype=np.uint8)
    w2c = _poses(5, seed=3)
    w2c[1] = np.nan
    K = intrinsics(W, H, 65.0)
    path = write_nerfstudio(tmp_path, frames, K, w2c)
    meta = json.loads(path.read_text())
    assert meta["camera_model"] == "OPENCV" and (meta["w"], meta["h"]) == (W, H)
    assert all(meta[k] == 0.0 for k in ("k1", "k2", "p1", "p2"))
    assert (meta["fl_x"], meta["fl_y"], meta["cx"], meta["cy"]) == (K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    keep = [0, 2, 3, 4]
    back = read_nerfstudio_poses(path)
    assert back.names == [f"images/frame_{i:05d}.png" for i in keep]
    _assert_same_poses(back.w2c, w2c[keep])
    np.testing.assert_allclose(back.K, np.broadcast_to(K, (4, 3, 3)), rtol=0, atol=0)
    for name, i in zip(back.names, keep, strict=True):
        img = np.asarray(Image.open(tmp_path / name))
        assert img.shape == (H, W, 3)
        np.testing.assert_array_equal(img, frames[i])  # PNG is lossless
    assert not (tmp_path / "images" / "frame_00001.png").exists()


def test_nerfstudio_transform_matrix_is_opengl_camera_to_world(tmp_path: Path) -> None:
    # A camera at `eye` looking at `target` with no roll: in OpenGL axes it looks down its -z and its +y is up.
    eye, target = np.array([2.0, 3.0, 1.0]), np.array([-1.0, 5.0, 0.0])
    w2c = look_at(eye, target)[None]
    frames = np.zeros((1, H, W, 3), dtype=np.uint8)
    path = write_nerfstudio(tmp_path, frames, intrinsics(W, H, 60.0), w2c, names=["shot"])
    T = np.array(json.loads(path.read_text())["frames"][0]["transform_matrix"])
    assert json.loads(path.read_text())["frames"][0]["file_path"] == "images/shot.png"
    np.testing.assert_allclose(T[:3, 3], eye, atol=1e-12)
    view = (target - eye) / np.linalg.norm(target - eye)
    np.testing.assert_allclose(-T[:3, 2], view, atol=1e-12)
    assert T[2, 1] > 0.0  # camera up has a positive world-z component
    np.testing.assert_allclose(T[3], [0, 0, 0, 1])


def test_nerfstudio_per_frame_intrinsics(tmp_path: Path) -> None:
    Ks = np.stack([intrinsics(W, H, 50.0), intrinsics(W, H, 80.0)])
    path = write_nerfstudio(tmp_path, np.zeros((2, H, W, 3), np.uint8), Ks, _poses(2), names=["a.png", "b.png"])
    meta = json.loads(path.read_text())
    assert "fl_x" not in meta and meta["frames"][1]["fl_x"] == Ks[1, 0, 0]
    np.testing.assert_allclose(read_nerfstudio_poses(path).K, Ks, rtol=0, atol=0)


# ------------------------------------------------------------------------------------------- camera path


def test_camera_path_round_trip_and_convention(tmp_path: Path) -> None:
    w2c = _poses(6, seed=5)
    K = intrinsics(W, H, 60.0)
    path = write_camera_path(tmp_path / "sub" / "path.json", w2c, K, W, H, fps=24.0)
    d = json.loads(path.read_text())
    for word in ("W2C", "row-major", "OpenCV", "+z up", "world units", "+0.5"):
        assert word.lower() in d["convention"].lower()
    assert [f["time_s"] for f in d["frames"]] == [i / 24.0 for i in range(6)]
    np.testing.assert_allclose(np.array([f["center"] for f in d["frames"]]), camera_centers(w2c), atol=1e-12)
    back, fps = read_camera_path(path)
    assert fps == 24.0 and (back.width, back.height) == (W, H)
    np.testing.assert_array_equal(back.w2c, w2c)  # JSON floats are exact
    np.testing.assert_array_equal(back.K, np.broadcast_to(K, (6, 3, 3)))
    assert back.names == [f"{i:05d}" for i in range(6)]


def test_camera_path_per_frame_intrinsics_and_nan(tmp_path: Path) -> None:
    Ks = np.stack([intrinsics(W, H, f) for f in (40.0, 60.0)])
    path = write_camera_path(tmp_path / "p.json", _poses(2), Ks, W, H, fps=30.0, names=["a", "b"])
    back, _ = read_camera_path(path)
    np.testing.assert_array_equal(back.K, Ks)
    assert back.names == ["a", "b"]
    bad = _poses(2)
    bad[1] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        write_camera_path(tmp_path / "q.json", bad, Ks[0], W, H, fps=30.0)
    (tmp_path / "other.json").write_text('{"format": "something else"}')
    with pytest.raises(ValueError, match="not a"):
        read_camera_path(tmp_path / "other.json")

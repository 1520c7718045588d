"""Exports for other tools: the COLMAP dataset (read back by pycolmap, and parsed by COLMAP's documented binary
layout as the trainers' own readers do), the nerfstudio dataset with depth PNGs, points and camera paths (checked
against the keys and conventions nerfstudio's data parser and camera-path loader read), our camera path."""

from __future__ import annotations

import json
import struct
import tempfile
from pathlib import Path

import numpy as np
import open3d as o3d
import pycolmap
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image
from scipy.spatial.transform import Rotation

from wonderverse.camera import camera_centers, intrinsics, look_at
from wonderverse.exports import (
    OPENCV_TO_OPENGL,
    ColmapTracks,
    depth_png_scale,
    fits_scale,
    nerfstudio_dataparser_frame,
    project_tracks,
    read_camera_path,
    read_colmap_poses,
    read_colmap_tracks,
    read_nerfstudio_poses,
    write_camera_path,
    write_colmap_dataset,
    write_nerfstudio,
    write_nerfstudio_camera_path,
)
from wonderverse.mesh import PointCloud

W, H = 64, 48


def _poses(n: int, seed: int = 0) -> np.ndarray:
    """Random rigid W2C poses with translations of a few metres."""
    rng = np.random.default_rng(seed)
    out = np.tile(np.eye(4), (n, 1, 1))
    out[:, :3, :3] = Rotation.random(n, random_state=seed).as_matrix()
    out[:, :3, 3] = rng.uniform(-5.0, 5.0, (n, 3))
    return out


def _ring(n: int, radius: float = 4.0) -> np.ndarray:
    """Cameras on a circle at height 1.5, all looking at the origin (they all see points near it)."""
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.stack([look_at(np.array([radius * np.cos(t), radius * np.sin(t), 1.5]), np.zeros(3)) for t in a])


def _frames(n: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (n, H, W, 3), dtype=np.uint8)


def _assert_same_poses(a: np.ndarray, b: np.ndarray) -> None:
    np.testing.assert_allclose(a[:, :3, :3], b[:, :3, :3], rtol=0, atol=1e-9)
    np.testing.assert_allclose(a[:, :3, 3], b[:, :3, 3], rtol=0, atol=1e-9)


# ------------------------------------------------------------------------------------------------ COLMAP


def _read_images_bin(path: Path) -> dict[int, dict]:
    """images.bin by COLMAP's documented binary layout (what INRIA 3DGS and other trainers' readers parse):
    uint64 count; per image uint32 id, 4 double qw qx qy qz, 3 double t, uint32 camera id, name NUL-ended,
    uint64 n, n x (double x, double y, int64 point id)."""
    data, out, at = path.read_bytes(), {}, 8
    for _ in range(struct.unpack_from("<Q", data, 0)[0]):
        image_id, *qt, cam = struct.unpack_from("<I7dI", data, at)
        at += 64
        end = data.index(b"\0", at)
        name, at = data[at:end].decode(), end + 1
        (n,) = struct.unpack_from("<Q", data, at)
        at += 8
        pts = np.array(struct.unpack_from(f"<{'ddq' * n}", data, at)).reshape(n, 3) if n else np.zeros((0, 3))
        at += 24 * n
        out[image_id] = {"q": np.array(qt[:4]), "t": np.array(qt[4:]), "camera": cam, "name": name, "points": pts}
    assert at == len(data)
    return out


def _read_points_bin(path: Path) -> dict[int, dict]:
    """points3D.bin by COLMAP's documented layout: uint64 count; per point uint64 id, 3 double xyz, 3 uint8
    rgb, double error, uint64 track length, length x (int32 image id, int32 point2D index)."""
    data, out, at = path.read_bytes(), {}, 8
    for _ in range(struct.unpack_from("<Q", data, 0)[0]):
        pid, x, y, z, r, g, b, err, n = struct.unpack_from("<Q3d3BdQ", data, at)
        at += 51
        track = np.array(struct.unpack_from(f"<{2 * n}i", data, at)).reshape(n, 2)
        at += 8 * n
        out[pid] = {"xyz": np.array([x, y, z]), "rgb": (r, g, b), "error": err, "track": track}
    assert at == len(data)
    return out


def _projected_tracks(w2c: np.ndarray, K: np.ndarray, n_points: int = 40, seed: int = 0) -> ColmapTracks:
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-1.0, 1.0, (n_points, 3))
    obs = project_tracks(pts, w2c, K, W, H)
    return ColmapTracks(pts, rng.integers(0, 256, (n_points, 3), dtype=np.uint8), rng.random(n_points), obs)


def test_colmap_dataset_opens_in_pycolmap_with_images_tracks_and_our_poses(tmp_path: Path) -> None:
    w2c = _ring(8)
    w2c[[2, 5]] = np.nan
    names = [f"s000_{i:04d}" for i in range(8)]
    K = intrinsics(W, H, 70.0)
    frames = _frames(8)
    tracks = _projected_tracks(w2c, K)
    out = write_colmap_dataset(tmp_path / "colmap", frames, K, w2c, names, tracks)
    model = out / "sparse" / "0"
    assert {p.name for p in model.iterdir()} >= {"cameras.bin", "images.bin", "points3D.bin"}
    rec = pycolmap.Reconstruction(str(model))
    keep = [0, 1, 3, 4, 6, 7]
    assert sorted(rec.images) == [i + 1 for i in keep]  # ids are input index + 1
    assert len(rec.cameras) == 1 and rec.cameras[1].model.name == "PINHOLE"
    np.testing.assert_allclose(rec.cameras[1].calibration_matrix(), K, atol=1e-12)
    for i in keep:
        im = rec.images[i + 1]
        assert im.name == f"{names[i]}.png"
        np.testing.assert_array_equal(np.asarray(Image.open(out / "images" / im.name)), frames[i])
    assert sorted(p.name for p in (out / "images").iterdir()) == [f"{names[i]}.png" for i in keep]
    back = read_colmap_poses(model)
    _assert_same_poses(back.w2c, w2c[keep])
    # every point has a track of at least two of the written images, and the observations reproject exactly
    assert len(rec.points3D) > 20
    assert all(p.track.length() >= 2 for p in rec.points3D.values())
    for p in rec.points3D.values():
        for el in p.track.elements:
            im = rec.images[el.image_id]
            uv = im.camera.img_from_cam(im.cam_from_world() * p.xyz)
            np.testing.assert_allclose(uv, im.points2D[el.point2D_idx].xy, atol=1e-9)
    errors = {tuple(np.round(p.xyz, 9)): p.error for p in rec.points3D.values()}
    for j, xyz in enumerate(tracks.points):  # each written point keeps its own error
        if tuple(np.round(xyz, 9)) in errors:
            assert errors[tuple(np.round(xyz, 9))] == pytest.approx(tracks.errors[j])
    read, read_names, sizes = read_colmap_tracks(model)
    assert read_names == [f"{names[i]}.png" for i in keep] and set(sizes) == {(W, H)}
    assert sum(len(o[1]) for o in read.observations) == rec.compute_num_observations()


def test_colmap_binary_files_have_colmaps_classic_layout(tmp_path: Path) -> None:
    # Readers other than COLMAP (INRIA 3DGS's colmap_loader, older gsplat/nerfstudio parsers) parse the bytes
    # themselves: images.bin and points3D.bin must keep the layout COLMAP has always written.
    w2c, K = _ring(5), intrinsics(W, H, 60.0)
    tracks = _projected_tracks(w2c, K, 30, seed=3)
    out = write_colmap_dataset(tmp_path, _frames(5), K, w2c, [f"f{i}" for i in range(5)], tracks)
    images = _read_images_bin(out / "sparse" / "0" / "images.bin")
    assert sorted(images) == [1, 2, 3, 4, 5]
    for i, im in images.items():
        assert im["name"] == f"f{i - 1}.png" and im["camera"] == 1
        R = Rotation.from_quat(np.r_[im["q"][1:], im["q"][0]]).as_matrix()  # COLMAP's quaternion: w first
        np.testing.assert_allclose(R, w2c[i - 1, :3, :3], atol=1e-12)
        np.testing.assert_allclose(im["t"], w2c[i - 1, :3, 3], atol=1e-12)
    points = _read_points_bin(out / "sparse" / "0" / "points3D.bin")
    assert points and all(len(p["track"]) >= 2 for p in points.values())
    for pid, p in points.items():
        for image_id, idx in p["track"]:  # each track element is a 2-D point of that image, pointing back
            assert images[image_id]["points"][idx, 2] == pid
            uv = K @ (w2c[image_id - 1, :3, :3] @ p["xyz"] + w2c[image_id - 1, :3, 3])
            np.testing.assert_allclose(images[image_id]["points"][idx, :2], uv[:2] / uv[2], atol=1e-9)


def test_project_tracks_keeps_only_points_the_depth_sees(tmp_path: Path) -> None:
    w2c = look_at(np.array([0.0, -5.0, 0.0]), np.zeros(3))[None]
    K = intrinsics(W, H, 60.0)
    near, far, behind = [0.0, 0.0, 0.0], [0.1, 3.0, 0.0], [0.0, -6.0, 0.0]  # far: hidden by a wall at depth 5
    depth = np.full((H // 2, W // 2), 5.0)  # half-resolution depth map, its own intrinsics
    ((xy, idx),) = project_tracks(
        np.array([near, far, behind]), w2c, K, W, H, [depth], intrinsics(W // 2, H // 2, 60.0)
    )
    assert idx.tolist() == [0]
    np.testing.assert_allclose(xy[0], [W / 2, H / 2], atol=1e-9)
    ((_, idx),) = project_tracks(np.array([near, far, behind]), w2c, K, W, H)  # no depth: every point in front
    assert idx.tolist() == [0, 1]


def test_colmap_per_image_intrinsics_and_no_points(tmp_path: Path) -> None:
    w2c = _poses(3, seed=4)
    Ks = np.stack([intrinsics(W, H, f) for f in (50.0, 60.0, 70.0)])
    out = write_colmap_dataset(tmp_path, _frames(3), Ks, w2c, ["a", "b", "c"])
    back = read_colmap_poses(out / "sparse" / "0")
    _assert_same_poses(back.w2c, w2c)
    np.testing.assert_allclose(back.K, Ks, rtol=0, atol=1e-12)
    assert len(pycolmap.Reconstruction(str(out / "sparse" / "0")).points3D) == 0


def test_colmap_rejects_bad_input(tmp_path: Path) -> None:
    K = intrinsics(W, H, 60.0)
    with pytest.raises(ValueError, match="unique"):
        write_colmap_dataset(tmp_path, _frames(2), K, _poses(2), ["a", "a"])
    with pytest.raises(ValueError, match="whitespace"):
        write_colmap_dataset(tmp_path, _frames(1), K, _poses(1), ["a b"])
    with pytest.raises(ValueError, match="one name per pose"):
        write_colmap_dataset(tmp_path, _frames(2), K, _poses(2), ["a"])
    with pytest.raises(ValueError, match="one pose per frame"):
        write_colmap_dataset(tmp_path, _frames(3), K, _poses(2), ["a", "b"])
    skewed = K.copy()
    skewed[0, 1] = 1.0
    with pytest.raises(ValueError, match="skew"):
        write_colmap_dataset(tmp_path, _frames(1), skewed, _poses(1), ["a"])


@settings(max_examples=15, deadline=None)
@given(
    quat=st.lists(st.floats(-1.0, 1.0), min_size=4, max_size=4).filter(lambda q: np.linalg.norm(q) > 1e-3),
    t=st.lists(st.floats(-1e3, 1e3), min_size=3, max_size=3),
)
def test_colmap_round_trip_any_pose(quat: list[float], t: list[float]) -> None:
    w2c = np.eye(4)[None].copy()
    w2c[0, :3, :3] = Rotation.from_quat(quat).as_matrix()
    w2c[0, :3, 3] = t
    with tempfile.TemporaryDirectory() as d:
        out = write_colmap_dataset(Path(d), _frames(1), intrinsics(W, H, 60.0), w2c, ["x"])
        back = read_colmap_poses(out / "sparse" / "0")
    _assert_same_poses(back.w2c, w2c)


# -------------------------------------------------------------------------------------------- nerfstudio


def _ns_dataparser(meta: dict) -> tuple[np.ndarray, float]:
    """nerfstudio's data-parser frame as its documentation and source describe it, for orientation "none"
    (what our files ask with orientation_override), center_method "poses", auto_scale_poses, scale_factor 1:
    centre = mean of the frames' transform_matrix translations; scale = 1 / max |centred translation|."""
    t = np.array([np.asarray(f["transform_matrix"])[:3, 3] for f in meta["frames"]])
    centre = t.mean(0)
    return centre, 1.0 / np.abs(t - centre).max()


def test_nerfstudio_dataset_has_the_keys_its_parser_reads(tmp_path: Path) -> None:
    frames = _frames(5, seed=2)
    w2c = _ring(5)
    w2c[1] = np.nan
    K = intrinsics(W, H, 65.0)
    rng = np.random.default_rng(0)
    depths = [np.where(rng.random((H // 2, W // 2)) < 0.2, np.inf, rng.uniform(1.0, 9.0, (H // 2, W // 2)))] * 5
    cloud = PointCloud(rng.normal(size=(50, 3)), rng.random((50, 3)), np.tile([0.0, 0.0, 1.0], (50, 1)))
    path, stats = write_nerfstudio(tmp_path, frames, K, w2c, None, depths, cloud, "world: +Z up, metres")
    meta = json.loads(path.read_text())
    # NerfstudioDataParser: camera_model in CAMERA_MODEL_TO_TYPE, shared intrinsics and size at the top level
    assert meta["camera_model"] == "OPENCV" and (meta["w"], meta["h"]) == (W, H)
    assert all(meta[k] == 0.0 for k in ("k1", "k2", "p1", "p2"))
    assert (meta["fl_x"], meta["fl_y"], meta["cx"], meta["cy"]) == (K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    assert meta["orientation_override"] == "none"  # keep our +Z up; nerfstudio's world is +Z up too
    assert "applied_transform" not in meta and "applied_scale" not in meta
    keep = [0, 2, 3, 4]
    assert len(meta["frames"]) == len(keep)
    for f, i in zip(meta["frames"], keep, strict=True):
        assert np.asarray(f["transform_matrix"]).shape == (4, 4)
        np.testing.assert_array_equal(np.asarray(Image.open(tmp_path / f["file_path"])), frames[i])
        # depth: a 16-bit PNG (cv2.IMREAD_ANYDEPTH reads it as uint16) of thousandths of the file's unit
        png = np.asarray(Image.open(tmp_path / f["depth_file_path"]))
        assert png.dtype in (np.uint16, np.int32) and png.shape == depths[i].shape
        a = stats["scale_from_world"]
        expect = np.where(np.isfinite(depths[i]), np.round(depths[i] * a * 1000), 0)
        np.testing.assert_array_equal(png.astype(np.int64), expect.astype(np.int64))
    assert stats["scale_from_world"] == 1.0 and stats["depth_clipped"] == 0  # 1-9 m: millimetres as they are
    # ply_file_path: open3d (what the parser loads it with) reads the points and their colours
    pcd = o3d.io.read_point_cloud(str(tmp_path / meta["ply_file_path"]))
    np.testing.assert_allclose(np.asarray(pcd.points), cloud.points, atol=1e-5)
    np.testing.assert_allclose(np.asarray(pcd.colors), cloud.colors, atol=0.5 / 255 + 1e-9)
    assert pcd.has_normals()
    back = read_nerfstudio_poses(path)
    _assert_same_poses(back.w2c, w2c[keep])
    assert not (tmp_path / "images" / "frame_00001.png").exists()


def test_nerfstudio_depth_units_fit_the_png(tmp_path: Path) -> None:
    # depths of hundreds of units (SfM's scale) would overflow 16-bit millimetres: the dataset is scaled by a
    # power of ten, and nerfstudio's reading (PNG x 1e-3 x its scene scale) still gives the depth in its frame
    assert depth_png_scale([np.full((4, 4), 300.0)]) == 0.1
    assert depth_png_scale([np.full((4, 4), 0.02)]) == 1000.0
    assert depth_png_scale([np.full((4, 4), 3.0), np.full((2, 2), np.inf)]) == 1.0
    assert depth_png_scale([np.full((4, 4), np.inf)]) == 1.0
    # an extension's frames 30 units away would get 1 alone; files at 0.1 hold them at 3 000 thousandths: kept
    assert fits_scale([np.full((4, 4), 30.0)], 0.1) and fits_scale([np.full((4, 4), 300.0)], 0.1)
    assert not fits_scale([np.full((4, 4), 700.0)], 0.1)  # 70 file units: beyond 16 bits of thousandths
    assert not fits_scale([np.full((4, 4), 3.0)], 0.1)  # 0.3 file units: two significant digits
    w2c = _ring(4, radius=200.0)
    depths = [np.full((H, W), 200.0 + k) for k in range(4)]
    path, stats = write_nerfstudio(tmp_path, _frames(4), intrinsics(W, H, 60.0), w2c, None, depths)
    meta = json.loads(path.read_text())
    assert stats["scale_from_world"] == 0.1 and meta["wonderverse"]["scale_from_world"] == 0.1
    _, ns_scale = _ns_dataparser(meta)
    for k, f in enumerate(meta["frames"]):
        png = np.asarray(Image.open(tmp_path / f["depth_file_path"])).astype(np.float64)
        # nerfstudio: depth in its frame = PNG * depth_unit_scale_factor (1e-3) * dataparser scale
        np.testing.assert_allclose(png * 1e-3 * ns_scale, depths[k] * 0.1 * ns_scale, rtol=1e-4)
    _assert_same_poses(read_nerfstudio_poses(path).w2c, w2c)  # the reader undoes the scale


def test_nerfstudio_transform_matrix_is_opengl_camera_to_world(tmp_path: Path) -> None:
    # A camera at `eye` looking at `target` with no roll: in OpenGL axes it looks down its -z and its +y is up.
    eye, target = np.array([2.0, 3.0, 1.0]), np.array([-1.0, 5.0, 0.0])
    w2c = look_at(eye, target)[None]
    path, _ = write_nerfstudio(tmp_path, np.zeros((1, H, W, 3), np.uint8), intrinsics(W, H, 60.0), w2c, ["shot"])
    frame = json.loads(path.read_text())["frames"][0]
    T = np.array(frame["transform_matrix"])
    assert frame["file_path"] == "images/shot.png"
    np.testing.assert_allclose(T[:3, 3], eye, atol=1e-12)
    view = (target - eye) / np.linalg.norm(target - eye)
    np.testing.assert_allclose(-T[:3, 2], view, atol=1e-12)
    assert T[2, 1] > 0.0  # camera up has a positive world-z component
    np.testing.assert_allclose(T[3], [0, 0, 0, 1])


def test_nerfstudio_per_frame_intrinsics(tmp_path: Path) -> None:
    Ks = np.stack([intrinsics(W, H, 50.0), intrinsics(W, H, 80.0)])
    path, _ = write_nerfstudio(tmp_path, np.zeros((2, H, W, 3), np.uint8), Ks, _poses(2), names=["a.png", "b.png"])
    meta = json.loads(path.read_text())
    assert "fl_x" not in meta and meta["frames"][1]["fl_x"] == Ks[1, 0, 0]
    np.testing.assert_allclose(read_nerfstudio_poses(path).K, Ks, rtol=0, atol=0)


def test_nerfstudio_camera_path_renders_our_cameras_in_its_frame(tmp_path: Path) -> None:
    """The keys nerfstudio's camera-path loader (get_path_from_json), ns-render (seconds) and the viewer's path
    loader (keyframes) read, and the cameras they describe: nerfstudio's camera (c2w in its data-parser frame,
    fx = fy from the vertical fov, principal point at the centre) projects world points where ours does."""
    w2c = _ring(6, radius=30.0)
    K = intrinsics(W, H, 55.0)
    dataset, _ = write_nerfstudio(tmp_path, _frames(6), K, w2c, None, [np.full((H, W), 30.0)] * 6)
    meta = json.loads(dataset.read_text())
    path = _ring(23, radius=25.0)
    a = meta["wonderverse"]["scale_from_world"]
    frame = nerfstudio_dataparser_frame(w2c)  # from our world poses: the same map as from the file's
    cam_path = write_nerfstudio_camera_path(tmp_path / "camera_paths" / "fly.json", path, K, W, H, 12.0, frame, "w")
    d = json.loads(cam_path.read_text())
    assert d["camera_type"] == "perspective" and (d["render_width"], d["render_height"]) == (W, H)
    assert d["seconds"] == pytest.approx(23 / 12.0) and d["fps"] == 12.0
    assert len(d["camera_path"]) == 23 and {"smoothness_value", "is_cycle", "default_fov"} <= set(d)
    assert [len(k["matrix"]) for k in d["keyframes"]] == [16] * len(d["keyframes"]) and len(d["keyframes"]) >= 3
    centre_ns, scale_ns = _ns_dataparser(meta)  # from transforms.json alone, as nerfstudio computes it
    rng = np.random.default_rng(0)
    world_pts = rng.uniform(-3, 3, (10, 3))
    for entry, pose in zip(d["camera_path"], path, strict=True):
        c2w = np.asarray(entry["camera_to_world"], np.float64).reshape(4, 4)  # row-major, OpenGL axes
        f = 0.5 * H / np.tan(np.radians(entry["fov"]) / 2)  # nerfstudio: fx = fy from the vertical fov
        assert entry["aspect"] == pytest.approx(W / H)
        p_ns = (world_pts * a - centre_ns) * scale_ns  # the points in nerfstudio's frame
        cam = (p_ns - c2w[:3, 3]) @ c2w[:3, :3]  # OpenGL camera coordinates: x right, y up, z back
        uv_ns = np.column_stack([f * cam[:, 0] / -cam[:, 2] + W / 2, -f * cam[:, 1] / -cam[:, 2] + H / 2])
        ours = (world_pts @ pose[:3, :3].T + pose[:3, 3]) @ K.T
        np.testing.assert_allclose(uv_ns, ours[:, :2] / ours[:, 2:], atol=1e-6)


# ------------------------------------------------------------------------------------------- camera path


def test_camera_path_round_trip_and_convention(tmp_path: Path) -> None:
    w2c = _poses(6, seed=5)
    K = intrinsics(W, H, 60.0)
    world = "world frame: right-handed, +Z up, origin on the ground; units: SfM units"
    path = write_camera_path(tmp_path / "sub" / "path.json", w2c, K, W, H, fps=24.0, world=world)
    d = json.loads(path.read_text())
    assert d["format"] == "wonderverse.camera_path/2" and d["world"] == world
    for word in ("W2C", "row-major", "OpenCV", "world", "+0.5"):
        assert word.lower() in d["convention"].lower()
    assert "+z up" not in d["convention"].lower()  # the frame is the one stated in `world`, not assumed
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


def test_opengl_flip_is_its_own_inverse() -> None:
    np.testing.assert_array_equal(OPENCV_TO_OPENGL @ OPENCV_TO_OPENGL, np.eye(4))

"""Mesh and point-cloud export with real Open3D and trimesh, and the Chamfer/F-score metric.

The scene for fusion is built here: a square ground plane with a box on it (and, where asked, a small
floating cube), ray-cast exactly with numpy, so the surface the mesh must lie on is known in closed form.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
import trimesh

from wonderverse.camera import Sim3, intrinsics, look_at, scene_extent
from wonderverse.mesh import (
    SH_C0,
    MeshParams,
    PointCloud,
    TriMesh,
    TsdfFusion,
    clean_mesh,
    fuse_tsdf,
    fusion_cameras,
    gaussian_points,
    write_mesh,
    write_points_ply,
)
from wonderverse.metrics import chamfer_fscore, sample_mesh_points

W, H = 80, 60
K = intrinsics(W, H, 60.0)
HALF = 1.5  # ground plane |x|, |y| <= HALF, z = 0
BOX = (np.array([-0.3, -0.3, 0.0]), np.array([0.3, 0.3, 0.4]))
FLOATER = (np.array([0.9, -0.1, 1.0]), np.array([1.1, 0.1, 1.2]))
PLANE_RGB, BOX_RGB = np.array([0.5, 0.5, 0.5]), np.array([0.9, 0.1, 0.1])
EXTENT = 4.0
PARAMS = MeshParams(voxel_frac=1 / 128, trunc_voxels=4, max_depth_frac=2.0, min_component_frac=0.0)  # 3.1 cm


def ring_cameras(n: int = 8, radius: float = 3.0, height: float = 2.0) -> np.ndarray:
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.stack([look_at(np.array([radius * np.cos(t), radius * np.sin(t), height]), np.zeros(3)) for t in a])


def raycast(w2c: np.ndarray, boxes: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """Exact depth (H,W) float32 (+inf where the ray misses everything) and rgb (H,W,3) of the plane + boxes."""
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    d_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1).reshape(-1, 3)
    R = w2c[:3, :3]
    c = -R.T @ w2c[:3, 3]
    d = d_cam @ R  # world directions with camera z = 1, so the ray parameter is the depth
    with np.errstate(divide="ignore", invalid="ignore"):
        t_plane = np.where(d[:, 2] < 0, -c[2] / d[:, 2], np.inf)
        p = c + t_plane[:, None] * d
        t_plane = np.where((np.abs(p[:, 0]) <= HALF) & (np.abs(p[:, 1]) <= HALF), t_plane, np.inf)
        t_box = np.full(len(d), np.inf)
        for lo, hi in boxes:
            t0, t1 = (lo - c) / d, (hi - c) / d
            near, far = np.minimum(t0, t1).max(axis=1), np.maximum(t0, t1).min(axis=1)
            t_box = np.minimum(t_box, np.where((near <= far) & (near > 0), near, np.inf))
    depth = np.minimum(t_plane, t_box)
    rgb = np.where((t_box <= t_plane)[:, None], BOX_RGB, PLANE_RGB)
    return depth.reshape(H, W).astype(np.float32), rgb.reshape(H, W, 3)


def gt_points(n: int = 40_000) -> np.ndarray:
    """Points on the true surface: the plane square and the box's top and four sides."""
    (x0, y0, _), (x1, y1, z1) = BOX
    quads = [
        [(-HALF, -HALF, 0), (HALF, -HALF, 0), (HALF, HALF, 0), (-HALF, HALF, 0)],
        [(x0, y0, z1), (x1, y0, z1), (x1, y1, z1), (x0, y1, z1)],
        [(x0, y0, 0), (x1, y0, 0), (x1, y0, z1), (x0, y0, z1)],
        [(x0, y1, 0), (x1, y1, 0), (x1, y1, z1), (x0, y1, z1)],
        [(x0, y0, 0), (x0, y1, 0), (x0, y1, z1), (x0, y0, z1)],
        [(x1, y0, 0), (x1, y1, 0), (x1, y1, z1), (x1, y0, z1)],
    ]
    verts = np.array([p for q in quads for p in q], dtype=np.float64)
    tris = np.array(
        [[4 * i, 4 * i + 1, 4 * i + 2] for i in range(6)] + [[4 * i, 4 * i + 2, 4 * i + 3] for i in range(6)]
    )
    return sample_mesh_points(verts, tris, n, seed=3)


def views(boxes: list[tuple[np.ndarray, np.ndarray]] | None = None, n: int = 8):
    for w2c in ring_cameras(n):
        depth, rgb = raycast(w2c, [BOX] if boxes is None else boxes)
        yield rgb, depth, K, w2c


@pytest.fixture(scope="module")
def fused() -> TriMesh:
    return fuse_tsdf(views(), EXTENT, PARAMS)


def test_fused_mesh_lies_on_the_true_surface_and_covers_it(fused: TriMesh):
    voxel = EXTENT * PARAMS.voxel_frac
    assert len(fused.triangles) > 1000 and fused.triangles.dtype == np.int32
    pred = sample_mesh_points(fused.vertices, fused.triangles, 40_000, seed=1)
    m = chamfer_fscore(pred, gt_points(), [voxel, 2 * voxel])
    assert m["accuracy"] < 0.35 * voxel  # on the surface to a third of a voxel
    assert m["precision"][1] > 0.98
    assert m["recall"][1] > 0.9  # the plane under the box is never seen: a few percent missing
    # triangles wind counter-clockwise seen from the cameras: the normals of the ground and box top point up
    v, t = fused.vertices, fused.triangles
    normal_z = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])[:, 2]
    centre = v[t].mean(axis=1)
    up = (np.abs(centre[:, :2]).max(axis=1) > 0.6) | (centre[:, 2] > BOX[1][2] - 0.01)  # open ground, box top
    assert up.sum() > 1000 and np.all(normal_z[up] > 0)
    # colours follow the surface: the box top is red, the plane grey
    top = fused.vertices[:, 2] > BOX[1][2] - 0.5 * voxel
    assert top.sum() > 50
    np.testing.assert_allclose(fused.colors[top].mean(0), BOX_RGB, atol=0.08)
    ground = (fused.vertices[:, 2] < 0.5 * voxel) & (np.abs(fused.vertices[:, :2]).max(1) > 0.6)
    np.testing.assert_allclose(fused.colors[ground].mean(0), PLANE_RGB, atol=0.05)


def test_sky_pixels_add_nothing_and_carve_nothing(fused: TriMesh):
    voxel = EXTENT * PARAMS.voxel_frac
    # every vertex lies within the plane square (beyond it the depth is +inf) and below the box top
    assert np.abs(fused.vertices[:, :2]).max() < HALF + 1.5 * voxel
    assert fused.vertices[:, 2].max() < BOX[1][2] + voxel and fused.vertices[:, 2].min() > -voxel
    # an all-sky view integrates nothing; 0, NaN and +inf all mean "nothing here"
    f = TsdfFusion(EXTENT, PARAMS)
    rgb, depth, _, w2c = next(views())
    for nothing in (np.inf, np.nan, 0.0):
        assert f.integrate(rgb, np.full_like(depth, nothing), K, w2c) == 0
    assert len(f.extract().triangles) == 0
    # a view that is sky except for one pixel, looking down through the whole scene, changes nothing away
    # from that pixel: +inf pixels carve no free space (a finite "far" depth would erase what they cross)
    top = look_at(np.array([0.0, 0.0, 3.0]), np.zeros(3), np.array([0.0, 1.0, 0.0]))
    depth_top, rgb_top = raycast(top, [BOX])
    assert np.isfinite(depth_top).mean() > 0.5  # it does look at the scene
    one = np.full_like(depth_top, np.inf)
    one[H // 2, W // 2] = depth_top[H // 2, W // 2]  # on the box top, near (0, 0, 0.4)
    f = TsdfFusion(EXTENT, PARAMS)
    for v in views():
        f.integrate(*v)
    assert f.integrate(rgb_top, one, K, top) == 1
    again = f.extract()

    def far_from_pixel(m: TriMesh) -> set[tuple[float, ...]]:
        far = np.linalg.norm(m.vertices - [0.0, 0.0, 0.4], axis=1) > 0.25
        return {tuple(p) for p in np.round(m.vertices[far], 9)}

    assert far_from_pixel(again) == far_from_pixel(fused)
    # depths beyond max_depth_frac * extent are background: far cameras see nothing
    near_only = MeshParams(voxel_frac=1 / 128, max_depth_frac=0.5)  # 2 m; the ring sees the scene at 2.5-4 m
    assert len(fuse_tsdf(views(), EXTENT, near_only).triangles) == 0


def test_clean_mesh_drops_a_floating_blob_and_decimates():
    raw = fuse_tsdf(views([BOX, FLOATER]), EXTENT, PARAMS)
    floating = raw.vertices[:, 2] > 0.8
    assert floating.sum() > 10  # the floater was reconstructed, as its own component
    for params in (MeshParams(min_component_frac=0.05), MeshParams(keep_largest=1, min_component_frac=0.0)):
        kept = clean_mesh(raw, params)
        assert kept.vertices[:, 2].max() < 0.6
        assert len(kept.triangles) > 0.85 * len(raw.triangles)
    target = len(raw.triangles) // 5
    small = clean_mesh(raw, MeshParams(keep_largest=1, target_triangles=target))
    assert 0.5 * target <= len(small.triangles) <= 1.05 * target
    assert len(small.colors) == len(small.vertices) and small.colors.max() <= 1.0
    m = chamfer_fscore(sample_mesh_points(small.vertices, small.triangles, 20_000), gt_points(), [0.05])
    assert m["accuracy"] < 0.02  # decimation keeps the shape (plane and box are flat)


def test_ply_and_glb_load_back_in_open3d_and_trimesh(fused: TriMesh, tmp_path):
    ply = write_mesh(fused, tmp_path / "mesh.ply")
    glb = write_mesh(fused, tmp_path / "mesh.glb")
    o = o3d.io.read_triangle_mesh(str(ply))
    assert len(o.vertices) == len(fused.vertices) and len(o.triangles) == len(fused.triangles)
    np.testing.assert_allclose(np.asarray(o.vertices), fused.vertices, atol=1e-5)
    np.testing.assert_allclose(np.asarray(o.vertex_colors), fused.colors, atol=1 / 255)
    t = trimesh.load(ply, process=False)
    assert len(t.vertices) == len(fused.vertices)
    np.testing.assert_array_equal(np.asarray(t.faces), fused.triangles)
    g = trimesh.load(glb, force="mesh", process=False)
    assert len(g.vertices) == len(fused.vertices) and len(g.faces) == len(fused.triangles)
    # glTF is +Y up: world z (up) becomes y, world y becomes -z
    np.testing.assert_allclose(g.vertices[:, 1], fused.vertices[:, 2], atol=1e-5)
    np.testing.assert_allclose(g.vertices[:, 2], -fused.vertices[:, 1], atol=1e-5)
    assert len(o3d.io.read_triangle_mesh(str(glb)).triangles) == len(fused.triangles)
    with pytest.raises(ValueError, match="unsupported"):
        write_mesh(fused, tmp_path / "mesh.obj")


def test_points_ply_loads_in_open3d_and_trimesh(tmp_path):
    rng = np.random.default_rng(0)
    cloud = PointCloud(rng.normal(size=(500, 3)) * 10, rng.random((500, 3)))
    path = write_points_ply(tmp_path / "points.ply", cloud)
    o = o3d.io.read_point_cloud(str(path))
    np.testing.assert_allclose(np.asarray(o.points), cloud.points, rtol=1e-6, atol=1e-5)
    np.testing.assert_allclose(np.asarray(o.colors), cloud.colors, atol=0.5 / 255 + 1e-9)
    t = trimesh.load(path)
    assert len(t.vertices) == 500
    np.testing.assert_array_equal(t.colors[:, :3], np.round(cloud.colors * 255).astype(np.uint8))


def test_gaussian_points_filter_by_opacity_and_return_to_the_world():
    from wonderverse.splats.model import SH_C0 as MODEL_SH_C0

    assert SH_C0 == MODEL_SH_C0
    rng = np.random.default_rng(1)
    world = rng.normal(size=(6, 3)) * 5 + [100.0, -20.0, 3.0]
    a = np.pi / 5
    rot = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    norm = Sim3(0.2, rot, np.zeros(3), center=np.array([100.0, -20.0, 0.0]))
    opacity = np.array([0.9, 0.2, 0.6, 0.49, 0.51, 0.99])
    rgb = rng.random((6, 3))
    arrays = {
        "means": norm.apply(world).astype(np.float32),
        "logit_opacities": np.log(opacity / (1 - opacity)).astype(np.float32),
        "sh0": ((rgb - 0.5) / SH_C0)[:, None, :].astype(np.float32),
        "shN": np.zeros((6, 3, 3), np.float32),
        "quats": np.tile([1.0, 0, 0, 0], (6, 1)).astype(np.float32),
        "log_scales": np.zeros((6, 3), np.float32),
    }
    pc = gaussian_points(arrays, norm, min_opacity=0.5)
    keep = opacity >= 0.5
    np.testing.assert_allclose(pc.points, world[keep], atol=1e-4)
    np.testing.assert_allclose(pc.colors, rgb[keep], atol=1e-5)
    np.testing.assert_allclose(gaussian_points(arrays, norm, 0.95).points, world[5:], atol=1e-4)  # only 0.99
    arrays["sh0"][0] = 10.0  # far out of gamut: clipped to white
    assert gaussian_points(arrays, norm, 0.8).colors[0].tolist() == [1.0, 1.0, 1.0]


def test_scene_extent_and_fusion_cameras():
    cams = np.stack([look_at(np.array([x, 0.0, 1.0]), np.array([x, 5.0, 1.0])) for x in (0.0, 3.0, 6.0)])
    depths = [np.full((4, 4), 2.0), np.array([[2.0, np.inf], [0.0, np.nan]])]
    assert scene_extent(cams, depths) == pytest.approx(6.0 + 2 * 2.0)
    assert scene_extent(cams[:1], [np.full((2, 2), np.inf)]) == 1.0  # nothing valid
    with_nan = np.concatenate([cams[:2], np.full((1, 4, 4), np.nan), cams[2:]])
    out = fusion_cameras(with_nan, 1)
    assert out.shape == (5, 4, 4)
    centres = -np.einsum("nji,nj->ni", out[:, :3, :3], out[:, :3, 3])
    np.testing.assert_allclose(centres[:, 0], [0.0, 1.5, 3.0, 4.5, 6.0], atol=1e-9)
    np.testing.assert_allclose(fusion_cameras(with_nan, 0), cams)


def test_chamfer_fscore_known_answers():
    grid = np.stack(np.meshgrid(np.arange(5.0), np.arange(5.0), np.arange(5.0)), -1).reshape(-1, 3)
    m = chamfer_fscore(grid + np.array([0.1, 0.0, 0.0]), grid, [0.05, 0.2])
    assert m["chamfer"] == pytest.approx(0.1) and m["accuracy"] == pytest.approx(0.1)
    assert m["precision"] == [0.0, 1.0] and m["recall"] == [0.0, 1.0] and m["fscore"] == [0.0, 1.0]
    # prediction = 4 GT points exactly + 1 outlier 3 m from the nearest GT point; GT has 8 points
    gt = np.array([[x, 0.0, 0.0] for x in range(8)])
    pred = np.vstack([gt[:4], [[0.0, 3.0, 0.0]]])
    m = chamfer_fscore(pred, gt, [0.5])
    assert m["accuracy"] == pytest.approx(3.0 / 5)
    assert m["completeness"] == pytest.approx((1 + 2 + 3 + 4) / 8)  # GT 4..7 are 1..4 m from pred[3]
    assert m["chamfer"] == pytest.approx((0.6 + 10 / 8) / 2)
    p, r = 4 / 5, 4 / 8
    assert m["precision"] == [pytest.approx(p)] and m["recall"] == [pytest.approx(r)]
    assert m["fscore"] == [pytest.approx(2 * p * r / (p + r))]
    assert (m["n_pred"], m["n_gt"]) == (5, 8)
    empty = chamfer_fscore(np.zeros((0, 3)), gt, [0.5])
    assert np.isnan(empty["chamfer"]) and empty["fscore"] == [0.0]


def test_sample_mesh_points_uniform_by_area_and_seeded():
    # triangle A (area 0.5) in z = 0, triangle B (area 1.5) in z = 1
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [3, 0, 1], [0, 1, 1], [5, 5, 5]], dtype=float)
    f = np.array([[0, 1, 2], [3, 4, 5], [6, 6, 6]])  # the last one is degenerate
    p = sample_mesh_points(v, f, 20_000, seed=7)
    np.testing.assert_array_equal(p, sample_mesh_points(v, f, 20_000, seed=7))
    on_b = np.isclose(p[:, 2], 1.0, atol=1e-12)
    assert np.all(on_b | np.isclose(p[:, 2], 0.0, atol=1e-12))
    assert on_b.mean() == pytest.approx(0.75, abs=0.015)
    a = p[~on_b]
    assert np.all((a[:, 0] >= 0) & (a[:, 1] >= 0) & (a[:, 0] + a[:, 1] <= 1 + 1e-12))
    # uniform inside a triangle: the mean is the centroid
    np.testing.assert_allclose(a[:, :2].mean(0), [1 / 3, 1 / 3], atol=0.01)
    assert sample_mesh_points(v, np.zeros((0, 3), int), 10).shape == (0, 3)


def test_mesh_from_views_fuses_at_the_scene_extent_of_those_views():
    from wonderverse.mesh import mesh_from_views

    cams = ring_cameras(6)
    views = [(np.round(rgb * 255).astype(np.uint8), depth) for depth, rgb in (raycast(c, []) for c in cams)]
    mesh, extent = mesh_from_views(views, cams, K, MeshParams(voxel_frac=1 / 64, min_component_frac=0.0))
    assert extent == scene_extent(cams, [d for _, d in views])
    assert len(mesh.triangles) > 100
    assert np.abs(mesh.vertices[:, 2]).max() < 2 * extent / 64  # on the plane, within two voxels
    np.testing.assert_allclose(mesh.colors.mean(0), PLANE_RGB, atol=0.02)

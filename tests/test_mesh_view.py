"""The mesh picture: ground truth from geometry built here (planes, a cube, triangles) and from an
independent ray-box intersection, never from the renderer's own output."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import Delaunay

from wonderverse.camera import camera_centers, invert_se3, look_at, so3_exp
from wonderverse.mesh_view import MeshViewParams, overview_camera, render_mesh

W, H = 128, 96
K = np.array([[100.0, 0, W / 2], [0, 100.0, H / 2], [0, 0, 1]])
# A camera away from the origin, so that world and camera coordinates differ.
W2C = look_at(np.array([1.0, -3.0, 0.5]), np.array([0.2, 0.0, 0.3]))
WHITE = 255
P = MeshViewParams(ambient=0.3)


def to_world(points_cam: np.ndarray, w2c: np.ndarray = W2C) -> np.ndarray:
    c2w = invert_se3(w2c)
    return points_cam @ c2w[:3, :3].T + c2w[:3, 3]


def quad(corners_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two triangles over four corners given in camera coordinates, returned in world coordinates."""
    return to_world(np.asarray(corners_cam, float)), np.array([[0, 1, 2], [0, 2, 3]])


def test_plane_facing_the_camera_covers_exactly_the_projection_of_its_corners():
    # corners at z = 2 project to u in [39, 89], v in [23, 73] (integer pixel edges: no centre is on an edge)
    V, F = quad([[-0.5, -0.5, 2], [0.5, -0.5, 2], [0.5, 0.5, 2], [-0.5, 0.5, 2]])
    colour = np.array([1.0, 0.5, 0.25])
    img = render_mesh(V, F, np.tile(colour, (4, 1)), K, W2C, W, H, P)
    assert img.shape == (H, W, 3) and img.dtype == np.uint8
    covered = (img != WHITE).any(axis=2)
    want = np.zeros((H, W), bool)
    want[23:73, 39:89] = True
    np.testing.assert_array_equal(covered, want)
    assert (img[~want] == WHITE).all()  # background where nothing is hit
    # the pixel around the optical axis faces the plane squarely: the full colour, unshaded
    u, v = W // 2, H // 2
    cos = 1 / np.sqrt(1 + (0.5 / 100) ** 2 * 2)
    np.testing.assert_allclose(img[v, u], 255 * colour * (0.3 + 0.7 * cos), atol=1)


@settings(max_examples=25, deadline=None)
@given(st.floats(0, 80), st.floats(0, 1))
def test_lambert_shading_follows_the_cosine_to_the_ray(angle_deg, ambient):
    """One ray along the optical axis hits a plane tilted by `angle_deg`: value = ambient + (1-ambient) cos."""
    K1 = np.array([[1.0, 0, 0.5], [0, 1.0, 0.5], [0, 0, 1]])
    a = np.radians(angle_deg)
    R = so3_exp(np.array([0.0, a, 0.0]))  # tilt about the camera's y axis
    corners = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], float) @ R.T + [0, 0, 3]
    V, F = quad(corners)
    img = render_mesh(V, F, np.ones((4, 3)), K1, W2C, 1, 1, MeshViewParams(ambient=ambient))
    np.testing.assert_allclose(img[0, 0], 255 * (ambient + (1 - ambient) * np.cos(a)), atol=1)


def test_face_towards_the_camera_is_brighter_than_an_oblique_one_and_back_faces_are_lit():
    left, F = quad([[-1.0, -0.3, 3], [-0.2, -0.3, 3], [-0.2, 0.3, 3], [-1.0, 0.3, 3]])  # square on
    right, _ = quad([[0.2, -0.3, 2.6], [1.0, -0.3, 3.4], [1.0, 0.3, 3.4], [0.2, 0.3, 2.6]])  # turned by 45°
    V = np.vstack([left, right])
    Fs = np.vstack([F, F + 4])
    img = render_mesh(V, Fs, np.ones((8, 3)), K, W2C, W, H, P).astype(float)
    lum = img.mean(axis=2)
    facing, oblique = lum[H // 2, 33:55], lum[H // 2, 75:90]
    assert (facing < WHITE).all() and (oblique < WHITE).all()
    assert facing.min() > oblique.max() + 30
    # the same plane with its triangles wound the other way (normal away from the camera) looks the same
    flipped = render_mesh(V, Fs[:, ::-1], np.ones((8, 3)), K, W2C, W, H, P)
    np.testing.assert_array_equal(flipped, img.astype(np.uint8))


def test_vertex_colours_are_interpolated_and_the_nearest_surface_wins():
    # a red/green/blue triangle in front of a blue square; a ray through the point with barycentric
    # weights (0.5, 0.3, 0.2) sees that mix of the corner colours
    tri_cam = np.array([[-0.6, -0.4, 2.0], [0.6, -0.4, 2.0], [0.0, 0.8, 2.0]])
    weights = np.array([0.5, 0.3, 0.2])
    point = weights @ tri_cam
    # a 1x1 camera looking straight through that point, axes parallel to the main camera's
    K1 = np.array([[1.0, 0, 0.5], [0, 1.0, 0.5], [0, 0, 1]])
    w2c1 = W2C.copy()
    w2c1[:3, 3] -= point * [1, 1, 0]  # shift the camera sideways so its axis passes the point
    back, F = quad([[-2, -2, 4], [2, -2, 4], [2, 2, 4], [-2, 2, 4]])
    V = np.vstack([to_world(tri_cam), back])
    Fs = np.vstack([[[0, 1, 2]], F + 3])
    C = np.vstack([np.eye(3), np.tile([0.0, 0.0, 1.0], (4, 1))])
    img = render_mesh(V, Fs, C, K1, w2c1, 1, 1, P)
    np.testing.assert_allclose(img[0, 0], 255 * weights, atol=1)  # facing the ray: cos = 1
    # move the triangle behind the square: the square's blue wins
    V2 = np.vstack([to_world(tri_cam + np.array([0, 0, 3])), back])
    img2 = render_mesh(V2, Fs, C, K1, w2c1, 1, 1, P)
    np.testing.assert_allclose(img2[0, 0], [0, 0, 255], atol=1)


def slab_hits(rays: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Independent ray / axis-aligned box intersection: (hit mask, outward normal of the entry face)."""
    o, d = rays[:, :3].astype(float), rays[:, 3:].astype(float)
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (lo - o) / d, (hi - o) / d
    t_near = np.minimum(t1, t2)
    t_far = np.maximum(t1, t2)
    enter, leave = t_near.max(axis=1), t_far.min(axis=1)
    hit = (enter <= leave) & (leave > 0)
    axis = t_near.argmax(axis=1)
    normal = np.zeros_like(o)
    normal[np.arange(len(o)), axis] = -np.sign(d[np.arange(len(o)), axis])
    return hit, normal


def test_unit_cube_matches_its_projected_hull_and_per_face_shading():
    import trimesh

    cube = trimesh.creation.box(extents=(1, 1, 1))  # centred at the origin, axis-aligned
    V, F = np.asarray(cube.vertices), np.asarray(cube.faces)
    w2c = look_at(np.array([2.1, -2.6, 1.7]), np.zeros(3))
    colour = np.array([0.9, 0.8, 0.7])
    img = render_mesh(V, F, np.tile(colour, (len(V), 1)), K, w2c, W, H, P)
    covered = (img != WHITE).any(axis=2)
    # ground truth 1: the silhouette of a convex body is the convex hull of its projected corners
    cam = V @ w2c[:3, :3].T + w2c[:3, 3]
    uv = (cam @ K.T)[:, :2] / cam[:, 2:]
    uu, vv = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    inside = Delaunay(uv).find_simplex(np.stack([uu, vv], -1).reshape(-1, 2)).reshape(H, W) >= 0
    assert covered.sum() > 1000
    np.testing.assert_array_equal(covered, inside)
    # ground truth 2: each pixel shaded by the cosine of the face a slab test says it enters
    from wonderverse.mesh_view import camera_rays

    rays = camera_rays(K, w2c, W, H).reshape(-1, 6)
    hit, normal = slab_hits(rays, -0.5 * np.ones(3), 0.5 * np.ones(3))
    np.testing.assert_array_equal(hit.reshape(H, W), inside)
    cos = np.abs((normal * rays[:, 3:]).sum(axis=1))
    want = 255 * colour * (0.3 + 0.7 * cos[:, None])
    got = img.reshape(-1, 3)
    np.testing.assert_allclose(got[hit], want[hit], atol=1.01)
    assert len(np.unique(np.round(cos[hit], 2))) >= 3  # three faces in view, three different shades


def test_supersampling_blends_a_half_covered_pixel_and_empty_meshes_are_background():
    # the plane's right edge at u = 40.5 (z = 2): pixel 40 is half covered
    x_edge = (40.5 - W / 2) * 2 / 100
    V, F = quad([[-1.0, -0.5, 2], [x_edge, -0.5, 2], [x_edge, 0.5, 2], [-1.0, 0.5, 2]])
    black = np.zeros((4, 3))
    img = render_mesh(V, F, black, K, W2C, W, H, MeshViewParams(supersample=2))
    row = img[H // 2, :, 0].astype(int)
    assert row[39] == 0 and row[41] == WHITE and abs(row[40] - 128) <= 1
    empty = render_mesh(np.zeros((0, 3)), np.zeros((0, 3), int), None, K, W2C, W, H)
    assert (empty == WHITE).all()
    with pytest.raises(ValueError, match="face indices"):
        render_mesh(V, F + 4, None, K, W2C, W, H)
    with pytest.raises(ValueError, match="one colour per vertex"):
        render_mesh(V, F, black[:3], K, W2C, W, H)


def test_overview_camera_is_above_and_behind_the_cameras_and_sees_the_mesh():
    # cameras along +x at 1.6 m height looking +y at a scene of boxes ahead of them; world +z up
    eyes = np.array([[x, 0.0, 1.6] for x in np.linspace(-2, 2, 9)])
    cams = np.stack([look_at(e, e + np.array([0.0, 1.0, -0.1])) for e in eyes])
    # a grid symmetric about its centre (0, 6, 1.5), and one stray vertex far away that must not count
    grid = np.stack(np.meshgrid(np.linspace(-4, 4, 9), np.linspace(3, 9, 7), np.linspace(0, 3, 4)), -1).reshape(-1, 3)
    centre = np.array([0.0, 6.0, 1.5])
    points = np.vstack([grid, [[0.0, 60.0, 1.5]]])

    def check(pose: np.ndarray, pts: np.ndarray, c: np.ndarray, centres: np.ndarray, up: np.ndarray, fwd: np.ndarray):
        eye = camera_centers(pose)
        assert ((eye - centres) @ up > 0.5).all()  # above every camera
        assert ((eye - centres) @ fwd < 0).all()  # behind every camera
        cam = np.vstack([pts, centres]) @ pose[:3, :3].T + pose[:3, 3]
        assert (cam[:, 2] > 0).all()
        uv = (cam @ K.T)[:, :2] / cam[:, 2:]
        assert ((uv >= 0) & (uv <= [W, H])).all()  # everything in the picture
        c = c @ pose[:3, :3].T + pose[:3, 3]
        np.testing.assert_allclose((K @ c)[:2] / c[2], [W / 2, H / 2], atol=1e-6)  # looking at the centre

    pose = overview_camera(points, cams, K, W, H)
    check(pose, grid, centre, camera_centers(cams), np.array([0, 0, 1.0]), np.array([0, 1.0, 0]))
    # the same scene in an arbitrary (SfM-like) frame: "up" comes from the cameras, not from world z
    S = np.eye(4)
    S[:3, :3] = so3_exp(np.array([0.7, -1.1, 0.4]))
    S[:3, 3] = [3.0, -1.0, 2.0]
    cams2 = cams @ invert_se3(S)
    points2 = points @ S[:3, :3].T + S[:3, 3]
    pose2 = overview_camera(points2, cams2, K, W, H)
    np.testing.assert_allclose(pose2, pose @ invert_se3(S), atol=1e-9)
    grid2, centre2 = grid @ S[:3, :3].T + S[:3, 3], S[:3, :3] @ centre + S[:3, 3]
    check(pose2, grid2, centre2, camera_centers(cams2), S[:3, :3] @ [0, 0, 1.0], S[:3, :3] @ [0, 1.0, 0])
    with pytest.raises(ValueError, match="finite camera"):
        overview_camera(points, np.full((2, 4, 4), np.nan), K, W, H)

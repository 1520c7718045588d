"""Pictures of a triangle mesh for people: ray-cast with Open3D's `RaycastingScene`, Lambert-shaded.

`render_mesh` draws a mesh (vertex colours interpolated across each triangle) from one pinhole camera
(`render_mesh_views` from several, building Open3D's ray-casting structure once), lit by a head light:
each face is shaded by the cosine between its normal and the viewing ray (either side, since fused meshes
are not consistently oriented), so the shape reads even where the colours are flat. `overview_camera`
places a camera above and behind a set of cameras, looking at a mesh's centre.

Conventions: OpenCV camera axes (x right, y down, z forward), W2C 4x4 poses, K in pixels with pixel
centres at +0.5. Open3D is imported inside the functions (the CLI never loads it at start-up).
"""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel, ConfigDict, Field


class MeshViewParams(BaseModel):
    """How a mesh picture looks, and where the overview camera goes."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    ambient: float = Field(0.3, ge=0, le=1, description="brightness of a face seen edge-on (1: no shading)")
    supersample: int = Field(1, ge=1, le=4, description="rays per pixel side (anti-aliasing); 1 = pixel centres")
    background_rgb: tuple[int, int, int] = (255, 255, 255)
    default_rgb: tuple[float, float, float] = Field((0.75, 0.75, 0.75), description="colour without vertex colours")
    overview_elevation_deg: float = Field(35.0, gt=0, lt=90, description="overview camera above the horizon")
    overview_margin: float = Field(1.15, ge=1, le=4, description="overview distance over the fitting distance")


def camera_rays(K: np.ndarray, w2c: np.ndarray, width: int, height: int, supersample: int = 1) -> np.ndarray:
    """Rays (height*s, width*s, 6) float32 [origin, unit direction] in world coordinates, one per
    sub-pixel centre ((u + (j + 0.5)/s, v + (i + 0.5)/s) for s = supersample), row-major."""
    s = int(supersample)
    u = (np.arange(width * s) + 0.5) / s
    v = (np.arange(height * s) + 0.5) / s
    uu, vv = np.meshgrid(u, v)
    pix = np.stack([uu, vv, np.ones_like(uu)], axis=-1)
    d_cam = pix @ np.linalg.inv(np.asarray(K, np.float64)).T
    R = np.asarray(w2c, np.float64)[:3, :3]
    d_world = d_cam @ R  # R^T d for each row vector d
    d_world /= np.linalg.norm(d_world, axis=-1, keepdims=True)
    centre = -R.T @ np.asarray(w2c, np.float64)[:3, 3]
    origin = np.broadcast_to(centre, d_world.shape)
    return np.concatenate([origin, d_world], axis=-1).astype(np.float32)


def render_mesh(
    vertices: np.ndarray,
    faces: np.ndarray,
    colors: np.ndarray | None,
    K: np.ndarray,
    w2c: np.ndarray,
    width: int,
    height: int,
    params: MeshViewParams | None = None,
) -> np.ndarray:
    """RGB (height, width, 3) uint8 picture of a triangle mesh seen from a pinhole camera.

    vertices (V,3) and faces (F,3) vertex indices; colors (V,3) in [0,1] per vertex (None: a light grey).
    A pixel shows the first surface its ray hits, coloured by the vertex colours interpolated at the hit
    and scaled by `ambient + (1 - ambient) * |cos|` (cos: face normal against the ray); pixels whose rays
    hit nothing are `background_rgb`. With `supersample` s > 1, s*s rays per pixel are averaged."""
    return render_mesh_views(vertices, faces, colors, K, np.asarray(w2c)[None], width, height, params)[0]


def render_mesh_views(
    vertices: np.ndarray,
    faces: np.ndarray,
    colors: np.ndarray | None,
    K: np.ndarray,
    poses: np.ndarray,
    width: int,
    height: int,
    params: MeshViewParams | None = None,
) -> np.ndarray:
    """`render_mesh` from several cameras sharing K and size: (N, height, width, 3) uint8 for W2C `poses`
    (N,4,4). The ray-casting structure is built once (on a million triangles that is most of the time)."""
    import open3d as o3d

    p = params or MeshViewParams()
    V = np.ascontiguousarray(vertices, dtype=np.float32).reshape(-1, 3)
    F = np.ascontiguousarray(faces, dtype=np.int64).reshape(-1, 3)
    poses = np.asarray(poses, np.float64).reshape(-1, 4, 4)
    s = p.supersample
    bg = np.asarray(p.background_rgb, np.float32) / 255.0
    C = None
    if colors is not None:
        C = np.asarray(colors, np.float32).reshape(-1, 3)
        if len(C) != len(V):
            raise ValueError(f"need one colour per vertex: {len(C)} colours for {len(V)} vertices")
    if len(F) and (F.min() < 0 or F.max() >= len(V)):
        raise ValueError(f"face indices must lie in [0, {len(V)}), got [{F.min()}, {F.max()}]")
    scene = None
    if len(F):
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(V), o3d.core.Tensor(F.astype(np.uint32)))
    images = []
    for w2c in poses:
        out = np.broadcast_to(bg, (height * s, width * s, 3)).copy()
        if scene is not None:
            rays = camera_rays(K, w2c, width, height, s).reshape(-1, 6)
            ans = scene.cast_rays(o3d.core.Tensor.from_numpy(np.ascontiguousarray(rays)))
            hit = np.flatnonzero(np.isfinite(ans["t_hit"].numpy()))
            if len(hit):
                normals = ans["primitive_normals"].numpy()[hit]
                cos = np.abs(np.einsum("ij,ij->i", normals, rays[hit, 3:]))
                shade = p.ambient + (1.0 - p.ambient) * np.clip(cos, 0.0, 1.0)
                if C is None:
                    base = np.broadcast_to(np.asarray(p.default_rgb, np.float32), (len(hit), 3))
                else:
                    tri = ans["primitive_ids"].numpy()[hit].astype(np.int64)
                    uv = ans["primitive_uvs"].numpy()[hit]  # weights of the face's 2nd and 3rd vertex
                    w = np.stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=1)
                    base = np.einsum("ij,ijk->ik", w, C[F[tri]])
                out.reshape(-1, 3)[hit] = np.clip(base, 0.0, 1.0) * shade[:, None]
        if s > 1:
            out = out.reshape(height, s, width, s, 3).mean(axis=(1, 3))
        images.append(np.round(out * 255.0).astype(np.uint8))
    return np.stack(images) if images else np.zeros((0, height, width, 3), np.uint8)


def overview_camera(
    points: np.ndarray,
    w2c: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    params: MeshViewParams | None = None,
) -> np.ndarray:
    """W2C (4,4) of a camera above and behind the cameras `w2c` (N,4,4; non-finite rows skipped), looking
    at the centre (mean) of `points` (M,3, e.g. mesh vertices; the 1 % farthest from their mean left out)
    from `overview_elevation_deg` above the cameras' horizon, far enough that a sphere around that centre
    holding those points and the cameras fits in the view.

    "Up" is the cameras' mean image-up direction (their frame's world may be SfM's, with no known up) and
    "behind" is against their mean horizontal viewing direction. Raises ValueError with no finite camera."""
    from wonderverse.camera import camera_centers, look_at

    p = params or MeshViewParams()
    poses = np.asarray(w2c, np.float64).reshape(-1, 4, 4)
    poses = poses[np.isfinite(poses).all(axis=(1, 2))]
    if not len(poses):
        raise ValueError("overview_camera needs at least one finite camera pose")
    R = poses[:, :3, :3]
    up = -R[:, 1, :].mean(axis=0)  # camera y points down; row 1 of R is that axis in world coordinates
    up /= np.linalg.norm(up)
    fwd = R[:, 2, :].mean(axis=0)
    fwd -= fwd.dot(up) * up
    if np.linalg.norm(fwd) < 1e-9:  # cameras looking straight down/up on average: any horizontal direction
        fwd = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    fwd /= np.linalg.norm(fwd)
    centres = camera_centers(poses)
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    if len(pts):
        # stray far vertices (the farthest 1 %) neither move the centre nor widen the view; distances, not
        # per-axis percentiles, so the camera turns with the scene whatever the world frame's axes
        far = np.linalg.norm(pts - pts.mean(axis=0), axis=1)
        pts = pts[far <= np.percentile(far, 99) * (1 + 1e-9)]  # ties at the threshold stay, whatever the rounding
        target = pts.mean(axis=0)
        inside = np.vstack([pts, centres])
    else:
        target = centres.mean(axis=0)
        inside = centres
    radius = max(float(np.linalg.norm(inside - target, axis=1).max()), 1e-6)
    Kf = np.asarray(K, np.float64)
    half_fov = min(np.arctan(0.5 * width / Kf[0, 0]), np.arctan(0.5 * height / Kf[1, 1]))
    dist = p.overview_margin * radius / np.sin(half_fov)
    el = np.radians(p.overview_elevation_deg)
    eye = target + dist * (-np.cos(el) * fwd + np.sin(el) * up)
    return look_at(eye, target, up)

"""Cameras, points and frames for other tools: a COLMAP dataset (images/ + sparse/0/ binary model with
tracks), a nerfstudio dataset (transforms.json, images, depth PNGs, a point cloud) with nerfstudio camera paths,
and our own camera-path JSON.

Inputs follow the project conventions: W2C poses (N,4,4) float64 in OpenCV camera axes (x right, y down,
z forward) in the caller's world frame (the outputs step passes its gravity-aligned frame: +Z up), intrinsics
K (3,3) shared or (N,3,3) per frame, in pixels with pixel centres at +0.5 (cx = W/2 for a centred camera).
COLMAP and nerfstudio use the same pixel-centre convention, so K is written unchanged. Frames whose pose is
not finite (NaN: not registered) are left out of every export. Numbers in JSON are written exactly (repr),
so re-reading gives the poses back to rounding (far below 1e-9).
"""

from __future__ import annotations

import json
from collections.abc import Collection
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from wonderverse.camera import camera_centers, invert_se3

if TYPE_CHECKING:
    from wonderverse.mesh import PointCloud


CAMERA_PATH_FORMAT = "wonderverse.camera_path/2"  # 2: the world frame is stated in `world`
CAMERA_PATH_CONVENTION = (
    "w2c: world-to-camera 4x4 rigid transform, row-major, acting on column vectors: [x_cam; 1] = w2c @ [x_world; 1]. "
    "Camera axes OpenCV: x right, y down, z forward (depth = camera z). The world frame (axes, origin, units) is "
    "stated in `world`. K: 3x3 pinhole intrinsics in pixels for an image of width x height, pixel centres at +0.5 "
    "(cx = width/2 for a centred camera). time_s = index / fps."
)
# transform_matrix (OpenGL C2W) = C2W (OpenCV) @ diag(1, -1, -1, 1): flips the camera y and z axes.
OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass(frozen=True)
class PosedImages:
    """Cameras read back from an export. names (M,); w2c (M,4,4) float64 OpenCV axes; K (M,3,3) pixels;
    width, height: image size in pixels (shared)."""

    names: list[str]
    w2c: np.ndarray
    K: np.ndarray
    width: int
    height: int


def _check_poses(w2c: np.ndarray, K: np.ndarray, names: list[str] | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(w2c (N,4,4), K (N,3,3), valid (N,) bool) with shapes checked; valid = pose entirely finite."""
    w2c = np.asarray(w2c, dtype=np.float64)
    if w2c.ndim != 3 or w2c.shape[1:] != (4, 4):
        raise ValueError(f"w2c must be (N,4,4), got {w2c.shape}")
    n = w2c.shape[0]
    K = np.asarray(K, dtype=np.float64)
    if K.shape not in ((3, 3), (n, 3, 3)):
        raise ValueError(f"K must be (3,3) or (N,3,3) with N={n}, got {K.shape}")
    Ks = np.broadcast_to(K, (n, 3, 3))
    if not np.all(np.isfinite(Ks)) or np.any(Ks[:, 0, 1] != 0.0) or np.any(Ks[:, 2] != [0.0, 0.0, 1.0]):
        raise ValueError("K must be finite pinhole intrinsics [[fx,0,cx],[0,fy,cy],[0,0,1]] (no skew)")
    if names is not None:
        if len(names) != n:
            raise ValueError(f"need one name per pose: {len(names)} names for {n} poses")
        if len(set(names)) != n:
            raise ValueError("image names must be unique")
        if any(not s or any(ch.isspace() for ch in s) for s in names):
            raise ValueError("image names must be non-empty and contain no whitespace")
    valid = np.all(np.isfinite(w2c), axis=(1, 2))
    return w2c, Ks, valid


def _colors_uint8(colors: np.ndarray | None, n: int) -> np.ndarray:
    """(n,3) uint8 colours from uint8 or from floats in [0,1]; grey when None."""
    if colors is None:
        return np.full((n, 3), 128, dtype=np.uint8)
    colors = np.asarray(colors)
    if colors.shape != (n, 3):
        raise ValueError(f"colors must be (P,3) matching the points, got {colors.shape} for {n} points")
    if colors.dtype == np.uint8:
        return colors
    return np.clip(np.rint(np.asarray(colors, dtype=np.float64) * 255.0), 0, 255).astype(np.uint8)


# ----------------------------------------------------------------------------------------------- COLMAP


@dataclass(frozen=True)
class ColmapTracks:
    """3D points with their observations. points (P,3) float64 world; colors (P,3) uint8; errors (P,) mean
    reprojection error in pixels (0 when unknown); observations: per image, (xy (M,2) float64 pixel
    coordinates, centres at +0.5 as COLMAP's, point index (M,) int into `points`)."""

    points: np.ndarray
    colors: np.ndarray
    errors: np.ndarray
    observations: list[tuple[np.ndarray, np.ndarray]]


def read_colmap_tracks(model_dir: Path) -> tuple[ColmapTracks, list[str], list[tuple[int, int]]]:
    """The points of a COLMAP model (binary or text) with every observation of them, the image names the
    observation lists belong to (one list per image of the model, in image-id order) and each image's camera
    size (width, height) in pixels."""
    import pycolmap

    rec = pycolmap.Reconstruction(str(model_dir))
    ids = sorted(rec.points3D)
    index = {pid: j for j, pid in enumerate(ids)}
    pts = [rec.points3D[pid] for pid in ids]
    observations, names, sizes = [], [], []
    for image_id in sorted(rec.images):
        im = rec.images[image_id]
        cam = rec.cameras[im.camera_id]
        sizes.append((int(cam.width), int(cam.height)))
        seen = [p for p in im.points2D if p.has_point3D()]
        xy = np.array([p.xy for p in seen], np.float64).reshape(-1, 2)
        observations.append((xy, np.array([index[p.point3D_id] for p in seen], np.int64)))
        names.append(im.name)
    tracks = ColmapTracks(
        points=np.array([p.xyz for p in pts], np.float64).reshape(-1, 3),
        colors=np.array([p.color for p in pts], np.uint8).reshape(-1, 3),
        errors=np.array([max(float(p.error), 0.0) for p in pts], np.float64),
        observations=observations,
    )
    return tracks, names, sizes


def project_tracks(
    points: np.ndarray,
    w2c: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    depths: list[np.ndarray] | None = None,
    depth_K: np.ndarray | None = None,
    depth_rel_tol: float = 0.03,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Observations of `points` (P,3) in every camera (N,4,4) W2C with K (3,3), images width x height: the
    projection of each point in front of the camera and inside the image, where a depth map is given
    (depths[i] (h,w) camera z at intrinsics depth_K, +inf where nothing is) only where the point is the
    surface seen (|z - depth| <= depth_rel_tol z). For points with no measured tracks (poses not from SfM):
    their observations are exact projections. Returns per camera (xy (M,2), point index (M,))."""
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    out = []
    for i, pose in enumerate(np.asarray(w2c, np.float64).reshape(-1, 4, 4)):
        cam = pts @ pose[:3, :3].T + pose[:3, 3]
        z = cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = (cam @ np.asarray(K, np.float64).T)[:, :2] / z[:, None]
        ok = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < width) & (uv[:, 1] >= 0) & (uv[:, 1] < height)
        if depths is not None and depth_K is not None:
            d = np.asarray(depths[i])
            with np.errstate(divide="ignore", invalid="ignore"):
                duv = (cam @ np.asarray(depth_K, np.float64).T)[:, :2] / z[:, None]
            col = np.clip(np.floor(np.nan_to_num(duv[:, 0], nan=-1.0)), -1, d.shape[1]).astype(np.int64)
            row = np.clip(np.floor(np.nan_to_num(duv[:, 1], nan=-1.0)), -1, d.shape[0]).astype(np.int64)
            inside = (col >= 0) & (col < d.shape[1]) & (row >= 0) & (row < d.shape[0])
            seen = np.full(len(pts), np.inf)
            seen[inside] = d[row[inside], col[inside]]
            ok &= inside & (np.abs(z - seen) <= depth_rel_tol * z)
        idx = np.flatnonzero(ok)
        out.append((uv[idx], idx))
    return out


def write_colmap_dataset(
    out_dir: Path,
    frames: np.ndarray,
    K: np.ndarray,
    w2c: np.ndarray,
    names: list[str],
    tracks: ColmapTracks | None = None,
    keep_images: Collection[str] = (),
) -> Path:
    """A COLMAP dataset as trainers read it (gsplat's examples, INRIA 3DGS, nerfstudio's COLMAP parser):
    `out_dir/images/<name>.png` (the frames) and `out_dir/sparse/0/` written by pycolmap's
    `Reconstruction.write_binary` (cameras.bin, images.bin, points3D.bin, and COLMAP 3.12's rigs.bin and
    frames.bin, which older readers ignore). Returns out_dir.

    Cameras: one PINHOLE camera (id 1) when K is (3,3), else one per image (id = image id). Images: id =
    index in the input + 1 (stable when frames without a finite pose are left out), cam_from_world = our W2C,
    with the observations of `tracks` (xy in the frame's pixels) as their 2-D points. Points3D: `tracks`'
    points with their colours and errors, each with the track of its observations in the written images;
    points seen by fewer than two of them are left out (COLMAP's own models hold none). frames: (N,H,W,3)
    uint8; names: file stems, unique, without whitespace; keep_images: names whose image file is already there
    and holds the frame (an extended scene's earlier frames): not written again.
    """
    import pycolmap
    from PIL import Image

    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.dtype != np.uint8:
        raise ValueError(f"frames must be (N,H,W,3) uint8, got {frames.shape} {frames.dtype}")
    w2c, Ks, valid = _check_poses(w2c, K, names)
    n, height, width = frames.shape[:3]
    if len(w2c) != n:
        raise ValueError(f"need one pose per frame: {len(w2c)} poses for {n} frames")
    if tracks is not None and len(tracks.observations) != n:
        raise ValueError(f"need one observation list per frame: {len(tracks.observations)} for {n} frames")
    out_dir = Path(out_dir)
    model_dir = out_dir / "sparse" / "0"
    (out_dir / "images").mkdir(parents=True, exist_ok=True)
    model_dir.mkdir(parents=True, exist_ok=True)
    shared = np.asarray(K).ndim == 2
    rec = pycolmap.Reconstruction()
    ids = np.flatnonzero(valid) + 1
    for cam_id, k in [(1, Ks[0])] if shared else [(int(i), Ks[i - 1]) for i in ids]:
        params = [k[0, 0], k[1, 1], k[0, 2], k[1, 2]]
        rec.add_camera_with_trivial_rig(
            pycolmap.Camera(model="PINHOLE", width=width, height=height, params=params, camera_id=cam_id)
        )
    # which written observations see each point: (image id, index among the image's 2-D points)
    seen_by: dict[int, list[tuple[int, int]]] = {}
    for i in ids:
        k = int(i) - 1
        if names[k] not in keep_images:
            Image.fromarray(frames[k]).save(out_dir / "images" / f"{names[k]}.png")
        xy, idx = (np.zeros((0, 2)), np.zeros(0, np.int64)) if tracks is None else tracks.observations[k]
        points2d = pycolmap.Point2DList([pycolmap.Point2D(np.asarray(p, np.float64)) for p in xy])
        for m, j in enumerate(np.asarray(idx, np.int64)):
            seen_by.setdefault(int(j), []).append((int(i), m))
        image = pycolmap.Image(
            name=f"{names[k]}.png", points2D=points2d, camera_id=1 if shared else int(i), image_id=int(i)
        )
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(w2c[k, :3, :4]))
    if tracks is not None:
        pts = np.asarray(tracks.points, np.float64).reshape(-1, 3)
        if not np.all(np.isfinite(pts)):
            raise ValueError("points must be finite")
        cols = _colors_uint8(tracks.colors, len(pts))
        for j, elements in sorted(seen_by.items()):
            if len({image_id for image_id, _ in elements}) < 2:
                continue
            track = pycolmap.Track([pycolmap.TrackElement(image_id, m) for image_id, m in elements])
            pid = rec.add_point3D(pts[j], track, cols[j])
            rec.points3D[pid].error = float(tracks.errors[j])
    rec.write_binary(str(model_dir))
    return out_dir


def read_colmap_poses(model_dir: Path) -> PosedImages:
    """Cameras of a COLMAP model (text or binary) read with pycolmap, in image-id order; W2C OpenCV axes.

    Raises ValueError if the cameras differ in size (PosedImages holds one width and height).
    """
    import pycolmap

    rec = pycolmap.Reconstruction(str(model_dir))
    names, poses, Ks, sizes = [], [], [], set()
    for image_id in sorted(rec.images):
        im = rec.images[image_id]
        if not im.has_pose:
            continue
        cam = rec.cameras[im.camera_id]
        names.append(im.name)
        pose = np.eye(4)
        pose[:3] = im.cam_from_world().matrix()
        poses.append(pose)
        Ks.append(np.asarray(cam.calibration_matrix(), dtype=np.float64))
        sizes.add((int(cam.width), int(cam.height)))
    if len(sizes) > 1:
        raise ValueError(f"read_colmap_poses: cameras of different sizes {sorted(sizes)}")
    w, h = sizes.pop() if sizes else (0, 0)
    return PosedImages(names, np.array(poses).reshape(-1, 4, 4), np.array(Ks).reshape(-1, 3, 3), w, h)


# -------------------------------------------------------------------------------------------- nerfstudio


# nerfstudio reads depth PNGs as integers times its `depth_unit_scale_factor` (1e-3 unless told otherwise)
NERFSTUDIO_DEPTH_UNIT = 1e-3
NERFSTUDIO_DEPTH_MAX = 65535 * NERFSTUDIO_DEPTH_UNIT  # 16-bit PNG


def write_nerfstudio(
    out_dir: Path,
    frames: np.ndarray,
    K: np.ndarray,
    w2c: np.ndarray,
    names: list[str] | None = None,
    depths: list[np.ndarray] | None = None,
    points: PointCloud | None = None,
    world: str | None = None,
    keep: Collection[str] = (),
    scale: float | None = None,
) -> tuple[Path, dict[str, Any]]:
    """A nerfstudio dataset in `out_dir`; returns (the transforms.json path, {"scale_from_world",
    "depth_pixels", "depth_clipped", "per_frame": {name: [depth pixels, clipped]}} of the depth files written).

    transforms.json: camera_model "OPENCV" with k1 = k2 = p1 = p2 = 0, w, h, and fl_x, fl_y, cx, cy (top level
    when K is shared (3,3), else in each frame); frames: [{file_path: "images/<name>.png", transform_matrix,
    depth_file_path: "depths/<name>.png" (with `depths`)}], transform_matrix = camera-to-world in OpenGL
    camera axes (x right, y up, z back): C2W_opencv @ diag(1, -1, -1, 1); ply_file_path "points.ply" (with
    `points`: x, y, z, normals and colours); orientation_override "none", since the world is already +Z up as
    nerfstudio's (its default "up" orientation would turn it by the mean camera up); `wonderverse`: the world
    frame in words (`world`), the units and the depth convention.
    Units: nerfstudio reads depth PNGs as integers times its depth_unit_scale_factor (1e-3 by default: mm
    when the poses are in metres), so a 16-bit PNG holds depths up to 65.535 units at 0.001 precision. When
    the depths (their 99.9th percentile) do not fit that well (beyond 65.535, or below 0.65535 units), every
    length of the dataset (poses, points, depths) is the world's times a power of ten, `scale_from_world`,
    that fits them; nerfstudio scales every scene to its own box anyway, so nothing else changes.
    depths: per frame (any size: nerfstudio resizes it to the image, nearest) camera z in world units, +inf or
    NaN where nothing is; PNG 0 where nothing is, or where the depth is still beyond 65.535 (depth_clipped).
    frames: (N,H,W,3) uint8; names: file stems (default frame_00000, ...); frames without a finite pose are
    left out (no file written). keep: names whose image and depth files are already there, written at `scale` (an
    extended scene's earlier frames): not written again (their depths may be None). scale: the lengths' factor to
    use (None: `depth_png_scale` of the depths).
    """
    from PIL import Image

    from wonderverse.mesh import PointCloud, write_points_ply

    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.dtype != np.uint8:
        raise ValueError(f"frames must be (N,H,W,3) uint8, got {frames.shape} {frames.dtype}")
    n, h, w = frames.shape[:3]
    names = [f"frame_{i:05d}" for i in range(n)] if names is None else [Path(s).stem for s in names]
    w2c, Ks, valid = _check_poses(w2c, K, names)
    if len(w2c) != n:
        raise ValueError(f"need one pose per frame: {len(w2c)} poses for {n} frames")
    if depths is not None and len(depths) != n:
        raise ValueError(f"need one depth map per frame: {len(depths)} for {n} frames")
    out_dir = Path(out_dir)
    (out_dir / "images").mkdir(parents=True, exist_ok=True)
    if depths is not None:
        (out_dir / "depths").mkdir(parents=True, exist_ok=True)

    def intr(k: np.ndarray) -> dict[str, float]:
        return {"fl_x": float(k[0, 0]), "fl_y": float(k[1, 1]), "cx": float(k[0, 2]), "cy": float(k[1, 2])}

    shared = np.asarray(K).ndim == 2
    meta: dict = {"camera_model": "OPENCV", "w": int(w), "h": int(h), "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0}
    if shared:
        meta.update(intr(Ks[0]))
    if scale is None:
        scale = 1.0 if depths is None else depth_png_scale([d for d in depths if d is not None])
    stats: dict[str, Any] = {"scale_from_world": scale, "depth_pixels": 0, "depth_clipped": 0, "per_frame": {}}
    entries = []
    c2w_gl = invert_se3(w2c[valid]) @ OPENCV_TO_OPENGL
    c2w_gl[:, :3, 3] *= scale
    for i, T in zip(np.flatnonzero(valid), c2w_gl, strict=True):
        rel = f"images/{names[i]}.png"
        kept = names[i] in keep
        if not kept:
            Image.fromarray(frames[i]).save(out_dir / rel)
        entry: dict = {"file_path": rel, "transform_matrix": T.tolist()}
        if depths is not None:
            entry["depth_file_path"] = f"depths/{names[i]}.png"
        if depths is not None and not kept:
            png, clipped = _depth_png(np.asarray(depths[i], np.float64) * scale)
            Image.fromarray(png).save(out_dir / entry["depth_file_path"])
            stats["per_frame"][names[i]] = [int(np.count_nonzero(png)), clipped]
            stats["depth_pixels"] += int(np.count_nonzero(png))
            stats["depth_clipped"] += clipped
        if not shared:
            entry.update(intr(Ks[i]))
        entries.append(entry)
    meta["frames"] = entries
    meta["orientation_override"] = "none"
    if points is not None:
        scaled = PointCloud(np.asarray(points.points, np.float64) * scale, points.colors, points.normals)
        write_points_ply(out_dir / "points.ply", scaled, f"{world}; lengths times {scale!r}")
        meta["ply_file_path"] = "points.ply"
    meta["wonderverse"] = {
        "world": world or "the caller's world frame",
        "scale_from_world": scale,
        "units": f"every length here (poses, points.ply, depths) is the world's times {scale!r}",
        "transform_matrix": "camera-to-world, OpenGL camera axes (x right, y up, z back)",
        "depth": "16-bit PNG, camera z in thousandths of this file's unit (nerfstudio's default "
        "depth_unit_scale_factor 1e-3); 0 where nothing is (sky, background) or beyond 65.535 units",
    }
    path = out_dir / "transforms.json"
    path.write_text(json.dumps(meta, indent=1))  # json writes floats with repr: exact round trip
    return path, stats


def depth_png_scale(depths: list[np.ndarray]) -> float:
    """A power of ten a (1 when the depths already fit) such that the 99.9th percentile of the finite positive
    depths times a lies in [0.65535, 65.535]: 16-bit thousandths then keep 3 to 5 significant digits."""
    valid = [d[np.isfinite(d) & (d > 0)] for d in (np.asarray(x, np.float64) for x in depths)]
    allz = np.concatenate(valid) if valid else np.zeros(0)
    if not allz.size:
        return 1.0
    top = float(np.percentile(allz, 99.9))
    if NERFSTUDIO_DEPTH_MAX / 100 <= top <= NERFSTUDIO_DEPTH_MAX:
        return 1.0
    return float(10.0 ** np.floor(np.log10(NERFSTUDIO_DEPTH_MAX / top)))


def fits_scale(depths: list[np.ndarray], scale: float) -> bool:
    """Whether `depths` written at `scale` keep `depth_png_scale`'s band (their 99.9th percentile at 0.65535 to
    65.535 file units): a dataset extended with them can keep the scale its files were written at."""
    return depth_png_scale([np.asarray(d, np.float64) * scale for d in depths]) == 1.0


def _depth_png(depth: np.ndarray) -> tuple[np.ndarray, int]:
    """(uint16 image of depth / NERFSTUDIO_DEPTH_UNIT, 0 where not finite, not positive or too far; pixels too far)."""
    d = np.asarray(depth, np.float64)
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(d) & (d > 0)
        far = ok & (np.round(d / NERFSTUDIO_DEPTH_UNIT) > 65535)
    q = np.where(ok & ~far, np.round(np.where(ok, d, 0.0) / NERFSTUDIO_DEPTH_UNIT), 0.0)
    return q.astype(np.uint16), int(np.count_nonzero(far))


def nerfstudio_dataparser_frame(w2c: np.ndarray) -> tuple[np.ndarray, float]:
    """Where nerfstudio's NerfstudioDataParser puts this world, with its defaults (center_method "poses",
    auto_scale_poses, scale_factor 1) and our transforms.json's orientation_override "none": x_ns = (x -
    centre) * scale, centre = the mean camera centre of every frame (N,4,4 W2C, finite ones), scale = 1 /
    the largest |coordinate| of the centred camera centres. Returns (centre (3,), scale)."""
    w2c = np.asarray(w2c, np.float64).reshape(-1, 4, 4)
    c = camera_centers(w2c[np.isfinite(w2c).all(axis=(1, 2))])
    centre = c.mean(0)
    spread = float(np.abs(c - centre).max()) if len(c) else 0.0
    return centre, 1.0 / spread if spread > 0 else 1.0


def write_nerfstudio_camera_path(
    path: Path,
    w2c: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    fps: float,
    dataparser_frame: tuple[np.ndarray, float],
    world: str | None = None,
    keyframe_every: int = 10,
) -> Path:
    """A camera path in nerfstudio's format (what its viewer exports and `ns-render camera-path` reads);
    returns the path. Every pose must be finite.

    Keys: camera_type "perspective", render_width, render_height, fps, seconds (frames / fps), is_cycle false,
    smoothness_value 0, default_fov, default_transition_sec, keyframes [{matrix, fov, aspect}] (every
    keyframe_every-th pose and the last, for the viewer's path editor) and camera_path [{camera_to_world, fov,
    aspect}] (every pose, what ns-render renders): camera_to_world is a row-major 4x4 camera-to-world in OpenGL
    axes, fov the vertical field of view in degrees (nerfstudio renders with fx = fy from it and the principal
    point at the image centre). Poses are in nerfstudio's dataparser frame (`nerfstudio_dataparser_frame` of
    the dataset's cameras): the frame its models live in, so a model trained on our transforms.json with
    nerfstudio's defaults renders this path as it is. `wonderverse` states that and the world it came from.
    """
    w2c, Ks, valid = _check_poses(w2c, K, None)
    if not np.all(valid):
        raise ValueError(f"camera path has {int(np.sum(~valid))} non-finite poses")
    centre, scale = dataparser_frame
    c2w = invert_se3(w2c) @ OPENCV_TO_OPENGL
    c2w[:, :3, 3] = (c2w[:, :3, 3] - centre) * scale
    fov = np.degrees(2.0 * np.arctan(0.5 * height / Ks[:, 1, 1]))
    aspect = float(width) / float(height)
    n = len(w2c)
    cams = [{"camera_to_world": c2w[i].reshape(-1).tolist(), "fov": float(fov[i]), "aspect": aspect} for i in range(n)]
    keys = sorted({*range(0, n, max(1, keyframe_every)), n - 1})
    out = {
        "camera_type": "perspective",
        "render_height": int(height),
        "render_width": int(width),
        "fps": float(fps),
        "seconds": n / float(fps),
        "is_cycle": False,
        "smoothness_value": 0.0,
        "default_fov": float(fov[0]),
        "default_transition_sec": (keys[1] - keys[0]) / float(fps) if len(keys) > 1 else 1.0,
        "keyframes": [{"matrix": cams[i]["camera_to_world"], "fov": cams[i]["fov"], "aspect": aspect} for i in keys],
        "camera_path": cams,
        "wonderverse": {
            "frame": "nerfstudio's dataparser frame of ../transforms.json with its defaults (orientation none, as the "
            "file asks; center_method poses; auto_scale_poses; scale_factor 1): x_ns = (x_world - centre) * scale",
            "centre": centre.tolist(),
            "scale": float(scale),
            "world": world or "the caller's world frame",
        },
    }
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=1))
    return path


def read_nerfstudio_poses(path: Path) -> PosedImages:
    """Cameras of a nerfstudio transforms.json, in file order; names are the frames' file_path; W2C OpenCV axes,
    in the world's units (our files' `scale_from_world` undone)."""
    meta = json.loads(Path(path).read_text())
    scale = float(meta.get("wonderverse", {}).get("scale_from_world", 1.0))
    names, poses, Ks = [], [], []
    for fr in meta["frames"]:
        d = {**meta, **fr}  # per-frame intrinsics override the shared ones
        names.append(fr["file_path"])
        c2w_cv = np.asarray(fr["transform_matrix"], dtype=np.float64) @ OPENCV_TO_OPENGL
        c2w_cv[:3, 3] /= scale
        poses.append(invert_se3(c2w_cv))
        Ks.append(np.array([[d["fl_x"], 0.0, d["cx"]], [0.0, d["fl_y"], d["cy"]], [0.0, 0.0, 1.0]]))
    return PosedImages(names, np.array(poses).reshape(-1, 4, 4), np.array(Ks).reshape(-1, 3, 3), meta["w"], meta["h"])


# ------------------------------------------------------------------------------------------- camera path


def write_camera_path(
    path: Path,
    w2c: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    fps: float,
    names: list[str] | None = None,
    world: str | None = None,
) -> Path:
    """Write a camera path as JSON; returns the path. Every pose must be finite (a path is rendered whole).

    Layout: {format, convention (CAMERA_PATH_CONVENTION: W2C 4x4 row-major, OpenCV axes, K in pixels with
    centres at +0.5), world (the world frame in words: axes, origin, units), width, height, fps, K (3x3, when
    shared), frames: [{name, time_s, w2c (4x4), center (camera centre in world coordinates, for reading by
    eye), K (when per frame)}]}.
    """
    w2c, Ks, valid = _check_poses(w2c, K, names)
    if not np.all(valid):
        raise ValueError(f"camera path has {int(np.sum(~valid))} non-finite poses")
    n = len(w2c)
    names = [f"{i:05d}" for i in range(n)] if names is None else list(names)
    shared = np.asarray(K).ndim == 2
    centres = camera_centers(w2c)
    out: dict = {
        "format": CAMERA_PATH_FORMAT,
        "convention": CAMERA_PATH_CONVENTION,
        "world": world or "the caller's world frame",
        "width": int(width),
        "height": int(height),
        "fps": float(fps),
    }
    if shared:
        out["K"] = Ks[0].tolist()
    frames = []
    for i in range(n):
        fr: dict = {"name": names[i], "time_s": i / float(fps), "w2c": w2c[i].tolist(), "center": centres[i].tolist()}
        if not shared:
            fr["K"] = Ks[i].tolist()
        frames.append(fr)
    out["frames"] = frames
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=1))
    return path


def read_camera_path(path: Path) -> tuple[PosedImages, float]:
    """(cameras, fps) of a camera-path JSON written by write_camera_path; W2C OpenCV axes."""
    d = json.loads(Path(path).read_text())
    if d.get("format") not in (CAMERA_PATH_FORMAT, "wonderverse.camera_path/1"):
        raise ValueError(f"{path}: not a {CAMERA_PATH_FORMAT} file (format={d.get('format')!r})")
    frames = d["frames"]
    w2c = np.array([f["w2c"] for f in frames], dtype=np.float64).reshape(-1, 4, 4)
    K = np.array([f.get("K", d.get("K")) for f in frames], dtype=np.float64).reshape(-1, 3, 3)
    return PosedImages([f["name"] for f in frames], w2c, K, d["width"], d["height"]), float(d["fps"])

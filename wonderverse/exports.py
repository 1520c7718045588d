"""Cameras and points for other tools: COLMAP text models, nerfstudio `transforms.json`, camera-path JSON.

Inputs follow the project conventions: W2C poses (N,4,4) float64 in OpenCV camera axes (x right, y down,
z forward), a right-handed world with +z up, intrinsics K (3,3) shared or (N,3,3) per frame, in pixels with
pixel centres at +0.5 (cx = W/2 for a centred camera). COLMAP and nerfstudio use the same pixel-centre
convention, so K is written unchanged. Frames whose pose is not finite (NaN: not registered) are left out
of every export. Numbers are written with 17 significant digits, so re-reading gives the poses back to
rounding (far below 1e-9).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from wonderverse.camera import camera_centers, invert_se3, quat_from_matrix

CAMERA_PATH_FORMAT = "wonderverse.camera_path/1"
CAMERA_PATH_CONVENTION = (
    "w2c: world-to-camera 4x4 rigid transform, row-major, acting on column vectors: [x_cam; 1] = w2c @ [x_world; 1]. "
    "Camera axes OpenCV: x right, y down, z forward (depth = camera z). World right-handed, +z up, in world units "
    "(the scene's units; metres when the scene is metric). K: 3x3 pinhole intrinsics in pixels for an image of "
    "width x height, pixel centres at +0.5 (cx = width/2 for a centred camera). time_s = index / fps."
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


def _g(x: float) -> str:
    """A float with 17 significant digits: parses back to the same double."""
    return f"{float(x):.17g}"


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


def write_colmap_text(
    out_dir: Path,
    K: np.ndarray,
    w2c: np.ndarray,
    width: int,
    height: int,
    image_names: list[str],
    points: np.ndarray | None = None,
    colors: np.ndarray | None = None,
) -> Path:
    """Write a COLMAP text model (cameras.txt, images.txt, points3D.txt) into `out_dir`; returns out_dir.

    cameras.txt: PINHOLE cameras `CAMERA_ID PINHOLE W H fx fy cx cy`: one shared camera (id 1) when K is
    (3,3), else one per image with the image's id. images.txt: `IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME`
    and an empty 2-D point line, where (q, t) is COLMAP's cam_from_world, i.e. exactly our W2C (OpenCV axes):
    R = matrix of the Hamilton quaternion (w first), x_cam = R x_world + t. IMAGE_ID = index in the input
    + 1, so ids stay stable when frames without a finite pose are left out. points3D.txt:
    `POINT3D_ID X Y Z R G B ERROR` with error 0 and empty tracks (COLMAP and pycolmap read these).
    points (P,3) world coordinates; colors (P,3) uint8 or floats in [0,1] (grey when None).
    """
    w2c, Ks, valid = _check_poses(w2c, K, image_names)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    shared = np.asarray(K).ndim == 2
    ids = np.flatnonzero(valid) + 1

    cam_lines = ["# Camera list with one line of data per camera:", "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]"]
    for cam_id, k in [(1, Ks[0])] if shared else [(i, Ks[i - 1]) for i in ids]:
        params = " ".join(_g(v) for v in (k[0, 0], k[1, 1], k[0, 2], k[1, 2]))
        cam_lines.append(f"{cam_id} PINHOLE {int(width)} {int(height)} {params}")
    (out_dir / "cameras.txt").write_text("\n".join(cam_lines) + "\n")

    img_lines = [
        "# Image list with two lines of data per image:",
        "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
        "#   POINTS2D[] as (X, Y, POINT3D_ID)",
    ]
    for i in ids:
        pose = w2c[i - 1]
        q = quat_from_matrix(pose[:3, :3])
        nums = " ".join(_g(v) for v in (*q, *pose[:3, 3]))
        img_lines += [f"{i} {nums} {1 if shared else i} {image_names[i - 1]}", ""]
    (out_dir / "images.txt").write_text("\n".join(img_lines) + "\n")

    pts = np.zeros((0, 3)) if points is None else np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or not np.all(np.isfinite(pts)):
        raise ValueError(f"points must be finite (P,3), got shape {pts.shape}")
    cols = _colors_uint8(colors, len(pts))
    pt_lines = ["# 3D point list with one line of data per point:", "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[]"]
    for j, (p, c) in enumerate(zip(pts, cols, strict=True)):
        pt_lines.append(f"{j + 1} {_g(p[0])} {_g(p[1])} {_g(p[2])} {c[0]} {c[1]} {c[2]} 0")
    (out_dir / "points3D.txt").write_text("\n".join(pt_lines) + "\n")
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


def write_nerfstudio(
    out_dir: Path,
    frames: np.ndarray,
    K: np.ndarray,
    w2c: np.ndarray,
    names: list[str] | None = None,
) -> Path:
    """Write a nerfstudio dataset: `out_dir/images/<name>.png` and `out_dir/transforms.json`; returns the json path.

    transforms.json: camera_model "OPENCV" with k1 = k2 = p1 = p2 = 0, w, h, and fl_x, fl_y, cx, cy (top
    level when K is shared (3,3), else in each frame); frames: [{file_path: "images/<name>.png",
    transform_matrix}], where transform_matrix is camera-to-world in OpenGL camera axes (x right, y up,
    z back): C2W_opencv @ diag(1, -1, -1, 1). The world is ours (right-handed, +z up, world units),
    which is nerfstudio's up axis. frames: (N,H,W,3) uint8; names: file stems (default frame_00000, ...);
    frames without a finite pose are left out (no image written).
    """
    from PIL import Image

    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.dtype != np.uint8:
        raise ValueError(f"frames must be (N,H,W,3) uint8, got {frames.shape} {frames.dtype}")
    n, h, w = frames.shape[:3]
    names = [f"frame_{i:05d}" for i in range(n)] if names is None else [Path(s).stem for s in names]
    w2c, Ks, valid = _check_poses(w2c, K, names)
    if len(w2c) != n:
        raise ValueError(f"need one pose per frame: {len(w2c)} poses for {n} frames")
    out_dir = Path(out_dir)
    (out_dir / "images").mkdir(parents=True, exist_ok=True)

    def intr(k: np.ndarray) -> dict[str, float]:
        return {"fl_x": float(k[0, 0]), "fl_y": float(k[1, 1]), "cx": float(k[0, 2]), "cy": float(k[1, 2])}

    shared = np.asarray(K).ndim == 2
    meta: dict = {"camera_model": "OPENCV", "w": int(w), "h": int(h), "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0}
    if shared:
        meta.update(intr(Ks[0]))
    entries = []
    c2w_gl = invert_se3(w2c[valid]) @ OPENCV_TO_OPENGL
    for i, T in zip(np.flatnonzero(valid), c2w_gl, strict=True):
        rel = f"images/{names[i]}.png"
        Image.fromarray(frames[i]).save(out_dir / rel)
        entry: dict = {"file_path": rel, "transform_matrix": T.tolist()}
        if not shared:
            entry.update(intr(Ks[i]))
        entries.append(entry)
    meta["frames"] = entries
    path = out_dir / "transforms.json"
    path.write_text(json.dumps(meta, indent=1))  # json writes floats with repr: exact round trip
    return path


def read_nerfstudio_poses(path: Path) -> PosedImages:
    """Cameras of a nerfstudio transforms.json, in file order; names are the frames' file_path; W2C OpenCV axes."""
    meta = json.loads(Path(path).read_text())
    names, poses, Ks = [], [], []
    for fr in meta["frames"]:
        d = {**meta, **fr}  # per-frame intrinsics override the shared ones
        names.append(fr["file_path"])
        c2w_cv = np.asarray(fr["transform_matrix"], dtype=np.float64) @ OPENCV_TO_OPENGL
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
) -> Path:
    """Write a camera path as JSON; returns the path. Every pose must be finite (a path is rendered whole).

    Layout: {format, convention (CAMERA_PATH_CONVENTION: W2C 4x4 row-major, OpenCV axes, +z-up world, world
    units, K in pixels with centres at +0.5), width, height, fps, K (3x3, when shared), frames: [{name,
    time_s, w2c (4x4), center (camera centre in world coordinates, for reading by eye), K (when per frame)}]}.
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
    if d.get("format") != CAMERA_PATH_FORMAT:
        raise ValueError(f"{path}: not a {CAMERA_PATH_FORMAT} file (format={d.get('format')!r})")
    frames = d["frames"]
    w2c = np.array([f["w2c"] for f in frames], dtype=np.float64).reshape(-1, 4, 4)
    K = np.array([f.get("K", d.get("K")) for f in frames], dtype=np.float64).reshape(-1, 3, 3)
    return PosedImages([f["name"] for f in frames], w2c, K, d["width"], d["height"]), float(d["fps"])

"""The dataset products: the posed frames as a COLMAP dataset and as a nerfstudio one, for other trainers."""

from __future__ import annotations

import shutil
from collections.abc import Callable, Collection
from pathlib import Path
from typing import Any

import numpy as np

from wonderverse.exports import ColmapTracks, project_tracks, read_colmap_tracks, write_colmap_dataset, write_nerfstudio
from wonderverse.mesh import PointCloud
from wonderverse.products import Written

FROM_MODEL = "the global SfM (the poses step's COLMAP model)"
FROM_PROJECTIONS = "projections of points.ply into the frames where the rendered depth sees them"


def model_tracks(
    model_dir: Path, names: list[str], size: tuple[int, int], to_output: Callable[[np.ndarray], np.ndarray]
) -> ColmapTracks:
    """The points of the COLMAP model in `model_dir` (the global SfM's), mapped by `to_output` into the output
    frame, with their measured observations: one list per frame of `names` (`s000_0007`), scaled from the model's
    image size to `size` (width, height)."""
    model, model_names, sizes = read_colmap_tracks(model_dir)
    ours = {name: i for i, name in enumerate(names)}
    empty = (np.zeros((0, 2)), np.zeros(0, np.int64))
    obs = [empty] * len(names)
    for name, seen, (mw, mh) in zip(model_names, model.observations, sizes, strict=True):
        # COLMAP names are `global_poses.image_names`: <lane><frame>_<segment>_<index>.png
        key = "_".join(Path(name).stem.split("_")[-2:])
        if key in ours:
            obs[ours[key]] = (seen[0] * [size[0] / mw, size[1] / mh], seen[1])
    points = to_output(model.points) if len(model.points) else model.points
    return ColmapTracks(points, model.colors, model.errors, obs)


def projected_tracks(
    cloud: PointCloud, w2c: np.ndarray, K: np.ndarray, size: tuple[int, int], depths: list[np.ndarray], depth_K: Any
) -> ColmapTracks:
    """Tracks made from the point cloud where no SfM model exists: each point observed in the frames whose rendered
    depth (`depths`, camera z at `depth_K`) sees it."""
    obs = project_tracks(cloud.points, w2c, K, size[0], size[1], depths, depth_K)
    return ColmapTracks(cloud.points, cloud.colors, np.zeros(len(cloud.points)), obs)


def export_colmap(
    frames: np.ndarray, K: np.ndarray, w2c: np.ndarray, names: list[str], tracks: ColmapTracks, tracks_from: str,
    world: str, out: Path, keep: Collection[str] = (),
) -> list[Written]:  # fmt: skip
    """out/colmap/: images/ and sparse/0/ (binary model with `tracks`), and a README.txt saying what it holds.
    `keep`: frames whose image file is there from an earlier export of the same frame (not written again)."""
    folder = _refresh(out / "colmap", names, keep)
    write_colmap_dataset(folder, frames, K, w2c, names, tracks, keep_images=keep)
    (folder / "README.txt").write_text(_colmap_readme(world, tracks_from))
    return [Written(folder, f"COLMAP dataset (images/, sparse/0/ binary model with tracks from {tracks_from})")]


def export_nerfstudio(
    frames: np.ndarray, K: np.ndarray, w2c: np.ndarray, names: list[str], depths: list[np.ndarray | None],
    cloud: PointCloud, world: str, out: Path, keep: Collection[str] = (), scale: float | None = None,
) -> tuple[list[Written], dict[str, Any]]:  # fmt: skip
    """out/nerfstudio/: transforms.json, images, 16-bit depth PNGs and points.ply (its camera_paths/ are the
    camera-path product's and are kept). `keep`: frames whose image and depth files are there from an earlier
    export at `scale` (not written again; their depths may be None). Returns the files and {depth_pixels,
    depth_clipped, per_frame, scale_from_world} of what was written."""
    folder = _refresh(out / "nerfstudio", names, keep, spare="camera_paths")
    path, stats = write_nerfstudio(folder, frames, K, w2c, names, depths, cloud, world, keep=keep, scale=scale)
    what = "nerfstudio dataset (transforms.json, images, 16-bit depth PNGs, points.ply, camera paths)"
    return [Written(path.parent, what)], stats


def _refresh(folder: Path, names: list[str], keep: Collection[str], spare: str | None = None) -> Path:
    """`folder` (the product's own) made ready to be written: files of an earlier run must not stay beside the new
    ones (frames since dropped, an older layout), so everything goes but its entry `spare` and, in its images/ and
    depths/, the files of the frames in `keep`."""
    if folder.is_symlink() or not folder.is_dir():
        return folder
    kept = {f"{name}.png" for name in keep} & {f"{name}.png" for name in names}
    for child in folder.iterdir():
        if child.name == spare:
            continue
        if child.name in ("images", "depths") and child.is_dir() and not child.is_symlink():
            for f in child.iterdir():
                if f.name not in kept:
                    f.unlink()
        elif child.is_dir() and not child.is_symlink():
            shutil.rmtree(child)
        else:
            child.unlink()
    return folder


def _colmap_readme(world: str, tracks_from: str) -> str:
    return (
        "A COLMAP dataset written by WonderVerse: images/ (the stitched frames, PNG) and sparse/0/ (COLMAP's binary\n"
        "model, written by pycolmap: cameras.bin with one PINHOLE camera, images.bin with every posed frame as\n"
        "cam_from_world, points3D.bin with tracks). Trainers read it as it is (gsplat's examples, INRIA 3DGS,\n"
        "nerfstudio's colmap data parser).\n"
        f"{world}.\n"
        f"Points and their 2-D observations: {tracks_from}. Frames the SfM did not solve directly have poses\n"
        "and no observations.\n"
    )

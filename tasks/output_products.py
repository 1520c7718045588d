"""How each product of the outputs step is made from an `OutputScene`: one function per product, each calling the
library's entry point for it (`wonderverse.products`) and returning what is kept in its group `outputs/<product>`
(`Made`: the files written, its figures, its arrays). The records of the products it comes after are in
`scene.records`; the mesh's maker is `tasks.output_mesh`."""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from tasks.output_scene import Made, OutputScene
from tasks.progress import callback
from wonderverse.schema import SFM
from wonderverse.schema.attrs import OutputProductAttrs

MIN_GROUND_POINTS = 30  # fewer SfM points than this: the ground is sought among the splats' opaque centres


def make_frame(scene: OutputScene) -> Made:
    """The output world frame: the `sfm/` frame turned so that +Z is up (`estimate_gravity` from the cameras and the
    ground), origin on the ground below the cameras' centroid; poses from the conditioning path are already in the
    video backend's +Z-up world, which is kept as it is."""
    from wonderverse.gravity import estimate_gravity, given_frame
    from wonderverse.mesh import gaussian_points
    from wonderverse.products import world_statement

    store = scene.store
    source = store.meta(SFM.path).source
    if source == "conditioning":  # the video backend's own world: its paths were planned with +Z up
        gravity = given_frame("the conditioning camera path's world, +Z up by construction")
    else:
        # the ground plane is sought in the SfM points: on procedural scenes their plane was 2.5°, 13.2°, 8.7° and
        # 5.0° off the true up where the fused mesh's was 10.2°, 14.5°, 16.1° and 14.6° (the cameras decided on
        # all of them: within 0.05° on the 3-segment preview scenes, 0.2° and 1.6° on two 10-frame ones)
        points = store.array(SFM.points3d)
        if len(points) < MIN_GROUND_POINTS:
            points = gaussian_points(scene.arrays, scene.norm_sfm, 0.5).points
        gravity = estimate_gravity(scene.w2c_sfm, points)
    g = gravity.world_from_input
    world = world_statement(gravity, source)
    frame = {"world_from_sfm": g.to_dict(), "up_in_sfm": gravity.up.tolist(), "world": world} | gravity.evidence
    return Made(record={"frame": frame})


def make_splat_files(scene: OutputScene) -> Made:
    """The Gaussians, pruned of floaters, absurd and invisible ones (viewers frame and render what is left)."""
    from wonderverse.products.splat_files import export_splats
    from wonderverse.splats.ply import to_world

    store, g = scene.store, scene.to_world
    points = g.apply(store.array(SFM.points3d)) if store.exists(SFM.points3d) else None
    extent = scene.records["mesh"].mesh.extent
    gaussians = to_world(scene.arrays, scene.norm)
    files, pruned = export_splats(
        gaussians, scene.w2c, scene.K, scene.size, points, extent, scene.p.prune, scene.world, scene.out
    )
    return Made(files, {"pruned": pruned})


def make_points(scene: OutputScene) -> Made:
    from wonderverse.products.splat_files import export_points

    return Made(export_points(scene.cloud, scene.world, scene.out), {"points": len(scene.cloud.points)})


def make_colmap(scene: OutputScene) -> Made:
    """A COLMAP dataset with the global SfM's tracks (or, without an SfM model, the point cloud's projections); the
    images of frames an earlier export wrote as they are now stay."""
    from wonderverse.products.datasets import FROM_MODEL, FROM_PROJECTIONS, export_colmap, projected_tracks

    if not scene.p.colmap:
        return Made()
    tracks = _model_tracks(scene)
    tracks_from = FROM_MODEL
    if tracks is None:
        tracks_from = FROM_PROJECTIONS
        tracks = projected_tracks(scene.cloud, scene.w2c, scene.K, scene.size, scene.training_depths, scene.Kr)
    keep, _ = _kept(scene, "colmap")
    args = (scene.frames, scene.K, scene.w2c, scene.names, tracks, tracks_from, scene.world, scene.out)
    files = export_colmap(*args, keep=keep)
    return Made(files, {"colmap": {"tracks_from": tracks_from}, "frames": scene.frame_digests})


def _model_tracks(scene: OutputScene) -> Any:
    """The global SfM's points and observations in the output frame (its COLMAP model, mapped into the world
    through `model_to_world` and on into the output frame), or None when the poses did not come from SfM."""
    from wonderverse.camera import Sim3
    from wonderverse.products.datasets import model_tracks

    store = scene.store
    if not store.exists(SFM.colmap_model):
        return None
    stored = store.meta(SFM.path).model_to_world
    model_to_world = Sim3.identity() if stored is None else Sim3.from_dict(stored)
    g = scene.to_world
    with tempfile.TemporaryDirectory() as d:
        for f in store.children(SFM.colmap_model):
            (Path(d) / f).write_bytes(store.array(SFM.colmap_model.array(f)).tobytes())
        return model_tracks(Path(d), scene.names, scene.size, lambda p: g.apply(model_to_world.apply(p)))


def make_nerfstudio(scene: OutputScene) -> Made:
    """A nerfstudio dataset; the images and depths of frames an earlier export wrote as they are now stay (their
    depths rendered from the splats of then), unless the new frames' depths do not fit the files' scale of lengths
    (`depth_png_scale`'s band of three to five significant digits). Any scale that fits will do: the new frames' own
    scale may be another power of ten whenever they alone fall in another decade."""
    from wonderverse.exports import fits_scale
    from wonderverse.products.datasets import export_nerfstudio

    if not scene.p.nerfstudio:
        return Made()
    keep, before = _kept(scene, "nerfstudio")
    todo = [k for k, name in enumerate(scene.names) if name not in keep]
    new = [d for _, d in scene.views(scene.w2c_sfm[todo], "views rendered for depth")]
    old = before.nerfstudio if before is not None and before.nerfstudio else {}
    scale = old.get("scale_from_world")
    if keep and (scale is None or not fits_scale(new, scale)):
        keep, todo = set(), list(range(len(scene.names)))
        new = [d for _, d in scene.views(scene.w2c_sfm, "views rendered for depth")]
    depths: list[np.ndarray | None] = [None] * len(scene.names)
    for k, d in zip(todo, new, strict=True):
        depths[k] = d
    scale = scale if keep else None
    args = (scene.frames, scene.K, scene.w2c, scene.names, depths, scene.cloud, scene.world, scene.out)
    files, stats = export_nerfstudio(*args, keep=keep, scale=scale)
    per_frame = {n: c for n, c in (old.get("per_frame") or {}).items() if n in keep} | stats["per_frame"]
    stats |= {"per_frame": per_frame, "depth_pixels": sum(c[0] for c in per_frame.values())}
    stats["depth_clipped"] = sum(c[1] for c in per_frame.values())
    return Made(files, {"nerfstudio": stats, "frames": scene.frame_digests})


def _kept(scene: OutputScene, product: str) -> tuple[set[str], OutputProductAttrs | None]:
    """The frames whose files an earlier export of `product` with these settings wrote as they are now (same
    pixels, same pose), and that export's record; none when there was no such export."""
    from wonderverse.schema import OUTPUT_PRODUCT

    before = scene.store.meta(OUTPUT_PRODUCT.at(product=product))
    if before is None or before.settings != scene.settings[product]:
        return set(), None
    now = scene.frame_digests
    return {name for name, digest in before.frames.items() if now.get(name) == digest}, before


def _video_paths(scene: OutputScene) -> dict[str, np.ndarray]:
    from wonderverse.products.camera_paths import video_paths

    p = scene.p
    return video_paths(scene.w2c, p.video_frames, p.novel_offset_frac, scene.records["mesh"].mesh.look)


def make_camera_paths(scene: OutputScene) -> Made:
    from wonderverse.products.camera_paths import export_camera_paths

    p = scene.p
    ns = scene.w2c if p.nerfstudio else None
    return Made(
        export_camera_paths(_video_paths(scene), scene.Kr, scene.render_size, p.video_fps, scene.world, scene.out, ns)
    )


def make_videos(scene: OutputScene) -> Made:
    from wonderverse.products.videos import export_video

    paths, files = _video_paths(scene), []
    for name, unit, what in (
        ("flythrough", "fly-through frames", "fly-through video of the splats (H.264, faststart)"),
        ("novel", "novel-view frames", "novel-view video off the training path (H.264)"),
    ):
        rgb = _rgb(scene.render(paths[name], scene.norm, unit))
        scene.video_frames[name] = rgb
        files.append(export_video(rgb, scene.p.video_fps, scene.out / f"{name}.mp4", what))
    return Made(files)


def make_quality(scene: OutputScene) -> Made:
    """No-reference quality of novel views: the scored frames of the novel video (rendered alone when the video was
    not made in this run)."""
    from wonderverse.products.videos import quality_picks
    from wonderverse.quality import score_views

    novel = _video_paths(scene)["novel"]
    picks = quality_picks(len(novel), scene.p.quality_frames)
    made = scene.video_frames.get("novel")
    rgb = made[picks] if made is not None else _rgb(scene.render(novel[picks], scene.norm, "views scored"))
    metrics = callback("quality metrics", eta=False)  # unequal: NIQE is quick, a CLIP model loads first
    return Made(record={"quality": score_views(list(rgb), scene.prompt, scene.p.quality, metrics)})


def _rgb(views: list[Any]) -> np.ndarray:
    return np.stack([np.round(v.rgb * 255).astype(np.uint8) for v in views])

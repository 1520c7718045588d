"""Step `outputs`: the files users open elsewhere, written beside the store from the trained splats, all in
one gravity-aligned world frame.

  splats.ply              the Gaussians, INRIA 3DGS layout (floaters and absurd Gaussians pruned first)
  splats.spz, splats.glb  the same Gaussians for the web: Niantic's SPZ, glTF with KHR_gaussian_splatting
  points.ply              Gaussian centres at least `mesh.points_min_opacity` opaque, base colour, normals
  mesh.ply, mesh.glb      TSDF fusion of splat renders from the training cameras (sky/background excluded)
  colmap/                 images/ + sparse/0/ (binary model with the global SfM's tracks): a training dataset
  nerfstudio/             transforms.json, images/, depths/, points.ply, camera_paths/{flythrough,novel}.json
  camera_path.json        the fly-through path, novel_path.json the novel track (W2C, OpenCV axes; our format)
  flythrough.mp4          splat renders along a smooth path through the whole scene
  novel.mp4               splat renders along a parallel path off the training trajectory

The world frame: the global poses' frame (`sfm/`, SfM's arbitrary orientation) turned so that +Z is up
(`wonderverse.gravity.estimate_gravity` from the cameras and the ground in the SfM points), with its origin on the
ground below the cameras' centroid, in the poses' units; poses from the conditioning path are already in the
video backend's +Z-up world, which is kept as it is. `output_frame(store)` gives the transform from the
`sfm/` frame; the `outputs` group records it (`frame`) with the evidence, and lists the files with their
sizes and what each holds. It is committed last, so a killed run rewrites them all on the next run.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from tasks.base import Step, StepContext
from tasks.progress import callback
from wonderverse.config import Model, OutputsParams, RunConfig
from wonderverse.schema import OUTPUTS, SFM, SPLATS
from wonderverse.store import SceneStore

if TYPE_CHECKING:
    from wonderverse.camera import Sim3
    from wonderverse.exports import ColmapTracks
    from wonderverse.gravity import GravityFrame

log = logging.getLogger("wonderverse.outputs")


class Params(Model):
    """The outputs' settings, and the prompt the novel views are scored against (CLIP-S)."""

    outputs: OutputsParams
    prompt: str


def params(cfg: RunConfig) -> Params:
    return Params(outputs=cfg.steps.outputs, prompt=cfg.scene.prompt)


def posed_frames(store: SceneStore) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Stitched frames that have a global pose: frames (N,H,W,3) uint8, W2C (N,4,4) in the `sfm/` frame,
    names `s000_0007`."""
    from tasks.segments import attempt_path, posed_stitched

    rows, w2c, names = posed_stitched(store, {"frames": lambda seg: attempt_path(store, seg).frames})
    return rows["frames"], w2c, names


def output_frame(store: SceneStore) -> Sim3:
    """The rigid transform from the global poses' frame (`sfm/`) to the frame every output file is in
    (x_out = R (x_sfm - origin)); for readers that compare the files with the store (the report, benchmarks).
    Raises KeyError when the outputs step has not recorded one."""
    from wonderverse.camera import Sim3

    return Sim3.from_dict(store.attrs(OUTPUTS.path)["frame"]["world_from_sfm"])


def world_statement(gravity: GravityFrame, source: str | None) -> str:
    """The output world frame in words, as every file states it."""
    units = (
        "SfM units (the reconstruction's own arbitrary scale, not metres)"
        if source == "sfm"
        else "the units of the conditioning camera path (the procedural world's: metres times its scene_scale)"
    )
    how = gravity.evidence["source"]
    up = f"gravity estimated from {how}" if source == "sfm" else how
    return f"world frame: right-handed, +Z up ({up}), origin {gravity.evidence['origin']}; units: {units}"


def run(store: SceneStore, params: Params, ctx: StepContext) -> str:
    from tasks.splats import stored_sky
    from wonderverse.camera import camera_centers, fit_intrinsics
    from wonderverse.exports import (
        nerfstudio_dataparser_frame,
        write_camera_path,
        write_colmap_dataset,
        write_nerfstudio,
        write_nerfstudio_camera_path,
    )
    from wonderverse.gravity import estimate_gravity, given_frame
    from wonderverse.media import write_mp4
    from wonderverse.mesh import (
        TriMesh,
        fusion_cameras,
        gaussian_points,
        mesh_from_views,
        set_ply_comments,
        write_mesh,
        write_points_ply,
    )
    from wonderverse.paths import flythrough_path, novel_view_path
    from wonderverse.quality import score_views
    from wonderverse.splats.cleanup import prune_for_export
    from wonderverse.splats.model import GaussianModel, normalization_from_dict
    from wonderverse.splats.ply import to_world, write_ply
    from wonderverse.splats.renderer import make_renderer
    from wonderverse.splats.views import render_views
    from wonderverse.splats.web import write_splat_glb, write_spz

    p = params.outputs
    out = Path(store.scene_dir)
    splats = store.attrs(SPLATS.path)
    norm_sfm = normalization_from_dict(splats["normalization"])
    arrays = {name: store.array(getattr(SPLATS, name)) for name in GaussianModel.PARAM_NAMES}
    background = stored_sky(store)
    frames, w2c_sfm, names = posed_frames(store)
    K = store.array(SFM.K)
    height, width = frames.shape[1:3]
    w, h, Kr = fit_intrinsics(width, height, K, p.render_max_side_px)
    renderer = make_renderer(ctx.execution.renderer)
    workers = ctx.execution.render_workers or _usable_cores()
    files: list[tuple[Path, str]] = []

    def render(poses: np.ndarray, norm: Sim3, unit: str) -> list[Any]:
        views = render_views(
            arrays, norm, poses, Kr, w, h, renderer, background=background, workers=workers, progress=callback(unit)
        )
        return list(views)

    # The fused mesh first, in the SfM frame (it is turned into the output frame once that is known).
    # Colour as uint8 and depth only: nothing else is needed, and every view is held until the extent is known.
    cams_sfm = fusion_cameras(w2c_sfm, p.mesh.extra_views_per_gap)
    rendered = render(cams_sfm, norm_sfm, "views rendered for the mesh")
    views = [(np.round(v.rgb * 255).astype(np.uint8), v.depth) for v in rendered]
    del rendered
    mesh_sfm, extent = mesh_from_views(views, cams_sfm, Kr, p.mesh, progress=callback("views fused"))

    source = store.attrs(SFM.path).get("source")
    if source == "conditioning":  # the video backend's own world: its paths were planned with +Z up
        gravity = given_frame("the conditioning camera path's world, +Z up by construction")
    else:
        # the ground plane is sought in the SfM points: on procedural scenes their plane was 2.5°, 13.2°, 8.7° and
        # 5.0° off the true up where the fused mesh's was 10.2°, 14.5°, 16.1° and 14.6° (the cameras decided on
        # all of them: within 0.05° on the 3-segment preview scenes, 0.2° and 1.6° on two 10-frame ones)
        points = store.array(SFM.points3d)
        gravity = estimate_gravity(w2c_sfm, points if len(points) >= 30 else mesh_sfm.vertices)
    g = gravity.world_from_input
    world = world_statement(gravity, source)
    log.info("output frame: %s", world)
    norm = norm_sfm.compose(g.inverse())  # output world -> the splats' training frame
    w2c = g.transform_w2c(w2c_sfm)
    centres = camera_centers(w2c)

    # floaters, absurd and invisible Gaussians go before export: viewers frame and render what is left
    points_world = g.apply(store.array(SFM.points3d)) if store.exists(SFM.points3d) else None
    gaussians, pruned = prune_for_export(to_world(arrays, norm), w2c, K, width, height, points_world, extent, p.prune)
    ply = write_ply(out / "splats.ply", gaussians)
    set_ply_comments(ply, [f"WonderVerse Gaussian splats (INRIA 3DGS layout): {world}"])
    files.append((ply, f"Gaussian splats, INRIA 3DGS PLY layout; {world}"))
    spz_axes = "SPZ's RUB axes: +Y up (the world's +Z), +Z the world's -Y"
    files.append((write_spz(out / "splats.spz", gaussians), f"Gaussian splats, Niantic SPZ v3; {spz_axes}; {world}"))
    glb_axes = "glTF axes: +Y up (the world's +Z)"
    splat_glb = write_splat_glb(out / "splats.glb", gaussians)
    files.append((splat_glb, f"Gaussian splats, glTF with KHR_gaussian_splatting; {glb_axes}; {world}"))
    cloud = gaussian_points(arrays, norm, p.mesh.points_min_opacity, toward=centres)
    files.append((write_points_ply(out / "points.ply", cloud, world), f"point cloud with normals; {world}"))
    mesh = TriMesh(g.apply(mesh_sfm.vertices), mesh_sfm.triangles, mesh_sfm.colors)
    files.append((write_mesh(mesh, out / "mesh.ply", world), f"mesh with vertex normals (PLY); {world}"))
    glb = f"glTF axes: +Y up (the world's +Z), +Z towards the viewer (the world's -Y), +X the world's +X; {world}"
    files.append((write_mesh(mesh, out / "mesh.glb", glb), "mesh for viewers (glTF binary, +Y up, vertex colours)"))

    extra = p.mesh.extra_views_per_gap + 1  # views[i * extra] was rendered from training camera i
    stats: dict[str, Any] = {}
    if p.colmap:
        tracks, tracks_from = _colmap_tracks(store, g, names, (width, height))
        if tracks is None:
            from wonderverse.exports import ColmapTracks, project_tracks

            depths = [views[i * extra][1] for i in range(len(w2c))]
            obs = project_tracks(cloud.points, w2c, K, width, height, depths, Kr)
            tracks = ColmapTracks(cloud.points, cloud.colors, np.zeros(len(cloud.points)), obs)
        _fresh(out / "colmap")
        colmap = write_colmap_dataset(out / "colmap", frames, K, w2c, names, tracks)
        (colmap / "README.txt").write_text(_colmap_readme(world, tracks_from))
        stats["colmap"] = {"tracks_from": tracks_from}
        files.append((colmap, f"COLMAP dataset (images/, sparse/0/ binary model with tracks from {tracks_from})"))
    if p.nerfstudio:
        depths = [views[i * extra][1] for i in range(len(w2c))]
        _fresh(out / "nerfstudio")
        path, stats["nerfstudio"] = write_nerfstudio(out / "nerfstudio", frames, K, w2c, names, depths, cloud, world)
        files.append(
            (path.parent, "nerfstudio dataset (transforms.json, images, 16-bit depth PNGs, points.ply, camera paths)")
        )

    finite = np.concatenate([d[np.isfinite(d)] for _, d in views]) if views else np.zeros(0)
    look = float(np.median(finite)) if finite.size else None
    del views
    fly = flythrough_path(w2c, p.video_frames)
    novel = novel_view_path(w2c, p.video_frames, p.novel_offset_frac, look)
    ns_frame = nerfstudio_dataparser_frame(w2c)
    for poses, ours, name in ((fly, "camera_path.json", "flythrough"), (novel, "novel_path.json", "novel")):
        files.append((write_camera_path(out / ours, poses, Kr, w, h, p.video_fps, world=world), f"{name} camera path"))
        if p.nerfstudio:
            ns = out / "nerfstudio" / "camera_paths" / f"{name}.json"
            write_nerfstudio_camera_path(ns, poses, Kr, w, h, p.video_fps, ns_frame, world)

    def video(poses: np.ndarray, name: str, unit: str, what: str) -> np.ndarray:
        rgb = np.stack([np.round(v.rgb * 255).astype(np.uint8) for v in render(poses, norm, unit)])
        files.append((write_mp4(rgb, out / name, p.video_fps), what))
        return rgb

    video(fly, "flythrough.mp4", "fly-through frames", "fly-through video of the splats (H.264, faststart)")
    novel_rgb = video(novel, "novel.mp4", "novel-view frames", "novel-view video off the training path (H.264)")
    picks = np.linspace(0, len(novel_rgb) - 1, min(p.quality_frames, len(novel_rgb))).round().astype(int)
    metrics = callback("quality metrics", eta=False)  # unequal: NIQE is quick, a CLIP model loads first
    quality = score_views(list(novel_rgb[picks]), params.prompt, p.quality, metrics)  # of the novel views

    listed = [{"path": f.name, "bytes": _size(f), "description": what} for f, what in files]
    mesh_stats = {"triangles": len(mesh.triangles), "vertices": len(mesh.vertices), "points": len(cloud.points)}
    frame = {"world_from_sfm": g.to_dict(), "up_in_sfm": gravity.up.tolist(), "world": world} | gravity.evidence
    with store.staged(
        OUTPUTS.path,
        ctx.key,
        files=listed,
        mesh=mesh_stats | {"extent": extent},
        render_size=[w, h],
        quality=quality,
        frame=frame,
        pruned=pruned,
        **stats,
    ):
        pass
    return (
        f"{len(files)} files: mesh {mesh_stats['triangles']} triangles, {mesh_stats['points']} points, 2 videos; "
        f"up from {gravity.evidence['source']}"
    )


def _colmap_tracks(
    store: SceneStore, g: Sim3, names: list[str], size: tuple[int, int]
) -> tuple[ColmapTracks | None, str]:
    """The global SfM's points with their measured observations (the poses step's COLMAP model, mapped into
    the output frame through `model_to_world` and `g`), one observation list per frame of `names`; or
    (None, how the caller makes them) when the poses did not come from SfM."""
    import tempfile

    from wonderverse.camera import Sim3
    from wonderverse.exports import ColmapTracks, read_colmap_tracks

    if not store.exists(SFM.colmap_model):
        return None, "projections of points.ply into the frames where the rendered depth sees them"
    attrs = store.attrs(SFM.path)
    to_world = Sim3.from_dict(attrs["model_to_world"]) if "model_to_world" in attrs else Sim3.identity()
    with tempfile.TemporaryDirectory() as d:
        for f in store.children(SFM.colmap_model):
            (Path(d) / f).write_bytes(store.array(SFM.colmap_model.array(f)).tobytes())
        model, model_names, sizes = read_colmap_tracks(Path(d))
    ours = {name: i for i, name in enumerate(names)}
    empty = (np.zeros((0, 2)), np.zeros(0, np.int64))
    obs = [empty] * len(names)
    for name, seen, (mw, mh) in zip(model_names, model.observations, sizes, strict=True):
        # COLMAP names are `global_poses.image_names`: <lane><frame>_<segment>_<index>.png
        key = "_".join(Path(name).stem.split("_")[-2:])
        if key in ours:
            obs[ours[key]] = (seen[0] * [size[0] / mw, size[1] / mh], seen[1])
    points = g.apply(to_world.apply(model.points)) if len(model.points) else model.points
    return ColmapTracks(points, model.colors, model.errors, obs), "the global SfM (the poses step's COLMAP model)"


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


def _fresh(folder: Path) -> None:
    """An export folder emptied before it is written: files of an earlier run (frames since dropped, an older
    layout) must not stay beside the new ones. The folder is the outputs step's own."""
    import shutil

    if folder.is_dir() and not folder.is_symlink():
        shutil.rmtree(folder)


def _usable_cores() -> int:
    """The cores this process may run on (its CPU affinity where the OS has one), not the host's count."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def _size(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file()) if path.is_dir() else path.stat().st_size


# 3: the step contract
# 4: one gravity-aligned frame for every file; splats.ply written here, pruned, with splats.spz and splats.glb;
#    COLMAP dataset with tracks; nerfstudio depths, points and camera paths; novel_path.json; faststart videos
STEP = Step(
    "outputs", 4, ("splats",), params, run, "mesh, point cloud, COLMAP/nerfstudio exports, videos", group=OUTPUTS.path
)

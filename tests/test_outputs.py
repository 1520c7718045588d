"""The outputs step on a tiny trained scene posed by SfM (an arbitrary frame): every file is in one world frame
whose +Z is the procedural world's up (within 2°), states it, loads in the tools that read it and gives back
the global poses; the mesh lies on the world's surface and the videos are upright (ground truth rendered from
the same cameras)."""

from __future__ import annotations

import json
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import open3d as o3d
import pycolmap
import pytest
import trimesh
from conftest import tiny_config
from plyfile import PlyData
from test_media import assert_web_video

from flows.pipeline import execute
from tasks.output_scene import posed_frames
from tasks.outputs import output_frame
from wonderverse.camera import Sim3, camera_centers
from wonderverse.config import RunConfig
from wonderverse.exports import read_camera_path, read_colmap_poses, read_nerfstudio_poses
from wonderverse.gravity import angle_deg
from wonderverse.mesh import MeshParams
from wonderverse.store import SceneStore
from wonderverse.video import make_video_model

pytestmark = pytest.mark.e2e  # a whole scene through the pipeline


VIDEO = {"width": 160, "height": 112, "frames_per_segment": 10}
FRAMES = 12
UP = np.array([0.0, 0.0, 1.0])


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    cfg = tiny_config(video=VIDEO, extensions={"rounds": 0})
    overrides = {
        # a 60° turn: the cameras' headings spread enough for SfM's frame to give its up from their x axes
        "plan": {"initial_move": "up 0, right 60, forward 1"},
        "poses": {"source": "sfm"},
        "splats": {"max_side_px": 112, "train": {"iterations": 150, "holdout_every": 0, "sky_map_rows": 16}},
        "outputs": {"video_frames": FRAMES},
    }
    steps = cfg.steps.model_validate(
        cfg.steps.model_dump() | {k: cfg.steps.model_dump()[k] | v for k, v in overrides.items()}
    )
    cfg = cfg.model_copy(update={"steps": steps, "execution": cfg.execution.model_copy(update={"renderer": "torch"})})
    d = tmp_path_factory.mktemp("outputs") / "scene"
    results = execute(d, cfg)
    assert results[-1].step == "outputs" and results[-1].status == "ran"
    return d


def _truth(store: SceneStore) -> tuple[np.ndarray, np.ndarray]:
    """The posed frames' true W2C (the procedural world's, +z up, metres) and their W2C in the outputs' frame."""
    from tasks.segments import attempt_path
    from wonderverse.schema import SFM

    segs, index, poses = store.meta(SFM.path).segments, store.array(SFM.frame_index), store.array(SFM.poses)
    ok = np.isfinite(poses).all(axis=(1, 2))
    gt = {a: store.array(attempt_path(store, segs[a]).gt.poses) for a in np.unique(index[:, 0])}
    true = np.stack([gt[a][i] for (a, i), keep in zip(index, ok, strict=True) if keep])
    return true, output_frame(store).transform_w2c(poses[ok])


def _to_truth(store: SceneStore) -> Sim3:
    """The similarity from the outputs' frame to the true world, from the cameras alone: the rotation that
    takes their orientations onto the true ones (chordal mean), the scale of their spread, their centroids.
    (The path is nearly straight, so a Sim(3) of the camera centres alone would leave a rotation free.)"""
    true, ours = _truth(store)
    M = np.einsum("nji,njk->ik", true[:, :3, :3], ours[:, :3, :3])
    U, _, Vt = np.linalg.svd(M)
    R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt  # R_cam_ours = R_cam_true R
    c_true, c_ours = camera_centers(true), camera_centers(ours)
    s = np.linalg.norm(c_true - c_true.mean(0)) / np.linalg.norm(c_ours - c_ours.mean(0))
    return Sim3(s, R, c_true.mean(0), center=c_ours.mean(0))


def _world(store: SceneStore):
    return make_video_model(RunConfig.model_validate(store.root.attrs["config"]).scene.video_source)


def test_files_are_listed_and_a_rerun_is_cached(scene: Path) -> None:
    store = SceneStore.open(scene)
    listed = {f.path: f.description for f in store.meta("outputs").files}
    expected = {"splats.ply", "splats.spz", "splats.glb", "points.ply", "mesh.ply", "mesh.glb", "colmap", "nerfstudio"}
    assert set(listed) == expected | {"camera_path.json", "novel_path.json", "flythrough.mp4", "novel.mp4"}
    assert all((scene / f).exists() for f in listed)
    assert "+Z up" in listed["splats.ply"] and "SfM units" in listed["mesh.ply"]
    # novel views of 160x112 are under NIQE's two 96-px blocks per side, and no CLIP/Q-Align weights are given
    assert store.meta("outputs").quality.model_dump() == {"niqe": None, "clip_s": None, "q_align": None}
    again = RunConfig.model_validate(store.root.attrs["config"])
    assert [r.status for r in execute(scene, again)] == ["cached"] * 7
    # how many views render at once changes the speed, not the files: still cached
    faster = again.model_copy(update={"execution": again.execution.model_copy(update={"render_workers": 3})})
    assert [r.status for r in execute(scene, faster)] == ["cached"] * 7


def test_the_priors_mark_most_of_the_true_sky_and_say_how_much(scene: Path) -> None:
    """The priors step's sky rule against the procedural truth of each accepted attempt: most true sky pixels
    become +inf, few true surfaces do, and `sky_share` is what was marked."""
    from tasks.segments import attempt_path
    from wonderverse.schema import PRIORS_SEGMENT

    store = SceneStore.open(scene)
    for seg in store.meta("sfm").segments:
        truth = np.isinf(store.array(attempt_path(store, seg).gt.depth))
        depth = store.array(PRIORS_SEGMENT.at(seg=seg).depth)
        marked = np.isinf(depth)
        assert truth.mean() > 0.02, seg  # the scene shows sky
        # seen (s000): 86 % of the sky, 1.1 % of the surfaces (far terrain no SfM point reaches)
        assert marked[truth].mean() > 0.5 and marked[~truth].mean() < 0.02, seg
        assert store.meta(PRIORS_SEGMENT.at(seg=seg)).sky_share == pytest.approx(marked.mean(), abs=1e-4)


def test_the_sky_map_is_stored_with_the_splats(scene: Path) -> None:
    from tasks.splats import stored_sky

    store = SceneStore.open(scene)
    sky = stored_sky(store)
    assert sky.shape == (16, 32, 3) and sky.dtype == np.float32 and sky.min() >= 0.0 and sky.max() <= 1.0
    assert sky.reshape(-1, 3).std(axis=0).max() > 0.01  # more than one colour was learnt
    metrics = store.meta("splats").metrics
    np.testing.assert_allclose(metrics.background_rgb, sky.reshape(-1, 3).mean(axis=0), rtol=1e-5)


def test_the_exported_splats_are_pruned_and_the_same_in_every_format(scene: Path) -> None:
    from wonderverse.splats.ply import read_ply
    from wonderverse.splats.web import read_splat_glb, read_spz

    pruned = SceneStore.open(scene).meta("outputs").pruned
    assert pruned.before == len(SceneStore.open(scene).array("splats/means"))
    assert pruned.after == pruned.before - sum(pruned.removed.values()) > 0
    ply, spz, glb = read_ply(scene / "splats.ply"), read_spz(scene / "splats.spz"), read_splat_glb(scene / "splats.glb")
    assert len(ply["means"]) == len(spz["means"]) == len(glb["means"]) == pruned.after
    lo, hi = ply["means"].min(0), ply["means"].max(0)
    assert np.allclose([lo, hi], [pruned.bounds_after.min, pruned.bounds_after.max], atol=1e-3)
    from flows.report import write_report

    text = write_report(scene).read_text()  # the counts and bounds are in the report
    assert f"{pruned.after} of {pruned.before}" in text
    assert f"{hi[0] - lo[0]:.3g} × {hi[1] - lo[1]:.3g} × {hi[2] - lo[2]:.3g}" in text


def test_the_output_frame_is_upright_and_every_file_says_so(scene: Path) -> None:
    store = SceneStore.open(scene)
    frame = store.meta("outputs").frame
    camera = (frame.model_extra or {})["camera"]  # the evidence the frame was estimated from
    up_err = angle_deg(_to_truth(store).R @ UP, UP)
    assert up_err < 2.0, (up_err, frame.source, camera)
    assert frame.source == "cameras" and camera["mode"] == "x axes"
    world = frame.world
    assert "+Z up" in world and "SfM units" in world and "origin" in world
    # SfM's own frame is far from upright here: the outputs had something to correct
    assert angle_deg(np.asarray(frame.up_in_sfm), UP) > 10.0
    for name in ("points.ply", "mesh.ply", "splats.ply", "nerfstudio/points.ply"):
        assert any(world in c for c in PlyData.read(str(scene / name)).comments), name
    for name in ("camera_path.json", "novel_path.json"):
        assert json.loads((scene / name).read_text())["world"] == world
    assert world in json.loads((scene / "nerfstudio" / "transforms.json").read_text())["wonderverse"]["world"]
    assert world in (scene / "colmap" / "README.txt").read_text()


def test_colmap_dataset_is_what_trainers_read(scene: Path) -> None:
    store = SceneStore.open(scene)
    frames, w2c_sfm, names = posed_frames(store)
    w2c = output_frame(store).transform_w2c(w2c_sfm)
    model = scene / "colmap" / "sparse" / "0"
    rec = pycolmap.Reconstruction(str(model))
    assert [rec.images[i].name for i in sorted(rec.images)] == [f"{n}.png" for n in names]
    for i in sorted(rec.images):
        assert (scene / "colmap" / "images" / rec.images[i].name).is_file()
    np.testing.assert_array_equal(iio.imread(scene / "colmap" / "images" / f"{names[0]}.png"), frames[0])
    np.testing.assert_allclose(read_colmap_poses(model).w2c, w2c, atol=1e-9)
    # the global SfM's points, with tracks of measured keypoints that agree with the exported poses
    assert store.meta("outputs").colmap["tracks_from"].startswith("the global SfM")
    assert len(rec.points3D) > 50 and all(p.track.length() >= 2 for p in rec.points3D.values())
    errors = []
    for p in rec.points3D.values():
        for el in p.track.elements:
            im = rec.images[el.image_id]
            errors.append(
                np.linalg.norm(im.camera.img_from_cam(im.cam_from_world() * p.xyz) - im.points2D[el.point2D_idx].xy)
            )
    assert np.median(errors) < 1.0 and np.mean(errors) < 2.0, (np.median(errors), np.mean(errors))


def test_nerfstudio_dataset_and_camera_paths(scene: Path) -> None:
    store = SceneStore.open(scene)
    frames, w2c_sfm, _ = posed_frames(store)
    w2c = output_frame(store).transform_w2c(w2c_sfm)
    ns = scene / "nerfstudio"
    meta = json.loads((ns / "transforms.json").read_text())
    np.testing.assert_allclose(read_nerfstudio_poses(ns / "transforms.json").w2c, w2c, atol=1e-9)
    assert meta["orientation_override"] == "none" and (ns / meta["ply_file_path"]).is_file()
    scale = meta["wonderverse"]["scale_from_world"]
    first = meta["frames"][0]
    np.testing.assert_array_equal(iio.imread(ns / first["file_path"]), frames[0])
    depth = iio.imread(ns / first["depth_file_path"])
    assert depth.dtype == np.uint16 and np.count_nonzero(depth) > 0.3 * depth.size
    # the depth PNG is the splats' depth at that camera: where the mesh (another export, fused from the splats'
    # depth) is the nearest surface at a pixel, the PNG holds about its depth
    mesh = trimesh.load(scene / "mesh.ply", force="mesh")
    K = read_nerfstudio_poses(ns / "transforms.json").K[0]
    v_cam = mesh.vertices @ w2c[0, :3, :3].T + w2c[0, :3, 3]
    v_cam = v_cam[v_cam[:, 2] > 1e-6]
    col = np.floor(v_cam[:, 0] / v_cam[:, 2] * K[0, 0] + K[0, 2]).astype(int)
    row = np.floor(v_cam[:, 1] / v_cam[:, 2] * K[1, 1] + K[1, 2]).astype(int)
    inside = (col >= 0) & (col < depth.shape[1]) & (row >= 0) & (row < depth.shape[0])
    col, row, z = col[inside], row[inside], v_cam[inside, 2]
    nearest = np.full(depth.shape, np.inf)
    np.minimum.at(nearest, (row, col), z)
    front = (z <= nearest[row, col] * 1.001) & (depth[row, col] > 0)
    assert front.sum() > 200
    ratio = depth[row[front], col[front]] / 1000 / scale / z[front]
    assert np.median(ratio) == pytest.approx(1.0, abs=0.15), np.median(ratio)
    for name, ours in (("flythrough", "camera_path.json"), ("novel", "novel_path.json")):
        path = json.loads((ns / "camera_paths" / f"{name}.json").read_text())
        assert len(path["camera_path"]) == FRAMES and path["seconds"] > 0
        assert {"render_height", "render_width", "camera_type", "keyframes"} <= set(path)
        mine, fps = read_camera_path(scene / ours)
        assert len(mine.w2c) == FRAMES and fps == store.root.attrs["config"]["steps"]["outputs"]["video_fps"]
        centre, s = np.asarray(path["wonderverse"]["centre"]), path["wonderverse"]["scale"]
        c2w = np.asarray(path["camera_path"][0]["camera_to_world"]).reshape(4, 4)
        np.testing.assert_allclose(c2w[:3, 3] / s + centre, camera_centers(mine.w2c[:1])[0], atol=1e-9)


def test_point_cloud_mesh_and_splats_lie_on_the_world(scene: Path) -> None:
    pcd = o3d.io.read_point_cloud(str(scene / "points.ply"))
    assert len(pcd.points) > 20 and pcd.has_colors() and pcd.has_normals()
    mesh = o3d.io.read_triangle_mesh(str(scene / "mesh.ply"))
    assert len(mesh.triangles) > 100 and mesh.has_vertex_normals()
    glb = trimesh.load(scene / "mesh.glb", force="mesh")
    assert len(glb.faces) == len(mesh.triangles)
    np.testing.assert_allclose(np.sort(glb.vertices[:, 1]), np.sort(np.asarray(mesh.vertices)[:, 2]), atol=1e-4)
    store = SceneStore.open(scene)
    splats = PlyData.read(str(scene / "splats.ply"))["vertex"]  # the INRIA 3DGS layout, every Gaussian kept
    names = [p.name for p in splats.properties]
    assert splats.count == store.meta("outputs").pruned.after
    assert names[:9] == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    assert names[-8:] == ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    to_truth = _to_truth(store)
    world = _world(store).world
    extent = store.meta("outputs").mesh.extent * to_truth.s
    near_reach = MeshParams().max_depth_frac * extent  # the scene keeps the default
    centres = camera_centers(_truth(store)[0])
    for name, xyz in (
        ("mesh", np.asarray(mesh.vertices)),
        ("splats", np.stack([PlyData.read(str(scene / "splats.ply"))["vertex"][c] for c in "xyz"], -1)),
    ):
        points = to_truth.apply(xyz)
        dist = world.scene.compute_distance(o3d.core.Tensor(points.astype(np.float32))).numpy()
        near = np.linalg.norm(points[:, None] - centres[None], axis=-1).min(axis=1) <= near_reach
        # 150 iterations at 112 px: a rough surface, but in the right place (a wrong frame or scale is metres off);
        # judged within the fine volume's reach: beyond it the mesh goes on (the coarse far volume), coarsely
        assert near.sum() > 20 and np.median(dist[near]) < 0.08 * extent, (name, np.median(dist[near]), extent)
        if name == "mesh":
            assert not near.all()  # the far terrain is meshed too


def test_gltf_validator_passes_the_mesh(scene: Path) -> None:
    from test_mesh import _validate_gltf

    issues = _validate_gltf(scene / "mesh.glb")
    assert issues["numErrors"] == 0 and issues["numWarnings"] == 0, issues["messages"]


def test_videos_are_upright_web_ready_and_show_the_world(scene: Path) -> None:
    store = SceneStore.open(scene)
    to_truth = _to_truth(store)
    video = _world(store)
    for name, path in (("flythrough.mp4", "camera_path.json"), ("novel.mp4", "novel_path.json")):
        assert_web_video(scene / name)
        frames = np.stack(list(iio.imiter(scene / name)))
        assert frames.shape[0] == FRAMES and frames.std() > 5, name  # something was drawn, not a flat colour
        cams, _ = read_camera_path(scene / path)
        true_w2c = to_truth.transform_w2c(cams.w2c)
        sky_rows, agree, flipped = [], [], []
        for f, pose in zip(frames, true_w2c, strict=True):
            rgb, depth, _ = video.render(pose)  # the truth from the same camera (the video's size: 160x112)
            h = depth.shape[0]
            sky_rows.append(np.nonzero(~np.isfinite(depth))[0])
            lum, true_lum = f[:h, : depth.shape[1]].mean(-1), rgb.mean(-1)
            agree.append(np.corrcoef(lum.ravel(), true_lum.ravel())[0, 1])
            flipped.append(np.corrcoef(lum[::-1].ravel(), true_lum.ravel())[0, 1])
        rows = np.concatenate(sky_rows)
        assert rows.size > 0.05 * frames[:, :h].size / 3, name  # the views see sky
        assert np.mean(rows < h / 2) > 0.9, (name, np.mean(rows < h / 2))  # ... in the upper half
        assert np.mean(agree) > 0.5 and np.mean(agree) > np.mean(flipped) + 0.3, (name, agree, flipped)

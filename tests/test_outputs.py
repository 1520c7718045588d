"""The outputs step on a tiny trained scene: every file exists, loads in the tools that read it, and
gives back the global poses; the mesh lies on the procedural world's surface (ground truth)."""

from __future__ import annotations

from pathlib import Path

import imageio.v3 as iio
import numpy as np
import open3d as o3d
import pytest
import trimesh
from conftest import tiny_config

from flows.pipeline import execute
from tasks.outputs import posed_frames
from wonderverse.exports import read_camera_path, read_colmap_poses, read_nerfstudio_poses
from wonderverse.store import SceneStore
from wonderverse.video import make_video_model

VIDEO = {"width": 160, "height": 112, "frames_per_segment": 10}
FRAMES = 12


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    cfg = tiny_config(video=VIDEO, extensions={"rounds": 0})
    overrides = {
        # the planned path as the world frame, so the mesh can be compared with the world's own surface
        "poses": {"source": "conditioning"},
        "splats": {"max_side_px": 112, "train": {"iterations": 150, "holdout_every": 0}},
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


def test_files_are_listed_and_a_rerun_is_cached(scene: Path) -> None:
    store = SceneStore.open(scene)
    listed = {f["path"] for f in store.attrs("outputs")["files"]}
    expected = {"points.ply", "mesh.ply", "mesh.glb", "colmap", "nerfstudio", "camera_path.json"}
    assert listed == expected | {"flythrough.mp4", "novel.mp4"}
    assert all((scene / f).exists() for f in listed)
    # novel views of 160x112 are under NIQE's two 96-px blocks per side, and no CLIP/Q-Align weights are given
    assert store.attrs("outputs")["quality"] == {"niqe": None, "clip_s": None, "q_align": None}
    cfg_dump = store.root.attrs["config"]
    from wonderverse.config import RunConfig

    again = RunConfig.model_validate(cfg_dump)
    assert [r.status for r in execute(scene, again)] == ["cached"] * 7
    # how many views render at once changes the speed, not the files: still cached
    faster = again.model_copy(update={"execution": again.execution.model_copy(update={"render_workers": 3})})
    assert [r.status for r in execute(scene, faster)] == ["cached"] * 7


def test_exports_give_back_the_global_poses(scene: Path) -> None:
    store = SceneStore.open(scene)
    frames, w2c, names = posed_frames(store)
    colmap = read_colmap_poses(scene / "colmap")
    assert colmap.names == names
    np.testing.assert_allclose(colmap.w2c, w2c, atol=1e-9)
    ns = read_nerfstudio_poses(scene / "nerfstudio" / "transforms.json")
    np.testing.assert_allclose(ns.w2c, w2c, atol=1e-9)
    first = iio.imread(scene / "nerfstudio" / "images" / f"{names[0]}.png")
    np.testing.assert_array_equal(first, frames[0])
    path, fps = read_camera_path(scene / "camera_path.json")
    assert (
        len(path.w2c) == FRAMES and fps == SceneStore.open(scene).root.attrs["config"]["steps"]["outputs"]["video_fps"]
    )


def test_videos_have_the_requested_frames(scene: Path) -> None:
    for name in ("flythrough.mp4", "novel.mp4"):
        video = np.stack(list(iio.imiter(scene / name)))
        assert video.shape[0] == FRAMES and video.std() > 5, name  # something was drawn, not a flat colour


def test_point_cloud_and_mesh_load_and_lie_on_the_world(scene: Path) -> None:
    pcd = o3d.io.read_point_cloud(str(scene / "points.ply"))
    assert len(pcd.points) > 20 and pcd.has_colors()
    assert len(trimesh.load(scene / "points.ply").vertices) == len(pcd.points)
    mesh = o3d.io.read_triangle_mesh(str(scene / "mesh.ply"))
    assert len(mesh.triangles) > 100
    glb = trimesh.load(scene / "mesh.glb", force="mesh")
    assert len(glb.faces) == len(mesh.triangles)
    # ground truth: distance of the mesh vertices to the procedural world's surface
    store = SceneStore.open(scene)
    from wonderverse.config import RunConfig

    world = make_video_model(RunConfig.model_validate(store.root.attrs["config"]).scene.video_source).world
    extent = store.attrs("outputs")["mesh"]["extent"]
    v = np.asarray(mesh.vertices, np.float32)
    dist = world.scene.compute_distance(o3d.core.Tensor(v)).numpy()
    # 150 iterations at 112 px: a rough surface, but in the right place (a wrong frame or scale is metres off)
    assert np.median(dist) < 0.08 * extent, (np.median(dist), extent)

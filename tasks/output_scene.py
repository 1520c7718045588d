"""What the outputs' products are made from, read once per run: the trained splats, the posed stitched frames, the
output world frame (the `frame` product's record) and splat renders, made when a product first needs them."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from tasks.progress import callback
from tasks.segments import attempt_path, posed_stitched
from tasks.splats import stored_sky
from wonderverse.config import ExecutionParams, OutputsParams
from wonderverse.products import Written
from wonderverse.schema import SFM, SPLATS
from wonderverse.schema.attrs import OutputProductAttrs
from wonderverse.store import SceneStore

if TYPE_CHECKING:
    from wonderverse.camera import Sim3
    from wonderverse.mesh import PointCloud


@dataclass(frozen=True)
class Made:
    """What a product made: the files it wrote beside the store, its figures (fields of `OutputProductAttrs`) and
    the arrays its group keeps."""

    files: list[Written] = field(default_factory=list)
    record: dict[str, Any] = field(default_factory=dict)
    arrays: dict[str, np.ndarray] = field(default_factory=dict)


def posed_frames(store: SceneStore) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Stitched frames that have a global pose: frames (N,H,W,3) uint8, W2C (N,4,4) in the `sfm/` frame,
    names `s000_0007`."""
    rows, w2c, names = posed_stitched(store, {"frames": lambda seg: attempt_path(store, seg).frames})
    return rows["frames"], w2c, names


@dataclass
class OutputScene:
    """The splats (`arrays` in the training frame, `norm_sfm` mapping it to the `sfm/` frame, the `background`),
    the posed frames (`frames`, `w2c_sfm`, `names`, K at `size` = (width, height)), the render size and K of every
    product's renders (`render_size`, `Kr`), and the records of the products made so far (`records`)."""

    store: SceneStore
    p: OutputsParams
    execution: ExecutionParams
    arrays: dict[str, np.ndarray]
    norm_sfm: Sim3
    background: np.ndarray | None
    frames: np.ndarray
    w2c_sfm: np.ndarray
    names: list[str]
    K: np.ndarray
    render_size: tuple[int, int]
    Kr: np.ndarray
    prompt: str = ""  # what the novel views are scored against (CLIP-S)
    settings: dict[str, str] = field(default_factory=dict)  # product -> digest of the settings it reads
    records: dict[str, OutputProductAttrs] = field(default_factory=dict)
    video_frames: dict[str, np.ndarray] = field(default_factory=dict)  # videos rendered in this run, by name
    _rendered: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict, repr=False)  # camera id -> view

    @classmethod
    def load(cls, store: SceneStore, p: OutputsParams, execution: ExecutionParams, prompt: str) -> OutputScene:
        from wonderverse.camera import fit_intrinsics
        from wonderverse.splats.model import GaussianModel, normalization_from_dict

        frames, w2c_sfm, names = posed_frames(store)
        K = store.array(SFM.K)
        height, width = frames.shape[1:3]
        w, h, Kr = fit_intrinsics(width, height, K, p.render_max_side_px)
        norm = normalization_from_dict(store.meta(SPLATS.path).normalization)
        arrays = {name: store.array(getattr(SPLATS, name)) for name in GaussianModel.PARAM_NAMES}
        sky = stored_sky(store)
        return cls(store, p, execution, arrays, norm, sky, frames, w2c_sfm, names, K, (w, h), Kr, prompt=prompt)

    @property
    def out(self) -> Path:
        """The folder the files are written to: the scene's, beside the store."""
        return Path(self.store.scene_dir)

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) of the frames."""
        return self.frames.shape[2], self.frames.shape[1]

    @property
    def to_world(self) -> Sim3:
        """The rigid transform from the `sfm/` frame to the output world frame (the `frame` product's)."""
        from wonderverse.camera import Sim3

        return Sim3.from_dict(self.records["frame"].frame.world_from_sfm)

    @property
    def world(self) -> str:
        """The output world frame in words (what every file states)."""
        return self.records["frame"].frame.world

    @property
    def norm(self) -> Sim3:
        """Output world -> the splats' training frame."""
        return self.norm_sfm.compose(self.to_world.inverse())

    @property
    def w2c(self) -> np.ndarray:
        """The training cameras W2C in the output world frame."""
        return self.to_world.transform_w2c(self.w2c_sfm)

    def render(self, poses: np.ndarray, norm: Sim3, unit: str) -> list[Any]:
        """Splat renders (`RenderedView`s) from W2C `poses` of the frame `norm` maps to training, at the render
        size; `unit` names them in the progress line."""
        from wonderverse.splats.renderer import make_renderer
        from wonderverse.splats.views import render_views

        w, h = self.render_size
        workers = self.execution.render_workers or _usable_cores()
        renderer = make_renderer(self.execution.renderer)
        views = render_views(
            self.arrays, norm, poses, self.Kr, w, h, renderer, self.background, workers=workers, progress=callback(unit)
        )
        return list(views)

    def views(self, w2c_sfm: np.ndarray, unit: str) -> list[tuple[np.ndarray, np.ndarray]]:
        """Renders from cameras W2C (N,4,4) of the `sfm/` frame, each once per run: colour as uint8 and depth (camera
        z in `sfm/` units, +inf where nothing is)."""
        from wonderverse.products.mesh import camera_ids

        ids = camera_ids(w2c_sfm)
        todo = [k for k, i in enumerate(ids) if i not in self._rendered]
        if todo:
            rendered = self.render(w2c_sfm[todo], self.norm_sfm, unit)
            for k, v in zip(todo, rendered, strict=True):
                self._rendered[ids[k]] = (np.round(v.rgb * 255).astype(np.uint8), v.depth)
        return [self._rendered[i] for i in ids]

    @cached_property
    def frame_digests(self) -> dict[str, str]:
        """Per frame name, a digest of its pixels and its pose (`sfm/` frame): what a file written of it holds."""
        import hashlib

        return {
            name: hashlib.sha1(frame.tobytes() + np.ascontiguousarray(pose).tobytes()).hexdigest()[:16]
            for name, frame, pose in zip(self.names, self.frames, self.w2c_sfm, strict=True)
        }

    @cached_property
    def training_depths(self) -> list[np.ndarray]:
        """Rendered depth (camera z, at `Kr`) from every training camera (those the mesh rendered are reused)."""
        return [d for _, d in self.views(self.w2c_sfm, "views rendered for depth")]

    @cached_property
    def cloud(self) -> PointCloud:
        """The opaque Gaussians' centres in the output frame (points.ply and the datasets' points)."""
        from wonderverse.camera import camera_centers
        from wonderverse.products.splat_files import point_cloud

        return point_cloud(self.arrays, self.norm, self.p.mesh.points_min_opacity, camera_centers(self.w2c))


def _usable_cores() -> int:
    """The cores this process may run on (its CPU affinity where the OS has one), not the host's count."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1

"""The scene store's schema: every group and array a scene holds, declared once.

A `Group` is a path template (`segments/{seg}/attempts/{attempt}`) with its arrays and the attributes it
carries; an `Array` names its dtype, its shape (names for sizes that vary, numbers for fixed ones) and its
chunking. Code reaches the store through these declarations only, so no group path is spelled anywhere else:

    SFM.poses                                   -> "sfm/poses"          (an ArrayPath: a str)
    ATTEMPT.at(seg="s001", attempt=2).frames    -> "segments/s001/attempts/2/frames"
    store.array(SFM.poses); store.meta(SEGMENT.at(seg=seg)).role; write_array(group, ATTEMPT.frames, frames)

`GroupPath` and `ArrayPath` are `str`s, so every `SceneStore` method takes them as they are. A group's attributes
are a pydantic model (`wonderverse.schema.attrs`): validated when written, typed when read
(`store.meta(SFM.path).k_source`). Every group names the one step that writes it (`writer`), and the steps that may
write it on that step's behalf (`shared`: a guided flow's generate_segments checks segments and computes their raw
depth under the check's and the priors' own keys); the store refuses any other writer while a step runs.

Adding a group: declare it here (doc: what it holds; its writer; its attributes' model), then use it.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from string import Formatter
from typing import Any, Literal

import numpy as np

from wonderverse.schema import attrs as A

Chunking = Literal["frame", "whole", "blob"]
BLOB_CHUNK = 1 << 24  # bytes per chunk of an opaque byte array (a COLMAP database, model files)


@dataclass(frozen=True)
class Array:
    """dtype; shape: per axis a size name ("T" frames, "H", "W", "N" rows) or a fixed size; chunking: one
    leading index per chunk ("frame": per-frame access), the whole array in one chunk ("whole"), or byte
    blocks of BLOB_CHUNK ("blob")."""

    dtype: str
    shape: tuple[str | int, ...]
    chunks: Chunking = "frame"
    doc: str = ""

    def chunk_shape(self, shape: tuple[int, ...]) -> tuple[int, ...]:
        if self.chunks == "blob":
            return (max(1, min(shape[0], BLOB_CHUNK)),)
        if self.chunks == "whole" or len(shape) < 3:
            return tuple(max(1, s) for s in shape) or (1,)
        return (1, *shape[1:])

    def check(self, name: str, data: np.ndarray) -> np.ndarray:
        """`data` as this array's dtype; ValueError when its rank or a fixed size differs."""
        data = np.asarray(data)
        if data.ndim != len(self.shape) or any(
            isinstance(s, int) and s != n for s, n in zip(self.shape, data.shape, strict=True)
        ):
            raise ValueError(f"array {name}: shape {data.shape} does not match the schema's {self.shape}")
        if data.dtype != np.dtype(self.dtype) and not np.can_cast(data.dtype, self.dtype, "same_kind"):
            raise ValueError(f"array {name}: dtype {data.dtype} cannot be stored as {self.dtype}")
        return data.astype(self.dtype, copy=False)


class ArrayPath(str):
    """The path of one array in the store, with its declaration (`spec`)."""

    spec: Array

    def __new__(cls, path: str, spec: Array) -> ArrayPath:
        obj = super().__new__(cls, path)
        obj.spec = spec
        return obj


class GroupPath(str):
    """The path of one group in the store; its declared arrays and sub-groups are attributes."""

    group: Group

    def __new__(cls, path: str, group: Group) -> GroupPath:
        obj = super().__new__(cls, path)
        obj.group = group
        return obj

    def __getattr__(self, name: str) -> Any:
        """A declared array (ATTEMPT.at(...).frames) or sub-group (ATTEMPT.at(...).gt) of this group."""
        if name.startswith("_"):
            raise AttributeError(name)
        if name in self.group.arrays:
            return ArrayPath(f"{self}/{name}", self.group.arrays[name])
        child = _CHILDREN.get((self.group.template, name))
        if child is None:
            raise AttributeError(f"group {self.group.template!r} declares no array or sub-group {name!r}")
        return GroupPath(f"{self}/{name}", child)

    def relative_to(self, parent: GroupPath) -> str:
        """This path below `parent` (to create it inside a staged copy of the parent)."""
        if not self.startswith(f"{parent}/"):
            raise ValueError(f"{self} is not below {parent}")
        return self[len(parent) + 1 :]

    def array(self, name: str) -> ArrayPath:
        """An array by name (for groups whose arrays are named at run time, declared with `any_arrays`)."""
        spec = self.group.arrays.get(name) or self.group.any_arrays
        if spec is None:
            raise KeyError(f"group {self.group.template!r} declares no array {name!r}")
        return ArrayPath(f"{self}/{name}", spec)


@dataclass(frozen=True)
class Group:
    """A group of the store: path template, what it is for, the step that writes it (and those that share it), its
    arrays and the model of its attributes."""

    template: str
    doc: str
    writer: str
    arrays: Mapping[str, Array] = field(default_factory=dict)
    attrs: type[A.Attrs] = A.NoAttrs
    shared: tuple[str, ...] = ()  # steps that write it too, on the writer's behalf (under the writer's keys)
    any_arrays: Array | None = None  # arrays named at run time all follow this declaration

    def may_write(self, step: str) -> bool:
        """Whether `step` may commit this group."""
        return step == self.writer or step in self.shared

    @property
    def ids(self) -> tuple[str, ...]:
        return tuple(f for _, f, _, _ in Formatter().parse(self.template) if f)

    def at(self, **ids: Any) -> GroupPath:
        """The concrete path, e.g. ATTEMPT.at(seg="s000", attempt=0)."""
        if set(ids) != set(self.ids):
            raise KeyError(f"group {self.template!r} needs {self.ids}, got {tuple(ids)}")
        return GroupPath(self.template.format(**ids), self)

    def __getattr__(self, name: str) -> Any:
        """An array or sub-group of a group without ids (SFM.poses, SFM.colmap_model); a templated group
        needs `at` first."""
        if name.startswith("_"):
            raise AttributeError(name)
        if self.ids:
            raise AttributeError(f"group {self.template!r} needs ids {self.ids}: use .at(...).{name}")
        return getattr(GroupPath(self.template, self), name)

    @property
    def name(self) -> str:
        """The last component of the path (to create the group inside a staged parent)."""
        return self.template.rsplit("/", 1)[-1]

    @property
    def path(self) -> GroupPath:
        """The path of a group without ids."""
        return self.at()


def _frames(doc: str) -> Array:
    return Array("uint8", ("T", "H", "W", 3), "frame", doc)


POSES = Array("float64", ("T", 4, 4), "whole", "world-to-camera 4x4, OpenCV axes; NaN where unknown")
K = Array("float64", (3, 3), "whole", "pinhole intrinsics in pixels, pixel centres at +0.5")

GT = "generate_segments"  # the guided flow's generate_segments: checks segments and computes their raw depth

ROOT = Group("", "the scene: written by the store (format, version) and the flow (spec, config)", "", attrs=A.RootAttrs)
PLAN = Group("plan", "step plan: one camera move per segment", "plan", attrs=A.PlanAttrs)
SEGMENTS = Group(
    "segments",
    "step generate_segments: the parent of every segment; complete when every planned segment is",
    "generate_segments",
    attrs=A.SegmentsAttrs,
)
SEGMENT = Group(
    "segments/{seg}",
    "one segment (s000, s001, ... in generation order): its planned path, K and attempts (attempt 0 is committed "
    "with it)",
    "generate_segments",
    arrays={
        "path": Array("float64", ("T", 4, 4), "whole", "conditioning path, W2C (NaN for user clips)"),
        "K": K,
    },
    attrs=A.SegmentAttrs,
)
ATTEMPTS = Group("segments/{seg}/attempts", "the generation attempts of a segment (0, 1, ...)", "generate_segments")
ATTEMPT = Group(
    "segments/{seg}/attempts/{attempt}",
    "one generation attempt: its frames (attempts after the first: the check's regenerations)",
    "check",
    arrays={"frames": _frames("the rendered or read frames, RGB")},
    attrs=A.AttemptAttrs,
    shared=(GT,),
)
ATTEMPT_GT = Group(
    "segments/{seg}/attempts/{attempt}/gt",
    "ground truth of a procedural attempt (never read by the pipeline's decisions); committed with its attempt",
    "check",
    arrays={
        "poses": POSES,
        "depth": Array("float32", ("T", "H", "W"), "frame", "camera z; +inf for sky"),
        "normals": Array("float16", ("T", "H", "W", 3), "frame", "camera-space unit normals"),
        "labels": Array("int16", ("T", "H", "W"), "frame", "content the user's words placed, by label id; -1 none"),
    },
    attrs=A.GroundTruthAttrs,
    shared=(GT,),
)
ATTEMPT_SFM = Group(
    "segments/{seg}/attempts/{attempt}/sfm",
    "step check: the attempt's own SfM",
    "check",
    arrays={
        "poses": POSES,
        "registered": Array("bool", ("T",), "whole"),
        "K": K,
        "points": Array("float64", ("N", 3), "whole", "sparse points"),
        "colors": Array("uint8", ("N", 3), "whole"),
    },
    attrs=A.AttemptSfmAttrs,
    shared=(GT,),
)
ATTEMPT_CHECK = Group(
    "segments/{seg}/attempts/{attempt}/check",
    "step check: the abnormal-sequence decision on the attempt",
    "check",
    attrs=A.AttemptCheckAttrs,
    shared=(GT,),
)
ACCEPTED = Group(
    "segments/{seg}/accepted",
    "step check: the attempt later steps follow (None: dropped)",
    "check",
    attrs=A.AcceptedAttrs,
    shared=(GT,),
)
SEGMENT_GEOMETRY = Group(
    "segments/{seg}/geometry",
    "guided flows (generate_segments): the accepted attempt's frames placed in the plan's world, what its "
    "extensions' guides are rendered from (wonderverse.segment_geometry); keyed by the accepted attempt and "
    "the depth settings",
    "generate_segments",
    arrays={
        "depth": Array("float32", ("T", "H", "W"), "frame", "camera z in plan units; +inf sky; NaN unregistered"),
        "poses": Array("float64", ("T", 4, 4), "whole", "W2C in the plan's world; NaN where not registered"),
        "K": K,
        "registered": Array("bool", ("T",), "whole"),
        "aligned": Array("bool", ("T",), "whole", "the frame's depth alignment to the SfM points held"),
    },
    attrs=A.GeometryAttrs,
)
CHECK = Group("check", "step check: the summary over segments", "check", attrs=A.CheckAttrs)
SFM = Group(
    "sfm",
    "step poses: one camera path for every stitched frame, in one world frame",
    "poses",
    arrays={
        "poses": POSES,
        "registered": Array("bool", ("T",), "whole"),
        "K": K,
        "frame_index": Array("int32", ("T", 2), "whole", "per stitched frame: segment number, frame in segment"),
        "points3d": Array("float64", ("N", 3), "whole", "global SfM points"),
        "colors": Array("uint8", ("N", 3), "whole"),
        "colmap_database": Array("uint8", ("N",), "blob", "COLMAP's database.db, bytes"),
    },
    attrs=A.SfmAttrs,
)
SFM_MODEL = Group(
    "sfm/colmap_model",
    "step poses: the COLMAP model files (cameras.bin, images.bin, points3D.bin) as bytes",
    "poses",
    any_arrays=Array("uint8", ("N",), "blob"),
)
PRIORS = Group(
    "priors",
    "step priors: complete when every segment's priors are (none at all when both backends are none)",
    "priors",
    attrs=A.PriorsAttrs,
)
PRIORS_SEGMENT = Group(
    "priors/{seg}",
    "step priors: a segment's depth and normal priors, depth aligned per frame to the global SfM points",
    "priors",
    arrays={
        "depth": Array("float32", ("T", "H", "W"), "frame", "aligned camera z; +inf for sky"),
        "normals": Array("float16", ("T", "H", "W", 3), "frame", "camera-space unit normals"),
        "confidence": Array("float16", ("T", "H", "W"), "frame", "the network's confidence, when it gives one"),
        "scale": Array("float64", ("T",), "whole"),
        "shift": Array("float64", ("T",), "whole"),
        "aligned": Array("bool", ("T",), "whole"),
    },
    attrs=A.PriorsSegmentAttrs,
)
PRIORS_RAW = Group(
    "priors_raw", "step priors: the depth network's raw output, kept across extensions", "priors", shared=(GT,)
)
PRIORS_RAW_SEGMENT = Group(
    "priors_raw/{seg}",
    "step priors: a segment's raw depth prediction (per attempt and model settings)",
    "priors",
    arrays={
        "depth": Array("float32", ("T", "H", "W"), "frame", "network output, affine-ambiguous"),
        "confidence": Array("float16", ("T", "H", "W"), "frame"),
    },
    attrs=A.PriorsRawAttrs,
    shared=(GT,),
)
_GAUSSIANS = {
    "means": Array("float32", ("N", 3), "whole"),
    "quats": Array("float32", ("N", 4), "whole", "wxyz"),
    "log_scales": Array("float32", ("N", 3), "whole"),
    "logit_opacities": Array("float32", ("N",), "whole"),
    "sh0": Array("float32", ("N", 1, 3), "whole"),
    "shN": Array("float32", ("N", "S", 3), "whole"),
}
SPLATS = Group(
    "splats",
    "step splats: the trained Gaussians, in the training frame (`normalization` maps it to the world)",
    "splats",
    arrays={
        **_GAUSSIANS,
        "sky_map": Array(
            "float32",
            ("R", "C", 3),
            "whole",
            "the sky's colour per direction of the training frame, latitude-longitude (wonderverse.splats.sky); "
            "only with train.sky_map_rows > 0, else the sky is metrics.background_rgb",
        ),
    },
    attrs=A.SplatsAttrs,
)
SPLATS_CHECKPOINT = Group(
    "splats_checkpoint",
    "step splats: the latest training checkpoint (removed when training completes)",
    "splats",
    arrays={"state": Array("uint8", ("N",), "blob", "the tensors end to end, as `layout` says; never a pickle")},
    attrs=A.CheckpointAttrs,
)
OUTPUTS = Group("outputs", "step outputs: the files written beside the store", "outputs", attrs=A.OutputsAttrs)
OUTPUT_PRODUCT = Group(
    "outputs/{product}",
    "step outputs: one product (frame, mesh, splat_files, points, colmap, nerfstudio, camera_paths, videos, quality), "
    "keyed by the settings it reads (tasks.outputs.PRODUCTS)",
    "outputs",
    arrays={
        "volume_near": Array(
            "uint8", ("N",), "blob", "mesh: the fine TSDF volume (Open3D .npz), what extensions fuse into"
        ),
        "volume_far": Array("uint8", ("N",), "blob", "mesh: the coarse TSDF volume (Open3D .npz)"),
    },
    attrs=A.OutputProductAttrs,
)

GROUPS: tuple[Group, ...] = (
    ROOT, PLAN, SEGMENTS, SEGMENT, ATTEMPTS, ATTEMPT, ATTEMPT_GT, ATTEMPT_SFM, ATTEMPT_CHECK, ACCEPTED,
    SEGMENT_GEOMETRY, CHECK, SFM, SFM_MODEL, PRIORS, PRIORS_SEGMENT, PRIORS_RAW, PRIORS_RAW_SEGMENT, SPLATS,
    SPLATS_CHECKPOINT, OUTPUTS, OUTPUT_PRODUCT,
)  # fmt: skip

_MATCHERS = [
    (re.compile("^" + re.sub(r"\\\{\w+\\\}", "[^/]+", re.escape(g.template)) + "$"), g) for g in GROUPS if g.template
]


def group_of(path: str) -> Group | None:
    """The declared group a concrete path belongs to (None: not declared, e.g. a test's ad-hoc group)."""
    if isinstance(path, GroupPath):
        return path.group
    if path == "":
        return ROOT
    return next((g for pattern, g in _MATCHERS if pattern.match(path)), None)


_CHILDREN: dict[tuple[str, str], Group] = {
    (g.template.rsplit("/", 1)[0], g.template.rsplit("/", 1)[1]): g for g in GROUPS if "/" in g.template
}  # (parent template, literal name) -> sub-group, for attribute access; templated names ("{seg}") need `at`

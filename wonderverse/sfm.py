"""Structure from motion on one video segment with pycolmap (CPU): SIFT, sequential matching, mapping.

`reconstruct(frames, params, prior)` returns camera poses (W2C, OpenCV axes, SfM units and an arbitrary world
frame), the sparse points, the estimated intrinsics and quality gates in words; the frames are arrays or the paths
of image files, the prior a `camera.CameraPrior` (K and whether it was given or guessed) or None. It never raises
on bad video content (textureless, a single frame, frames of different sizes, unreadable files, nothing
registered); it returns `registered` all False and says why in `problems`. Only invalid argument types or shapes
raise ValueError.

pycolmap is imported inside the functions so that importing this module (for `SfmParams`) stays cheap.
Hazards we avoid (see COLMAP-FACTS.md): loop detection is never enabled (offline it aborts the process),
incremental mapping is capped by `max_runtime_s`, "all frames registered" is not a pass on its own.

Mapper choice (measured here, 16-frame 384x256 RealEstate10K clips against their pose files, one thread):
global SfM (after `calibrate_view_graph`) reached ATE 0.2-2.0 % of path length on all 7 clips; incremental
SfM passed every gate on 0c11dbe7 and 0c9b371c yet was 9.7 % and 7.0 % off (focal 0.72 and 1.85 x W
instead of 0.47). So `auto` tries global first and falls back to incremental (relaxed initialisation) when
the global model fails the gates; that fallback gave clip 0c9b371c its model (ATE 0.6 %) when global's
weakest frame saw fewer than `min_points_per_image` points.
Without a focal prior, global's view-graph calibration also writes its focal estimate into the database,
which the incremental fallback then starts from.
A given K (`CameraPrior(K, "given")`: the procedural renderer's, or a clip whose field of view the user gave) is
held fixed by every mapper (`hold_known_intrinsics`), and `auto` then tries incremental first
(`auto_order_known_k`): incremental's errors above
were focal errors, which a held K removes. Measured on the flows benchmark's 17-frame 240x160 segments
(true focal 208 px): unheld, global refined it to 298 px on one segment (check poses 6.4 % of the path off);
held, incremental's worst rotation step was 0.03-0.62 deg off on every fault-free segment, in 4-6 s, while
held global was 4.8 deg off on the low-parallax turn (unheld, that turn needed the third mapper, 11 s).
Over a stitched video of several segments the opposite held (names in stitched order, 2 seeds each, the
flows benchmark's 3- and 4-segment scenes): refined, global was right in 4 of 4 (ATE 0.09-0.11 % of the
path); held, with incremental first, wrong in 3 of 4 (10-23 %). So the global `poses` step refines a generated
video's K (`global_poses`: `hold_known_intrinsics` off). The user's camera (a clip whose field of view the user
gave) is held there too, as in the check, so that every output uses the camera the user stated, with the global
mapper first (the poses step's `auto_order_known_k`): on the seven RealEstate10K clips with the FOV of their pose
files held, global first ended 0.10-0.56 % of the path off (median 0.37 %), incremental first 0.15-6.3 % (`0c11`),
and refining the same FOV 0.09-0.77 % (median 0.37 %). But the global mapper holding K from its start once settled
on a wrong path: two procedural clips (160x112, the exact K given) 9.7 % off, 0.41 % refined. So the global mapper
always refines, and a held camera is set back afterwards and bundle-adjusted with it fixed
(`_hold_database_camera`): that clip 0.43 %, the seven RealEstate10K clips 0.10-0.67 % (median 0.39 %). The user
may ask for refinement
(`steps.poses.refine_intrinsics`, `reconstruct --refine-intrinsics`). Reproducibility: with
`num_threads=1` and a fixed `random_seed` two runs give bit-identical poses; with 2 threads they differ slightly
(measured).

A guessed K (`CameraPrior(K, "guessed")`: a clip whose field of view nobody gave, assumed 60°) is not a
prior. Measured on the seven 16-frame 384x256 RealEstate10K clips (ATE after a Sim(3), share of the path;
their pose files give fx 182-195 px and fy/fx = 32/27: 16:9 footage resized to 3:2, non-square pixels):
the guess as a refined prior left `3c35` 2.55 % off (focal 199 px), `0f47` 1.76 % and `2f25` 1.35 %,
the same as with their true FOV on a square-pixel camera. Started from no prior at all (view-graph
calibration) `3c35` came to 0.23 %, the two others stayed at 1.3-2.0 %; a free PINHOLE camera (fx and fy
refined apart) ran fy to 63-328 px on some clips (up to 2.5 %); stretching the frames 32/27 times in x
left `0f47` at 1.6 % and once ran its focal to 554 px (11 %). What worked: SIFT once on the frames, the
keypoints' x then times the pixel aspect fy/fx of the K given (`keep_pixel_aspect`, `_stretch_x`), so
one focal is refined with the aspect held; the guess only starting the view graph's self-calibration
(`guessed_focal: calibrate`, bounded to the gate's plausible focal range: unbounded from COLMAP's own
1.2·max(W,H) start it once went to 2113 px); and SIFT keeping weaker features when the focal is not known
(`uncalibrated_peak_threshold` 0.004 for COLMAP's 0.0067; the clips give 300-600 features a frame).
With all three, seed 0: 0.07-0.83 % (median 0.38 %); over seeds 0-4 the worst clip was 0.70-1.04 %
(`0c9b`, `0f47`). Reprojection error does not pick the better focal (it was lowest for `0c9b`'s worst
seeds), so several hypotheses are not scored by it. A given FOV with the pixel aspect held (incremental
first, as above): 0.15-0.90 %. The fox capture (guessed, square pixels): 0.035 %.

Without a known focal, a few frames are looked at for parallax before anything else
(`wonderverse.parallax`, `min_parallax_deg`): a clip with too little is not mapped (`stopped`), which on
near-static CogVideoX clips takes 1.5-4 s where the three mappers took 49-234 s.

Frame pairs are those of COLMAP's sequential matcher (`features.sequential_pairs`), matched as an imported list
so that the caller's frame order counts, not the order of the image names. `reconstruct(names=...,
keep_workspace=True)` hands back the COLMAP database and kept model (`SfmWorkspace`), into which
`sfm_extend.extend_reconstruction` later registers new frames.
"""

from __future__ import annotations

import os
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from wonderverse.camera import CameraPrior
from wonderverse.features import extract_features, match_pairs, sequential_pairs
from wonderverse.progress import ProgressFn, no_progress

if TYPE_CHECKING:
    import pycolmap

# Last resort with a K prior: the incremental mapper with the camera held at the prior. On low-parallax video
# (a turn with little travel) both mappers can fail while refining the focal: at 240x160 the outdoor test
# scene's first segment gave "no 3D points" (global) and a focal of 15 px instead of 208 (incremental);
# held at the prior, the same frames gave every rotation step within 0.002 rad of the truth.
PRIOR_FOCAL = "incremental_prior_focal"
# What `progress` reports: done/total over these stages, the stage now running as the note.
STAGES = ("writing frames", "extracting features", "matching features", "mapping")

# COLMAP logs every mapper iteration through glog; keep warnings and errors only unless asked otherwise.
os.environ.setdefault("GLOG_minloglevel", "2")


class SfmParams(BaseModel):
    """Step `sfm`: feature extraction, matching, mapper choice, resource caps and quality gates.

    The relaxed incremental initialisation (`init_*`, `abs_pose_min_num_inliers`, `min_tri_angle_deg`) is
    what COLMAP-FACTS measured to solve clips that COLMAP's defaults (16°, 100, 30, 1.5°) fail on; it is used
    whenever the incremental mapper runs.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    max_image_size_px: int = Field(1024, ge=64, le=8192, description="SIFT runs on frames downscaled to this")
    max_num_features: int = Field(4096, ge=64, le=65536, description="SIFT features per frame")
    matcher_overlap: int = Field(10, ge=1, le=1000, description="each frame is matched to this many next ones")
    quadratic_overlap: bool = Field(
        True, description="match frames 2^k apart (k < overlap) instead of the next ones: COLMAP 4.2.1's quadratic mode"
    )
    mapper: Literal["incremental", "global", "auto"] = Field(
        "auto", description="auto: the mappers of `auto_order` in turn, until a model passes the gates"
    )
    init_min_tri_angle_deg: float = Field(
        4.0, gt=0, le=60, description="incremental mapper: smallest triangulation angle of the initial pair (°)"
    )
    init_min_num_inliers: int = Field(50, ge=8, description="incremental mapper: inlier matches of the initial pair")
    abs_pose_min_num_inliers: int = Field(
        15, ge=6, description="incremental mapper: 2D-3D inliers needed to register a further frame"
    )
    min_tri_angle_deg: float = Field(1.0, gt=0, le=30, description="triangulation and filtering")
    max_runtime_s: float = Field(
        120.0, gt=0, le=86400, description="cap on incremental mapping (global has no cancel hook in 4.2.1)"
    )
    auto_order: tuple[Literal["incremental", "global"], Literal["incremental", "global"]] = Field(
        ("global", "incremental"),
        description="global first: more accurate on real clips (see module notes)",
    )
    auto_order_known_k: tuple[Literal["incremental", "global"], Literal["incremental", "global"]] = Field(
        ("incremental", "global"),
        description="`auto_order` when a known K is held: incremental first (see module notes)",
    )
    prior_focal_fallback: bool = Field(
        True,
        description="with a K prior, when no mapper passes the gates, map once more holding the camera at the prior",
    )
    hold_known_intrinsics: bool = Field(
        True,
        description="with a given K (the renderer's, or a clip's given field of view; not a guess), every mapper "
        "keeps it fixed instead of refining it (the check's SfM; the global poses step sets it itself: held for the "
        "user's camera unless steps.poses.refine_intrinsics, refined for a generated video's: module notes)",
    )
    num_threads: int = Field(
        1, ge=1, le=256, description="every COLMAP stage; 1 is bit-reproducible with random_seed, >1 is not"
    )
    random_seed: int = Field(0, ge=0, lt=2**31, description="seed of every COLMAP stage's random sampling")
    camera_model: Literal["SIMPLE_PINHOLE", "PINHOLE"] = Field(
        "SIMPLE_PINHOLE", description="generated video has no lens distortion and square pixels"
    )
    min_registered_frac: float = Field(0.8, ge=0, le=1, description="gate: share of frames registered")
    min_points: int = Field(100, ge=0, description="gate: 3D points in the model")
    min_points_per_image: int = Field(10, ge=0, description="gate: 3D points seen by the weakest registered frame")
    focal_range_frac: tuple[float, float] = Field(
        (0.3, 3.0), description="gate: plausible focal as a multiple of max(W, H) (FOV ~118° .. ~19°)"
    )
    max_reproj_px: float = Field(2.0, gt=0, description="gate: mean reprojection error")
    guessed_focal: Literal["calibrate", "prior"] = Field(
        "calibrate",
        description="a guessed K's focal only starts the view graph's self-calibration (calibrate), or is a "
        "trusted prior the mappers refine (prior); see module notes",
    )
    keep_pixel_aspect: bool = Field(
        True, description="with a K prior (SIMPLE_PINHOLE), hold its fy/fx while the focal is refined"
    )
    min_parallax_deg: float | None = Field(
        3.0,
        gt=0,
        le=45,
        description="focal not known: stop before mapping when the pair of `parallax_frames` that sees most "
        "has a smaller median triangulation angle (None: never look; `wonderverse.parallax`)",
    )
    parallax_homography_px: float = Field(
        2.0, ge=0, description="... or when one homography explains 90 % of every pair's matches to this (px)"
    )
    uncalibrated_peak_threshold: float | None = Field(
        0.004,
        gt=0,
        description="SIFT peak threshold when the focal is not known (no K, or a guess): weaker features kept "
        "for the self-calibration (None: COLMAP's 0.0067, which a known focal always uses)",
    )
    parallax_frames: int = Field(9, ge=3, le=1000, description="frames looked at for parallax, spread over the clip")
    parallax_max_features: int = Field(2048, ge=64, le=65536, description="SIFT features per frame of that look")

    @model_validator(mode="after")
    def _consistent(self) -> SfmParams:
        lo, hi = self.focal_range_frac
        if not 0 < lo < hi:
            raise ValueError(f"focal_range_frac must be 0 < low < high, got {self.focal_range_frac}")
        for name in ("auto_order", "auto_order_known_k"):
            order = getattr(self, name)
            if order[0] == order[1]:
                raise ValueError(f"{name} must name two different mappers, got {order}")
        return self


@dataclass(frozen=True)
class SfmWorkspace:
    """A reconstruction's COLMAP state as bytes, so that a pipeline step can keep it in the store and a
    later extension can register new frames into it (`sfm_extend.extend_reconstruction`) instead of
    re-solving every frame.

    database: the SQLite database (camera, images, SIFT features, matches, two-view geometries).
    model: the kept model's COLMAP binary files (`Reconstruction.write`), file name -> bytes.
    Image names in both are the caller's (`reconstruct(names=...)`), so they stay stable across extensions.
    """

    database: bytes
    model: dict[str, bytes]

    @classmethod
    def pack(cls, db_path: Path, rec: Any, folder: Path) -> SfmWorkspace:
        """The database file at `db_path` (closed) and `rec` written under `folder` (created), as bytes."""
        folder.mkdir(parents=True, exist_ok=True)
        rec.write(folder)
        model = {f.name: f.read_bytes() for f in sorted(folder.iterdir()) if f.is_file()}
        return cls(database=Path(db_path).read_bytes(), model=model)

    def restore(self, folder: Path) -> tuple[Path, Path]:
        """Write the database and the model into `folder`; returns (database path, model folder)."""
        folder.mkdir(parents=True, exist_ok=True)
        db_path, model_dir = folder / "database.db", folder / "model"
        db_path.write_bytes(self.database)
        model_dir.mkdir(exist_ok=True)
        for name, data in self.model.items():
            if Path(name).name != name:
                raise ValueError(f"workspace model file names must be plain names, got {name!r}")
            (model_dir / name).write_bytes(data)
        return db_path, model_dir


@dataclass
class SfmResult:
    """One segment's reconstruction.

    poses: (T,4,4) float64 world-to-camera, OpenCV camera axes, SfM units; NaN rows where unregistered.
    registered: (T,) bool. points: (P,3) float64 world. colors: (P,3) uint8. K: (3,3) estimated
    intrinsics in pixels of the input frames (NaN if nothing was reconstructed). reproj_error_px: mean
    reprojection error (NaN if none). mapper: which mapper produced the kept model ("" if none).
    timings: seconds per stage. gates_passed: every quality gate held. problems: what failed, in words.
    workspace: the COLMAP database and kept model, only when asked for (`keep_workspace`) and a model exists
    (with a held pixel aspect a ≠ 1 its pixels are the frames' stretched a times in x, `pixel_aspect`).
    k_source: where K came from: "given" (a known K held, or a trusted prior kept as it was), "estimated"
    (refined or self-calibrated by SfM), "guessed" (a guess kept as it was); "" when nothing was mapped.
    stopped: why SfM stopped before mapping (too little parallax), in words; "" when it mapped.
    parallax: the look before mapping (`wonderverse.parallax.ParallaxReport.to_attrs`), when taken.
    pixel_aspect: the fy/fx held while mapping (1: square pixels or not held).
    """

    poses: np.ndarray
    registered: np.ndarray
    points: np.ndarray
    colors: np.ndarray
    K: np.ndarray
    reproj_error_px: float
    n_points: int
    mapper: str
    timings: dict[str, float] = field(default_factory=dict)
    gates_passed: bool = False
    problems: list[str] = field(default_factory=list)
    workspace: SfmWorkspace | None = None
    k_source: str = ""
    stopped: str = ""
    parallax: dict[str, Any] | None = None
    pixel_aspect: float = 1.0

    @property
    def n_registered(self) -> int:
        return int(self.registered.sum())


def k_record(res: SfmResult | None, prior: CameraPrior) -> dict[str, Any]:
    """Where the K a reconstruction used came from, for store attributes: {"k_source": "given" | "estimated"
    | "guessed", "K": 3x3 list (pixels), "fov_deg": its horizontal field of view over the frame width
    2·cx, "pixel_aspect": fy/fx}. The K is the estimated one, or else the prior's (also when nothing was
    mapped, or there was no reconstruction (`res` None): the K given or guessed)."""
    source = (res.k_source if res is not None else "") or prior.source
    estimated = source == "estimated" and res is not None and np.all(np.isfinite(res.K))
    K = res.K if estimated and res is not None else prior.K
    fov = float(np.degrees(2.0 * np.arctan(K[0, 2] / K[0, 0])))
    return {"k_source": source, "K": K.tolist(), "fov_deg": fov, "pixel_aspect": float(K[1, 1] / K[0, 0])}


def empty_result(n_frames: int, problems: list[str], timings: dict[str, float] | None = None) -> SfmResult:
    """A result with nothing registered, for inputs SfM cannot use."""
    return SfmResult(
        poses=np.full((n_frames, 4, 4), np.nan),
        registered=np.zeros(n_frames, dtype=bool),
        points=np.zeros((0, 3)),
        colors=np.zeros((0, 3), dtype=np.uint8),
        K=np.full((3, 3), np.nan),
        reproj_error_px=float("nan"),
        n_points=0,
        mapper="",
        timings=dict(timings or {}),
        gates_passed=False,
        problems=list(problems),
    )


def _validate_frames(frames: np.ndarray | Sequence[np.ndarray]) -> list[np.ndarray]:
    """The frames as a list of (H,W,3) uint8 arrays; ValueError for wrong types, dtypes or ranks."""
    if isinstance(frames, np.ndarray):
        if frames.dtype != np.uint8 or frames.ndim != 4 or frames.shape[-1] != 3:
            raise ValueError(f"frames must be a (T,H,W,3) uint8 array, got {frames.dtype} {frames.shape}")
        return list(frames)
    if not isinstance(frames, Sequence) or isinstance(frames, str | bytes):
        raise ValueError(f"frames must be a (T,H,W,3) uint8 array or a list of (H,W,3) arrays, got {type(frames)}")
    out = []
    for i, f in enumerate(frames):
        if not isinstance(f, np.ndarray) or f.dtype != np.uint8 or f.ndim != 3 or f.shape[-1] != 3:
            desc = f"{f.dtype} {f.shape}" if isinstance(f, np.ndarray) else type(f).__name__
            raise ValueError(f"frame {i} must be an (H,W,3) uint8 array, got {desc}")
        out.append(f)
    return out


def _validate_prior(prior: CameraPrior | None) -> CameraPrior | None:
    if prior is not None and not isinstance(prior, CameraPrior):
        raise ValueError(f"prior must be a camera.CameraPrior or None, got {type(prior).__name__}")
    return prior


def _input_problems(sizes: list[tuple[int, int]]) -> list[str]:
    """Problems that make SfM pointless before it starts; sizes are (W,H) per frame."""
    if len(sizes) == 0:
        return ["no frames given"]
    if len(sizes) == 1:
        return ["only 1 frame: SfM needs at least 2"]
    distinct = sorted(set(sizes))
    if len(distinct) > 1:
        shown = ", ".join(f"{w}x{h}" for w, h in distinct[:4])
        more = f" and {len(distinct) - 4} more" if len(distinct) > 4 else ""
        return [f"frames have {len(distinct)} different sizes ({shown}{more}); one camera needs one size"]
    w, h = distinct[0]
    if min(w, h) < 16:
        return [f"frames of {w}x{h} px are too small for SIFT"]
    return []


def _camera_params_string(K: np.ndarray, model: str) -> str:
    """COLMAP camera parameters for a prior K (COLMAP also puts pixel centres at +0.5, as we do)."""
    fx, fy, cx, cy = (float(v) for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
    values = [0.5 * (fx + fy), cx, cy] if model == "SIMPLE_PINHOLE" else [fx, fy, cx, cy]
    return ",".join(repr(v) for v in values)


def _incremental_options(params: SfmParams, hold_camera: bool = False) -> pycolmap.IncrementalPipelineOptions:
    """COLMAP's incremental pipeline with the relaxed initialisation; `hold_camera` keeps the intrinsics
    at their initial (prior) values through every bundle adjustment and pose estimate."""
    import pycolmap

    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = params.num_threads
    opts.random_seed = params.random_seed
    opts.max_runtime_seconds = int(np.ceil(params.max_runtime_s))
    # A segment is short: a model of 3+ frames is worth keeping so that we can report how much registered.
    opts.min_model_size = 3
    opts.extract_colors = True
    m = opts.mapper
    m.num_threads = params.num_threads
    m.random_seed = params.random_seed
    m.init_min_tri_angle = params.init_min_tri_angle_deg
    m.init_min_num_inliers = params.init_min_num_inliers
    m.abs_pose_min_num_inliers = params.abs_pose_min_num_inliers
    m.filter_min_tri_angle = params.min_tri_angle_deg
    opts.triangulation.min_angle = params.min_tri_angle_deg
    opts.triangulation.random_seed = params.random_seed
    if hold_camera:
        opts.ba_refine_focal_length = False
        opts.ba_refine_principal_point = False
        opts.ba_refine_extra_params = False
        m.abs_pose_refine_focal_length = False
        m.abs_pose_refine_extra_params = False
    return opts


def _global_options(params: SfmParams) -> pycolmap.GlobalPipelineOptions:
    """COLMAP's global pipeline (it refines the intrinsics; `_hold_database_camera` holds them afterwards)."""
    import pycolmap

    opts = pycolmap.GlobalPipelineOptions()
    opts.num_threads = params.num_threads
    opts.random_seed = params.random_seed
    opts.min_model_size = 3
    m = opts.mapper
    m.num_threads = params.num_threads
    m.random_seed = params.random_seed
    m.rotation_averaging.random_seed = params.random_seed
    m.global_positioning.random_seed = params.random_seed
    m.global_positioning.use_gpu = False
    m.bundle_adjustment.ceres.use_gpu = False
    m.bundle_adjustment.ceres.solver_options.num_threads = params.num_threads
    m.retriangulation.random_seed = params.random_seed
    return opts


def _largest_model(models: dict[int, Any]) -> Any | None:
    if not models:
        return None
    return max(models.values(), key=lambda r: (r.num_reg_images(), r.num_points3D()))


def _result_from_model(
    rec: Any, names: list[str], size_wh: tuple[int, int], mapper: str, params: SfmParams, aspect: float = 1.0
) -> SfmResult:
    """Poses, points and intrinsics out of a pycolmap Reconstruction, with the quality gates applied.
    size_wh: the frames' (W,H); aspect: the pixel aspect held while mapping (the model's x pixels are the
    frames' stretched `aspect` times), undone in K."""
    n = len(names)
    index = {name: i for i, name in enumerate(names)}
    poses = np.full((n, 4, 4), np.nan)
    registered = np.zeros(n, dtype=bool)
    per_image_points = []
    camera = None
    for image in rec.images.values():
        if not image.has_pose or image.name not in index:
            continue
        i = index[image.name]
        poses[i] = np.vstack([image.cam_from_world().matrix(), [0.0, 0.0, 0.0, 1.0]])
        registered[i] = True
        per_image_points.append(image.num_points3D)
        camera = image.camera
    pts = rec.points3D
    points = np.array([p.xyz for p in pts.values()], dtype=np.float64).reshape(-1, 3)
    colors = np.array([p.color for p in pts.values()], dtype=np.uint8).reshape(-1, 3)
    K = np.asarray(camera.calibration_matrix(), dtype=np.float64) if camera is not None else np.full((3, 3), np.nan)
    K = np.diag([1.0 / aspect, 1.0, 1.0]) @ K
    reproj = float(rec.compute_mean_reprojection_error()) if len(points) else float("nan")
    res = SfmResult(
        poses=poses,
        registered=registered,
        points=points,
        colors=colors,
        K=K,
        reproj_error_px=reproj,
        n_points=len(points),
        mapper=mapper,
        pixel_aspect=aspect,
    )
    res.problems = _gate_problems(res, per_image_points, size_wh, params)
    res.gates_passed = not res.problems
    return res


def _gate_problems(
    res: SfmResult, per_image_points: list[int], size_wh: tuple[int, int], params: SfmParams
) -> list[str]:
    """Every quality gate that fails, in words (COLMAP-FACTS: "all frames registered" is not a pass)."""
    n, k = len(res.registered), res.n_registered
    problems = []
    if k == 0:
        return ["COLMAP registered no frames"]
    if k < max(2, int(np.ceil(params.min_registered_frac * n))):
        problems.append(f"only {k} of {n} frames registered")
    if res.n_points < max(1, params.min_points):
        problems.append(f"{res.n_points} 3D points (need {max(1, params.min_points)})")
    weakest = min(per_image_points) if per_image_points else 0
    if weakest < params.min_points_per_image:
        problems.append(f"a registered frame sees only {weakest} 3D points (need {params.min_points_per_image})")
    max_dim = max(size_wh)
    focal = float(0.5 * (res.K[0, 0] + res.K[1, 1]))
    lo, hi = params.focal_range_frac
    if not lo * max_dim <= focal <= hi * max_dim:
        problems.append(
            f"focal {focal:.0f} px implausible for {max_dim} px frame "
            f"(expected {lo * max_dim:.0f}-{hi * max_dim:.0f} px)"
        )
    if not res.reproj_error_px <= params.max_reproj_px:
        problems.append(f"reprojection error {res.reproj_error_px:.2f} px > {params.max_reproj_px} px")
    return problems


def _feature_problems(db_path: Path, names: list[str], min_inliers: int) -> tuple[list[str], int]:
    """Why mapping had little to work with (few features, unmatched neighbours), in words, and the number
    of geometrically verified frame pairs."""
    import pycolmap

    db = pycolmap.Database.open(db_path)
    try:
        images = db.read_all_images()
        n_kp = [db.num_keypoints_for_image(im.image_id) for im in images]
        index = {im.image_id: names.index(im.name) for im in images if im.name in names}
        pair_ids, inliers = db.read_two_view_geometry_num_inliers()
    finally:
        db.close()
    verified = [pycolmap.pair_id_to_image_pair(p) for p, k in zip(pair_ids, inliers, strict=True) if k >= min_inliers]
    neighbours = {
        min(index[a], index[b]) for a, b in verified if a in index and b in index and abs(index[a] - index[b]) == 1
    }
    problems = []
    median_kp = int(np.median(n_kp)) if n_kp else 0
    if median_kp < 50:
        problems.append(f"too little texture: median {median_kp} SIFT features per frame")
    n = len(names)
    if len(neighbours) < n - 1:
        problems.append(f"only {len(neighbours)} of {n - 1} consecutive frame pairs matched geometrically")
    return problems, len(verified)


def _run_mapper(
    kind: str, db_path: Path, image_dir: Path, out_dir: Path, params: SfmParams, hold_camera: bool = False
) -> Any | None:
    import pycolmap

    pycolmap.set_random_seed(params.random_seed)
    out = out_dir / kind
    out.mkdir(parents=True, exist_ok=True)
    hold_camera = hold_camera or kind == PRIOR_FOCAL
    if kind in ("incremental", PRIOR_FOCAL):
        options = _incremental_options(params, hold_camera)
        models = pycolmap.incremental_mapping(db_path, image_dir, out, options=options)
    else:
        # Held from the start, the global mapper can settle on a wrong path (a 2-clip procedural video: 9.7 % of
        # the path off with the exact K held, 0.41 % refined); so it refines, and the camera is held afterwards.
        models = pycolmap.global_mapping(db_path, image_dir, out, options=_global_options(params))
    rec = _largest_model(models)
    if hold_camera and rec is not None and kind == "global":
        _hold_database_camera(rec, db_path, params)
    return rec


def _hold_database_camera(rec: Any, db_path: Path, params: SfmParams) -> None:
    """`rec`'s cameras set back to the database's (the K held) and bundle-adjusted with them fixed, in place."""
    import pycolmap

    db = pycolmap.Database.open(db_path)
    try:
        held = {camera.camera_id: np.array(camera.params) for camera in db.read_all_cameras()}
    finally:
        db.close()
    for camera_id, camera in rec.cameras.items():
        camera.params = held[camera_id]
    opts = pycolmap.BundleAdjustmentOptions()
    opts.refine_focal_length = opts.refine_principal_point = opts.refine_extra_params = False
    opts.ceres.solver_options.num_threads = params.num_threads
    pycolmap.bundle_adjustment(rec, opts)


def _extract(
    db_path: Path,
    image_dir: Path,
    names: list[str],
    params: SfmParams,
    reader: pycolmap.ImageReaderOptions,
    peak_threshold: float | None = None,
) -> None:
    """SIFT on `names` (files in `image_dir`) into the database, all with one camera; `peak_threshold`
    None is COLMAP's."""
    extract_features(
        db_path,
        image_dir,
        names,
        reader,
        params.max_image_size_px,
        params.max_num_features,
        params.num_threads,
        peak_threshold,
    )


def _match(db_path: Path, pairs: list[tuple[str, str]], params: SfmParams) -> pycolmap.TwoViewGeometryOptions:
    """Match and verify the given image-name pairs (never loop detection: offline it aborts the process);
    returns the verification options used."""
    return match_pairs(db_path, pairs, params.random_seed, params.num_threads)


ASPECT_TOL = 1e-3  # pixel aspects this close to 1 are square


def _pixel_aspect(K: np.ndarray | None, params: SfmParams) -> float:
    """fy/fx of a K prior to hold while mapping: 1 without a prior, for square pixels, or when not held."""
    if K is None or not params.keep_pixel_aspect or params.camera_model != "SIMPLE_PINHOLE":
        return 1.0
    aspect = float(K[1, 1] / K[0, 0])
    return 1.0 if abs(aspect - 1.0) < ASPECT_TOL else aspect


def _set_camera(db_path: Path, K: np.ndarray, width: int, model: str, has_prior: bool) -> None:
    """The database's one camera set to K (3,3, SfM pixels) and `width`; `has_prior`: COLMAP trusts its
    focal (no view-graph self-calibration; the mappers start from it)."""
    import pycolmap

    db = pycolmap.Database.open(db_path)
    try:
        for camera in db.read_all_cameras():
            camera.width = int(width)
            camera.params = np.array([float(v) for v in _camera_params_string(K, model).split(",")])
            camera.has_prior_focal_length = has_prior
            db.update_camera(camera)
    finally:
        db.close()


def _stretch_x(db_path: Path, image_dir: Path, names: list[str], aspect: float, width: int) -> None:
    """Hold a pixel aspect fy/fx = `aspect` with a one-focal camera: every keypoint's x (and its affine
    shape's first row) times `aspect`, so the features are those of frames stretched to `width` with square
    pixels; the image files are stretched too, since COLMAP takes the points' colours from them."""
    import pycolmap
    from PIL import Image

    db = pycolmap.Database.open(db_path)
    try:
        for image in db.read_all_images():
            kp = np.array(db.read_keypoints(image.image_id), dtype=np.float32)
            kp[:, 0] *= aspect
            if kp.shape[1] >= 6:
                kp[:, 2:4] *= aspect
            db.update_keypoints(image.image_id, kp)
    finally:
        db.close()
    for name in names:
        path = image_dir / name
        with Image.open(path) as im:
            stretched = im.convert("RGB").resize((width, im.height), Image.Resampling.LANCZOS)
        path.unlink()  # may be a link to the caller's file: replace it, never write through it
        stretched.save(path)


def _calibration_options(
    params: SfmParams, K_start: np.ndarray | None, size_wh: tuple[int, int], aspect: float
) -> pycolmap.ViewGraphCalibrationOptions:
    """View-graph self-calibration; started from a guess (`K_start`, SfM pixels) it may only move the focal
    within the gate's plausible range (`focal_range_frac`), else COLMAP keeps the guess."""
    import pycolmap

    calibration = pycolmap.ViewGraphCalibrationOptions()
    calibration.random_seed = params.random_seed
    if K_start is not None:
        # the gate judges 0.5 (fx + fy) of the frames; in SfM pixels that is f (1 + 1/aspect) / 2
        f0, scale = float(K_start[1, 1]), 0.5 * (1.0 + 1.0 / aspect)
        lo, hi = params.focal_range_frac
        calibration.min_focal_length_ratio = lo * max(size_wh) / scale / f0
        calibration.max_focal_length_ratio = hi * max(size_wh) / scale / f0
    return calibration


def _looks_for_parallax(prior: CameraPrior | None, params: SfmParams) -> bool:
    """The parallax look runs when the focal is not known: no K at all, or a guessed one."""
    return params.min_parallax_deg is not None and (prior is None or not prior.given)


def _parallax_stop(
    image_files: list[Path], size_wh: tuple[int, int], prior: CameraPrior | None, params: SfmParams, work: Path
) -> tuple[str, dict[str, Any]]:
    """(why there is too little parallax to map, or ""; the look's attrs) over the frames' files."""
    from wonderverse.parallax import measure_parallax

    report = measure_parallax(
        image_files,
        size_wh,
        None if prior is None else prior.K,
        params.parallax_frames,
        params.max_image_size_px,
        min(params.parallax_max_features, params.max_num_features),
        params.random_seed,
        params.num_threads,
        workdir=work / "parallax",
    )
    assert params.min_parallax_deg is not None
    return report.verdict(params.min_parallax_deg, params.parallax_homography_px), report.to_attrs()


def _reconstruct_dir(
    image_dir: Path,
    names: list[str],
    size_wh: tuple[int, int],
    params: SfmParams,
    prior: CameraPrior | None,
    work: Path,
    timings: dict[str, float],
    keep_workspace: bool = False,
    progress: ProgressFn = no_progress,
) -> SfmResult:
    """SIFT + sequential matching + mapping over `names` in `image_dir` (all of size `size_wh`, in sequence
    order); with `keep_workspace` the result carries the database and the kept model. Reports stages 1-3
    of `STAGES` to `progress` (not the last one, done: the caller's)."""
    import pycolmap

    pycolmap.set_random_seed(params.random_seed)
    db_path = work / "database.db"
    db_path.unlink(missing_ok=True)  # a reused workdir must not append to an old database
    K = None if prior is None else prior.K  # in the frames' pixels
    guessed = prior is not None and not prior.given
    aspect = _pixel_aspect(K, params)
    K_sfm = None if K is None else np.diag([aspect, 1.0, 1.0]) @ K  # in the mapped (stretched) pixels
    size_sfm = (round(size_wh[0] * aspect), size_wh[1])
    # A guessed focal is not a prior: it only starts the view graph's self-calibration (module notes).
    trusted = K is not None and not (guessed and params.guessed_focal == "calibrate")
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = params.camera_model
    if trusted and aspect == 1.0:
        # The prior both fixes the initial focal and marks it as trusted (has_prior_focal_length).
        reader.camera_params = _camera_params_string(K, params.camera_model)
    t = time.perf_counter()
    progress(1, len(STAGES), f"{STAGES[1]} ({len(names)} frames)")
    uncalibrated = K is None or guessed
    _extract(db_path, image_dir, names, params, reader, params.uncalibrated_peak_threshold if uncalibrated else None)
    if aspect != 1.0:
        _stretch_x(db_path, image_dir, names, aspect, size_sfm[0])
    if K_sfm is not None and (aspect != 1.0 or not trusted):
        _set_camera(db_path, K_sfm, size_sfm[0], params.camera_model, has_prior=trusted)
    timings["extract"] = time.perf_counter() - t

    t = time.perf_counter()
    pairs = sequential_pairs(len(names), params.matcher_overlap, params.quadratic_overlap)
    progress(2, len(STAGES), f"{STAGES[2]} ({len(pairs)} pairs)")
    verification = _match(db_path, [(names[i], names[j]) for i, j in pairs], params)
    timings["match"] = time.perf_counter() - t

    feature_problems, n_verified = _feature_problems(db_path, names, verification.min_num_inliers)
    if n_verified == 0:
        return empty_result(len(names), ["COLMAP registered no frames", *feature_problems], timings)

    hold = prior is not None and prior.given and params.hold_known_intrinsics  # module notes

    def run(kind: str) -> tuple[SfmResult, Any] | None:
        t0 = time.perf_counter()
        if kind == "global" and not trusted:
            # Without a focal prior the global mapper fails at random; calibrating the view graph fixes it.
            pycolmap.calibrate_view_graph(db_path, _calibration_options(params, K_sfm, size_wh, aspect))
        if kind == PRIOR_FOCAL and K_sfm is not None and not trusted:
            _set_camera(db_path, K_sfm, size_sfm[0], params.camera_model, has_prior=True)  # back to the guess
        rec = _run_mapper(kind, db_path, image_dir, work, params, hold)
        timings[f"map_{kind}"] = time.perf_counter() - t0
        return None if rec is None else (_result_from_model(rec, names, size_wh, kind, params, aspect), rec)

    auto = params.auto_order_known_k if hold else params.auto_order
    kinds = list(auto) if params.mapper == "auto" else [params.mapper]
    if K is not None and params.prior_focal_fallback and not (hold and "incremental" in kinds):
        kinds.append(PRIOR_FOCAL)  # with the camera held, "incremental" already is this
    tried: list[tuple[str, tuple[SfmResult, Any] | None]] = []
    for k, kind in enumerate(kinds):
        fallback = f", fallback {k} of {len(kinds) - 1}" if k else ""
        progress(3, len(STAGES), f"{STAGES[3]} ({kind}{fallback})")
        out = run(kind)
        tried.append((kind, out))
        if out is not None and out[0].gates_passed:
            break
    results = [out for _, out in tried if out is not None]
    if not results:
        return empty_result(len(names), ["COLMAP registered no frames", *feature_problems], timings)
    best, best_rec = max(results, key=lambda o: (o[0].gates_passed, o[0].n_registered, o[0].n_points))
    if not best.gates_passed:
        # Say what each mapper got wrong, so a rejection can be diagnosed from the words alone.
        best.problems = [
            f"{kind}: {p}" if len(kinds) > 1 else p
            for kind, out in tried
            for p in (out[0].problems if out is not None else ["COLMAP registered no frames"])
        ] + ([p for p in feature_problems if best.n_registered < len(names)])
    if keep_workspace:
        best.workspace = SfmWorkspace.pack(db_path, best_rec, work / "kept")
    kept_prior = prior is not None and (hold or best.mapper == PRIOR_FOCAL)
    best.k_source = prior.source if kept_prior and prior is not None else "estimated"
    best.timings = timings
    return best


def write_png_frames(image_dir: Path, names: Sequence[str], frames: Sequence[np.ndarray]) -> None:
    """Frames as PNG files (lossless, so SIFT sees exactly the frames) named `names` in `image_dir`."""
    import imageio.v3 as iio

    for name, f in zip(names, frames, strict=True):
        iio.imwrite(image_dir / name, f)


def _checked_names(names: Sequence[str] | None, n_frames: int) -> list[str]:
    """Image file names for the frames: the caller's (unique plain .png names) or frame positions."""
    if names is None:
        return [f"{i:06d}.png" for i in range(n_frames)]
    out = list(names)
    if len(out) != n_frames:
        raise ValueError(f"names: need one per frame ({n_frames}), got {len(out)}")
    bad = [n for n in out if not isinstance(n, str) or Path(n).name != n or not n.endswith(".png")]
    if bad:
        raise ValueError(f"names must be plain file names ending in .png, got {bad[0]!r}")
    if len(set(out)) != len(out):
        raise ValueError("names must be unique")
    return out


@dataclass
class _Images:
    """What SfM reads: one image name per frame, and either the frames to write as PNG files (`arrays`) or the
    caller's files to link (`files`); sizes (W,H) per frame; problems: files that cannot be read."""

    names: list[str]
    sizes: list[tuple[int, int]]
    arrays: list[np.ndarray] | None = None
    files: list[Path] | None = None
    problems: list[str] = field(default_factory=list)

    def place(self, image_dir: Path, indices: Sequence[int]) -> None:
        """The frames at `indices` into `image_dir`: written losslessly (SIFT sees exactly the frames), or
        linked (the files are not decoded here; a reused workdir may hold a stretched copy or an old link)."""
        if self.arrays is not None:
            write_png_frames(image_dir, [self.names[i] for i in indices], [self.arrays[i] for i in indices])
            return
        assert self.files is not None
        for i in indices:
            link = image_dir / self.names[i]
            if link.is_symlink() or link.exists():
                link.unlink()
            link.symlink_to(self.files[i].resolve())


def _is_paths(frames: Any) -> bool:
    return (
        isinstance(frames, Sequence)
        and not isinstance(frames, str | bytes | np.ndarray)
        and len(frames) > 0
        and all(isinstance(f, str | Path) for f in frames)
    )


def _images(frames: np.ndarray | Sequence[np.ndarray] | Sequence[Path | str], names: Sequence[str] | None) -> _Images:
    """The frames as SfM's images (ValueError for wrong types, shapes or names)."""
    if not _is_paths(frames):
        arrays = _validate_frames(frames)  # type: ignore[arg-type]
        sizes = [(int(f.shape[1]), int(f.shape[0])) for f in arrays]
        return _Images(_checked_names(names, len(arrays)), sizes, arrays=arrays)
    if names is not None:
        raise ValueError("names apply to frames given as arrays; image files are named by their position")
    from PIL import Image

    files = [Path(f) for f in frames]
    sizes: list[tuple[int, int]] = []
    for f in files:
        try:
            with Image.open(f) as im:
                sizes.append(im.size)
        except OSError as e:
            return _Images([], [], files=files, problems=[f"cannot read image {f.name}: {e}"])
    return _Images([f"{i:06d}{f.suffix.lower()}" for i, f in enumerate(files)], sizes, files=files)


def reconstruct(
    frames: np.ndarray | Sequence[np.ndarray] | Sequence[Path | str],
    params: SfmParams | None = None,
    prior: CameraPrior | None = None,
    *,
    workdir: Path | None = None,
    names: Sequence[str] | None = None,
    keep_workspace: bool = False,
    progress: ProgressFn | None = None,
) -> SfmResult:
    """Reconstruct one segment, frames in sequence order -> SfmResult. frames: (T,H,W,3) uint8, a list of
    (H,W,3) uint8, or the paths of image files (frame i = frames[i]; not decoded into memory: COLMAP reads them,
    downscaled to `max_image_size_px` for SIFT, and K is in full-size pixels).

    prior: the camera's intrinsics as far as known (`camera.CameraPrior`, K in pixels of these frames), or None.
    Its pixel aspect fy/fx is held while mapping (`keep_pixel_aspect`), the focal refined. A given K is the
    camera's calibration: with `params.hold_known_intrinsics` (default) no mapper refines it, and `auto` follows
    `auto_order_known_k`; with it off, the K seeds the shared camera's focal, which the mappers refine. A guessed
    K (an assumed field of view), with `guessed_focal="calibrate"`, only starts the view graph's
    self-calibration, and is held as it was only by the last-resort mapper. Without a prior the incremental
    mapper starts from COLMAP's 1.2·max(W,H) and the global one calibrates the view graph.
    Without a given K (no prior, or a guessed one) a few frames are first looked at for parallax
    (`wonderverse.parallax`); with too little, nothing is mapped and `stopped` says why.
    workdir keeps the images, database and models there (for debugging); otherwise a temp dir is used.
    names (frames given as arrays only): one unique `.png` file name per frame, used for the images in COLMAP
    (default: the frame's position); give stable ids when the workspace is to be extended later, sorting in
    sequence order: COLMAP numbers images by sorted name and the global mapper depends on that
    (`global_poses.image_names`).
    keep_workspace: return the database and kept model in `result.workspace` (for
    `sfm_extend.extend_reconstruction`).
    progress(stage, len(STAGES), what it is doing): each of `STAGES` as it starts, then done.
    """
    from wonderverse.parallax import subset

    report = progress or no_progress
    params = params or SfmParams()
    prior = _validate_prior(prior)
    images = _images(frames, names)
    t_start = time.perf_counter()
    problems = images.problems or _input_problems(images.sizes)
    if problems:
        return empty_result(len(images.files) if images.files is not None else len(images.names), problems)
    names = images.names
    with tempfile.TemporaryDirectory(prefix="wv-sfm-") as tmp:
        work = Path(workdir) if workdir is not None else Path(tmp)
        image_dir = work / "images"
        image_dir.mkdir(parents=True, exist_ok=True)
        timings: dict[str, float] = {}
        t = time.perf_counter()
        report(0, len(STAGES), STAGES[0])
        look = _looks_for_parallax(prior, params)
        first = [int(i) for i in subset(len(names), params.parallax_frames)] if look else []
        images.place(image_dir, first)  # the look starts on these while the rest wait
        seen = None
        if look:
            stop, seen = _parallax_stop([image_dir / n for n in names], images.sizes[0], prior, params, work)
            timings["parallax"] = seen["seconds"]
            if stop:
                return _stopped(len(names), stop, seen, prior, timings, t_start)
        images.place(image_dir, [i for i in range(len(names)) if i not in set(first)])
        timings["write"] = time.perf_counter() - t - timings.get("parallax", 0.0)
        res = _reconstruct_dir(image_dir, names, images.sizes[0], params, prior, work, timings, keep_workspace, report)
        res.parallax = seen
    res.timings["total"] = time.perf_counter() - t_start
    report(len(STAGES), len(STAGES), f"{res.n_registered}/{len(names)} frames registered")
    return res


def _stopped(
    n_frames: int,
    reason: str,
    seen: dict[str, Any],
    prior: CameraPrior | None,
    timings: dict[str, float],
    t_start: float,
) -> SfmResult:
    """The result of a reconstruction stopped before mapping for `reason` (too little parallax)."""
    res = empty_result(n_frames, [reason], timings)
    res.stopped, res.parallax = reason, seen
    res.k_source = "" if prior is None else prior.source
    res.timings["total"] = time.perf_counter() - t_start
    return res

"""Step `splats`: optimise 3D Gaussians on the stitched video with the paper's RGB + depth + normal
losses, from the global poses and the aligned priors. Checkpoints go to `splats_checkpoint/` every
`checkpoint_every_iters`, so a killed run resumes; the result goes to `splats/` and `splats.ply` (INRIA
layout, original world frame) beside the store."""

from __future__ import annotations

import io
import logging
from pathlib import Path
from typing import Any

import numpy as np

from tasks.base import Step
from tasks.progress import callback
from wonderverse.config import RunConfig
from wonderverse.errors import WonderError
from wonderverse.store import SceneStore, cache_key, write_array

log = logging.getLogger("wonderverse.splats")
CHECKPOINT = "splats_checkpoint"


def _params(cfg: RunConfig) -> dict[str, Any]:
    return {"splats": cfg.steps.splats.model_dump(exclude={"renderer"})}


def load_views(store: SceneStore) -> tuple[Any, list[str]]:
    """Every posed stitched frame with its priors, in SfM world units (frames without a pose skipped), and
    the frames' names (`s000_0007`: segment, generation-order index)."""
    from wonderverse.splats.trainer import Views

    segs = store.attrs("sfm")["segments"]
    index = store.array("sfm/frame_index")
    poses = store.array("sfm/poses")
    keep = np.isfinite(poses).all(axis=(1, 2))
    frames, depth, normals, names = [], [], [], []
    cache: dict[str, dict[str, np.ndarray]] = {}
    for (a, i), ok in zip(index, keep, strict=True):
        if not ok:
            continue
        seg = segs[a]
        names.append(f"{seg}_{int(i):04d}")
        if seg not in cache:
            from tasks.segments import attempt_path

            ap = attempt_path(store, seg)
            cache[seg] = {
                "frames": store.array(f"{ap}/frames"),
                "depth": store.array(f"priors/{seg}/depth"),
                "normals": store.array(f"priors/{seg}/normals"),
            }
        frames.append(cache[seg]["frames"][i])
        depth.append(cache[seg]["depth"][i])
        normals.append(cache[seg]["normals"][i].astype(np.float32))
    if not frames:
        raise WonderError("no posed frames to train on")
    views = Views(
        frames=np.stack(frames),
        w2c=poses[keep],
        K=store.array("sfm/K"),
        prior_depth=np.stack(depth),
        prior_normals=np.stack(normals),
    )
    return views, names


def _initial_model(views: Any, points: np.ndarray, colors: np.ndarray, cfg: RunConfig) -> Any:
    """SfM points plus back-projected prior depth, voxel-averaged at a size that follows the scene."""
    from wonderverse.splats.data import backproject_depth
    from wonderverse.splats.model import init_from_points, voxel_downsample
    from wonderverse.splats.trainer import auto_scene_scale

    p = cfg.steps.splats
    if p.init_from_depth:
        dp, dc = backproject_depth(views, p.init_depth_stride_px, p.init_depth_frame_stride)
        points, colors = np.concatenate([points, dp]), np.concatenate([colors, dc])
    if len(points) == 0:
        raise WonderError("no points to start the splats from (no SfM points and no valid prior depth)")
    rgb = colors.astype(np.float64) / 255.0  # averaged as floats in [0,1], as init_from_points expects
    points, rgb = voxel_downsample(points, rgb, p.init_voxel_frac * auto_scene_scale(views.w2c, points))
    return init_from_points(points, rgb, p.train.sh_degree, init_opacity=p.init_opacity)


def _train_digest(cfg: RunConfig) -> str:
    """What must not change for an extension to continue the previous optimisation instead of restarting."""
    p = cfg.steps.splats.model_dump(exclude={"renderer", "extend_iterations_frac", "extend_new_view_share"})
    return cache_key("splats_train", 2, {"splats": p})


def _extendable(store: SceneStore, cfg: RunConfig, names: list[str]) -> dict[str, Any] | None:
    """The previous `splats/` attrs when this run only adds frames to it (same training settings, every
    previous frame still there, something new): the scene was extended; else None (train from scratch)."""
    prev = store.attrs("splats")
    if prev.get("complete") is not True or prev.get("train_digest") != _train_digest(cfg):
        return None
    old = set(prev.get("frames", []))
    return prev if old and old < set(names) else None


def _extended_model(
    store: SceneStore, nviews: Any, norm: Any, new: list[int], previous: dict[str, Any], cfg: RunConfig
) -> tuple[Any, int]:
    """The previous Gaussians (moved into this run's training frame) followed by new ones seeded from the
    prior depth of the `new` views only, away from the old ones; returns (model, number of old Gaussians)."""
    from scipy.spatial import cKDTree

    from wonderverse.splats.data import backproject_depth
    from wonderverse.splats.model import GaussianModel, init_from_points, normalization_from_dict, voxel_downsample
    from wonderverse.splats.ply import to_training_frame, to_world
    from wonderverse.splats.trainer import auto_scene_scale

    p = cfg.steps.splats
    old = {k: store.array(f"splats/{k}") for k in GaussianModel.PARAM_NAMES}
    old = to_training_frame(to_world(old, normalization_from_dict(previous["normalization"])), norm)
    sub = nviews.subset(new)
    pts, cols = backproject_depth(sub, p.init_depth_stride_px, p.init_depth_frame_stride)
    voxel = p.init_voxel_frac * auto_scene_scale(nviews.w2c, old["means"])
    pts, rgb = voxel_downsample(pts, cols.astype(np.float64) / 255.0, voxel)
    if len(pts) and len(old["means"]):  # where old Gaussians already are, the scene is modelled
        far = cKDTree(old["means"]).query(pts)[0] > 2 * voxel
        pts, rgb = pts[far], rgb[far]
    n_old = len(old["means"])
    if not len(pts):
        return GaussianModel.from_numpy(old), n_old
    # sized by their nearest Gaussians old or new: a seed beside the old ones must not span the gap to the next seed
    seeds = init_from_points(pts, rgb, p.train.sh_degree, p.init_opacity, neighbours=old["means"]).to_numpy()
    both = {k: np.concatenate([np.asarray(old[k], np.float32), seeds[k]]) for k in GaussianModel.PARAM_NAMES}
    return GaussianModel.from_numpy(both), n_old


def _save_checkpoint(store: SceneStore, key: str, step: int, state: dict[str, Any]) -> None:
    import torch

    buf = io.BytesIO()
    torch.save(state, buf)
    with store.staged(CHECKPOINT, cache_key("checkpoint", 1, {"step": step}, [key]), step=step, run_key=key) as g:
        write_array(g, "state", np.frombuffer(buf.getvalue(), np.uint8), chunks=(1 << 24,))


def _load_checkpoint(store: SceneStore, key: str) -> dict[str, Any] | None:
    import torch

    a = store.attrs(CHECKPOINT)
    if a.get("complete") is not True or a.get("run_key") != key:
        return None
    state = torch.load(io.BytesIO(store.array(f"{CHECKPOINT}/state").tobytes()), weights_only=False)
    log.warning("resuming splat training from the checkpoint at step %d", a["step"])
    return state


def run(store: SceneStore, cfg: RunConfig, key: str) -> str:
    from wonderverse.splats.data import downscale_views
    from wonderverse.splats.model import normalization_from_cameras, normalization_to_dict
    from wonderverse.splats.ply import write_ply
    from wonderverse.splats.renderer import make_renderer
    from wonderverse.splats.trainer import continuation_params, normalize_views, train

    p = cfg.steps.splats
    views, names = load_views(store)
    views, names = views.subset(slice(None, None, p.frame_stride)), names[:: p.frame_stride]
    views = downscale_views(views, p.max_side_px)
    points, colors = store.array("sfm/points3d"), store.array("sfm/colors")
    norm = normalization_from_cameras(views.w2c, points)  # train in a unit-sized frame
    nviews = normalize_views(views, norm)
    previous = _extendable(store, cfg, names)
    train_params, fixed, new_views = p.train, 0, []
    if previous is None:
        model = _initial_model(nviews, norm.apply(points), colors, cfg)
    else:
        seen = set(previous["frames"])
        new_views = [i for i, n in enumerate(names) if n not in seen]
        model, fixed = _extended_model(store, nviews, norm, new_views, previous, cfg)
        train_params = continuation_params(p.train, p.extend_iterations_frac)
        log.info(
            "extending the splats: %d existing Gaussians kept, %d new, %d iterations (%.0f %% on %d new views)",
            fixed,
            model.num_gaussians - fixed,
            train_params.iterations,
            100 * p.extend_new_view_share,
            len(new_views),
        )
    renderer = make_renderer(p.renderer)
    model, curves, metrics = train(
        model,
        nviews,
        train_params,
        renderer,
        checkpoint_cb=lambda step, state: _save_checkpoint(store, key, step, state),
        resume_state=_load_checkpoint(store, key),
        fixed_gaussians=fixed,
        focus_views=new_views,
        focus_share=p.extend_new_view_share,
        progress=callback("iterations"),
    )
    arrays = model.to_numpy()
    ply = write_ply(Path(store.scene_dir) / "splats.ply", arrays, norm)
    with store.staged(
        "splats",
        key,
        normalization=normalization_to_dict(norm),
        metrics=metrics,
        files=[ply.name],
        frames=names,
        train_digest=_train_digest(cfg),
        extended_from=None if previous is None else {"frames": len(previous["frames"]), "kept_gaussians": fixed},
        curves={k: [float(x) for x in v] for k, v in curves.items()},
    ) as g:
        for name, arr in arrays.items():
            write_array(g, name, np.asarray(arr, np.float32), chunks=(max(1, len(arr)), *np.shape(arr)[1:]))
    store.remove(CHECKPOINT)
    psnr = metrics.get("test_psnr", metrics.get("train_psnr", float("nan")))
    return f"{metrics['n_gaussians']} Gaussians, held-out PSNR {psnr:.2f} dB, {renderer.__class__.__name__}"


STEP = Step("splats", 4, ("priors",), _params, run, "3D Gaussian splatting with depth and normal losses")

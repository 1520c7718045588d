"""Step `splats`: optimise 3D Gaussians on the stitched video with the paper's RGB + depth + normal
losses, from the global poses and the aligned priors. Checkpoints go to `splats_checkpoint/` every
`checkpoint_every_iters`, so a killed run resumes; the result goes to `splats/` (training frame, with the
normalisation that maps it to the global poses' frame). The exported `splats.ply` is written by the outputs
step, in the outputs' gravity-aligned frame."""

from __future__ import annotations

import hashlib
import logging
from collections.abc import Collection
from typing import TYPE_CHECKING, Any

import numpy as np

from tasks.base import Step, StepContext
from tasks.progress import callback
from tasks.splats_checkpoint import CHECKPOINT, load_checkpoint, save_checkpoint
from wonderverse.config import RunConfig, SplatsStepParams
from wonderverse.errors import WonderError
from wonderverse.schema import PRIORS_SEGMENT, SFM, SPLATS
from wonderverse.store import SceneStore, cache_key, write_array

if TYPE_CHECKING:
    from wonderverse.splats.region import Region
    from wonderverse.splats.seeding import PreviousSplats
    from wonderverse.splats.trainer import Views

log = logging.getLogger("wonderverse.splats")


Params = SplatsStepParams  # the step reads its own settings only


def params(cfg: RunConfig) -> SplatsStepParams:
    return cfg.steps.splats


def load_views(store: SceneStore, only: Collection[str] | None = None) -> tuple[Views, list[str]]:
    """Every posed stitched frame with its priors (with `only`, the frames of those names), in SfM world units
    (frames without a pose skipped), and the frames' names (`s000_0007`: segment, generation-order index)."""
    from tasks.segments import attempt_path, posed_stitched
    from wonderverse.splats.trainer import Views

    first = store.meta(SFM.path).segments[0]
    priors = {
        name for name in ("depth", "aligned", "normals") if store.exists(getattr(PRIORS_SEGMENT.at(seg=first), name))
    }
    arrays = {"frames": lambda seg: attempt_path(store, seg).frames}
    arrays |= {name: (lambda seg, n=name: getattr(PRIORS_SEGMENT.at(seg=seg), n)) for name in priors}
    rows, w2c, names = posed_stitched(store, arrays, only)
    if not names:
        raise WonderError("no posed frames to train on")
    views = Views(
        frames=rows["frames"],
        w2c=w2c,
        K=store.array(SFM.K),
        prior_depth=rows.get("depth"),
        prior_aligned=rows.get("aligned"),
        prior_normals=rows["normals"].astype(np.float32) if "normals" in rows else None,
    )
    return views, names


def poses_digest(w2c: np.ndarray) -> str:
    """A digest of the W2C poses (N,4,4) the splats are trained with, bit for bit."""
    return hashlib.sha256(np.ascontiguousarray(w2c, np.float64).tobytes()).hexdigest()


# which pixels count, not what the Gaussians are: the optimisation continues across a change of these
_CONTINUABLE = {"newest_frames_win", "superseded_margin"}


def _train_digest(p: SplatsStepParams) -> str:
    """What must not change for an extension to continue the previous optimisation instead of restarting."""
    fields = SplatsStepParams.model_fields
    kept = p.model_dump(exclude={name for name in fields if name.startswith("extend_") or name in _CONTINUABLE})
    return cache_key("splats_train", 2, {"splats": kept})


def _previous(store: SceneStore, p: SplatsStepParams, names: list[str]) -> PreviousSplats | None:
    """The previous splats when this run only adds frames to them (same training settings, every previous
    frame still there, something new): the scene was extended; else None (train from scratch)."""
    from wonderverse.splats.model import GaussianModel, normalization_from_dict
    from wonderverse.splats.seeding import PreviousSplats

    prev = store.meta(SPLATS.path)
    if prev is None or prev.train_digest != _train_digest(p):
        return None
    old = set(prev.frames)
    if not (old and old < set(names)):
        return None
    arrays = {k: store.array(getattr(SPLATS, k)) for k in GaussianModel.PARAM_NAMES}
    return PreviousSplats(arrays, normalization_from_dict(prev.normalization), prev.frames, prev.poses_digest)


def stored_sky(store: SceneStore) -> np.ndarray | None:
    """What the stored splats show behind their Gaussians: the sky map (R, 2R, 3) when one was trained, else
    the learnt colour (3,); None for splats stored without either."""
    if "sky_map" in store.group(SPLATS.path):
        return store.array(SPLATS.sky_map)
    colour = store.meta(SPLATS.path, complete=False).metrics.background_rgb
    return None if colour is None else np.asarray(colour, np.float32)


def _region(
    store: SceneStore, p: SplatsStepParams, previous: PreviousSplats, names: list[str], w2c: np.ndarray
) -> Region | None:
    """The region an extension trains (`wonderverse.splats.region`), None when the whole scene is to be: no
    region is asked for, or the frames the previous splats were trained on have moved (the global poses were solved
    again, not only extended): Gaussians kept as they were would no longer line up with their views."""
    from tasks.segments import attempt_path
    from wonderverse.splats.region import extension_region

    if p.extend_old_views_max is None:
        return None
    at = {n: i for i, n in enumerate(names)}
    trained_with = previous.poses_digest
    if trained_with is not None and poses_digest(w2c[[at[n] for n in previous.frames]]) != trained_with:
        log.warning("the poses of the frames the splats were trained on have moved: every view trains again")
        return None
    seen = set(previous.frames)
    new = [i for i, n in enumerate(names) if n not in seen]
    height, width = store.shape(attempt_path(store, names[new[0]].split("_")[0]).frames)[1:3]
    means = previous.normalization.apply_inverse(np.asarray(previous.arrays["means"], np.float64))
    limits = (p.extend_old_views_max, p.extend_min_overlap, p.extend_view_margin_frac)
    return extension_region(means, w2c, store.array(SFM.K), width, height, new, *limits)


def run(store: SceneStore, p: SplatsStepParams, ctx: StepContext) -> str:
    from tasks.segments import posed_stitched
    from wonderverse.splats.model import normalization_to_dict
    from wonderverse.splats.region import held_out, scene_figures
    from wonderverse.splats.renderer import make_renderer
    from wonderverse.splats.seeding import merged, start_training
    from wonderverse.splats.trainer import train

    _, w2c, names = posed_stitched(store, {})
    w2c, names = w2c[:: p.frame_stride], names[:: p.frame_stride]
    previous = _previous(store, p, names)
    region = None if previous is None else _region(store, p, previous, names, w2c)
    views, local = load_views(store, set(names if region is None else [names[i] for i in region.views]))
    test = held_out(names, p.train.holdout_every)
    held = {names[i] for i in test}
    points, colors = store.array(SFM.points3d), store.array(SFM.colors)
    start = start_training(views, local, points, colors, p, previous, region, held)
    model, fixed, norm = start.model, start.fixed, start.normalization
    focus = start.focus(p.extend_new_view_share, p.extend_near_view_share)
    if previous is not None:
        log.info("extending the splats: %s", start.describe(focus))
    renderer = make_renderer(ctx.execution.renderer)
    model, curves, metrics = train(
        model,
        start.views,
        start.train,
        renderer,
        checkpoint_cb=lambda step, state: save_checkpoint(store, ctx.key, step, state),
        resume_state=load_checkpoint(store, ctx.key, renderer.device, len(start.views), model.shN.shape[1]),
        fixed_gaussians=fixed,
        focus=focus,
        progress=callback("iterations"),
        view_gap=p.frame_stride,
        test_views=[i for i, n in enumerate(local) if n in held],
        sky_start=None if previous is None else stored_sky(store),
        frozen_gaussians=start.frozen,
    )
    arrays = model.to_numpy()
    if start.kept is not None:
        arrays, norm = merged(start, arrays, previous), previous.normalization
    before = None if previous is None else store.meta(SPLATS.path).metrics
    metrics = scene_figures(metrics, local, names, test, before) | {"n_gaussians": len(arrays["means"])}
    sky_map = metrics.pop("sky_map", None)
    if sky_map is not None:
        arrays["sky_map"] = sky_map
    with store.staged(
        SPLATS.path,
        ctx.key,
        normalization=normalization_to_dict(norm),
        metrics=metrics,
        frames=names,
        poses_digest=poses_digest(w2c),
        train_digest=_train_digest(p),
        extended_from=None if previous is None else start.extended_from(len(previous.frames)),
        curves={k: [float(x) for x in v] for k, v in curves.items()},
    ) as g:
        for name, arr in arrays.items():
            write_array(g, getattr(SPLATS, name), arr)
    store.remove(CHECKPOINT)
    return f"{metrics['n_gaussians']} Gaussians, {_psnr_label(metrics)}, {renderer.__class__.__name__}"


def _psnr_label(metrics: dict[str, Any]) -> str:  # held-out only where views were held out
    if metrics.get("test_views") and "test_psnr" in metrics:
        return f"held-out PSNR {metrics['test_psnr']:.2f} dB ({len(metrics['test_views'])} views)"
    return f"training PSNR {metrics.get('train_psnr', float('nan')):.2f} dB"


# 6: held-out views chosen per segment (region.held_out); an extension trains a region
STEP = Step("splats", 6, ("priors",), params, run, "3D Gaussian splatting with depth and normal losses", SPLATS.path)

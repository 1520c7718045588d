"""Where splat training starts: the views in a unit-sized training frame, and the Gaussians to optimise.

A new scene starts from the SfM points plus the aligned prior depth back-projected, voxel-averaged at a
size that follows the scene (`initial_model`). An extended scene (the same training settings, more frames)
continues from the previous Gaussians, moved into this run's training frame, followed by new ones seeded
from the new frames' depth only where no Gaussian is yet (`extension_seeds`, `extended_model`); training
then keeps the previous ones fixed in number and spends part of its steps on the new views
(`start_training`). Arrays are in the layout of `GaussianModel.to_numpy`; poses W2C; colours uint8.
"""

from __future__ import annotations

from collections.abc import Collection, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from wonderverse.errors import WonderError

if TYPE_CHECKING:
    from wonderverse.camera import Sim3
    from wonderverse.config import SplatsStepParams
    from wonderverse.splats.model import GaussianModel
    from wonderverse.splats.params import TrainParams
    from wonderverse.splats.region import Region
    from wonderverse.splats.trainer import Views


@dataclass
class PreviousSplats:
    """A previous training run to continue: its Gaussians (training frame of `normalization`), that
    normalisation, the names of the views it was trained on and a digest of their poses (None: not recorded)."""

    arrays: dict[str, np.ndarray]
    normalization: Sim3
    frames: list[str]
    poses_digest: str | None = None


@dataclass
class TrainingStart:
    """views: the training views in the training frame; normalization: world -> training frame; model:
    the Gaussians to start from, the first `fixed` of them the previous run's (0 for a new scene);
    new_views: indices of the views the previous run did not see; train: the training schedule (a
    shortened continuation after an extension); kept: the previous Gaussians a region's training does not change
    (arrays in the previous run's training frame, `previous.normalization`), None when every one is trained;
    frozen: how many of them the model starts with (rendered, never changed: they come first); near_views: the old
    views that see what the new ones see (`near_views`), whose Gaussians the new views' steps move."""

    views: Views
    normalization: Sim3
    model: GaussianModel
    fixed: int
    new_views: list[int]
    train: TrainParams
    kept: dict[str, np.ndarray] | None = None
    frozen: int = 0
    near_views: list[int] = field(default_factory=list)

    def extended_from(self, frames: int) -> dict[str, int]:
        """What a continuation started from: the previous run's `frames`, its Gaussians carried over (kept as
        they were or continued), those continued, and the views trained."""
        kept = 0 if self.kept is None else len(self.kept["means"]) - self.frozen
        return {
            "frames": frames,
            "kept_gaussians": kept + self.fixed,
            "continued_gaussians": self.fixed - self.frozen,
            "views": len(self.views),
        }

    def focus(self, new_share: float, near_share: float) -> list[tuple[list[int], float]]:
        """The views a continuation favours (`trainer.view_order`): the new ones `new_share` of the steps, the old
        ones near them (`near_views`) `near_share` of the rest."""
        return [(self.new_views, new_share), (self.near_views, (1.0 - new_share) * near_share)]

    def describe(self, focus: list[tuple[list[int], float]]) -> str:
        """What a continuation does, in words (`focus`: as `TrainingStart.focus` gives it)."""
        kept = 0 if self.kept is None else len(self.kept["means"])
        continued, new = self.fixed - self.frozen, self.model.num_gaussians - self.fixed
        (_, new_share), (near, near_share) = focus
        return (
            f"{kept} Gaussians kept as they are ({self.frozen} of them rendered), {continued} continued, {new} new; "
            f"{self.train.iterations} iterations on {len(self.views)} views, {100 * new_share:.0f} % on the "
            f"{len(self.new_views)} new, {100 * near_share:.0f} % on the {len(near)} old ones that see what they see"
        )


def initial_model(views: Views, points: np.ndarray, colors: np.ndarray, params: SplatsStepParams) -> GaussianModel:
    """Gaussians at the SfM `points` (P,3, the views' frame; `colors` (P,3) uint8) plus, with
    `params.init_from_depth`, the prior depth back-projected, voxel-averaged at `init_voxel_frac` of the
    scene scale. WonderError when there is no point at all."""
    from wonderverse.splats.data import backproject_depth
    from wonderverse.splats.model import init_from_points, voxel_downsample
    from wonderverse.splats.trainer import auto_scene_scale

    p = params
    if p.init_from_depth:
        dp, dc = backproject_depth(views, p.init_depth_stride_px, p.init_depth_frame_stride)
        points, colors = np.concatenate([points, dp]), np.concatenate([colors, dc])
    if len(points) == 0:
        raise WonderError("no points to start the splats from (no SfM points and no valid prior depth)")
    rgb = colors.astype(np.float64) / 255.0  # averaged as floats in [0,1], as init_from_points expects
    points, rgb = voxel_downsample(points, rgb, p.init_voxel_frac * auto_scene_scale(views.w2c, points))
    return init_from_points(points, rgb, p.train.sh_degree, init_opacity=p.init_opacity)


def extension_seeds(
    old_means: np.ndarray, new_views: Views, stride_px: int, frame_stride: int, voxel: float
) -> tuple[np.ndarray, np.ndarray]:
    """Where new Gaussians go: the prior depth of `new_views` back-projected (every `stride_px` pixels of
    every `frame_stride`-th view), voxel-averaged at `voxel`, and kept only farther than 2 voxels from every
    old Gaussian centre (`old_means` (M,3); where old Gaussians are, the scene is modelled already).
    Returns points (P,3) float64 and colours (P,3) float64 in [0,1]."""
    from scipy.spatial import cKDTree

    from wonderverse.splats.data import backproject_depth
    from wonderverse.splats.model import voxel_downsample

    pts, cols = backproject_depth(new_views, stride_px, frame_stride)
    pts, rgb = voxel_downsample(pts, cols.astype(np.float64) / 255.0, voxel)
    if len(pts) and len(old_means):
        far = cKDTree(old_means).query(pts)[0] > 2 * voxel
        pts, rgb = pts[far], rgb[far]
    return pts, rgb


def extended_model(
    previous: PreviousSplats, views: Views, normalization: Sim3, new: Sequence[int], params: SplatsStepParams
) -> tuple[GaussianModel, int]:
    """The previous Gaussians moved into this run's training frame (`normalization`; `views` are in it),
    followed by new ones seeded from the prior depth of the `new` views only, away from the old ones, each
    sized by its nearest Gaussians old or new (a seed beside the old ones must not span the gap to the next
    seed). Returns (model, number of old Gaussians, which come first)."""
    from wonderverse.splats.model import GaussianModel, init_from_points
    from wonderverse.splats.ply import to_training_frame, to_world
    from wonderverse.splats.trainer import auto_scene_scale

    p = params
    old = to_training_frame(to_world(previous.arrays, previous.normalization), normalization)
    voxel = p.init_voxel_frac * auto_scene_scale(views.w2c, old["means"])
    stride_px, frame_stride = p.init_depth_stride_px, p.init_depth_frame_stride
    pts, rgb = extension_seeds(old["means"], views.subset(new), stride_px, frame_stride, voxel)
    n_old = len(old["means"])
    if not len(pts):
        return GaussianModel.from_numpy(old), n_old
    seeds = init_from_points(pts, rgb, p.train.sh_degree, p.init_opacity, neighbours=old["means"]).to_numpy()
    both = {k: np.concatenate([np.asarray(old[k], np.float32), seeds[k]]) for k in GaussianModel.PARAM_NAMES}
    return GaussianModel.from_numpy(both), n_old


def start_training(
    views: Views,
    names: Sequence[str],
    points: np.ndarray,
    colors: np.ndarray,
    params: SplatsStepParams,
    previous: PreviousSplats | None = None,
    region: Region | None = None,
    held_out: Collection[str] = (),
) -> TrainingStart:
    """Training set up from world-frame `views` (one per name in `names`) and SfM `points` (P,3) with
    `colors` (P,3) uint8: frames downscaled to `max_side_px`, everything moved into a frame centred on the
    cameras with unit extent (`model.normalization_from_cameras`), and the Gaussians to start from: a new
    model, or `previous` continued (`extended_model`, a shortened schedule, `trainer.continuation_params`).
    With a `region` (`wonderverse.splats.region`), `views` are the region's and only the previous Gaussians
    of `region.gaussians` are continued; the others are returned as `kept`, for `merged` after training.
    The frames named in `held_out` (the views training holds out to score itself) seed nothing: what only they
    see must not be in the model before training, or their PSNR would not measure it. With `newest_frames_win`,
    the views' `superseded` pixels are set (`splats.superseded`)."""
    from wonderverse.splats.data import downscale_views
    from wonderverse.splats.model import normalization_from_cameras
    from wonderverse.splats.superseded import with_superseded
    from wonderverse.splats.trainer import continuation_params, normalize_views

    p = params
    views = downscale_views(views, p.max_side_px)
    norm = normalization_from_cameras(views.w2c, points)  # train in a unit-sized frame
    nviews = normalize_views(views, norm)
    if p.newest_frames_win:  # where later words changed the world under older frames, the splats show it
        nviews = with_superseded(nviews, names, held_out, p.superseded_margin)
    held = set(held_out)
    if previous is None:
        seeding = [i for i, n in enumerate(names) if n not in held]
        model = initial_model(nviews.subset(seeding), norm.apply(points), colors, p)
        return TrainingStart(nviews, norm, model, 0, [], p.train)
    seen = set(previous.frames)
    new_views = [i for i, n in enumerate(names) if n not in seen]
    kept, frozen = None, 0
    if region is not None:  # the region's untrained Gaussians first: the trainer keeps them as they are
        kept = {k: a[~region.trained] for k, a in previous.arrays.items()}
        order = np.concatenate([np.flatnonzero(region.rendered & ~region.trained), np.flatnonzero(region.trained)])
        frozen = int((region.rendered & ~region.trained).sum())
        previous = PreviousSplats({k: a[order] for k, a in previous.arrays.items()}, previous.normalization, [])
    model, fixed = extended_model(previous, nviews, norm, [i for i in new_views if names[i] not in held], p)
    train = continuation_params(p.train, p.extend_iterations_frac)
    near = near_views(model.means[:fixed].detach().cpu().numpy(), nviews, new_views, p.extend_min_overlap)
    return TrainingStart(nviews, norm, model, fixed, new_views, train, kept, frozen, near)


def near_views(old_means: np.ndarray, views: Views, new: Sequence[int], min_overlap: float) -> list[int]:
    """The views other than `new` that see at least `min_overlap` of the old Gaussians (centres (N,3), in the
    views' frame) the `new` views see (`region.overlap`); none when the new views see no old Gaussian."""
    from wonderverse.splats.region import overlap

    if not len(old_means) or not len(new):
        return []
    h, w = views.frames.shape[1:3]
    Ks = np.stack([views.K_of(i) for i in range(len(views))])
    share = overlap(np.asarray(old_means, np.float64), views.w2c, Ks, w, h, new, margin_frac=0.0)
    mine = set(new)
    return [i for i in np.flatnonzero(share >= min_overlap).tolist() if i not in mine]


def merged(start: TrainingStart, trained: dict[str, np.ndarray], previous: PreviousSplats) -> dict[str, np.ndarray]:
    """The whole scene after a region's training: the Gaussians it did not train (`kept`) as they were, bit for
    bit, followed by the ones it did (`trained` after its first `start.frozen`, arrays in `start.normalization`'s
    frame) moved into the previous run's frame, which the result is in."""
    from wonderverse.splats.ply import to_training_frame, to_world

    if start.kept is None:
        raise ValueError("merged() is for a region's training, which keeps the Gaussians outside it")
    rest = {k: np.asarray(a)[start.frozen :] for k, a in trained.items()}
    moved = to_training_frame(to_world(rest, start.normalization), previous.normalization)
    return {k: np.concatenate([start.kept[k], np.asarray(moved[k], start.kept[k].dtype)]) for k in start.kept}

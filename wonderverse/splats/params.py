"""Splat parameters (pydantic only, so config loading does not import torch)."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, SerializerFunctionWrapHandler, field_validator, model_serializer


class RobustLossParams(BaseModel):
    """Robust photometric weights against moving objects (`losses.outlier_blobs`): pixels where the frame disagrees
    with the other training frames warped into it by the rendered depth (`test: cross_view`, `losses.
    cross_view_residual`) or with the render (`test: render`, `losses.robust_weights`), in dense patches, leave the
    photometric and prior terms. Residuals are the mean over the three channels of colours in [0, 1]."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    enabled: bool = Field(
        False,
        description="weigh down outlier pixels (moving people, vehicles); off by default (docs/usage.md, transients)",
    )
    test: Literal["cross_view", "render"] = Field(
        "cross_view",
        description="what a pixel must disagree with to be an outlier: the other training frames warped into its view "
        "by the rendered depth (movers move, the world agrees across views; a ghost in the scene is in no frame), or "
        "the render (cannot tell a mover from a ghost or from what is not yet learnt; wants start_frac 0.3)",
    )
    neighbours: int = Field(
        12,
        ge=2,
        le=64,
        description="cross_view: the training views nearest in the video order a frame is compared with",
    )
    start_frac: float = Field(
        0.0,
        ge=0,
        le=1,
        description="share of the iterations trained on every pixel before the weights apply (cross_view needs none: "
        "it asks no render colour; render: 0.3, the static scene forms first)",
    )
    residual_ratio: float = Field(
        3.0, gt=1, description="a pixel is an outlier candidate above this many times its view's median residual"
    )
    min_residual: float = Field(
        0.1, ge=0, le=1, description="nor below this residual (colour units): a well-fitted view drops no texture"
    )
    patch_px: int = Field(
        7, ge=1, le=63, description="side of the square around each pixel whose candidates are counted (odd)"
    )
    patch_share: float = Field(
        0.5, gt=0, lt=1, description="a pixel is an outlier when more than this share of its patch are candidates"
    )
    dilate_px: int = Field(
        0, ge=0, le=32, description="outliers grow by this many pixels (soft edges; 2 lost ground: docs/benchmarks.md)"
    )
    min_outlier_share: float = Field(
        0.005,
        ge=0,
        lt=1,
        description="a view with a smaller share of outlier pixels keeps every pixel (static footage has few)",
    )
    max_outlier_share: float = Field(
        0.4,
        gt=0,
        le=1,
        description="a view with a larger share keeps every pixel too: movers fill less of a frame; more is a "
        "rendered depth that does not yet fit (cross_view) or a scene not yet learnt (render)",
    )
    outlier_weight: float = Field(0.0, ge=0, lt=1, description="weight of an outlier pixel (inliers weigh 1)")
    confirm_from_frac: float | None = Field(
        0.2,
        ge=0,
        le=1,
        description="cross_view: from this share of the iterations on, a flagged pixel stays an outlier only where the "
        "render disagrees with its frame too (`losses.confirmed_by_render`): what the scene already shows as this "
        "frame does is the world, though a slow mover covers it in most other frames; None: never",
    )
    confirm_share: float = Field(
        0.2,
        gt=0,
        lt=1,
        description="a flagged pixel is confirmed when more than this share of its patch disagrees with the render",
    )

    @field_validator("patch_px")
    @classmethod
    def _odd(cls, v: int) -> int:
        if v % 2 == 0:
            raise ValueError(f"patch_px must be odd (a patch centred on its pixel), got {v}")
        return v


class LossParams(BaseModel):
    """Weights of the splat loss. The paper gives no values; these follow 3DGS (λ_ssim) and DN-Splatter."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    lambda_ssim: float = Field(0.2, ge=0, le=1, description="share of (1 - SSIM) in L_rgb (3DGS: 0.2)")
    lambda_depth: float = Field(0.2, ge=0, description="λ_d, weight of the log-L1 depth term")
    lambda_normal: float = Field(0.1, ge=0, description="λ_n, weight of the normal term")
    lambda_normal_tv: float = Field(0.1, ge=0, description="λ_s, weight of TV(N̂) inside the normal term")
    alpha_threshold: float = Field(0.5, ge=0, lt=1, description="rendered alpha above which depth/normal count")
    ssim_window_px: int = Field(11, ge=3, description="Gaussian SSIM window size (odd)")
    ssim_sigma_px: float = Field(1.5, gt=0, description="Gaussian SSIM window standard deviation")
    depth_min_valid_px: int = Field(16, ge=2, description="fewer valid pixels: no depth fit, L_depth = 0")
    depth_use_expected: bool = Field(True, description="compare D̂/alpha (expected depth) instead of D̂ = Σ w z")
    depth_fit: Literal["unaligned", "every"] = Field(
        "unaligned",
        description="frames whose depth prior is fitted (scale and shift, least squares) to the rendered depth at each "
        "step: those the priors step could not align (their scale is unknown), or every frame (the fit then absorbs "
        "the prior's absolute depth, and surfaces that parallax does not place drift: benchmarks.enhancement)",
    )
    depth_units: Literal["scene", "median"] = Field(
        "median",
        description="units of |D̂ - (aD+b)| inside the log: the scene's, or the frame's median aligned prior "
        "depth (scale-free: the same loss for a room and a valley)",
    )
    prior_texture_ref: float | None = Field(
        0.02,
        gt=0,
        description="texture-aware prior weights: a pixel's depth/normal prior weight is 1 / (1 + (g / ref)²) with "
        "g its grey-level gradient magnitude (Sobel / 8, grey in [0, 1], per pixel); None: every pixel weighs 1",
    )
    prior_parallax_ref: float | None = Field(
        None,
        gt=0,
        description="texture lowers the prior weights only where parallax places the surface: by q = 1 / (1 + (u / "
        "ref)²), u the relative depth error of triangulating the pixel (1 px over the widest angle to another "
        "training view), ref the prior's relative error (`splats.parallax`); None: wherever there is texture",
    )
    prior_decay_start_frac: float = Field(
        0.3, ge=0, le=1, description="share of the iterations after which λ_d and λ_n start to decay (1: never)"
    )
    prior_final_ratio: float = Field(
        0.05, gt=0, le=1, description="λ_d and λ_n at the last iteration / their value before the decay (log-linear)"
    )
    normal_target: Literal["rendered", "depth", "both"] = Field(
        "both",
        description="normals the normal prior supervises: the rendered Σ w n (the paper's), the normals of the "
        "rendered depth (they move the surface itself), or the mean of both terms",
    )
    lambda_depth_normal: float = Field(
        0.0, ge=0, description="weight of mean (1 - cos) between rendered normals and rendered-depth normals"
    )
    lambda_flatten: float = Field(
        0.0,
        ge=0,
        description="weight of the mean over Gaussians of shortest / middle axis: flat Gaussians (surfels), whose "
        "shortest axis is a surface normal and whose depth is a surface's (0.01 made meshes worse: README)",
    )
    robust: RobustLossParams = Field(
        RobustLossParams(), description="per-pixel weights that keep moving objects out of the static scene"
    )

    @model_serializer(mode="wrap")
    def _default_robust_unwritten(self, handler: SerializerFunctionWrapHandler) -> dict[str, Any]:
        """`robust` is written only when it differs from its default (off), so every cache key made before it
        existed stays the same: off, the loss is what it was."""
        data = handler(self)
        if self.robust == RobustLossParams():
            data.pop("robust", None)
        return data


class DefaultStrategyParams(BaseModel):
    """3DGS adaptive density control (`strategy.DefaultStrategy`) in gsplat 1.5.3 `DefaultStrategy`'s own field
    names and defaults, with three additions of ours (`reset_opacity`, `split_factor`, `cap_max`). Steps are
    optimisation iterations; 3D scales are relative to the scene scale, 2D ones to the image's larger side. gsplat's
    `absgrad` (our renderers give no absolute gradients), `verbose` and `key_for_gradient` (2DGS) are left out."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    kind: Literal["default"] = Field("default", description="3DGS adaptive density control (gsplat's DefaultStrategy)")
    prune_opa: float = Field(0.005, gt=0, lt=1, description="opacity below which a Gaussian is pruned")
    grow_grad2d: float = Field(
        0.0002, gt=0, description="mean view-space gradient of a Gaussian's 2D mean (NDC units) above which it grows"
    )
    grow_scale3d: float = Field(
        0.01, gt=0, description="largest axis / scene scale up to which a growing Gaussian is cloned, above: split"
    )
    grow_scale2d: float = Field(
        0.05,
        gt=0,
        description="largest 2D radius / image side above which a growing Gaussian is split too "
        "(until refine_scale2d_stop_iter)",
    )
    prune_scale3d: float = Field(
        0.1, gt=0, description="largest axis / scene scale above which a Gaussian is pruned (after the first reset)"
    )
    prune_scale2d: float = Field(
        0.15,
        gt=0,
        description="largest 2D radius / image side above which a Gaussian is pruned (after the first reset, until "
        "refine_scale2d_stop_iter)",
    )
    refine_scale2d_stop_iter: int = Field(
        0, ge=0, description="step until which the 2D radius criteria (grow_scale2d, prune_scale2d) apply; 0: never"
    )
    refine_start_iter: int = Field(500, ge=0, description="step after which Gaussians are grown and pruned")
    refine_stop_iter: int = Field(15_000, ge=0, description="step from which Gaussians are no longer grown or pruned")
    reset_every: int = Field(
        3000, ge=0, description="opacities are clamped to reset_opacity every this many steps; 0: never"
    )
    refine_every: int = Field(100, ge=1, description="steps between two growing and pruning passes")
    pause_refine_after_reset: int = Field(
        0, ge=0, description="steps after each opacity reset without growing or pruning (the opacities recover)"
    )
    revised_opacity: bool = Field(
        False, description="a split Gaussian's two children get opacity 1 - sqrt(1 - o) (arXiv:2404.06109), not o"
    )
    reset_opacity: float = Field(
        0.01, gt=0, lt=1, description="opacity the reset clamps to (ours; gsplat uses 2 * prune_opa, the same 0.01)"
    )
    split_factor: float = Field(
        1.6, gt=1, description="a split Gaussian's children have its scales / this (ours; gsplat fixes 1.6)"
    )
    cap_max: int | None = Field(
        300_000,
        ge=1,
        description="Gaussian budget (ours; gsplat's DefaultStrategy has none): growth stops there, the candidates "
        "with the highest gradients first; None: unlimited",
    )


class MCMCStrategyParams(BaseModel):
    """3DGS-as-MCMC (`strategy.MCMCStrategy`) in gsplat 1.5.3 `MCMCStrategy`'s field names, with its hard-coded
    growth rate and the regularisers of gsplat's example trainer (`opacity_reg`, `scale_reg`) as settings."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    kind: Literal["mcmc"] = Field("mcmc", description="3DGS as Markov chain Monte Carlo (gsplat's MCMCStrategy)")
    cap_max: int = Field(
        300_000, ge=1, description="Gaussian budget, filled by growth_rate per refinement (gsplat's default: 1000000)"
    )
    noise_lr: float = Field(5e5, ge=0, description="position noise = means' learning rate * this * Σ ε")
    refine_start_iter: int = Field(500, ge=0, description="step after which dead Gaussians are relocated and added")
    refine_stop_iter: int = Field(25_000, ge=0, description="step from which nothing is relocated, added or noised")
    refine_every: int = Field(100, ge=1, description="steps between two relocation and growth passes")
    min_opacity: float = Field(0.005, gt=0, lt=1, description="opacity at or below which a Gaussian is dead")
    growth_rate: float = Field(
        1.05, gt=1, description="each refinement grows the count to min(cap_max, this * N) (gsplat fixes 1.05)"
    )
    opacity_reg: float = Field(0.01, ge=0, description="weight of the mean opacity in the loss")
    scale_reg: float = Field(0.01, ge=0, description="weight of the mean scale in the loss")


class NoStrategy(BaseModel):
    """No densification: the initial Gaussians are optimised as they are."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    kind: Literal["none"] = Field("none", description="no densification: the initial Gaussians only")


StrategyParams = Annotated[DefaultStrategyParams | MCMCStrategyParams | NoStrategy, Field(discriminator="kind")]


class TrainParams(BaseModel):
    """Splat optimisation. Learning rates are per iteration of Adam; lengths are in normalised-scene units."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    iterations: int = Field(
        7000, ge=0, le=200_000, description="optimisation steps, one training view each (high: 30 000)"
    )
    lr_means: float = Field(1.6e-4, ge=0, description="times scene_scale; decays exponentially")
    lr_means_final_ratio: float = Field(0.01, gt=0, le=1, description="lr_means at the end / at the start")
    lr_quats: float = Field(1e-3, ge=0, description="learning rate of the rotations (quaternions)")
    lr_log_scales: float = Field(5e-3, ge=0, description="learning rate of the log scales")
    lr_logit_opacities: float = Field(5e-2, ge=0, description="learning rate of the logit opacities")
    lr_sh0: float = Field(2.5e-3, ge=0, description="learning rate of the SH band 0 (base colour)")
    lr_shN: float = Field(2.5e-3 / 20, ge=0, description="learning rate of the higher SH bands (3DGS: lr_sh0 / 20)")
    lr_background: float = Field(1e-2, ge=0, description="learning rate of the sky colour or sky map")
    sh_degree: int = Field(3, ge=0, le=3, description="largest SH degree used (the model may store more)")
    sh_degree_interval_iters: int = Field(1000, ge=1, description="active degree += 1 this often")
    loss: LossParams = Field(LossParams(), description="weights and options of the loss terms")
    strategy: StrategyParams = Field(
        DefaultStrategyParams(),
        description="the densification strategy, chosen by `kind` (default, mcmc or none); its fields are "
        "gsplat's own, and its `cap_max` is the Gaussian budget",
    )
    scene_scale: float | None = Field(
        None, gt=0, description="scene extent the lengths above are relative to; None = `auto_scene_scale`"
    )
    background_rgb: tuple[float, float, float] | None = Field(
        None, description="initial background (sky) colour; None = median colour of the sky pixels, else black"
    )
    learn_background: bool = Field(True, description="optimise the sky colour (else it keeps its initial value)")
    sky_map_rows: int = Field(
        0,
        ge=0,
        le=2048,
        description="0: the sky is one colour; else a colour per ray direction, a latitude-longitude map of "
        "this many rows and twice as many columns (`wonderverse.splats.sky`)",
    )
    motion_blur_shutter: float = Field(
        0.0,
        ge=0,
        le=1,
        description="share of the frame interval the video's shutter was open (0.5: a 180° shutter); > 0 smears "
        "each training render along its image motion before the photometric loss (`wonderverse.splats.motion_blur`)",
    )
    motion_blur_samples: int = Field(5, ge=2, le=64, description="points averaged along each pixel's smear")
    motion_blur_max_px: float = Field(32.0, gt=0, description="cap on a smear's length in pixels (a cut, a jump)")
    sky_from_invalid_prior: bool = Field(True, description="treat pixels with an invalid depth prior as sky")
    sky_alpha_weight: float = Field(0.1, ge=0, description="weight of mean alpha over sky pixels")
    holdout_every: int = Field(8, ge=0, description="every Nth view is held out for evaluation; 0 = none")
    checkpoint_every_iters: int = Field(1000, ge=1, description="steps between two resumable checkpoints")
    near: float = Field(0.01, gt=0, description="near clipping depth (normalised-scene units)")
    far: float = Field(1e10, gt=0, description="far clipping depth (normalised-scene units)")
    seed: int = Field(
        0, ge=0, description="seed of the view order and the strategy's random draws (split offsets, relocation, noise)"
    )
    compile_loss: bool = Field(
        True,
        description="on CUDA, fuse the loss and its gradients (`trainer.loss_and_grads`) into a few kernels "
        "with torch.compile and replay them as one CUDA graph (eager when it cannot)",
    )

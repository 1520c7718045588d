"""What the procedural video backend can be told (`scene.video.options` when `scene.video.backend` is
`procedural`): the world's layout, the surface patterns, faults, texture, light, and the defects of real AI
video (`DefectParams`, named levels in `DEFECT_LEVELS`). Imports only pydantic, so the config validates these
options when it is built, and the renderer's modules share them without importing each other.
"""

from __future__ import annotations

from typing import Any, Literal, get_args

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    SerializerFunctionWrapHandler,
    field_validator,
    model_serializer,
    model_validator,
)

Range = tuple[float, float]
# "ignore": the camera follows a smooth, plausible but wrong path (the video model ignored its instruction);
# not among the default `fault_types`, so it is drawn only when forced or listed explicitly.
FaultType = Literal["teleport", "rotation", "morph", "freeze", "ignore"]


class WorldParams(BaseModel):
    """Sizes and counts of the procedural worlds (metres, degrees)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    terrain_radius_m: float = Field(60.0, gt=10, description="half-size of the square terrain")
    terrain_cell_m: float = Field(1.0, gt=0.1, le=5, description="grid spacing of the terrain mesh")
    hill_height_m: float = Field(1.5, ge=0, description="amplitude of the gentle hills")
    hill_wavelength_m: Range = Field((18.0, 45.0), description="the hills' five sinusoids draw wavelengths from this")
    flat_radius_m: float = Field(10.0, ge=0, description="hills fade in from the origin out to here")
    rim_height_m: float = Field(9.0, ge=0, description="skyline hills rising at the terrain's edge")
    rim_start_m: float = Field(42.0, gt=0, description="distance from the origin where the skyline rim starts rising")
    clear_radius_m: float = Field(4.0, ge=0, description="no object intrudes on this disc (camera zone)")
    object_radius_m: Range = Field((5.0, 40.0), description="outdoor objects stand at distances in this range")
    object_gap_m: float = Field(0.6, ge=0, description="free space between object footprints")
    outdoor_objects: int = Field(60, ge=0, le=400, description="objects of a meadow; themes scale it")
    placement_tries: int = Field(60, ge=1, le=10_000, description="rejection-sampling tries per object")
    camera_height_m: float = Field(3.0, gt=0, description="outdoors: the start pose's height above the ground")
    camera_pitch_deg: float = Field(10.0, ge=-60, le=60, description="downwards pitch of the start pose")
    shore_distance_m: float = Field(14.0, gt=0, description="beach: the sea begins this far out")
    shore_drop_m: float = Field(3.5, gt=0, description="beach: how far the ground sinks beyond the shore")
    room_size_m: tuple[float, float, float] = Field(
        (10.0, 12.0, 3.0), description="x, y, z; the camera starts looking along y, the long side"
    )
    wall_thickness_m: float = Field(0.2, gt=0, description="thickness of the room's walls")
    indoor_camera_height_m: float = Field(1.6, gt=0, description="indoors: the start pose's height above the floor")
    indoor_camera_pitch_deg: float = Field(8.0, ge=-60, le=60, description="indoors: downwards pitch of the start pose")
    indoor_clear_radius_m: float = Field(1.5, ge=0, description="indoors: furniture keeps off this disc")
    indoor_objects: int = Field(30, ge=0, le=200, description="pieces of furniture of a room; room types share it out")
    sun_elevation_deg: Range = Field((30.0, 60.0), description="outdoors: the sun's elevation is drawn from this")
    sun_azimuth_deg: Range = Field((100.0, 260.0), description="outdoors: the sun's azimuth is drawn from this")
    indoor_light_elevation_deg: float = Field(65.0, gt=0, le=90, description="indoors: elevation of the main light")
    cylinder_segments: int = Field(12, ge=3, le=64, description="sides of every cylinder and cone (trunks, posts)")


class PatternParams(BaseModel):
    """Sizes of the per-material surface patterns (metres, or fractions of a cell)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    brick_m: Range = Field((0.25, 0.085), description="a brick's width and height")
    mortar_frac: float = Field(0.12, ge=0, lt=0.5, description="share of a brick or shingle cell that is mortar gap")
    plank_width_m: float = Field(0.16, gt=0, description="width of a floor or wall plank")
    plank_length_m: float = Field(1.8, gt=0, description="length of a plank between joints")
    shingle_m: Range = Field((0.32, 0.22), description="a roof shingle's width and height")
    tile_m: float = Field(0.4, gt=0, description="side of a square tile")
    grout_frac: float = Field(0.06, ge=0, lt=0.5, description="share of a tile cell that is grout")
    stripe_m: float = Field(0.11, gt=0, description="width of a wallpaper stripe")
    motif_m: float = Field(0.3, gt=0, description="wallpaper diamonds")
    check_m: float = Field(0.15, gt=0, description="side of a fabric check")
    window_cell_m: Range = Field((2.2, 3.2), description="facades: width and height of the cell holding one window")
    window_frac: Range = Field((0.55, 0.5), description="facades: share of the cell's width, height a window fills")
    lit_window_share: float = Field(0.6, ge=0, le=1, description="at night")
    bark_groove_m: float = Field(0.06, gt=0, description="width of the grooves in bark")
    bark_stretch: float = Field(6.0, gt=1, description="bark streaks are this many times longer than wide")


class DefectParams(BaseModel):
    """The defects of real AI video the procedural backend can add, each independently; every one is off at
    its default (0, None, or 1 for `parallax_scale`). Ground truth stays the truth: poses are the poses
    actually rendered, depth and normals those of the world's own (undeformed) mesh at those poses.

    Metres are native metres of the procedural world (whatever `scene_scale` presents it in). Per-segment
    draws (curves, fields, flicker) are seeded by (scene seed, attempt seed): the same attempt renders the
    same frames, another attempt draws again. The texture-poor choice is the world's own: seeded by the
    scene seed alone, it holds for every segment and attempt of the scene.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    texture_poor_share: float = Field(
        0.0,
        ge=0,
        le=1,
        description="share of surfaces rendered texture-poor (flat albedo, shading only: no noise, no pattern). "
        "It counts surface area on the world's shell (ground, water, walls, floor, ceiling, rug, door: a smooth "
        "field in patches of `texture_poor_patch_m` marks that share of it plain) and parts of objects "
        "(each part - a roof, a trunk, a book - is plain when a hash of scene seed and part falls below the "
        "share). A surface plain at one share stays plain at every larger share",
    )
    texture_poor_patch_m: float = Field(8.0, gt=0, description="size of the plain and textured patches of the shell")
    exposure_drift_stops: float = Field(
        0.0, ge=0, le=3, description="peak exposure change over a segment in stops (1 = twice as bright); 0 at the "
        "first frame, a smooth curve after"
    )  # fmt: skip
    white_balance_drift_frac: float = Field(
        0.0,
        ge=0,
        le=0.5,
        description="peak relative change of one colour channel's gain over a segment (0.05: up to 5 %); the three "
        "gains keep their product 1 (a colour-temperature and tint shift, not a brightness one); 0 at the first "
        "frame, a smooth curve after",
    )
    appearance_drift_cycles: Range = Field(
        (0.25, 1.0), description="the exposure and white-balance curves mix sinusoids of this many cycles per segment"
    )
    detail_flicker_contrast: float = Field(
        0.0,
        ge=0,
        le=2,
        description="strength of fine detail re-drawn every frame, in the texture's contrast units: its standard "
        "deviation as a share of the surface texture's own (0.2: flicker a fifth as strong as the texture)",
    )
    detail_flicker_wavelength_px: float = Field(3.0, ge=1, le=64, description="size of the flickering detail")
    geometric_drift_m: float = Field(
        0.0,
        ge=0,
        description="peak displacement of the world's surfaces along any axis at a segment's last frame; a smooth "
        "field that grows linearly from 0 at the first frame. The frames show the deformed world, ground truth "
        "the undeformed one",
    )
    geometric_drift_wavelength_m: float = Field(15.0, gt=0, description="wavelength of the displacement field")
    blur_sigma_px: float = Field(0.0, ge=0, le=20, description="Gaussian blur: standard deviation in pixels")
    motion_blur_shutter: float = Field(
        0.0,
        ge=0,
        le=1,
        description="motion blur: share of the frame interval the shutter is open (0.5 = a 180° shutter); each "
        "pixel is smeared along its own image motion between the neighbouring frames",
    )
    motion_blur_samples: int = Field(7, ge=2, le=64, description="samples along each pixel's smear")
    motion_blur_max_px: float = Field(32.0, gt=0, description="cap on a smear's length (a jump fault is a cut)")
    jpeg_quality: int | None = Field(
        None, ge=1, le=100, description="JPEG quality every frame is compressed at (libjpeg via Pillow); None = off"
    )
    parallax_scale: float = Field(
        1.0,
        gt=0,
        le=1,
        description="share of the asked camera translation actually rendered, measured from the segment's first "
        "pose; rotation kept (1 = the path as asked)",
    )

    @model_validator(mode="after")
    def _cycles_ok(self) -> DefectParams:
        lo, hi = self.appearance_drift_cycles
        if not 0 < lo <= hi:
            raise ValueError(
                f"appearance_drift_cycles must satisfy 0 < low <= high, got {self.appearance_drift_cycles}"
            )
        return self

    def is_clean(self) -> bool:
        """True when no defect is on (the frames are exactly those without defects)."""
        return self == DefectParams(
            texture_poor_patch_m=self.texture_poor_patch_m,
            appearance_drift_cycles=self.appearance_drift_cycles,
            detail_flicker_wavelength_px=self.detail_flicker_wavelength_px,
            geometric_drift_wavelength_m=self.geometric_drift_wavelength_m,
            motion_blur_samples=self.motion_blur_samples,
            motion_blur_max_px=self.motion_blur_max_px,
        )


# The "ai_like" level: our argued match to today's video models (CogVideoX 1.5, Wan 2.1/2.2, Runway Gen-3), read
# off their published samples and known mechanisms; a judgement, not a measurement of those models here.
# - texture_poor_share 0.35: a latent VAE (8x spatial compression) and the denoiser's prior for clean surfaces
#   turn large plain-ish areas (walls, floors, snow, water, distant ground) into smooth albedo with shading;
#   detail survives where the prompt or the reference frame put it. About a third of the surface, not all.
# - exposure_drift_stops 0.15 (±11 %), white_balance_drift_frac 0.03: generated clips brighten or darken and
#   shift colour slowly over a few seconds, more as they move away from the conditioning frame; a few percent
#   of brightness and colour, no jumps.
# - detail_flicker_contrast 0.2 at 3 px: detail finer than a latent cell is re-synthesised by the decoder for
#   every frame (the "boiling" of grass, gravel, foliage); a fifth of the texture's contrast.
# - geometric_drift_m 0.05 over 15 m: shapes swim by centimetres over a segment (no model is 3D-consistent),
#   smooth, so the check's continuity thresholds (step ratio 3.5, 0.5 rad) are never approached: the per-frame
#   change (2 mm over 25 frames) is a few percent of a typical camera step (5-10 cm).
# - blur_sigma_px 0.5, motion_blur_shutter 0.5: decoders give softer frames than their pixel count, and the
#   models reproduce the 180° shutter motion blur of the footage they learnt from.
# - jpeg_quality 85: clips come as H.264/H.265 MP4 at a few Mbit/s; per-frame JPEG at 85 stands for that
#   codec's blocking and ringing.
# - parallax_scale 0.7: camera-controlled and prompt-driven models under-shoot translation and prefer to turn
#   (less parallax than asked), the failure camera-control papers report.
DefectLevel = Literal["none", "texture_poor", "ai_like"]
DEFECT_LEVELS: dict[str, DefectParams] = {
    "none": DefectParams(),
    "texture_poor": DefectParams(texture_poor_share=0.5),
    "ai_like": DefectParams(
        texture_poor_share=0.35,
        exposure_drift_stops=0.15,
        white_balance_drift_frac=0.03,
        detail_flicker_contrast=0.2,
        geometric_drift_m=0.05,
        blur_sigma_px=0.5,
        motion_blur_shutter=0.5,
        jpeg_quality=85,
        parallax_scale=0.7,
    ),
}


assert tuple(DEFECT_LEVELS) == get_args(DefectLevel), "every level has a name in DefectLevel"


class ProceduralOptions(BaseModel):
    """Everything the procedural video model can be told (`VideoSpec.options`)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    world: Literal["auto", "outdoor", "indoor"] = Field(
        "auto", description="outdoor terrain or a room; auto: whichever the prompt's words name more of"
    )
    layout: WorldParams = WorldParams()
    scene_scale: float = Field(
        1.0,
        gt=0,
        allow_inf_nan=False,
        description="presents the same world with every distance times this factor (1e-3: a 40 m village spans "
        "0.04 units): paths consumed, poses, depth, start pose and fault distances reported; frames are identical "
        "at any scale (layout and fault ranges stay in native metres)",
    )
    patterns: PatternParams = PatternParams()
    # faults (per generation attempt)
    fault_probability: float = Field(0.2, ge=0, le=1, description="chance that a generation attempt gets a fault")
    fault_types: tuple[FaultType, ...] = Field(
        ("teleport", "rotation", "morph", "freeze"),
        min_length=1,
        description="the faults drawn from, with equal chance (`ignore` only when listed or forced)",
    )
    force_fault: FaultType | None = Field(None, description="always inject this fault (tests, benchmarks)")
    fault_window: Range = Field((0.25, 0.75), description="the fault starts in this fraction of the segment")
    teleport_m: Range = Field((0.8, 2.5), description="teleport fault: length of the camera's jump")
    teleport_vertical_share: float = Field(0.3, ge=0, le=1, description="vertical part of a jump, relative")
    sudden_rotation_deg: Range = Field((10.0, 25.0), description="rotation fault: angle of the camera's sudden turn")
    morph_m: Range = Field((0.8, 2.0), description="morph fault: how far the chosen objects move")
    morph_scale: Range = Field((0.7, 1.4), description="morph fault: each moved object is rescaled by this")
    morph_objects: int = Field(3, ge=1, description="morph fault: objects moved, picked among those in view")
    morph_probe_stride_px: int = Field(4, ge=1, description="pixel stride of the pass finding visible objects")
    freeze_frames: int = Field(5, ge=2, description="freeze fault: frames that repeat one frame")
    ignore_min_turn_deg: float = Field(
        5.0, ge=0, description="ignore fault: a planned turn at least this large may be reversed or left out"
    )
    ignore_min_move_m: float = Field(
        0.1, ge=0, description="ignore fault: a planned move at least this long may go another way"
    )
    ignore_move_turn_deg: Range = Field(
        (90.0, 180.0), description="ignore fault: the move's direction is turned about the world up by this much"
    )
    ignore_turn_deg: Range = Field(
        (15.0, 30.0), description="ignore fault: a camera told to stay still turns (yaw) by this much instead"
    )
    # texture
    texture_detail: float = Field(1.0, ge=0, description="contrast of the surface texture; 0 = flat colours")
    texture_octaves: int = Field(4, ge=1, le=8, description="noise octaves of the surface texture")
    octave_gain: float = Field(0.7, gt=0, lt=1, description="amplitude ratio of successive octaves")
    octave_lacunarity: float = Field(2.5, gt=1, description="frequency ratio of octaves; not 2, so they do not line up")
    noise_contrast: float = Field(2.0, gt=0, description="maps the noise sum onto the colour ramp")
    brightness_variation: float = Field(0.3, ge=0, lt=1, description="texture-driven brightness swing")
    lod_fade_px: Range = Field((1.5, 3.0), description="an octave fades out as its wavelength drops to these px")
    min_cos_incidence: float = Field(0.15, gt=0, le=1, description="caps texture blur at grazing angles")
    noise_seed: int = Field(7, ge=0, description="seed of the texture noise (the sky's is this plus 1)")
    chunk_px: int = Field(16384, ge=256, description="pixels shaded at once; small chunks stay in cache")
    shading_threads: int = Field(2, ge=1, le=64, description="threads shading pixel chunks")
    # lighting and atmosphere
    shadows: bool = Field(True, description="sun shadows outdoors")
    shadow_method: Literal["map", "rays"] = Field(
        "map", description="shadow-map lookup (fast) or one shadow ray per pixel (exact reference)"
    )
    shadow_bias_m: float = Field(0.02, gt=0, description="shadow rays start this far off the surface")
    shadow_map_px: int = Field(1024, ge=64, le=8192, description="texels per side of each cascade")
    shadow_near_m: float = Field(20.0, gt=0, description="half-size of the fine cascade around the origin")
    shadow_bias_texels: float = Field(
        1.5, ge=0, description="shadow map: points are pushed this many texels off their surface before the lookup"
    )
    fog_distance_m: float = Field(220.0, ge=0, description="e-folding distance of the haze; 0 = none")
    cloud_height_m: float = Field(800.0, gt=0, description="height of the plane the clouds are drawn on")
    cloud_scale_m: float = Field(500.0, gt=0, description="size of the cloud pattern on that plane")
    cloud_octaves: int = Field(4, ge=1, le=8, description="noise octaves of the clouds")
    sun_disc_cos: float = Field(
        0.9995, gt=0.9, lt=1, description="cosine of the sun disc's angular radius (0.9995: about 1.8°)"
    )
    # the defects of real AI video
    defects: DefectLevel | DefectParams = Field(
        "none",
        description=f"a level name ({', '.join(DEFECT_LEVELS)}) or explicit DefectParams; 'none': today's frames",
    )

    # transient objects
    movers: int = Field(
        0,
        ge=0,
        le=50,
        description="moving people and vehicles per segment (`wonderverse.video.movers`), composited by depth; "
        "gt `movers` holds their per-frame masks and the same clip with 0 is its static truth; 0: none",
    )
    # guided extensions
    accept_guide: bool = Field(
        False,
        description="act as a guided video model (`takes_guide`): with a guide, keep its known pixels and render the "
        "truth where it is unknown, and record its coverage and error against the truth (gt `guide`); false: a guide "
        "is ignored and extensions are generated unguided, as before",
    )

    @model_serializer(mode="wrap")
    def _default_guide_unwritten(self, handler: SerializerFunctionWrapHandler) -> dict[str, Any]:
        """`accept_guide` is written only when true and `movers` only when set, so every cache key made before they
        existed stays the same."""
        data = handler(self)
        if not self.accept_guide:
            data.pop("accept_guide", None)
        if not self.movers:
            data.pop("movers", None)
        return data

    @field_validator("defects", mode="before")
    @classmethod
    def _known_level(cls, v: Any) -> Any:
        """One clear error for an unknown name (the union would add that it is no DefectParams either)."""
        if isinstance(v, str) and v not in DEFECT_LEVELS:
            raise ValueError(f"unknown defect level {v!r}; the levels are {', '.join(DEFECT_LEVELS)}")
        return v

    @model_validator(mode="after")
    def _ranges_ok(self) -> ProceduralOptions:
        for name in (
            "fault_window",
            "teleport_m",
            "sudden_rotation_deg",
            "morph_m",
            "morph_scale",
            "lod_fade_px",
            "ignore_move_turn_deg",
            "ignore_turn_deg",
        ):
            lo, hi = getattr(self, name)
            if not lo <= hi:
                raise ValueError(f"{name}: lower bound {lo} exceeds upper bound {hi}")
        if not 0 <= self.fault_window[0] < self.fault_window[1] <= 1:
            raise ValueError("fault_window must lie within [0, 1]")
        return self


def resolved_defects(opts: ProceduralOptions) -> DefectParams:
    """The DefectParams that `opts.defects` names (a level of DEFECT_LEVELS) or gives."""
    return DEFECT_LEVELS[opts.defects] if isinstance(opts.defects, str) else opts.defects

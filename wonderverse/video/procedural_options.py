"""What the procedural video backend can be told (`scene.video.options` when `scene.video.backend` is
`procedural`): the world's layout, the surface patterns, faults, texture, light. Imports only pydantic, so the
config validates these options when it is built, and the renderer's modules share them without importing
each other.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

Range = tuple[float, float]
FaultType = Literal["teleport", "rotation", "morph", "freeze"]


class WorldParams(BaseModel):
    """Sizes and counts of the procedural worlds (metres, degrees)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    terrain_radius_m: float = Field(60.0, gt=10, description="half-size of the square terrain")
    terrain_cell_m: float = Field(1.0, gt=0.1, le=5)
    hill_height_m: float = Field(1.5, ge=0, description="amplitude of the gentle hills")
    hill_wavelength_m: Range = (18.0, 45.0)
    flat_radius_m: float = Field(10.0, ge=0, description="hills fade in from the origin out to here")
    rim_height_m: float = Field(9.0, ge=0, description="skyline hills rising at the terrain's edge")
    rim_start_m: float = Field(42.0, gt=0)
    clear_radius_m: float = Field(4.0, ge=0, description="no object intrudes on this disc (camera zone)")
    object_radius_m: Range = (5.0, 40.0)
    object_gap_m: float = Field(0.6, ge=0, description="free space between object footprints")
    outdoor_objects: int = Field(60, ge=0, le=400, description="objects of a meadow; themes scale it")
    placement_tries: int = Field(60, ge=1, description="rejection-sampling tries per object")
    camera_height_m: float = Field(3.0, gt=0)
    camera_pitch_deg: float = Field(10.0, ge=-60, le=60, description="downwards pitch of the start pose")
    shore_distance_m: float = Field(14.0, gt=0, description="beach: the sea begins this far out")
    shore_drop_m: float = Field(3.5, gt=0)
    room_size_m: tuple[float, float, float] = Field(
        (10.0, 12.0, 3.0), description="x, y, z; the camera starts looking along y, the long side"
    )
    wall_thickness_m: float = Field(0.2, gt=0)
    indoor_camera_height_m: float = Field(1.6, gt=0)
    indoor_camera_pitch_deg: float = Field(8.0, ge=-60, le=60)
    indoor_clear_radius_m: float = Field(1.5, ge=0)
    indoor_objects: int = Field(30, ge=0, le=200)
    sun_elevation_deg: Range = (30.0, 60.0)
    sun_azimuth_deg: Range = (100.0, 260.0)
    indoor_light_elevation_deg: float = Field(65.0, gt=0, le=90)
    cylinder_segments: int = Field(12, ge=3, le=64)


class PatternParams(BaseModel):
    """Sizes of the per-material surface patterns (metres, or fractions of a cell)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    brick_m: Range = (0.25, 0.085)
    mortar_frac: float = Field(0.12, ge=0, lt=0.5)
    plank_width_m: float = Field(0.16, gt=0)
    plank_length_m: float = Field(1.8, gt=0)
    shingle_m: Range = (0.32, 0.22)
    tile_m: float = Field(0.4, gt=0)
    grout_frac: float = Field(0.06, ge=0, lt=0.5)
    stripe_m: float = Field(0.11, gt=0)
    motif_m: float = Field(0.3, gt=0, description="wallpaper diamonds")
    check_m: float = Field(0.15, gt=0)
    window_cell_m: Range = (2.2, 3.2)
    window_frac: Range = (0.55, 0.5)
    lit_window_share: float = Field(0.6, ge=0, le=1, description="at night")
    bark_groove_m: float = Field(0.06, gt=0)
    bark_stretch: float = Field(6.0, gt=1, description="bark streaks are this many times longer than wide")


class ProceduralOptions(BaseModel):
    """Everything the procedural video model can be told (`VideoSpec.options`)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    world: Literal["auto", "outdoor", "indoor"] = "auto"
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
    fault_probability: float = Field(0.2, ge=0, le=1)
    fault_types: tuple[FaultType, ...] = Field(("teleport", "rotation", "morph", "freeze"), min_length=1)
    force_fault: FaultType | None = Field(None, description="always inject this fault (tests, benchmarks)")
    fault_window: Range = Field((0.25, 0.75), description="the fault starts in this fraction of the segment")
    teleport_m: Range = (0.8, 2.5)
    teleport_vertical_share: float = Field(0.3, ge=0, le=1, description="vertical part of a jump, relative")
    sudden_rotation_deg: Range = (10.0, 25.0)
    morph_m: Range = (0.8, 2.0)
    morph_scale: Range = (0.7, 1.4)
    morph_objects: int = Field(3, ge=1)
    morph_probe_stride_px: int = Field(4, ge=1, description="pixel stride of the pass finding visible objects")
    freeze_frames: int = Field(5, ge=2)
    # texture
    texture_detail: float = Field(1.0, ge=0, description="contrast of the surface texture; 0 = flat colours")
    texture_octaves: int = Field(4, ge=1, le=8)
    octave_gain: float = Field(0.7, gt=0, lt=1, description="amplitude ratio of successive octaves")
    octave_lacunarity: float = Field(2.5, gt=1, description="frequency ratio of octaves; not 2, so they do not line up")
    noise_contrast: float = Field(2.0, gt=0, description="maps the noise sum onto the colour ramp")
    brightness_variation: float = Field(0.3, ge=0, lt=1, description="texture-driven brightness swing")
    lod_fade_px: Range = Field((1.5, 3.0), description="an octave fades out as its wavelength drops to these px")
    min_cos_incidence: float = Field(0.15, gt=0, le=1, description="caps texture blur at grazing angles")
    noise_seed: int = Field(7, ge=0)
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
    shadow_bias_texels: float = Field(1.5, ge=0)
    fog_distance_m: float = Field(220.0, ge=0, description="e-folding distance of the haze; 0 = none")
    cloud_height_m: float = Field(800.0, gt=0)
    cloud_scale_m: float = Field(500.0, gt=0)
    cloud_octaves: int = Field(4, ge=1, le=8)
    sun_disc_cos: float = Field(0.9995, gt=0.9, lt=1)

    @model_validator(mode="after")
    def _ranges_ok(self) -> ProceduralOptions:
        for name in (
            "fault_window",
            "teleport_m",
            "sudden_rotation_deg",
            "morph_m",
            "morph_scale",
            "lod_fade_px",
        ):
            lo, hi = getattr(self, name)
            if not lo <= hi:
                raise ValueError(f"{name}: lower bound {lo} exceeds upper bound {hi}")
        if not 0 <= self.fault_window[0] < self.fault_window[1] <= 1:
            raise ValueError("fault_window must lie within [0, 1]")
        return self

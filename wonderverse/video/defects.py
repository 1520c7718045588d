"""The defects of real AI video, for the procedural renderer (`DefectParams`, levels in `DEFECT_LEVELS`).

Three kinds, by where they act:
- the world's look (`SurfaceLook`): texture-poor surfaces, chosen once per scene from the scene seed, so every
  segment and attempt of a scene shows the same plain walls;
- each frame's look (`FrameLook`, drawn per segment from (scene seed, attempt seed)): exposure and white-balance
  gains, detail that flickers, and the smooth geometric drift of the world's surfaces;
- the finished frames (`degrade_frames`): motion blur along each pixel's image motion, Gaussian blur, JPEG.
`scale_parallax` shrinks the camera's translation. Ground truth is never touched here: the renderer takes depth
and normals from the world's own mesh at the poses it really rendered.

Drifts (exposure, white balance, geometry) are 0 at a segment's first frame, as an image-to-video model starts
from its conditioning frame, and change smoothly after. Vectors are (3,n) as in texture.py.
"""

from __future__ import annotations

import io
from dataclasses import dataclass

import numpy as np

from wonderverse.camera import camera_centers
from wonderverse.video.procedural_options import DefectParams, Range
from wonderverse.video.texture import Noise, smoothstep
from wonderverse.video.world import World

# Separate the defects' random streams from the faults' (FAULT_STREAM) and from each other.
WORLD_STREAM = 0xDEF0
SEGMENT_STREAM = 0xDEF1
DENSE_SAMPLES = 257  # the drift curves are normalised on this many points of [0, 1]
NOISE_CDF_SAMPLES = 1 << 16  # value-noise samples that map a share onto a threshold
PATCH_BLEND = 0.02  # half-width, in noise units, of the fade between a plain and a textured patch
MIN_CURVE_SPAN = 0.5  # a drift curve's peak is at least this share of its sinusoids' summed weights
# white balance moves along colour temperature (red against blue) and tint (green against magenta): zero-sum
# directions, so that the three gains keep their product
WB_AXES = np.array([[1.0, 0.0, -1.0], [-1.0, 2.0, -1.0]]) / np.array([[np.sqrt(2.0)], [np.sqrt(6.0)]])


# ---------------------------------------------------------------- the world's look: texture-poor surfaces


@dataclass(frozen=True)
class SurfaceLook:
    """Which surfaces render texture-poor. part_plain (P,) float32 per part: 1 plain, 0 textured, -1 a part of
    the shell (ground, water, walls, floor, ceiling), decided per point by `field`: plain where the field at
    tex / patch_m lies below `threshold` (the `share` quantile of the field's values), fading over PATCH_BLEND."""

    share: float
    part_plain: np.ndarray
    field: Noise
    inv_patch_m: float
    threshold: float

    def plain_weight(self, tex: np.ndarray, part: np.ndarray) -> np.ndarray | None:
        """(n,) float32 in [0,1]: how plain each hit is (1 = flat albedo), from texture-space points tex (3,n)
        in metres and part ids (n,); None when no hit is plain."""
        w = self.part_plain.take(part)
        shell = np.flatnonzero(w < 0)
        if len(shell):
            if self.share >= 1.0:
                w[shell] = 1.0
            else:
                f = self.field.at(tex.take(shell, axis=1) * np.float32(self.inv_patch_m))
                w[shell] = smoothstep(self.threshold + PATCH_BLEND, self.threshold - PATCH_BLEND, f)
        return w if w.any() else None


def surface_look(world: World, scene_seed: int, params: DefectParams) -> SurfaceLook | None:
    """The texture-poor surfaces of the scene (cached on the world), or None when `texture_poor_share` is 0.

    The share counts area on the shell (tri_object 0: one part per wall, floor, ground) through a smooth field,
    so that large surfaces are plain in about that share of their area, and parts of objects one by one (each
    plain when its uniform draw falls below the share). Draws come from SeedSequence([WORLD_STREAM, scene_seed])
    alone, so they do not depend on the share: a surface plain at one share is plain at every larger one."""
    share = params.texture_poor_share
    if share <= 0:
        return None
    key = ("texture_poor", scene_seed, share, params.texture_poor_patch_m)
    if key not in world.cache:
        rng = np.random.default_rng(np.random.SeedSequence([WORLD_STREAM, scene_seed]))
        field = Noise(int(rng.integers(2**31)))
        n_parts = int(world.tri_part.max()) + 1
        draw = rng.random(n_parts)
        part_object = np.zeros(n_parts, dtype=np.int64)
        part_object[world.tri_part] = world.tri_object
        plain = np.where(draw < share, 1.0, 0.0)
        plain[part_object == 0] = -1.0
        world.cache[key] = SurfaceLook(
            share=share,
            part_plain=plain.astype(np.float32),
            field=field,
            inv_patch_m=1.0 / params.texture_poor_patch_m,
            threshold=_noise_quantile(field, share),
        )
    return world.cache[key]


def _noise_quantile(noise: Noise, share: float) -> float:
    """The value below which `share` of the noise's values lie (from NOISE_CDF_SAMPLES seeded samples)."""
    if share >= 1.0:
        return float("inf")
    p = np.random.default_rng(0).uniform(-500.0, 500.0, (3, NOISE_CDF_SAMPLES)).astype(np.float32)
    return float(np.quantile(noise.at(p), share))


# ---------------------------------------------------------------- each frame's look


@dataclass(frozen=True)
class DriftField:
    """A smooth displacement field, unit(p) (3,n) per component in [-1, 1] at world points p (3,n) metres:
    value noise of wavelength `1 / inv_wavelength_m`, one independent lattice per axis."""

    noise: Noise
    inv_wavelength_m: float
    offsets: np.ndarray  # (3,3) float32: lattice offset of each axis' noise

    def unit(self, p: np.ndarray) -> np.ndarray:
        q = p * np.float32(self.inv_wavelength_m)
        return np.stack([np.float32(2.0) * self.noise.at(q + self.offsets[a][:, None]) for a in range(3)])

    def displacement(self, p: np.ndarray, amount_m: float) -> np.ndarray:
        """(3,n) float32 displacement at points p (3,n) when the drift has grown to `amount_m`."""
        return self.unit(p) * np.float32(amount_m)


@dataclass(frozen=True)
class FrameLook:
    """One frame's defects. gain (3,) float32 RGB multiplier of the shaded colour (exposure x white balance),
    None for 1. flicker: the noise that re-draws fine detail this frame, with its amplitude (contrast units),
    inverse wavelength (1/px) and lattice offset (3,); None for none. drift_m: how far the geometric drift has
    grown (native metres; the field `SegmentDefects.drift` gives its shape)."""

    gain: np.ndarray | None = None
    flicker: Noise | None = None
    flicker_contrast: float = 0.0
    flicker_inv_px: float = 0.0
    flicker_offset: np.ndarray | None = None
    drift_m: float = 0.0

    def detail(self, pixel_u: np.ndarray, pixel_v: np.ndarray, octaves: int, octave_gain: float) -> np.ndarray | None:
        """(n,) float32 detail added to the texture's noise sum at pixel centres (u, v), or None: one noise
        layer of the flicker's wavelength, whose standard deviation is `flicker_contrast` times that of the
        texture's sum of `octaves` layers of amplitude ratio `octave_gain` at full detail (independent layers:
        the sum's deviation is the layer's times 2 sqrt(sum a^2) / sum a, as `Noise.fbm` scales it)."""
        if self.flicker is None or self.flicker_offset is None:
            return None
        s = np.float32(self.flicker_inv_px)
        o = self.flicker_offset
        q = np.stack([pixel_u * s + o[0], pixel_v * s + o[1], np.full_like(pixel_u, o[2])])
        amps = octave_gain ** np.arange(octaves)
        out = self.flicker.at(q)
        out *= np.float32(2.0 * self.flicker_contrast * np.sqrt((amps**2).sum()) / amps.sum())
        return out


@dataclass(frozen=True)
class SegmentDefects:
    """The per-frame defects of one generation attempt (`frames`, one FrameLook each) and the shape of its
    geometric drift (None without). exposure_stops (T,) and wb_gain (T,3) are what the frames were given."""

    frames: list[FrameLook]
    drift: DriftField | None
    exposure_stops: np.ndarray
    wb_gain: np.ndarray


def smooth_curves(
    rng: np.random.Generator, n_frames: int, n_curves: int, cycles: Range
) -> tuple[np.ndarray, np.ndarray]:
    """Smooth curves over a segment: their values (n_curves, n_frames) at the frames (t = i / (T - 1)) and
    (n_curves, DENSE_SAMPLES) over the segment's duration (t in [0, 1]); each is 0 at t = 0 and its peak |value|
    over the duration is 1.

    Each is w1 (sin(2 pi f1 t + p1) - sin p1) + w2 (...) with f in `cycles` (cycles per segment), normalised;
    draws whose peak is below MIN_CURVE_SPAN of |w1| + |w2| are drawn again, so |dg/dt| <= 4 pi max(cycles)."""
    t_dense = np.linspace(0.0, 1.0, DENSE_SAMPLES)
    t = np.linspace(0.0, 1.0, n_frames) if n_frames > 1 else np.zeros(1)
    at_frames, dense = np.zeros((n_curves, len(t))), np.zeros((n_curves, DENSE_SAMPLES))

    def g(tt: np.ndarray, f: np.ndarray, phase: np.ndarray, w: np.ndarray) -> np.ndarray:
        arg = 2 * np.pi * f[:, None] * tt[None] + phase[:, None]
        return (w[:, None] * (np.sin(arg) - np.sin(phase)[:, None])).sum(axis=0)

    for c in range(n_curves):
        for _try in range(100):
            f = rng.uniform(*cycles, size=2)
            phase = rng.uniform(0.0, 2 * np.pi, size=2)
            w = rng.uniform(0.5, 1.0, size=2) * rng.choice([-1.0, 1.0], size=2)
            curve = g(t_dense, f, phase, w)
            peak = np.abs(curve).max()
            if peak >= MIN_CURVE_SPAN * np.abs(w).sum():
                break
        at_frames[c], dense[c] = g(t, f, phase, w) / peak, curve / peak
    return at_frames, dense


def plan_segment(params: DefectParams, scene_seed: int, seed: int, n_frames: int) -> SegmentDefects:
    """The per-frame defects of attempt `seed` of a segment of n_frames, drawn from
    SeedSequence([SEGMENT_STREAM, scene_seed, seed]); every draw is made whatever is switched on, so turning one
    defect on or off never changes another's draw."""
    rng = np.random.default_rng(np.random.SeedSequence([SEGMENT_STREAM, scene_seed, seed]))
    curves, dense = smooth_curves(rng, n_frames, 3, params.appearance_drift_cycles)
    exposure = params.exposure_drift_stops * curves[0]
    # zero-sum log-gain directions (T,3), scaled so that the largest channel change over the segment's duration
    # is exactly white_balance_drift_frac
    wb_dir = curves[1:].T @ WB_AXES
    peak = np.abs(dense[1:].T @ WB_AXES).max()
    wb_log = wb_dir * (np.log1p(params.white_balance_drift_frac) / peak)
    wb_gain = np.exp(wb_log)
    flicker_noise = Noise(int(rng.integers(2**31)))
    flicker_offsets = rng.uniform(-1000.0, 1000.0, (n_frames, 3)).astype(np.float32)
    drift_noise = Noise(int(rng.integers(2**31)))
    drift_offsets = rng.uniform(-1000.0, 1000.0, (3, 3)).astype(np.float32)
    t = np.linspace(0.0, 1.0, n_frames) if n_frames > 1 else np.zeros(1)

    appearance = params.exposure_drift_stops > 0 or params.white_balance_drift_frac > 0
    flicker = params.detail_flicker_contrast > 0
    frames = []
    for i in range(n_frames):
        gain = (np.exp2(exposure[i]) * wb_gain[i]).astype(np.float32) if appearance else None
        frames.append(
            FrameLook(
                gain=gain,
                flicker=flicker_noise if flicker else None,
                flicker_contrast=params.detail_flicker_contrast,
                flicker_inv_px=1.0 / params.detail_flicker_wavelength_px,
                flicker_offset=flicker_offsets[i] if flicker else None,
                drift_m=float(params.geometric_drift_m * t[i]),
            )
        )
    drift = (
        DriftField(drift_noise, 1.0 / params.geometric_drift_wavelength_m, drift_offsets)
        if params.geometric_drift_m > 0
        else None
    )
    return SegmentDefects(frames, drift, exposure, wb_gain)


# ---------------------------------------------------------------- the camera: low parallax


def scale_parallax(poses: np.ndarray, scale: float) -> np.ndarray:
    """W2C poses (T,4,4) whose camera centres moved `scale` times as far from the first one as in `poses`,
    rotations kept; `poses` itself when scale is 1."""
    if scale == 1.0:
        return poses
    c = camera_centers(poses)
    c = c[0] + scale * (c - c[0])
    out = np.array(poses, dtype=np.float64, copy=True)
    out[1:, :3, 3] = -np.einsum("tij,tj->ti", out[1:, :3, :3], c[1:])
    return out


# ---------------------------------------------------------------- the finished frames


def image_motion(depth: np.ndarray, w2c: np.ndarray, other: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(H,W,2) float32 pixel displacement (du, dv) of what each pixel of a view (camera-z depth (H,W), +inf for
    sky: a direction) shows, from pose w2c to pose `other` (W2C); 0 where it falls behind the other camera."""
    h, w = depth.shape
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)
    finite = np.isfinite(depth)
    z = np.where(finite, depth, 0.0)[..., None]
    R, t, R2, t2 = w2c[:3, :3], w2c[:3, 3], other[:3, :3], other[:3, 3]
    world = np.where(finite[..., None], (rays * z - t) @ R, rays @ R)  # R^T (x - t), or R^T d for sky
    cam = world @ R2.T + np.where(finite[..., None], t2, 0.0)
    zc = cam[..., 2]
    ok = zc > 1e-9
    zs = np.where(ok, zc, 1.0)
    du = np.where(ok, K[0, 0] * cam[..., 0] / zs + K[0, 1] * cam[..., 1] / zs + K[0, 2] - u, 0.0)
    dv = np.where(ok, K[1, 1] * cam[..., 1] / zs + K[1, 2] - v, 0.0)
    return np.stack([du, dv], axis=-1).astype(np.float32)


def motion_blur(frame: np.ndarray, flow: np.ndarray, shutter: float, samples: int, max_px: float) -> np.ndarray:
    """(H,W,3) float32: the frame (H,W,3) averaged over `samples` points along shutter x flow (H,W,2 pixels per
    frame interval), centred on each pixel, the smear capped at max_px; bilinear, edges clamped."""
    smear = flow * np.float32(shutter)
    length = np.linalg.norm(smear, axis=-1, keepdims=True)
    smear *= np.minimum(1.0, max_px / np.maximum(length, 1e-9)).astype(np.float32)
    h, w = frame.shape[:2]
    rows, cols = np.meshgrid(np.arange(h, dtype=np.float32), np.arange(w, dtype=np.float32), indexing="ij")
    # bilinear gathers from a copy padded by one row and column, so the corner (r0+1, c0+1) always exists
    src = np.pad(frame.astype(np.float32), ((0, 1), (0, 1), (0, 0)), mode="edge").reshape(-1, 3)
    stride = w + 1
    out = np.zeros((h * w, 3), dtype=np.float32)
    for s in np.linspace(-0.5, 0.5, samples, dtype=np.float32):
        r = np.clip(rows + s * smear[..., 1], 0, h - 1).ravel()
        c = np.clip(cols + s * smear[..., 0], 0, w - 1).ravel()
        r0, c0 = np.floor(r), np.floor(c)
        fr, fc = (r - r0)[:, None], (c - c0)[:, None]
        i00 = r0.astype(np.int32) * stride + c0.astype(np.int32)
        top = src.take(i00, axis=0)
        top += (src.take(i00 + 1, axis=0) - top) * fc
        bottom = src.take(i00 + stride, axis=0)
        bottom += (src.take(i00 + stride + 1, axis=0) - bottom) * fc
        top += (bottom - top) * fr
        out += top
    out *= np.float32(1.0 / samples)
    return out.reshape(h, w, 3)


def jpeg(frame: np.ndarray, quality: int) -> np.ndarray:
    """(H,W,3) uint8 frame after a JPEG round trip at `quality` (Pillow's libjpeg, 4:2:0 chroma)."""
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(frame).save(buf, format="JPEG", quality=int(quality))
    buf.seek(0)
    with Image.open(buf) as im:
        return np.asarray(im.convert("RGB"), dtype=np.uint8).copy()


def degrade_frames(
    frames: np.ndarray, depth: np.ndarray, poses: np.ndarray, K: np.ndarray, params: DefectParams
) -> np.ndarray:
    """Frames (T,H,W,3) uint8 after motion blur (from the rendered poses (T,4,4) W2C and depth (T,H,W) camera z,
    one unit for both), Gaussian blur and JPEG, in that order; the input itself when all three are off.

    Each pixel's motion per frame interval is half the displacement from the previous to the next frame (one
    side at the ends); frames that repeat their neighbours' pose (a freeze) get none."""
    blur = params.motion_blur_shutter > 0 and len(frames) > 1
    if not blur and params.blur_sigma_px <= 0 and params.jpeg_quality is None:
        return frames
    out = np.empty_like(frames)
    T = len(frames)
    for i in range(T):
        img: np.ndarray = frames[i]
        if blur or params.blur_sigma_px > 0:
            work = img.astype(np.float32)
            if blur:
                a, b = max(i - 1, 0), min(i + 1, T - 1)
                flow = image_motion(depth[i], poses[i], poses[b], K) - image_motion(depth[i], poses[i], poses[a], K)
                flow /= np.float32(b - a)
                work = motion_blur(work, flow, params.motion_blur_shutter, params.motion_blur_samples,
                                   params.motion_blur_max_px)  # fmt: skip
            if params.blur_sigma_px > 0:
                from scipy.ndimage import gaussian_filter

                work = gaussian_filter(work, sigma=(params.blur_sigma_px, params.blur_sigma_px, 0), mode="nearest")
            img = np.clip(work + 0.5, 0, 255).astype(np.uint8)
        if params.jpeg_quality is not None:
            img = jpeg(np.ascontiguousarray(img), params.jpeg_quality)
        out[i] = img
    return out

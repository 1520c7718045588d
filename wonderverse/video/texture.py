"""Surface and sky colours of the procedural renderer: solid 3D value noise, material patterns, light.

Everything here maps world-space hit points (not pixels) to colours, so a surface looks the same
from every view; detail finer than a pixel fades out (level of detail) instead of shimmering.
Arrays are float32 and processed in pixel chunks by the caller.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from wonderverse.video.world import MATERIALS, Pattern, World

if TYPE_CHECKING:
    from wonderverse.video.procedural import ProceduralOptions

Range = tuple[float, float]


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


# int32 multipliers of the lattice hash (odd, large, unrelated)
_HX, _HY, _HZ, _HMIX = (
    np.int32(-1640531535),
    np.int32(-2048144777),
    np.int32(-1028477379),
    np.int32(668265263),
)
_TO_UNIT = np.float32(2.0**-24)


class Noise:
    """Value noise on a hashed integer lattice, 3D, float32; pure arithmetic (no tables, no period)."""

    def __init__(self, seed: int) -> None:
        self.salt = np.int32(((seed * 0x27D4EB2D) ^ 0x165667B1) & 0x7FFFFFFF)

    def __call__(self, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Smooth noise in [-0.5, 0.5) at float32 coordinates in lattice units (one cell = one unit)."""
        fx, fy, fz = np.floor(x), np.floor(y), np.floor(z)
        tx, ty, tz = x - fx, y - fy, z - fz
        ix = fx.astype(np.int32)
        ix += self.salt  # added, not xor-ed, so that corner ix + 1 of one cell is corner ix of the next
        iy, iz = fy.astype(np.int32), fz.astype(np.int32)
        iy1, iz1 = iy + 1, iz + 1
        x0 = ix * _HX
        x1 = x0 + _HX
        sx, sy, sz = _smooth01(tx), _smooth01(ty), _smooth01(tz)
        c = []
        for xx in (x0, x1):
            for yy in (iy, iy1):
                xy = xx ^ yy
                xy *= _HY  # chained multiply-xor (FNV-like): every axis reaches every bit
                c.append(_lerp_(_corner(xy ^ iz), _corner(xy ^ iz1), sz))
        out = _lerp_(_lerp_(c[0], c[1], sy), _lerp_(c[2], c[3], sy), sx)
        out *= _TO_UNIT
        return out

    def hash(self, *ints: np.ndarray) -> np.ndarray:
        """A value in [0, 1) per integer tuple (cell ids, part ids): constant over each cell."""
        h = np.full(np.shape(ints[0]), self.salt, dtype=np.int32)
        for i in ints:
            h ^= np.asarray(i, dtype=np.int32)
            h *= _HMIX
            h ^= h >> 15
            h *= _HX
        return (h >> 8).astype(np.float32) * _TO_UNIT + np.float32(0.5)

    def fbm(self, q: np.ndarray, footprint: np.ndarray, octaves: int, opts: ProceduralOptions) -> np.ndarray:
        """Sum of `octaves` noise layers at q (n,3) lattice units, roughly in [-1, 1].

        footprint (n,) is the pixel's size in lattice units. An octave whose wavelength falls below
        `lod_fade_px` pixels fades to its mean and is not evaluated (no shimmer, and less work far away).
        """
        lo, hi = opts.lod_fade_px
        out = np.zeros(len(q), dtype=np.float32)
        inv_fp = np.float32(1.0) / np.maximum(footprint, np.float32(1e-6))
        freq, amp, norm = 1.0, 1.0, 0.0
        for i in range(octaves):
            w = np.clip((inv_fp * np.float32(1.0 / freq) - lo) * np.float32(1.0 / (hi - lo)), 0.0, 1.0)
            norm += amp
            sel = np.flatnonzero(w > 0)
            if len(sel) == 0:
                break
            off = np.float32(17.31 * (i + 1))
            f = np.float32(freq)
            if len(sel) == len(q):
                n = self(q[:, 0] * f + off, q[:, 1] * f - off, q[:, 2] * f + 2 * off)
                out += np.float32(2 * amp) * w * n
            else:
                qs = q.take(sel, axis=0)
                n = self(qs[:, 0] * f + off, qs[:, 1] * f - off, qs[:, 2] * f + 2 * off)
                out[sel] += np.float32(2 * amp) * w.take(sel) * n
            freq *= opts.octave_lacunarity
            amp *= opts.octave_gain
        out *= np.float32(1.0 / norm)
        return out


def _corner(h: np.ndarray) -> np.ndarray:
    """Lattice value of a combined corner key h (int32, consumed): signed float in [-2^23, 2^23)."""
    h *= _HZ
    u = h.view(np.uint32)  # logical shift for the xorshift
    u ^= u >> 15
    h *= _HMIX
    h >>= 8
    return h.astype(np.float32)


def _lerp_(a: np.ndarray, b: np.ndarray, t: np.ndarray) -> np.ndarray:
    """a + t (b - a), reusing b's memory."""
    b -= a
    b *= t
    b += a
    return b


def _smooth01(t: np.ndarray) -> np.ndarray:
    return t * t * (np.float32(3.0) - np.float32(2.0) * t)


# Small products written out by hand: numpy's matmul hands (n,3)@(3,3) to a threaded BLAS, which
# is 30x slower than this when the cores are shared.
def dot3(a: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(n,) rows of a (n,3) dotted with one vector v (3,)."""
    return a[:, 0] * v[0] + a[:, 1] * v[1] + a[:, 2] * v[2]


def rowdot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(n,) row-wise dot products of two (n,3) arrays."""
    return a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1] + a[:, 2] * b[:, 2]


def rotate(a: np.ndarray, M: np.ndarray) -> np.ndarray:
    """(n,3) rows of a (n,3) multiplied by a 3x3 matrix: a @ M.T."""
    out = np.empty_like(a)
    for j in range(3):
        out[:, j] = dot3(a, M[j])
    return out


def lerp(a: np.ndarray, b: np.ndarray, t: np.ndarray) -> np.ndarray:
    return a + t * (b - a)


def smoothstep(a: float, b: float, x: np.ndarray) -> np.ndarray:
    t = np.clip((x - np.float32(a)) * np.float32(1.0 / (b - a)), 0.0, 1.0)
    return _smooth01(t)


_PATTERN = np.array([m[0] for m in MATERIALS.values()], dtype=np.int8)
_INV_SCALE = np.array([1.0 / m[1] for m in MATERIALS.values()], dtype=np.float32)
_CONTRAST = np.array([m[2] for m in MATERIALS.values()], dtype=np.float32)
_JITTER = np.array([m[3] for m in MATERIALS.values()], dtype=np.float32)


@dataclass(frozen=True)
class PartTables:
    """Per-part (primitive) look-up tables, so a pixel needs one index: colours with the part's own
    tint folded in (P,3), inverse texture scale (P,), texture gain (P,) and pattern (P,)."""

    color_a: np.ndarray
    color_b: np.ndarray
    inv_scale: np.ndarray
    gain: np.ndarray
    pattern: np.ndarray


def part_tables(world: World, opts: ProceduralOptions, noise: Noise) -> PartTables:
    """The world's PartTables (cached on the world)."""
    key = ("parts", opts.noise_contrast, opts.texture_detail)
    if key not in world.cache:
        n_parts = int(world.tri_part.max()) + 1
        mat = np.zeros(n_parts, dtype=np.int64)
        mat[world.tri_part] = world.tri_material
        ids = np.arange(n_parts, dtype=np.int32)
        h = np.stack([noise.hash(ids, np.full_like(ids, c)) for c in range(3)], axis=1)
        tint = np.clip(1.0 + _JITTER[mat][:, None] * 1.2 * (h - 0.5), 0.15, 2.0).astype(np.float32)
        world.cache[key] = PartTables(
            color_a=world.colors_a[mat] * tint,
            color_b=world.colors_b[mat] * tint,
            inv_scale=_INV_SCALE[mat],
            gain=(opts.noise_contrast * opts.texture_detail * _CONTRAST[mat]).astype(np.float32),
            pattern=_PATTERN[mat],
        )
    return world.cache[key]


def surface_colour(
    world: World,
    opts: ProceduralOptions,
    noise: Noise,
    sunlight: Any,
    points: np.ndarray,
    tex: np.ndarray,
    n_geo: np.ndarray,
    n_face: np.ndarray,
    dist: np.ndarray,
    footprint: np.ndarray,
    tri: np.ndarray,
) -> np.ndarray:
    """RGB (n,3) float32 of surface hits: palette x solid texture x pattern, lit by sky and sun, hazed.

    points: world hit points; tex: texture-space points (metres); n_geo: geometric normals (winding),
    n_face: the same turned towards the camera; dist: ray length (m); footprint: pixel size on the
    surface (m); sunlight(points, normals) -> (n,) share of the sun reaching them, or None (no shadows).
    """
    tables = part_tables(world, opts, noise)
    part = world.tri_part.take(tri)
    inv_scale = tables.inv_scale.take(part)
    fbm = noise.fbm(tex * inv_scale[:, None], footprint * inv_scale, opts.texture_octaves, opts)
    ramp = np.clip(np.float32(0.5) + tables.gain.take(part) * fbm, 0.0, 1.0)
    col = lerp(tables.color_a.take(part, axis=0), tables.color_b.take(part, axis=0), ramp[:, None])
    # brightness follows the ramp too: palettes of similar greys still give SIFT some contrast
    bv = opts.brightness_variation
    col *= (np.float32(1.0 - bv) + np.float32(2 * bv) * ramp)[:, None]
    pattern = tables.pattern.take(part)
    present = np.flatnonzero(np.bincount(pattern, minlength=len(Pattern)))
    for pat in present:
        if pat == Pattern.NOISE or pat == Pattern.EMISSIVE:
            continue
        sel = np.flatnonzero(pattern == pat)
        args = (
            tex.take(sel, axis=0),
            n_geo.take(sel, axis=0),
            ramp.take(sel),
            footprint.take(sel),
            part.take(sel),
        )
        col[sel] = _pattern(Pattern(int(pat)), col.take(sel, axis=0), *args, world, opts, noise)

    sky = world.sky
    sun = sky.sun_dir.astype(np.float32)
    lam = np.maximum(dot3(n_face, sun), 0.0)
    if sunlight is not None:
        lit = np.flatnonzero(lam > 0)
        if len(lit):
            lam[lit] *= sunlight(points.take(lit, axis=0), n_face.take(lit, axis=0))
    # ambient light from the sky is stronger on faces turned up; the sun adds where it is not shadowed
    ambient = np.float32(sky.ambient) * (np.float32(0.8) + np.float32(0.2) * n_face[:, 2])
    light = ambient[:, None] + (np.float32(sky.sun_strength) * lam)[:, None] * sky.sun_color.astype(np.float32)
    if Pattern.EMISSIVE in present:  # lamps and lit windows shine by themselves
        light[pattern == Pattern.EMISSIVE] = 1.0
    col *= light
    if opts.fog_distance_m > 0 and world.kind == "outdoor":
        haze = (1.0 - np.exp(-dist * np.float32(1.0 / opts.fog_distance_m)))[:, None]
        col = lerp(col, sky.horizon.astype(np.float32), haze)
    return col


def _tangent_u(p: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Horizontal coordinate along a wall: p on the horizontal tangent of the geometric normal."""
    tx, ty = -n[:, 1], n[:, 0]
    norm = np.sqrt(tx * tx + ty * ty)
    inv = np.float32(1.0) / np.maximum(norm, np.float32(1e-6))
    return np.where(norm < 0.3, p[:, 0], (p[:, 0] * tx + p[:, 1] * ty) * inv)  # near-flat faces: use x


def _fade(cell_m: float, footprint: np.ndarray, opts: ProceduralOptions) -> np.ndarray:
    """(n,1): 1 while a pattern cell spans enough pixels, fading to 0 as it nears a pixel (no moiré)."""
    lo, hi = opts.lod_fade_px
    return np.clip((np.float32(cell_m) / footprint - 2 * lo) * np.float32(1.0 / (2 * hi - 2 * lo)), 0.0, 1.0)[:, None]


def _modulate(col: np.ndarray, shade: np.ndarray, fade: np.ndarray) -> np.ndarray:
    return col * (np.float32(1.0) + fade * (shade - np.float32(1.0)))


def _pattern(
    pat: Pattern,
    col: np.ndarray,
    p: np.ndarray,
    n: np.ndarray,
    ramp: np.ndarray,
    footprint: np.ndarray,
    part: np.ndarray,
    world: World,
    opts: ProceduralOptions,
    noise: Noise,
) -> np.ndarray:
    """Colour (n,3) of the pixels of one pattern; p are texture-space points (m), n geometric normals."""
    pp = opts.patterns
    vertical = np.abs(n[:, 2]) < 0.7
    u = _tangent_u(p, n)
    v = np.where(vertical, p[:, 2], p[:, 1])  # up a wall, or across a floor
    if pat in (Pattern.BRICK, Pattern.TILES, Pattern.ROOF):
        if pat == Pattern.TILES:
            cw = ch = pp.tile_m
            gap, stagger = pp.grout_frac, 0.0
        else:
            (cw, ch), gap, stagger = (
                (pp.brick_m if pat == Pattern.BRICK else pp.shingle_m),
                pp.mortar_frac,
                0.5,
            )
        row = np.floor(v * np.float32(1 / ch))
        uu = u * np.float32(1 / cw) + np.float32(stagger) * (row % 2)
        cell = np.floor(uu)
        joint = ((v * np.float32(1 / ch) - row) < gap) | ((uu - cell) < gap * ch / cw)
        tint = np.float32(0.8) + np.float32(0.4) * noise.hash(row.astype(np.int32), cell.astype(np.int32))
        shade = np.where(joint, np.float32(0.5 if pat == Pattern.ROOF else 1.3), tint)[:, None]
        return _modulate(col, shade, _fade(min(cw, ch), footprint, opts))
    if pat == Pattern.PLANKS:
        across = np.where(vertical, u, p[:, 1])
        along = np.where(vertical, p[:, 2], p[:, 0])
        plank = np.floor(across * np.float32(1 / pp.plank_width_m))
        pid = plank.astype(np.int32)
        seg = np.floor(along * np.float32(1 / pp.plank_length_m) + noise.hash(pid)).astype(np.int32)
        tint = np.float32(0.75) + np.float32(0.5) * noise.hash(pid, seg)
        grain = noise(along * np.float32(1.5), across * np.float32(40.0), plank)
        gap = (across * np.float32(1 / pp.plank_width_m) - plank) < 0.06
        shade = np.where(gap, np.float32(0.45), tint * (np.float32(1.0) + grain))[:, None]
        return _modulate(col, shade, _fade(pp.plank_width_m, footprint, opts))
    if pat == Pattern.BARK:
        q = p * np.float32(1.0 / pp.bark_groove_m)
        streak = noise(q[:, 0], q[:, 1], q[:, 2] * np.float32(1.0 / pp.bark_stretch))
        shade = np.float32(0.45) + np.float32(0.6) * smoothstep(-0.2, -0.05, streak)[:, None]
        return _modulate(col, shade, _fade(pp.bark_groove_m, footprint, opts))
    if pat in (Pattern.LEAVES, Pattern.GRASS):
        # sharpen the ramp into clumps: dark gaps between bright leaf or grass patches
        k = 0.35 if pat == Pattern.LEAVES else 0.2
        return col * (np.float32(0.65) + np.float32(0.55) * smoothstep(0.5 - k, 0.5 + k, ramp)[:, None])
    if pat == Pattern.WATER:
        ripple = noise(p[:, 0] * np.float32(0.8), p[:, 1] * np.float32(3.0), p[:, 2])[:, None]
        f = _fade(0.3, footprint, opts)
        return col * (np.float32(1.0) + np.float32(0.5) * ripple * f) + np.float32(0.08) * f * (ripple > 0.2)
    if pat == Pattern.FABRIC:
        inv = np.float32(1.0 / pp.check_m)
        check = (np.floor(u * inv) + np.floor(v * inv)) % 2
        stripe = np.floor(u * inv * 4) % 2
        shade = (np.float32(0.75) + np.float32(0.35) * check + np.float32(0.03) * stripe)[:, None]
        return _modulate(col, shade, _fade(pp.check_m * 0.5, footprint, opts))
    if pat == Pattern.WALLPAPER:
        stripe = np.floor(u * np.float32(1.0 / pp.stripe_m)) % 2
        mu, mv = u * np.float32(1.0 / pp.motif_m), v * np.float32(1.0 / pp.motif_m)
        cu, cv = np.floor(mu), np.floor(mv)
        diamond = (np.abs(mu - cu - 0.5) + np.abs(mv - cv - 0.5)) < 0.22
        tint = noise.hash(cu.astype(np.int32), cv.astype(np.int32))
        shade = np.float32(0.9) + np.float32(0.1) * stripe - diamond * (np.float32(0.15) + np.float32(0.3) * tint)
        return _modulate(col, shade[:, None], _fade(pp.stripe_m * 0.5, footprint, opts))
    if pat == Pattern.FACADE:
        (cw, ch), (fw, fh) = pp.window_cell_m, pp.window_frac
        fu, fv = u / np.float32(cw), v / np.float32(ch)
        iu, iv = np.floor(fu), np.floor(fv)
        win = vertical & (np.abs(fu - iu - 0.5) < fw / 2) & (np.abs(fv - iv - 0.5) < fh / 2)
        glass = np.array([0.12, 0.16, 0.22], dtype=np.float32) * (np.float32(0.7) + np.float32(0.6) * ramp[:, None])
        if world.night:  # lit windows; bright enough to stay bright under the dim night light
            lit = noise.hash(iu.astype(np.int32), iv.astype(np.int32)) < pp.lit_window_share
            glass = np.where(lit[:, None], np.array([1.6, 1.35, 0.8], dtype=np.float32), glass)
        return np.where(win[:, None], lerp(col, glass, _fade(cw * 0.3, footprint, opts)), col)
    if pat == Pattern.PAINTING:
        phase = noise.hash(part)[:, None] * np.float32(6.283)
        hue = ramp[:, None] * np.float32(9.0) + phase + np.array([0.0, 2.1, 4.2], dtype=np.float32)
        return np.float32(0.5) + np.float32(0.45) * np.cos(hue)
    return col


def sky_colour(world: World, opts: ProceduralOptions, noise: Noise, d: np.ndarray, fx: float) -> np.ndarray:
    """RGB (n,3) float32 of rays (world directions d) that hit nothing: gradient, clouds, sun."""
    sky = world.sky
    d = d / np.sqrt(rowdot(d, d))[:, None]
    e = d[:, 2]
    horizon, zenith = sky.horizon.astype(np.float32), sky.zenith.astype(np.float32)
    col = lerp(horizon, zenith, smoothstep(0.0, 0.6, e)[:, None])
    col[e < 0] = horizon * np.float32(0.92)
    up = np.flatnonzero(e > 0.02)
    if len(up) and sky.cloud_cover > 0:
        # clouds live on a plane `cloud_height_m` up; seen edge-on they fade into the haze
        eu = e.take(up)
        rel = np.float32(opts.cloud_height_m / opts.cloud_scale_m)
        reach = rel / eu
        q = np.stack([d[up, 0] * reach, d[up, 1] * reach, np.zeros_like(eu)], axis=1)
        footprint = rel / np.float32(fx) / (eu * eu)
        n = noise.fbm(q, footprint, opts.cloud_octaves, opts)
        cover = smoothstep(1.0 - 2 * sky.cloud_cover, 1.3 - 2 * sky.cloud_cover, 0.5 + n) * smoothstep(0.02, 0.2, eu)
        shade = (np.float32(0.82) + np.float32(0.3) * n)[:, None] * sky.cloud.astype(np.float32)
        col[up] = lerp(col[up], shade, (np.float32(0.92) * cover)[:, None])
    if not world.night and world.kind == "outdoor":
        cs = dot3(d, sky.sun_dir.astype(np.float32))
        disc = smoothstep(opts.sun_disc_cos, 1.0 - (1.0 - opts.sun_disc_cos) * 0.3, cs)
        glow = np.maximum(cs, 0.0) ** 16 * np.float32(0.25)
        col = col + (disc + glow)[:, None] * sky.sun_color.astype(np.float32)
    return col

"""Surface and sky colours of the procedural renderer: solid 3D value noise, material patterns, light.

Everything here maps world-space hit points (not pixels) to colours, so a surface looks the same
from every view; detail finer than a pixel fades out (level of detail) instead of shimmering.
Arrays are float32 and processed in pixel chunks by the caller. Vectors are stored by component,
(3,n) rather than (n,3): numpy then runs every operation over n contiguous values, where an (n,3)
array broadcast against a colour runs loops of length 3, about ten times slower.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property
from typing import Protocol

import numpy as np

from wonderverse.video.procedural_options import ProceduralOptions
from wonderverse.video.world import MATERIALS, Pattern, World


class PlainSurfaces(Protocol):
    """Which surface hits render texture-poor (`defects.SurfaceLook` is one; declared here so that this module,
    which `defects` builds on, needs nothing of it)."""

    def plain_weight(self, tex: np.ndarray, part: np.ndarray) -> np.ndarray | None:
        """(n,) float32 in [0,1], 1 = flat albedo, for texture-space points tex (3,n) and part ids (n,); None
        when no hit is plain."""


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
        return self.at(np.stack([x, y, z]))

    def at(self, p: np.ndarray) -> np.ndarray:
        """Smooth noise in [-0.5, 0.5) at float32 points p (3,n) in lattice units (one cell = one unit).

        Each step runs once over all axes or all 8 cell corners ((2,2,2,n) arrays, [x][y][z]), in
        place where it can: fewer numpy calls, and less fresh memory to fault in."""
        n = p.shape[1]
        cell = np.floor(p)
        s = p - cell
        t2 = s * s
        s *= np.float32(-2.0)
        s += np.float32(3.0)
        s *= t2  # smoothstep t * t * (3 - 2 t)
        ii = np.empty((3, 2, n), dtype=np.int32)  # corner indices [axis][low, high]
        ii[:, 0] = cell
        np.add(ii[:, 0], 1, out=ii[:, 1])
        ii[0] += self.salt  # added, not xor-ed, so that corner ix + 1 of one cell is corner ix of the next
        ii[0] *= _HX
        h = np.empty((2, 2, 2, n), dtype=np.int32)
        xy = np.bitwise_xor(ii[0][:, None], ii[1][None], out=h[:, :, 0])
        xy *= _HY  # chained multiply-xor (FNV-like): every axis reaches every bit
        np.bitwise_xor(xy, ii[2][1], out=h[:, :, 1])
        xy ^= ii[2][0]
        c = _corner(h)
        c = _lerp_(c[:, :, 0], c[:, :, 1], s[2])
        c = _lerp_(c[:, 0], c[:, 1], s[1])
        out = _lerp_(c[0], c[1], s[0])
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
        """Sum of `octaves` noise layers at q (3,n) lattice units, roughly in [-1, 1].

        footprint (n,) is the pixel's size in lattice units. An octave whose wavelength falls below
        `lod_fade_px` pixels fades to its mean and is not evaluated (no shimmer, and less work far away).
        """
        lo, hi = opts.lod_fade_px
        out = np.zeros(q.shape[1], dtype=np.float32)
        inv_fp = np.float32(1.0) / np.maximum(footprint, np.float32(1e-6))
        # The points still evaluated (`active`, None = all) only shrink from octave to octave: an octave
        # that is too fine for a pixel is too fine for the next, finer one too.
        active: np.ndarray | None = None
        freq, amp, norm = 1.0, 1.0, 0.0
        for i in range(octaves):
            w = np.clip((inv_fp * np.float32(1.0 / freq) - lo) * np.float32(1.0 / (hi - lo)), 0.0, 1.0)
            norm += amp
            keep = np.flatnonzero(w > 0)
            if len(keep) == 0:
                break
            if len(keep) < len(w):
                q, inv_fp, w = q.take(keep, axis=1), inv_fp.take(keep), w.take(keep)
                active = keep if active is None else active.take(keep)
            off = np.float32(17.31 * (i + 1))
            n = self.at(q * np.float32(freq) + np.array([[off], [-off], [2 * off]], dtype=np.float32))
            n *= np.float32(2 * amp) * w
            if active is None:
                out += n
            else:
                out[active] += n
            freq *= opts.octave_lacunarity
            amp *= opts.octave_gain
        out *= np.float32(1.0 / norm)
        return out


def _corner(h: np.ndarray) -> np.ndarray:
    """Lattice value of a combined corner key h (int32, consumed): signed float in [-2^23, 2^23)."""
    h *= _HZ
    u = h.view(np.uint32)  # logical shift for the xorshift
    tmp = u >> 15
    u ^= tmp
    h *= _HMIX
    h >>= 8
    out = tmp.view(np.float32)  # the shift's memory, reused
    out[...] = h
    return out


def _lerp_(a: np.ndarray, b: np.ndarray, t: np.ndarray) -> np.ndarray:
    """a + t (b - a), reusing b's memory."""
    b -= a
    b *= t
    b += a
    return b


def _smooth01(t: np.ndarray) -> np.ndarray:
    return t * t * (np.float32(3.0) - np.float32(2.0) * t)


# Small products written out by hand: numpy's matmul hands them to a threaded BLAS, which is 30x
# slower than this when the cores are shared. Vectors are (3,n): a[0] is every x.
def dot3(a: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(n,) vectors a (3,n) dotted with one vector v (3,)."""
    return a[0] * v[0] + a[1] * v[1] + a[2] * v[2]


def rowdot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(n,) dot products of the vectors of two (3,n) arrays."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def rotate(a: np.ndarray, M: np.ndarray) -> np.ndarray:
    """(3,n) vectors a (3,n) multiplied by a 3x3 matrix: M @ a."""
    out = np.empty(a.shape, dtype=np.result_type(a, M))
    for j in range(3):
        out[j] = dot3(a, M[j])
    return out


def lerp(a: np.ndarray, b: np.ndarray, t: np.ndarray) -> np.ndarray:
    return a + t * (b - a)


def smoothstep(a: float, b: float, x: np.ndarray) -> np.ndarray:
    t = np.clip((x - np.float32(a)) * np.float32(1.0 / (b - a)), 0.0, 1.0)
    return _smooth01(t)


@dataclass(frozen=True)
class Sunlight:
    """share(points, normals) -> (n,) float32 share of the sun reaching world points (3,n) whose
    camera-facing normals are (3,n). cheap: looking it up at every point costs less than gathering
    the points that face the sun first."""

    share: Callable[[np.ndarray, np.ndarray], np.ndarray]
    cheap: bool


_PATTERN = np.array([m[0] for m in MATERIALS.values()], dtype=np.int8)
_INV_SCALE = np.array([1.0 / m[1] for m in MATERIALS.values()], dtype=np.float32)
_CONTRAST = np.array([m[2] for m in MATERIALS.values()], dtype=np.float32)
_JITTER = np.array([m[3] for m in MATERIALS.values()], dtype=np.float32)


@dataclass(frozen=True)
class PartTables:
    """Per-part (primitive) look-up tables, so a pixel needs one index: colours with the part's own
    tint folded in (3,P), inverse texture scale (P,), texture gain (P,) and pattern (P,)."""

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
            color_a=np.ascontiguousarray((world.colors_a[mat] * tint).T),
            color_b=np.ascontiguousarray((world.colors_b[mat] * tint).T),
            inv_scale=_INV_SCALE[mat],
            gain=(opts.noise_contrast * opts.texture_detail * _CONTRAST[mat]).astype(np.float32),
            pattern=_PATTERN[mat],
        )
    return world.cache[key]


def surface_colour(
    world: World,
    opts: ProceduralOptions,
    noise: Noise,
    sunlight: Sunlight | None,
    points: np.ndarray,
    tex: np.ndarray,
    n_geo: np.ndarray,
    n_face: np.ndarray,
    dist: np.ndarray,
    footprint: np.ndarray,
    tri: np.ndarray,
    look: PlainSurfaces | None = None,
    detail: np.ndarray | None = None,
) -> np.ndarray:
    """RGB (3,n) float32 of surface hits: palette x solid texture x pattern, lit by sky and sun, hazed.

    points (3,n): world hit points; tex (3,n): texture-space points (metres); n_geo (3,n): geometric
    normals (winding), n_face: the same turned towards the camera; dist: ray length (m); footprint:
    pixel size on the surface (m); sunlight: the share of the sun reaching them, or None (no shadows).
    look: which surfaces are texture-poor (their colour is the palette's mid colour, then lit), None for
    none; detail (n,): added to the texture's noise sum (flickering detail), None for none.
    """
    tables = part_tables(world, opts, noise)
    part = world.tri_part.take(tri)
    inv_scale = tables.inv_scale.take(part)
    fbm = noise.fbm(tex * inv_scale, footprint * inv_scale, opts.texture_octaves, opts)
    if detail is not None:
        fbm += detail
    ramp = np.clip(np.float32(0.5) + tables.gain.take(part) * fbm, 0.0, 1.0)
    col = lerp(tables.color_a.take(part, axis=1), tables.color_b.take(part, axis=1), ramp)
    # brightness follows the ramp too: palettes of similar greys still give SIFT some contrast
    bv = opts.brightness_variation
    col *= np.float32(1.0 - bv) + np.float32(2 * bv) * ramp
    pattern = tables.pattern.take(part)
    counts = np.bincount(pattern, minlength=len(Pattern))
    present = [Pattern(int(i)) for i in np.flatnonzero(counts)]
    for pat in present:
        if pat == Pattern.NOISE or pat == Pattern.EMISSIVE:
            continue
        sel = None if counts[pat] == len(pattern) else np.flatnonzero(pattern == pat)
        px = _Pixels(sel, col=col, p=tex, n=n_geo, ramp=ramp, footprint=footprint, part=part)
        shaded = _pattern(pat, px, world, opts, noise)
        if sel is None:  # one pattern over the whole chunk: no gather, no scatter
            col = shaded
        else:
            for c in range(3):
                col[c][sel] = shaded[c]
    plain = None if look is None else look.plain_weight(tex, part)
    if plain is not None:  # texture-poor: flat albedo (the ramp's middle: no noise, no pattern), shading kept
        flat = lerp(tables.color_a.take(part, axis=1), tables.color_b.take(part, axis=1), np.float32(0.5))
        col += plain * (flat - col)

    sky = world.sky
    sun = sky.sun_dir.astype(np.float32)
    lam = np.maximum(dot3(n_face, sun), 0.0)
    if sunlight is not None:
        lit = np.flatnonzero(lam > 0)
        if len(lit) == len(lam) or (len(lit) and sunlight.cheap):  # lam is 0 where the sun is not looked up
            lam *= sunlight.share(points, n_face)
        elif len(lit):
            lam[lit] *= sunlight.share(points.take(lit, axis=1), n_face.take(lit, axis=1))
    # ambient light from the sky is stronger on faces turned up; the sun adds where it is not shadowed
    ambient = np.float32(sky.ambient) * (np.float32(0.8) + np.float32(0.2) * n_face[2])
    sun_lam = np.float32(sky.sun_strength) * lam
    sun_color = sky.sun_color.astype(np.float32)
    emissive = pattern == Pattern.EMISSIVE if Pattern.EMISSIVE in present else None
    for c in range(3):
        light = ambient + sun_lam * sun_color[c]
        if emissive is not None:  # lamps and lit windows shine by themselves
            light[emissive] = 1.0
        col[c] *= light
    if opts.fog_distance_m > 0 and world.kind == "outdoor":
        haze = np.float32(1.0) - np.exp(-dist * np.float32(1.0 / opts.fog_distance_m))
        horizon = sky.horizon.astype(np.float32)
        for c in range(3):  # lerp(col, horizon, haze) in place
            col[c] += haze * (horizon[c] - col[c])
    return col


def _tangent_u(p: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Horizontal coordinate along a wall: p (3,n) on the horizontal tangent of the geometric normal."""
    tx, ty = -n[1], n[0]
    norm = np.sqrt(tx * tx + ty * ty)
    inv = np.float32(1.0) / np.maximum(norm, np.float32(1e-6))
    return np.where(norm < 0.3, p[0], (p[0] * tx + p[1] * ty) * inv)  # near-flat faces: use x


def _fade(cell_m: float, footprint: np.ndarray, opts: ProceduralOptions) -> np.ndarray:
    """(n,): 1 while a pattern cell spans enough pixels, fading to 0 as it nears a pixel (no moiré)."""
    lo, hi = opts.lod_fade_px
    return np.clip((np.float32(cell_m) / footprint - 2 * lo) * np.float32(1.0 / (2 * hi - 2 * lo)), 0.0, 1.0)


def _modulate(col: np.ndarray, shade: np.ndarray, fade: np.ndarray) -> np.ndarray:
    return col * (np.float32(1.0) + fade * (shade - np.float32(1.0)))


class _Pixels:
    """The pixels of one pattern (`sel` of a chunk's, or all of them when None): the chunk's arrays,
    gathered on first use, so that a pattern pays only for what it reads. col (3,n) colours so far,
    p (3,n) texture-space points (m), n (3,n) geometric normals, ramp, footprint, part (n,)."""

    def __init__(self, sel: np.ndarray | None, **arrays: np.ndarray) -> None:
        self._sel, self._arrays = sel, arrays

    def __getattr__(self, name: str) -> np.ndarray:
        if name.startswith("_") or name not in self._arrays:
            raise AttributeError(name)
        a = self._arrays[name]
        a = a if self._sel is None else a.take(self._sel, axis=-1)
        setattr(self, name, a)
        return a

    @cached_property
    def vertical(self) -> np.ndarray:
        return np.abs(self.n[2]) < 0.7

    @cached_property
    def u(self) -> np.ndarray:
        return _tangent_u(self.p, self.n)

    @cached_property
    def v(self) -> np.ndarray:
        return np.where(self.vertical, self.p[2], self.p[1])  # up a wall, or across a floor


def _pattern(pat: Pattern, px: _Pixels, world: World, opts: ProceduralOptions, noise: Noise) -> np.ndarray:
    """Colour (3,n) of the pixels `px` of one pattern."""
    pp = opts.patterns
    if pat in (Pattern.BRICK, Pattern.TILES, Pattern.ROOF):
        u, v = px.u, px.v
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
        shade = np.where(joint, np.float32(0.5 if pat == Pattern.ROOF else 1.3), tint)
        return _modulate(px.col, shade, _fade(min(cw, ch), px.footprint, opts))
    if pat == Pattern.PLANKS:
        p, vertical = px.p, px.vertical
        across = np.where(vertical, px.u, p[1])
        along = np.where(vertical, p[2], p[0])
        plank = np.floor(across * np.float32(1 / pp.plank_width_m))
        pid = plank.astype(np.int32)
        seg = np.floor(along * np.float32(1 / pp.plank_length_m) + noise.hash(pid)).astype(np.int32)
        tint = np.float32(0.75) + np.float32(0.5) * noise.hash(pid, seg)
        grain = noise(along * np.float32(1.5), across * np.float32(40.0), plank)
        gap = (across * np.float32(1 / pp.plank_width_m) - plank) < 0.06
        shade = np.where(gap, np.float32(0.45), tint * (np.float32(1.0) + grain))
        return _modulate(px.col, shade, _fade(pp.plank_width_m, px.footprint, opts))
    if pat == Pattern.BARK:
        q = px.p * np.float32(1.0 / pp.bark_groove_m)
        streak = noise(q[0], q[1], q[2] * np.float32(1.0 / pp.bark_stretch))
        shade = np.float32(0.45) + np.float32(0.6) * smoothstep(-0.2, -0.05, streak)
        return _modulate(px.col, shade, _fade(pp.bark_groove_m, px.footprint, opts))
    if pat in (Pattern.LEAVES, Pattern.GRASS):
        # sharpen the ramp into clumps: dark gaps between bright leaf or grass patches
        k = 0.35 if pat == Pattern.LEAVES else 0.2
        return px.col * (np.float32(0.65) + np.float32(0.55) * smoothstep(0.5 - k, 0.5 + k, px.ramp))
    if pat == Pattern.WATER:
        p = px.p
        ripple = noise(p[0] * np.float32(0.8), p[1] * np.float32(3.0), p[2])
        f = _fade(0.3, px.footprint, opts)
        return px.col * (np.float32(1.0) + np.float32(0.5) * ripple * f) + np.float32(0.08) * f * (ripple > 0.2)
    if pat == Pattern.FABRIC:
        u, v = px.u, px.v
        inv = np.float32(1.0 / pp.check_m)
        check = (np.floor(u * inv) + np.floor(v * inv)) % 2
        stripe = np.floor(u * inv * 4) % 2
        shade = np.float32(0.75) + np.float32(0.35) * check + np.float32(0.03) * stripe
        return _modulate(px.col, shade, _fade(pp.check_m * 0.5, px.footprint, opts))
    if pat == Pattern.WALLPAPER:
        u, v = px.u, px.v
        stripe = np.floor(u * np.float32(1.0 / pp.stripe_m)) % 2
        mu, mv = u * np.float32(1.0 / pp.motif_m), v * np.float32(1.0 / pp.motif_m)
        cu, cv = np.floor(mu), np.floor(mv)
        diamond = (np.abs(mu - cu - 0.5) + np.abs(mv - cv - 0.5)) < 0.22
        tint = noise.hash(cu.astype(np.int32), cv.astype(np.int32))
        shade = np.float32(0.9) + np.float32(0.1) * stripe - diamond * (np.float32(0.15) + np.float32(0.3) * tint)
        return _modulate(px.col, shade, _fade(pp.stripe_m * 0.5, px.footprint, opts))
    if pat == Pattern.FACADE:
        (cw, ch), (fw, fh) = pp.window_cell_m, pp.window_frac
        fu, fv = px.u / np.float32(cw), px.v / np.float32(ch)
        iu, iv = np.floor(fu), np.floor(fv)
        win = px.vertical & (np.abs(fu - iu - 0.5) < fw / 2) & (np.abs(fv - iv - 0.5) < fh / 2)
        glass = np.array([[0.12], [0.16], [0.22]], dtype=np.float32) * (np.float32(0.7) + np.float32(0.6) * px.ramp)
        if world.night:  # lit windows; bright enough to stay bright under the dim night light
            lit = noise.hash(iu.astype(np.int32), iv.astype(np.int32)) < pp.lit_window_share
            glass = np.where(lit, np.array([[1.6], [1.35], [0.8]], dtype=np.float32), glass)
        return np.where(win, lerp(px.col, glass, _fade(cw * 0.3, px.footprint, opts)), px.col)
    if pat == Pattern.PAINTING:
        phase = noise.hash(px.part) * np.float32(6.283)
        hue = (px.ramp * np.float32(9.0) + phase) + np.array([[0.0], [2.1], [4.2]], dtype=np.float32)
        return np.float32(0.5) + np.float32(0.45) * np.cos(hue)
    return px.col


def sky_colour(world: World, opts: ProceduralOptions, noise: Noise, d: np.ndarray, fx: float) -> np.ndarray:
    """RGB (3,n) float32 of rays (world directions d (3,n)) that hit nothing: gradient, clouds, sun."""
    sky = world.sky
    d = d / np.sqrt(rowdot(d, d))
    e = d[2]
    horizon, zenith = sky.horizon.astype(np.float32)[:, None], sky.zenith.astype(np.float32)[:, None]
    col = lerp(horizon, zenith, smoothstep(0.0, 0.6, e))
    col[:, e < 0] = horizon * np.float32(0.92)
    up = np.flatnonzero(e > 0.02)
    if len(up) and sky.cloud_cover > 0:
        # clouds live on a plane `cloud_height_m` up; seen edge-on they fade into the haze
        eu = e.take(up)
        rel = np.float32(opts.cloud_height_m / opts.cloud_scale_m)
        reach = rel / eu
        q = np.stack([d[0].take(up) * reach, d[1].take(up) * reach, np.zeros_like(eu)])
        footprint = rel / np.float32(fx) / (eu * eu)
        n = noise.fbm(q, footprint, opts.cloud_octaves, opts)
        cover = smoothstep(1.0 - 2 * sky.cloud_cover, 1.3 - 2 * sky.cloud_cover, 0.5 + n) * smoothstep(0.02, 0.2, eu)
        shade = (np.float32(0.82) + np.float32(0.3) * n) * sky.cloud.astype(np.float32)[:, None]
        col[:, up] = lerp(col.take(up, axis=1), shade, np.float32(0.92) * cover)
    if not world.night and world.kind == "outdoor":
        cs = dot3(d, sky.sun_dir.astype(np.float32))
        disc = smoothstep(opts.sun_disc_cos, 1.0 - (1.0 - opts.sun_disc_cos) * 0.3, cs)
        glow = np.maximum(cs, 0.0) ** 16 * np.float32(0.25)
        col = col + (disc + glow) * sky.sun_color.astype(np.float32)[:, None]
    return col

"""Sun shadows from shadow maps: the static world is ray-cast once from the sun's side, and each
pixel then looks its shadow up instead of tracing a ray (a table lookup instead of a BVH walk).

Two cascades: a fine map around the origin, where the camera travels, and a coarse one over the
whole world. Maps are orthographic along the sun direction s, with axes e1, e2 across it; a texel
holds the height (along s) of the first surface the sunlight meets.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from wonderverse.video.texture import dot3


@dataclass(frozen=True)
class ShadowMap:
    """One orthographic cascade. heights (n,n) float32: occluder height along `sun`, -inf where the
    light passes; texel (i, j) covers e1 coordinate u0 + (j + 0.5) * texel_m, e2 likewise with v0."""

    sun: np.ndarray
    e1: np.ndarray
    e2: np.ndarray
    u0: float
    v0: float
    texel_m: float
    heights: np.ndarray

    def light(self, points: np.ndarray, normals: np.ndarray, bias_texels: float) -> tuple[np.ndarray, np.ndarray]:
        """(lit, inside) at points and normals (3,n): lit (n,) float32 in [0,1] is the share of sunlight
        reaching each point (bilinear over 4 texels, so shadow edges are soft rather than stair-stepped),
        inside (n,) bool says which points the map covers (the others read as lit). Each point is first
        pushed off its surface along its camera-facing normal and towards the sun by `bias_texels`
        texels, so that a surface does not shadow itself."""
        n = self.heights.shape[0]
        bias = np.float32(bias_texels * self.texel_m)
        p = points + normals * bias
        inv = np.float32(1.0 / self.texel_m)
        u = (dot3(p, self.e1) - np.float32(self.u0)) * inv - np.float32(0.5)
        v = (dot3(p, self.e2) - np.float32(self.v0)) * inv - np.float32(0.5)
        h = dot3(p, self.sun) + bias
        iu, iv = np.floor(u), np.floor(v)
        fu, fv = u - iu, v - iv
        iu, iv = iu.astype(np.int32), iv.astype(np.int32)
        inside = (iu >= 0) & (iv >= 0) & (iu < n - 1) & (iv < n - 1)
        # clamped in place (np.clip's wrapper costs more than the work at these sizes)
        np.minimum(np.maximum(iv, 0, out=iv), n - 2, out=iv)
        np.minimum(np.maximum(iu, 0, out=iu), n - 2, out=iu)
        idx = iv
        idx *= np.int32(n)
        idx += iu
        flat = self.heights.ravel()
        gu, gv = np.float32(1.0) - fu, np.float32(1.0) - fv
        lit = (gu * gv) * (h >= flat.take(idx))
        lit += (fu * gv) * (h >= flat.take(idx + 1))
        idx += np.int32(n)
        lit += (gu * fv) * (h >= flat.take(idx))
        lit += (fu * fv) * (h >= flat.take(idx + 1))
        lit[~inside] = 1.0
        return lit, inside


def _basis(sun: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    helper = np.array([0.0, 0.0, 1.0]) if abs(sun[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = np.cross(helper, sun)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(sun, e1)


def build_shadow_map(
    scene: Any, sun: np.ndarray, box_min: np.ndarray, box_max: np.ndarray, top: float, resolution: int
) -> ShadowMap:
    """Ray-cast `scene` along -sun over the axis-aligned box [box_min, box_max] (world metres); rays
    start at height `top` along the sun direction, above everything that can cast a shadow."""
    import open3d as o3d

    sun = np.asarray(sun, dtype=np.float64) / np.linalg.norm(sun)
    e1, e2 = _basis(sun)
    corners = np.array([[x, y, z] for x in (box_min[0], box_max[0]) for y in (box_min[1], box_max[1])
                        for z in (box_min[2], box_max[2])])  # fmt: skip
    pu, pv = corners @ e1, corners @ e2
    u0, v0 = pu.min(), pv.min()
    texel = max(pu.max() - u0, pv.max() - v0) / resolution
    jj, ii = np.meshgrid(np.arange(resolution) + 0.5, np.arange(resolution) + 0.5)
    origins = (u0 + jj.ravel()[:, None] * texel) * e1 + (v0 + ii.ravel()[:, None] * texel) * e2 + top * sun
    rays = np.empty((len(origins), 6), dtype=np.float32)
    rays[:, :3] = origins
    rays[:, 3:] = -sun
    t = scene.cast_rays(o3d.core.Tensor.from_numpy(rays))["t_hit"].numpy()
    heights = np.where(np.isfinite(t), top - t, -np.inf).astype(np.float32).reshape(resolution, resolution)
    f32 = np.float32
    return ShadowMap(sun.astype(f32), e1.astype(f32), e2.astype(f32), float(u0), float(v0), float(texel), heights)


@dataclass(frozen=True)
class Cascades:
    """A fine map near the origin and a coarse one over everything; `light` picks per point."""

    near: ShadowMap
    far: ShadowMap

    def light(self, points: np.ndarray, normals: np.ndarray, bias_texels: float) -> np.ndarray:
        """(n,) float32 sunlight share at world points (3,n) with camera-facing normals (3,n): the fine map
        wherever it reaches, the coarse one elsewhere."""
        lit, inside = self.near.light(points, normals, bias_texels)
        out = np.flatnonzero(~inside)
        if len(out):
            lit[out] = self.far.light(points.take(out, axis=1), normals.take(out, axis=1), bias_texels)[0]
        return lit


def build_cascades(scene: Any, sun: np.ndarray, vertices: np.ndarray, near_half_m: float, resolution: int) -> Cascades:
    """Both cascades of a world whose mesh has `vertices` (V,3)."""
    lo, hi = vertices.min(axis=0).astype(np.float64), vertices.max(axis=0).astype(np.float64)
    top = float(dot3(vertices.T, np.asarray(sun, dtype=np.float32)).max()) + 1.0
    near_lo = np.array([-near_half_m, -near_half_m, lo[2]])
    near_hi = np.array([near_half_m, near_half_m, hi[2]])
    return Cascades(
        build_shadow_map(scene, sun, near_lo, near_hi, top, resolution),
        build_shadow_map(scene, sun, lo, hi, top, resolution),
    )

"""TSDF fusion of depth + colour views (Open3D's voxel block grids), a volume that can be stored and fused into again.

Conventions as in `wonderverse.mesh`: rgb (H,W,3) uint8 or float in [0,1]; depth (H,W) camera z in world units,
+inf, NaN or <= 0 for "nothing here" (never integrated: it neither adds surface nor carves free space); K (3,3)
pixels, centres at +0.5; W2C (4,4) OpenCV axes. Lengths follow the extent given: voxel = voxel_frac * extent;
depths up to max_depth_frac * extent go to a fine volume, farther ones (up to far_depth_frac * extent, or all) to
a coarse one with far_voxel_scale times the voxel.

A fusion's state (`TsdfFusion.state`: each volume as Open3D's own .npz bytes, with the extent) is what an extended
scene fuses its new views into (`TsdfFusion.from_state`), so an extension costs its new views, not the world's.
Marching cubes runs over the whole volume; its vertices and triangles come out in one canonical order (sorted),
whatever order Open3D's parallel hash map holds its blocks in, so the same volume always gives the same mesh.
"""

from __future__ import annotations

import tempfile
from collections.abc import Iterable, Sequence, Sized
from pathlib import Path
from typing import Any

import numpy as np

from wonderverse.mesh import MeshParams, TriMesh, clean_mesh
from wonderverse.progress import ProgressFn, no_progress

BLOCK_RESOLUTION = 8
MIN_WEIGHT = 0.5  # marching cubes over voxels seen at least once
VOLUMES = ("near", "far")


class TsdfFusion:
    """Accumulates views in sparse voxel block grids (only the seen space costs memory): a fine one for depths up
    to `max_depth` and, beyond it up to `far_depth`, a coarse one; `extract` runs marching cubes on both."""

    def __init__(self, extent: float, params: MeshParams | None = None):
        if not (extent > 0 and np.isfinite(extent)):
            raise ValueError(f"scene extent must be a positive finite length, got {extent}")
        self.params = params or MeshParams()
        self.extent = float(extent)
        self.voxel = self.params.voxel_frac * self.extent
        self.max_depth = self.params.max_depth_frac * self.extent
        self.far_depth = self.params.reach_frac * self.extent
        voxels = {"near": self.voxel}
        if self.far_depth > self.max_depth:
            voxels["far"] = self.voxel * self.params.far_voxel_scale
        self._volumes = {name: _grid(v) for name, v in voxels.items()}
        self.views = 0
        self.pixels = 0

    def integrate(self, rgb: np.ndarray, depth: np.ndarray, K: np.ndarray, w2c: np.ndarray) -> int:
        """Fuse one view; returns the number of depth pixels used (0: the view was skipped)."""
        import open3d as o3d
        import open3d.core as o3c

        depth = np.asarray(depth, np.float32)
        h, w = depth.shape
        if np.shape(rgb)[:2] != (h, w):
            raise ValueError(f"rgb {np.shape(rgb)} and depth {depth.shape} differ in size")
        if not np.isfinite(w2c).all():
            return 0
        with np.errstate(invalid="ignore"):
            ok = np.isfinite(depth) & (depth > 0)
            near = ok & (depth <= self.max_depth)
            far = ok & ~near & (depth <= self.far_depth)
        n = int(near.sum() + far.sum())
        if n == 0:
            return 0
        rgb = np.asarray(rgb)
        colour = rgb[..., :3].astype(np.float32) / 255.0 if rgb.dtype == np.uint8 else np.clip(rgb[..., :3], 0, 1)
        color = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(colour, np.float32)))
        # the voxel grid samples the depth pixel a projection falls in (its floor): centres at +0.5, as ours are
        intrinsic = o3c.Tensor(np.ascontiguousarray(K, np.float64))
        extrinsic = o3c.Tensor(np.ascontiguousarray(w2c, np.float64))
        for name, mask in (("near", near), ("far", far)):
            grid = self._volumes.get(name)
            if grid is None or not mask.any():
                continue
            d = np.where(mask, depth, 0.0).astype(np.float32)  # Open3D reads depth 0 as "no measurement"
            image = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(d)))
            reach = float(d.max()) * 1.001
            trunc = float(self.params.trunc_voxels)
            try:
                blocks = grid.compute_unique_block_coordinates(image, intrinsic, extrinsic, 1.0, reach, trunc)
            except RuntimeError:  # Open3D's way of saying the few pixels touch no block (it samples the image)
                continue
            grid.integrate(blocks, image, color, intrinsic, intrinsic, extrinsic, 1.0, reach, trunc)
        self.views += 1
        self.pixels += n
        return n

    def extract(self) -> TriMesh:
        """Marching cubes over the fused volumes: the raw mesh, both volumes' triangles in one, in canonical order
        (empty arrays when nothing was fused)."""
        parts = [_extracted(grid) for grid in self._volumes.values()]
        offsets = np.cumsum([0] + [len(m.vertices) for m in parts])
        return _canonical(
            TriMesh(
                vertices=np.concatenate([m.vertices for m in parts]),
                triangles=np.concatenate([m.triangles + o for m, o in zip(parts, offsets, strict=False)]),
                colors=np.concatenate([m.colors for m in parts]),
            )
        )

    def state(self) -> dict[str, bytes]:
        """Each volume as Open3D's .npz bytes (what `from_state` takes back)."""
        out = {}
        with tempfile.TemporaryDirectory() as d:
            for name, grid in self._volumes.items():
                path = Path(d) / f"{name}.npz"
                if grid.hashmap().size():
                    grid.save(str(path))
                out[name] = path.read_bytes() if path.exists() else b""
        return out

    @classmethod
    def from_state(cls, state: dict[str, bytes], extent: float, params: MeshParams | None = None) -> TsdfFusion:
        """A fusion that goes on from a stored `state` made with the same `extent` and settings."""
        import open3d as o3d

        fusion = cls(extent, params)
        if set(state) != set(fusion._volumes):
            have, need = sorted(state), sorted(fusion._volumes)
            raise ValueError(f"a stored fusion holds volumes {have}, these settings need {need}")
        with tempfile.TemporaryDirectory() as d:
            for name, data in state.items():
                if data:  # an empty volume is stored as no bytes: Open3D cannot load a grid without blocks
                    path = Path(d) / f"{name}.npz"
                    path.write_bytes(data)
                    fusion._volumes[name] = o3d.t.geometry.VoxelBlockGrid.load(str(path))
        return fusion


def fuse_tsdf(
    views: Iterable[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]],
    extent: float,
    params: MeshParams | None = None,
    progress: ProgressFn | None = None,
    fusion: TsdfFusion | None = None,
) -> TsdfFusion:
    """Fuse (rgb, depth, K, w2c) views into `fusion` (a new one at `extent` by default) and return it.
    progress(views fused, number of views, "") after each view, when `views` has a length (a list)."""
    fusion = fusion or TsdfFusion(extent, params)
    n = len(views) if isinstance(views, Sized) else 0
    report = progress if progress is not None and n else no_progress
    report(0, n, "")
    for i, (rgb, depth, K, w2c) in enumerate(views):
        fusion.integrate(rgb, depth, K, w2c)
        report(i + 1, n, "")
    return fusion


def mesh_from_views(
    views: Sequence[tuple[np.ndarray, np.ndarray]],
    w2c: np.ndarray,
    K: np.ndarray,
    params: MeshParams | None = None,
    progress: ProgressFn | None = None,
) -> tuple[TriMesh, float]:
    """The cleaned mesh (`fuse_tsdf`, then `mesh.clean_mesh`) of views (rgb (H,W,3), depth (H,W) world z, +inf
    where nothing is) seen from W2C cameras (N,4,4) with intrinsics K (3,3), and the extent its lengths
    followed: `camera.scene_extent` of those cameras and depths. Returns (mesh, extent)."""
    from wonderverse.camera import scene_extent

    extent = scene_extent(w2c, [d for _, d in views])
    fused = [(rgb, d, K, c) for (rgb, d), c in zip(views, w2c, strict=True)]
    return clean_mesh(fuse_tsdf(fused, extent, params, progress=progress).extract(), params), extent


def _grid(voxel: float) -> Any:
    import open3d as o3d
    import open3d.core as o3c

    return o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight", "color"),
        attr_dtypes=(o3c.float32, o3c.float32, o3c.float32),
        attr_channels=((1), (1), (3)),
        voxel_size=voxel,
        block_resolution=BLOCK_RESOLUTION,
        block_count=4096,  # the hash map grows as the seen space does
        device=o3c.Device("CPU:0"),
    )


def _extracted(grid: Any) -> TriMesh:
    if grid.hashmap().size() == 0:
        return TriMesh(np.zeros((0, 3)), np.zeros((0, 3), np.int32), np.zeros((0, 3)))
    m = grid.extract_triangle_mesh(weight_threshold=MIN_WEIGHT)
    if "positions" not in m.vertex or m.vertex.positions.shape[0] == 0:
        return TriMesh(np.zeros((0, 3)), np.zeros((0, 3), np.int32), np.zeros((0, 3)))
    colors = m.vertex.colors.numpy().astype(np.float64) if "colors" in m.vertex else None
    v = m.vertex.positions.numpy().astype(np.float64)
    return TriMesh(
        vertices=v,
        triangles=m.triangle.indices.numpy().astype(np.int32).reshape(-1, 3),
        colors=np.clip(colors, 0.0, 1.0) if colors is not None else np.full((len(v), 3), 0.5),
    )


def _canonical(mesh: TriMesh) -> TriMesh:
    """`mesh` with its vertices sorted (by position, then colour) and its triangles sorted, each rotated to start at
    its smallest index (the winding kept): one order for one mesh, whatever order its parts were found in."""
    if len(mesh.vertices) == 0:
        return TriMesh(mesh.vertices, mesh.triangles.astype(np.int32).reshape(-1, 3), mesh.colors)
    keys = np.concatenate([mesh.vertices, mesh.colors], axis=1)
    order = np.lexsort(keys.T[::-1])
    rank = np.empty(len(order), np.int64)
    rank[order] = np.arange(len(order))
    tri = rank[mesh.triangles]
    first = np.argmin(tri, axis=1)
    tri = np.stack([tri[np.arange(len(tri)), (first + k) % 3] for k in range(3)], axis=1)
    tri = tri[np.lexsort(tri.T[::-1])]
    return TriMesh(mesh.vertices[order], tri.astype(np.int32), mesh.colors[order])

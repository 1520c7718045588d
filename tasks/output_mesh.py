"""The mesh product of the outputs step: TSDF fusion that goes on from its stored volume when the scene only grew."""

from __future__ import annotations

from typing import Any

import numpy as np

from tasks.output_scene import Made, OutputScene
from tasks.progress import callback


def make_mesh(scene: OutputScene) -> Made:
    """TSDF fusion of splat renders from the fusion cameras, cleaned and in the output frame. When the stored fusion
    was made with the same settings and every frame it fused is still there, pose unchanged (an extension), only the
    new cameras are rendered and fused into it (`products.mesh.reusable`); else every camera is, at the extent of
    their renders."""
    from wonderverse.camera import scene_extent
    from wonderverse.mesh import fusion_cameras
    from wonderverse.products.mesh import camera_ids, export_mesh, fuse_views, median_depth
    from wonderverse.tsdf import TsdfFusion

    p = scene.p.mesh
    cams = fusion_cameras(scene.w2c_sfm, p.extra_views_per_gap)
    ids = camera_ids(cams)
    frames = set(camera_ids(scene.w2c_sfm[np.isfinite(scene.w2c_sfm).all(axis=(1, 2))]))
    stored = _stored_fusion(scene, ids, sorted(frames))
    if stored is None:
        views = scene.views(cams, "views rendered for the mesh")
        fusion, fused, keys, depths = TsdfFusion(scene_extent(cams, [d for _, d in views]), p), [], [], []
        new = list(range(len(cams)))
    else:
        fusion, figures = stored
        fused, keys, depths = list(figures.fused), list(figures.keys), list(figures.view_depths)
        new = [k for k, i in enumerate(ids) if i not in set(fused)]
        views = scene.views(cams[new], "views rendered for the mesh (new cameras)")
    fuse_views(fusion, views, cams[new], scene.Kr, callback("views fused"))
    files, mesh = export_mesh(fusion, p, scene.to_world, scene.world, scene.out)
    fused += [ids[k] for k in new]
    keys += [ids[k] for k in new if ids[k] in frames]
    depths += [median_depth(d) for _, d in views]
    look = float(np.median([d for d in depths if d is not None])) if any(d is not None for d in depths) else None
    figures_now = {"triangles": len(mesh.triangles), "vertices": len(mesh.vertices), "extent": fusion.extent}
    figures_now |= {"look": look, "fused": fused, "keys": keys, "view_depths": depths}
    state = fusion.state()
    arrays = {f"volume_{name}": np.frombuffer(data, np.uint8) for name, data in state.items()}
    return Made(files, {"mesh": figures_now}, arrays)


def _stored_fusion(scene: OutputScene, cameras: list[str], keys: list[str]) -> tuple[Any, Any] | None:
    """The stored fusion and its figures when it can go on: made with these settings, every frame it fused still
    among the frames' poses `keys` (of the fusion's `cameras`), pose unchanged; else None."""
    from wonderverse.products.mesh import reusable
    from wonderverse.schema import OUTPUT_PRODUCT
    from wonderverse.tsdf import VOLUMES, TsdfFusion

    group = OUTPUT_PRODUCT.at(product="mesh")
    meta = scene.store.meta(group)
    figures = meta.mesh if meta is not None and meta.settings == scene.settings["mesh"] else None
    if figures is None or not reusable(figures.fused, figures.keys, cameras, keys):
        return None
    names = [n for n in VOLUMES if scene.store.exists(getattr(group, f"volume_{n}"))]
    state = {n: scene.store.array(getattr(group, f"volume_{n}")).tobytes() for n in names}
    try:
        return TsdfFusion.from_state(state, figures.extent, scene.p.mesh), figures
    except (ValueError, RuntimeError):  # a stored fusion Open3D cannot read: start over
        return None

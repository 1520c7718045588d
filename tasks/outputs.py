"""Step `outputs`: the files users open elsewhere, written beside the store from the trained splats, all in
one gravity-aligned world frame.

  splats.ply              the Gaussians, INRIA 3DGS layout (floaters and absurd Gaussians pruned first)
  splats.spz, splats.glb  the same Gaussians for the web: Niantic's SPZ, glTF with KHR_gaussian_splatting
  points.ply              Gaussian centres at least `mesh.points_min_opacity` opaque, base colour, normals
  mesh.ply, mesh.glb      TSDF fusion of splat renders from the training cameras (sky/background excluded)
  colmap/                 images/ + sparse/0/ (binary model with the global SfM's tracks): a training dataset
  nerfstudio/             transforms.json, images/, depths/, points.ply, camera_paths/{flythrough,novel}.json
  camera_path.json        the fly-through path, novel_path.json the novel track (W2C, OpenCV axes; our format)
  flythrough.mp4          splat renders along a smooth path through the whole scene
  novel.mp4               splat renders along a parallel path off the training trajectory

A product, a key: each product (`PRODUCTS`) is a unit of its own, `outputs/<product>`, keyed by the part of the
settings it reads, the trained splats' key and the keys of the products it comes after (`product_keys`), so a
change re-makes that product alone (a new `video_fps`: the camera paths and the videos). The `frame` product
holds the output world frame: the global poses' frame (`sfm/`, SfM's arbitrary orientation) turned so that +Z is
up, origin on the ground below the cameras' centroid, in the poses' units (`tasks.output_products.make_frame`);
`output_frame(store)` gives it. The step's group `outputs` lists every file with its size and what it holds.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import tasks.output_products as make
from tasks.base import Step, StepContext
from tasks.output_mesh import make_mesh
from tasks.output_scene import Made, OutputScene
from wonderverse.config import Model, OutputsParams, RunConfig
from wonderverse.schema import OUTPUT_PRODUCT, OUTPUTS, SPLATS
from wonderverse.store import SceneStore, cache_key, path_digest, write_array

if TYPE_CHECKING:
    from wonderverse.camera import Sim3


class Params(Model):
    """The outputs' settings, and the prompt the novel views are scored against (CLIP-S)."""

    outputs: OutputsParams
    prompt: str


def params(cfg: RunConfig) -> Params:
    return Params(outputs=cfg.steps.outputs, prompt=cfg.scene.prompt)


@dataclass(frozen=True)
class Product:
    """One product of the step: its name (its group `outputs/<name>`), version, the settings it reads, the products
    whose records it reads, and how it is made (`tasks.output_products`)."""

    name: str
    version: int
    reads: Callable[[Params], dict[str, Any]]
    make: Callable[[OutputScene], Made]
    after: tuple[str, ...] = ()
    writes_into: tuple[str, ...] = ()  # folders another product lists that this one writes files into


def _video(p: Params) -> dict[str, Any]:
    """What every rendered path reads: its length, where the novel one runs, and the render size."""
    o = p.outputs
    return {"video_frames": o.video_frames, "novel_offset_frac": o.novel_offset_frac, "size": o.render_max_side_px}


def _dataset(p: Params, on: bool) -> dict[str, Any]:
    """What a dataset reads: whether it is on and, for tracks projected from the point cloud (no SfM model), the
    cloud's opacity and the rendered depth's size."""
    return {"on": on, "min_opacity": p.outputs.mesh.points_min_opacity, "size": p.outputs.render_max_side_px}


PRODUCTS: tuple[Product, ...] = (
    Product("frame", 1, lambda p: {}, make.make_frame),
    Product(
        "mesh",
        1,
        lambda p: {
            "mesh": p.outputs.mesh.model_dump(exclude={"points_min_opacity"}),
            "size": p.outputs.render_max_side_px,
        },
        make_mesh,
        ("frame",),
    ),
    Product("splat_files", 1, lambda p: {"prune": p.outputs.prune}, make.make_splat_files, ("frame", "mesh")),
    Product("points", 1, lambda p: {"min_opacity": p.outputs.mesh.points_min_opacity}, make.make_points, ("frame",)),
    Product("colmap", 1, lambda p: _dataset(p, p.outputs.colmap), make.make_colmap, ("frame",)),
    Product("nerfstudio", 1, lambda p: _dataset(p, p.outputs.nerfstudio), make.make_nerfstudio, ("frame",)),
    Product(
        "camera_paths",
        1,
        lambda p: _video(p) | {"fps": p.outputs.video_fps, "nerfstudio": p.outputs.nerfstudio},
        make.make_camera_paths,
        ("frame", "mesh"),
        ("nerfstudio",),  # nerfstudio/camera_paths/
    ),
    Product("videos", 1, lambda p: _video(p) | {"fps": p.outputs.video_fps}, make.make_videos, ("frame", "mesh")),
    Product(
        "quality",
        1,
        lambda p: _video(p) | {"quality": p.outputs.quality, "frames": p.outputs.quality_frames, "prompt": p.prompt},
        make.make_quality,
        ("frame", "mesh"),
    ),
)


def settings_digests(p: Params) -> dict[str, str]:
    """Per product, a digest of the settings it reads (what a product that goes on from its stored state checks)."""
    return {
        product.name: cache_key(f"outputs.{product.name}", product.version, product.reads(p)) for product in PRODUCTS
    }


def product_keys(p: Params, splats_key: str) -> dict[str, str]:
    """Every product's key: sha256 of its name, version and the settings it reads, the splats' key and the keys of
    the products it comes after (in `PRODUCTS` order, so those are known)."""
    keys: dict[str, str] = {}
    for product in PRODUCTS:
        inputs = [splats_key, *(keys[a] for a in product.after)]
        keys[product.name] = cache_key(f"outputs.{product.name}", product.version, product.reads(p), inputs)
    return keys


def altered_files(store: SceneStore) -> set[str]:
    """The files beside the store that the outputs step's last commit recorded with a digest and that are now missing
    or differ from it (a user deleted `mesh.ply`, truncated `splats.ply`)."""
    from wonderverse.store import DamagedData

    try:
        meta = store.meta(OUTPUTS.path, complete=False)
    except DamagedData:
        return set()
    altered = set()
    for f in meta.files if meta is not None else []:
        if f.digest is not None and path_digest(store.scene_dir / f.path) != f.digest:
            altered.add(f.path)
    return altered


def _touches(store: SceneStore, product: Product, altered: set[str]) -> bool:
    """Whether `product` wrote one of the `altered` files, or writes into one of them (a folder)."""
    if not altered:
        return False
    record = store.meta(OUTPUT_PRODUCT.at(product=product.name))
    listed = {f.path for f in record.files} if record is not None else set()
    return bool((listed | set(product.writes_into)) & altered)


def output_frame(store: SceneStore) -> Sim3:
    """The rigid transform from the global poses' frame (`sfm/`) to the frame every output file is in
    (x_out = R (x_sfm - origin)); for readers that compare the files with the store (the report, benchmarks).
    Raises KeyError when the outputs step has not recorded one."""
    from wonderverse.camera import Sim3

    meta = store.meta(OUTPUTS.path)
    if meta is None:
        raise KeyError("the outputs step has not recorded the output frame")
    return Sim3.from_dict(meta.frame.world_from_sfm)


def run(store: SceneStore, params: Params, ctx: StepContext) -> str:
    scene = OutputScene.load(store, params.outputs, ctx.execution, params.prompt)
    scene.settings = settings_digests(params)
    keys = product_keys(params, store.cache_key_of(SPLATS.path) or "")
    made = []
    altered = altered_files(store)
    for product in PRODUCTS:
        group = OUTPUT_PRODUCT.at(product=product.name)
        if _touches(store, product, altered):  # made again from scratch: nothing of its files is kept
            store.mark_damaged(group, [f"file {name} is missing or altered" for name in sorted(altered)])
        if not store.is_complete(group, keys[product.name]):
            m = product.make(scene)
            listed = [{"path": f.path.name, "bytes": f.size, "description": f.description} for f in m.files]
            settings = scene.settings[product.name]
            with store.staged(group, keys[product.name], files=listed, settings=settings, **m.record) as g:
                for name, data in m.arrays.items():
                    write_array(g, getattr(group, name), data)
            made.append(product.name)
        scene.records[product.name] = store.meta(group)
    r = scene.records
    # the files as the step leaves them, each with its digest: a file deleted or altered later makes the products that
    # wrote it run again (`altered_files`), and the step's group counts as damaged until then (`SceneStore.damage`)
    files = [
        f.model_copy(update={"digest": path_digest(store.scene_dir / f.path)})
        for product in PRODUCTS
        for f in r[product.name].files
    ]
    mesh = r["mesh"].mesh.model_copy(update={"points": r["points"].points, "fused": [], "keys": [], "view_depths": []})
    store.mark_complete(
        OUTPUTS.path,
        ctx.key,
        files=files,
        mesh=mesh,
        render_size=list(scene.render_size),
        quality=r["quality"].quality,
        frame=r["frame"].frame,
        pruned=r["splat_files"].pruned,
        colmap=r["colmap"].colmap,
        nerfstudio=r["nerfstudio"].nerfstudio,
        made=made,
    )
    return (
        f"{len(files)} files ({len(made)} of {len(PRODUCTS)} products made, the rest unchanged): mesh "
        f"{mesh.triangles} triangles, {mesh.points} points, 2 videos; up from {r['frame'].frame.source}"
    )


# 3: the step contract
# 4: one gravity-aligned frame for every file; splats.ply written here, pruned, with splats.spz and splats.glb;
#    COLMAP dataset with tracks; nerfstudio depths, points and camera paths; novel_path.json; faststart videos
# 5: a product, a key (`outputs/<product>`)
STEP = Step(
    "outputs", 5, ("splats",), params, run, "mesh, point cloud, COLMAP/nerfstudio exports, videos", group=OUTPUTS.path
)

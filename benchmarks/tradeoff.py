"""What each preset buys: speed against accuracy on the same procedural scenes, faults switched on.

- Scenes: one outdoor ("a small house decorated for Christmas") and one indoor ("a cosy reading room with
  shelves and armchairs"), 3 segments each (initial + left + right), procedural faults at 30 % per attempt.
- Per preset and scene, the whole pipeline (plan → outputs, local engine, the preset as shipped) runs in a
  fresh process, so its peak memory is its own: peak RSS of the process and its children (MB) and, on CUDA,
  torch's peak allocated GPU memory.
- Scored against the procedural ground truth, never against the pipeline's own output:
  - `ate_frac`: global SfM poses vs the true poses (Sim(3)-aligned), RMSE / length of the true path;
  - `depth_absrel`: the splats' rendered depth at the held-out frames (their SfM poses, video resolution),
    in metres through the Sim(3) scale, vs the true depth (where alpha > 0.5 and the truth is finite);
  - `psnr`: held-out PSNR from the splat step (frames the optimisation never saw);
  - `fscore_1pct`: the exported mesh.ply mapped into the world by that Sim(3), against points sampled on the
    world's surfaces that the true cameras see within the fusion's reach; threshold 1 % of the scene extent;
    `by_range` (rows only) splits it by distance to the nearest camera (bands of 0.5, 1, 2 extents and beyond):
    the share of the seen surface and of the mesh in each band, its recall and its precision;
  - `extra_trials`: regenerated segment attempts per segment (check step); `niqe`: mean NIQE (no reference,
    lower is better) of 8 frames of novel.mp4.
- Pareto: per machine, presets sorted by mean seconds; `pareto` is true when, on every machine that ran two
  presets or more, each slower preset has a higher mean F-score (by > 0.01) and a higher mean PSNR (by > 0.1 dB)
  than the faster one before it.
- Results of runs on different machines (the CPU for preview, a GPU for standard and high) merge with
  `--merge A.json B.json`: one table, one plot (seconds vs F-score, one point per preset), one JSON line.

Usage: `python -m benchmarks.tradeoff [--quick] [--presets preview,standard,high] [--out DIR]`; --quick
shrinks every preset to 128x96 frames, 9 per segment and 60 iterations (a smoke run, not a measurement).
Last line: {"presets": [{"name", "seconds", "peak_mb", "ate_frac", "depth_absrel", "psnr", "fscore_1pct",
"machine", "scenes"}, ...], "pareto": bool} — one entry per preset and machine: means over the scenes
that every preset on that machine ran (and over repeated runs).
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.common import machine, report
from tasks.outputs import output_frame
from wonderverse.schema import CHECK, OUTPUTS, SFM, SPLATS

SCENES = {
    "outdoor": "a small house decorated for Christmas",
    "indoor": "a cosy reading room with shelves and armchairs",
}
FAULT_PROBABILITY = 0.3
NIQE_FRAMES = 8
PARETO_MIN_FSCORE_GAIN = 0.01
PARETO_MIN_PSNR_GAIN_DB = 0.1
KEYS = ("seconds", "peak_mb", "ate_frac", "depth_absrel", "psnr", "fscore_1pct")
RANGE_EDGES = (0.0, 0.5, 1.0, 2.0, np.inf)  # distance to the nearest camera, in scene extents (`by_range`)


def scene_config(preset: str, prompt: str, quick: bool) -> Any:
    from wonderverse.config import build_config

    video: dict[str, Any] = {"options": {"fault_probability": FAULT_PROBABILITY}}
    steps: dict[str, Any] = {}
    if quick:
        video |= {"width": 128, "height": 96, "frames_per_segment": 9}
        steps = {
            "splats": {"max_side_px": 128, "train": {"iterations": 60}},
            "outputs": {"video_frames": 12, "render_max_side_px": 256},
        }
    return build_config(prompt, preset=preset, overrides={"scene": {"video": video}, "steps": steps})


def run_one(preset: str, scene: str, scene_dir: Path, quick: bool) -> dict[str, Any]:
    """Run the pipeline for one preset and scene in this process; timings, memory and scores."""
    from flows.pipeline import execute

    cfg = scene_config(preset, SCENES[scene], quick)
    t0 = time.perf_counter()
    results = execute(scene_dir, cfg)
    seconds = time.perf_counter() - t0
    kb = max(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)
    out: dict[str, Any] = {"preset": preset, "scene": scene, "seconds": seconds, "peak_mb": kb / 1024}
    out["steps_s"] = {r.step: r.seconds for r in results}
    import torch

    out["peak_gpu_mb"] = torch.cuda.max_memory_allocated() / 2**20 if torch.cuda.is_available() else 0.0
    out["gpu"] = torch.cuda.get_device_name() if torch.cuda.is_available() else ""
    return out | score(scene_dir, cfg)


def mesh_voxel_rows(scene_dir: Path, cfg: Any, voxel_fracs: list[float]) -> list[dict[str, Any]]:
    """The same splats meshed again at other TSDF voxel sizes (only `outputs` re-runs: its parameters are
    all that changed), each scored like the preset's own mesh: what the mesh voxel alone does to accuracy."""
    from flows.pipeline import execute

    rows = []
    for frac in voxel_fracs:
        data = cfg.model_dump()
        data["steps"]["outputs"]["mesh"]["voxel_frac"] = frac
        alt = type(cfg).model_validate(data)
        t = time.perf_counter()
        execute(scene_dir, alt)
        s = score(scene_dir, alt)
        rows.append(
            {"voxel_frac": frac, "outputs_s": time.perf_counter() - t}
            | {k: s[k] for k in ("fscore_1pct", "precision_1pct", "recall_1pct")}
        )
    return rows


def _scored_frames(store: Any) -> dict[str, Any]:
    """SfM and true poses, true depth and names of the posed frames (the splat step's order)."""
    from tasks.segments import attempt_path

    segs, index, poses = store.meta(SFM.path).segments, store.array(SFM.frame_index), store.array(SFM.poses)
    ok = np.isfinite(poses).all(axis=(1, 2))
    paths = {a: attempt_path(store, segs[a]) for a in np.unique(index[:, 0])}
    gt = {a: (store.array(p.gt.poses), store.array(p.gt.depth)) for a, p in paths.items()}
    rows = [(a, int(i)) for (a, i), keep in zip(index, ok, strict=True) if keep]
    return {
        "names": [f"{segs[a]}_{i:04d}" for a, i in rows],
        "w2c": poses[ok],
        "gt_w2c": np.stack([gt[a][0][i] for a, i in rows]),
        "gt_depth": np.stack([gt[a][1][i] for a, i in rows]),
        "all_gt_w2c": np.concatenate([gt[a][0][i][None] for a, i in index]),
        "all_w2c": poses,
    }


def by_range(
    pred: np.ndarray, gt: np.ndarray, centres: np.ndarray, extent: float, tolerance: float
) -> list[dict[str, Any]]:
    """Where a mesh's F-score comes from: per band of distance to the nearest camera (`RANGE_EDGES`, in units of
    `extent`), the share of the seen surface `gt` (M,3) and of the mesh sample `pred` (N,3) that lie there, the
    recall of that surface and the precision of that part of the mesh at `tolerance` (NaN for an empty band)."""
    from scipy.spatial import cKDTree

    err_pred, err_gt = cKDTree(gt).query(pred)[0], cKDTree(pred).query(gt)[0]
    range_pred, range_gt = (cKDTree(centres).query(x)[0] / extent for x in (pred, gt))
    bands = []
    for lo, hi in itertools.pairwise(RANGE_EDGES):
        in_pred, in_gt = (range_pred >= lo) & (range_pred < hi), (range_gt >= lo) & (range_gt < hi)
        bands.append(
            {
                "band": f"{lo:g}-{hi:g}",
                "seen_share": float(in_gt.mean()),
                "recall": float((err_gt[in_gt] < tolerance).mean()) if in_gt.any() else float("nan"),
                "mesh_share": float(in_pred.mean()),
                "precision": float((err_pred[in_pred] < tolerance).mean()) if in_pred.any() else float("nan"),
            }
        )
    return bands


def score(scene_dir: Path, cfg: Any) -> dict[str, Any]:
    import imageio.v3 as iio
    import trimesh

    from benchmarks.mesh import visible_gt_points
    from wonderverse.camera import camera_centers, scene_extent, umeyama
    from wonderverse.metrics import ate, chamfer_fscore, depth_errors, sample_mesh_points
    from wonderverse.quality import niqe_many
    from wonderverse.splats.model import GaussianModel, normalization_from_dict
    from wonderverse.splats.renderer import make_renderer
    from wonderverse.splats.views import render_views
    from wonderverse.store import SceneStore
    from wonderverse.video import make_video_model

    store = SceneStore.open(scene_dir)
    f = _scored_frames(store)
    to_world = umeyama(camera_centers(f["w2c"]), camera_centers(f["gt_w2c"]), with_scale=True)
    splats = store.meta(SPLATS.path)
    metrics = splats.metrics
    test = [f["names"].index(splats.frames[j]) for j in metrics.test_views]

    # rendered depth at the held-out frames, in metres, against the truth
    arrays = {n: store.array(getattr(SPLATS, n)) for n in GaussianModel.PARAM_NAMES}
    norm = normalization_from_dict(splats.normalization)
    v = cfg.scene.video
    absrel = []
    views = render_views(arrays, norm, f["w2c"][test], store.array(SFM.K), v.width, v.height, make_renderer("auto"))
    for i, view in zip(test, views, strict=True):
        mask = np.isfinite(view.depth) & np.isfinite(f["gt_depth"][i])
        absrel.append(depth_errors(view.depth * to_world.s, f["gt_depth"][i], mask)["absrel"])

    # the exported mesh in the world, against the true surfaces the cameras see within the fusion's reach
    video = make_video_model(cfg.scene.video_source)  # builds the world: once
    mesh = trimesh.load(scene_dir / "mesh.ply", force="mesh")
    vertices = output_frame(store).apply_inverse(np.asarray(mesh.vertices))  # the files' frame -> sfm/ frame
    pred = to_world.apply(sample_mesh_points(vertices, np.asarray(mesh.faces), 300_000, seed=1))
    reach = cfg.steps.outputs.mesh.reach_frac * store.meta(OUTPUTS.path).mesh.extent * to_world.s
    extent = scene_extent(f["gt_w2c"], f["gt_depth"])
    gt_pts = visible_gt_points(video.world, video.K, f["gt_w2c"], f["gt_depth"], reach)
    fs = chamfer_fscore(pred, gt_pts, [0.01 * extent])

    novel = iio.imread(scene_dir / "novel.mp4")
    picks = novel[np.linspace(0, len(novel) - 1, NIQE_FRAMES).round().astype(int)]
    return {
        "extra_trials": store.meta(CHECK.path).mean_extra_trials,
        "ate_frac": ate(f["all_w2c"], f["all_gt_w2c"])["rmse_frac"],
        "depth_absrel": float(np.mean(absrel)),
        "psnr": float(metrics.test_psnr),
        "fscore_1pct": float(fs["fscore"][0]),
        "precision_1pct": float(fs["precision"][0]),
        "recall_1pct": float(fs["recall"][0]),
        "niqe": niqe_many(list(picks)) if min(picks.shape[1:3]) >= 192 else float("nan"),
        "gaussians": metrics.n_gaussians,
        "by_range": by_range(pred, gt_pts, camera_centers(f["gt_w2c"]), extent, 0.01 * extent),
    }


def run_preset(preset: str, quick: bool, tmp: Path) -> list[dict[str, Any]]:
    """Each scene of `preset` in a fresh interpreter (its own peak memory); their result rows."""
    rows = []
    for scene in SCENES:
        cmd = [sys.executable, "-m", "benchmarks.tradeoff", "--one", preset, scene, str(tmp / f"{preset}_{scene}")]
        r = subprocess.run(cmd + (["--quick"] if quick else []), capture_output=True, text=True)
        if r.returncode != 0:
            raise RuntimeError(f"{preset}/{scene} failed:\n{r.stderr[-4000:]}")
        rows.append(json.loads(r.stdout.strip().splitlines()[-1]))
        print(f"{preset}/{scene}: {rows[-1]['seconds']:.0f} s", file=sys.stderr, flush=True)
    return rows


def _shared_scenes(rows: list[dict[str, Any]], where: str) -> list[str]:
    """The scenes every preset run on machine `where` has: means over other scenes would not compare."""
    here = [r for r in rows if r.get("machine", "") == where]
    per_preset = [{r["scene"] for r in here if r["preset"] == p} for p in dict.fromkeys(r["preset"] for r in here)]
    return sorted(set.intersection(*per_preset)) if per_preset else []


def summary(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Per preset and machine, the means over the scenes all presets on that machine ran (repeated runs
    averaged too), sorted by seconds; `pareto`: on every machine that ran two presets or more, each slower
    preset is more accurate than the faster one before it."""
    presets = []
    for name, where in dict.fromkeys((r["preset"], r.get("machine", "")) for r in rows):
        scenes = _shared_scenes(rows, where)
        mine = [r for r in rows if r["preset"] == name and r.get("machine", "") == where and r["scene"] in scenes]
        if not mine:
            continue
        means = {k: round(float(np.mean([r[k] for r in mine])), 4) for k in KEYS}
        presets.append({"name": name} | means | {"machine": where, "scenes": scenes})
    presets.sort(key=lambda p: p["seconds"])
    fronts = [[p for p in presets if p["machine"] == where] for where in dict.fromkeys(p["machine"] for p in presets)]
    fronts = [f for f in fronts if len(f) > 1]
    pareto = bool(fronts) and all(
        b["fscore_1pct"] > a["fscore_1pct"] + PARETO_MIN_FSCORE_GAIN and b["psnr"] > a["psnr"] + PARETO_MIN_PSNR_GAIN_DB
        for front in fronts
        for a, b in itertools.pairwise(front)
    )
    return {"presets": presets, "pareto": pareto}


def plot(rows: list[dict[str, Any]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4), dpi=120)
    presets = summary(rows)["presets"]
    first = presets[0]["machine"] if presets else ""
    for p in presets:
        ax.scatter(p["seconds"], p["fscore_1pct"], s=40)
        label = f"{p['name']}, {p['machine'].split(', Python')[0]}\nPSNR {p['psnr']:.1f} dB"
        below = p["machine"] != first  # one machine's labels above their points, the others' below
        ax.annotate(
            label,
            (p["seconds"], p["fscore_1pct"]),
            fontsize=7,
            xytext=(4, -20 if below else 4),
            textcoords="offset points",
        )
    ax.margins(0.4)
    ax.set_xlabel("seconds, prompt to outputs (mean of scenes)")
    ax.set_ylabel("mesh F-score @ 1 % of extent")
    ax.set_title("WonderVerse presets: speed against accuracy")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)


def show(rows: list[dict[str, Any]], out: Path) -> None:
    table = [
        {
            "preset": r["preset"],
            "scene": r["scene"],
            "machine": r.get("machine", ""),
            "seconds": r["seconds"],
            "splats_s": r["steps_s"].get("splats", 0.0),
            "peak_mb": r["peak_mb"],
            "gpu_mb": r["peak_gpu_mb"],
            "extra_trials": r["extra_trials"],
            "ate_frac": r["ate_frac"],
            "depth_absrel": r["depth_absrel"],
            "psnr": r["psnr"],
            "fscore_1pct": r["fscore_1pct"],
            "niqe": r["niqe"],
        }
        for r in rows
    ]
    plot(rows, out / "tradeoff.png")
    report(f"tradeoff (plot: {out / 'tradeoff.png'})", table, summary(rows))  # type: ignore[arg-type]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="tiny frames and few iterations (smoke run)")
    p.add_argument("--presets", default="preview", help="comma-separated preset names")
    p.add_argument("--out", default=".", help="folder for tradeoff_<presets>.json and tradeoff.png")
    p.add_argument("--merge", nargs="+", metavar="JSON", help="combine earlier runs' JSON files instead of running")
    p.add_argument("--one", nargs=3, metavar=("PRESET", "SCENE", "DIR"), help=argparse.SUPPRESS)
    p.add_argument(
        "--mesh-voxels",
        type=float,
        nargs="+",
        default=[],
        help="with --one: also re-mesh the same splats at these TSDF voxel fractions and score each",
    )
    args = p.parse_args()
    if args.mesh_voxels:  # refuse a bad voxel before the run it would follow, not after it
        from pydantic import ValidationError

        from wonderverse.mesh import MeshParams

        try:
            [MeshParams(voxel_frac=f) for f in args.mesh_voxels]
        except ValidationError as e:
            p.error(f"--mesh-voxels: {e.errors()[0]['msg']}")
    if args.one:
        os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
        preset, scene, d = args.one
        row = run_one(preset, scene, Path(d), args.quick) | {"machine": machine()}
        if args.mesh_voxels:
            cfg = scene_config(preset, SCENES[scene], args.quick)
            row["mesh_voxels"] = mesh_voxel_rows(Path(d), cfg, args.mesh_voxels)
        print(json.dumps(row), flush=True)
        return
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.merge:
        rows = [r for f in args.merge for r in json.loads(Path(f).read_text())]
    else:
        names = args.presets.split(",")
        with tempfile.TemporaryDirectory(prefix="wv_tradeoff_") as tmp:
            rows = [r for name in names for r in run_preset(name, args.quick, Path(tmp))]
        (out / f"tradeoff_{'_'.join(names)}.json").write_text(json.dumps(rows, indent=1))
    show(rows, out)


if __name__ == "__main__":
    main()

"""A world that grows: what each extension costs as one procedural world grows, and whether its quality holds.

- One world (preview preset, procedural, the default prompt: an initial segment with one left and one right
  extension) is grown by N extensions (`--quick`: 6, else 12) with `extend`, the user's words alternating left and
  right for six, then going forward. Each extension runs in a fresh process (its peak RSS is its own, read from the
  OS when it exits).
- Per extension: seconds per step and of writing the report (as the CLI does after every run), peak RSS (MB), the
  scene folder's size (MB: the store and the files beside it), Gaussians, held-out PSNR (every held-out view
  rendered again), the global poses' ATE against the procedural world's true path (a share of its length) and
  whether the whole stitched path passes the check's jump test (no seam where the world was grown:
  `wonderverse.check.check_trajectory` over the global poses, the scene's rules).
- Then the final world is built from scratch (one `generate` with every extension's words) in a fresh process (its
  held-out PSNR tells how much of a fall is the world getting harder rather than the growing), and,
  with `--dask`, once more on a real Dask cluster the benchmark starts (`dask scheduler` and two `dask worker`
  processes on 127.0.0.1): the speedup of the steps that run segments on Dask (check, priors).
- A plot of the seconds of every extension, stacked by step, is written to `--out` (default: a temporary folder);
  the grown scene's report shows the same (`report.html`, "Steps and timings").

Usage: `python -m benchmarks.scale [--quick] [--extensions N] [--dask] [--out DIR] [--seed N]` (`--seed`: another
world for the same prompt and words).
Last line (JSON): `extensions`; `growth` (seconds of the last extension / of the first); `extend_ratio` (seconds of
the last extension / of building the final world from scratch); `rss_growth` (peak RSS of the last extension / of
the first) with `frames_growth` (stitched frames after the last / after the first) to compare it with;
`ate_frac_first`, `ate_frac_last`; `psnr_start` (the world before its first extension), `psnr_first`, `psnr_last`
(dB), `psnr_new_first`, `psnr_new_last` (the held-out PSNR of the segment the first and the last extension added,
right after it: does an extension still make its new views as well?), `psnr_kept_first`, `psnr_kept_last` (the mean
of the per-segment held-out PSNR of the segments the first extension left, after it and after the last: does what
was built hold?), `psnr_scratch` (the final world built from scratch: its held-out PSNR when nothing was grown);
`psnr_unchanged_first`, `psnr_unchanged_last` (the held-out PSNR over the pixels whose world did not change since
the frame was made: content a later extension's words placed where an older frame shows something else can be right
in the splats for the newer frames or for the older one, not both) with `changed_share_last` (the share of held-out
pixels the world changed under); `psnr_now_first`, `psnr_now_last` (the held-out PSNR against the world as it now
is: each held-out frame with the pixels the world changed under rendered as the procedural world now shows them);
`psnr_seen_first`, `psnr_seen_last` (the same, over the pixels whose content as the world now has it some frame
shows: changed pixels whose new content no later frame shows (`shown_later`) are left out);
`superseded_precision`, `superseded_recall` (the grown world's training views: the share of the pixels the splats
step leaves to later frames that the world did change under, and of those it changed under that are left);
`seams` (extensions whose stitched path failed the jump test); `scratch_seconds`;
`last_extension_seconds`; with `--dask`: `dask_speedup` (segment-parallel steps' seconds in one process / on the
cluster).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from flows.openmp import WAIT_KEYS, busy_cpus, command_env, wait_env

# Before torch loads, as the CLI does: idle OpenMP threads spin briefly on an idle machine, sleep on a busy one (a
# child keeps what its parent chose)
if not any(k in os.environ for k in WAIT_KEYS):
    os.environ.update(wait_env(os.environ, busy_cpus()))

import numpy as np

from benchmarks.common import report
from benchmarks.flows import pose_error
from wonderverse.config import RunConfig, build_config
from wonderverse.schema import SFM, SPLATS
from wonderverse.store import SceneStore

PROMPT = "a small house decorated for Christmas"
WORDS = (
    "a frozen lake on the left",
    "pine trees on the right",
    "a wooden cabin on the left",
    "a snowy hill on the right",
    "a stone wall on the left",
    "a row of lanterns on the right",
    # then forward: six more turns would take the views all the way round (a plan refuses a 360° span)
    "further ahead, a frozen pond",
    "further ahead, a sled by a fence",
    "further ahead, a snowman",
    "further ahead, an ice rink",
    "further ahead, a market stall",
    "further ahead, a clock tower",
)
PARALLEL_STEPS = ("check", "priors")  # per-segment work on Dask (map_segments)


def config(extensions: tuple[str, ...] = (), dask_address: str | None = None, seed: int | None = None) -> RunConfig:
    """The preview preset on the procedural world, its initial segment with one left and one right extension,
    and `extensions` (the user's words) added; one SfM thread, so that runs repeat. `seed`: the scene's (another
    world for the same words), else the default one."""
    execution: dict[str, Any] = {"dask_address": dask_address} if dask_address else {}
    scene: dict[str, Any] = {"extensions": {"added": list(extensions)}} | ({} if seed is None else {"seed": seed})
    return build_config(
        PROMPT,
        preset="preview",
        overrides={
            "scene": scene,
            "steps": {"poses": {"sfm": {"num_threads": 1}}, "check": {"sfm": {"num_threads": 1}}},
            "execution": execution,
        },
    )


def _child(args: list[str]) -> dict[str, Any]:
    """Run `python -m benchmarks.scale --child ARGS` in a fresh process: its JSON result, with its wall seconds and
    its peak RSS (MB, from the OS when it exits)."""
    t = time.perf_counter()
    proc = subprocess.Popen(
        [sys.executable, "-m", "benchmarks.scale", "--child", *args],
        stdout=subprocess.PIPE,
        text=True,
        env=command_env(os.environ, args[:1]),  # as the CLI's parent chooses for its child
    )
    out = proc.stdout.read() if proc.stdout else ""
    _, status, usage = os.wait4(proc.pid, 0)
    if status != 0:
        raise RuntimeError(f"child {args} failed (status {status})")
    result = json.loads(out.strip().splitlines()[-1])
    return result | {"wall_s": time.perf_counter() - t, "peak_mb": usage.ru_maxrss / 1024}


def child_main(what: str, scene: str, payload: str) -> None:
    """In the child: `generate` (payload: JSON of [words, Dask address, seed]) or `extend` (payload: the words), then
    the report, as the CLI does; prints the seconds of every step that ran and of the report, as JSON."""
    from flows.extend import extend
    from flows.pipeline import execute
    from flows.report import write_report

    if what == "extend":
        results = extend(scene, payload, engine="local")
    else:
        words, address, seed = json.loads(payload)
        results = execute(scene, config(tuple(words), address, seed))
    t = time.perf_counter()
    write_report(scene)
    steps = {r.step: r.seconds for r in results if r.status == "ran"} | {"report": time.perf_counter() - t}
    print(json.dumps({"steps": steps}), flush=True)


def world_now(
    store: SceneStore, names: list[str], render: bool = True, world: Any = None
) -> dict[str, tuple[np.ndarray, np.ndarray | None, np.ndarray | None]]:
    """Per frame name ("s003_0008"): the (H,W) bool pixels where the procedural world now shows other content than
    the frame was rendered with (the world changed under it: a later segment's words placed something where the
    frame shows the world, or in front of what it shows), and where any did, the world as it now is, rendered clean
    at the frame's pose ((H,W,3) uint8, and its camera z (H,W) float32; else None, None). Ground truth: the content
    each pixel showed when the frame was rendered (its attempt's `gt/labels`), against the content the world shows at
    the same pose now, every stored segment's words replayed, compared by name. Without `render`, no render. `world`:
    the scene's procedural world (`_world`), when the caller has it already."""
    from tasks.segments import attempt_path
    from wonderverse.video.procedural import content_labels

    model = _world(store) if world is None else world
    world, object_label, now_names = model.content.snapshot()
    shape = (model.height, model.width)
    truth: dict[str, tuple[np.ndarray, np.ndarray | None, dict[int, str]]] = {}
    out = {}
    for name in names:
        seg, frame = name.split("_")
        if seg not in truth:  # each segment's truth read once, whatever its held-out frames
            gt = attempt_path(store, seg).gt
            labels = store.array(gt.labels) if store.exists(gt.labels) else None
            label_names = {int(k): v for k, v in store.meta(gt, complete=False).label_names.items()}
            truth[seg] = (store.array(gt.poses), labels, label_names)
        poses, labels, then_names = truth[seg]
        pose = poses[int(frame)]
        native = pose.copy()
        native[:3, 3] /= model.options.scene_scale  # the world is cast in native metres
        now = (
            np.full(shape, -1)
            if world is None
            else content_labels(world, object_label, model.K, native[None], *shape[::-1])[0]
        )
        then = np.full(shape, -1) if labels is None else labels[int(frame)]
        changed = _named(now, now_names) != _named(then, then_names)
        out[name] = (changed, *(model.render(pose)[:2] if render and changed.any() else (None, None)))
    return out


def _world(store: SceneStore) -> Any:
    """The scene's procedural world as it now is (every stored segment's words replayed)."""
    from flows.inspect import run_config
    from tasks.attempts import video_model

    return video_model(store, run_config(store).scene.video_source)


def shown_later(
    store: SceneStore,
    changed: dict[str, np.ndarray],
    depth_tol: float = 0.02,
    world: Any = None,
    depth_now: dict[str, np.ndarray] | None = None,
) -> dict[str, np.ndarray]:
    """Per frame name ("s003_0008") of `changed` ((H,W) bool: the pixels the world changed under, `world_now`): those
    of them whose content as the world now has it a frame of a later segment shows (every other frame of each: in its
    view and unoccluded, its true depth at the point within `depth_tol` of the point's). The rest no frame ever showed:
    no reconstruction from the frames can show it. Ground truth: the world's depth now at the frame's true pose, and
    the later frames' true poses and depth (`gt`). `world` and `depth_now` (per name, the world's camera z at the
    frame's pose): as `world_now` gave them, when the caller has them already."""
    from tasks.segments import attempt_path, segment_ids
    from wonderverse.camera import pixels_to_world, world_to_pixels

    model = _world(store) if world is None else world
    segments = sorted(segment_ids(store))  # ids count up as segments are made
    truth = {seg: attempt_path(store, seg).gt for seg in segments}
    poses = {seg: store.array(truth[seg].poses) for seg in segments}
    later: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {}  # every other frame's pose and depth, read once
    out = {}
    for name, mask in changed.items():
        seg, frame = name.split("_")
        pose = poses[seg][int(frame)]
        depth = model.render(pose)[1] if depth_now is None else depth_now[name]
        v, u = np.nonzero(mask & np.isfinite(depth))
        points = pixels_to_world(u + 0.5, v + 0.5, depth[v, u].astype(np.float64), model.K, pose)
        seen = np.zeros(len(points), bool)
        for other in (s for s in segments if s > seg):
            if other not in later:
                later[other] = list(zip(poses[other][::2], store.array(truth[other].depth)[::2], strict=True))
            for w2c, d in later[other]:
                h, w = d.shape
                pu, pv, z, framed = world_to_pixels(points, model.K, w2c, h, w)
                at = d[pv[framed].astype(int), pu[framed].astype(int)]
                seen[np.flatnonzero(framed)[np.abs(at - z[framed]) <= depth_tol * z[framed]]] = True
        shown = np.zeros_like(mask)
        shown[v[seen], u[seen]] = True
        out[name] = shown
    return out


def changed_under(changed: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """`changed` (H,W) at `size` (w,h): each pixel there covers a block, changed if any of it is."""
    rows = np.arange(size[1]) * changed.shape[0] // size[1]
    cols = np.arange(size[0]) * changed.shape[1] // size[0]
    return np.maximum.reduceat(np.maximum.reduceat(changed, rows, axis=0), cols, axis=1)


def _named(labels: np.ndarray, names: dict[int, str]) -> np.ndarray:
    """Label ids (-1: none) as the names they stand for ("" for none), so two labellings compare by content."""
    table = np.array(["", *(names.get(i, "") for i in range(int(labels.max(initial=-1)) + 1))], dtype=object)
    return table[labels.astype(np.int64) + 1]


def _trained_views(store: SceneStore, meta: Any) -> Any:
    """The frames the stored splats (`meta`) were trained on, in their order, at full size in the world frame."""
    from tasks.splats import load_views

    views, names = load_views(store)
    at = {n: i for i, n in enumerate(names)}
    return views.subset([at[n] for n in meta.frames])


def _as_trained(views: Any, meta: Any) -> Any:
    """`views` as the splats step saw them: downscaled, in the stored splats' training frame."""
    from wonderverse.splats.data import downscale_views
    from wonderverse.splats.model import normalization_from_dict
    from wonderverse.splats.trainer import normalize_views

    views = downscale_views(views, config().steps.splats.max_side_px)
    return normalize_views(views, normalization_from_dict(meta.normalization))


def held_out_psnr(scene: Path) -> dict[str, float]:
    """Held-out PSNR of the stored splats (dB), every held-out view rendered again now: `all` (their mean) and per
    segment (the views grouped by the segment they come from), so that a segment can be followed from the
    extension that added it to the last one (does what was built hold?) and compared with the world built from
    scratch. (The splats step's own figure carries the figures of views an extension's region did not touch.)
    Also, as `world_now` tells the pixels the world changed under: `unchanged`, the mean over the pixels it did not
    change under, `changed`, the share of held-out pixels it did change under, and `now`, the mean against the
    world as it now is (each frame with the pixels the world changed under rendered as the world shows them now), and
    `seen`, the same over the pixels whose content now some frame shows (`shown_later`)."""
    import torch

    from tasks.splats import stored_sky
    from wonderverse.splats.model import GaussianModel
    from wonderverse.splats.renderer import make_renderer
    from wonderverse.splats.trainer import evaluate

    store = SceneStore.open(scene)
    meta = store.meta(SPLATS.path)
    p = config().steps.splats
    model = GaussianModel.from_numpy({k: store.array(getattr(SPLATS, k)) for k in GaussianModel.PARAM_NAMES})
    views = _trained_views(store, meta)
    ids = list(meta.metrics.test_views)
    if not ids:
        return dict.fromkeys(("all", "unchanged", "changed", "now", "seen"), float("nan"))
    world = _world(store)
    now = world_now(store, [meta.frames[i] for i in ids], world=world)
    frames_now = views.frames.copy()
    for i in ids:
        changed, render, _ = now[meta.frames[i]]
        if render is not None:
            frames_now[i] = np.where(changed[..., None], render, frames_now[i])
    views, views_now = _as_trained(views, meta), _as_trained(views.replace(frames=frames_now), meta)
    sky = stored_sky(store)
    sky = torch.from_numpy(np.asarray(np.zeros(3) if sky is None else sky, np.float32))
    h, w = views.frames.shape[1:3]
    changed = {i: changed_under(now[meta.frames[i]][0], (w, h)) for i in ids}
    renderer = make_renderer("auto")
    per_view = evaluate(
        model, views, ids, renderer, p.train, sky, per_view=True, keep={i: ~c for i, c in changed.items()}
    )
    psnr_now = dict(zip(ids, per_view["psnr_views"], strict=True))
    moved = [i for i in ids if now[meta.frames[i]][1] is not None]  # the other views' references are their frames
    names = [meta.frames[i] for i in moved]
    shown = shown_later(store, {n: now[n][0] for n in names}, world=world, depth_now={n: now[n][2] for n in names})
    unseen = {i: changed_under(now[meta.frames[i]][0] & ~shown[meta.frames[i]], (w, h)) for i in moved}
    against_now = evaluate(
        model, views_now, moved, renderer, p.train, sky, per_view=True, keep={i: ~unseen[i] for i in moved}
    )
    psnr_now |= dict(zip(moved, against_now.get("psnr_views", []), strict=True))
    psnr_seen = dict(zip(ids, per_view["psnr_views"], strict=True))
    psnr_seen |= dict(zip(moved, against_now.get("psnr_kept_views", []), strict=True))
    groups: dict[str, list[float]] = {}
    for i, value in zip(ids, per_view["psnr_views"], strict=True):
        groups.setdefault(meta.frames[i].split("_")[0], []).append(value)
    out = {seg: round(float(np.mean(v)), 3) for seg, v in sorted(groups.items())}
    return out | {
        "all": float(np.mean(per_view["psnr_views"])),
        "unchanged": float(np.nanmean(per_view["psnr_kept_views"])),
        "changed": float(np.mean([c.mean() for c in changed.values()])),
        "now": float(np.mean(list(psnr_now.values()))),
        "seen": float(np.nanmean(list(psnr_seen.values()))),
    }


def superseded_agreement(scene: Path) -> dict[str, float]:
    """How the training views' superseded pixels (`wonderverse.splats.superseded`, as the splats step sets them)
    agree with the pixels the world changed under (`world_now`, at the views' size): `precision` (the share of
    superseded pixels that changed) and `recall` (the share of changed pixels superseded)."""
    from wonderverse.splats.region import held_out
    from wonderverse.splats.superseded import with_superseded

    store = SceneStore.open(scene)
    meta, p = store.meta(SPLATS.path), config().steps.splats
    views = _as_trained(_trained_views(store, meta), meta)
    held = {meta.frames[i] for i in held_out(meta.frames, p.train.holdout_every)}
    marked = with_superseded(views, meta.frames, held, p.superseded_margin).superseded
    train = [i for i, n in enumerate(meta.frames) if n not in held]
    h, w = views.frames.shape[1:3]
    changed = world_now(store, [meta.frames[i] for i in train], render=False)
    both = marked_all = changed_all = 0
    for i in train:
        c = changed_under(changed[meta.frames[i]][0], (w, h))
        m = np.zeros_like(c) if marked is None else marked[i]
        both, marked_all, changed_all = both + (c & m).sum(), marked_all + m.sum(), changed_all + c.sum()
    return {"precision": both / max(marked_all, 1), "recall": both / max(changed_all, 1)}


def _psnr_figures(scene: Path) -> dict[str, Any]:
    by_segment = held_out_psnr(scene)
    psnr, unchanged, changed, now, seen = (by_segment.pop(k) for k in ("all", "unchanged", "changed", "now", "seen"))
    return {
        "psnr": psnr,
        "psnr_unchanged": unchanged,
        "changed_share": changed,
        "psnr_now": now,
        "psnr_seen": seen,
        "psnr_by_segment": by_segment,
    }


def measure(scene: Path) -> dict[str, Any]:
    """Figures of the scene as it stands: its size, frames, Gaussians, held-out PSNR, pose ATE and seams."""
    from wonderverse.check import check_trajectory

    store = SceneStore.open(scene)
    splats = store.meta(SPLATS.path)
    poses, registered = store.array(SFM.poses), store.array(SFM.registered)
    rules = config().steps.check.rules
    seams = check_trajectory(poses, registered & np.isfinite(poses).all(axis=(1, 2)), rules)
    size = sum(f.stat().st_size for f in scene.rglob("*") if f.is_file())
    return {
        "frames": len(poses),
        "store_mb": size / 2**20,
        "gaussians": splats.metrics.n_gaussians,
        **_psnr_figures(scene),
        "ate_frac": pose_error(scene),
        "seam": not seams.accepted,
        "seam_reasons": seams.reasons,
    }


@contextmanager
def dask_cluster(folder: Path, workers: int = 2) -> Iterator[str]:
    """A real Dask cluster for the block: `dask scheduler` and `workers` `dask worker` processes (one thread each)
    on 127.0.0.1; yields the scheduler's address."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    address = f"tcp://127.0.0.1:{port}"
    dask = [sys.executable, "-m", "distributed.cli.dask_scheduler"]
    log = open(folder / "dask.log", "w")  # noqa: SIM115 - closed below, after the processes
    procs = [subprocess.Popen([*dask, "--host", "127.0.0.1", "--port", str(port), "--dashboard-address", ":0"],
                              stdout=log, stderr=subprocess.STDOUT, start_new_session=True)]  # fmt: skip
    worker = [sys.executable, "-m", "distributed.cli.dask_worker", address, "--nthreads", "1", "--host", "127.0.0.1"]
    try:
        time.sleep(3)
        procs += [
            subprocess.Popen(
                [*worker, "--dashboard-address", ":0"],
                stdout=log,
                stderr=subprocess.STDOUT,
                start_new_session=True,
                cwd=Path(__file__).resolve().parents[1],
            )
            for _ in range(workers)
        ]
        from dask.distributed import Client

        with Client(address, timeout=60) as client:
            client.wait_for_workers(workers, timeout=120)
        yield address
    finally:
        for p in procs:
            os.killpg(p.pid, signal.SIGTERM)
        for p in procs:
            p.wait(30)
        log.close()


def plot(rows: list[dict[str, Any]], path: Path) -> Path:
    """Seconds of every extension, stacked by step (PNG; the report's growth plot)."""
    from wonderverse.plots import growth_plot

    title = "What each extension costs as the world grows (preview, procedural)"
    path.write_bytes(growth_plot([r["steps"] for r in rows], [str(r["extension"]) for r in rows], title))
    return path


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="6 extensions instead of 12")
    p.add_argument("--extensions", type=int, default=None)
    p.add_argument("--dask", action="store_true", help="also build the final world on a real Dask cluster")
    p.add_argument("--out", type=Path, default=None, help="folder for the plot and the rows (default: temporary)")
    p.add_argument("--seed", type=int, default=None, help="the scene's seed (another world; default: the preset's)")
    p.add_argument("--child", nargs=3, help=argparse.SUPPRESS)
    a = p.parse_args()
    if a.child:
        child_main(*a.child)
        return
    n = a.extensions or (6 if a.quick else 12)
    words = tuple(WORDS[i % len(WORDS)] for i in range(n))
    tmp = Path(tempfile.mkdtemp(prefix="wv-scale-"))
    out = a.out or tmp
    out.mkdir(parents=True, exist_ok=True)
    scene = tmp / "grown"
    start = _child(["generate", str(scene), json.dumps([[], None, a.seed])])
    start |= measure(scene)
    rows = []
    for k, w in enumerate(words, 1):
        r = _child(["extend", str(scene), w])
        rows.append(
            {"extension": k, "seconds": r["wall_s"], "steps": r["steps"], "peak_mb": r["peak_mb"]} | measure(scene)
        )
        steps = ", ".join(f"{step} {sec:.1f}" for step, sec in r["steps"].items())
        print(f"extension {k}: {r['wall_s']:.1f} s ({steps}), {rows[-1]['frames']} frames", file=sys.stderr, flush=True)
    scratch = _child(["generate", str(tmp / "scratch"), json.dumps([list(words), None, a.seed])])
    scratch |= measure(tmp / "scratch")  # the same world trained whole: how hard it is, apart from growing it
    head: dict[str, Any] = {}
    if a.dask:
        with dask_cluster(tmp) as address:
            on_dask = _child(["generate", str(tmp / "scratch_dask"), json.dumps([list(words), address, a.seed])])
        local = sum(scratch["steps"].get(s, 0.0) for s in PARALLEL_STEPS)
        head["dask_speedup"] = round(local / max(sum(on_dask["steps"].get(s, 0.0) for s in PARALLEL_STEPS), 1e-9), 3)
    plot(rows, out / "scale.png")
    (out / "scale_rows.json").write_text(json.dumps({"start": start, "rows": rows, "scratch": scratch}, indent=1))
    first, last = rows[0], rows[-1]

    def kept(row: dict[str, Any]) -> float:  # what the first extension built, as `row` renders it
        return float(np.mean([row["psnr_by_segment"][s] for s in first["psnr_by_segment"]]))

    def new(row: dict[str, Any], before: dict[str, Any]) -> float:  # the segment(s) the extension added
        return float(np.mean([v for s, v in row["psnr_by_segment"].items() if s not in before["psnr_by_segment"]]))

    table = [
        {
            "extension": r["extension"],
            "seconds": r["seconds"],
            **{
                s: r["steps"].get(s, 0.0)
                for s in ("generate_segments", "check", "poses", "priors", "splats", "outputs")
            },
            "peak MB": r["peak_mb"],
            "store MB": r["store_mb"],
            "frames": r["frames"],
            "Gaussians": r["gaussians"],
            "PSNR": r["psnr"],
            "PSNR unchanged": r["psnr_unchanged"],
            "PSNR now": r["psnr_now"],
            "PSNR seen": r.get("psnr_seen", float("nan")),
            "changed %": 100 * r["changed_share"],
            "ATE %": 100 * r["ate_frac"],
            "seam": r["seam"],
        }
        for r in rows
    ]
    head = {
        "extensions": n,
        "growth": round(last["seconds"] / first["seconds"], 3),
        "extend_ratio": round(last["seconds"] / scratch["wall_s"], 3),
        "rss_growth": round(last["peak_mb"] / first["peak_mb"], 3),
        "frames_growth": round(last["frames"] / first["frames"], 3),
        "ate_frac_first": round(first["ate_frac"], 5),
        "ate_frac_last": round(last["ate_frac"], 5),
        "psnr_start": round(start["psnr"], 3),
        "psnr_first": round(first["psnr"], 3),
        "psnr_last": round(last["psnr"], 3),
        "psnr_new_first": round(new(first, start), 3),
        "psnr_new_last": round(new(last, rows[-2] if len(rows) > 1 else start), 3),
        "psnr_kept_first": round(kept(first), 3),
        "psnr_kept_last": round(kept(last), 3),
        "psnr_scratch": round(scratch["psnr"], 3),
        "psnr_unchanged_first": round(first["psnr_unchanged"], 3),
        "psnr_unchanged_last": round(last["psnr_unchanged"], 3),
        "changed_share_last": round(last["changed_share"], 4),
        "psnr_now_first": round(first["psnr_now"], 3),
        "psnr_now_last": round(last["psnr_now"], 3),
        "psnr_seen_first": round(first["psnr_seen"], 3),
        "psnr_seen_last": round(last["psnr_seen"], 3),
        **{f"superseded_{k}": round(float(v), 3) for k, v in superseded_agreement(scene).items()},
        "seams": sum(r["seam"] for r in rows),
        "scratch_seconds": round(scratch["wall_s"], 1),
        "last_extension_seconds": round(last["seconds"], 1),
    } | head
    report(f"benchmarks.scale: {n} extensions of one world (plot: {out / 'scale.png'})", table, head)
    if a.out is None:
        shutil.rmtree(tmp / "scratch", ignore_errors=True)


if __name__ == "__main__":
    main()

"""`wonderverse preview`: files a person looks at — the stitched video, a contact sheet, and per
attempt the check plot (steps against T1/T2, flagged frames) and a top view of its SfM trajectory."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from tasks.segments import attempt_ids, segment_ids, stitched
from wonderverse.errors import WonderError
from wonderverse.schema import ATTEMPT, SFM
from wonderverse.store import SceneStore, check_writable

PREVIEW_FILE = "preview.mp4"


def _check_result(attrs: dict) -> object:
    from wonderverse.check import CheckResult

    arr = {
        k: np.array([np.nan if v is None else v for v in attrs.get(k, [])], float)
        for k in ("trans_steps", "step_ratio", "rot_steps")
    }
    median = attrs.get("median_step")
    return CheckResult(
        accepted=attrs["accepted"],
        reasons=attrs.get("reasons", []),
        flagged_frames=attrs.get("flagged_frames", []),
        notes=attrs.get("notes", []),
        median_step=np.nan if median is None else median,
        registered_frac=attrs.get("registered_frac", 0.0),
        **arr,
    )


def write_plots(store: SceneStore, out: Path) -> list[Path]:
    """Check plot + SfM top view per checked attempt, and the global trajectory; returns the paths."""
    from wonderverse.config import validate_config
    from wonderverse.plots import segment_check_plot, trajectory_topview_plot

    config = store.root.attrs.get("config")
    params = validate_config(config).steps.check.rules if config else None
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for seg in segment_ids(store):
        for k in attempt_ids(store, seg):
            ap = ATTEMPT.at(seg=seg, attempt=k)
            attrs = store.attrs(ap.check)
            if attrs.get("complete") is not True:
                continue
            p = out / f"{seg}_attempt{k}_check.png"
            p.write_bytes(segment_check_plot(_check_result(attrs), params, f"{seg} attempt {k}"))
            written.append(p)
            p = out / f"{seg}_attempt{k}_topview.png"
            p.write_bytes(
                trajectory_topview_plot(
                    [store.array(ap.sfm.poses)],
                    [f"{seg}/{k} SfM"],
                    f"{seg} attempt {k}: SfM camera path (top view)",
                )
            )
            written.append(p)
    if store.cache_key_of(SFM.path):
        p = out / "trajectory_topview.png"
        p.write_bytes(
            trajectory_topview_plot(
                [store.array(SFM.poses)], ["global"], "stitched video: global camera path (top view)"
            )
        )
        written.append(p)
    return written


def write_preview(scene_dir: Path) -> list[Path]:
    """preview.mp4, contact_sheet.png and plots/ in the scene folder; returns the files written."""
    from wonderverse.media import contact_sheet, write_mp4

    store = SceneStore.open(scene_dir)
    frames, index = stitched(store)
    if len(frames) == 0:
        raise WonderError(f"{scene_dir} has no rendered segments yet; run `wonderverse generate` first")
    check_writable(scene_dir, f"{PREVIEW_FILE} in {scene_dir}")  # before ffmpeg starts (it prints its own errors)
    fps = float((store.root.attrs.get("spec") or {}).get("video", {}).get("fps", 8))
    mp4 = write_mp4(frames, Path(scene_dir) / PREVIEW_FILE, fps)
    pick = sorted(set(range(0, len(frames), max(1, len(frames) // 32))))
    png = Path(scene_dir) / "contact_sheet.png"
    png.write_bytes(contact_sheet(frames[pick], [f"{index[i][0]}:{index[i][1]}" for i in pick]))
    return [mp4, png, *write_plots(store, Path(scene_dir) / "plots")]

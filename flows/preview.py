"""`wonderverse preview`: files a person looks at — the stitched video, a contact sheet, and per
attempt the check plot (steps against T1/T2, flagged frames) and a top view of its SfM trajectory."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from flows.inspect import run_config, scene_spec
from tasks.segments import attempt_ids, segment_ids, stitched
from wonderverse.check import CheckResult
from wonderverse.errors import WonderError
from wonderverse.schema import ATTEMPT, SFM
from wonderverse.schema.attrs import AttemptCheckAttrs
from wonderverse.store import SceneStore, check_writable

PREVIEW_FILE = "preview.mp4"


def check_result(check: AttemptCheckAttrs) -> CheckResult:
    """The check's decision on an attempt as the `CheckResult` it was recorded from (None -> NaN), to plot it."""

    def steps(values: list[float | None]) -> np.ndarray:
        return np.array([np.nan if v is None else v for v in values], float)

    return CheckResult(
        accepted=check.accepted,
        reasons=list(check.reasons),
        flagged_frames=list(check.flagged_frames),
        notes=list(check.notes),
        median_step=np.nan if check.median_step is None else check.median_step,
        registered_frac=check.registered_frac,
        trans_steps=steps(check.trans_steps),
        step_ratio=steps(check.step_ratio),
        rot_steps=steps(check.rot_steps),
    )


def write_plots(store: SceneStore, out: Path) -> list[Path]:
    """Check plot + SfM top view per checked attempt, and the global trajectory; returns the paths."""
    from wonderverse.plots import segment_check_plot, trajectory_topview_plot

    cfg = run_config(store)
    params = cfg.steps.check.rules if cfg is not None else None
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for seg in segment_ids(store):
        for k in attempt_ids(store, seg):
            ap = ATTEMPT.at(seg=seg, attempt=k)
            check = store.meta(ap.check)
            if check is None:
                continue
            p = out / f"{seg}_attempt{k}_check.png"
            p.write_bytes(segment_check_plot(check_result(check), params, f"{seg} attempt {k}"))
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
    spec = scene_spec(store)
    fps = spec.video.fps if spec is not None else 8.0
    mp4 = write_mp4(frames, Path(scene_dir) / PREVIEW_FILE, fps)
    pick = sorted(set(range(0, len(frames), max(1, len(frames) // 32))))
    png = Path(scene_dir) / "contact_sheet.png"
    png.write_bytes(contact_sheet(frames[pick], [f"{index[i][0]}:{index[i][1]}" for i in pick]))
    return [mp4, png, *write_plots(store, Path(scene_dir) / "plots")]

"""Diagnostic plots as PNG bytes: a segment's continuity check and camera trajectories seen from above.

Built on `matplotlib.figure.Figure` with the Agg canvas, never pyplot: no global state, safe in worker
threads and processes. Each `*_plot` returns PNG bytes; the matching `*_figure` returns the Figure and a
small info dict (what was drawn) for callers and tests that want to inspect it.
"""

from __future__ import annotations

import io
from collections.abc import Sequence
from typing import Any, Literal

import numpy as np

from wonderverse.camera import camera_centers
from wonderverse.check import CheckParams, CheckResult

DPI = 100
# Fixed margins rather than a layout engine: constrained layout doubled the time a plot takes (0.19 s -> 0.09 s for
# a check plot), and a report draws two per attempt
FIXED_MARGINS = {"left": 0.1, "right": 0.97, "bottom": 0.1, "top": 0.9}


def _png(fig: Any) -> bytes:
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(fig)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI)
    return buf.getvalue()


def segment_check_figure(
    check: CheckResult, params: CheckParams | None = None, title: str = ""
) -> tuple[Any, dict[str, Any]]:
    """Figure of one segment's check: translation (step ratio in scale-free mode, step length in absolute
    mode) and rotation step per frame pair i -> i+1 against their thresholds, flagged pairs marked in red.

    Returns (Figure, info) with info = {"flagged_marked": number of flagged pairs drawn, "n_steps": T-1}.
    """
    from matplotlib.figure import Figure

    params = params or CheckParams()
    fig = Figure(figsize=(8, 5), dpi=DPI)
    fig.subplots_adjust(**FIXED_MARGINS, hspace=0.12)
    ax_t, ax_r = fig.subplots(2, 1, sharex=True)
    steps = np.arange(len(check.rot_steps))
    flagged = np.array(sorted(set(check.flagged_frames)), dtype=int)
    if params.translation_mode == "scale_free":
        t_values, t_thresh, t_label = check.step_ratio, params.max_step_ratio, "step ÷ median step"
    else:
        t_values, t_thresh, t_label = check.trans_steps, params.abs_trans_thresh, "step (SfM units)"
    panels = ((ax_t, t_values, t_thresh, t_label), (ax_r, check.rot_steps, params.rot_thresh_rad, "rotation (rad)"))
    for ax, values, thresh, label in panels:
        ax.plot(steps, values, "o-", color="tab:blue", ms=3, lw=1)
        ax.axhline(thresh, color="tab:orange", ls="--", lw=1, label=f"threshold {thresh:g}")
        ax.set_ylabel(label)
        ax.set_ylim(bottom=0)
        if len(flagged):
            y = np.nan_to_num(values[flagged], nan=thresh)
            ax.scatter(flagged, y, s=60, marker="x", color="red", zorder=3, gid="flagged", label="flagged")
        ax.legend(loc="upper right", fontsize=8)
        ax.grid(alpha=0.3)
    ax_r.set_xlabel("frame pair i → i+1")
    verdict = "accepted" if check.accepted else "rejected"
    fig.suptitle(f"{title} — {verdict}" if title else verdict)
    # Counted from what was drawn (the markers on the translation panel), not from the input.
    marked = sum(len(c.get_offsets()) for c in ax_t.collections if c.get_gid() == "flagged")
    return fig, {"flagged_marked": marked, "n_steps": len(steps)}


def segment_check_plot(check: CheckResult, params: CheckParams | None = None, title: str = "") -> bytes:
    """PNG bytes of `segment_check_figure`."""
    return _png(segment_check_figure(check, params, title)[0])


def _plane_axes(centres: np.ndarray, plane: Literal["pca", "xy"]) -> tuple[np.ndarray, np.ndarray, str]:
    """Two orthonormal world directions to project on, and the axis names.

    "xy": world x and y (a +z-up world, e.g. procedural ground truth, seen from above).
    "pca": the two largest principal components of the camera centres (SfM worlds have an arbitrary
    orientation; for a camera moving over the ground this is the plane it moves in). Falls back to xy
    when fewer than 2 distinct centres are given.
    """
    if plane == "pca" and len(centres) >= 2 and np.ptp(centres, axis=0).max() > 0:
        _, _, vt = np.linalg.svd(centres - centres.mean(axis=0), full_matrices=True)
        return vt[0], vt[1], "PC"
    return np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]), "xy"


def trajectory_topview_figure(
    poses_list: Sequence[np.ndarray],
    labels: Sequence[str],
    title: str = "",
    plane: Literal["pca", "xy"] = "pca",
) -> tuple[Any, dict[str, Any]]:
    """Camera centres of one or more W2C trajectories ((T,4,4), NaN rows skipped) seen from above, with
    each camera's viewing direction (+z axis) as a short arrow. All trajectories must share one world
    frame (align SfM to ground truth first); they are projected on one common plane (see `_plane_axes`).

    Returns (Figure, info) with info = {"plane": "PC" or "xy", "n_cameras": [drawn per trajectory]}.
    """
    from matplotlib.figure import Figure

    if len(poses_list) != len(labels):
        raise ValueError(f"{len(poses_list)} trajectories but {len(labels)} labels")
    centres_list, dirs_list = [], []
    for poses in poses_list:
        poses = np.asarray(poses, dtype=np.float64)
        if poses.ndim != 3 or poses.shape[1:] != (4, 4):
            raise ValueError(f"poses must be (T,4,4), got {poses.shape}")
        ok = np.all(np.isfinite(poses.reshape(len(poses), -1)), axis=1)
        centres_list.append(camera_centers(poses[ok]))
        dirs_list.append(poses[ok, 2, :3])  # third row of R = camera +z (viewing direction) in world
    all_c = np.concatenate([c for c in centres_list if len(c)] or [np.zeros((0, 3))])
    u, v, name = _plane_axes(all_c, plane)
    extent = float(np.ptp(all_c @ np.stack([u, v]).T, axis=0).max()) if len(all_c) >= 2 else 1.0
    arrow = 0.08 * (extent if extent > 0 else 1.0)

    fig = Figure(figsize=(6, 6), dpi=DPI)
    fig.subplots_adjust(**FIXED_MARGINS | {"left": 0.16, "right": 0.95})  # room for long tick labels
    ax = fig.subplots()
    drawn = []
    for k, (c, dirs, label) in enumerate(zip(centres_list, dirs_list, labels, strict=True)):
        color = f"C{k % 10}"
        if len(c) == 0:
            ax.plot([], [], color=color, label=f"{label} (no registered frames)")
            drawn.append(0)
            continue
        x, y = c @ u, c @ v
        # Unit viewing directions projected: an arrow shrinks as the camera looks out of the plane.
        du, dv = dirs @ u, dirs @ v
        ax.plot(x, y, "o-", color=color, ms=3, lw=1, label=label)
        ax.plot(x[:1], y[:1], "s", color=color, ms=7)
        ax.quiver(x, y, du * arrow, dv * arrow, color=color, angles="xy", scale_units="xy", scale=1, width=0.004)
        ax.update_datalim(np.stack([x + du * arrow, y + dv * arrow], axis=1))  # keep arrow tips in view
        drawn.append(len(c))
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel(f"{name}1" if name == "PC" else "world x")
    ax.set_ylabel(f"{name}2" if name == "PC" else "world y")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    ax.set_title(title or "camera centres from above (square = first frame)")
    return fig, {"plane": name, "n_cameras": drawn}


def trajectory_topview_plot(
    poses_list: Sequence[np.ndarray],
    labels: Sequence[str],
    title: str = "",
    plane: Literal["pca", "xy"] = "pca",
) -> bytes:
    """PNG bytes of `trajectory_topview_figure`."""
    return _png(trajectory_topview_figure(poses_list, labels, title, plane)[0])


STEP_ORDER = ("plan", "generate_segments", "check", "poses", "priors", "splats", "outputs")


def growth_plot(runs: Sequence[dict[str, float]], labels: Sequence[str], title: str = "") -> bytes:
    """PNG bytes: the seconds of each run (one dict of step -> seconds each), a bar per run stacked by step, the
    runs labelled on the x axis."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(8, 3.6))
    ax = fig.subplots()
    x = np.arange(len(runs))
    bottom = np.zeros(len(runs))
    named = [s for s in STEP_ORDER if any(s in r for r in runs)]
    others = [s for s in dict.fromkeys(k for r in runs for k in r) if s not in STEP_ORDER]  # e.g. the report
    for step in named + others:
        h = np.array([r.get(step, 0.0) for r in runs])
        ax.bar(x, h, bottom=bottom, label=step)
        bottom += h
    ax.set_xticks(x, list(labels), fontsize=8, rotation=45 if len(runs) > 12 else 0)
    ax.set_ylabel("seconds")
    ax.set_title(title or "seconds of each run, by step")
    ax.legend(fontsize=8, ncols=4)
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    return _png(fig)

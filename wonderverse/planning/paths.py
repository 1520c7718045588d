"""The camera path each planned segment is conditioned on, and the waves segments can be generated in.

Segments form a tree (each extension continues from a frame of an earlier one): a segment's path starts at the
frame of its parent it continues from, so segments of one wave (same depth in the tree) can be generated together.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from wonderverse.camera import move_path
from wonderverse.planning.segments import Plan, PlannedSegment


@dataclass(frozen=True)
class SegmentPath:
    """A planned segment with its conditioning path (T,4,4) W2C (NaN for a user's clip), the generation-order index
    of the parent's frame it continues (None: no parent, or a clip) and its wave (0 for the initial segment)."""

    plan: PlannedSegment
    path: np.ndarray
    ref_idx: int | None
    wave: int

    @property
    def parent(self) -> str | None:
        return self.plan.reference_segment


def stitched_frame_index(reversed_: bool, n_frames: int, which: str) -> int:
    """Generation-order index of the `which` ('first'|'last') frame a segment shows in the stitched video."""
    first, last = (n_frames - 1, 0) if reversed_ else (0, n_frames - 1)
    return first if which == "first" else last


def conditioning_paths(
    plan: Plan,
    start_w2c: np.ndarray,
    frames_per_segment: int,
    strafe_m_per_deg: float,
    clip_lengths: Sequence[int] | None = None,
) -> dict[str, SegmentPath]:
    """Per segment id, in generation order: its path from `start_w2c` (the initial segment) or from the frame of its
    parent it continues, turning by its move and strafing `strafe_m_per_deg` sideways per degree of yaw. User clips
    (`clip_lengths` frames each) have no conditioning path (NaN) and no reference frame."""
    out: dict[str, SegmentPath] = {}
    for s in plan.segments:
        parent = out.get(s.reference_segment) if s.reference_segment else None
        if s.reference_segment and parent is None:
            raise ValueError(f"segment {s.id} continues from unknown segment {s.reference_segment}")
        if clip_lengths is not None:
            ref_idx, path = None, np.full((clip_lengths[len(out)], 4, 4), np.nan)
        else:
            T = frames_per_segment
            ref_idx = stitched_frame_index(parent.plan.reversed, T, s.reference) if parent else None
            start = parent.path[ref_idx] if parent and ref_idx is not None else start_w2c
            m = s.move
            yaw, pitch = np.radians(m.yaw_deg), np.radians(m.pitch_deg)
            path = move_path(start, yaw, pitch, m.forward_m, strafe_m_per_deg * m.yaw_deg, T)
        out[s.id] = SegmentPath(s, path, ref_idx, parent.wave + 1 if parent else 0)
    return out


def waves(paths: dict[str, SegmentPath]) -> list[list[str]]:
    """Segment ids grouped by wave, in order: each wave's parents are all in earlier waves."""
    return [[seg for seg, p in paths.items() if p.wave == w] for w in sorted({p.wave for p in paths.values()})]

"""What a scene store holds, as a JSON-able summary (`wonderverse inspect`)."""

from __future__ import annotations

from typing import Any

import zarr

from tasks import STEPS, step_keys
from tasks.segments import accepted_attempt, attempt_ids, segment_ids
from wonderverse.config import validate_config
from wonderverse.errors import WonderError
from wonderverse.schema import ATTEMPT, SEGMENT, SEGMENTS
from wonderverse.store import SceneStore


def _arrays(store: SceneStore, group_path: str) -> dict[str, Any]:
    """Every array under a group: relative path -> shape, dtype, chunks."""
    out: dict[str, Any] = {}
    g = store.group(group_path)
    for name, arr in g.arrays():
        out[name] = {"shape": list(arr.shape), "dtype": str(arr.dtype), "chunks": list(arr.chunks)}
    for name, sub in g.groups():
        if isinstance(sub, zarr.Group):
            out |= {f"{name}/{k}": v for k, v in _arrays(store, f"{group_path}/{name}").items()}
    return out


def _expected_keys(store: SceneStore) -> dict[str, str]:
    config = store.root.attrs.get("config")
    if not config:
        return {}
    try:
        return step_keys(STEPS, validate_config(config))
    except WonderError:
        return {}


def summarize(store: SceneStore) -> dict[str, Any]:
    """The scene's steps, segments and sizes. Schema documented in README.md (`inspect --json`)."""
    expected = _expected_keys(store)
    steps = []
    for s in STEPS:
        key = store.cache_key_of(s.group)
        status = "missing" if key is None else ("complete" if key == expected.get(s.name) else "stale")
        steps.append({"name": s.name, "group": s.group, "status": status, "cache_key": key})
    segments = []
    for seg in segment_ids(store):
        a = store.attrs(SEGMENT.at(seg=seg))
        attempts = []
        for k in attempt_ids(store, seg):
            ap = ATTEMPT.at(seg=seg, attempt=k)
            at = store.attrs(ap)
            attempts.append(
                {
                    "index": k,
                    "seed": at.get("seed"),
                    "check": store.attrs(ap.check) or None,
                    "faults": store.attrs(ap.gt).get("faults") if store.exists(ap.gt) else None,
                    "arrays": _arrays(store, ap),
                    "bytes": store.size_bytes(ap),
                }
            )
        segments.append(
            {
                "id": seg,
                "role": a.get("role"),
                "move": a.get("move"),
                "intent": a.get("intent"),
                "reversed": a.get("reversed"),
                "reference_segment": a.get("reference_segment"),
                "reference_frame": a.get("reference_frame"),
                "complete": a.get("complete") is True,
                "accepted_attempt": accepted_attempt(store, seg),
                "attempts": attempts,
            }
        )
    root = dict(store.root.attrs)
    added = ((root.get("spec") or {}).get("extensions") or {}).get("added") or []
    # the added extensions are the last segments of the plan, in order
    extensions = [
        {"words": w, "segment": seg["id"]}
        for w, seg in zip(added, segments[len(segments) - len(added) :], strict=False)
    ]
    return {
        "scene_dir": str(store.scene_dir),
        "format": root.get("format"),
        "wonderverse_version": root.get("wonderverse_version"),
        "spec": root.get("spec"),
        "order": store.attrs(SEGMENTS.path).get("order", []),
        "steps": steps,
        "segments": segments,
        "extensions": extensions,
        "size_bytes": store.size_bytes(),
    }

"""What a scene store holds, as a JSON-able summary (`wonderverse inspect`).

A scene made from the user's clips (video backend `files`) is described as what it is: `clips` lists each clip
in order with the frames used, where its K came from and its check's verdict; `priors` says which priors every
scene has (none: the splats train on colours alone)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import zarr

from tasks import STEPS, step_keys
from tasks.segments import accepted_attempt, attempt_ids, segment_ids
from wonderverse.config import validate_config
from wonderverse.errors import WonderError
from wonderverse.schema import ATTEMPT, PRIORS, PRIORS_SEGMENT, SEGMENT, SEGMENTS, SFM
from wonderverse.store import SceneStore


def _arrays(store: SceneStore, group_path: str) -> dict[str, Any]:
    """Every array under a group: relative path -> shape, dtype, chunks."""
    out: dict[str, Any] = {}
    g = store.group(group_path)
    try:
        arrays, groups = list(g.arrays()), list(g.groups())
    except Exception:  # damaged metadata (listed under `damaged`): name what still reads, one node at a time
        arrays, groups = _readable_members(store, group_path)
    for name, arr in arrays:
        out[name] = {"shape": list(arr.shape), "dtype": str(arr.dtype), "chunks": list(arr.chunks)}
    for name, sub in groups:
        if isinstance(sub, zarr.Group):
            out |= {f"{name}/{k}": v for k, v in _arrays(store, f"{group_path}/{name}").items()}
    return out


def _readable_members(store: SceneStore, group_path: str) -> tuple[list[tuple[str, Any]], list[tuple[str, Any]]]:
    """The arrays and sub-groups directly under a group whose metadata zarr can read (others are left out)."""
    arrays, groups = [], []
    for name in store.children(group_path):
        try:
            node = zarr.open(store.root.store, path=f"{group_path}/{name}", mode="r")
        except Exception:
            continue
        (groups if isinstance(node, zarr.Group) else arrays).append((name, node))
    return arrays, groups


def _shape(store: SceneStore, path: str) -> tuple[int, ...] | None:
    """An array's shape from its metadata (no data read), None when it is absent."""
    try:
        return tuple(zarr.open_array(store.root.store, path=path, mode="r").shape)
    except Exception:
        return None


def _spec(store: SceneStore) -> dict[str, Any]:
    return store.root.attrs.get("spec") or {}


def is_clip_scene(store: SceneStore) -> bool:
    """Whether the scene is the user's own clips (video backend `files`): nothing generated, nothing planned."""
    return (_spec(store).get("video") or {}).get("backend") == "files"


def fov_deg(K: Any, width: int) -> float | None:
    """Horizontal field of view in degrees (to 0.01) of a pinhole K (pixels) for frames `width` pixels wide."""
    try:
        fx = float(np.asarray(K, dtype=np.float64)[0, 0])
    except (TypeError, ValueError, IndexError):
        return None
    if not (math.isfinite(fx) and fx > 0 and width > 0):
        return None
    return round(math.degrees(2.0 * math.atan(width / (2.0 * fx))), 2)


def _k_source(store: SceneStore, seg: str, sfm: str, width: int) -> tuple[str, float | None]:
    """Where a clip's K came from ("given", "estimated" or "guessed") and its horizontal FOV in degrees.

    The check's SfM records `k_source` (and the K it used, as `K` or `fov_deg`) in its attributes; stores
    written before it did say only whether the segment's K was a guess (`k_is_guess`; absent: a guess)."""
    a = store.attrs(sfm)
    source = a.get("k_source")
    if source is None:
        source = "guessed" if store.attrs(SEGMENT.at(seg=seg)).get("k_is_guess", True) is not False else "given"
    if a.get("K") is not None:  # the K itself before its recorded FOV: one truth
        return str(source), fov_deg(a["K"], width)
    if isinstance(a.get("fov_deg"), int | float):
        return str(source), float(a["fov_deg"])
    # an estimated K is the one the SfM found; a given or guessed one is the segment's
    k_path = f"{sfm}/K" if source == "estimated" and _shape(store, f"{sfm}/K") else SEGMENT.at(seg=seg).K
    try:
        return str(source), fov_deg(store.array(k_path), width)
    except Exception:
        return str(source), None


def _verdict(store: SceneStore, seg: str, check: dict[str, Any]) -> tuple[str, list[str]]:
    """The check's verdict on a clip (`accepted`, `kept_failing`, `dropped`, `unchecked`) and its reasons."""
    acc = store.attrs(SEGMENT.at(seg=seg).accepted)
    if acc.get("complete") is not True:
        return "unchecked", []
    reasons = [str(r) for r in acc.get("reasons") or check.get("reasons") or []]
    if acc.get("dropped"):
        return "dropped", reasons
    if acc.get("reasons"):
        return "kept_failing", reasons
    return "accepted", []


def clip_kind(source: str) -> str:
    """The kind of a clip source as given: `video` (a file), `folder` (of images) or `pattern` (a glob)."""
    if set(source) & set("*?["):
        return "pattern"
    path = Path(source)
    if path.is_dir() or (not path.exists() and not path.suffix):
        return "folder"
    return "video"


def clips(store: SceneStore) -> list[dict[str, Any]] | None:
    """Per clip of a `files` scene, in the given order: segment, source (as given), name, kind, frames used,
    size [width, height], k_source and fov_deg, the check's verdict and its reasons. None for other scenes."""
    if not is_clip_scene(store):
        return None
    given = list((_spec(store).get("video") or {}).get("clips") or [])
    segs = segment_ids(store)
    n = max(len(given), max((int(s.lstrip("s")) + 1 for s in segs if s.lstrip("s").isdigit()), default=0))
    out = []
    for i in range(n):
        seg = f"s{i:03d}"
        # the segment records the clip it was read from (its plan entry's words); before that, the spec says
        source = str(store.attrs(SEGMENT.at(seg=seg)).get("intent") or (given[i] if i < len(given) else ""))
        row: dict[str, Any] = {
            "segment": seg,
            "source": source,
            "name": Path(source).name or source,
            "kind": clip_kind(source),
            "frames": None,
            "size": None,
            "k_source": None,
            "fov_deg": None,
            "verdict": "unread",
            "reasons": [],
        }
        ks = attempt_ids(store, seg)
        if ks:
            k = accepted_attempt(store, seg)
            ap = ATTEMPT.at(seg=seg, attempt=ks[-1] if k is None else k)
            shape = _shape(store, ap.frames)
            if shape:
                row["frames"], row["size"] = shape[0], [shape[2], shape[1]]
                row["k_source"], row["fov_deg"] = _k_source(store, seg, ap.sfm, shape[2])
            row["verdict"], row["reasons"] = _verdict(store, seg, store.attrs(ap.check))
        out.append(row)
    return out


def priors_words(depth: str | None, normal: str | None) -> str:
    """Which priors a scene has, in a few words ("none: colours only" when it has none)."""
    if depth is None and normal is None:
        return "unknown (no configuration stored)"
    if depth == "none" and normal == "none":
        return "none: colours only"
    return f"depth {depth}, normals {normal}"


def priors(store: SceneStore) -> dict[str, Any]:
    """The scene's priors: depth and normal backends (from the priors step when it ran, else from the stored
    configuration), whether the step computed them, the mean share of pixels the depth prior marked sky (None
    without one), and in words."""
    backends = store.attrs(PRIORS.path).get("backends")
    done = store.cache_key_of(PRIORS.path) is not None and isinstance(backends, list) and len(backends) == 2
    if done:
        depth, normal = (str(b) for b in backends)
    else:
        models = (((store.root.attrs.get("config") or {}).get("steps") or {}).get("priors") or {}).get("models") or {}
        depth, normal = models.get("depth_backend"), models.get("normal_backend")
    # the share of pixels the depth prior calls sky (`sky_beyond_ref`), over all frames as the step's line gives it
    segs = [store.attrs(PRIORS_SEGMENT.at(seg=s)) for s in store.children(PRIORS.path)] if done else []
    counted = [
        (float(a["sky_share"]), int(a["frames"]))
        for a in segs
        if isinstance(a.get("sky_share"), int | float) and isinstance(a.get("frames"), int)
    ]
    frames = sum(n for _, n in counted)
    sky = round(sum(x * n for x, n in counted) / frames, 4) if frames else None
    words = priors_words(depth, normal) + ("" if sky is None else f"; {100 * sky:.1f} % of pixels sky")
    return {"depth_backend": depth, "normal_backend": normal, "computed": done, "sky_share": sky, "words": words}


def global_k(store: SceneStore) -> dict[str, Any] | None:
    """Where the global solve's K came from (`k_source`, recorded by the poses step) and its FOV; None when the
    poses step has not run or did not record it."""
    a = store.attrs(SFM.path)
    if store.cache_key_of(SFM.path) is None or a.get("k_source") is None:
        return None
    segs = a.get("segments") or []
    k = accepted_attempt(store, segs[0]) if segs else None
    shape = _shape(store, ATTEMPT.at(seg=segs[0], attempt=k).frames) if k is not None else None
    fov = None
    if shape and (a.get("K") is not None or _shape(store, SFM.K)):  # the K itself before its recorded FOV
        fov = fov_deg(a["K"] if a.get("K") is not None else store.array(SFM.K), shape[2])
    if fov is None and isinstance(a.get("fov_deg"), int | float):
        fov = float(a["fov_deg"])
    return {"k_source": str(a["k_source"]), "fov_deg": fov}


GUIDE_TRUTH = ("coverage", "psnr_db", "depth_absrel", "depth_off_share")


def guide(store: SceneStore, seg: str, k: int) -> dict[str, Any] | None:
    """The guide attempt `k` of segment `seg` was generated from (guided flows' extensions): {source, coverage,
    reason, truth}. source: where it was rendered from ("segment s000, attempt 0"), None when the extension was
    generated without one (its parent could not be placed in the plan's world: `reason` says why); coverage:
    share of its pixels known (0..1); truth: the guide against the ground truth, measured by the procedural
    backend ({coverage, psnr_db, depth_absrel, depth_off_share}; None for other backends). None when the attempt
    was generated without looking for a guide (an unguided flow, an initial segment)."""
    ap = ATTEMPT.at(seg=seg, attempt=k)
    record = store.attrs(ap).get("guide")
    if not isinstance(record, dict):
        return None
    truth = store.attrs(ap.gt).get("guide") if store.exists(ap.gt) else None
    coverage = record.get("coverage")
    return {
        "source": record.get("source"),
        "coverage": float(coverage) if isinstance(coverage, int | float) else None,
        "reason": str(record.get("reason") or ""),
        "truth": {name: truth.get(name) for name in GUIDE_TRUTH} if isinstance(truth, dict) else None,
    }


def guide_words(g: dict[str, Any] | None) -> str:
    """A guide (`guide`) in a few words: its share of known pixels ("71 %"), "none" when the extension was
    generated without one, "-" for an attempt that looked for none."""
    if g is None:
        return "-"
    if g["source"] is None or g["coverage"] is None:
        return "none"
    return f"{100 * g['coverage']:.0f} %"


def _expected_keys(store: SceneStore) -> dict[str, str]:
    config = store.root.attrs.get("config")
    if not config:
        return {}
    try:
        return step_keys(STEPS, validate_config(config))
    except WonderError:
        return {}


def summarize(store: SceneStore) -> dict[str, Any]:
    """The scene's steps, segments and sizes. Schema documented in docs/usage.md (`inspect --json`)."""
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
                    "guide": guide(store, seg, k),
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
        "clips": clips(store),
        "priors": priors(store),
        "global_k": global_k(store),
        "size_bytes": store.size_bytes(),
        "damaged": damaged(store),
    }


def damaged(store: SceneStore) -> list[dict[str, Any]]:
    """The store's damaged groups (`SceneStore.damaged_groups`): [{group, problems}], by path. A group listed here
    is rebuilt by the step that wrote it on the next run, where its inputs are intact."""
    return [{"group": g, "problems": p} for g, p in store.damaged_groups().items()]


def damaged_lines(info: dict[str, Any]) -> list[str]:
    """One line per damaged group of a `summarize` result, for the text output (none when nothing is damaged)."""
    return [
        f"damaged: {d['group']}: {'; '.join(d['problems'][:3])}{' …' if len(d['problems']) > 3 else ''}"
        for d in info.get("damaged") or []
    ]

"""What a scene store holds, as typed records (`scene_summary`) and as JSON (`summarize`, `wonderverse inspect`).

Every attribute is read through the schema's models (`SceneStore.meta`). A scene made from the user's clips (video
backend `files`) is described as what it is: `clips` lists each clip in order with the frames used, where its K came
from and its verdict (the check's, or `recovered` where the global solve registered a clip the check had failed,
with both figures); `priors` says which priors every scene has (none: the splats train on colours alone);
`global_k` which K every output uses and why; `quality` the poses against their gates and the splats' PSNR/SSIM
(`flows.scene_quality`)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import zarr
from pydantic import BaseModel, ConfigDict, ValidationError

from flows.scene_quality import Quality, gates_of, quality, registration
from tasks import STEPS, step_keys
from tasks.segments import accepted_attempt, attempt_ids, segment_ids, segment_meta
from wonderverse.config import RunConfig, SceneSpec, validate_config
from wonderverse.errors import WonderError
from wonderverse.schema import ATTEMPT, PRIORS, PRIORS_SEGMENT, ROOT, SEGMENT, SEGMENTS, SFM
from wonderverse.schema.attrs import AttemptCheckAttrs, GuideTruth, RootAttrs
from wonderverse.store import SceneStore


class Record(BaseModel):
    """A record `inspect` shows; `model_dump(mode="json")` is its part of `inspect --json`."""

    model_config = ConfigDict(frozen=True)


class StepStatus(Record):
    """A pipeline step in the store: `complete` (its key matches the stored config's), `stale` (complete under
    another key), `missing` (not run), and after a run that stopped on a failed step (`RootAttrs.failed_run`):
    `failed` (the step it stopped at) and `ran_then_failed` (complete under that run's key: that run completed it,
    then failed at a later step; a re-run reuses it)."""

    name: str
    group: str
    status: str
    cache_key: str | None


class GuideInfo(Record):
    """The guide an attempt of a guided flow's extension was generated from (see `guide`)."""

    source: str | None
    coverage: float | None
    reason: str = ""
    truth: GuideTruth | None = None


class ArrayInfo(Record):
    shape: list[int]
    dtype: str
    chunks: list[int]


class AttemptSummary(Record):
    """A generation attempt: its seed, the check's decision (None: not checked), the injected faults (procedural
    ground truth; None without one), its guide, its arrays by path below it, and its bytes."""

    index: int
    seed: int | None
    check: AttemptCheckAttrs | None
    faults: dict[str, Any] | None
    guide: GuideInfo | None
    arrays: dict[str, ArrayInfo]
    bytes: int


class SegmentSummary(Record):
    id: str
    role: str
    move: str
    intent: str
    reversed: bool
    reference_segment: str | None
    reference_frame: int | None
    complete: bool
    accepted_attempt: int | None
    attempts: list[AttemptSummary]


class Extension(Record):
    """One `extend`: the user's words and the segment they made."""

    words: str
    segment: str


class ClipRow(Record):
    """One of the user's clips (see `clips`). check_registered, poses_registered: [frames registered, frames given]
    by the check's SfM and by the global solve (None: not run)."""

    segment: str
    source: str
    name: str
    kind: str
    frames: int | None = None
    size: list[int] | None = None
    k_source: str | None = None
    fov_deg: float | None = None
    verdict: str = "unread"
    reasons: list[str] = []
    check_registered: list[int] | None = None
    poses_registered: list[int] | None = None


class PriorsInfo(Record):
    """The scene's priors (see `priors`)."""

    depth_backend: str | None
    normal_backend: str | None
    computed: bool
    sky_share: float | None
    words: str


class GlobalK(Record):
    """The K every output uses (the global solve's): where it came from, its horizontal field of view (degrees), the
    matrix (pixels of the frames), whether the given K was held fixed (None: recorded before it was) and why, in
    words."""

    k_source: str
    fov_deg: float | None
    K: list[list[float]] | None = None
    held: bool | None = None
    reason: str = ""


class DamagedGroup(Record):
    group: str
    problems: list[str]


class SceneSummary(Record):
    """Everything `inspect` shows; its JSON is documented in docs/usage.md (`inspect --json`)."""

    scene_dir: str
    format: int
    wonderverse_version: str
    spec: dict[str, Any] | None
    order: list[str]
    steps: list[StepStatus]
    segments: list[SegmentSummary]
    extensions: list[Extension]
    clips: list[ClipRow] | None
    priors: PriorsInfo
    global_k: GlobalK | None
    quality: Quality
    size_bytes: int
    damaged: list[DamagedGroup]


# -- the scene's settings -------------------------------------------------------------------------


def root_meta(store: SceneStore) -> RootAttrs:
    """The root group's attributes: format, version, spec and config as stored."""
    return store.meta(ROOT.path, complete=False)


def scene_spec(store: SceneStore) -> SceneSpec | None:
    """The SceneSpec of the scene's latest run; None when none is stored or this version cannot read it."""
    spec = root_meta(store).spec
    try:
        return SceneSpec.model_validate(spec) if spec is not None else None
    except ValidationError:
        return None


def run_config(store: SceneStore) -> RunConfig | None:
    """The RunConfig of the scene's last completed run; None when none is stored or this version cannot read it."""
    config = root_meta(store).config
    try:
        return validate_config(config) if config else None
    except WonderError:
        return None


def is_clip_scene(store: SceneStore) -> bool:
    """Whether the scene is the user's own clips (video backend `files`): nothing generated, nothing planned."""
    spec = scene_spec(store)
    return spec is not None and spec.video.backend == "files"


# -- arrays ---------------------------------------------------------------------------------------


def _arrays(store: SceneStore, group_path: str) -> dict[str, ArrayInfo]:
    """Every array under a group: relative path -> shape, dtype, chunks."""
    out: dict[str, ArrayInfo] = {}
    g = store.group(group_path)
    try:
        arrays, groups = list(g.arrays()), list(g.groups())
    except Exception:  # damaged metadata (listed under `damaged`): name what still reads, one node at a time
        arrays, groups = _readable_members(store, group_path)
    for name, arr in arrays:
        out[name] = ArrayInfo(shape=list(arr.shape), dtype=str(arr.dtype), chunks=list(arr.chunks))
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
        return tuple(store.open_array(path).shape)
    except Exception:
        return None


def fov_deg(K: Any, width: int) -> float | None:
    """Horizontal field of view in degrees (to 0.01) of a pinhole K (pixels) for frames `width` pixels wide."""
    try:
        fx = float(np.asarray(K, dtype=np.float64)[0, 0])
    except (TypeError, ValueError, IndexError):
        return None
    if not (math.isfinite(fx) and fx > 0 and width > 0):
        return None
    return round(math.degrees(2.0 * math.atan(width / (2.0 * fx))), 2)


# -- clips ----------------------------------------------------------------------------------------


def _k_source(store: SceneStore, seg: str, sfm: str, width: int) -> tuple[str, float | None]:
    """Where a clip's K came from ("given", "estimated" or "guessed") and its horizontal FOV in degrees.

    The check's SfM records `k_source` (and the K it used, as `K` or `fov_deg`) in its attributes; stores
    written before it did say only whether the segment's K was a guess (`k_is_guess`; absent: a guess)."""
    a = store.meta(sfm, complete=False)
    source = a.k_source if a is not None else None
    if source is None:
        source = "guessed" if segment_meta(store, seg).k_is_guess else "given"
    if a is not None and a.K is not None:  # the K itself before its recorded FOV: one truth
        return source, fov_deg(a.K, width)
    if a is not None and a.fov_deg is not None:
        return source, float(a.fov_deg)
    # an estimated K is the one the SfM found; a given or guessed one is the segment's
    k_path = f"{sfm}/K" if source == "estimated" and _shape(store, f"{sfm}/K") else SEGMENT.at(seg=seg).K
    try:
        return source, fov_deg(store.array(k_path), width)
    except Exception:
        return source, None


def _verdict(
    store: SceneStore,
    seg: str,
    check: AttemptCheckAttrs | None,
    registered: tuple[tuple[int, int] | None, tuple[int, int] | None] = (None, None),
    min_frac: float = 0.8,
) -> tuple[str, list[str]]:
    """A clip's verdict (`accepted`, `kept_failing`, `recovered`, `dropped`, `unchecked`) and the check's reasons.
    `recovered`: kept although its check failed, and the global solve registered more of its frames than the check
    did, at least `min_frac` of those it was given (`registered`: the check's and the global solve's figures)."""
    acc = store.meta(SEGMENT.at(seg=seg).accepted)
    if acc is None:
        return "unchecked", []
    reasons = [str(r) for r in acc.reasons or (check.reasons if check is not None else [])]
    if acc.dropped:
        return "dropped", reasons
    if acc.reasons:
        by_check, by_poses = registered
        registers = by_poses is not None and by_poses[1] > 0 and by_poses[0] / by_poses[1] >= min_frac
        if registers and (by_check is None or by_poses[0] > by_check[0]):  # type: ignore[index]
            return "recovered", reasons
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


def clips(store: SceneStore) -> list[ClipRow] | None:
    """Per clip of a `files` scene, in the given order: segment, source (as given), name, kind, frames used,
    size [width, height], k_source and fov_deg, the check's verdict and its reasons. None for other scenes."""
    spec = scene_spec(store)
    if spec is None or spec.video.backend != "files":
        return None
    given = list(spec.video.clips)
    min_frac = gates_of(run_config(store)).min_registered_frac
    segs = segment_ids(store)
    n = max(len(given), max((int(s.lstrip("s")) + 1 for s in segs if s.lstrip("s").isdigit()), default=0))
    out = []
    for i in range(n):
        seg = f"s{i:03d}"
        # the segment records the clip it was read from (its plan entry's words); before that, the spec says
        written = store.meta(SEGMENT.at(seg=seg), complete=False)
        source = str((written.intent if written is not None else "") or (given[i] if i < len(given) else ""))
        row: dict[str, Any] = {}
        ks = attempt_ids(store, seg)
        if ks:
            k = accepted_attempt(store, seg)
            ap = ATTEMPT.at(seg=seg, attempt=ks[-1] if k is None else k)
            shape = _shape(store, ap.frames)
            if shape:
                row["frames"], row["size"] = shape[0], [shape[2], shape[1]]
                row["k_source"], row["fov_deg"] = _k_source(store, seg, ap.sfm, shape[2])
            figures = registration(store, seg)
            row["check_registered"], row["poses_registered"] = (list(f) if f else None for f in figures)
            row["verdict"], row["reasons"] = _verdict(store, seg, store.meta(ap.check), figures, min_frac)
        out.append(ClipRow(segment=seg, source=source, name=Path(source).name or source, kind=clip_kind(source), **row))
    return out


# -- priors, K, guides ----------------------------------------------------------------------------


def priors_words(depth: str | None, normal: str | None) -> str:
    """Which priors a scene has, in a few words ("none: colours only" when it has none)."""
    if depth is None and normal is None:
        return "unknown (no configuration stored)"
    if depth == "none" and normal == "none":
        return "none: colours only"
    return f"depth {depth}, normals {normal}"


def priors(store: SceneStore) -> PriorsInfo:
    """The scene's priors: depth and normal backends (from the priors step when it ran, else from the stored
    configuration), whether the step computed them, the share of pixels the depth prior marked sky (None
    without one), and in words."""
    step = store.meta(PRIORS.path)
    done = step is not None and len(step.backends) == 2
    depth: str | None
    normal: str | None
    if done:
        depth, normal = (str(b) for b in step.backends)
    else:
        cfg = run_config(store)
        models = cfg.steps.priors.models if cfg is not None else None
        depth, normal = (models.depth_backend, models.normal_backend) if models is not None else (None, None)
    # the share of pixels the depth prior calls sky (`sky_beyond_ref`), over all frames as the step's line gives it
    segs = [store.meta(PRIORS_SEGMENT.at(seg=s), complete=False) for s in store.children(PRIORS.path)] if done else []
    counted = [(a.sky_share, a.frames) for a in segs if a is not None and a.sky_share is not None]
    frames = sum(n for _, n in counted)
    sky = round(sum(x * n for x, n in counted) / frames, 4) if frames else None
    words = priors_words(depth, normal) + ("" if sky is None else f"; {100 * sky:.1f} % of pixels sky")
    return PriorsInfo(depth_backend=depth, normal_backend=normal, computed=done, sky_share=sky, words=words)


def global_k(store: SceneStore) -> GlobalK | None:
    """Where the global solve's K came from (`k_source`, recorded by the poses step) and its FOV; None when the
    poses step has not run or did not record it."""
    a = store.meta(SFM.path)
    if a is None or a.k_source is None:
        return None
    k = accepted_attempt(store, a.segments[0]) if a.segments else None
    shape = _shape(store, ATTEMPT.at(seg=a.segments[0], attempt=k).frames) if k is not None else None
    fov = None
    if shape and (a.K is not None or _shape(store, SFM.K)):  # the K itself before its recorded FOV
        fov = fov_deg(a.K if a.K is not None else store.array(SFM.K), shape[2])
    if fov is None and a.fov_deg is not None:
        fov = float(a.fov_deg)
    K = a.K if a.K is not None else (store.array(SFM.K).tolist() if _shape(store, SFM.K) else None)
    return GlobalK(k_source=a.k_source, fov_deg=fov, K=K, held=a.k_held, reason=a.k_reason)


def guide(store: SceneStore, seg: str, k: int) -> GuideInfo | None:
    """The guide attempt `k` of segment `seg` was generated from (guided flows' extensions). source: where it was
    rendered from ("segment s000, attempt 0"), None when the extension was generated without one (its parent could
    not be placed in the plan's world: `reason` says why); coverage: share of its pixels known (0..1); truth: the
    guide against the ground truth, measured by the procedural backend (None for other backends). None when the
    attempt was generated without looking for a guide (an unguided flow, an initial segment)."""
    ap = ATTEMPT.at(seg=seg, attempt=k)
    attempt = store.meta(ap, complete=False)
    record = attempt.guide if attempt is not None else None
    if record is None:
        return None
    truth = store.meta(ap.gt, complete=False)
    return GuideInfo(
        source=record.source,
        coverage=record.coverage,
        reason=record.reason,
        truth=truth.guide if truth is not None else None,
    )


def guide_words(g: GuideInfo | None) -> str:
    """A guide (`guide`) in a few words: its share of known pixels ("71 %"), "none" when the extension was
    generated without one, "-" for an attempt that looked for none."""
    if g is None:
        return "-"
    if g.source is None or g.coverage is None:
        return "none"
    return f"{100 * g.coverage:.0f} %"


# -- the summary ----------------------------------------------------------------------------------


def expected_keys(store: SceneStore) -> dict[str, str]:
    """The cache key of every step under the stored config ({} when none is stored or readable)."""
    cfg = run_config(store)
    return step_keys(STEPS, cfg) if cfg is not None else {}


def step_statuses(store: SceneStore) -> list[StepStatus]:
    """Every pipeline step with its status (`StepStatus`) against the stored config, the last run's failure, and its
    cache key."""
    expected = expected_keys(store)
    failed = root_meta(store).failed_run
    out = []
    for s in STEPS:
        key = store.cache_key_of(s.group)
        status = "missing" if key is None else ("complete" if key == expected.get(s.name) else "stale")
        if failed is not None and s.name == failed.step:
            status = "failed"
        elif failed is not None and status == "stale" and key == failed.keys.get(s.name):
            status = "ran_then_failed"
        out.append(StepStatus(name=s.name, group=s.group, status=status, cache_key=key))
    return out


def _attempt(store: SceneStore, seg: str, k: int) -> AttemptSummary:
    ap = ATTEMPT.at(seg=seg, attempt=k)
    attempt, truth = store.meta(ap, complete=False), store.meta(ap.gt, complete=False)
    return AttemptSummary(
        index=k,
        seed=attempt.seed if attempt is not None else None,
        check=store.meta(ap.check),
        faults=truth.faults if truth is not None else None,
        guide=guide(store, seg, k),
        arrays=_arrays(store, ap),
        bytes=store.size_bytes(ap),
    )


def _segment(store: SceneStore, seg: str) -> SegmentSummary:
    a = segment_meta(store, seg)
    return SegmentSummary(
        id=seg,
        role=a.role,
        move=a.move,
        intent=a.intent,
        reversed=a.reversed,
        reference_segment=a.reference_segment,
        reference_frame=a.reference_frame,
        complete=store.cache_key_of(SEGMENT.at(seg=seg)) is not None,
        accepted_attempt=accepted_attempt(store, seg),
        attempts=[_attempt(store, seg, k) for k in attempt_ids(store, seg)],
    )


def scene_summary(store: SceneStore) -> SceneSummary:
    """The scene's steps, segments, clips, priors and sizes."""
    root = root_meta(store)
    segments = [_segment(store, seg) for seg in segment_ids(store)]
    spec = scene_spec(store)
    added = list(spec.extensions.added) if spec is not None else []
    # the added extensions are the last segments of the plan, in order
    extensions = [
        Extension(words=w, segment=seg.id)
        for w, seg in zip(added, segments[len(segments) - len(added) :], strict=False)
    ]
    order = store.meta(SEGMENTS.path, complete=False)
    return SceneSummary(
        scene_dir=str(store.scene_dir),
        format=root.format,
        wonderverse_version=root.wonderverse_version,
        spec=root.spec,
        order=order.order if order is not None else [],
        steps=step_statuses(store),
        segments=segments,
        extensions=extensions,
        clips=clips(store),
        priors=priors(store),
        global_k=global_k(store),
        quality=quality(store, gates_of(run_config(store))),
        size_bytes=store.size_bytes(),
        damaged=damaged(store),
    )


def summarize(store: SceneStore) -> dict[str, Any]:
    """`scene_summary` as JSON (`inspect --json`; schema documented in docs/usage.md)."""
    return scene_summary(store).model_dump(mode="json")


def damaged(store: SceneStore) -> list[DamagedGroup]:
    """The store's damaged groups (`SceneStore.damaged_groups`), by path. A group listed here is rebuilt by the step
    that wrote it on the next run, where its inputs are intact."""
    return [DamagedGroup(group=g, problems=p) for g, p in store.damaged_groups().items()]


def damaged_lines(summary: SceneSummary) -> list[str]:
    """One line per damaged group of a summary, for the text output (none when nothing is damaged)."""
    return [
        f"damaged: {d.group}: {'; '.join(d.problems[:3])}{' …' if len(d.problems) > 3 else ''}" for d in summary.damaged
    ]

"""The studio's scenes: the folders of its root, what the page shows of each, and their files, read-only.

Every scene is a folder directly inside the studio's root, named by one path component (`scene_dir` refuses
anything else before a path is built), and every file served must resolve inside that folder (`scene_entry`:
symlinks leading out are refused). The studio writes nothing into a scene itself: only its jobs (the CLI, under
the scene lock) do; the splats it shows before the outputs step has exported them are written into the studio's
own cache folder (`live_splats`).
"""

from __future__ import annotations

import os
import threading
from pathlib import Path
from typing import Any
from urllib.parse import unquote

from wonderverse.errors import WonderError

REPORT = "report.html"
LIVE_SPLATS = "live.ply"


class NotFound(WonderError):
    """No such scene (404, not 400: the name itself is fine)."""


def check_name(name: str) -> str:
    """`name` when it is one folder name for a scene inside the root, else WonderError saying why: the project's one
    rule for names that become paths (`wonderverse.text.scene_name_problem`: one path component, not `.` or `..`
    after NFKC normalisation, not hidden, no separator or control character, no space at either end, at most 255
    bytes)."""
    from wonderverse.text import scene_name_problem

    problem = scene_name_problem(name)
    if problem is not None:
        shown = repr(name[:40] + ("…" if len(name) > 40 else "")) if isinstance(name, str) else "?"
        raise WonderError(f"scene name {shown}: {problem}")
    return name


def scene_dir(root: Path, name: str) -> Path:
    """The folder of scene `name` inside `root` (which need not exist yet); WonderError for a bad name, or when the
    folder is a symlink or resolves outside the root."""
    path = Path(root) / check_name(name)
    if path.is_symlink() or not path.resolve().is_relative_to(Path(root).resolve()):
        raise WonderError(f"scene name {name!r}: that folder leads outside the studio's folder (a symlink)")
    return path


def existing_scene(root: Path, name: str) -> Path:
    """The folder of an existing scene `name` (one holding a store); NotFound when there is none."""
    from wonderverse.store import STORE_NAME

    path = scene_dir(root, name)
    if not (path / STORE_NAME).is_dir():
        raise NotFound(f"no scene {name!r} in the studio's folder")
    return path


def scene_names(root: Path) -> list[str]:
    """The scenes of the root: its non-hidden, non-symlink folders holding a store, by name."""
    from wonderverse.store import STORE_NAME

    if not Path(root).is_dir():
        return []
    return sorted(
        p.name
        for p in Path(root).iterdir()
        if not p.name.startswith(".") and not p.is_symlink() and (p / STORE_NAME).is_dir()
    )


def scene_entry(folder: Path, rel: str) -> Path | None:
    """The regular file or folder inside `folder` that the URL path `rel` names (still %-encoded), or None: the
    rules of `flows.view.scene_file` (no `..`, hidden parts, backslashes, NUL or drive letters; symlinks must stay
    inside), folders allowed (they download as a zip)."""
    raw = unquote(rel)
    if "\\" in raw or "\0" in raw:
        return None
    parts = [p for p in raw.split("/") if p]
    if not parts or any(p in (".", "..") or p.startswith(".") or ":" in p for p in parts):
        return None
    base = Path(folder).resolve()
    try:
        path = base.joinpath(*parts).resolve(strict=True)
    except (OSError, RuntimeError):
        return None
    return path if (path.is_file() or path.is_dir()) and path.is_relative_to(base) else None


def folder_files(folder: Path) -> list[tuple[Path, str]]:
    """(path, name in the zip) of every regular file under `folder` that stays inside it (symlinks out skipped)."""
    base = folder.resolve()
    found = []
    for dirpath, dirnames, filenames in os.walk(base):
        dirnames[:] = sorted(d for d in dirnames if not d.startswith("."))
        for f in sorted(filenames):
            p = Path(dirpath) / f
            if not f.startswith(".") and p.resolve().is_relative_to(base) and p.resolve().is_file():
                found.append((p, str(p.relative_to(base.parent))))
    return found


def _verdict(ok: bool | None) -> str:
    return "-" if ok is None else ("ok" if ok else "rejected")


def scene_info(root: Path, name: str) -> dict[str, Any]:
    """What the page shows of a scene: prompt, steps, segments (planned move, words, check and plan-following
    verdicts), Gaussians, the exports present, and `view_key`: the splats' cache key, so the 3D view reloads once
    per new splats (as soon as the splats step has written them), not again when the outputs step re-levels the
    frame by a fraction of a degree (the next load shows that). Read while a job may be writing: the store
    commits whole groups, and what is not there yet is left out."""
    from flows.inspect import scene_summary
    from wonderverse.schema import OUTPUTS, SFM, SPLATS
    from wonderverse.store import SceneStore

    folder = existing_scene(root, name)
    store = SceneStore.open(folder)
    summary = scene_summary(store)
    spec = summary.spec or {}
    segments = []
    for s in summary.segments:
        shown = next((a for a in s.attempts if a.index == s.accepted_attempt), s.attempts[-1] if s.attempts else None)
        check = shown.check if shown is not None else None
        plan = check.plan_following if check is not None else None
        plan = plan.model_dump() if hasattr(plan, "model_dump") else plan or {}
        segments.append(
            {
                "id": s.id,
                "role": s.role,
                "move": s.move,
                "words": s.intent,
                "complete": s.complete,
                "check": _verdict(check.accepted if check is not None else None),
                "check_reasons": list(check.reasons) if check is not None else [],
                "plan_following": _verdict(plan.get("ok")),
                "plan_reasons": [str(r) for r in plan.get("reasons") or []],
            }
        )
    splats = store.meta(SPLATS.path)
    outputs = store.meta(OUTPUTS.path)
    files = [f.path for f in outputs.files if (folder / f.path).exists()] if outputs is not None else []
    if (folder / REPORT).is_file():
        files.append(REPORT)
    splats_key = store.cache_key_of(SPLATS.path)
    return {
        "name": name,
        "prompt": spec.get("prompt"),
        "seed": spec.get("seed"),
        "steps": [{"name": s.name, "status": s.status} for s in summary.steps],
        "segments": segments,
        "extensions": [e.model_dump() for e in summary.extensions],
        "gaussians": splats.metrics.n_gaussians if splats is not None else None,
        "posed": store.cache_key_of(SFM.path) is not None,
        "view_key": splats_key[:16] if splats_key else None,
        "files": files,
        "damaged": [d.group for d in summary.damaged],
    }


_live_lock = threading.Lock()


def live_splats(folder: Path, cache: Path) -> Path:
    """A splats.ply of the scene's current Gaussians (the store's `splats/`, written as soon as the splats step
    has run) in the frame the viewer's cameras are in (`flows.view.world_from_sfm`), written into `cache` once per
    splats and outputs key; WonderError when the scene has no splats yet. The outputs step's own splats.ply is
    pruned and comes later: this one shows the new Gaussians of an extension a step sooner."""
    from flows.view import world_from_sfm
    from wonderverse.schema import OUTPUTS, SPLATS
    from wonderverse.store import SceneStore

    store = SceneStore.open(folder)
    for _ in range(3):  # a job may commit new splats while they are read: read again under the new key
        key = (store.cache_key_of(SPLATS.path), store.cache_key_of(OUTPUTS.path))
        if key[0] is None:
            raise WonderError(f"{folder.name} has no splats yet (the splats step has not run)")
        path = Path(cache) / f"{folder.name}.{key[0][:16]}.{(key[1] or 'none')[:16]}.ply"
        if path.is_file():
            return path
        with _live_lock:
            from wonderverse.splats.model import GaussianModel, normalization_from_dict
            from wonderverse.splats.ply import write_ply

            try:
                meta = store.meta(SPLATS.path)
                arrays = {n: store.array(getattr(SPLATS, n)) for n in GaussianModel.PARAM_NAMES}
                norm = normalization_from_dict(meta.normalization).compose(world_from_sfm(store).inverse())
            except (OSError, KeyError, ValueError, AttributeError):  # a group replaced while it was read
                continue
            if (store.cache_key_of(SPLATS.path), store.cache_key_of(OUTPUTS.path)) != key:
                continue
            tmp = path.with_name(f".{path.name}.tmp")
            write_ply(tmp, arrays, norm)
            os.replace(tmp, path)
            for old in Path(cache).glob(f"{folder.name}.*.ply"):  # earlier splats of this scene
                if old != path:
                    old.unlink(missing_ok=True)
        return path
    raise WonderError(f"{folder.name}: the splats kept changing while they were read; reload the view")


def view_page(folder: Path, cache: Path) -> str:
    """The viewer's page (`flows.view.page_html`, cameras drawn) of the scene's current splats, which it fetches as
    LIVE_SPLATS beside it."""
    from flows.view import page_html, scene_view

    live = live_splats(folder, cache)
    view = scene_view(folder, splat_path=live)
    view = type(view)(**{**view.__dict__, "splat_file": LIVE_SPLATS})
    return page_html(view, folder.name, studio=True)

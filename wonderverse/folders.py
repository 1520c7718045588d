"""Judging a scene folder and the files a command reads, before anything is written or anything heavy loads.

Standard library only: a command refuses a bad `--out`, a folder that is not a scene, a config that is a pipe or a
store whose metadata is hostile in the time Python takes to start, and it does so before it takes any lock or
creates anything, so a refusal leaves every byte and every name of the folder as it was. `wonderverse.store`
re-exports what it needs of this (the names, `check_scene_dir`, `scene_name_problem`).
"""

from __future__ import annotations

import json
import os
import stat
from pathlib import Path
from typing import Any

from wonderverse.errors import StoreError, WonderError
from wonderverse.text import scene_name_problem

__all__ = [
    "LOCK_NAME",
    "STORE_NAME",
    "check_scene_dir",
    "check_writable",
    "json_problem",
    "read_limited_json",
    "read_regular",
    "root_attrs",
    "scene_name_problem",
]

STORE_NAME = "scene.zarr"
LOCK_NAME = ".wonderverse.lock"  # beside the store; see `wonderverse.store.scene_lock`
# Zarr metadata (a node's zarr.json) as this version writes it: a root's attributes (configs, the run history) stay
# well under a megabyte, arrays' under a few kilobytes. What exceeds these was not written by WonderVerse.
MAX_META_BYTES = 16_000_000
MAX_META_DEPTH = 64  # nesting of lists and mappings (ours: under 15)
MAX_META_INT = 2**53  # JSON integers beyond this are not exact in most readers
_LOCK_KEYS = frozenset({"pid", "host", "since"})


def json_problem(value: Any, max_depth: int = MAX_META_DEPTH, max_int: int = MAX_META_INT) -> str | None:
    """Why parsed JSON `value` is outside the limits (nested deeper than `max_depth`, an integer beyond `max_int`),
    None when within; iterative, so a hostile document cannot exhaust the stack."""
    stack: list[tuple[Any, int]] = [(value, 1)]
    while stack:
        x, depth = stack.pop()
        if depth > max_depth:
            return f"it is nested deeper than {max_depth} levels"
        if isinstance(x, dict):
            stack += [(v, depth + 1) for v in x.values()]
        elif isinstance(x, list):
            stack += [(v, depth + 1) for v in x]
        elif isinstance(x, int) and not isinstance(x, bool) and abs(x) > max_int:
            return f"it holds an integer beyond {max_int}"
    return None


def read_limited_json(path: Path, max_bytes: int = MAX_META_BYTES) -> Any:
    """The JSON document in the regular file `path`, read within limits (at most `max_bytes` bytes, nesting and
    integers as `json_problem` allows); ValueError saying what is wrong (OSError when it cannot be read). Every read
    of zarr metadata before zarr parses it goes through this: Python's parser recurses (a document nested 100 000
    deep raises RecursionError) and zarr allocates what the metadata asks for."""
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_NOFOLLOW", 0))
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise ValueError("it is not a regular file")
        with os.fdopen(fd, "rb", closefd=False) as f:
            raw = f.read(max_bytes + 1)
    finally:
        os.close(fd)
    if len(raw) > max_bytes:
        raise ValueError(f"it is larger than {max_bytes} bytes")
    try:
        data = json.loads(raw)
    except RecursionError:
        raise ValueError(f"it is nested deeper than {MAX_META_DEPTH} levels") from None
    except ValueError as e:  # malformed, not UTF-8, an integer beyond Python's digit limit
        raise ValueError(f"it is not JSON ({' '.join(str(e).split())[:120]})") from None
    problem = json_problem(data)
    if problem is not None:
        raise ValueError(problem)
    return data


def root_attrs(scene_dir: Path | str) -> dict[str, Any] | None:
    """The attributes of the scene's root group, read without zarr (a refusal needs none of it); None when the folder
    holds no readable store."""
    try:
        meta = read_limited_json(Path(scene_dir) / STORE_NAME / "zarr.json")
    except (OSError, ValueError):
        return None
    attrs = meta.get("attributes") if isinstance(meta, dict) else None
    return attrs if isinstance(attrs, dict) else None


def read_regular(path: Path | str, what: str, max_bytes: int) -> bytes:
    """At most `max_bytes` + 1 bytes of the regular file `path` (a config, a spec): opened without blocking and
    refused in one line when it is anything else (a pipe, a device, a socket: a FIFO would block the command
    forever, a device never ends), as clips are. WonderError naming `what` and the path."""

    def judged(mode: int) -> None:
        if stat.S_ISDIR(mode):
            raise WonderError(f"cannot read {what} {path}: Is a directory")
        if not stat.S_ISREG(mode):
            raise WonderError(f"{what} {path}: not a regular file (a device or a pipe)")

    try:
        judged(os.stat(path).st_mode)  # before opening: a socket cannot be opened, a device may act on open
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    except OSError as e:
        raise WonderError(f"cannot read {what} {path}: {e.strerror or e}") from None
    try:
        judged(os.fstat(fd).st_mode)  # what was opened, should the name have been swapped meanwhile
        os.set_blocking(fd, True)
        with os.fdopen(fd, "rb", closefd=False) as f:
            return f.read(max_bytes + 1)
    except OSError as e:
        raise WonderError(f"cannot read {what} {path}: {e.strerror or e}") from None
    finally:
        os.close(fd)


def _our_lock_file(lock_file: Path) -> bool:
    """Whether `lock_file` is a lock file a WonderVerse run left (a regular file, empty or holding its holder's
    details): a file of the same name that is anything else is the user's, and is never opened for writing."""
    try:
        st = lock_file.lstat()
    except OSError:
        return False
    if not stat.S_ISREG(st.st_mode) or st.st_size > 4096:
        return False
    if st.st_size == 0:
        return True
    try:
        info = json.loads(lock_file.read_bytes())
    except (OSError, ValueError, RecursionError):
        return False
    return isinstance(info, dict) and set(info) <= _LOCK_KEYS


def check_scene_dir(scene_dir: Path | str) -> None:
    """StoreError, touching nothing, when `scene_dir` cannot hold a scene: a file; a folder that holds no scene store
    and anything else than a lock file a run left (a user's own `.wonderverse.lock` included); a `scene.zarr` that is
    no store (its zarr.json missing); a lock file that is not a regular file (a link); a folder that could not be
    created or written (the nearest existing ancestor is a file or not writable). Cheap and read-only, so a command
    judges its --out with it before it takes a lock or writes anything."""
    scene_dir = Path(scene_dir)
    if scene_dir.exists() and not scene_dir.is_dir():
        raise StoreError(f"output path {scene_dir} exists and is not a folder")
    if scene_dir.is_dir():
        try:
            names = set(os.listdir(scene_dir))
        except OSError as e:
            raise StoreError(f"cannot read output folder {scene_dir}: {e.strerror or e}") from None
        lock_file = scene_dir / LOCK_NAME
        if LOCK_NAME in names and (lock_file.is_symlink() or not lock_file.is_file()):
            raise StoreError(f"cannot write to output folder {scene_dir}: {LOCK_NAME} is not a regular file")
        if STORE_NAME in names:
            if not (scene_dir / STORE_NAME / "zarr.json").is_file():
                raise StoreError(f"{scene_dir} holds no scene store ({STORE_NAME}/zarr.json is missing)")
        elif names - {LOCK_NAME} or (LOCK_NAME in names and not _our_lock_file(lock_file)):
            raise StoreError(f"output folder {scene_dir} is not empty and holds no scene; choose another --out")
    existing = next(p for p in (scene_dir, *scene_dir.absolute().parents) if p.exists() or p == p.parent)
    if not existing.is_dir():
        raise StoreError(f"cannot write to output folder {scene_dir}: {existing} is not a folder")
    check_writable(existing, f"output folder {scene_dir}")


def check_writable(folder: Path | str, what: str | None = None) -> None:
    """StoreError, touching nothing, when no file can be created in the existing folder `folder` (a read-only file
    system, or no permission); `what` names it in the message (default: the folder)."""
    folder = Path(folder)
    if os.access(folder, os.W_OK | os.X_OK):
        return
    try:
        read_only = bool(os.statvfs(folder).f_flag & os.ST_RDONLY)
    except OSError:
        read_only = False
    why = f"{folder} is on a read-only file system" if read_only else f"permission denied on {folder}"
    raise StoreError(f"cannot write to {what or folder}: {why}")


def check_child_name(name: str, what: str) -> None:
    """WonderError when `name` cannot name a scene folder (`scene_name_problem`); `what` says where it comes from."""
    problem = scene_name_problem(name)
    if problem is not None:
        raise WonderError(f"{what}: {name!r} cannot name a scene folder: {problem}")

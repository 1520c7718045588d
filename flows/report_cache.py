"""What the report draws per segment, kept between reports (`SCENE_DIR/.report-cache/`): a growing world redraws only
its new segments' plots and figures, so that writing the report costs about the same after every extension.

An entry is named by a fingerprint of what it is drawn from: the metadata of the store groups it reads (their
attributes carry each step's cache key, so new content comes with new metadata, the argument `report_state` rests
on too), and the report's code and parameters. An entry holds PNG bytes or a JSON object of numbers, nothing that
runs. New entries are written, and those the report did not use removed, only once the report itself is written (a
report refused on a damaged store changes nothing); a cache that cannot be written (a read-only folder, a full disk)
costs only the drawing.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

from wonderverse.store import SceneStore

CACHE_DIR = ".report-cache"


def metadata_files(root: Path) -> list[tuple[str, bytes]]:
    """(relative path, bytes) of every node's `zarr.json` under `root` (groups' attributes, arrays' shapes), sorted;
    leftovers of killed runs (`_staging`, `_trash`) are not part of the scene."""
    out = []
    stack = [root]
    while stack:
        d = stack.pop()
        try:
            raw = (d / "zarr.json").read_bytes()
        except OSError:
            continue
        out.append((d.relative_to(root).as_posix(), raw))
        try:
            is_group = json.loads(raw).get("node_type") == "group"
        except (ValueError, RecursionError, AttributeError):  # unreadable, nested beyond the parser, not a mapping
            continue
        if is_group:  # an array's folder holds only chunks
            with os.scandir(d) as entries:
                stack += [Path(e.path) for e in entries if e.is_dir() and not e.name.startswith("_")]
    return sorted(out)


def _numbers(raw: bytes) -> dict[str, float | int | None]:
    """A stored object of numbers; ValueError for anything else (an entry altered by hand is computed again)."""
    value = json.loads(raw)
    if not isinstance(value, dict) or not all(
        v is None or (isinstance(v, int | float) and not isinstance(v, bool)) for v in value.values()
    ):
        raise ValueError("not an object of numbers")
    return value


class DrawingCache:
    """Entries of one report being gathered; `salt` fingerprints the report's code and parameters."""

    def __init__(self, store: SceneStore, salt: str) -> None:
        self.store = store
        self.folder = store.scene_dir / CACHE_DIR
        self.salt = salt
        self.used: set[str] = set()
        self.fresh: dict[str, bytes] = {}  # drawn by this report, written by `save`
        self._groups: dict[str, bytes] = {}  # group -> digest of its metadata (several entries read one group)

    def key(self, what: str, *groups: str) -> str:
        """The name of what is drawn from `groups` (store paths) as `what` says (its kind and any settings)."""
        h = hashlib.sha256(f"{self.salt}\0{what}".encode())
        for g in groups:
            h.update(f"\0{g}\0".encode() + self._group_digest(g))
        return h.hexdigest()[:32]

    def _group_digest(self, group: str) -> bytes:
        if group not in self._groups:
            h = hashlib.sha256()
            for rel, raw in metadata_files(self.store.path / group):
                h.update(f"{rel}\0{len(raw)}\0".encode())
                h.update(raw)
            self._groups[group] = h.digest()
        return self._groups[group]

    def png(self, key: str, draw: Callable[[], bytes]) -> bytes:
        return self._entry(f"{key}.png", draw, bytes, bytes)

    def figures(self, key: str, compute: Callable[[], dict[str, Any]]) -> dict[str, Any]:
        """A JSON object of numbers (floats, ints, None), computed once."""
        return self._entry(f"{key}.json", compute, lambda v: json.dumps(v).encode(), _numbers)

    def _entry(self, name: str, make: Callable[[], Any], dump: Callable[[Any], bytes], load: Callable[[bytes], Any]):
        self.used.add(name)
        path = self.folder / name
        with contextlib.suppress(OSError, ValueError):
            return load(path.read_bytes())
        value = make()
        self.fresh[name] = dump(value)
        return value

    def save(self) -> None:
        """Write the entries drawn by this report and remove those it did not use (segments since replaced, older
        code or settings)."""
        for name, data in self.fresh.items():
            tmp = self.folder / f".{name}.{uuid.uuid4().hex}"
            try:
                self.folder.mkdir(exist_ok=True)
                tmp.write_bytes(data)
                os.replace(tmp, self.folder / name)  # whole or absent: a killed report leaves no half entry
            except OSError:
                with contextlib.suppress(OSError):
                    tmp.unlink(missing_ok=True)
        with contextlib.suppress(OSError), os.scandir(self.folder) as entries:
            for e in entries:
                if e.name not in self.used:
                    with contextlib.suppress(OSError):
                        os.unlink(e.path)

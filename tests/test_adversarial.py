"""Every known bad input at the command line, under both engines.

Each case is one `wonderverse` call that must be refused: exit code 2, exactly one non-empty stderr line, starting
with `error: ` and saying what is wrong, no traceback, no raw control character on the terminal, and the scene
folder it names byte-identical before and after (or never created when there was none). Prefect never starts for
any of them (no database appears in PREFECT_HOME). Bad configs, options and presets; prompts and extension words
with terminal escapes; foreign, file, read-only and unwritable `--out`; a store of a newer version or with a
broken root; a held lock, and one whose lock file was removed; clips that are no video; commands that must write
into a read-only scene or onto a full disk. Read-only and full file systems are real ones: a read-only bind mount
or a small tmpfs in a private mount namespace of the one call (as root), else permissions.

Damaged data that a step can rebuild is repaired (exit 0, its own test), and a chat planner whose server answers
nonsense falls back to the rules with a warning (exit 0, its own test)."""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import ClassVar

import imageio.v2 as imageio
import numpy as np
import pytest
import yaml
from conftest import ROOT, TINY_VIDEO, complete_config, lock_held_elsewhere, tiny_config

from flows.pipeline import execute
from wonderverse.schema import ATTEMPT, PLAN
from wonderverse.store import LOCK_NAME, SceneStore

ENGINE_COMMANDS = ("generate", "reconstruct", "extend")  # the commands that take --engine
PROMPT = "a small house decorated for Christmas"
FRAMES = ATTEMPT.at(seg="s000", attempt=0).frames
AS_ROOT = os.geteuid() == 0
CALL_TIMEOUT_S = 60  # a refusal takes ~1 s; a call still running after this was not refused


@dataclass(frozen=True)
class Case:
    """One refused call: `args` after `wonderverse`; `message`: a part of the error line; `target`: the folder that
    must stay as it was (or stay absent); `read_only`: a folder mounted read-only for the call; `full_disk`: run with
    `target` copied onto a full file system (`read_only` is then the mount point)."""

    name: str
    args: tuple[str, ...]
    message: str
    target: Path | None = None
    read_only: Path | None = None
    full_disk: bool = False
    secret: str | None = None  # must appear nowhere in what the call prints
    env: tuple[tuple[str, str], ...] = ()  # more environment variables for the call
    fsize_bytes: int | None = None  # a file-size limit (ulimit -f) for the call

    @property
    def takes_engine(self) -> bool:
        return self.args[0] in ENGINE_COMMANDS


@dataclass
class World:
    root: Path
    scene: Path  # a real tiny scene: plan and segments, its config stored
    copies: dict[str, Path]
    specs: Path
    clips: Path
    batches: dict[str, Path]  # a folder of specs whose one spec file has a name that is no folder name


SECRET = "hunter2-PASSWORD"  # a password in a URL: no call may print it
FRAMES_META = f"scene.zarr/{FRAMES}/zarr.json"
# Spec file names that are no single folder name: `..yaml` names OUT itself, `...yaml` its parent (the file's stem)
BAD_SPEC_NAMES = {
    "dot": "..yaml",
    "dotdot": "...yaml",
    "hidden": ".hidden.yaml",
    "fullwidth-dots": "\uff0e\uff0e.yaml",
    "one-dot-leader": "\u2025.yaml",
    "backslash": "a\\b.yaml",
    "fullwidth-slash": "a\uff0fb.yaml",
    "rlo": "\u202escene.yaml",
    "esc": "\x1b[2Jscene.yaml",
    "zero-width": "\u200b.yaml",
    "space-end": "scene .yaml",
    "space-start": " scene.yaml",
    "newline": "a\nb.yaml",
}


def _prefect_env(home: Path) -> dict[str, str]:
    return {"PREFECT_HOME": str(home), "PREFECT_SERVER_ANALYTICS_ENABLED": "false"}


def _spec_data(**changes: object) -> dict:
    """A valid tiny scene spec with `changes` (dotted by `__`) set deep in it."""
    data: dict = {"preset": "preview", "scene": {"prompt": PROMPT, "video": dict(TINY_VIDEO)}}
    for path, value in changes.items():
        node = data
        *parents, leaf = path.split("__")
        for p in parents:
            node = node.setdefault(p, {})
        node[leaf] = value
    return data


def _set_format(scene: Path, value: object) -> None:
    meta_file = scene / "scene.zarr" / "zarr.json"
    meta = json.loads(meta_file.read_text())
    meta["attributes"]["format"] = value
    meta_file.write_text(json.dumps(meta))


def _forge_frames_meta(scene: Path, kind: str) -> None:
    """Rewrite the first attempt's frames metadata as a hostile store would (`kind`), and, unless `kind` ends in
    `-unrecorded`, its digest in the segment's record too, so the digests pass and only the limits can tell."""
    import google_crc32c

    meta_file = scene / FRAMES_META
    meta = json.loads(meta_file.read_text())
    grid = meta["chunk_grid"]["configuration"]
    if kind.startswith("deep"):
        raw = meta_file.read_bytes().rstrip()[:-1] + b', "x": ' + b"[" * 100_000 + b"]" * 100_000 + b"}"
    else:
        if kind == "huge-shape":
            meta["shape"][0] = 6_000_000
        elif kind == "tiny-chunks":
            grid["chunk_shape"] = [1] * len(meta["shape"])
        elif kind == "huge-bytes":
            meta["shape"] = grid["chunk_shape"] = [6, 64_000, 96_000, 3]
        elif kind == "schema-shape":
            meta["shape"][-1] = grid["chunk_shape"][-1] = 4
        elif kind == "float-shape":
            meta["shape"][0] = 6.5
        elif kind == "huge-int":
            meta["shape"][0] = 10**30
        elif kind == "dtype":
            meta["data_type"] = "object"
        raw = json.dumps(meta).encode()
    meta_file.write_bytes(raw)
    if kind.endswith("-unrecorded"):
        return
    group = scene / "scene.zarr" / "segments" / "s000" / "zarr.json"
    gm = json.loads(group.read_text())
    gm["attributes"]["chunk_digests"]["arrays"]["attempts/0/frames"]["zarr.json"] = [
        len(raw),
        f"{google_crc32c.value(raw):08x}",
    ]
    group.write_text(json.dumps(gm))


FORGED = ("deep", "deep-unrecorded", "huge-shape", "tiny-chunks", "huge-bytes", "schema-shape", "huge-int", "dtype")


def _as_clip_scene(scene: Path, clip: Path) -> None:
    """Make `scene`'s records say its segments are a clip (what `reconstruct` records): cheaper than reconstructing."""
    meta_file = scene / "scene.zarr" / "zarr.json"
    meta = json.loads(meta_file.read_text())
    for name in ("config", "segments_config"):
        cfg = meta["attributes"].get(name)
        if cfg is None:
            continue
        cfg["scene"]["video"] = {**cfg["scene"]["video"], "backend": "files", "clips": [str(clip)], "options": {}}
        cfg["steps"]["priors"]["models"] |= {"depth_backend": "none", "normal_backend": "none"}
    meta_file.write_text(json.dumps(meta))


def folder_state(folder: Path) -> str:
    """One hash of every name under `folder` (files, folders, links, pipes: a new empty folder or lock file counts),
    each with its kind and, for files, bytes, for links, target."""
    h = hashlib.sha256()
    for p in sorted(folder.rglob("*")):
        rel = str(p.relative_to(folder)).encode("utf-8", "surrogateescape")
        if p.is_symlink():
            h.update(b"L" + rel + os.readlink(p).encode("utf-8", "surrogateescape"))
        elif p.is_dir():
            h.update(b"D" + rel)
        elif p.is_file():
            h.update(b"F" + rel + p.read_bytes())
        else:
            h.update(b"S" + rel)
        h.update(b"\0")
    return h.hexdigest()


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory) -> World:
    root = tmp_path_factory.mktemp("adversarial")
    scene = root / "scene"
    execute(scene, complete_config())  # every step: view, report and preview have what they show
    copies: dict[str, Path] = {}

    def copy(name: str) -> Path:
        copies[name] = root / name
        shutil.copytree(scene, copies[name])
        return copies[name]

    _set_format(copy("newer"), 999)
    _set_format(copy("formatless"), "one")
    (copy("broken-root") / "scene.zarr" / "zarr.json").write_text("{not json")
    (copy("no-root-meta") / "scene.zarr" / "zarr.json").unlink()
    copy("locked")
    copy("lock-removed")
    (root / "victim.txt").write_text("keep me")
    (copy("lock-symlink") / LOCK_NAME).unlink()
    (copies["lock-symlink"] / LOCK_NAME).symlink_to(root / "victim.txt")
    copy("read-only")
    (copy("damaged") / "scene.zarr" / FRAMES / "c" / "2" / "0" / "0" / "0").unlink()
    copies["no-run"] = root / "no-run"
    SceneStore.open_or_create(copies["no-run"], spec={"prompt": PROMPT})  # a store whose runs never completed
    for name in ("empty-ro", "parent-ro", "full"):
        copies[name] = root / name
        copies[name].mkdir()
    copies["foreign"] = root / "photos"
    copies["foreign"].mkdir()
    (copies["foreign"] / "holiday.jpg").write_bytes(b"\xff\xd8\xff")
    copies["a-file"] = root / "a-file"
    copies["a-file"].write_text("not a folder")
    copies["none"] = root / "none"  # never created

    specs = root / "specs"
    specs.mkdir()
    (specs / "one.yaml").write_text(yaml.safe_dump(_spec_data()))

    clips = root / "clips"
    clips.mkdir()
    (clips / "notvideo.mp4").write_text("hello")
    (clips / "empty.mp4").write_bytes(b"")
    with imageio.get_writer(clips / "one.mp4", fps=8) as w:
        w.append_data(np.zeros((64, 96, 3), np.uint8))
    os.symlink(clips / "loop2", clips / "loop1")
    os.symlink(clips / "loop1", clips / "loop2")
    (clips / "no-images").mkdir()
    (clips / "bad-images").mkdir()
    for i in range(3):
        (clips / "bad-images" / f"f{i}.png").write_bytes(b"not a png" * (i + 1))
    (clips / "mixed").mkdir()
    for i, (w_, h_) in enumerate([(96, 64), (128, 64)]):  # no shape most of them have: refused
        imageio.imwrite(clips / "mixed" / f"f{i}.png", np.full((h_, w_, 3), 40 * i, np.uint8))
    (clips / "model-file").write_text("not a folder")
    (clips / "\u202ex.mp4").write_text("not a video")  # a name that reorders what a terminal shows
    os.mkfifo(clips / "pipe.mp4")

    # folders that are no scene, however they look like one, and stores whose metadata is hostile
    for name, entries in {
        "zarr-file": {"scene.zarr": "a file"},
        "zarr-empty": {"scene.zarr/": None},
        "zarr-no-root": {"scene.zarr/segments/": None},
        "user-lock": {LOCK_NAME: "my own notes, not a lock"},
        "user-lock-json": {LOCK_NAME: '{"pid": 1, "user": "me"}'},
        "lock-and-file": {LOCK_NAME: "", "notes.txt": "mine"},
        "lock-a-folder": {f"{LOCK_NAME}/": None},
        "only-hidden": {".hidden": "x"},
    }.items():
        copies[name] = root / name
        copies[name].mkdir()
        for entry, content in entries.items():
            if content is None:
                (copies[name] / entry).mkdir(parents=True)
            else:
                (copies[name] / entry).write_text(content)
    copies["lock-fifo"] = root / "lock-fifo"
    copies["lock-fifo"].mkdir()
    os.mkfifo(copies["lock-fifo"] / LOCK_NAME)
    copies["lock-fifo-scene"] = copy("lock-fifo-scene")
    (copies["lock-fifo-scene"] / LOCK_NAME).unlink()
    os.mkfifo(copies["lock-fifo-scene"] / LOCK_NAME)
    for kind in FORGED:
        _forge_frames_meta(copy(f"forged-{kind}"), kind)
    root_meta = copy("root-deep") / "scene.zarr" / "zarr.json"
    root_meta.write_bytes(root_meta.read_bytes().rstrip()[:-1] + b', "x": ' + b"[" * 100_000 + b"]" * 100_000 + b"}")
    _as_clip_scene(copy("clip-scene"), clips / "one.mp4")
    copies["parent"] = root / "parent"  # batches write OUT below it: nothing may appear here
    copies["parent"].mkdir()

    batches = {}
    for key, file_name in BAD_SPEC_NAMES.items():
        batches[key] = root / "batches" / key
        batches[key].mkdir(parents=True)
        (batches[key] / "good.yaml").write_text(yaml.safe_dump(_spec_data()))
        (batches[key] / file_name).write_text(yaml.safe_dump(_spec_data()))
    batches["fifo-only"] = root / "batches" / "fifo-only"
    batches["fifo-only"].mkdir()
    os.mkfifo(batches["fifo-only"] / "scene.yaml")
    batches["empty"] = root / "batches" / "empty"
    batches["empty"].mkdir()
    return World(root, scene, copies, specs, clips, batches)


def _config_files(folder: Path) -> dict[str, tuple[Path, str]]:
    """Bad --config files: name -> (file, a part of the error line)."""
    folder.mkdir(exist_ok=True)
    raw: dict[str, tuple[bytes, str]] = {
        "list": (b"- preset: preview\n- scene: {prompt: x}\n", "must hold a mapping of settings, not a list"),
        "scalar": (b"just some words\n", "must hold a mapping of settings, not a str"),
        "binary": (bytes(range(256)) * 8, "is not UTF-8 text"),
        "latin1": ("scene: {prompt: une maison en été}\n".encode("latin-1"), "is not UTF-8 text (byte 0xe9"),
        "nul": (b"scene: {prompt: a house}\n\x00\x00\n", "binary (it holds NUL bytes)"),
        "malformed": (b"scene: {prompt: [unclosed\n", "malformed YAML"),
        "tabs": (b"scene:\n\tprompt: x\n", "malformed YAML"),
        "deep": (b"scene: " + b"[" * 20000 + b"]" * 20000 + b"\n", "malformed YAML"),
        "huge-int": (b"scene: {prompt: x, seed: " + b"9" * 6000 + b"}\n", "malformed YAML"),
        "recursive": (b"scene: &a {prompt: x, video: *a}\n", "expands to more than 100000 values"),
        "huge": (b"# " + b"x" * 1_100_000 + b"\n", "is larger than 1 MB"),
        "prompt-number": (b"scene: {prompt: 5}\n", "scene.prompt: Input should be a valid string"),
        "prompt-list": (b"scene: {prompt: [a, b]}\n", "scene.prompt: Input should be a valid string"),
        "prompt-null": (b"preset: preview\nscene: {prompt: null}\n", "scene.prompt"),
        "prompt-esc": (b'scene: {prompt: "a house \\e[2J\\e[31mred"}\n', "U+001B (ESC) at character 9"),
        "prompt-nul": (b'scene: {prompt: "a house\\0"}\n', "U+0000 (NUL) at character 8"),
        "prompt-csi": (b'scene: {prompt: "a house \\x9b31m"}\n', "U+009B (CSI)"),
        "key-esc": (b'scene: {prompt: x, "\\e[2Jbad": 1}\n', "unknown setting"),
        "intent-bel": (b'scene: {prompt: x, extensions: {intents: ["go \\a left"]}}\n', "extensions.intents.0"),
        "added-esc": (b'scene: {prompt: x, extensions: {added: [ok, "\\e]0;title\\a"]}}\n', "extensions.added.1"),
        "empty": (b"", "scene.prompt: no prompt given"),
        "dup-top": (b"preset: preview\npreset: high\nscene: {prompt: x}\n", "duplicate key 'preset'"),
        "dup-nested": (
            b"scene:\n  prompt: a\n  seed: 1\n  prompt: b\n",
            "duplicate key 'prompt' (first given at line 2)",
        ),
        "dup-flow": (b"scene: {prompt: a, prompt: b}\n", "duplicate key 'prompt'"),
        "dup-deep": (
            b"steps:\n  splats:\n    train: {iterations: 5, iterations: 6}\nscene: {prompt: x}\n",
            "duplicate key",
        ),
        "prompt-zwsp": ('scene: {prompt: "\u200b\u200c\u200d"}\n'.encode(), "holds no visible character"),
        "prompt-bom": ('scene: {prompt: "\ufeff \u2060"}\n'.encode(), "holds no visible character"),
        "prompt-filler": ('scene: {prompt: "\u3164\u3164"}\n'.encode(), "holds no visible character"),
        "prompt-combining": ('scene: {prompt: "\u0301\u0302"}\n'.encode(), "holds no visible character"),
        "prompt-rlo": ('scene: {prompt: "a \u202ehouse"}\n'.encode(), "U+202E (RLO) at character 3"),
        "prompt-lri": ('scene: {prompt: "a \u2066house"}\n'.encode(), "U+2066 (LRI)"),
        "added-zwsp": ('scene: {prompt: x, extensions: {added: ["\u200b"]}}\n'.encode(), "extensions.added"),
    }
    bomb = ["a: &a [lol, lol, lol, lol, lol, lol, lol, lol, lol]"]
    bomb += [f"{c}: &{c} [{', '.join(['*' + p] * 9)}]" for p, c in zip("abcdefghi", "bcdefghij", strict=True)]
    raw["alias-bomb"] = ("\n".join(bomb).encode() + b"\nscene: {prompt: *j}\n", "expands to more than 100000 values")
    raw["options-bomb"] = (
        "\n".join(bomb[:8]).encode() + b"\nscene: {prompt: x, video: {options: {fault_probability: *h}}}\n",
        "expands to more than 100000 values",
    )
    files = {}
    for name, (content, message) in raw.items():
        (folder / f"{name}.yaml").write_bytes(content)
        files[name] = (folder / f"{name}.yaml", message)
    settings: dict[str, tuple[dict, str]] = {
        "scene-5": (_spec_data(scene=5), "scene: must be a mapping of settings (got 5)"),
        "unknown-top": (_spec_data(bogus=1), "bogus: unknown setting"),
        "unknown-option": (_spec_data(scene__video__options={"bogus_option": 1}), "options.bogus_option: unknown"),
        "fault-5": (_spec_data(scene__video__options={"fault_probability": 5}), "fault_probability: Input should"),
        "width-0": (_spec_data(scene__video__width=0), "scene.video.width"),
        "width-text": (_spec_data(scene__video__width="wide"), "scene.video.width"),
        "frames-huge": (_spec_data(scene__video__frames_per_segment=10**9), "frames_per_segment"),
        "fps-nan": (_spec_data(scene__video__fps=float("nan")), "scene.video.fps"),
        "fps-inf": (_spec_data(scene__video__fps=float("inf")), "scene.video.fps"),
        "fov-180": (_spec_data(scene__video__fov_deg=180), "scene.video.fov_deg"),
        "seed-negative": (_spec_data(scene__seed=-1), "scene.seed"),
        "seed-huge": (_spec_data(scene__seed=2**40), "scene.seed"),
        "backend": (_spec_data(scene__video__backend="bogus"), "scene.video.backend"),
        "no-clip": (_spec_data(scene__video={"backend": "files", "clips": ["/x/clip.mp4"]}), "/x/clip.mp4: no such"),
        "files-no-clips": (_spec_data(scene__video={"backend": "files"}), "needs at least one clip"),
        "oracle-files": (
            _spec_data(
                scene__video={"backend": "files", "clips": ["/x/clip.mp4"]},
                steps__priors__models={"depth_backend": "oracle"},
            ),
            "the oracle prior needs the procedural world's ground truth",
        ),
        "move": (_spec_data(steps__plan={"initial_move": "sideways 5"}), "steps.plan.initial_move"),
        "unknown-step": (_spec_data(steps__bogus={"x": 1}), "steps.bogus: unknown setting"),
        "workers-0": (_spec_data(execution__generate_workers=0), "execution.generate_workers"),
        "planner": (_spec_data(scene__planner={"backend": "gpt"}), "scene.planner.backend"),
        "timeout-0": (_spec_data(scene__planner={"timeout_s": 0}), "scene.planner.timeout_s"),
        "rounds-100": (_spec_data(scene__extensions={"rounds": 100}), "scene.extensions.rounds"),
        "directions-none": (_spec_data(scene__extensions={"directions": []}), "scene.extensions.directions"),
        "direction-up": (_spec_data(scene__extensions={"directions": ["sideways"]}), "scene.extensions.directions"),
        "preset-path": (_spec_data(preset="../../etc/passwd"), "unknown preset '../../etc/passwd'"),
        "preset-list": (_spec_data(preset=["preview"]), "unknown preset"),
        "poses-source": (
            _spec_data(scene__video={"backend": "files", "clips": ["/x/c.mp4"]}, steps__poses={"source": "x"}),
            "steps.poses.source",
        ),
        "iterations-huge": (_spec_data(steps__splats={"train": {"iterations": 10**9}}), "train.iterations"),
        "iterations-negative": (_spec_data(steps__splats={"train": {"iterations": -1}}), "train.iterations"),
        "video-frames-huge": (_spec_data(steps__outputs={"video_frames": 10**7}), "outputs.video_frames"),
        "placement-huge": (
            _spec_data(scene__video__options={"placement_tries": 10**9}),
            "options.placement_tries",
        ),
        "ransac-huge": (_spec_data(steps__priors={"models": {"align": {"ransac_iters": 10**9}}}), "ransac_iters"),
        "segments-cap": (
            _spec_data(scene__extensions={"rounds": 16, "directions": ["left", "right", "up", "down"]}),
            "at most 64 segments",
        ),
        "url-password": (
            _spec_data(scene__planner={"backend": "chat", "base_url": f"http://user:{SECRET}@127.0.0.1:9/v1"}),
            "carries credentials",
        ),
        "url-password-long": (
            _spec_data(scene__planner={"base_url": f"https://u:{SECRET * 8}@{'h' * 80}.example/v1"}),
            "carries credentials",
        ),
        "url-user-only": (
            _spec_data(scene__planner={"base_url": "http://admin@127.0.0.1:9/v1"}),
            "carries credentials",
        ),
        "dask-password": (_spec_data(execution__dask_address=f"tcp://u:{SECRET}@127.0.0.1:8786"), "credentials"),
    }
    for name, (data, message) in settings.items():
        (folder / f"{name}.yaml").write_text(yaml.safe_dump(data))
        files[name] = (folder / f"{name}.yaml", message)
    return files


def _special_files(folder: Path) -> tuple[Path, Path, Path]:
    """A FIFO (opening it for reading would block until a writer came), a link to it, and a Unix socket."""
    import socket

    if not folder.exists():
        folder.mkdir()
        os.mkfifo(folder / "config.yaml")
        (folder / "link.yaml").symlink_to(folder / "config.yaml")
        with socket.socket(socket.AF_UNIX) as s:
            s.bind(str(folder / "sock.yaml"))
    return folder / "config.yaml", folder / "link.yaml", folder / "sock.yaml"


def cases(world: World) -> list[Case]:
    c, scene, clips = world.copies, world.scene, world.clips
    out = ("--out", str(scene))
    fifo, fifo_link, sock = _special_files(world.root / "special")
    found = [
        Case(f"config {name}", ("generate", "--config", str(f), *out), message, scene)
        for name, (f, message) in _config_files(world.root / "configs").items()
    ]
    found += [
        Case("config missing", ("generate", "--config", str(world.root / "nope.yaml"), *out), "cannot read", scene),
        Case("config a folder", ("generate", "--config", str(world.specs), *out), "cannot read config file", scene),
        Case("config /dev/zero", ("generate", "--config", "/dev/zero", *out), "not a regular file", scene),
        Case("config /dev/null", ("generate", "--config", "/dev/null", *out), "not a regular file", scene),
        Case("config /dev/urandom", ("generate", "--config", "/dev/urandom", *out), "not a regular file", scene),
        Case(
            "config a FIFO", ("generate", "--config", str(fifo), *out), "not a regular file (a device or a pipe)", scene
        ),
        Case("config a link to a FIFO", ("generate", "--config", str(fifo_link), *out), "not a regular file", scene),
        Case("config a socket", ("generate", "--config", str(sock), *out), "not a regular file", scene),
        Case(
            "reconstruct config a FIFO",
            ("reconstruct", str(clips / "one.mp4"), "--config", str(fifo), "--out", str(c["none"])),
            "not a regular file",
            c["none"],
        ),
    ]
    prompt = ("generate", PROMPT, "--preset", "preview")
    found += [
        Case("prompt empty", ("generate", "", *out), "prompt is empty", scene),
        Case("prompt blank", ("generate", " \t\n ", *out), "prompt is empty", scene),
        Case("prompt too long", ("generate", "a" * 2001, *out), "prompt has 2001 characters", scene),
        Case("prompt none", ("generate", *out), "no prompt given", scene),
        Case("prompt ESC", ("generate", "a \x1b[31mred\x1b[0m house", *out), "U+001B (ESC) at character 3", scene),
        Case("prompt OSC title", ("generate", "\x1b]0;pwned\x07a house", *out), "U+001B (ESC) at character 1", scene),
        Case("prompt BEL", ("generate", "a house\x07", *out), "U+0007 (BEL)", scene),
        Case("prompt BS", ("generate", "a house\x08\x08\x08", *out), "U+0008 (BS)", scene),
        Case("prompt DEL", ("generate", "a house\x7f", *out), "U+007F (DEL)", scene),
        Case("prompt CSI", ("generate", "a house \x9b2J", *out), "U+009B (CSI)", scene),
        Case("prompt VT", ("generate", "a\x0bhouse", *out), "U+000B (VT)", scene),
        Case("prompt ESC new folder", ("generate", "\x1b[2Ja house", "--out", str(c["none"])), "U+001B", c["none"]),
        Case("preset path", (*prompt[:2], "--preset", "../../tmp/x", *out), "unknown preset '../../tmp/x'", scene),
        Case("preset empty", (*prompt[:2], "--preset", "", *out), "unknown preset ''", scene),
        Case("preset unknown", (*prompt[:2], "--preset", "ultra", *out), "unknown preset 'ultra'", scene),
        Case("preset ESC", (*prompt[:2], "--preset", "\x1b[31m", *out), "unknown preset '\\x1b[31m'", scene),
        Case("until unknown", (*prompt, "--until", "bogus", *out), "unknown step 'bogus'", scene),
        Case("engine unknown", (*prompt[:2], "--engine", "dask", *out), "--engine must be", scene),
        Case("seed negative", (*prompt, "--seed", "-5", *out), "scene.seed", scene),
        Case("seed text", (*prompt, "--seed", "abc", *out), "Invalid value for '--seed'", scene),
        Case("option unknown", (*prompt, "--bogus", *out), "No such option: --bogus", scene),
        Case("other prompt", ("generate", "a desert canyon at noon", *out), "--replace-segments", scene),
        Case("out a file", (*prompt, "--out", str(c["a-file"])), "exists and is not a folder", c["a-file"]),
        Case("out under a file", (*prompt, "--out", str(c["a-file"] / "s")), "a-file is not a folder", c["a-file"]),
        Case("out /dev/null", (*prompt, "--out", "/dev/null"), "/dev/null exists and is not a folder"),
        Case("out foreign", (*prompt, "--out", str(c["foreign"])), "not empty and holds no scene", c["foreign"]),
        Case("out newer store", (*prompt, "--out", str(c["newer"])), "written by a newer WonderVerse", c["newer"]),
        Case("out store format", (*prompt, "--out", str(c["formatless"])), "store format 'one'", c["formatless"]),
        Case("out broken root", (*prompt, "--out", str(c["broken-root"])), "cannot open scene store", c["broken-root"]),
        Case("out no root", (*prompt, "--out", str(c["no-root-meta"])), "holds no scene store", c["no-root-meta"]),
        Case("out locked", (*prompt, "--out", str(c["locked"])), "is being written by another run (pid", c["locked"]),
        Case(
            "out lock removed",
            (*prompt, "--out", str(c["lock-removed"])),
            f"(holder unknown: {LOCK_NAME} was removed",
            c["lock-removed"],
        ),
        Case("out lock symlink", (*prompt, "--out", str(c["lock-symlink"])), "cannot write", c["lock-symlink"]),
        Case(
            "out read-only",
            (*prompt, "--out", str(c["empty-ro"])),
            "is on a read-only file system",
            c["empty-ro"],
            read_only=c["empty-ro"] if AS_ROOT else None,
        ),
        Case(
            "out under read-only",
            (*prompt, "--out", str(c["parent-ro"] / "new" / "scene")),
            "is on a read-only file system",
            c["parent-ro"],
            read_only=c["parent-ro"],
        ),
        Case(
            "out read-only scene",
            (*prompt, "--out", str(c["read-only"])),
            "is on a read-only file system",
            c["read-only"],
            read_only=c["read-only"],
        ),
    ]
    rec = ("reconstruct",)
    none = ("--out", str(c["none"]))
    found += [
        Case(
            "clip not video", (*rec, str(clips / "notvideo.mp4"), *none), "notvideo.mp4: cannot read video", c["none"]
        ),
        Case("clip 0 bytes", (*rec, str(clips / "empty.mp4"), *none), "empty.mp4: cannot read video", c["none"]),
        Case("clip one frame", (*rec, str(clips / "one.mp4"), *none), "one.mp4: only 1 frame", c["none"]),
        Case("clip symlink loop", (*rec, str(clips / "loop1"), *none), "loop1: cannot be read", c["none"]),
        Case("clip /dev/zero", (*rec, "/dev/zero", *none), "/dev/zero: not a video file", c["none"]),
        Case("clip missing", (*rec, str(clips / "nope.mp4"), *none), "nope.mp4: no such file", c["none"]),
        Case("clip no images", (*rec, str(clips / "no-images"), *none), "folder has no images", c["none"]),
        Case("clip bad images", (*rec, str(clips / "bad-images"), *none), "bad-images", c["none"]),
        Case("clip mixed sizes", (*rec, str(clips / "mixed"), *none), "f1.png: image is 128x64", c["none"]),
        Case("clip glob empty", (*rec, str(clips / "none-*.png"), *none), "none-*.png", c["none"]),
        Case(
            "clip two folders",
            (*rec, str(clips / "mixed/f0.png"), str(clips / "bad-images/f0.png"), *none),
            "images from several folders",
            c["none"],
        ),
        Case("fov nan", (*rec, str(clips / "one.mp4"), "--fov-deg", "nan", *none), "options.fov_deg", c["none"]),
        Case("fov -5", (*rec, str(clips / "one.mp4"), "--fov-deg", "-5", *none), "options.fov_deg", c["none"]),
        Case("fov 500", (*rec, str(clips / "one.mp4"), "--fov-deg", "500", *none), "options.fov_deg", c["none"]),
        Case(
            "depth model missing",
            (*rec, str(clips / "one.mp4"), "--depth-model", "/nonexistent/da", *none),
            "--depth-model /nonexistent/da: no such folder",
            c["none"],
        ),
        Case(
            "depth model a file",
            (*rec, str(clips / "one.mp4"), "--depth-model", str(clips / "model-file"), *none),
            "model-file: no such folder",
            c["none"],
        ),
        Case("on failure", (*rec, str(clips / "one.mp4"), "--on-failure", "retry", *none), "on_failure", c["none"]),
        Case("clip out a file", (*rec, str(clips / "one.mp4"), "--out", str(c["a-file"])), "not a folder", c["a-file"]),
        Case("clip ESC name", (*rec, str(clips / "\x1b[2Jx.mp4"), *none), "\\x1b[2Jx.mp4: no such file", c["none"]),
    ]
    found += [
        Case("extend missing", ("extend", str(c["none"]), "go left"), "holds no scene store", c["none"]),
        Case("extend foreign", ("extend", str(c["foreign"]), "go left"), "holds no scene store", c["foreign"]),
        Case("extend no run", ("extend", str(c["no-run"]), "go left"), "holds no completed run", c["no-run"]),
        Case("extend newer", ("extend", str(c["newer"]), "go left"), "written by a newer WonderVerse", c["newer"]),
        Case("extend empty", ("extend", str(scene), " \n "), "the extension request is empty", scene),
        Case("extend too long", ("extend", str(scene), "w" * 501), "has 501 characters", scene),
        Case("extend ESC", ("extend", str(scene), "go \x1b[1Aleft"), "U+001B (ESC) at character 4", scene),
        Case("extend BEL", ("extend", str(scene), "go left\x07"), "U+0007 (BEL) at character 8", scene),
        Case("extend C1", ("extend", str(scene), "go \x85left"), "U+0085 at character 4", scene),
        Case("extend locked", ("extend", str(c["locked"]), "go left"), "being written by another run", c["locked"]),
        Case(
            "extend read-only",
            ("extend", str(c["read-only"]), "go left"),
            "read-only file system",
            c["read-only"],
            read_only=c["read-only"],
        ),
    ]
    for command in ("inspect", "report", "preview", "view"):
        found += [
            Case(f"{command} missing", (command, str(c["none"])), "no", c["none"]),
            Case(f"{command} foreign", (command, str(c["foreign"])), "no scene", c["foreign"]),
            Case(f"{command} newer", (command, str(c["newer"])), "newer WonderVerse", c["newer"]),
        ]
    found += [
        Case("inspect a file", ("inspect", str(c["a-file"])), "holds no scene store", c["a-file"]),
        Case(
            "report read-only",
            ("report", str(c["read-only"])),
            "report.html in",
            c["read-only"],
            read_only=c["read-only"],
        ),
        Case(
            "preview read-only",
            ("preview", str(c["read-only"])),
            "preview.mp4 in",
            c["read-only"],
            read_only=c["read-only"],
        ),
        Case(
            "report full disk",
            ("report", str(c["full"] / "scene")),
            "No space left on device",
            scene,
            read_only=c["full"],
            full_disk=True,
        ),
        Case("preview damaged", ("preview", str(c["damaged"])), "damaged scene data in segments/s000", c["damaged"]),
        Case("preview no segments", ("preview", str(c["no-run"])), "no rendered segments yet", c["no-run"]),
        Case("view no splats", ("view", str(c["no-run"])), "has no splats yet", c["no-run"]),
        Case(
            "view read-only",
            ("view", str(c["read-only"])),
            "cannot write viewer.html",
            c["read-only"],
            read_only=c["read-only"],
        ),
        Case("view port", ("view", str(scene), "--port", "70000"), "Invalid value for '--port'", scene),
        Case(
            "batch out a file", ("batch", str(world.specs), "--out", str(c["a-file"])), "is not a folder", c["a-file"]
        ),
        Case(
            "batch missing", ("batch", str(world.root / "nope"), "--out", str(c["none"])), "does not exist", c["none"]
        ),
        Case(
            "batch until",
            ("batch", str(world.specs), "--until", "x", "--out", str(c["none"])),
            "unknown step 'x'",
            c["none"],
        ),
        Case(
            "serve no server", ("serve", str(world.specs), "--out", str(c["none"])), "needs a Prefect server", c["none"]
        ),
        Case("no command", ("bogus",), "No such command 'bogus'"),
    ]
    return found + hardening_cases(world)


# Folders that are no scene however much they look like one: what each command says (generate and reconstruct judge
# them as --out; the others as a scene to read). A refusal leaves every name and byte as it was (`folder_state`).
NOT_A_SCENE = {
    "zarr-file": ("holds no scene store", "holds no scene store"),
    "zarr-empty": ("holds no scene store", "holds no scene store"),
    "zarr-no-root": ("holds no scene store", "holds no scene store"),
    "user-lock": ("not empty and holds no scene", "holds no scene store"),
    "user-lock-json": ("not empty and holds no scene", "holds no scene store"),
    "lock-and-file": ("not empty and holds no scene", "holds no scene store"),
    "lock-a-folder": (f"{LOCK_NAME} is not a regular file", "holds no scene store"),
    "lock-fifo": (f"{LOCK_NAME} is not a regular file", "holds no scene store"),
    "only-hidden": ("not empty and holds no scene", "holds no scene store"),
    "root-deep": ("cannot open scene store", "cannot open scene store"),
}


def hardening_cases(world: World) -> list[Case]:
    """The cases of issue 40 and those found beside them: folders that look like scenes, spec names that are no folder
    name, hostile store metadata, extending a reconstruction, credentials in URLs, invisible and reordering text,
    bounds on run time, a file-size limit."""
    c, scene, clips = world.copies, world.scene, world.clips
    good_clip = str(scene / "flythrough.mp4")  # the scene's own video: a clip that passes every check
    prompt = ("generate", PROMPT, "--preset", "preview")
    none = ("--out", str(c["none"]))
    found: list[Case] = []
    for kind, (as_out, as_scene) in NOT_A_SCENE.items():
        folder = c[kind]
        found += [
            Case(f"out {kind}", (*prompt, "--out", str(folder)), as_out, folder),
            Case(f"clip out {kind}", ("reconstruct", good_clip, "--out", str(folder)), as_out, folder),
            Case(f"extend {kind}", ("extend", str(folder), "go left"), as_scene, folder),
        ]
        found += [
            Case(f"{command} {kind}", (command, str(folder)), as_scene, folder) for command in ("inspect", "report")
        ]
        found += [Case(f"{command} {kind}", (command, str(folder)), "no", folder) for command in ("preview", "view")]
    found += [
        Case(
            "out lock fifo scene", (*prompt, "--out", str(c["lock-fifo-scene"])), "not a regular", c["lock-fifo-scene"]
        ),
        Case(
            "extend lock fifo scene", ("extend", str(c["lock-fifo-scene"]), "go"), "not a regular", c["lock-fifo-scene"]
        ),
    ]
    damaged = "damaged scene data in segments/s000"
    found += [Case(f"report forged {k}", ("report", str(c[f"forged-{k}"])), damaged, c[f"forged-{k}"]) for k in FORGED]
    found += [
        Case(f"preview forged {k}", ("preview", str(c[f"forged-{k}"])), damaged, c[f"forged-{k}"])
        for k in ("deep", "tiny-chunks", "huge-bytes")
    ]
    out = ("--out", str(c["parent"] / "out"))
    found += [
        Case(f"batch spec {key}", ("batch", str(world.batches[key]), *out), "cannot name a scene folder", c["parent"])
        for key in BAD_SPEC_NAMES
    ]
    found += [
        Case(f"batch {key}", ("batch", str(world.batches[key]), *out), "no scene specs", c["parent"])
        for key in ("fifo-only", "empty")
    ]
    found += [
        Case(
            "extend a reconstruction",
            ("extend", str(c["clip-scene"]), "go left"),
            "reconstruction of clips",
            c["clip-scene"],
        ),
        Case("dask password", (*prompt, "--dask", f"tcp://u:{SECRET}@127.0.0.1:8786", *none), "credentials", c["none"]),
        Case(
            "serve api password",
            ("serve", str(world.specs), *none),
            "PREFECT_API_URL=http://u:***@127.0.0.1:9/api",
            c["none"],
            env=(("PREFECT_API_URL", f"http://u:{SECRET}@127.0.0.1:9/api"),),
        ),
        Case("prompt RLO", ("generate", "a \u202ehouse", *none), "U+202E (RLO) at character 3", c["none"]),
        Case("prompt LRM", ("generate", "a house\u200e", *none), "U+200E (LRM)", c["none"]),
        Case("prompt zero-width", ("generate", "\u200b\u200d\u2060", *none), "no visible character", c["none"]),
        Case("prompt BOM", ("generate", "\ufeff", *none), "no visible character", c["none"]),
        Case("prompt filler", ("generate", "\u3164 \u3164", *none), "no visible character", c["none"]),
        Case("prompt braille blank", ("generate", "\u2800", *none), "no visible character", c["none"]),
        Case("extend zero-width", ("extend", str(scene), "\u200b\u200c"), "the extension request is empty", scene),
        Case("extend RLO", ("extend", str(scene), "go \u202eleft"), "U+202E (RLO) at character 4", scene),
        Case("extend PDI", ("extend", str(scene), "go \u2069left"), "U+2069 (PDI)", scene),
        Case("clip RLO name", ("reconstruct", str(clips / "\u202ex.mp4"), *none), "\\u202ex.mp4", c["none"]),
        Case("clip a pipe", ("reconstruct", str(clips / "pipe.mp4"), *none), "pipe.mp4: not a video file", c["none"]),
        Case("file-size limit", (*prompt, *none), "ulimit -f", c["none"], fsize_bytes=1 << 20),
        Case("file-size limit scene", (*prompt, "--out", str(scene)), "ulimit -f", scene, fsize_bytes=1 << 20),
    ]
    return found


# A private mount namespace for one call: $1 is mounted read-only on itself, or (full disk) a small tmpfs is mounted
# on $1, the scene $2 copied into it and the rest filled, and the scene's digest written to $3 before and after.
READ_ONLY = 'mount --bind -o ro "$1" "$1" && shift 3 && exec "$@"'
FULL_DISK = """size=$((2 * $(du -sm "$2" | cut -f1) + 4))m
mount -t tmpfs -o size=$size tmpfs "$1" && cp -a "$2" "$1/scene" || exit 99
cat /dev/zero > "$1/fill" 2>/dev/null
digest() { (cd "$1/scene" && find . -type f | LC_ALL=C sort | xargs sha256sum | sha256sum); }
digest "$1" > "$3"; m="$1"; d="$3"; shift 3
"$@"; rc=$?
digest "$m" >> "$d"; exit $rc"""


def call(case: Case, engine: str, env: dict[str, str], scratch: Path) -> subprocess.CompletedProcess:
    own = "--engine" in case.args  # a case about the option itself
    args = [*case.args, "--engine", engine] if case.takes_engine and not own else list(case.args)
    command = [sys.executable, "-m", "flows", *args]
    if case.read_only is not None:
        source = str(case.target) if case.full_disk else ""
        script = FULL_DISK if case.full_disk else READ_ONLY
        digest_file = scratch / f"{case.name}.digest"
        command = ["unshare", "-m", "sh", "-c", script, "sh", str(case.read_only), source, str(digest_file), *command]
    limit = case.fsize_bytes

    def preexec() -> None:
        if limit is not None:
            import resource

            resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    return subprocess.run(
        command,
        capture_output=True,
        text=True,
        timeout=CALL_TIMEOUT_S,
        env={**os.environ, "PYTHONUNBUFFERED": "1", **env, **dict(case.env)},
        cwd=ROOT,
        preexec_fn=preexec if limit is not None else None,
    )


BIDI = frozenset("\u061c\u200e\u200f\u202a\u202b\u202c\u202d\u202e\u2066\u2067\u2068\u2069")


def _raw_controls(text: str) -> list[str]:
    return [
        f"U+{ord(ch):04X}" for ch in text if (ord(ch) < 32 and ch not in "\n\t") or 0x7F <= ord(ch) < 0xA0 or ch in BIDI
    ]


def check(case: Case, engine: str, env: dict[str, str], scratch: Path) -> str | None:
    """Run one case; None when it was refused as promised, else what went wrong."""
    target = case.target
    existed = target is not None and target.exists()
    before = folder_state(target) if existed and target.is_dir() else None
    try:
        r = call(case, engine, env, scratch)
    except subprocess.TimeoutExpired:
        return f"{case.name} ({engine}): still running after {CALL_TIMEOUT_S} s: not refused"
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    problems = []
    if r.returncode != 2:
        problems.append(f"exit code {r.returncode}")
    if len(lines) != 1 or not lines[0].startswith("error: "):
        problems.append(f"{len(lines)} stderr lines")
    elif case.message not in lines[0]:
        problems.append(f"message lacks {case.message!r}")
    if "Traceback" in r.stderr:
        problems.append("a traceback")
    if r.stdout:
        problems.append(f"stdout {r.stdout[:200]!r}")
    if _raw_controls(r.stderr + r.stdout):
        problems.append(f"raw control characters {_raw_controls(r.stderr + r.stdout)}")
    if case.full_disk:
        digest_file = scratch / f"{case.name}.digest"
        digests = digest_file.read_text().splitlines() if digest_file.exists() else ["the full disk was not set up"]
        if len(digests) != 2 or digests[0] != digests[1]:
            problems.append(f"the scene on the full disk changed: {digests}")
    elif target is not None and not existed and target.exists():
        problems.append(f"{target} was created")
    elif before is not None and folder_state(target) != before:
        problems.append(f"{target} changed")
    if SECRET in r.stderr + r.stdout:
        problems.append("the password of a URL was printed")
    if not problems:
        return None
    return f"{case.name} ({engine}): {', '.join(problems)}\n  stderr: {r.stderr[-1500:]!r}"


def run_all(world: World, engine: str, tmp_path: Path) -> list[Case]:
    home = tmp_path / "prefect"
    env = _prefect_env(home)
    todo = [case for case in cases(world) if engine == "local" or case.takes_engine]
    todo = [case for case in todo if AS_ROOT or case.read_only is None]  # read-only mounts need root
    with lock_held_elsewhere(world.copies["locked"]), lock_held_elsewhere(world.copies["lock-removed"]):
        (world.copies["lock-removed"] / LOCK_NAME).unlink()
        with ThreadPoolExecutor(max_workers=3) as pool:
            failures = [f for f in pool.map(lambda case: check(case, engine, env, tmp_path), todo) if f]
    assert not failures, f"{len(failures)} of {len(todo)} cases failed:\n" + "\n".join(failures)
    assert not (home / "prefect.db").exists()  # refused before Prefect started, every one
    return todo


@pytest.mark.e2e
def test_every_bad_input_is_one_error_line_exit_2_and_changes_nothing_local(world: World, tmp_path: Path):
    done = run_all(world, "local", tmp_path)
    assert len({c.name for c in done}) == len(done) >= 250


@pytest.mark.e2e
def test_every_bad_input_is_one_error_line_exit_2_and_changes_nothing_prefect(world: World, tmp_path: Path):
    done = run_all(world, "prefect", tmp_path)
    assert len(done) >= 170


def _run(*args: str, env: dict[str, str] | None = None, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "flows", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        env={**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})},
        cwd=ROOT,
    )


@pytest.mark.e2e
@pytest.mark.parametrize("engine", ["local", "prefect"])
def test_damaged_segment_data_is_rebuilt_by_its_step(world: World, tmp_path: Path, engine: str):
    """A deleted frame chunk and a segment's damaged array metadata (its inputs, the plan, intact): the same run
    again regenerates that segment, exit 0, and the frames come back as they were; nothing else runs again."""
    truth = SceneStore.open(world.scene).array(FRAMES)
    spec = tmp_path / "spec.yaml"
    spec.write_text(yaml.safe_dump(_spec_data(scene__video={**TINY_VIDEO, "options": {"fault_probability": 0.0}})))
    for kind in ("chunk", "metadata"):
        scene = tmp_path / kind
        shutil.copytree(world.scene, scene)
        array = scene / "scene.zarr" / FRAMES
        if kind == "chunk":
            (array / "c" / "1" / "0" / "0" / "0").unlink()
        else:
            meta = json.loads((array / "zarr.json").read_text())
            del meta["data_type"]
            (array / "zarr.json").write_text(json.dumps(meta))
        assert SceneStore.open(scene).damaged_groups()
        args = ("generate", "--config", str(spec), "--out", str(scene), "--until", "generate_segments")
        r = _run(*args, "--engine", engine, env=_prefect_env(tmp_path / "prefect"))
        assert r.returncode == 0 and "error" not in r.stderr and "Traceback" not in r.stderr, r.stderr[-3000:]
        assert "] plan: cached" in r.stderr and "] generate_segments: " in r.stderr, r.stderr
        store = SceneStore.open(scene)
        assert store.damaged_groups() == {}
        np.testing.assert_array_equal(store.array(FRAMES), truth)
        if engine == "prefect":
            break  # one kind is enough to show the same under Prefect (its server costs ~15 s)


class _Nonsense(BaseHTTPRequestHandler):
    answers: ClassVar[list[bytes]] = [
        b'{"choices": [{"message": {"role": "assistant", "content": "\\u001b[2Jbanana \\u0007 42"}}]}',
        b"<html>not json</html>",
        b'{"choices": []}',
    ]

    def do_POST(self) -> None:
        self.rfile.read(int(self.headers.get("Content-Length", 0)))
        body = self.answers[self.server.calls % len(self.answers)]  # type: ignore[attr-defined]
        self.server.calls += 1  # type: ignore[attr-defined]
        self.send_response(200)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, *args: object) -> None:
        pass


@pytest.mark.e2e
def test_a_chat_server_answering_nonsense_falls_back_to_the_rules_with_a_warning(tmp_path: Path):
    httpd = ThreadingHTTPServer(("127.0.0.1", 0), _Nonsense)
    httpd.calls = 0  # type: ignore[attr-defined]
    thread = threading.Thread(target=httpd.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)
    thread.start()
    try:
        url = f"http://127.0.0.1:{httpd.server_address[1]}/v1"
        planner = {"backend": "chat", "base_url": url, "timeout_s": 10, "api_key_env": "WV_ADVERSARIAL_KEY"}
        spec = tmp_path / "chat.yaml"
        spec.write_text(yaml.safe_dump(_spec_data(scene__planner=planner)))
        scene = tmp_path / "scene"
        env = {"WV_ADVERSARIAL_KEY": "sk-adversarial-0123456789", "NO_PROXY": "*", "no_proxy": "*"}
        t0 = time.monotonic()
        r = _run(
            "generate", "--config", str(spec), "--out", str(scene), "--until", "plan", "--engine", "local", env=env
        )
        assert r.returncode == 0, r.stderr
        assert time.monotonic() - t0 < 60
        assert not any(ln.startswith("error") for ln in r.stderr.splitlines()) and "Traceback" not in r.stderr
        assert "rules (fallback from chat)" in r.stderr, r.stderr  # the plan line says so
        assert not _raw_controls(r.stderr + r.stdout), r.stderr
        plan = SceneStore.open(scene).meta(PLAN.path).plan
        assert plan.planner == "rules (fallback from chat)" and plan.fallback_reason, plan
        stored = json.dumps(plan.model_dump(mode="json"), ensure_ascii=False)
        assert not _raw_controls(stored), plan  # the answer's escapes are not kept
        assert httpd.calls >= 1  # type: ignore[attr-defined]
    finally:
        httpd.shutdown()
        httpd.server_close()


def test_control_characters_are_refused_and_tabs_and_line_breaks_become_spaces():
    """The policy, character by character, where every path builds its config: the prompt and extension words."""
    from flows.extend import extended_config
    from wonderverse.errors import ConfigError, WonderError

    cfg = tiny_config("a house\tby the\r\nsea \u2028 at  dusk")
    assert cfg.scene.prompt == "a house by the sea at dusk"
    assert extended_config(cfg, "go\tleft\n").scene.extensions.added == ("go left",)
    controls = [chr(c) for c in [*range(0x20), *range(0x7F, 0xA0)] if chr(c) not in "\t\n\r"]
    assert len(controls) == 32 - 3 + 33
    for ch in controls:
        where = re.escape(f"U+{ord(ch):04X}")
        with pytest.raises(ConfigError, match=f"scene.prompt: the prompt holds the control character {where}"):
            tiny_config(f"a house{ch}")
        with pytest.raises(ConfigError, match=f"scene.extensions.added.0: the extension holds .* {where}"):
            tiny_config(extensions={"added": [f"left{ch}"]})
        with pytest.raises(WonderError, match=f"request holds the control character {where}.* at character 4"):
            extended_config(cfg, f"go {ch}left")
    assert tiny_config("une maison en été, 雪の家 🎄").scene.prompt == "une maison en été, 雪の家 🎄"  # text is fine


@pytest.mark.e2e
def test_forged_metadata_that_passes_the_digests_is_damage_rebuilt_by_its_step(world: World, tmp_path: Path):
    """A segment's frames metadata rewritten, its digest re-recorded so that only the limits can tell (an impossible
    shape, millions of chunks, nesting beyond the parser, another shape than the schema's): the next run of the same
    config regenerates that segment, the frames come back as they were, nothing else runs again."""
    truth = SceneStore.open(world.scene).array(FRAMES)
    cfg = complete_config()
    for kind in ("huge-shape", "tiny-chunks", "deep", "schema-shape"):
        scene = tmp_path / kind
        shutil.copytree(world.scene, scene)
        _forge_frames_meta(scene, kind)
        assert "segments/s000" in SceneStore.open(scene).damaged_groups(), kind
        results = {r.step: r.status for r in execute(scene, cfg, until="generate_segments")}
        assert results == {"plan": "cached", "generate_segments": "ran"}, (kind, results)
        store = SceneStore.open(scene)
        assert store.damaged_groups() == {}, kind
        np.testing.assert_array_equal(store.array(FRAMES), truth)


@pytest.mark.e2e
def test_inspect_lists_forged_metadata_as_damage_without_a_traceback(world: World):
    for kind in ("deep", "huge-shape", "tiny-chunks"):
        r = _run("inspect", str(world.copies[f"forged-{kind}"]), timeout=120)
        assert r.returncode == 0 and "Traceback" not in r.stderr, r.stderr[-2000:]
        assert "damaged: segments/s000: the metadata of array attempts/0/frames" in r.stdout, r.stdout[-2000:]


@pytest.mark.e2e
def test_output_files_deleted_or_altered_are_made_again(world: World, tmp_path: Path):
    """`outputs` records every file it leaves beside the store with its digest: a deleted mesh.ply, a truncated
    splats.ply and a file removed inside nerfstudio/ make the products that wrote them run again; then all is
    cached."""
    from tasks.outputs import altered_files
    from wonderverse.schema import OUTPUTS

    scene = tmp_path / "scene"
    shutil.copytree(world.scene, scene)
    recorded = {f.path: f.digest for f in SceneStore.open(scene).meta(OUTPUTS.path).files}
    assert recorded["mesh.ply"] and recorded["splats.ply"] and recorded["nerfstudio"]
    (scene / "mesh.ply").unlink()
    os.truncate(scene / "splats.ply", 100)
    image = sorted((scene / "nerfstudio" / "images").iterdir())[0]
    image.unlink()
    store = SceneStore.open(scene)
    assert altered_files(store) == {"mesh.ply", "splats.ply", "nerfstudio"}
    assert any("file mesh.ply is missing" in p for p in store.damaged_groups().get(OUTPUTS.path, []))
    cfg = complete_config()
    results = {r.step: r.status for r in execute(scene, cfg)}
    assert results["outputs"] == "ran" and results["splats"] == "cached", results
    assert (scene / "mesh.ply").is_file() and image.is_file()
    assert (scene / "splats.ply").stat().st_size == (world.scene / "splats.ply").stat().st_size
    assert altered_files(SceneStore.open(scene)) == set()
    assert {r.status for r in execute(scene, cfg)} == {"cached"}

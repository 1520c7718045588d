"""The rules behind the refusals of tests/test_adversarial.py, one function each, without a subprocess: the name rule
for folders made from names, invisible and reordering text, credentials in URLs, configs read by type and without
duplicate keys, zarr metadata read within limits, and a scene folder judged before it is locked or written."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from wonderverse.errors import ConfigError, StoreError, WonderError, shown
from wonderverse.folders import LOCK_NAME, check_scene_dir, read_limited_json, read_regular
from wonderverse.text import control_character, redact_urls, scene_name_problem, url_credentials, visible, words_problem

GOOD_NAMES = ["garden", "a house", "scene-2", "x.y", "été", "雪の家", "🎄", "a..b", "-", "x" * 255, "é" * 127]
# name -> a part of why it is refused
BAD_NAMES = {
    "": "empty",
    " ": "empty",
    ".": "'.' is not a folder",
    "..": "'..' is not a folder",
    "...": "hidden",
    ".hidden": "hidden",
    "\uff0e": "'.' is not a folder",  # fullwidth full stop
    "\uff0e\uff0e": "'..' is not a folder",
    "\ufe52\ufe52": "'..' is not a folder",  # small full stop
    "\u2024": "'.' is not a folder",  # one dot leader
    "\u2025": "'..' is not a folder",  # two dot leader
    "a/b": "path separator",
    "/": "path separator",
    "a\\b": "path separator",
    "a\uff0fb": "path separator",  # fullwidth solidus
    "a\x00b": "control character U+0000",
    "\x1b[2Jx": "U+001B (ESC)",
    "x\x9b": "U+009B (CSI)",
    "\u202ex": "U+202E (RLO)",
    "x\u2066": "U+2066 (LRI)",
    "a\nb": "line break",
    "a\tb": "tab",
    "\u200b": "shows nothing",
    "\u3164": "shows nothing",
    " a": "space",
    "a ": "space",
    "a\u3000": "space",  # ideographic space: a space after normalisation
    "x" * 256: "longer than 255 bytes",
    "é" * 128: "longer than 255 bytes",
}


@pytest.mark.parametrize("name", GOOD_NAMES)
def test_a_single_plain_folder_name_is_a_scene_name(name: str):
    assert scene_name_problem(name) is None


@pytest.mark.parametrize(("name", "why"), BAD_NAMES.items(), ids=[ascii(n)[:30] for n in BAD_NAMES])
def test_names_that_are_no_single_folder_name_are_refused_with_the_reason(name: str, why: str):
    problem = scene_name_problem(name)
    assert problem is not None and why in problem, problem


def test_the_name_rule_is_one_function_the_store_exports():
    import wonderverse.store

    assert wonderverse.store.scene_name_problem is scene_name_problem
    assert scene_name_problem(None) is not None  # type: ignore[arg-type]


def test_a_batch_refuses_a_spec_whose_name_is_no_folder_name_before_anything_runs(tmp_path: Path):
    from flows.serve import find_specs

    (tmp_path / "good.yaml").write_text("scene: {prompt: x}\n")
    assert find_specs(tmp_path) == [tmp_path / "good.yaml"]
    for bad in ("..yaml", "...yaml", "\uff0e\uff0e.yaml"):
        (tmp_path / bad).write_text("scene: {prompt: x}\n")
        with pytest.raises(WonderError, match="cannot name a scene folder"):
            find_specs(tmp_path)
        (tmp_path / bad).unlink()


@pytest.mark.parametrize(
    "text", ["", "   ", "\u200b", "\u200b\u200c\u200d\u2060\ufeff", "\u3164", "\u2800", "\u0301", "\u200e"]
)
def test_text_made_only_of_invisible_characters_shows_nothing(text: str):
    assert not visible(text)
    assert words_problem(text, "the prompt", 100) is not None


def test_visible_text_in_any_script_is_fine():
    for text in ("a", "雪", "🎄", "שלום", "مرحبا", "é"):
        assert visible(text) and words_problem(text, "the prompt", 100) is None


def test_bidirectional_controls_are_control_characters_and_error_lines_escape_them():
    from flows.cli import error_line

    assert control_character("ab\u202ecd") == "U+202E (RLO) at character 3"
    assert control_character("\u2067") == "U+2067 (RLI) at character 1"
    assert error_line("no such file: \u202egnp.exe\x1b[2J") == "no such file: \\u202egnp.exe\\x1b[2J"
    assert error_line("a\u00e9\u05d0") == "a\u00e9\u05d0"  # letters of any script stay as they are


URLS = {
    "http://user:s3cret@host/v1": "http://user:***@host/v1",
    "https://u:p%40ss@h.example:8443/x?y=1": "https://u:***@h.example:8443/x?y=1",
    "see tcp://a:b@10.0.0.1:8786 and http://c:d@e/": "see tcp://a:***@10.0.0.1:8786 and http://c:***@e/",
    "http://host/v1": "http://host/v1",
    "mail me: a@b.c": "mail me: a@b.c",
}


@pytest.mark.parametrize(("text", "shown_as"), URLS.items())
def test_the_password_of_a_url_is_redacted(text: str, shown_as: str):
    assert redact_urls(text) == shown_as


def test_a_url_with_credentials_is_refused_in_config_without_showing_the_password():
    from conftest import tiny_config

    secret = "PW" + "x" * 200  # longer than any quote of a value: a cut URL must not leak its start
    for url in (f"http://user:{secret}@127.0.0.1/v1", f"http://u:{secret}@{'h' * 90}/v1", "http://admin@h/v1"):
        assert url_credentials(url) is not None
        with pytest.raises(ConfigError, match="carries credentials") as e:
            tiny_config(planner={"backend": "chat", "base_url": url})
        assert "PWx" not in str(e.value) and "api_key_env" in url_credentials(url)  # type: ignore[operator]
        assert "PWx" not in shown({"planner": {"base_url": url}})
    assert url_credentials("http://127.0.0.1:8000/v1") is None
    from wonderverse.config import validate_config

    data = tiny_config().model_dump()
    with pytest.raises(ConfigError, match=r"execution\.dask_address: .*carries credentials"):
        validate_config({**data, "execution": {**data["execution"], "dask_address": "tcp://u:p@h:1"}})


def test_configs_are_regular_files_read_without_blocking(tmp_path: Path):
    from wonderverse.yaml_files import read_yaml

    fifo = tmp_path / "config.yaml"
    os.mkfifo(fifo)
    for path in (fifo, Path("/dev/zero"), Path("/dev/null")):
        with pytest.raises(ConfigError, match="not a regular file"):
            read_yaml(path)
    with pytest.raises(WonderError, match="Is a directory"):
        read_regular(tmp_path, "scene spec", 10)


@pytest.mark.parametrize(
    ("text", "line"),
    [("a: 1\na: 2\n", 2), ("s:\n  p: 1\n  q: 2\n  p: 3\n", 4), ("s: {p: 1, p: 1}\n", 1), ("1: a\n1: b\n", 2)],
)
def test_a_key_given_twice_is_refused_with_its_lines(tmp_path: Path, text: str, line: int):
    from wonderverse.yaml_files import read_yaml

    f = tmp_path / "dup.yaml"
    f.write_text(text)
    with pytest.raises(ConfigError, match=rf"at line {line}, .*duplicate key"):
        read_yaml(f)


def test_merge_keys_and_recursive_aliases_keep_working(tmp_path: Path):
    from wonderverse.yaml_files import read_yaml

    f = tmp_path / "merge.yaml"
    f.write_text("base: &b {a: 1, b: 2}\nx:\n  <<: *b\n  a: 3\n")
    assert read_yaml(f)["x"] == {"a": 3, "b": 2}
    f.write_text("scene: &a {prompt: x, video: *a}\n")
    with pytest.raises(ConfigError, match="expands to more than"):
        read_yaml(f)


def test_json_metadata_is_read_within_limits(tmp_path: Path):
    f = tmp_path / "zarr.json"
    for raw, why in [
        (b"[" * 100_000 + b"]" * 100_000, "nested deeper than"),
        (b"[" * 65 + b"]" * 65, "nested deeper than"),
        (b'{"shape": [' + b"9" * 30 + b"]}", "integer beyond"),
        (b"{not json", "not JSON"),
        (b" " * 17_000_000, "larger than"),
    ]:
        f.write_bytes(raw)
        with pytest.raises(ValueError, match=why):
            read_limited_json(f)
    f.unlink()
    os.mkfifo(f)
    with pytest.raises(ValueError, match="not a regular file"):
        read_limited_json(f)


def _array_meta(shape: list, chunks: list, dtype: str = "uint8") -> dict:
    return {
        "node_type": "array",
        "shape": shape,
        "data_type": dtype,
        "chunk_grid": {"name": "regular", "configuration": {"chunk_shape": chunks}},
    }


@pytest.mark.parametrize(
    ("meta", "why"),
    [
        (_array_meta([6, 64, 96, 3], [1, 64, 96, 3]), None),
        (_array_meta([6_000_000, 64, 96, 3], [1, 64, 96, 3]), "chunks, more than"),
        (_array_meta([6, 64, 96, 3], [1, 1, 1, 1]), "chunks, more than"),
        (_array_meta([6, 64_000, 96_000, 3], [6, 64_000, 96_000, 3]), "bytes"),
        (_array_meta([2**41], [2**41]), "beyond the limits"),
        (_array_meta([1] * 9, [1] * 9), "beyond the limits"),
        (_array_meta([6, 64], [1, 64, 3]), "one per axis"),
        (_array_meta([6.5], [1]), "list of sizes"),
        (_array_meta([6], [0]), "list of sizes"),
        (_array_meta([6], [1], "object"), "not a number's"),
        (_array_meta([6], [1], "bogus"), "not a number's"),
        ({"node_type": "group"}, "not an array's"),
    ],
)
def test_array_metadata_is_judged_before_zarr_reads_it(meta: dict, why: str | None):
    from wonderverse.store import array_meta_problem

    problem = array_meta_problem(meta)
    assert (problem is None) if why is None else (problem is not None and why in problem), problem


def test_array_metadata_must_match_the_schema():
    from wonderverse.schema import ATTEMPT
    from wonderverse.store import array_meta_problem

    declared = ATTEMPT.at(seg="s000", attempt=0).frames.spec
    assert array_meta_problem(_array_meta([6, 64, 96, 3], [1, 64, 96, 3]), declared) is None
    assert "schema" in (array_meta_problem(_array_meta([6, 64, 96, 4], [1, 64, 96, 4]), declared) or "")
    assert "schema" in (array_meta_problem(_array_meta([6, 64, 96, 3], [1, 64, 96, 3], "float32"), declared) or "")


def _names(folder: Path) -> list[tuple[str, bytes | None]]:
    return sorted((str(p.relative_to(folder)), p.read_bytes() if p.is_file() else None) for p in folder.rglob("*"))


@pytest.mark.parametrize(
    ("entries", "why"),
    [
        ({LOCK_NAME: b"my own notes"}, "not empty and holds no scene"),
        ({LOCK_NAME: b'{"pid": 1, "note": "mine"}'}, "not empty and holds no scene"),
        ({LOCK_NAME: b"", "photo.jpg": b"\xff\xd8"}, "not empty and holds no scene"),
        ({"scene.zarr": b"a file"}, "holds no scene store"),
        ({"scene.zarr/segments/x": b""}, "holds no scene store"),
        ({f"{LOCK_NAME}/x": b""}, "is not a regular file"),
    ],
)
def test_a_folder_that_is_no_scene_is_refused_before_the_lock_and_stays_as_it_was(
    tmp_path: Path, entries: dict[str, bytes], why: str
):
    from wonderverse.store import scene_lock

    folder = tmp_path / "scene"
    for rel, content in entries.items():
        (folder / rel).parent.mkdir(parents=True, exist_ok=True)
        (folder / rel).write_bytes(content)
    before = _names(folder)
    with pytest.raises(StoreError, match=why):
        check_scene_dir(folder)
    with pytest.raises(StoreError, match=why), scene_lock(folder):
        pass
    assert _names(folder) == before


def test_a_lock_file_left_by_a_run_is_no_obstacle(tmp_path: Path):
    from wonderverse.store import scene_lock

    for content in (b"", b"{}", json.dumps({"pid": 1, "host": "h", "since": "t"}).encode()):
        folder = tmp_path / f"left-{len(content)}"
        folder.mkdir()
        (folder / LOCK_NAME).write_bytes(content)
        check_scene_dir(folder)
        with scene_lock(folder) as lock:
            assert json.loads(lock.read_text())["pid"] == os.getpid()


def test_a_refusal_judged_under_the_lock_leaves_no_folder_behind(tmp_path: Path):
    from wonderverse.store import scene_lock

    target = tmp_path / "new" / "deeper" / "scene"
    calls = []

    def judge() -> None:
        calls.append(target.exists())
        raise WonderError("refused")

    with pytest.raises(WonderError, match="refused"), scene_lock(target, judge=judge):
        pass
    assert calls == [False] and not (tmp_path / "new").exists()  # judged before the folder existed


def test_an_existing_scene_is_judged_under_its_lock_before_its_lock_file_is_written(tmp_path: Path):
    from wonderverse.store import SceneStore, scene_lock

    scene = tmp_path / "scene"
    SceneStore.open_or_create(scene, spec={"prompt": "x"})
    (scene / LOCK_NAME).write_bytes(b"")
    before = _names(scene)

    def judge() -> None:
        assert (scene / LOCK_NAME).read_bytes() == b""  # nothing written yet
        raise WonderError("refused")

    with pytest.raises(WonderError, match="refused"), scene_lock(scene, judge=judge):
        pass
    assert _names(scene) == before

"""Bad configuration at the command line: one `error:` line naming the field, exit code 2, and
the scene folder byte-identical before and after, under both engines; nothing reaches Prefect either."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from conftest import TINY_VIDEO, run_cli, tiny_config, tree_digest

from flows.pipeline import execute

pytestmark = pytest.mark.e2e  # the CLI in a subprocess, over a generated scene


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("bad-config") / "scene"
    execute(d, tiny_config(), until="plan")  # a real scene (store, plan, stored config) that must stay as it is
    return d


def spec(folder: Path, name: str, **changes) -> Path:
    """A valid tiny scene spec with `changes` deep in it (scene.video.options, steps.plan, ...)."""
    data = {"preset": "preview", "scene": {"prompt": "a small house", "video": dict(TINY_VIDEO)}}
    for path, value in changes.items():
        node = data
        *parents, leaf = path.split("__")
        for p in parents:
            node = node.setdefault(p, {})
        node[leaf] = value
    f = folder / f"{name}.yaml"
    f.write_text(yaml.safe_dump(data))
    return f


def bad_inputs(folder: Path) -> list[tuple[list[str], str]]:
    raw = {
        "list": (b"- preset: preview\n- scene: {prompt: x}\n", "must hold a mapping of settings, not a list"),
        "binary": (bytes(range(256)) * 8, "is not UTF-8 text"),
        "latin1": ("scene: {prompt: une maison en été}\n".encode("latin-1"), "is not UTF-8 text (byte 0xe9"),
    }
    cases = []
    for name, (content, message) in raw.items():
        (folder / f"{name}.yaml").write_bytes(content)
        cases.append((["--config", str(folder / f"{name}.yaml")], message))
    cases += [
        (["--config", str(spec(folder, "scene5", scene=5))], "scene: must be a mapping of settings (got 5)"),
        (
            ["--config", str(spec(folder, "unknown", scene__video__options={"bogus_option": 1}))],
            "scene.video.options.bogus_option: unknown setting",
        ),
        (
            ["--config", str(spec(folder, "range", scene__video__options={"fault_probability": 5}))],
            "scene.video.options.fault_probability: Input should be less than or equal to 1 (got 5)",
        ),
        (
            ["--config", str(spec(folder, "move", steps__plan={"initial_move": "sideways 5"}))],
            "steps.plan.initial_move: expected 3 clauses",
        ),
        (
            [
                "--config",
                str(
                    spec(
                        folder,
                        "oracle",
                        scene__video={"backend": "files", "clips": ["/x/clip.mp4"]},
                        steps__priors__models={"depth_backend": "oracle"},
                    )
                ),
            ],
            "steps.priors.models.depth_backend: the oracle prior needs the procedural world's ground truth",
        ),
        (
            ["--config", str(spec(folder, "noclip", scene__video={"backend": "files", "clips": ["/x/clip.mp4"]}))],
            "/x/clip.mp4: no such file",
        ),
        (["a small house", "--preset", "../../tmp/x"], "unknown preset '../../tmp/x'; choose one of: high,"),
        (["a small house", "--preset", ""], "unknown preset ''; choose one of: high, preview, standard"),
    ]
    return cases


@pytest.mark.parametrize("engine", ["local", "prefect"])
def test_bad_config_is_one_line_exit_2_and_leaves_the_scene_as_it_was(scene: Path, tmp_path: Path, engine: str):
    before = tree_digest(scene)
    prefect_home = tmp_path / "prefect"
    env = {"PREFECT_HOME": str(prefect_home), "PREFECT_SERVER_ANALYTICS_ENABLED": "false"}
    for args, message in bad_inputs(tmp_path):
        r = run_cli("generate", *args, "--out", str(scene), "--engine", engine, env=env)
        lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
        assert r.returncode == 2, (args, r.stderr)
        assert len(lines) == 1 and lines[0].startswith("error: ") and message in lines[0], (args, r.stderr)
        assert r.stdout == "", (args, r.stdout)
        assert tree_digest(scene) == before, args
    assert not (prefect_home / "prefect.db").exists()  # refused before Prefect started


def test_huge_and_exploding_config_files_are_refused_at_once(scene: Path, tmp_path: Path):
    before = tree_digest(scene)
    bomb = tmp_path / "bomb.yaml"
    lines = ["a: &a [lol, lol, lol, lol, lol, lol, lol, lol, lol]"]
    lines += [f"{c}: &{c} [{', '.join(['*' + p] * 9)}]" for p, c in zip("abcdefghi", "bcdefghij", strict=True)]
    bomb.write_text("\n".join(lines) + "\nscene: {prompt: *j}\n")
    huge = tmp_path / "huge.yaml"
    huge.write_text(yaml.safe_dump({"scene": {"prompt": "ok", "seed": "9" * 900_000}}))
    for f, message in ((bomb, "expands to more than 100000 values"), (huge, "scene.seed: ")):
        r = run_cli("generate", "--config", str(f), "--out", str(scene), "--engine", "local", timeout=60)
        lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
        assert r.returncode == 2 and len(lines) == 1 and message in lines[0], r.stderr[-2000:]
        assert len(lines[0]) < 400 + len(str(f))  # the 900 kB value is quoted in at most ~60 characters
    assert tree_digest(scene) == before


def test_reconstruct_refuses_in_one_line_before_writing_anything(tmp_path: Path):
    """A clip that cannot be read (here a folder without images) is refused before the scene folder exists."""
    clip = tmp_path / "clip"
    clip.mkdir()
    r = run_cli("reconstruct", str(clip), "--out", str(tmp_path / "s"), "--engine", "local")
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 2 and len(lines) == 1, r.stderr
    assert lines[0].startswith(f"error: {clip}: folder has no images"), r.stderr
    assert not (tmp_path / "s").exists()

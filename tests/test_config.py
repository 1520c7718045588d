"""Config: presets, precedence, and errors that name the field and the bad value."""

from __future__ import annotations

import copy
import typing
from pathlib import Path
from typing import Any, Literal

import pytest
import yaml
from pydantic import BaseModel

from wonderverse.config import PRESET_DIR, VideoSpec, build_config, deep_merge, preset_names, validate_config
from wonderverse.errors import ConfigError
from wonderverse.video.diffusion import DiffusionParams
from wonderverse.video.files import ClipParams
from wonderverse.video.procedural_options import ProceduralOptions


def test_presets_exist_and_order_speed_against_accuracy():
    assert {"preview", "standard", "high"} <= set(preset_names())
    sizes = {p: build_config("a forest", preset=p).scene.video for p in ("preview", "standard", "high")}
    px = {p: v.width * v.height * v.frames_per_segment for p, v in sizes.items()}
    assert px["preview"] < px["standard"] < px["high"]


def test_precedence_defaults_preset_file_cli(tmp_path: Path):
    f = tmp_path / "scene.yaml"
    f.write_text("preset: preview\nscene:\n  prompt: from file\n  seed: 3\n  video: {fps: 12}\n")
    cfg = build_config(config_file=f)
    assert cfg.preset == "preview" and cfg.scene.prompt == "from file" and cfg.scene.seed == 3
    assert cfg.scene.video.fps == 12 and cfg.scene.video.width == 320  # file over preset, preset kept
    cfg = build_config("from cli", preset="high", config_file=f, overrides={"scene": {"seed": 9}})
    assert (cfg.preset, cfg.scene.prompt, cfg.scene.seed, cfg.scene.video.width) == (
        "high",
        "from cli",
        9,
        720,
    )


def test_example_scene_loads():
    cfg = build_config(config_file=Path(__file__).parents[1] / "configs/scenes/christmas_house.yaml")
    assert "Christmas" in cfg.scene.prompt and cfg.scene.extensions.rounds >= 1


@pytest.mark.parametrize(
    ("prompt", "overrides", "message"),
    [
        ("   ", None, r"scene\.prompt: prompt is empty"),
        ("x" * 10_000, None, r"scene\.prompt: prompt has 10000 characters"),
        (
            "ok",
            {"scene": {"video": {"frames_per_segment": -3}}},
            r"scene\.video\.frames_per_segment: .*got -3",
        ),
        ("ok", {"scene": {"vidoe": {}}}, r"scene\.vidoe: unknown setting"),
        ("ok", {"scene": {"video": {"fov_deg": 200}}}, r"scene\.video\.fov_deg: .*got 200"),
        ("ok", {"scene": {"extensions": {"directions": ["sideways"]}}}, r"directions\.0: .*got 'sideways'"),
        ("ok", {"scene": {"seed": -1}}, r"scene\.seed: .*got -1"),
        (
            "ok",
            {"scene": {"video": {"backend": "diffusers"}}, "steps": {"poses": {"source": "conditioning"}}},
            r"take no camera input: use steps\.poses\.source sfm",
        ),
    ],
)
def test_bad_values_name_field_and_value(prompt, overrides, message):
    with pytest.raises(ConfigError, match=message):
        build_config(prompt, overrides=overrides)


def test_unknown_preset_malformed_yaml_missing_file(tmp_path: Path):
    with pytest.raises(ConfigError, match="unknown preset 'turbo'; choose one of: high, preview, standard"):
        build_config("ok", preset="turbo")
    bad = tmp_path / "bad.yaml"
    bad.write_text("scene:\n  prompt: [unclosed\n  seed: 1\n")
    with pytest.raises(ConfigError, match=r"malformed YAML in .*bad\.yaml at line \d+"):
        build_config(config_file=bad)
    scalar = tmp_path / "scalar.yaml"
    scalar.write_text("just a string\n")
    with pytest.raises(ConfigError, match="must hold a mapping"):
        build_config(config_file=scalar)
    with pytest.raises(ConfigError, match="cannot read config file"):
        build_config(config_file=tmp_path / "missing.yaml")
    with pytest.raises(ConfigError, match="no prompt given"):
        build_config()


# ---------------------------------------------------------------- deep merge: a partial block changes what it names

BACKENDS: dict[str, dict[str, Any]] = {
    "procedural": {},
    "files": {"scene": {"video": {"backend": "files", "clips": ["clip.mp4"]}}},
    "diffusers": {"scene": {"video": {"backend": "diffusers"}}},
}
# The oracle priors need the procedural world's ground truth; the other backends take a network's.
NETWORK_PRIORS = {"steps": {"priors": {"models": {"depth_backend": "depth_anything"}}}}


def _base_overrides(backend: str) -> dict[str, Any]:
    return deep_merge(BACKENDS[backend], NETWORK_PRIORS if backend != "procedural" else {})


def _nested_models(model: BaseModel, path: tuple[str, ...] = ()) -> list[tuple[tuple[str, ...], BaseModel]]:
    """Every model inside `model` (the video options included), with its path, depth first."""
    found = []
    for name in type(model).model_fields:
        value = getattr(model, name)
        if isinstance(value, BaseModel):
            found.append(((*path, name), value))
            found += _nested_models(value, (*path, name))
    return found


def _candidates(annotation: Any, value: Any) -> list[Any]:
    """Other values a leaf of this type might take (some may be out of its range; the caller tries them)."""
    if isinstance(value, bool):
        return [not value]
    args = typing.get_args(annotation)
    if typing.get_origin(annotation) is Literal:
        return [a for a in args if a != value]
    literal = [a for arg in args if typing.get_origin(arg) is Literal for a in typing.get_args(arg) if a != value]
    if literal:
        return literal
    if isinstance(value, int):
        return [value + 1, value - 1, value * 2, 1, 2]
    if isinstance(value, float):
        return [value * 1.1, value * 0.9, value + 0.05, value / 2, 0.5, 1.0, 2.0] if value else [0.1, 0.5, 1.0]
    return []


def _with_leaf(cfg: dict[str, Any], path: tuple[str, ...], leaf: str, value: Any, block: BaseModel) -> dict[str, Any]:
    out = copy.deepcopy(cfg)
    node = out
    for p in path:
        # a block left unwritten at its default (`loss.robust`, so that older cache keys hold) is written whole
        # once one of its leaves differs
        node = node.setdefault(p, {})
    if not node:
        node.update(block.model_dump())
    node[leaf] = value
    return out


def _nest(path: tuple[str, ...], leaf: str, value: Any) -> dict[str, Any]:
    block: dict[str, Any] = {leaf: value}
    for p in reversed(path):
        block = {p: block}
    return block


@pytest.mark.parametrize("backend", list(BACKENDS))
def test_overriding_one_leaf_of_any_nested_model_keeps_every_other_value(backend: str) -> None:
    """For every nested model of the config (found by walking it, so a new one is covered without a test change)
    override one leaf alone, as a user's partial block does: the result differs from the defaults in that leaf only."""
    base = build_config("a forest", preset="standard", overrides=_base_overrides(backend))
    base_data = base.model_dump()
    models = _nested_models(base)
    checked, blocks = [], []
    for path, model in models:
        if all(isinstance(getattr(model, name), BaseModel) for name in type(model).model_fields):
            blocks.append(".".join(path))
            continue  # only blocks (`steps`, `steps.generate_segments`): each is checked itself
        changed = False
        for leaf, field in type(model).model_fields.items():
            value = getattr(model, leaf)
            if isinstance(value, BaseModel) or (leaf == "backend" and isinstance(model, VideoSpec)):
                continue  # blocks are checked themselves; the video backend picks which model the options are
            for new in _candidates(field.annotation, value):
                over = deep_merge(_base_overrides(backend), _nest(path, leaf, new))
                try:
                    cfg = build_config("a forest", preset="standard", overrides=over)
                except ConfigError:
                    continue  # out of this leaf's range, or against another setting: try another value
                expected = _with_leaf(base_data, path, leaf, _get(cfg, path, leaf), model)
                assert cfg.model_dump() == expected, f"overriding {'.'.join(path)}.{leaf} changed other values"
                assert _get(cfg, path, leaf) != value
                changed = True
                break
            if changed:
                checked.append(".".join(path))
                break
        assert changed, f"no leaf of {'.'.join(path)} could be overridden: extend _candidates"
    assert blocks == ["steps", "steps.generate_segments"] and len(checked) == len(models) - len(blocks)
    assert {"steps.poses.sfm", "steps.check.sfm", "steps.priors.models", "steps.splats.train.strategy"} <= set(checked)
    assert "scene.video.options" in checked
    if backend == "procedural":
        assert {"scene.video.options.layout", "scene.video.options.patterns"} <= set(checked)


def _get(cfg: BaseModel, path: tuple[str, ...], leaf: str) -> Any:
    node: Any = cfg
    for p in (*path, leaf):
        node = getattr(node, p)
    return node


def test_the_reported_partial_blocks_keep_their_siblings(tmp_path: Path) -> None:
    """`poses: {sfm: {num_threads: 1}}` kept the class's 1024 px instead of the step's 480; a partial
    `priors.models` reset `depth_backend` to the class's depth_anything. From a file and from overrides."""
    f = tmp_path / "partial.yaml"
    f.write_text("steps:\n  poses: {sfm: {num_threads: 1}}\n  priors: {models: {batch_size: 2}}\n")
    for cfg in (
        build_config("a forest", preset="preview", config_file=f),
        build_config(
            "a forest",
            preset="preview",
            overrides={"steps": {"poses": {"sfm": {"num_threads": 1}}, "priors": {"models": {"batch_size": 2}}}},
        ),
    ):
        assert (cfg.steps.poses.sfm.num_threads, cfg.steps.poses.sfm.max_image_size_px) == (1, 480)
        assert (cfg.steps.priors.models.batch_size, cfg.steps.priors.models.depth_backend) == (2, "oracle")
        assert cfg.steps.priors.models.normal_backend == "from_depth"


def test_an_empty_block_changes_nothing_and_a_scalar_block_is_refused(tmp_path: Path) -> None:
    f = tmp_path / "empty.yaml"
    f.write_text("scene:\n  prompt: a forest\n  video:\nsteps:\n  poses:\n")
    assert build_config(config_file=f, preset="preview") == build_config("a forest", preset="preview")
    with pytest.raises(ConfigError, match=r"invalid config: steps\.poses: must be a mapping of settings \(got 3\)"):
        build_config("a forest", overrides={"steps": {"poses": 3}})


# ---------------------------------------------------------------- every option typed and checked when built


def test_video_options_are_the_backends_own_models() -> None:
    cfg = build_config("a forest", preset="preview", overrides={"scene": {"video": {"options": {"noise_seed": 3}}}})
    opts = cfg.scene.video.options
    assert isinstance(opts, ProceduralOptions) and opts.noise_seed == 3 and opts.fault_probability == 0.2
    files = build_config(
        "a forest", overrides=deep_merge(_base_overrides("files"), {"scene": {"video": {"options": {"fov_deg": 50}}}})
    )
    assert isinstance(files.scene.video.options, ClipParams) and files.scene.video.options.fov_deg == 50
    assert isinstance(build_config("x", overrides=_base_overrides("diffusers")).scene.video.options, DiffusionParams)
    # stored as plain data, read back as the same typed config
    assert validate_config(files.model_dump(mode="json")) == files
    layout = {"scene": {"video": {"options": {"layout": {"outdoor_objects": 7}}}}}
    layout_opts = build_config("a forest", overrides=layout).scene.video.options
    assert layout_opts.layout.outdoor_objects == 7 and layout_opts.layout.terrain_radius_m == 60.0


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (
            {"scene": {"video": {"options": {"bogus_option": 1}}}},
            r"scene\.video\.options\.bogus_option: unknown setting",
        ),
        (
            {"scene": {"video": {"options": {"fault_probability": 5}}}},
            r"scene\.video\.options\.fault_probability: .*less than or equal to 1 \(got 5\)",
        ),
        (
            {"scene": {"video": {"options": {"layout": {"outdoor_objects": -1}}}}},
            r"scene\.video\.options\.layout\.outdoor_objects: .*\(got -1\)",
        ),
        (
            {"scene": {"video": {"backend": "files", "clips": ["a.mp4"], "options": {"fault_probability": 0.0}}}},
            r"scene\.video\.options\.fault_probability: unknown setting",  # a procedural option, not a clip's
        ),
        ({"scene": {"video": {"options": 7}}}, r"scene\.video\.options: must be a mapping of settings \(got 7\)"),
        ({"steps": {"plan": {"initial_move": "sideways 5"}}}, r"steps\.plan\.initial_move: .*\(got 'sideways 5'\)"),
        (
            {"steps": {"plan": {"initial_move": "up 0, left 500, forward 1"}}},
            r"steps\.plan\.initial_move: .*out of range",
        ),
        (
            {
                "scene": {"video": {"backend": "files", "clips": ["a.mp4"]}},
                "steps": {"priors": {"models": {"depth_backend": "oracle"}}},
            },
            r"steps\.priors\.models\.depth_backend: the oracle prior needs the procedural world's ground truth, "
            r"which files video has none of: use depth_anything",
        ),
        (
            {
                "scene": {"video": {"backend": "diffusers"}},
                "steps": {"priors": {"models": {"depth_backend": "oracle"}}},
            },
            r"steps\.priors\.models\.depth_backend: .*diffusers video",
        ),
        (
            deep_merge(_base_overrides("files"), {"steps": {"priors": {"models": {"normal_backend": "oracle"}}}}),
            r"steps\.priors\.models\.normal_backend: .*use from_depth",
        ),
    ],
)
def test_options_moves_and_priors_are_checked_when_the_config_is_built(overrides, message) -> None:
    with pytest.raises(ConfigError, match=message) as e:
        build_config("a forest", preset="preview", overrides=overrides)
    assert "\n" not in str(e.value)


def test_a_move_in_any_clause_order_is_accepted() -> None:
    cfg = build_config("x", overrides={"steps": {"plan": {"initial_move": "forward 1, left 10 degrees, up 5"}}})
    assert cfg.steps.plan.initial_move == "forward 1, left 10 degrees, up 5"


# ---------------------------------------------------------------- presets are names


@pytest.mark.parametrize("name", ["../../tmp/x", "", "preview.yaml", "/etc/passwd", "presets/preview"])
def test_a_preset_is_a_name_from_the_list_never_a_path(name: str, tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"unknown preset .*; choose one of: high, preview, standard") as e:
        build_config("a forest", preset=name)
    assert "--config" in str(e.value)
    f = tmp_path / "s.yaml"
    f.write_text(yaml.safe_dump({"preset": name, "scene": {"prompt": "a forest"}}))
    with pytest.raises(ConfigError, match="unknown preset"):
        build_config(config_file=f)


def test_a_preset_like_file_is_a_config() -> None:
    cfg = build_config("a forest", preset="standard", config_file=PRESET_DIR / "high.yaml")
    assert cfg.preset == "standard" and cfg.scene.video.width == 720  # its settings, over the named preset


# ---------------------------------------------------------------- bad files are one line, fast, bounded


def _error(path: Path) -> str:
    with pytest.raises(ConfigError) as e:
        build_config(config_file=path)
    message = str(e.value)
    assert "\n" not in message and len(message) < 400 + len(str(path)), message
    return message


def test_bad_config_files_are_one_line_errors(tmp_path: Path) -> None:
    cases = {
        "list.yaml": (b"- a\n- b\n", "must hold a mapping of settings, not a list"),
        "binary.yaml": (bytes(range(256)) * 4, "is not UTF-8 text"),
        "nul.yaml": (b"scene:\x00\x01\x02 {prompt: x}\n", "is binary"),
        "latin1.yaml": ("scene: {prompt: un café}\n".encode("latin-1"), "is not UTF-8 text (byte 0xe9"),
        "scene5.yaml": (b"scene: 5\n", "scene: must be a mapping of settings (got 5)"),
        "deep.yaml": (b"[" * 50_000 + b"]" * 50_000, "nested too deeply"),
        "bigint.yaml": (b"scene: {seed: " + b"9" * 5000 + b"}\n", "malformed YAML"),
        "big.yaml": (b"# " + b"x" * 1_000_000 + b"\n", "is larger than 1 MB"),
    }
    for name, (content, expected) in cases.items():
        f = tmp_path / name
        f.write_bytes(content)
        assert expected in _error(f), name
    assert "not a regular file (a device or a pipe)" in _error(Path("/dev/zero"))  # never read: a device never ends
    assert "cannot read config file" in _error(tmp_path)  # a folder


def test_a_yaml_alias_bomb_is_refused_at_once(tmp_path: Path) -> None:
    lines = ['a: &a ["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]']
    for i in range(1, 10):  # 9^10 values once expanded
        prev, cur = chr(ord("a") + i - 1), chr(ord("a") + i)
        lines.append(f"{cur}: &{cur} [{', '.join([f'*{prev}'] * 9)}]")
    bomb = tmp_path / "bomb.yaml"
    bomb.write_text("\n".join(lines) + "\n")
    assert "expands to more than" in _error(bomb)
    loop = tmp_path / "loop.yaml"
    loop.write_text("scene: &s {prompt: x, video: {options: {layout: *s}}}\n")
    assert "expands to more than" in _error(loop)


def test_error_messages_quote_huge_values_briefly(tmp_path: Path) -> None:
    f = tmp_path / "huge.yaml"
    f.write_text(yaml.safe_dump({"scene": {"prompt": "ok", "seed": list(range(50_000)), "x" * 5000: 1}}))
    message = _error(f)
    assert "scene.seed" in message and "[0, 1, 2, 3, ...]" in message
    f.write_text(yaml.safe_dump({"scene": {"prompt": "ok", "video": {"fps": "y" * 100_000}}}))
    assert "scene.video.fps" in _error(f)
    many = {f"bad{i}": i for i in range(200)}
    f.write_text(yaml.safe_dump({"scene": {"prompt": "ok", **many}}))
    assert "and 195 more" in _error(f)

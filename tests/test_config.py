"""Config: presets, precedence, and errors that name the field and the bad value."""

from __future__ import annotations

from pathlib import Path

import pytest

from wonderverse.config import build_config, preset_names
from wonderverse.errors import ConfigError


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

"""docs/configuration.md is generated from the settings' declarations (`flows.config_docs`): the committed file must
be what the code writes now, and every setting must say what it does."""

from __future__ import annotations

from pathlib import Path

import yaml

from flows import config_docs
from flows.config_docs import DOC, main, missing_descriptions, render

ROOT = Path(__file__).resolve().parents[1]


def test_the_committed_configuration_page_is_current():
    assert DOC.read_text(encoding="utf-8") == render(), "docs/configuration.md is stale: python -m flows.config_docs"


def test_every_setting_has_a_description():
    assert missing_descriptions() == []


def test_check_fails_on_a_stale_page_and_passes_on_a_fresh_one(tmp_path: Path):
    page = tmp_path / "configuration.md"
    assert main(["--check", "--out", str(page)]) == 1  # absent
    assert main(["--out", str(page)]) == 0
    assert main(["--check", "--out", str(page)]) == 0
    page.write_text(page.read_text(encoding="utf-8").replace("segments rendered at once", "segments at once"))
    assert main(["--check", "--out", str(page)]) == 1


def _row(text: str, section: str, setting: str) -> list[str]:
    """The cells of `setting`'s row in the section headed `section`."""
    body = text.split(f"## `{section}`\n", 1)[1].split("\n## ", 1)[0]
    line = next(ln for ln in body.splitlines() if ln.startswith(f"| `{setting}` |"))
    return [c.strip() for c in line.strip("|").split(" | ")]


def test_rows_carry_the_default_at_their_path_and_each_presets_value():
    text = render()
    # the presets' own files are the truth for the presets column
    presets = {p.stem: yaml.safe_load(p.read_text()) for p in (ROOT / "configs" / "presets").glob("*.yaml")}
    iterations = _row(text, "steps.splats.train", "iterations")
    for name, data in presets.items():
        assert f"{name}: `{data['steps']['splats']['train']['iterations']}`" in iterations[4]
    # one model, two paths, two defaults: the check's SfM runs on one thread, the global poses' on two
    assert _row(text, "steps.check.sfm", "num_threads")[2] == "`1`"
    assert _row(text, "steps.poses.sfm", "num_threads")[2] == "`2`"
    # bounds as declared; no preset sets the chat timeout, so its presets cell stays empty
    timeout = _row(text, "scene.planner", "timeout_s")
    assert timeout[3] == "> 0, ≤ 600" and timeout[4] == ""


def test_each_video_backend_has_its_own_options_section():
    text = render()
    backends = (("procedural", "ProceduralOptions"), ("files", "ClipParams"), ("diffusers", "DiffusionParams"))
    for backend, model in backends:
        assert f"## `scene.video.options`, when `scene.video.backend` is `{backend}`" in text
        assert f'<a id="scene-video-options-{model.lower()}"></a>' in text
    assert _row(text, "scene.video.options.defects", "parallax_scale")[2] == "`1.0`"


def test_every_link_on_the_page_has_its_anchor():
    text = render()
    anchors = {part.split('"', 1)[0] for part in text.split('<a id="')[1:]}
    links = {part.split(")", 1)[0] for part in text.split("](#")[1:]}
    assert links and links <= anchors, sorted(links - anchors)


def test_the_page_lives_in_docs():
    assert DOC == ROOT / "docs" / "configuration.md" and config_docs.ROOT == ROOT

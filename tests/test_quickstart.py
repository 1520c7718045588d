"""The README's first command, verbatim, on a fresh copy of the project and in a fresh virtual environment
with only what that command installs: the main job a new user runs first must work end to end. (It once
failed at its last step, importing a module that only the test extra installed, and nothing here saw it.)"""

from __future__ import annotations

from pathlib import Path

import imageio.v2 as imageio
import pytest
from plyfile import PlyData

from benchmarks.first_run import fresh_copy, readme_commands, run_readme_command, scene_of

OUTPUTS = ("splats.ply", "points.ply", "mesh.ply", "mesh.glb", "camera_path.json", "flythrough.mp4", "novel.mp4")


def test_the_readme_holds_exactly_two_commands_the_second_running_the_tests():
    first, second = readme_commands()  # exactly two: unpacking fails otherwise
    assert " generate " in first and "--out" in first and "pip install -e ." in first
    assert "pytest" in second


@pytest.mark.e2e
def test_the_readme_first_command_makes_a_scene_on_a_fresh_copy(tmp_path: Path):
    work = fresh_copy(tmp_path / "wonderverse")
    r = run_readme_command(work)
    assert r.returncode == 0, f"exit {r.returncode}\n{r.stderr[-4000:]}"
    scene = work / scene_of(readme_commands()[0])
    for name in (*OUTPUTS, "report.html", "preview.mp4", "contact_sheet.png"):
        assert (scene / name).is_file() and (scene / name).stat().st_size > 0, name
    for name in OUTPUTS:
        assert str(Path(scene_of(readme_commands()[0])) / name) in r.stdout, name  # the files it says it wrote
    assert PlyData.read(str(scene / "splats.ply"))["vertex"].count > 1000
    with imageio.get_reader(scene / "novel.mp4") as video:
        assert video.get_meta_data()["size"][0] > 0 and sum(1 for _ in video) > 10
    assert any(ln.startswith("wonderverse: preset ") for ln in r.stderr.splitlines())  # it says which preset
    assert "Traceback" not in r.stderr

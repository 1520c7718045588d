"""The two test tiers: an unmarked test that runs a pipeline, the CLI, a server or a browser fails (conftest.py)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from conftest import launch_browser, run_cli, tiny_config

import flows.pipeline
import flows.view
from tasks import STEPS
from tasks.base import StepContext
from wonderverse.store import STORE_NAME, SceneStore

Failed = pytest.fail.Exception  # what pytest.fail raises: a BaseException, which no `except Exception` swallows


def test_an_unmarked_test_may_not_run_a_pipeline(tmp_path: Path) -> None:
    with pytest.raises(Failed, match=r"test_tiers\.py::test_an_unmarked.* runs a pipeline .*@pytest\.mark\.e2e"):
        flows.pipeline.execute(tmp_path / "scene", tiny_config(), until="plan")
    assert not (tmp_path / "scene" / STORE_NAME).exists(), "refused before the store was written"


def test_an_unmarked_test_may_not_run_a_step_on_a_store(tmp_path: Path) -> None:
    store = SceneStore.open_or_create(tmp_path / "scene", spec=tiny_config().scene.model_dump(mode="json"))
    plan = STEPS[0]
    module = sys.modules[plan.run.__module__]
    with pytest.raises(Failed, match="not marked e2e"):
        getattr(module, plan.run.__name__)(store, plan.params(tiny_config()), StepContext("key"))
    with pytest.raises(Failed, match="not marked e2e"):
        plan.run_in(str(tmp_path / "scene"), plan.params(tiny_config()), StepContext("key"))


@pytest.mark.parametrize(
    "argv",
    [
        [sys.executable, "-m", "flows", "--help"],
        ["wonderverse", "generate", "a room"],
        f"{sys.executable} -m benchmarks.tradeoff --quick",
        [sys.executable, "-m", "prefect", "server", "start"],
    ],
)
def test_an_unmarked_test_may_not_start_the_cli_a_benchmark_or_a_server(argv: list[str] | str) -> None:
    with pytest.raises(Failed, match="runs the command"):
        subprocess.run(argv, shell=isinstance(argv, str), capture_output=True)


def test_an_unmarked_test_may_run_other_commands() -> None:
    # a path that merely contains the package's name is no CLI run
    r = subprocess.run([sys.executable, "-c", "print('wonderverse/store.py')"], capture_output=True, text=True)
    assert r.stdout == "wonderverse/store.py\n"


def test_an_unmarked_test_may_not_run_the_cli_through_run_cli_or_typer() -> None:
    from typer.testing import CliRunner

    from flows.cli import app

    with pytest.raises(Failed, match="not marked e2e"):
        run_cli("--help")
    with pytest.raises(Failed, match=r"the CLI \(CliRunner\)"):
        CliRunner().invoke(app, ["--help"])


def test_an_unmarked_test_may_not_start_a_viewer_or_a_browser(tmp_path: Path) -> None:
    with pytest.raises(Failed, match="a server"):
        flows.view.serve_scene(tmp_path)
    with pytest.raises(Failed, match="a browser"):
        launch_browser(None)


@pytest.mark.e2e
def test_the_guard_stays_out_of_e2e_tests() -> None:
    from typer.testing import CliRunner

    from flows.cli import app

    r = CliRunner().invoke(app, ["--help"])
    assert r.exit_code == 0 and "generate" in r.output, r.output


_INNER_CONFTEST = """
import sys
sys.path[:0] = [{root!r}, {tests!r}]
exec(compile(open({conftest!r}).read(), {conftest!r}, "exec"))
"""

_INNER_TESTS = """
import pytest
from conftest import tiny_config
from flows.pipeline import execute


@pytest.fixture(scope="module")
def planned(tmp_path_factory):
    return execute(tmp_path_factory.mktemp("s"), tiny_config(), until="plan")


def test_unmarked_over_a_module_scoped_scene(planned):
    pass


@pytest.mark.e2e
def test_marked(tmp_path):
    assert [r.status for r in execute(tmp_path, tiny_config(), until="plan")] == ["ran"]
"""


@pytest.mark.e2e
def test_a_module_scoped_fixture_that_runs_a_pipeline_fails_the_unmarked_test_using_it(tmp_path: Path) -> None:
    """The whole hook in a pytest session of its own: the fixture is set up inside the unmarked test, so it errors
    there naming the marker, while the marked test runs its pipeline."""
    tests = Path(__file__).resolve().parent
    inner = _INNER_CONFTEST.format(root=str(tests.parent), tests=str(tests), conftest=str(tests / "conftest.py"))
    (tmp_path / "conftest.py").write_text(inner)
    (tmp_path / "test_inner.py").write_text(_INNER_TESTS)
    r = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-W", "ignore", str(tmp_path)],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=300,
    )
    assert "1 passed, 1 error" in r.stdout, r.stdout[-3000:]
    assert "test_unmarked_over_a_module_scoped_scene runs a pipeline (flows.pipeline) but is not marked e2e" in r.stdout

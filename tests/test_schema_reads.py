"""Store attributes are read through the schema only: no module of the pipeline, its flows or its benchmarks reads a
group's attributes by string (`store.meta` returns them as the group's model), and attributes that do not fit their
model are DamagedData in one line, never a traceback. (Every group's one declared writer: test_schema_writers.py.)

Ground truth: the source files themselves, code samples written here, and stores whose attributes the test writes
through zarr directly."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest
import zarr
from conftest import run_cli, tree_digest

from wonderverse.errors import WonderError
from wonderverse.schema import PLAN, SFM
from wonderverse.store import DamagedData, SceneStore

ROOT = Path(__file__).resolve().parents[1]
CHECKED = ("tasks", "flows", "benchmarks", "wonderverse", "scripts")
# the schema declares the attributes; the store keeps its bookkeeping beside them and validates what it reads
EXEMPT = ("wonderverse/schema/", "wonderverse/store.py")
# reading a zarr group's attributes as a mapping (writing them, `.attrs.update(...)`, is a commit's business)
MAPPING_READS = {"get", "items", "keys", "values", "__getitem__", "__contains__"}


def string_reads(source: str) -> list[tuple[int, str]]:
    """(line, what) of every read of store attributes by string in `source`: `x.attrs(...)` (the store's raw
    attributes), `x.attrs[...]`, `x.attrs.get(...)` and the other mapping reads, `dict(x.attrs)`, `k in x.attrs`,
    and any use of `root.attrs`."""
    found = []

    def is_attrs(node: ast.AST) -> bool:
        return isinstance(node, ast.Attribute) and node.attr == "attrs"

    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Call) and is_attrs(node.func):
            found.append((node.lineno, "x.attrs(...)"))
        elif isinstance(node, ast.Subscript) and is_attrs(node.value) and isinstance(node.ctx, ast.Load):
            found.append((node.lineno, "x.attrs[...]"))
        elif (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Attribute)
            and is_attrs(node.func.value)
            and node.func.attr in MAPPING_READS
        ):
            found.append((node.lineno, f"x.attrs.{node.func.attr}(...)"))
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "dict":
            if any(is_attrs(a) for a in node.args):
                found.append((node.lineno, "dict(x.attrs)"))
        elif isinstance(node, ast.Compare) and any(isinstance(op, ast.In | ast.NotIn) for op in node.ops):
            if any(is_attrs(c) for c in node.comparators):
                found.append((node.lineno, "k in x.attrs"))
        elif is_attrs(node):
            inner = node.value  # type: ignore[attr-defined]
            named_root = isinstance(inner, ast.Name) and inner.id == "root"
            if named_root or (isinstance(inner, ast.Attribute) and inner.attr == "root"):
                found.append((node.lineno, "root.attrs"))
    return sorted(set(found))


def modules() -> list[Path]:
    files = [p for folder in CHECKED for p in sorted((ROOT / folder).rglob("*.py"))]
    return [p for p in files if not p.relative_to(ROOT).as_posix().startswith(EXEMPT)]


def test_no_module_reads_store_attributes_by_string() -> None:
    checked = modules()
    assert len(checked) > 100  # the folders were found: tasks, flows, benchmarks, the library and scripts
    offending = {
        p.relative_to(ROOT).as_posix(): reads for p in checked if (reads := string_reads(p.read_text(encoding="utf-8")))
    }
    assert offending == {}, "read them with store.meta(GROUP.path) and the model's fields"


@pytest.mark.parametrize(
    "code, what",
    [
        ("seed = store.attrs(ATTEMPT.at(seg='s000', attempt=0)).get('seed')", "x.attrs(...)"),
        ("segs = store.group(SFM.path).attrs['segments']", "x.attrs[...]"),
        ("k = group.attrs.get('cache_key')", "x.attrs.get(...)"),
        ("spec = store.root.attrs.get('spec')", "root.attrs"),
        ("everything = dict(root.attrs)", "root.attrs"),
        ("a = dict(g.attrs)", "dict(x.attrs)"),
        ("done = 'complete' in g.attrs", "k in x.attrs"),
        ("for k, v in g.attrs.items(): pass", "x.attrs.items(...)"),
    ],
)
def test_the_check_finds_each_kind_of_string_read(code: str, what: str) -> None:
    assert what in [w for _, w in string_reads(code)]


def test_the_check_leaves_writes_and_typed_reads_alone() -> None:
    code = (
        "group.attrs.update(attrs_json(at, {'seed': 1}))\n"
        "g.attrs['complete'] = True\n"
        "segs = store.meta(SFM.path).segments\n"
        "attrs |= solved.attrs\n"  # a library record's own field, not a group's attributes
        "from wonderverse.schema.attrs import SfmAttrs\n"
    )
    assert string_reads(code) == []


def _committed_with(scene: Path, group: str, attrs: dict) -> None:
    """A group marked complete with `attrs`, written past the store's validation (as another program might)."""
    g = zarr.open_group(str(scene / "scene.zarr"), path=group, mode="a")
    g.attrs.update({**attrs, "cache_key": "0" * 64, "complete": True})


def test_attributes_that_do_not_fit_their_model_read_as_damaged_data_in_one_line(tmp_path: Path) -> None:
    scene = tmp_path / "scene"
    SceneStore.open_or_create(scene, spec={"prompt": "a lighthouse"})
    _committed_with(scene, SFM.path, {"segments": "s000", "source": "the moon"})
    _committed_with(scene, PLAN.path, {"moves": ["left 30"]})  # no plan
    store = SceneStore.open(scene)
    for group in (SFM.path, PLAN.path):
        with pytest.raises(DamagedData) as err:
            store.meta(group)
        message = str(err.value)
        assert err.value.group == group and message.startswith(f"damaged scene data in {group}: ")
        assert "do not fit the schema" in message and "\n" not in message and len(message) < 500
        assert isinstance(err.value, WonderError)  # the CLI prints it as one `error:` line
    # attributes that fit, keys of another version ignored, read as the model
    _committed_with(scene, SFM.path, {"segments": ["s000"], "source": "sfm", "written_by_a_later_version": 1})
    assert SceneStore.open(scene).meta(SFM.path).segments == ["s000"]


@pytest.mark.e2e
def test_inspect_of_attributes_that_do_not_fit_is_one_error_line_and_touches_nothing(tmp_path: Path) -> None:
    scene = tmp_path / "scene"
    SceneStore.open_or_create(scene, spec={"prompt": "a lighthouse"})
    _committed_with(scene, SFM.path, {"segments": "s000", "k_source": "given"})
    before = tree_digest(scene)
    r = run_cli("inspect", str(scene))
    errors = [line for line in r.stderr.splitlines() if line.startswith("error")]
    assert r.returncode == 2 and len(errors) == 1 and "Traceback" not in r.stderr, r.stderr
    assert errors[0].startswith(f"error: damaged scene data in {SFM.path}: its attributes do not fit the schema")
    assert tree_digest(scene) == before

"""Each step hashes exactly what it reads: for every setting of the configuration, changing it changes the key of
the steps whose params model holds it and of every step downstream of them, and no other key; the execution
settings change no key; and every field of every step's params model is reached by some setting (no step
hashes a constant, no setting is dead). A step gets nothing but its params model (`tasks.base`), so what it
reads is what it hashes by construction; this test checks the other half, enumerating every field."""

from __future__ import annotations

import types
import typing
from typing import Any, Literal, get_args, get_origin

from pydantic import BaseModel, ValidationError

from tasks import STEPS, step_keys
from tasks.segment_geometry import NORMAL_FIELDS
from wonderverse.config import RunConfig, build_config
from wonderverse.video import source_takes_guide

NOT_READ_BY_STEPS = {"preset"}  # the preset's name labels the run; its values are what the steps read
GUIDED_ONLY = ("steps", "generate_segments")  # settings that only a guided flow reads (an unguided one's keys
# never depend on them)
# A guided flow's generate_segments hashes the priors' depth settings with the normal prior's held at their defaults
# (`tasks.segment_geometry.depth_settings`: a new normal prior regenerates no extension): constants on purpose.
PINNED = {("generate_segments", f"depth.models.{name}") for name in NORMAL_FIELDS}


def leaves(model: BaseModel, prefix: tuple[str, ...] = ()) -> list[tuple[tuple[str, ...], Any, Any]]:
    """(path, value, annotation) of every leaf field of a model, nested models walked."""
    out = []
    for name, info in type(model).model_fields.items():
        value = getattr(model, name)
        if isinstance(value, BaseModel):
            out += leaves(value, (*prefix, name))
        else:
            out.append(((*prefix, name), value, info.annotation))
    return out


def _literals(annotation: Any) -> list[Any]:
    if get_origin(annotation) is Literal:
        return list(get_args(annotation))
    if get_origin(annotation) in (typing.Union, types.UnionType):
        return [v for a in get_args(annotation) for v in _literals(a)]
    return []


def candidates(value: Any, annotation: Any) -> list[Any]:
    """Other values to try for a leaf, most likely valid first."""
    options = [v for v in _literals(annotation) if v != value]
    if isinstance(value, bool):
        return [not value]
    if isinstance(value, int):
        return [*options, value + 1, value - 1, value * 2, 1, 2]
    if isinstance(value, float):
        nudges = [1.5, 0.5, 1.1, 0.9, 1 + 1e-4, 1 - 1e-4]
        return [*options, *(value * f for f in nudges), value + 0.1, value - 0.1, value + 1, 0.5, 0.01]
    if isinstance(value, str):
        numbers = [1.5] if float in get_args(annotation) else []  # a setting of "auto" or a number
        return [*options, *numbers, "up 0, right 10, forward 1", f"{value}x", "x", "auto"]
    if isinstance(value, tuple | list):
        out: list[Any] = [type(value)(reversed(value))]
        if value and all(isinstance(v, int | float) and not isinstance(v, bool) for v in value):
            for f in (0.9, 1.1):
                out += [
                    type(value)(v * f for v in value),
                    type(value)(v * (f if i else 1) for i, v in enumerate(value)),
                ]
        more = [*value, value[0]] if value else ["x"]
        return [*out, type(value)(more), type(value)(value[:-1])] + ([["left"]] if not value else [])
    if value is None:
        guesses: list[Any] = []
        for a in get_args(annotation):
            if get_origin(a) is tuple:
                guesses.append(tuple(0.5 for _ in get_args(a)))
            by_type = {str: ["x", "127.0.0.1:8786"], float: [1.0, 0.5, 60.0], int: [1, 2, 518, 1000, 100_000]}
            guesses += by_type.get(a, [])
        return [*options, *guesses]
    return options


def _with(data: dict, path: tuple[str, ...], value: Any) -> dict:
    if len(path) == 1:
        return {**data, path[0]: value}
    # a block left unwritten at its default (`loss.robust`, to keep the keys made before it) is created
    return {**data, path[0]: _with(data.get(path[0], {}), path[1:], value)}


def _tags(cfg: BaseModel, block: tuple[str, ...]) -> list[Any]:
    """The `kind`s a tagged block (a union of models told apart by `kind`: `steps.splats.train.strategy`) can be."""
    parent: Any = cfg
    for name in block[:-1]:
        parent = getattr(parent, name)
    members = get_args(type(parent).model_fields[block[-1]].annotation)
    models = [m for m in members if isinstance(m, type) and issubclass(m, BaseModel) and "kind" in m.model_fields]
    return [t for m in models for t in _literals(m.model_fields["kind"].annotation)]


def perturbed(cfg: RunConfig, path: tuple[str, ...], value: Any, annotation: Any) -> RunConfig | None:
    data = cfg.model_dump(mode="json")
    if path[-1] == "kind":  # another kind is another model, with its own defaults
        for tag in _tags(cfg, path[:-1]):
            if tag == value:
                continue
            try:
                return RunConfig.model_validate(_with(data, path[:-1], {"kind": tag}))
            except ValidationError:
                continue
    if path[-2:] == ("video", "backend"):  # another backend comes with its own options
        data = _with(data, (*path[:-1], "options"), {})
    for v in candidates(value, annotation):
        if v == value:
            continue
        try:
            return RunConfig.model_validate(_with(data, path, v))
        except (ValidationError, ValueError, TypeError):
            continue
    return None


def _jsonable(model: BaseModel) -> dict[str, Any]:
    return {".".join(p): v for p, v, _ in leaves(model)}


def downstream(names: set[str]) -> set[str]:
    """`names` and every step that depends on one of them, transitively."""
    out = set(names)
    for s in STEPS:  # dependency order: one pass suffices
        if out & set(s.depends):
            out.add(s.name)
    return out


BASES = {
    "procedural": lambda: build_config("a small house decorated for Christmas", preset="preview"),
    # a guided flow: generate_segments also reads the check's and the depth settings, and steps.generate_segments
    "guided": lambda: build_config(
        "a small house decorated for Christmas",
        preset="preview",
        overrides={"scene": {"video": {"options": {"accept_guide": True}}}},
    ),
    "files": lambda: build_config(
        "my clips",
        preset="preview",
        overrides={
            "scene": {"video": {"backend": "files", "clips": ["/clips/a.mp4", "/clips/b.mp4"]}},
            "steps": {"priors": {"models": {"depth_backend": "depth_anything", "depth_model": "/models/da"}}},
        },
    ),
    "diffusers": lambda: build_config(
        "a canyon",
        preset="preview",
        overrides={
            "scene": {"video": {"backend": "diffusers", "frames_per_segment": 17, "width": 320, "height": 208}},
            "steps": {"priors": {"models": {"depth_backend": "depth_anything", "depth_model": "/models/da"}}},
        },
    ),
}


def check_base(cfg: RunConfig) -> tuple[int, set[str], list[str], dict[str, set[str]]]:
    """(pairs checked, settings changed, problems, params fields reached per step) for one base config."""
    keys = step_keys(STEPS, cfg)
    params = {s.name: _jsonable(s.params(cfg)) for s in STEPS}
    reached: dict[str, set[str]] = {s.name: set() for s in STEPS}
    pairs, done, wrong = 0, set(), []
    for path, value, annotation in leaves(cfg):
        name = ".".join(path)
        other = perturbed(cfg, path, value, annotation) if path[0] not in NOT_READ_BY_STEPS else None
        if other is None:
            continue
        done.add(name)
        new_keys = step_keys(STEPS, other)
        changed = {s for s in keys if new_keys[s] != keys[s]}
        if path[0] == "execution":
            if changed:
                wrong.append(f"{name} (execution) changed the keys of {sorted(changed)}")
            continue
        reads = set()
        for s in STEPS:
            new = _jsonable(s.params(other))
            fields = {f for f in params[s.name].keys() | new.keys() if params[s.name].get(f) != new.get(f)}
            if fields:
                reads.add(s.name)
                reached[s.name] |= fields
        pairs += len(reads)
        if not reads and path[:2] == GUIDED_ONLY and not source_takes_guide(cfg.scene.video_source):
            continue  # read by guided flows only (the guided base checks them)
        if not reads:
            wrong.append(f"{name} is read by no step (a dead setting)")
        elif changed != downstream(reads):
            wrong.append(f"{name}: keys changed {sorted(changed)}, expected {sorted(downstream(reads))}")
    return pairs, done, wrong, reached


def test_every_setting_changes_exactly_the_keys_of_the_steps_that_read_it() -> None:
    """Over four base configs (procedural, guided procedural, user clips, a diffusion model), so every backend's
    options and the guided flow's settings count."""
    total, done, every = 0, set(), set()
    reached: dict[str, set[str]] = {s.name: set() for s in STEPS}
    fields: dict[str, set[str]] = {s.name: set() for s in STEPS}
    for backend, make in BASES.items():
        cfg = make()
        pairs, changed, wrong, seen = check_base(cfg)
        assert not wrong, f"{backend}:\n" + "\n".join(wrong)
        total += pairs
        done |= changed
        every |= {".".join(p) for p, _, _ in leaves(cfg) if p[0] not in NOT_READ_BY_STEPS}
        for s in STEPS:
            reached[s.name] |= seen[s.name]
            fields[s.name] |= set(_jsonable(s.params(cfg)))
    assert not every - done, f"settings with no valid other value in any base: {sorted(every - done)}"
    for s in STEPS:  # every field of every step's params is reached by some setting
        unreached = {f for f in fields[s.name] - reached[s.name] if (s.name, ".".join(f.split(".")[:3])) not in PINNED}
        assert not unreached, f"{s.name}: fields no setting changes: {unreached}"
    print(f"{total} (step, setting) pairs checked over {len(every)} settings")
    assert total >= len(every)


def test_every_output_setting_changes_exactly_the_keys_of_the_products_that_read_it() -> None:
    """The outputs step keys each product by the settings it reads (`tasks.outputs.PRODUCTS`): changing a setting
    re-makes the products that read it and those that come after them, nothing else; every product reads some
    setting or an earlier product's record; a new video_fps re-makes the camera paths and the videos alone."""
    from tasks.outputs import PRODUCTS, params, product_keys

    cfg = build_config("a small house decorated for Christmas", preset="preview")
    p = params(cfg)
    keys = product_keys(p, "splats-key")
    assert product_keys(p, "other-splats") != keys and all(
        a != b for a, b in zip(product_keys(p, "other-splats").values(), keys.values(), strict=True)
    )  # every product follows the splats
    by_name = {product.name: product for product in PRODUCTS}
    checked = 0
    for path, value, annotation in leaves(cfg.steps.outputs):
        other = perturbed(cfg, ("steps", "outputs", *path), value, annotation)
        if other is None:
            continue
        new_p = params(other)
        reads = {n for n, product in by_name.items() if product.reads(new_p) != product.reads(p)}
        expected = set(reads)
        for product in PRODUCTS:  # in order: what comes after a re-made product is re-made
            if set(product.after) & expected:
                expected.add(product.name)
        changed = {n for n, k in product_keys(new_p, "splats-key").items() if k != keys[n]}
        assert changed == expected, f"{'.'.join(path)}: changed {sorted(changed)}, expected {sorted(expected)}"
        assert reads, f"{'.'.join(path)} is read by no product"
        checked += 1
    assert checked >= 30
    fps = perturbed(cfg, ("steps", "outputs", "video_fps"), cfg.steps.outputs.video_fps, float)
    assert fps is not None
    changed = {n for n, k in product_keys(params(fps), "splats-key").items() if k != keys[n]}
    assert changed == {"camera_paths", "videos"}

"""Reading a config or scene spec YAML file, within limits and by type: standard library and PyYAML only, so that a
command refuses a bad file before pydantic, numpy or zarr load.

A config file holds settings, not data: it must be a regular file (a pipe would block the command forever, a device
never ends), at most MAX_CONFIG_BYTES long, UTF-8 text, YAML with no key given twice in one mapping (the second would
silently win), and its aliases may expand to at most MAX_CONFIG_VALUES values (a YAML alias bomb expands
exponentially).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import yaml

from wonderverse.errors import ConfigError, WonderError, shown
from wonderverse.folders import read_regular

MAX_CONFIG_BYTES = 1_000_000
MAX_CONFIG_VALUES = 100_000
_MERGE = "tag:yaml.org,2002:merge"


class _StrictLoader(yaml.SafeLoader):
    """PyYAML's safe loader, refusing a key given twice in one mapping (PyYAML keeps the last without a word)."""


def _mapping(loader: _StrictLoader, node: yaml.MappingNode) -> Iterator[dict[Any, Any]]:
    """PyYAML's mapping constructor (a generator: recursive aliases still resolve), refusing a key given twice."""
    data: dict[Any, Any] = {}
    yield data
    seen: dict[Any, yaml.Mark] = {}
    for key_node, _ in node.value:
        if key_node.tag == _MERGE:  # `<<: *base` merges a mapping whose keys the explicit ones override: allowed
            continue
        key = loader.construct_object(key_node, deep=True)
        try:
            first = seen.get(key)
        except TypeError:  # an unhashable key: the constructor below says so
            continue
        if first is not None:
            raise yaml.constructor.ConstructorError(
                None, None, f"duplicate key {shown(key)} (first given at line {first.line + 1})", key_node.start_mark
            )
        seen[key] = key_node.start_mark
    data.update(loader.construct_mapping(node))


_StrictLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _mapping)


def read_yaml(path: Path) -> dict[str, Any]:
    """A YAML mapping from `path`; a missing, unreadable, non-regular (a pipe, a device), oversized, non-UTF-8,
    malformed or non-mapping file, one that gives a key twice, or one whose aliases expand beyond MAX_CONFIG_VALUES
    values, is a ConfigError."""
    try:
        raw = read_regular(path, "config file", MAX_CONFIG_BYTES)  # bounded: a huge file is refused, not read
    except WonderError as e:
        raise ConfigError(str(e)) from None
    if len(raw) > MAX_CONFIG_BYTES:
        raise ConfigError(f"config file {path} is larger than {MAX_CONFIG_BYTES // 1_000_000} MB: is it a config?")
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise ConfigError(
            f"config file {path} is not UTF-8 text (byte 0x{raw[e.start]:02x} at offset {e.start}); "
            "a config is YAML saved as UTF-8"
        ) from None
    if "\x00" in text:
        raise ConfigError(f"config file {path} is binary (it holds NUL bytes), not YAML text")
    try:
        data = yaml.load(text, Loader=_StrictLoader)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = getattr(e, "problem", None) or str(e).splitlines()[0]
        raise ConfigError(f"malformed YAML in {path}{where}: {problem}") from None
    except RecursionError:
        raise ConfigError(f"malformed YAML in {path}: nested too deeply") from None
    except ValueError as e:  # e.g. an integer beyond Python's digit limit
        raise ConfigError(f"malformed YAML in {path}: {shown(str(e), 120)}") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path} must hold a mapping of settings, not a {type(data).__name__}")
    _refuse_expansion(data, path)
    return data


def _refuse_expansion(data: Any, path: Path) -> None:
    """ConfigError when `data`, its aliases expanded, holds more than MAX_CONFIG_VALUES values (YAML aliases are
    shared references: a small file can stand for billions of values, or for a cycle)."""
    stack, count = [data], 0
    while stack:
        x = stack.pop()
        count += 1
        if count > MAX_CONFIG_VALUES:
            raise ConfigError(
                f"config file {path} expands to more than {MAX_CONFIG_VALUES} values through its aliases "
                "(&anchor / *alias); a config needs far fewer"
            )
        if isinstance(x, dict):
            stack += [*x.keys(), *x.values()]
        elif isinstance(x, list | tuple | set):
            stack += list(x)

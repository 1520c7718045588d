"""A training state as plain bytes plus JSON, and back, without pickle.

`pack(state) -> (blob, layout)`: every tensor of the nested state (torch or numpy) and every list of floats (the
loss curves) is laid end to end in `blob` (little-endian, in order); `layout` is JSON (ints, floats, strings,
lists, dicts) holding the rest of the tree with references to those tensors. `unpack(blob, layout, device)` gives
the same tree back (same types: torch or numpy, tuples, int dict keys) and raises CheckpointError on anything
that does not fit: an unknown tag or dtype, a tensor that is missing, extra or used twice, sizes that do not add
up to the blob. Nothing is ever unpickled, so a checkpoint from an untrusted scene folder can at worst be refused.

`check_train_state` checks that an unpacked state is what `trainer.train`'s `checkpoint_cb` gives (its keys,
parameter shapes, optimiser moments, RNG states, view order), so a crafted one is refused before training uses it.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping
from typing import Any

import numpy as np

FORMAT = 1
_MAX_DEPTH = 32  # a training state nests 5 deep; a crafted layout nests deeper only to exhaust the stack
_MAX_RANK = 8
_DTYPES = ("bool", "uint8", "int8", "int16", "int32", "int64", "float16", "float32", "float64", "bfloat16")
_KINDS = ("torch", "numpy", "floats")  # a torch tensor, a numpy array, a list of Python floats
_NON_FINITE = {"nan": math.nan, "inf": math.inf, "-inf": -math.inf}
_TAGS = ("list", "tuple", "dict", "tensor", "float")


class CheckpointError(ValueError):
    """The checkpoint's bytes and layout do not make a state of the expected form (one line, says what)."""


def pack(state: Any) -> tuple[bytes, dict[str, Any]]:
    """(blob, layout) of a nested state of dicts (str or int keys), lists, tuples, torch tensors, numpy arrays,
    None, bools, ints, floats and strings. TypeError for anything else (a programming error, not data)."""
    parts: list[bytes] = []
    entries: list[dict[str, Any]] = []

    def add(arr: np.ndarray, dtype: str, kind: str, device: str) -> dict[str, int]:
        if arr.dtype.byteorder == ">":
            arr = arr.astype(arr.dtype.newbyteorder("<"))
        parts.append(arr.tobytes(order="C"))  # (np.ascontiguousarray would make a 0-d array 1-d)
        entries.append({"dtype": dtype, "shape": list(arr.shape), "kind": kind, "device": device})
        return {"tensor": len(entries) - 1}

    def enc(obj: Any) -> Any:
        import torch

        if obj is None or isinstance(obj, bool | str):
            return obj
        if isinstance(obj, int):
            return int(obj)
        if isinstance(obj, float):
            return float(obj) if math.isfinite(obj) else {"float": repr(float(obj))}
        if isinstance(obj, np.generic):
            return enc(obj.item())
        if isinstance(obj, torch.Tensor):
            t = obj.detach()
            device = "cpu" if t.device.type == "cpu" else "accel"
            t = t.cpu().contiguous()
            if t.dtype == torch.bfloat16:
                return add(t.view(torch.int16).numpy(), "bfloat16", "torch", device)
            return add(t.numpy(), _dtype_name(t.numpy().dtype), "torch", device)
        if isinstance(obj, np.ndarray):
            return add(obj, _dtype_name(obj.dtype), "numpy", "cpu")
        if isinstance(obj, list):
            if obj and all(type(x) is float for x in obj):
                return add(np.asarray(obj, np.float64), "float64", "floats", "cpu")
            return {"list": [enc(x) for x in obj]}
        if isinstance(obj, tuple):
            return {"tuple": [enc(x) for x in obj]}
        if isinstance(obj, Mapping):
            items = []
            for k, v in obj.items():
                if isinstance(k, bool) or not isinstance(k, str | int):
                    raise TypeError(f"checkpoint: dict key {k!r} is neither str nor int")
                items.append([k if isinstance(k, str) else int(k), enc(v)])
            return {"dict": items}
        raise TypeError(f"checkpoint: cannot store a {type(obj).__name__}")

    tree = enc(state)
    return b"".join(parts), {"format": FORMAT, "tensors": entries, "tree": tree}


def blob_size(layout: Any) -> int:
    """The number of bytes the layout's tensors take; CheckpointError when the layout is malformed."""
    return sum(n for _, n in _entries(layout))


def unpack(blob: bytes, layout: Any, device: Any = "cpu") -> Any:
    """The state `pack` was given. Torch tensors that lived on an accelerator go to `device`; the others (RNG
    states, numpy arrays) stay on the CPU. CheckpointError when blob and layout do not fit together."""
    import torch

    entries = _entries(layout)
    offsets = [0, *itertools.accumulate(n for _, n in entries)]
    if offsets[-1] != len(blob):
        raise CheckpointError(f"the layout's tensors take {offsets[-1]} bytes, the blob holds {len(blob)}")
    used = [False] * len(entries)

    def tensor(i: Any) -> Any:
        if isinstance(i, bool) or not isinstance(i, int) or not 0 <= i < len(entries):
            raise CheckpointError(f"reference to tensor {i!r}, the layout has {len(entries)}")
        if used[i]:
            raise CheckpointError(f"tensor {i} is referenced twice")
        used[i] = True
        entry, nbytes = entries[i]
        np_dtype = np.dtype("<i2" if entry["dtype"] == "bfloat16" else entry["dtype"]).newbyteorder("<")
        arr = np.frombuffer(blob, np_dtype, nbytes // np_dtype.itemsize, offsets[i]).reshape(entry["shape"])
        arr = arr.astype(arr.dtype.newbyteorder("="))  # a native, writable, aligned copy
        if entry["kind"] == "floats":
            return arr.tolist()
        if entry["kind"] == "numpy":
            return arr
        t = torch.from_numpy(arr)
        if entry["dtype"] == "bfloat16":
            t = t.view(torch.bfloat16)
        return t.to(device) if entry["device"] == "accel" else t

    def dec(obj: Any, depth: int) -> Any:
        if depth > _MAX_DEPTH:
            raise CheckpointError(f"the layout nests deeper than {_MAX_DEPTH}")
        if obj is None or isinstance(obj, bool | int | str):
            return obj
        if isinstance(obj, float):
            return obj
        if not isinstance(obj, dict) or len(obj) != 1 or next(iter(obj)) not in _TAGS:
            raise CheckpointError(f"unknown entry in the layout: {_short(obj)}")
        ((tag, value),) = obj.items()
        if tag == "tensor":
            return tensor(value)
        if tag == "float":
            if value not in _NON_FINITE:
                raise CheckpointError(f"unknown float {_short(value)}")
            return _NON_FINITE[value]
        if not isinstance(value, list):
            raise CheckpointError(f"{tag} entry holds a {type(value).__name__}, not a list")
        if tag == "list":
            return [dec(x, depth + 1) for x in value]
        if tag == "tuple":
            return tuple(dec(x, depth + 1) for x in value)
        out: dict[Any, Any] = {}
        for item in value:
            if not (isinstance(item, list) and len(item) == 2) or isinstance(item[0], bool):
                raise CheckpointError(f"dict item {_short(item)} is not a [key, value] pair")
            if not isinstance(item[0], str | int) or item[0] in out:
                raise CheckpointError(f"dict key {_short(item[0])} is not a new str or int")
            out[item[0]] = dec(item[1], depth + 1)
        return out

    state = dec(layout["tree"], 0)
    if not all(used):
        raise CheckpointError(f"tensor {used.index(False)} of the layout is never referenced")
    return state


def _entries(layout: Any) -> list[tuple[dict[str, Any], int]]:
    """The layout's tensor entries with their sizes in bytes, each checked."""
    if not isinstance(layout, dict) or set(layout) != {"format", "tensors", "tree"}:
        raise CheckpointError("the layout is not {format, tensors, tree}")
    if layout["format"] != FORMAT:
        raise CheckpointError(f"layout format {_short(layout['format'])}, this version reads {FORMAT}")
    if not isinstance(layout["tensors"], list):
        raise CheckpointError("the layout's tensors are not a list")
    out = []
    for i, e in enumerate(layout["tensors"]):
        if not isinstance(e, dict) or set(e) != {"dtype", "shape", "kind", "device"}:
            raise CheckpointError(f"tensor {i}: not {{dtype, shape, kind, device}}")
        shape = e["shape"]
        if (
            e["dtype"] not in _DTYPES
            or e["kind"] not in _KINDS
            or e["device"] not in ("cpu", "accel")
            or not isinstance(shape, list)
            or len(shape) > _MAX_RANK
            or not all(isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in shape)
            or (e["kind"] == "floats" and (e["dtype"] != "float64" or len(shape) != 1))
            or (e["kind"] != "torch" and (e["device"] != "cpu" or e["dtype"] == "bfloat16"))
        ):
            raise CheckpointError(f"tensor {i}: unsupported entry {_short(e)}")
        itemsize = 2 if e["dtype"] == "bfloat16" else np.dtype(e["dtype"]).itemsize
        out.append((e, math.prod(shape) * itemsize))
    return out


def _dtype_name(dtype: np.dtype) -> str:
    name = np.dtype(dtype).name
    if name not in _DTYPES:
        raise TypeError(f"checkpoint: cannot store dtype {name}")
    return name


def _short(obj: Any) -> str:
    text = repr(obj)
    return text if len(text) <= 60 else text[:57] + "..."


# -- the trainer's state ------------------------------------------------------------------------------------

TRAIN_STATE_KEYS = frozenset(
    {
        "step",
        "scene_scale",
        "params",
        "optimizer",
        "background",
        "bg_optimizer",
        "strategy_state",
        "curves",
        "rng_views",
        "rng_torch",
        "order",
    }
)


def check_train_state(state: Any, n_views: int, sh_rest: int | None = None) -> None:
    """CheckpointError unless `state` has the form of `trainer.train`'s checkpoint state for `n_views` views
    (and `sh_rest` higher-order SH coefficients per Gaussian, when given): exactly its keys, float32 parameters
    of one Gaussian count with moments of their shapes, CPU uint8 RNG states of torch's size, view indices in
    range."""
    import torch

    from wonderverse.splats.model import GaussianModel

    if not isinstance(state, dict) or set(state) != TRAIN_STATE_KEYS:
        keys = sorted(map(str, state)) if isinstance(state, dict) else type(state).__name__
        raise CheckpointError(f"the state's keys are {keys}, not the trainer's")
    step = state["step"]
    if isinstance(step, bool) or not isinstance(step, int) or step < 0:
        raise CheckpointError(f"step {_short(step)}")
    if isinstance(state["scene_scale"], bool) or not isinstance(state["scene_scale"], int | float):
        raise CheckpointError(f"scene_scale {_short(state['scene_scale'])}")
    params = state["params"]
    if not isinstance(params, dict) or set(params) != set(GaussianModel.PARAM_NAMES):
        raise CheckpointError("the parameters are not the model's")
    n = params["means"].shape[0] if isinstance(params["means"], np.ndarray) else -1
    shapes = {
        "means": (n, 3),
        "quats": (n, 4),
        "log_scales": (n, 3),
        "logit_opacities": (n,),
        "sh0": (n, 1, 3),
        "shN": (n, sh_rest, 3),
    }
    for name, want in shapes.items():
        a = params[name]
        ok = isinstance(a, np.ndarray) and a.dtype == np.float32 and a.ndim == len(want)
        if not ok or any(w is not None and w != s for w, s in zip(want, a.shape, strict=True)):
            raise CheckpointError(f"parameter {name}: not float32 of shape {want}")
    background = state["background"]
    is_sky = isinstance(background, np.ndarray) and background.dtype == np.float32
    shape = background.shape if is_sky else ()
    if not (shape == (3,) or (len(shape) == 3 and shape[1] == 2 * shape[0] > 0 and shape[2] == 3)):
        raise CheckpointError("the background is neither 3 float32 nor a float32 (R, 2R, 3) sky map")
    _check_adam(state["optimizer"], {k: v.shape for k, v in params.items()}, "optimizer")
    _check_adam(state["bg_optimizer"], {"background": shape}, "bg_optimizer")
    strategy = state["strategy_state"]
    if not isinstance(strategy, dict) or not all(isinstance(k, str) for k in strategy):
        raise CheckpointError("the strategy state is not a dict of names")
    for k, v in strategy.items():
        if torch.is_tensor(v) and tuple(v.shape) != (n,):
            raise CheckpointError(f"strategy state {k}: shape {tuple(v.shape)}, not ({n},)")
    curves = state["curves"]
    if not isinstance(curves, dict) or not all(
        isinstance(k, str) and isinstance(v, list) and all(type(x) is float for x in v) for k, v in curves.items()
    ):
        raise CheckpointError("the curves are not lists of floats by name")
    for name, want in (("rng_views", torch.Generator().get_state()), ("rng_torch", torch.get_rng_state())):
        r = state[name]
        if not (torch.is_tensor(r) and r.dtype == torch.uint8 and r.device.type == "cpu" and r.shape == want.shape):
            raise CheckpointError(f"{name} is not a CPU uint8 tensor of {tuple(want.shape)}")
    order = state["order"]
    if not isinstance(order, list) or not all(
        isinstance(i, int) and not isinstance(i, bool) and 0 <= i < n_views for i in order
    ):
        raise CheckpointError(f"the view order is not a list of view indices below {n_views}")


def _check_adam(sd: Any, shapes: Mapping[str, tuple[int, ...]], what: str) -> None:
    """An Adam state_dict whose parameter groups are named after `shapes` and whose moments have those shapes."""
    import torch

    if not isinstance(sd, dict) or set(sd) != {"state", "param_groups"}:
        raise CheckpointError(f"{what}: not an optimiser state")
    groups, per_param = sd["param_groups"], sd["state"]
    if not isinstance(groups, list) or not isinstance(per_param, dict):
        raise CheckpointError(f"{what}: not an optimiser state")
    names = [g.get("name") if isinstance(g, dict) else None for g in groups]
    if sorted(map(str, names)) != sorted(shapes):
        raise CheckpointError(f"{what}: parameter groups {names}, not {sorted(shapes)}")
    for g in groups:
        ids = g.get("params")
        if not (isinstance(ids, list) and len(ids) == 1 and isinstance(ids[0], int)):
            raise CheckpointError(f"{what}: group {g['name']} does not hold one parameter")
        moments = per_param.get(ids[0], {})
        if not isinstance(moments, dict):
            raise CheckpointError(f"{what}: state of {g['name']} is not a dict")
        for k, v in moments.items():
            want = () if k == "step" else tuple(shapes[g["name"]])
            if not (torch.is_tensor(v) and v.is_floating_point() and tuple(v.shape) == want):
                raise CheckpointError(f"{what}: {g['name']}.{k} is not a float tensor of shape {want}")
    if set(per_param) - {g["params"][0] for g in groups}:
        raise CheckpointError(f"{what}: state for parameters no group holds")

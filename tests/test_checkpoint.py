"""Splat training checkpoints are plain tensors and JSON: a resume from one stored in a scene gives exactly the
uninterrupted run, a pickle planted in a scene folder is never run, and a checkpoint that does not fit is
ignored with one warning (training starts over) instead of failing."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from tasks.splats_checkpoint import CHECKPOINT, load_checkpoint, save_checkpoint
from wonderverse.splats.checkpoint import CheckpointError, pack, unpack
from wonderverse.splats.model import init_from_points, normalization_from_cameras, voxel_downsample
from wonderverse.splats.params import DefaultStrategyParams, TrainParams
from wonderverse.splats.renderer import make_renderer
from wonderverse.splats.trainer import Views, normalize_views, train
from wonderverse.splats.views import torch_threads
from wonderverse.store import SceneStore, cache_key, write_array
from wonderverse.video.procedural import ProceduralVideo, demo_path

W, H, T = 48, 32, 6
RUN_KEY = "a" * 64
TRAIN = TrainParams(
    iterations=16,
    sh_degree=1,
    sh_degree_interval_iters=8,
    holdout_every=3,
    strategy=DefaultStrategyParams(refine_start_iter=3, refine_every=4, reset_every=10, grow_grad2d=1e-5),
    checkpoint_every_iters=8,
    sky_map_rows=4,  # the sky as a (4, 8, 3) map: the state's largest non-Gaussian tensor travels too
)


@pytest.fixture(autouse=True)
def one_thread():
    # two OpenMP threads on a shared 2-core machine spin-wait for each other; and gradients summed over another
    # number of threads may differ in their last bits, so every run here uses one
    with torch_threads(1):
        yield


@pytest.fixture(scope="module")
def scene() -> dict[str, Any]:
    video = ProceduralVideo("a small house decorated for Christmas", 0, W, H, 60.0, {"fault_probability": 0.0})
    path = demo_path(video.world.start_pose(), T, yaw_deg=12.0, forward_m=0.6)
    vid = video.generate("", path, 0, None)
    depth, K = vid.gt.depth, vid.K
    v, u = np.mgrid[0:H:2, 0:W:2]
    z = depth[0, v, u]
    ok = np.isfinite(z)
    xc = np.stack([(u + 0.5 - K[0, 2]) / K[0, 0] * z, (v + 0.5 - K[1, 2]) / K[1, 1] * z, z], -1)[ok]
    points, _ = voxel_downsample((xc - path[0, :3, 3]) @ path[0, :3, :3], None, 0.25)
    norm = normalization_from_cameras(path, points)
    views = Views(frames=vid.frames, w2c=path, K=K, prior_depth=depth, prior_normals=vid.gt.normals)
    return {"views": normalize_views(views, norm), "points": norm.apply(points)}


def _model(scene: dict[str, Any]):
    pts = scene["points"]
    return init_from_points(pts, np.full((len(pts), 3), 0.5), sh_degree=1, init_opacity=0.5)


@pytest.fixture(scope="module")
def uninterrupted(scene: dict[str, Any]) -> dict[str, Any]:
    """The uninterrupted run and its checkpoint states by step (as the trainer hands them over)."""
    saved: dict[int, dict] = {}
    with torch_threads(1):  # a module fixture starts before the autouse one
        model, curves, _ = train(
            _model(scene), scene["views"], TRAIN, make_renderer("torch"), checkpoint_cb=saved.__setitem__
        )
    assert sorted(saved) == [8, 16]
    return {"model": model, "curves": curves, "saved": saved}


def _load(store: SceneStore) -> dict[str, Any] | None:
    return load_checkpoint(store, RUN_KEY, "cpu", T, 3)


def assert_same_tree(a: Any, b: Any, where: str = "state") -> None:
    """Equal values of equal types (torch or numpy, tuple or list, int or str keys), NaN equal to NaN."""
    assert type(a) is type(b), f"{where}: {type(a).__name__} != {type(b).__name__}"
    if isinstance(a, dict):
        assert list(a) == list(b), where
        for k in a:
            assert_same_tree(a[k], b[k], f"{where}[{k!r}]")
    elif isinstance(a, list | tuple):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            assert_same_tree(x, y, f"{where}[{i}]")
    elif isinstance(a, torch.Tensor):
        assert a.dtype == b.dtype and a.shape == b.shape, where
        assert torch.equal(a.view(torch.uint8) if a.dtype == torch.bool else a, b) or (
            a.is_floating_point() and torch.equal(a.isnan(), b.isnan()) and torch.equal(a.nan_to_num(), b.nan_to_num())
        ), where
    elif isinstance(a, np.ndarray):
        assert a.dtype == b.dtype and a.shape == b.shape, where
        np.testing.assert_array_equal(a, b, err_msg=where)
    elif isinstance(a, float):
        assert a == b or (np.isnan(a) and np.isnan(b)), where
    else:
        assert a == b, where


# -- the format ---------------------------------------------------------------------------------------------

_floats = st.floats(allow_nan=True, allow_infinity=True, width=64)
_leaves = st.none() | st.booleans() | st.integers(-(2**62), 2**62) | _floats | st.text(max_size=8)
_dtypes = st.sampled_from(["float32", "float64", "float16", "int64", "int32", "uint8", "bool"])


@st.composite
def _arrays(draw: Any) -> Any:
    dtype = draw(_dtypes)
    shape = tuple(draw(st.lists(st.integers(0, 3), max_size=3)))
    arr = np.asarray(np.arange(int(np.prod(shape))).reshape(shape) * draw(st.sampled_from([1, -1]))).astype(dtype)
    return torch.from_numpy(arr) if draw(st.booleans()) else arr


_trees = st.recursive(
    _leaves | _arrays() | st.lists(_floats, min_size=1, max_size=4),
    lambda inner: (
        st.lists(inner, max_size=3)
        | st.lists(inner, max_size=3).map(tuple)
        | st.dictionaries(st.text(max_size=4) | st.integers(-5, 5), inner, max_size=3)
    ),
    max_leaves=12,
)


@settings(max_examples=60, deadline=None)
@given(_trees)
def test_pack_gives_back_the_same_tree(tree: Any) -> None:
    blob, layout = pack(tree)
    import json

    layout = json.loads(json.dumps(layout, allow_nan=False))  # plain JSON: what the store's attributes hold
    assert_same_tree(unpack(blob, layout), tree)


def test_pack_keeps_bfloat16_and_refuses_what_is_not_data() -> None:
    t = torch.tensor([1.5, -2.0, 3.25], dtype=torch.bfloat16)
    blob, layout = pack({"t": t})
    assert_same_tree(unpack(blob, layout), {"t": t})
    for bad in (object(), {1.5: 0}, np.array([1 + 2j]), {"f": lambda: 0}):
        with pytest.raises(TypeError):
            pack(bad)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda blob, lay: (blob[:-1], lay), "bytes, the blob holds"),
        (lambda blob, lay: (blob + b"\0", lay), "bytes, the blob holds"),
        (lambda blob, lay: (blob, {**lay, "format": 2}), "layout format"),
        (lambda blob, lay: (blob, {**lay, "extra": 1}), "not {format, tensors, tree}"),
        (lambda blob, lay: (blob, {**lay, "tree": {"pickle": "x"}}), "unknown entry"),
        (lambda blob, lay: (blob, {**lay, "tree": {"list": [{"tensor": 0}, {"tensor": 0}]}}), "referenced twice"),
        (lambda blob, lay: (blob, {**lay, "tree": {"tensor": 0}}), "never referenced"),
        (lambda blob, lay: (blob, {**lay, "tree": {"tensor": 9}}), "reference to tensor 9"),
        (lambda blob, lay: (blob, _entry(lay, dtype="object")), "unsupported entry"),
        (lambda blob, lay: (blob, _entry(lay, shape=[-1])), "unsupported entry"),
        (lambda blob, lay: (blob, _entry(lay, shape=[2, 1])), "bytes, the blob holds"),
        (lambda blob, lay: (blob, _entry(lay, device="cuda:7")), "unsupported entry"),
        (lambda blob, lay: (blob, {**lay, "tree": _nest(40)}), "nests deeper"),
    ],
)
def test_unpack_refuses_a_layout_that_does_not_fit(change: Any, message: str) -> None:
    blob, layout = pack({"a": torch.zeros(4), "b": np.ones(2, np.float64)})
    blob, layout = change(blob, layout)
    with pytest.raises(CheckpointError, match=message):
        unpack(blob, layout)


def _entry(layout: dict, **change: Any) -> dict:
    return {**layout, "tensors": [{**layout["tensors"][0], **change}, *layout["tensors"][1:]]}


def _nest(depth: int) -> Any:
    tree: Any = {"dict": [["a", {"tensor": 0}], ["b", {"tensor": 1}]]}
    for _ in range(depth):
        tree = {"list": [tree]}
    return tree


# -- resume through the store -------------------------------------------------------------------------------


def test_resume_from_a_stored_checkpoint_is_the_uninterrupted_run(
    tmp_path: Path, scene: dict[str, Any], uninterrupted: dict[str, Any], caplog: pytest.LogCaptureFixture
) -> None:
    store = SceneStore.open_or_create(tmp_path / "scene")
    save_checkpoint(store, RUN_KEY, 8, uninterrupted["saved"][8])
    assert store.cache_key_of(CHECKPOINT) is not None  # complete
    with caplog.at_level(logging.WARNING, logger="wonderverse.splats"):
        state = _load(store)
    assert [r.getMessage() for r in caplog.records] == ["resuming splat training from the checkpoint at step 8"]
    assert_same_tree(state, uninterrupted["saved"][8])
    # nothing in the scene folder is a pickle: no file starts with pickle's protocol marker
    files = [p for p in (tmp_path / "scene").rglob("*") if p.is_file()]
    assert files and not [p for p in files if p.read_bytes()[:1] == b"\x80"]

    resumed, curves, _ = train(_model(scene), scene["views"], TRAIN, make_renderer("torch"), resume_state=state)
    full = uninterrupted["model"]
    assert resumed.num_gaussians == full.num_gaussians
    for k, v in full.param_dict().items():
        np.testing.assert_array_equal(resumed.param_dict()[k].detach().numpy(), v.detach().numpy(), err_msg=k)
    assert curves["total"] == uninterrupted["curves"]["total"]


def test_a_checkpoint_for_another_run_is_not_read(tmp_path: Path, uninterrupted: dict[str, Any], caplog) -> None:
    store = SceneStore.open_or_create(tmp_path / "scene")
    save_checkpoint(store, "b" * 64, 8, uninterrupted["saved"][8])
    with caplog.at_level(logging.WARNING, logger="wonderverse.splats"):
        assert _load(store) is None
    assert not caplog.records  # another run's checkpoint: not ours, nothing to say


def _tamper_state(store: SceneStore, change: Any) -> None:
    a, key = store.meta(CHECKPOINT), store.cache_key_of(CHECKPOINT)
    state = unpack(store.array(CHECKPOINT.state).tobytes(), a.layout)
    change(state)
    blob, layout = pack(state)
    with store.staged(CHECKPOINT, key, step=a.step, run_key=a.run_key, layout=layout) as g:
        write_array(g, CHECKPOINT.state, np.frombuffer(blob, np.uint8))


def _set_attrs(store: SceneStore, **attrs: Any) -> None:
    store.group(CHECKPOINT).attrs.update(attrs)


def _replace_array(store: SceneStore, data: np.ndarray) -> None:
    write_array(store.group(CHECKPOINT), "state", data, chunks=(max(1, len(data)),))


TAMPERED = {
    "an extra key": lambda s: _tamper_state(s, lambda st: st.update(extra=1)),
    "a missing key": lambda s: _tamper_state(s, lambda st: st.pop("order")),
    "float64 parameters": lambda s: _tamper_state(
        s, lambda st: st["params"].update(means=st["params"]["means"].astype(np.float64))
    ),
    "parameters of two sizes": lambda s: _tamper_state(
        s, lambda st: st["params"].update(quats=st["params"]["quats"][:-1])
    ),
    "moments of another shape": lambda s: _tamper_state(
        s, lambda st: st["optimizer"]["state"][0].update(exp_avg=torch.zeros(2, 3))
    ),
    "a short RNG state": lambda s: _tamper_state(s, lambda st: st.update(rng_torch=st["rng_torch"][:100])),
    "a view out of range": lambda s: _tamper_state(s, lambda st: st.update(order=[0, 99])),
    "a step unlike the attribute": lambda s: _tamper_state(s, lambda st: st.update(step=9)),
    "no layout": lambda s: _set_attrs(s, layout=None),
    "an old cache key": lambda s: _set_attrs(s, cache_key=cache_key("checkpoint", 1, {"step": 8}, [RUN_KEY])),
    "a short blob": lambda s: _replace_array(s, s.array(CHECKPOINT.state)[:-4]),
    "float32 blob": lambda s: _replace_array(s, s.array(CHECKPOINT.state).astype(np.float32)),
    "no state array": lambda s: s.remove(f"{CHECKPOINT}/state"),
}


@pytest.mark.parametrize("damage", sorted(TAMPERED))
def test_a_checkpoint_that_does_not_fit_is_ignored_with_one_warning(
    tmp_path: Path, uninterrupted: dict[str, Any], caplog: pytest.LogCaptureFixture, damage: str
) -> None:
    store = SceneStore.open_or_create(tmp_path / "scene")
    save_checkpoint(store, RUN_KEY, 8, uninterrupted["saved"][8])
    TAMPERED[damage](store)
    with caplog.at_level(logging.WARNING, logger="wonderverse.splats"):
        assert _load(store) is None
    (record,) = caplog.records
    assert record.getMessage().startswith("ignoring the splat training checkpoint (")
    assert "training starts from the beginning" in record.getMessage() and "\n" not in record.getMessage()


# -- a hostile scene folder ---------------------------------------------------------------------------------


class Payload:
    """Unpickling this writes a marker file: proof that a pickle ran code."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self) -> tuple[Any, ...]:
        return (Path.write_text, (self.marker, "pwned"))


@pytest.mark.e2e
def test_a_pickle_planted_as_the_checkpoint_is_never_run(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    import io

    from conftest import tiny_config

    from flows.pipeline import execute
    from tasks import STEPS, step_keys

    train_params = {"iterations": 12, "checkpoint_every_iters": 6, "holdout_every": 4}
    cfg = tiny_config(video={"width": 96, "height": 64, "frames_per_segment": 6}, extensions={"rounds": 0})
    splats = cfg.steps.splats.model_copy(
        update={"train": cfg.steps.splats.train.model_copy(update=train_params), "max_side_px": 64}
    )
    cfg = cfg.model_copy(
        update={
            "steps": cfg.steps.model_copy(update={"splats": splats}),
            "execution": cfg.execution.model_copy(update={"renderer": "torch"}),
        }
    )
    scene = tmp_path / "scene"
    execute(scene, cfg, until="priors")
    key = step_keys(STEPS, cfg)["splats"]

    # The payload is live: the old reader (torch.load with weights_only=False) would have run it.
    buf = io.BytesIO()
    torch.save({"step": 6, "params": Payload(tmp_path / "proof")}, buf)
    torch.load(io.BytesIO(buf.getvalue()), weights_only=False)
    assert (tmp_path / "proof").read_text() == "pwned"

    # Planted the old way, complete, with the key of this very run (old and current checkpoint versions).
    marker = tmp_path / "marker"
    buf = io.BytesIO()
    torch.save({"step": 6, "params": Payload(marker)}, buf)
    store = SceneStore.open(scene, mode="r+")
    for version in (1, 2):
        ckpt_key = cache_key("checkpoint", version, {"step": 6}, [key])
        with store.staged(CHECKPOINT, ckpt_key, step=6, run_key=key, layout={}) as g:
            write_array(g, CHECKPOINT.state, np.frombuffer(buf.getvalue(), np.uint8))
        del store.group(CHECKPOINT).attrs["layout"]  # as those versions wrote it (the store refuses that now)
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="wonderverse.splats"):
            results = execute(scene, cfg, until="splats")
        assert results[-1].step == "splats" and results[-1].status == "ran", results[-1]
        assert not marker.exists(), f"the planted pickle ran (checkpoint version {version})"
        ignored = [r for r in caplog.records if "ignoring the splat training checkpoint" in r.getMessage()]
        assert len(ignored) == 1 and not [r for r in caplog.records if "resuming" in r.getMessage()]
        done = SceneStore.open(scene)
        assert len(done.meta("splats").curves["total"]) == 12  # trained from the start
        assert not done.exists(CHECKPOINT)
        done = SceneStore.open(scene, mode="r+")
        done.remove("splats")  # train again for the next plant

"""Depth Anything V2 backend, loaded through the user's code path from a tiny randomly initialised model
written with save_pretrained (no real weights exist here and nothing is downloaded)."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from wonderverse.errors import WonderError
from wonderverse.priors import PriorsParams, make_depth_model

torch = pytest.importorskip("torch")
transformers = pytest.importorskip("transformers")


def save_tiny_depth_anything(path: Path, metric: bool = False, seed: int = 0) -> Path:
    """A ~0.1M-parameter Depth Anything (Dinov2 backbone, 14 px patches) and its image processor."""
    from transformers import DepthAnythingConfig, DepthAnythingForDepthEstimation, Dinov2Config

    try:
        from transformers import DPTImageProcessorPil as Processor  # transformers 5 without torchvision
    except ImportError:  # pragma: no cover - transformers 4
        from transformers import DPTImageProcessor as Processor

    backbone = Dinov2Config(
        hidden_size=32,
        num_hidden_layers=4,
        num_attention_heads=2,
        intermediate_size=64,
        patch_size=14,
        image_size=56,
        out_indices=[1, 2, 3, 4],
        reshape_hidden_states=False,
    )
    config = DepthAnythingConfig(
        backbone_config=backbone,
        reassemble_hidden_size=32,
        neck_hidden_sizes=[8, 16, 32, 32],
        fusion_hidden_size=16,
        head_hidden_size=8,
        patch_size=14,
        depth_estimation_type="metric" if metric else "relative",
        max_depth=20,
    )
    torch.manual_seed(seed)
    model = DepthAnythingForDepthEstimation(config).eval()
    # Make the random network's output depend on the image (the default init is near-constant), and keep
    # the relative head's final ReLU from zeroing it: a positive bias on the last conv, weights that matter.
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.05 * torch.randn_like(p))
        model.head.conv3.weight.mul_(20.0)
        model.head.conv3.bias.fill_(1.0)
    model.save_pretrained(path)
    Processor(
        size={"height": 56, "width": 56},
        keep_aspect_ratio=True,
        ensure_multiple_of=14,
        do_resize=True,
        do_rescale=True,
        do_normalize=True,
        image_mean=[0.485, 0.456, 0.406],
        image_std=[0.229, 0.224, 0.225],
        resample=3,
    ).save_pretrained(path)
    return path


@pytest.fixture(scope="module")
def tiny_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return save_tiny_depth_anything(tmp_path_factory.mktemp("da_tiny"))


def frames(n: int, seed: int = 0, h: int = 40, w: int = 60) -> np.ndarray:
    rng = np.random.default_rng(seed)
    base = rng.integers(0, 256, (n, h // 4, w // 4, 3)).astype(np.uint8)
    return np.repeat(np.repeat(base, 4, axis=1), 4, axis=2)  # blocky images: structure at several scales


def test_loads_from_a_local_directory_and_predicts(tiny_dir: Path) -> None:
    model = make_depth_model(PriorsParams(depth_model=str(tiny_dir), device="cpu", batch_size=2))
    x = frames(3)
    pred = model.predict(x)
    assert pred.kind == "inverse_depth"
    assert pred.depth.shape == (3, 40, 60) and pred.depth.dtype == np.float32
    assert np.isfinite(pred.depth).all() and (pred.depth >= 0).all()  # relative head ends in a ReLU
    assert pred.depth.std() > 0
    assert not np.allclose(pred.depth[0], pred.depth[1])  # different images, different predictions


def test_batch_of_three_equals_three_singles_and_is_deterministic(tiny_dir: Path) -> None:
    x = frames(3, seed=1)
    batched = make_depth_model(PriorsParams(depth_model=str(tiny_dir), device="cpu", batch_size=3)).predict(x)
    single_model = make_depth_model(PriorsParams(depth_model=str(tiny_dir), device="cpu", batch_size=1))
    singles = np.concatenate([single_model.predict(x[i : i + 1]).depth for i in range(3)])
    np.testing.assert_allclose(batched.depth, singles, rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(single_model.predict(x).depth, single_model.predict(x).depth)


def test_output_follows_the_frame_size_and_input_size_setting(tiny_dir: Path) -> None:
    x = frames(2, h=32, w=80)
    p = make_depth_model(PriorsParams(depth_model=str(tiny_dir), device="cpu")).predict(x)
    assert p.depth.shape == (2, 32, 80)
    small = make_depth_model(PriorsParams(depth_model=str(tiny_dir), device="cpu", depth_input_size_px=28))
    q = small.predict(x)
    assert q.depth.shape == (2, 32, 80) and not np.allclose(p.depth, q.depth)


def test_metric_checkpoints_report_depth(tmp_path: Path) -> None:
    d = save_tiny_depth_anything(tmp_path / "metric", metric=True)
    pred = make_depth_model(PriorsParams(depth_model=str(d), device="cpu")).predict(frames(1))
    assert pred.kind == "depth" and np.isfinite(pred.depth).all() and (pred.depth > 0).all()


def test_missing_local_directory_is_a_wonder_error(tmp_path: Path) -> None:
    with pytest.raises(WonderError, match="not a directory"):
        make_depth_model(PriorsParams(depth_model=str(tmp_path / "nope"), device="cpu"))
    (tmp_path / "empty").mkdir()
    with pytest.raises(WonderError, match="could not be loaded"):
        make_depth_model(PriorsParams(depth_model=str(tmp_path / "empty"), device="cpu"))


def test_hub_id_without_download_is_a_one_line_wonder_error() -> None:
    t0 = time.perf_counter()
    with pytest.raises(WonderError) as err:
        make_depth_model(PriorsParams(depth_model="nobody-here/no-such-model-xyz", allow_download=False, device="cpu"))
    assert time.perf_counter() - t0 < 20
    msg = str(err.value)
    assert "\n" not in msg and "nobody-here/no-such-model-xyz" in msg and "allow_download" in msg


def test_hub_id_offline_is_a_one_line_wonder_error(tmp_path: Path) -> None:
    """What a user without network sees: HF_HUB_OFFLINE=1 and an empty cache, downloads allowed."""
    code = (
        "from wonderverse.errors import WonderError\n"
        "from wonderverse.priors import PriorsParams, make_depth_model\n"
        "try:\n"
        "    make_depth_model(PriorsParams(depth_model='depth-anything/Depth-Anything-V2-Small-hf', device='cpu'))\n"
        "except WonderError as e:\n"
        "    print('WONDER:' + str(e))\n"
    )
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "HF_HOME": str(tmp_path / "hf"), "TRANSFORMERS_OFFLINE": "1"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    lines = [ln for ln in out.stdout.splitlines() if ln.startswith("WONDER:")]
    assert len(lines) == 1, out.stdout + out.stderr
    assert "Depth-Anything-V2-Small-hf" in lines[0] and "could not be loaded" in lines[0]
    assert "Traceback" not in out.stderr


@pytest.mark.gpu
def test_cuda_fp16_matches_cpu(tiny_dir: Path) -> None:
    if not torch.cuda.is_available():
        pytest.skip("no CUDA device")
    x = frames(4, seed=2)
    cpu = make_depth_model(PriorsParams(depth_model=str(tiny_dir), device="cpu")).predict(x).depth
    gpu = make_depth_model(PriorsParams(depth_model=str(tiny_dir), device="cuda", fp16=True, batch_size=2))
    assert next(gpu.model.parameters()).dtype == torch.float16
    out = gpu.predict(x).depth
    assert out.dtype == np.float32 and np.isfinite(out).all()
    np.testing.assert_allclose(out, cpu, rtol=2e-2, atol=2e-2 * float(np.abs(cpu).max()))

"""PriorsParams validation, the backend factories, and that `import wonderverse.priors` stays light."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from pydantic import ValidationError

from wonderverse.errors import WonderError
from wonderverse.priors import (
    AlignParams,
    DepthPrediction,
    NormalPrediction,
    NormalsFromDepth,
    PriorsParams,
    make_normal_model,
)


def test_import_does_not_load_torch_or_transformers() -> None:
    code = (
        "import sys, wonderverse.priors\n"
        "heavy = [m for m in ('torch', 'transformers', 'scipy', 'open3d', 'pycolmap') if m in sys.modules]\n"
        "print(','.join(heavy))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    assert out.stdout.strip() == ""


def test_defaults_and_validation() -> None:
    p = PriorsParams()
    assert p.depth_backend == "depth_anything" and p.normal_backend == "from_depth"
    assert p.device == "auto" and p.align.method == "trimmed"
    with pytest.raises(ValidationError):
        PriorsParams(depth_backned="oracle")  # type: ignore[call-arg]  # typo: extra keys are errors
    with pytest.raises(ValidationError):
        PriorsParams(oracle_level="brutal")  # type: ignore[arg-type]
    with pytest.raises(ValidationError):
        PriorsParams(batch_size=0)
    with pytest.raises(ValidationError):
        AlignParams(trim_fraction=0.95)
    with pytest.raises(ValidationError):
        p.batch_size = 3  # type: ignore[misc]  # frozen
    q = PriorsParams.model_validate({"align": {"method": "ransac", "min_points": 50}, "oracle_level": "harsh"})
    assert q.align.method == "ransac" and q.align.min_points == 50 and q.oracle_level == "harsh"


def test_from_depth_is_the_default_normal_model() -> None:
    assert isinstance(make_normal_model(PriorsParams()), NormalsFromDepth)


def test_prediction_containers_check_their_arrays() -> None:
    DepthPrediction(np.zeros((1, 4, 5), np.float32), "inverse_depth")
    with pytest.raises(ValueError):
        DepthPrediction(np.zeros((1, 4, 5), np.float64), "depth")
    with pytest.raises(ValueError):
        DepthPrediction(np.zeros((1, 4, 5), np.float32), "disparity")  # type: ignore[arg-type]
    NormalPrediction(np.zeros((1, 4, 5, 3), np.float32), np.ones((1, 4, 5), np.float32))
    with pytest.raises(ValueError):
        NormalPrediction(np.zeros((1, 4, 5), np.float32))
    with pytest.raises(ValueError):
        NormalPrediction(np.zeros((1, 4, 5, 3), np.float32), np.ones((4, 5), np.float32))


def test_cuda_request_without_cuda_is_a_wonder_error() -> None:
    torch = pytest.importorskip("torch")
    if torch.cuda.is_available():
        pytest.skip("a CUDA device is present")
    from wonderverse.priors.runtime import resolve_device

    with pytest.raises(WonderError, match="no CUDA"):
        resolve_device("cuda", True)
    dev, dtype = resolve_device("auto", True)
    assert dev.type == "cpu" and dtype == torch.float32  # fp16 is a CUDA-only setting

"""Building and loading the rasteriser's C++ kernels (`native_raster`), and what happens where they cannot be had.
Their numbers are checked against the torch code in tests/test_splats_render_autograd.py."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest
import torch

from wonderverse.camera import intrinsics
from wonderverse.splats import native_raster
from wonderverse.splats.render_torch import render


@pytest.fixture
def fresh(monkeypatch, tmp_path):
    """`library()` loaded anew under this test's environment (and again after it, under the normal one)."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    native_raster.library.cache_clear()
    yield tmp_path
    native_raster.library.cache_clear()


def small_render() -> torch.Tensor:
    g = torch.Generator().manual_seed(2)
    n = 200
    K = torch.tensor(intrinsics(48, 32, 60.0), dtype=torch.float32)
    z = torch.rand(n, generator=g) * 3 + 2
    means = torch.cat([(torch.rand(n, 2, generator=g) - 0.5) * z[:, None], z[:, None]], 1)
    scales = torch.full((n, 3), 0.05) * z[:, None]
    rgb, *_ = render(
        means,
        torch.randn(n, 4, generator=g),
        scales,
        torch.full((n,), 0.6),
        torch.rand(n, 3, generator=g),
        torch.eye(4),
        K,
        48,
        32,
    )
    return rgb


def test_it_is_built_once_into_the_cache_and_reused(fresh: Path) -> None:
    assert native_raster.library() is not None
    built = list((fresh / "cache" / "wonderverse").glob("raster-*.so"))
    assert len(built) == 1
    stamp = built[0].stat().st_mtime_ns
    native_raster.library.cache_clear()
    assert native_raster.library() is not None
    assert built[0].stat().st_mtime_ns == stamp  # loaded, not rebuilt
    assert not list(built[0].parent.glob("*.so.*")) and len(list(built[0].parent.iterdir())) == 1  # no leftovers


def test_a_cache_that_cannot_be_written_builds_in_a_private_folder(fresh: Path, monkeypatch) -> None:
    (fresh / "not-a-folder").write_text("")
    monkeypatch.setenv("XDG_CACHE_HOME", str(fresh / "not-a-folder"))
    assert native_raster.library() is not None


@pytest.mark.parametrize("env", [{"CXX": "/nonexistent/c++"}, {"WONDERVERSE_NATIVE": "0"}])
def test_without_the_kernels_the_torch_code_renders_the_same_image(fresh: Path, monkeypatch, caplog, env) -> None:
    with_kernels = small_render()
    native_raster.library.cache_clear()
    monkeypatch.setenv("XDG_CACHE_HOME", str(fresh / "empty-cache"))
    for name, value in env.items():
        monkeypatch.setenv(name, value)
    with caplog.at_level(logging.WARNING):
        assert native_raster.library() is None
        without = small_render()
    assert ("rasterising with torch alone" in caplog.text) == ("CXX" in env)  # a missing compiler is said once
    assert float(with_kernels.mean()) > 0.05
    torch.testing.assert_close(without, with_kernels, rtol=1e-5, atol=1e-6)


def test_a_library_others_could_have_written_is_never_loaded(fresh: Path, monkeypatch) -> None:
    """A cache folder anyone may write: the file of the kernels' name in it is not loaded (here it is garbage, which
    would fail to load), the kernels are built in a private folder instead, and the file is left as it was."""
    assert native_raster.library() is not None
    built = next((fresh / "cache" / "wonderverse").glob("raster-*.so"))
    shared = fresh / "shared" / "wonderverse"
    shared.mkdir(parents=True)
    shared.chmod(0o777)
    planted = shared / built.name
    planted.write_bytes(b"not a library")
    native_raster.library.cache_clear()
    monkeypatch.setenv("XDG_CACHE_HOME", str(fresh / "shared"))
    assert native_raster.library() is not None
    assert planted.read_bytes() == b"not a library"

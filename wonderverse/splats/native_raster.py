"""The CPU rasteriser's inner loops in C++ (`native/raster.cpp`), built with the machine's C++ compiler on first use.

The vectorised torch versions in `render_torch` (candidate pairs, compositing and its backward) are exact but
spend their time moving pair-sized tensors through memory; the kernels walk each tile's and each pixel's lists
in registers and are 2-5x faster (`python -m benchmarks.splats`). They need no torch headers: a plain shared
library, called through ctypes on the tensors' memory (ctypes lets go of the GIL meanwhile), compiled in a few
seconds and cached under the user's cache folder by a hash of its source, flags and the machine's architecture; a
library is loaded only from a folder and a file that this user owns and nobody else may write (else it is built in a
private temporary folder).

Work is split among `torch.get_num_threads()` threads; each sums its pixels' gradients, and the sums are added in
thread order, so gradients repeat bit for bit at the same thread count and may differ in their last bits at another
(as torch's own parallel sums do): a resumed training run matches the uninterrupted one on the same machine.
Where there is no compiler, or `WONDERVERSE_NATIVE=0`, or the tensors are not on the CPU, the torch versions run
instead (the same pairs; images and gradients equal to rounding: tests/test_splats_render_autograd.py).
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import hashlib
import logging
import os
import platform
import shutil
import subprocess
import tempfile
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

log = logging.getLogger(__name__)

SOURCE = Path(__file__).with_name("native") / "raster.cpp"
FLAGS = ("-O3", "-shared", "-fPIC", "-std=c++17", "-ffp-contract=off", "-pthread")
_SUFFIX = {torch.float32: "f32", torch.float64: "f64"}


def cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "wonderverse"


def _build(target: Path) -> None:
    """Compile into a temporary file beside `target`, then rename: concurrent builders never see half a file."""
    compiler = os.environ.get("CXX") or shutil.which("c++") or shutil.which("g++")
    if compiler is None:
        raise RuntimeError("no C++ compiler (c++ or g++) on PATH")
    fd, tmp = tempfile.mkstemp(suffix=".so", dir=target.parent)
    os.close(fd)
    try:
        cmd = [compiler, *FLAGS, str(SOURCE), "-o", tmp]
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
        if done.returncode != 0:
            raise RuntimeError(f"{compiler} failed: {done.stderr.strip()[-500:]}")
        os.replace(tmp, target)
    finally:
        Path(tmp).unlink(missing_ok=True)


def _private(path: Path) -> bool:
    """Whether `path` is a folder or file of this user's that no one else may write."""
    try:
        st = path.stat()
    except OSError:
        return False
    return st.st_uid == os.getuid() and not st.st_mode & 0o022


def _declare(lib: ctypes.CDLL) -> ctypes.CDLL:
    ptr, i64, i32 = ctypes.c_void_p, ctypes.c_int64, ctypes.c_int
    for suffix in _SUFFIX.values():
        fwd = getattr(lib, f"wv_composite_forward_{suffix}")
        fwd.argtypes = [ptr] * 7 + [i64] + [ptr] * 4 + [i64, ptr, ptr, i32]
        fwd.restype = i64
        bwd = getattr(lib, f"wv_composite_backward_{suffix}")
        bwd.argtypes = [ptr] * 7 + [i64] + [ptr] * 4 + [i64, i64, ptr, ptr, ptr, i32]
        bwd.restype = None
        cand = getattr(lib, f"wv_candidates_{suffix}")
        cand.argtypes = [ptr] * 5 + [i64, i32, i64, i64, i64] + [ptr] * 4 + [i32]
        cand.restype = None
    return lib


@functools.cache
def library() -> ctypes.CDLL | None:
    """The compiled kernels, or None (logged once) where they cannot be had."""
    if os.environ.get("WONDERVERSE_NATIVE", "1") == "0":
        return None
    try:
        # the machine's architecture too: a home folder shared by an x86 and an ARM machine keeps one library each
        build = f"{' '.join(FLAGS)} {platform.machine()}".encode()
        key = hashlib.sha256(SOURCE.read_bytes() + build).hexdigest()[:16]
        folder = cache_dir()
        with contextlib.suppress(OSError):  # unwritable: judged below
            folder.mkdir(mode=0o700, parents=True, exist_ok=True)
        target = folder / f"raster-{key}.so"
        if not (_private(folder) and (not target.exists() or _private(target))):
            # a cache that cannot be written, or that others could have put a library in: a folder of our own
            target = Path(tempfile.mkdtemp(prefix="wonderverse-")) / target.name
        if not target.exists():
            _build(target)
        return _declare(ctypes.CDLL(str(target)))
    except (OSError, RuntimeError, subprocess.SubprocessError) as e:
        log.warning("the rasteriser's C++ kernels are unavailable (%s); rasterising with torch alone", e)
        return None


def usable(values: Tensor) -> bool:
    """Whether the kernels take tensors like `values` (on the CPU, float32 or float64) here."""
    return values.device.type == "cpu" and values.dtype in _SUFFIX and library() is not None


def candidates(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    gid: Tensor,
    tile: Tensor,
    tile_size: int,
    tiles_x: int,
    width: int,
    height: int,
) -> tuple[Tensor, Tensor, Tensor]:
    """`render_torch._candidate_pairs`' pairs from the tile lists (gid, tile: sorted by tile, then depth): the
    pairs' Gaussians (M,) int32, the runs' boundaries (S+1,) int32 and each run's flat pixel (S,) int64."""
    n_tiles = tiles_x * ((height + tile_size - 1) // tile_size)
    tile_start = torch.zeros(n_tiles + 1, dtype=torch.int32)
    torch.cumsum(torch.bincount(tile, minlength=n_tiles), 0, out=tile_start[1:])
    gid32 = gid.int().contiguous()
    per_gaussian = [t.detach().contiguous() for t in (means2d, conics, opacities)]
    fn = _kernel("candidates", means2d.dtype)
    inputs = (*_ptrs(*per_gaussian, gid32, tile_start), n_tiles, tile_size, tiles_x, width, height)
    counts = torch.zeros(n_tiles, 2, dtype=torch.int64)
    fn(*inputs, counts.data_ptr(), None, None, None, _threads())  # count each tile's pairs and runs
    totals = counts.sum(0).tolist()
    counts = torch.cumsum(counts, 0) - counts  # each tile's first pair and first run
    out_gid = torch.empty(totals[0], dtype=torch.int32)
    crow = torch.zeros(totals[1] + 1, dtype=torch.int32)
    pixel = torch.empty(totals[1], dtype=torch.int64)
    fn(*inputs, *_ptrs(counts, out_gid, crow[1:], pixel), _threads())  # fill them in
    return out_gid, crow, pixel


def _kernel(name: str, dtype: torch.dtype) -> Any:
    """The kernel `wv_NAME_f32` or `_f64` for `dtype` (callers have checked `usable`)."""
    lib = library()
    assert lib is not None
    return getattr(lib, f"wv_{name}_{_SUFFIX[dtype]}")


def _ptrs(*tensors: Tensor) -> list[int]:
    return [t.data_ptr() for t in tensors]


def forward(
    per_gaussian: tuple[Tensor, ...], features: Tensor, gid: Tensor, crow: Tensor, cx: Tensor, cy: Tensor
) -> tuple[Tensor, Tensor, int]:
    """Per run (pixel): Σ w_i f_i (S, F) and the final transmittance (S,); and the number of pairs drawn.
    `per_gaussian` = (mx, my, -a/2, -b, -c/2, opacity), each (N,) contiguous in the features' dtype."""
    n_runs, n_feat = len(cx), features.shape[1]
    acc = torch.empty(n_runs, n_feat, dtype=features.dtype)
    t_final = torch.empty(n_runs, dtype=features.dtype)
    drawn = _kernel("composite_forward", features.dtype)(
        *_ptrs(*per_gaussian, features), n_feat, *_ptrs(gid, crow, cx, cy), n_runs, *_ptrs(acc, t_final), _threads()
    )
    return acc, t_final, int(drawn)


def backward(
    per_gaussian: tuple[Tensor, ...],
    features: Tensor,
    gid: Tensor,
    crow: Tensor,
    cx: Tensor,
    cy: Tensor,
    g_acc: Tensor,
    g_tf_t: Tensor,
) -> tuple[Tensor, Tensor, Tensor]:
    """Per Gaussian: dL/dfeatures (N, F), dL/dopacity (N,) and Σ g_sigma (dx, dy, dx², dx dy, dy²) (5, N), given
    per run dL/dacc (S, F) and dL/dT_final times T_final (S,)."""
    n_gauss, n_feat = features.shape
    threads = _threads()
    grad = torch.zeros(threads, n_gauss, n_feat + 6, dtype=features.dtype)
    _kernel("composite_backward", features.dtype)(
        *_ptrs(*per_gaussian, features),
        n_feat,
        *_ptrs(gid, crow, cx, cy),
        len(cx),
        n_gauss,
        *_ptrs(g_acc, g_tf_t, grad),
        threads,
    )
    total = grad.sum(0)
    return total[:, :n_feat], total[:, n_feat], total[:, n_feat + 1 :].t()


def _threads() -> int:
    return max(1, torch.get_num_threads())

"""The web-ready splat files (SPZ, KHR_gaussian_splatting GLB) and the INRIA PLY, read by third-party readers.

Consumers (installed from npm by scripts/install-tools.sh into tools/node_modules): @playcanvas/splat-transform
reads PLY and SPZ (its SPZ decoding is Adobe's WebAssembly build of Niantic's library), three.js's
GLTFGaussianSplatLoaderExtension reads the GLB, Khronos gltf-validator checks it. Ground truth: the constructed
Gaussians, turned into the files' +Y-up axes by hand (world (x, y, z) -> (x, z, -y)).
"""

from __future__ import annotations

import json
import math
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from plyfile import PlyData

from wonderverse.camera import matrix_from_quat
from wonderverse.splats.model import SH_C0, eval_sh
from wonderverse.splats.ply import read_ply, write_ply
from wonderverse.splats.web import (
    Y_UP_FROM_WORLD,
    read_splat_glb,
    read_spz,
    rotate_gaussians,
    spz_fractional_bits,
    write_splat_glb,
    write_spz,
)

ROOT = Path(__file__).resolve().parents[1]
TOOLS = ROOT / "tools"
SPLAT_TRANSFORM = TOOLS / "node_modules" / "@playcanvas" / "splat-transform" / "bin" / "cli.mjs"
TURN = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])  # what +Y up means, written out independently


def _gaussians(n: int, degree: int, seed: int = 0, spread: float = 5.0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    k = (degree + 1) ** 2 - 1
    return {
        "means": (rng.normal(size=(n, 3)) * spread).astype(np.float32),
        "quats": rng.normal(size=(n, 4)).astype(np.float32),
        "log_scales": rng.uniform(-6, 1, size=(n, 3)).astype(np.float32),
        "logit_opacities": rng.uniform(-5, 5, size=n).astype(np.float32),
        "sh0": rng.uniform(-1.5, 1.5, size=(n, 1, 3)).astype(np.float32),
        "shN": rng.uniform(-0.5, 0.5, size=(n, k, 3)).astype(np.float32),
    }


def _node(script: Path, *args: str) -> subprocess.CompletedProcess:
    """Run a tools/ script with node; skip when node is missing, fail when the tools were not installed."""
    node = shutil.which("node")
    if node is None:
        pytest.skip("node is not installed (the npm consumers need Node.js >= 20 with npm)")
    if not script.exists():
        pytest.fail(f"{script.relative_to(ROOT)} is missing: run `bash scripts/install-tools.sh`")
    return subprocess.run([node, str(script), *args], capture_output=True, text=True, timeout=120, cwd=TOOLS)


def _splat_transform_stats(path: Path) -> dict:
    """splat-transform's own reading of a file: count, SH bands and the x/y/z columns' min and max."""
    run = _node(SPLAT_TRANSFORM, "-q", str(path), "--stats", "json", "null")
    assert run.returncode == 0, run.stderr
    info = json.loads(run.stdout)
    stats = info["stats"][0]
    col = stats["columns"].index
    lo = [stats["data"]["min"][col(c)] for c in "xyz"]
    hi = [stats["data"]["max"][col(c)] for c in "xyz"]
    return {"format": info["format"], "count": info["numGaussians"], "sh_bands": info["shBands"], "min": lo, "max": hi}


def _unit(q: np.ndarray) -> np.ndarray:
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def _rotation_error_rad(q0: np.ndarray, q1: np.ndarray) -> np.ndarray:
    return 2.0 * np.arccos(np.clip(np.abs(np.sum(_unit(q0) * _unit(q1), axis=1)), 0.0, 1.0))


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-np.asarray(x, np.float64)))


# ------------------------------------------------------------------------------------------- our own readers


def test_the_files_axes_are_y_up():
    np.testing.assert_array_equal(Y_UP_FROM_WORLD, TURN)
    assert np.linalg.det(TURN) == 1.0 and (TURN @ [0, 0, 1] == [0, 1, 0]).all()


def test_rotate_gaussians_turns_positions_shapes_and_colours_with_the_scene():
    g = _gaussians(50, 3, seed=1)
    R = matrix_from_quat(np.array([0.3, -0.5, 0.7, 0.2]))
    r = rotate_gaussians(g, R)
    np.testing.assert_allclose(r["means"], g["means"] @ R.T, atol=1e-5)

    def cov(a: dict[str, np.ndarray]) -> list[np.ndarray]:
        pairs = zip(a["quats"].astype(np.float64), a["log_scales"].astype(np.float64), strict=True)
        return [matrix_from_quat(q) @ np.diag(np.exp(2 * s)) @ matrix_from_quat(q).T for q, s in pairs]

    for c0, c1 in zip(cov(g), cov(r), strict=True):
        np.testing.assert_allclose(c1, R @ c0 @ R.T, atol=1e-6)
    # the colour seen along R d after the turn is the colour seen along d before it
    d = torch.from_numpy(np.random.default_rng(2).normal(size=(50, 3)))

    def coeffs(a: dict[str, np.ndarray]) -> torch.Tensor:
        return torch.from_numpy(np.concatenate([a["sh0"], a["shN"]], axis=1).astype(np.float64))

    before = eval_sh(3, coeffs(g), d)
    after = eval_sh(3, coeffs(r), d @ torch.from_numpy(R).T)
    torch.testing.assert_close(after, before, atol=1e-6, rtol=1e-6)


@settings(max_examples=20, deadline=None)
@given(degree=st.integers(0, 3), n=st.integers(1, 40), seed=st.integers(0, 2**31 - 1))
def test_spz_round_trip_is_within_its_quantisation(tmp_path_factory, degree, n, seed):
    g = _gaussians(n, degree, seed)
    path = write_spz(tmp_path_factory.mktemp("spz") / "s.spz", g)
    r = read_spz(path)
    assert {k: v.shape for k, v in r.items()} == {k: v.shape for k, v in g.items()}
    np.testing.assert_allclose(r["means"], g["means"], atol=2.0**-12)  # 12 fractional bits, rounded
    np.testing.assert_allclose(r["log_scales"], g["log_scales"], atol=1 / 32 + 1e-5)  # steps of 1/16
    np.testing.assert_allclose(_sigmoid(r["logit_opacities"]), _sigmoid(g["logit_opacities"]), atol=0.5 / 255 + 1e-6)
    np.testing.assert_allclose(r["sh0"], g["sh0"], atol=0.5 / (0.15 * 255) + 1e-5)  # 8 bits at scale 0.15
    assert _rotation_error_rad(r["quats"], g["quats"]).max() < 0.01  # 9 bits per component
    for band in range(1, degree + 1):  # 5 bits for degree 1, 4 above, in the file's axes: per-band L2 bounds
        sl = slice(band * band - 1, (band + 1) ** 2 - 1)
        step = (8 if band == 1 else 16) / 128
        err = np.linalg.norm(r["shN"][:, sl] - g["shN"][:, sl], axis=1)
        assert err.max() <= math.sqrt(2 * band + 1) * (step / 2 + 1 / 256) + 1e-5, band


def test_spz_positions_keep_their_range_with_fewer_fractional_bits(tmp_path: Path):
    assert spz_fractional_bits(np.array([[2047.0, 0, 0]])) == 12
    assert spz_fractional_bits(np.array([[5000.0, 0, 0]])) == 10
    assert spz_fractional_bits(np.array([[-1.0e5, 0, 0]])) == 6
    with pytest.raises(ValueError, match="24-bit"):
        spz_fractional_bits(np.array([[1.0e7, 0, 0]]))
    g = _gaussians(20, 1, spread=3.0e4)
    r = read_spz(write_spz(tmp_path / "far.spz", g))
    np.testing.assert_allclose(r["means"], g["means"], atol=2.0 ** -(spz_fractional_bits(g["means"]) + 1) + 0.01)


def test_glb_round_trip_is_exact_to_float32(tmp_path: Path):
    g = _gaussians(30, 2)
    r = read_splat_glb(write_splat_glb(tmp_path / "s.glb", g))
    for name in ("means", "log_scales", "sh0", "shN"):
        np.testing.assert_allclose(r[name], g[name], atol=2e-5, err_msg=name)
    np.testing.assert_allclose(_sigmoid(r["logit_opacities"]), _sigmoid(g["logit_opacities"]), atol=1e-6)
    assert _rotation_error_rad(r["quats"], g["quats"]).max() < 1e-3


def test_bad_input_is_refused(tmp_path: Path):
    g = _gaussians(5, 1)
    g["means"][2, 1] = np.nan
    with pytest.raises(ValueError, match="means holds non-finite"):
        write_spz(tmp_path / "a.spz", g)
    with pytest.raises(ValueError, match="means holds non-finite"):
        write_splat_glb(tmp_path / "a.glb", g)
    g = _gaussians(5, 1)
    g["shN"] = g["shN"][:, :2]
    with pytest.raises(ValueError, match="coefficients per channel"):
        write_spz(tmp_path / "b.spz", g)
    assert not list(tmp_path.iterdir())


def test_no_gaussians_write_empty_files(tmp_path: Path):
    g = _gaussians(0, 1)
    assert read_spz(write_spz(tmp_path / "e.spz", g))["shN"].shape == (0, 3, 3)
    assert read_splat_glb(write_splat_glb(tmp_path / "e.glb", g))["means"].shape == (0, 3)


# ------------------------------------------------------------------------------------------ the consumers


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> tuple[dict[str, np.ndarray], dict[str, Path]]:
    """One cloud (degree 3, 400 Gaussians, coordinates within ±25 units) written in every format."""
    g = _gaussians(400, 3, seed=7)
    folder = tmp_path_factory.mktemp("formats")
    paths = {
        "ply": write_ply(folder / "splats.ply", g),
        "spz": write_spz(folder / "splats.spz", g),
        "glb": write_splat_glb(folder / "splats.glb", g),
    }
    return g, paths


def test_splat_transform_reads_our_ply_and_spz_with_our_count_and_bounds(files):
    g, paths = files
    world = g["means"].astype(np.float64)
    y_up = world @ TURN.T
    ply = _splat_transform_stats(paths["ply"])
    assert (ply["format"], ply["count"], ply["sh_bands"]) == ("ply", 400, 3)
    np.testing.assert_allclose(ply["min"], world.min(0), atol=1e-5)
    np.testing.assert_allclose(ply["max"], world.max(0), atol=1e-5)
    spz = _splat_transform_stats(paths["spz"])
    assert (spz["format"], spz["count"], spz["sh_bands"]) == ("spz", 400, 3)
    # SPZ is +Y up: splat-transform decodes the stored axes as they are
    np.testing.assert_allclose(spz["min"], y_up.min(0), atol=2.0**-12 + 1e-5)
    np.testing.assert_allclose(spz["max"], y_up.max(0), atol=2.0**-12 + 1e-5)


def test_splat_transform_decodes_every_spz_attribute_to_our_values(files, tmp_path: Path):
    """SPZ -> PLY by splat-transform (Niantic's decoder compiled by Adobe), read back: each Gaussian equals ours,
    turned +Y up, within the format's quantisation."""
    g, paths = files
    out = tmp_path / "from_spz.ply"
    run = _node(SPLAT_TRANSFORM, "-q", "-w", str(paths["spz"]), str(out))
    assert run.returncode == 0, run.stderr
    theirs = read_ply(out)
    ours = rotate_gaussians(g, TURN)
    assert len(theirs["means"]) == 400
    np.testing.assert_allclose(theirs["means"], ours["means"], atol=2.0**-12 + 1e-5)
    np.testing.assert_allclose(theirs["log_scales"], ours["log_scales"], atol=1 / 32 + 1e-4)
    np.testing.assert_allclose(_sigmoid(theirs["logit_opacities"]), _sigmoid(ours["logit_opacities"]), atol=0.003)
    np.testing.assert_allclose(theirs["sh0"], ours["sh0"], atol=0.5 / (0.15 * 255) + 1e-4)
    assert _rotation_error_rad(theirs["quats"], ours["quats"]).max() < 0.01
    np.testing.assert_allclose(theirs["shN"][:, :3], ours["shN"][:, :3], atol=4 / 128 + 1 / 256 + 1e-4)
    np.testing.assert_allclose(theirs["shN"][:, 3:], ours["shN"][:, 3:], atol=8 / 128 + 1 / 256 + 1e-4)


def test_opaque_and_invisible_splats_decode_to_finite_opacities(tmp_path: Path):
    """SPZ's decoders take the logit of byte / 255: Niantic's library does not clamp it, so bytes 0 and 255 decode to
    -inf and +inf. Fully opaque and fully transparent splats are written as bytes 1..254: the spec's logit of every
    stored byte is finite, and splat-transform's decoding (SPZ -> PLY and its --stats) has no inf or NaN opacity."""
    import gzip

    logits = np.array([-40.0, -12.0, -6.0, 0.0, 6.0, 12.0, 40.0], np.float32)
    g = _gaussians(len(logits), 1, seed=3)
    g["logit_opacities"] = logits
    path = write_spz(tmp_path / "ends.spz", g)
    raw = gzip.decompress(path.read_bytes())
    n = int.from_bytes(raw[8:12], "little")
    alpha = np.frombuffer(raw, np.uint8, n, 16 + 9 * n)  # the header, then 3 x 24-bit positions per splat
    assert n == len(logits) and alpha.min() >= 1 and alpha.max() <= 254, alpha
    spec = np.log((alpha / 255.0) / (1.0 - alpha / 255.0))  # the library's invSigmoid, unclamped
    assert np.isfinite(spec).all()
    assert _sigmoid(spec[-1]) > 0.99 and _sigmoid(spec[0]) < 0.005  # opaque stays opaque, invisible nearly so
    out = tmp_path / "ends.ply"
    run = _node(SPLAT_TRANSFORM, "-q", "-w", str(path), str(out))
    assert run.returncode == 0, run.stderr
    theirs = PlyData.read(str(out))["vertex"]["opacity"].astype(np.float64)
    assert np.isfinite(theirs).all()
    np.testing.assert_allclose(theirs, spec, atol=1e-5)  # what splat-transform decodes is the spec's value
    run = _node(SPLAT_TRANSFORM, "-q", str(path), "--stats", "json", "null")
    assert run.returncode == 0, run.stderr
    stats = json.loads(run.stdout)["stats"][0]
    col = stats["columns"].index("opacity")
    assert stats["data"]["infCount"][col] == 0 and stats["data"]["nanCount"][col] == 0


def test_three_reads_our_glb_with_our_count_bounds_shapes_and_colours(files):
    g, paths = files
    run = _node(TOOLS / "read-splat-glb.mjs", str(paths["glb"]), "8")
    assert run.returncode == 0, run.stderr
    read = json.loads(run.stdout)
    y_up = g["means"].astype(np.float64) @ TURN.T
    assert (read["splats"], read["count"]) == (1, 400)
    np.testing.assert_allclose(read["min"], y_up.min(0), atol=1e-5)
    np.testing.assert_allclose(read["max"], y_up.max(0), atol=1e-5)
    for i in range(8):  # three builds Σ = R S S^T R^T from the linear SCALE and the xyzw ROTATION
        R = TURN @ matrix_from_quat(g["quats"][i].astype(np.float64))
        cov = R @ np.diag(np.exp(2.0 * g["log_scales"][i].astype(np.float64))) @ R.T
        upper = [cov[0, 0], cov[0, 1], cov[0, 2], cov[1, 1], cov[1, 2], cov[2, 2]]
        np.testing.assert_allclose(read["covariances"][6 * i : 6 * i + 6], upper, rtol=1e-4, atol=1e-9)
        rgb = np.clip(g["sh0"][i, 0] * SH_C0 + 0.5, 0, 1) * 255
        alpha = _sigmoid(g["logit_opacities"][i]) * 255
        np.testing.assert_allclose(read["colors"][4 * i : 4 * i + 4], [*rgb, alpha], atol=0.51)


def test_a_splat_long_along_world_up_is_long_along_the_files_y(tmp_path: Path):
    g = _gaussians(1, 0)
    g["means"] = np.array([[1.0, 2.0, 3.0]], np.float32)
    g["quats"] = np.array([[1.0, 0, 0, 0]], np.float32)
    g["log_scales"] = np.log(np.array([[0.1, 0.2, 2.0]], np.float32))  # σ 2 along world z (up)
    run = _node(TOOLS / "read-splat-glb.mjs", str(write_splat_glb(tmp_path / "up.glb", g)), "1")
    assert run.returncode == 0, run.stderr
    read = json.loads(run.stdout)
    np.testing.assert_allclose(read["min"], [1.0, 3.0, -2.0], atol=1e-6)
    xx, xy, xz, yy, yz, zz = read["covariances"]
    np.testing.assert_allclose([xx, yy, zz], [0.01, 4.0, 0.04], rtol=1e-5)
    np.testing.assert_allclose([xy, xz, yz], 0.0, atol=1e-7)
    stats = _splat_transform_stats(write_spz(tmp_path / "up.spz", g))
    np.testing.assert_allclose(stats["min"], [1.0, 3.0, -2.0], atol=2.0**-12)


def test_gltf_validator_objects_only_to_the_extension_attributes_it_does_not_know(files):
    """gltf-validator 2.0.0-dev.3.10 predates KHR_gaussian_splatting: it reports the extension as unsupported
    (an info) and every `KHR_gaussian_splatting:*` attribute as an invalid name (core glTF's rule for attributes
    no extension defines). Anything else — accessors, buffer views, bounds, alignment, COLOR_0 — must be clean."""
    _, paths = files
    run = _node(TOOLS / "validate-gltf.mjs", str(paths["glb"]))
    assert run.returncode in (0, 1), run.stderr
    report = json.loads(run.stdout)
    messages = report["issues"]["messages"]
    others = [
        m
        for m in messages
        if not (
            m["code"] == "MESH_PRIMITIVE_INVALID_ATTRIBUTE"
            and m["pointer"].startswith("/meshes/0/primitives/0/attributes/KHR_gaussian_splatting:")
        )
        and not (m["code"] == "UNSUPPORTED_EXTENSION" and m["severity"] >= 2)
    ]
    assert others == []
    assert report["issues"]["numWarnings"] == 0
    assert report["issues"]["numErrors"] == 4 + 15  # ROTATION, SCALE, OPACITY, SH0 and degree 1-3's 15 coefficients

"""The diffusers video backend on CPU with tiny random pipelines saved to disk and loaded back through
the backend's own loading code (no hub access: everything is built here)."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("diffusers")
pytest.importorskip("transformers")

from tiny_diffusers import save_tiny_pipelines

from wonderverse.config import build_config
from wonderverse.errors import ConfigError, WonderError
from wonderverse.video import make_video_model
from wonderverse.video.diffusion import (
    DiffusionParams,
    DiffusionVideo,
    nearest_frame_count,
    nearest_side,
)

T, H, W = 9, 32, 48
FOV = 60.0
PROMPT = "aerial shot, soft lighting, around left, realistic, high-quality, displaying a mountain village."
HAS_FTFY = importlib.util.find_spec("ftfy") is not None


@pytest.fixture(scope="module")
def tiny(tmp_path_factory: pytest.TempPathFactory) -> dict[str, dict[str, Path]]:
    families = ("cogvideox", "wan", "wan_vace") if HAS_FTFY else ("cogvideox",)
    return save_tiny_pipelines(tmp_path_factory.mktemp("tiny-pipelines"), families)


def _params(tiny: dict[str, dict[str, Path]], family: str = "cogvideox", **kw: object) -> DiffusionParams:
    f = tiny[family]
    return DiffusionParams(
        **{"family": family, "t2v_model": str(f["t2v"]), "i2v_model": str(f["i2v"]), "steps": 2, **kw}
    )


@pytest.fixture(scope="module")
def cog(tiny: dict[str, dict[str, Path]]) -> DiffusionVideo:
    return DiffusionVideo(W, H, T, FOV, _params(tiny))


def _path(n: int = T) -> np.ndarray:
    return np.tile(np.eye(4), (n, 1, 1))


def _reference(seed: int) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (H, W, 3), dtype=np.uint8)


def test_t2v_shape_dtype_intrinsics_and_seeds(cog: DiffusionVideo) -> None:
    a = cog.generate(PROMPT, _path(), 1, None)
    again = cog.generate(PROMPT, _path(), 1, None)
    other = cog.generate(PROMPT, _path(), 2, None)
    assert a.frames.shape == (T, H, W, 3) and a.frames.dtype == np.uint8
    assert a.gt is None
    assert a.frames.std() > 1.0  # a real decoded video, not a constant fill
    fx = (W / 2) / np.tan(np.radians(FOV / 2))
    np.testing.assert_allclose(a.K, [[fx, 0, W / 2], [0, fx, H / 2], [0, 0, 1]])
    assert a.K.dtype == np.float64
    np.testing.assert_array_equal(a.frames, again.frames)
    assert np.abs(a.frames.astype(int) - other.frames).mean() > 1.0


def test_i2v_follows_the_reference(cog: DiffusionVideo) -> None:
    a = cog.generate(PROMPT, _path(), 3, _reference(0))
    a2 = cog.generate(PROMPT, _path(), 3, _reference(0))
    b = cog.generate(PROMPT, _path(), 3, _reference(1))
    assert a.frames.shape == (T, H, W, 3) and a.frames.dtype == np.uint8
    np.testing.assert_array_equal(a.frames, a2.frames)
    assert np.abs(a.frames.astype(int) - b.frames).mean() > 1.0
    # the image-to-video pipeline was the one loaded for a reference, the text-to-video one for none
    assert type(cog.pipeline("i2v")).__name__ == "CogVideoXImageToVideoPipeline"
    assert type(cog.pipeline("t2v")).__name__ == "CogVideoXPipeline"


def test_prompt_reaches_the_text_encoder_unchanged(cog: DiffusionVideo) -> None:
    pipe = cog.pipeline("t2v")
    seen: list[list[int]] = []
    hook = pipe.text_encoder.register_forward_pre_hook(
        lambda _m, args, kwargs: seen.append((kwargs.get("input_ids", args[0] if args else None))[0].tolist()),
        with_kwargs=True,
    )
    try:
        a = cog.generate(PROMPT, _path(), 4, None)
    finally:
        hook.remove()
    assert PROMPT in {pipe.tokenizer.decode(ids, skip_special_tokens=True) for ids in seen}
    b = cog.generate("aerial shot, soft lighting, displaying a coastal city at dusk.", _path(), 4, None)
    assert np.abs(a.frames.astype(int) - b.frames).mean() > 0.5


@pytest.mark.skipif(not HAS_FTFY, reason="diffusers' Wan image-to-video pipeline needs ftfy")
def test_wan_family_t2v_and_i2v(tiny: dict[str, dict[str, Path]]) -> None:
    wan = DiffusionVideo(W, H, T, FOV, _params(tiny, "wan"))
    t2v = wan.generate(PROMPT, _path(), 5, None)
    i2v_a = wan.generate(PROMPT, _path(), 5, _reference(0))
    i2v_b = wan.generate(PROMPT, _path(), 5, _reference(1))
    assert t2v.frames.shape == i2v_a.frames.shape == (T, H, W, 3)
    assert type(wan.pipeline("i2v")).__name__ == "WanImageToVideoPipeline"
    # random weights pass little of the image latents through, but a reference that is not used gives equal frames
    assert not np.array_equal(i2v_a.frames, i2v_b.frames)
    np.testing.assert_array_equal(i2v_a.frames, wan.generate(PROMPT, _path(), 5, _reference(0)).frames)


# The oracle priors (the default) need the procedural world's ground truth: diffusion video takes a network's.
PRIORS = {"steps": {"priors": {"models": {"depth_backend": "depth_anything"}}}}


def test_make_video_model_from_run_config(tiny: dict[str, dict[str, Path]]) -> None:
    f = tiny["cogvideox"]
    opts = {"t2v_model": str(f["t2v"]), "i2v_model": str(f["i2v"]), "steps": 2, "device": "cpu"}
    video = {"backend": "diffusers", "frames_per_segment": T, "width": W, "height": H, "fov_deg": 70.0}
    cfg = build_config(
        "a mountain village", preset="preview", overrides={"scene": {"video": {**video, "options": opts}}, **PRIORS}
    )
    model = make_video_model(cfg.scene.video_source)
    assert isinstance(model, DiffusionVideo) and model.params.family == "cogvideox" and model.device == "cpu"
    v = model.generate(PROMPT, _path(), 0, None)
    assert v.frames.shape == (T, H, W, 3)
    assert v.K[0, 0] == pytest.approx((W / 2) / np.tan(np.radians(35.0)))
    # the preview preset's own sizes (17 frames, 320x208) are valid for every family
    preview = build_config("x", preset="preview", overrides={"scene": {"video": {"backend": "diffusers"}}, **PRIORS})
    assert isinstance(make_video_model(preview.scene.video_source), DiffusionVideo)


def test_bad_options_and_sizes_are_one_line_errors(tiny: dict[str, dict[str, Path]]) -> None:
    def scene(video: dict[str, object]) -> object:
        return build_config(
            "x", preset="preview", overrides={"scene": {"video": {"backend": "diffusers", **video}}, **PRIORS}
        ).scene

    # options and sizes are checked when the config is built, before any backend or store exists
    with pytest.raises(ConfigError, match=r"scene\.video\.options\.steps_count: unknown setting"):
        scene({"options": {"steps_count": 3}})
    with pytest.raises(
        ConfigError,
        match=r"scene\.video\.frames_per_segment: cogvideox renders 8k\+1 .* 21 is not, nearest valid is 25",
    ):
        scene({"frames_per_segment": 21})
    with pytest.raises(
        ConfigError, match=r"scene\.video\.width: wan needs a multiple of 16 px; 330 is not, nearest valid is 336"
    ):
        scene({"width": 330, "options": {"family": "wan"}})
    cog = DiffusionVideo(W, H, T, FOV, _params(tiny))
    with pytest.raises(WonderError, match=r"frames_per_segment: .* 13 is not, nearest valid is 17"):
        cog.generate(PROMPT, _path(13), 0, None)
    with pytest.raises(WonderError, match=r"camera path must be \(T,4,4\)"):
        cog.generate(PROMPT, np.eye(4), 0, None)
    with pytest.raises(WonderError, match=r"reference frame must be \(H,W,3\) uint8"):
        cog.generate(PROMPT, _path(), 0, _reference(0).astype(np.float32))
    with pytest.raises(WonderError, match=r"returned frames of shape \(1, 32, 48, 3\), not \(9, 32, 48, 3\)"):
        cog._to_uint8(np.zeros((1, 1, H, W, 3), np.float32), T)
    with pytest.raises(WonderError, match="non-finite"):
        cog._to_uint8(np.full((1, T, H, W, 3), np.nan, np.float32), T)
    assert (nearest_frame_count(19, 4), nearest_frame_count(2, 4), nearest_frame_count(50, 4)) == (21, 5, 49)
    assert (nearest_frame_count(21, 8), nearest_frame_count(13, 8), nearest_frame_count(5, 8)) == (25, 17, 9)
    assert (nearest_side(330, 16), nearest_side(3, 16), nearest_side(200, 16)) == (336, 16, 208)


def test_missing_weights_are_clear_errors(tmp_path: Path, tiny: dict[str, dict[str, Path]]) -> None:
    missing = DiffusionVideo(W, H, T, FOV, _params(tiny, t2v_model=str(tmp_path / "nope")))
    with pytest.raises(WonderError, match=r"t2v_model: .*nope does not exist"):
        missing.generate(PROMPT, _path(), 0, None)
    not_a_pipeline = DiffusionVideo(W, H, T, FOV, _params(tiny, i2v_model=str(tmp_path)))
    with pytest.raises(WonderError, match=r"i2v_model: .* has no model_index\.json"):
        not_a_pipeline.generate(PROMPT, _path(), 0, _reference(0))
    hub = DiffusionVideo(W, H, T, FOV, _params(tiny, t2v_model="wonderverse-tests/no-such-model"))
    with pytest.raises(WonderError, match=r"not in the local Hugging Face cache; set allow_download: true") as e:
        hub.generate(PROMPT, _path(), 0, None)
    assert "\n" not in str(e.value)


def test_cuda_offload_and_half_precision_need_a_gpu(tiny: dict[str, dict[str, Path]]) -> None:
    import torch

    if torch.cuda.is_available():
        pytest.skip("these errors are about a machine without CUDA")
    with pytest.raises(WonderError, match="cuda was asked for but torch sees no CUDA device"):
        DiffusionVideo(W, H, T, FOV, _params(tiny, device="cuda"))
    with pytest.raises(WonderError, match="model offload needs CUDA"):
        DiffusionVideo(W, H, T, FOV, _params(tiny, offload="model"))
    with pytest.raises(WonderError, match="float16 needs CUDA"):
        DiffusionVideo(W, H, T, FOV, _params(tiny, dtype="float16"))
    assert DiffusionVideo(W, H, T, FOV, _params(tiny)).device == "cpu"  # auto falls back to CPU


def test_gpu_check_script_runs_on_cpu(tiny: dict[str, dict[str, Path]], capsys: pytest.CaptureFixture[str]) -> None:
    root = Path(__file__).resolve().parent.parent
    spec = importlib.util.spec_from_file_location("gpu_video_diffusion", root / "scripts" / "gpu_video_diffusion.py")
    assert spec is not None and spec.loader is not None
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    tiny_dir = tiny["cogvideox"]["t2v"].parent
    rc = script.main(
        ["--device", "cpu", "--tiny-dir", str(tiny_dir), "--frames", "9", "--width", "32", "--height", "32"]
    )
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert rc == 0 and out["ok"] is True and out["cuda"] is False
    assert {r["family"] for r in out["runs"]} == set(tiny)
    for r in out["runs"]:
        assert r["t2v_shape"] == r["i2v_shape"] == [9, 32, 32, 3]
        assert r["finite"] is True and r["same_seed_identical"] is True and r["pipeline_dtype"] == "float32"
        assert r["takes_guide"] is (r["family"] == "wan_vace")
        if r["takes_guide"]:
            assert r["guided_shape"] == [9, 32, 32, 3]
            assert r["guide_changes_output"] is True and r["guided_same_seed_identical"] is True


def test_importing_the_backend_stays_light() -> None:
    import subprocess

    code = (
        "import sys, wonderverse.video.diffusion; "
        "heavy = ('open3d', 'zarr', 'pycolmap', 'prefect', 'torch', 'diffusers', 'yaml'); "
        "print(sorted(m for m in heavy if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"

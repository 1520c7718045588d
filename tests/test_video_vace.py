"""The guided diffusers family (wan_vace, WanVACEPipeline) on CPU: a tiny random VACE pipeline saved to disk and
loaded back through the backend's own loading code, generating with and without a `Guide`."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("diffusers")
pytest.importorskip("transformers")
if importlib.util.find_spec("ftfy") is None:
    pytest.skip("diffusers' Wan VACE pipeline needs ftfy", allow_module_level=True)

from pydantic import ValidationError
from tiny_diffusers import save_tiny_pipelines

from wonderverse.config import build_config
from wonderverse.errors import ConfigError, WonderError
from wonderverse.video import make_video_model
from wonderverse.video.base import Guide
from wonderverse.video.diffusion import (
    FAMILIES,
    DiffusionParams,
    DiffusionVideo,
    family_takes_guide,
    load_pipeline,
)

T, H, W = 9, 32, 48
FOV = 60.0
PROMPT = "aerial shot, soft lighting, around left, realistic, high-quality, displaying a mountain village."
# The oracle priors (the default) need the procedural world's ground truth: diffusion video takes a network's.
PRIORS = {"steps": {"priors": {"models": {"depth_backend": "depth_anything"}}}}


@pytest.fixture(scope="module")
def folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return save_tiny_pipelines(tmp_path_factory.mktemp("tiny-vace"), ("wan_vace",))["wan_vace"]["guided"]


def _params(folder: Path, **kw: Any) -> DiffusionParams:
    return DiffusionParams(**{"family": "wan_vace", "guided_model": str(folder), "steps": 2, **kw})


@pytest.fixture(scope="module")
def vace(folder: Path) -> DiffusionVideo:
    return DiffusionVideo(W, H, T, FOV, _params(folder))


def _path(n: int = T) -> np.ndarray:
    return np.tile(np.eye(4), (n, 1, 1))


def _frames(seed: int, n: int = T, h: int = H, w: int = W) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (n, h, w, 3), dtype=np.uint8)


def _right_half_unknown(n: int = T, h: int = H, w: int = W) -> np.ndarray:
    mask = np.zeros((n, h, w), bool)
    mask[:, :, w // 2 :] = True
    return mask


def _guide(frames: np.ndarray, mask: np.ndarray) -> Guide:
    depth = np.where(mask, np.inf, 2.0).astype(np.float32)
    return Guide(frames=np.where(mask[..., None], 0, frames).astype(np.uint8), mask=mask, depth=depth)


def _diff(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.abs(a.astype(int) - b).mean())


def _control_inputs(model: DiffusionVideo, *args: Any) -> tuple[np.ndarray, Any]:
    """The VACE control latents the transformer received first (B, 96, F, h, w), and the generated video."""
    pipe = model.pipeline("guided")
    seen: list[np.ndarray] = []
    hook = pipe.transformer.register_forward_pre_hook(
        lambda _m, _a, kwargs: seen.append(kwargs["control_hidden_states"].float().numpy()), with_kwargs=True
    )
    try:
        video = model.generate(*args)
    finally:
        hook.remove()
    return seen[0], video


def test_the_guided_family_loads_vace_through_the_backend(vace: DiffusionVideo, folder: Path) -> None:
    assert vace.takes_guide and family_takes_guide("wan_vace")
    assert not any(family_takes_guide(f) for f in ("cogvideox", "wan", "hunyuan"))
    assert FAMILIES["wan_vace"].guided_default == "Wan-AI/Wan2.1-VACE-1.3B-diffusers"
    pipe = vace.pipeline("guided")
    assert type(pipe).__name__ == "WanVACEPipeline"
    assert load_pipeline(_params(folder), "guided") is pipe  # loaded once per process
    with pytest.raises(WonderError, match="the wan_vace family has no t2v pipeline"):
        load_pipeline(_params(folder), "t2v")


def test_guided_generation_shape_dtype_and_seeds(vace: DiffusionVideo) -> None:
    guide = _guide(_frames(0), _right_half_unknown())
    a = vace.generate(PROMPT, _path(), 1, None, guide)
    again = vace.generate(PROMPT, _path(), 1, None, guide)
    other = vace.generate(PROMPT, _path(), 2, None, guide)
    assert a.frames.shape == (T, H, W, 3) and a.frames.dtype == np.uint8
    assert a.frames.std() > 1.0  # a decoded video, not a constant fill
    fx = (W / 2) / np.tan(np.radians(FOV / 2))
    np.testing.assert_allclose(a.K, [[fx, 0, W / 2], [0, fx, H / 2], [0, 0, 1]])
    np.testing.assert_array_equal(a.frames, again.frames)
    assert _diff(a.frames, other.frames) > 0.5


def test_the_mask_reaches_the_model_white_where_unknown(vace: DiffusionVideo) -> None:
    mask = _right_half_unknown()
    control, _ = _control_inputs(vace, PROMPT, _path(), 3, None, _guide(_frames(0), mask))
    # 16 latent channels of the known pixels, 16 of the unknown ones, then the mask folded from 8x8 pixel cells
    assert control.shape == (1, 96, 3, H // 8, W // 8)
    folded = control[0, 32:]
    np.testing.assert_array_equal(folded[..., : W // 16], 0.0)  # the known left half: keep
    np.testing.assert_array_equal(folded[..., W // 16 :], 1.0)  # the unknown right half: generate
    # with no guide and no reference every pixel is generated
    control, _ = _control_inputs(vace, PROMPT, _path(), 3, None)
    np.testing.assert_array_equal(control[0, 32:], 1.0)


def test_known_pixels_steer_the_output_unknown_ones_do_not(vace: DiffusionVideo) -> None:
    mask = _right_half_unknown()
    a, b = _frames(0), _frames(1)
    base = vace.generate(PROMPT, _path(), 4, None, _guide(a, mask)).frames
    other_known = vace.generate(PROMPT, _path(), 4, None, _guide(b, mask)).frames
    assert _diff(base, other_known) > 0.02
    # content under the mask is replaced by grey before the pipeline sees it: whatever is there changes nothing
    b_right = a.copy()
    b_right[mask] = b[mask]
    unknown_changed = Guide(frames=b_right, mask=mask, depth=np.ones((T, H, W), np.float32))
    np.testing.assert_array_equal(base, vace.generate(PROMPT, _path(), 4, None, unknown_changed).frames)
    # another mask over the same frames, and no guide at all, give other videos
    assert _diff(base, vace.generate(PROMPT, _path(), 4, None, _guide(a, ~mask)).frames) > 0.05
    assert _diff(base, vace.generate(PROMPT, _path(), 4, None).frames) > 0.05


def test_conditioning_scale_reaches_the_pipeline(folder: Path, vace: DiffusionVideo) -> None:
    mask = _right_half_unknown()
    off = DiffusionVideo(W, H, T, FOV, _params(folder, conditioning_scale=0.0))
    a = off.generate(PROMPT, _path(), 5, None, _guide(_frames(0), mask)).frames
    b = off.generate(PROMPT, _path(), 5, None, _guide(_frames(1), mask)).frames
    np.testing.assert_array_equal(a, b)  # scale 0: the control branch adds nothing, the guide is ignored
    on = vace.generate(PROMPT, _path(), 5, None, _guide(_frames(0), mask)).frames
    assert _diff(a, on) > 0.05


def test_without_a_guide_the_family_still_renders_from_text_or_a_reference(vace: DiffusionVideo) -> None:
    t2v = vace.generate(PROMPT, _path(), 6, None)
    ref_a = vace.generate(PROMPT, _path(), 6, _frames(0)[0])
    ref_b = vace.generate(PROMPT, _path(), 6, _frames(1)[0])
    assert t2v.frames.shape == ref_a.frames.shape == (T, H, W, 3) and ref_a.frames.dtype == np.uint8
    assert _diff(ref_a.frames, ref_b.frames) > 0.02
    np.testing.assert_array_equal(ref_a.frames, vace.generate(PROMPT, _path(), 6, _frames(0)[0]).frames)


def test_guide_reference_picks_how_the_reference_frame_is_given(folder: Path) -> None:
    ref = _frames(2)[0]
    guide = _guide(_frames(0), _right_half_unknown())
    frames_seen = {}
    for use in ("first_frame", "reference_image", "both"):
        model = DiffusionVideo(W, H, T, FOV, _params(folder, guide_reference=use))
        control, video = _control_inputs(model, PROMPT, _path(), 7, ref, guide)
        assert video.frames.shape == (T, H, W, 3)
        frames_seen[use] = control.shape[2]
    # a VACE reference image is one more latent frame in front of the video's three
    assert frames_seen == {"first_frame": 3, "reference_image": 4, "both": 4}
    small = DiffusionVideo(W, H, T, FOV, _params(folder, guide_reference="first_frame"))
    with pytest.raises(WonderError, match=r"reference frame is 16x16 but the video is 32x48"):
        small.generate(PROMPT, _path(), 0, np.zeros((16, 16, 3), np.uint8), guide)


def test_a_guide_for_an_unguided_family_is_a_one_line_error() -> None:
    guide = _guide(_frames(0), _right_half_unknown())
    for family in ("cogvideox", "wan", "hunyuan"):
        model = DiffusionVideo(W, H, T, FOV, DiffusionParams(family=family))  # no weights are loaded for this
        assert model.takes_guide is False
        with pytest.raises(WonderError, match=rf"the {family} family cannot take a guide.*wan_vace") as e:
            model.generate(PROMPT, _path(), 0, None, guide)
        assert "\n" not in str(e.value)


def test_a_guide_of_the_wrong_size_names_both_sizes(vace: DiffusionVideo) -> None:
    narrow = _guide(_frames(0, w=32), _right_half_unknown(w=32))
    with pytest.raises(WonderError, match=r"the guide is 9x32x32 \(frames x height x width\) but the video is 9x32x48"):
        vace.generate(PROMPT, _path(), 0, None, narrow)
    short = _guide(_frames(0, n=5), _right_half_unknown(n=5))
    with pytest.raises(WonderError, match=r"the guide is 5x32x48 .* but the video is 9x32x48") as e:
        vace.generate(PROMPT, _path(), 0, None, short)
    assert "\n" not in str(e.value)
    bad_mask = Guide(frames=_frames(0), mask=np.zeros((T, H, W), np.uint8), depth=np.ones((T, H, W), np.float32))
    with pytest.raises(WonderError, match=r"guide mask must be \(T,H,W\) bool"):
        vace.generate(PROMPT, _path(), 0, None, bad_mask)
    bad_frames = Guide(frames=_frames(0).astype(np.float32), mask=_right_half_unknown(), depth=np.ones((T, H, W)))
    with pytest.raises(WonderError, match=r"guide frames must be \(T,H,W,3\) uint8"):
        vace.generate(PROMPT, _path(), 0, None, bad_frames)


def test_weights_settings_must_fit_the_family() -> None:
    with pytest.raises(ValidationError, match=r"t2v_model\n.*the wan_vace family has no t2v pipeline; it reads guided"):
        DiffusionParams(family="wan_vace", t2v_model="/x")
    assert DiffusionParams(family="wan", guided_model="/x").guided_model == "/x"  # one block serves both families

    def scene(options: dict[str, object], **video: object) -> object:
        overrides = {"scene": {"video": {"backend": "diffusers", "options": options, **video}}, **PRIORS}
        return build_config("x", preset="preview", overrides=overrides).scene

    with pytest.raises(ConfigError, match=r"scene\.video\.options\.i2v_model: the wan_vace family has no i2v"):
        scene({"family": "wan_vace", "i2v_model": "/x"})
    with pytest.raises(ConfigError, match=r"scene\.video\.options\.conditioning_scale"):
        scene({"family": "wan_vace", "conditioning_scale": -1})
    with pytest.raises(
        ConfigError, match=r"scene\.video\.frames_per_segment: wan_vace renders 4k\+1 .* 20 is not, nearest valid is 21"
    ):
        scene({"family": "wan_vace"}, frames_per_segment=20)
    with pytest.raises(ConfigError, match=r"scene\.video\.height: wan_vace needs a multiple of 16 px"):
        scene({"family": "wan_vace"}, height=200)


def test_make_video_model_builds_the_guided_family(folder: Path) -> None:
    opts = {"family": "wan_vace", "guided_model": str(folder), "steps": 2, "device": "cpu"}
    video = {"backend": "diffusers", "frames_per_segment": T, "width": W, "height": H, "options": opts}
    cfg = build_config("a mountain village", preset="preview", overrides={"scene": {"video": video}, **PRIORS})
    model = make_video_model(cfg.scene.video_source)
    assert isinstance(model, DiffusionVideo) and model.takes_guide
    v = model.generate(PROMPT, _path(), 0, None, _guide(_frames(0), _right_half_unknown()))
    assert v.frames.shape == (T, H, W, 3)

"""No-reference metrics of rendered views: NIQE (numpy, project pristine model), CLIP-S and Q-Align (tiny random
transformers checkpoints written offline by tests/tiny_quality_models.py; their scores mean nothing)."""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError
from scipy.ndimage import gaussian_filter
from scipy.stats import gennorm
from tiny_quality_models import write_tiny_clip, write_tiny_llava  # tests/ is on sys.path (rootdir conftest)

from wonderverse.errors import WonderError
from wonderverse.quality import QualityParams, niqe, niqe_many
from wonderverse.quality.niqe_metric import aggd_fit, pristine_model
from wonderverse.quality.qalign import LEVELS, expand_to_square

# inside the shared data folder (the `data_dir` fixture)
FOX = "instant_ngp_fox/images/0025.jpg"
RE10K = "cameractrl_re10k/reference_videos/0c11dbe781b1c11c.mp4"
GRAY = np.array([0.298936021293775, 0.587043074451121, 0.114020904255103])  # MATLAB rgb2gray
BLUR_PX = (0.0, 1.0, 2.0, 4.0)
NOISE = (5.0, 10.0, 20.0, 40.0)


def gray_of(rgb: np.ndarray) -> np.ndarray:
    return np.round(rgb.astype(np.float64) @ GRAY)


def noisy(g: np.ndarray, sigma: float, seed: int = 0) -> np.ndarray:
    return np.clip(g + np.random.default_rng(seed).normal(0.0, sigma, g.shape), 0, 255)


def strictly_increasing(xs: list[float]) -> bool:
    return all(a < b for a, b in itertools.pairwise(xs))


@pytest.fixture(scope="module")
def fox(data_dir: Path) -> np.ndarray:
    if not (data_dir / FOX).exists():
        pytest.skip(f"real photo {data_dir / FOX} is absent")
    import imageio.v3 as iio

    return gray_of(np.asarray(iio.imread(data_dir / FOX))[..., :3])[300:780, 100:580]  # 480x480 around the fox


@pytest.fixture(scope="module")
def re10k_frame(data_dir: Path) -> np.ndarray:
    if not (data_dir / RE10K).exists():
        pytest.skip(f"real clip {data_dir / RE10K} is absent")
    import imageio.v3 as iio

    return np.asarray(iio.imread(data_dir / RE10K))[7]  # 256x384; odd frames are not in the pristine fit (every 5th is)


@pytest.fixture(scope="module")
def rendered() -> np.ndarray:
    from wonderverse.video.procedural import ProceduralVideo

    v = ProceduralVideo("a quiet village with houses and trees", 3, 288, 192, 60.0, {"fault_probability": 0.0})
    return v.render(v.world.start_pose())[0]


# ---------------------------------------------------------------- NIQE


def test_blur_and_noise_raise_niqe_on_a_real_photo(fox: np.ndarray) -> None:
    blurred = [niqe(gaussian_filter(fox, s) if s else fox) for s in BLUR_PX]
    assert strictly_increasing(blurred), blurred
    noised = [niqe(fox)] + [niqe(noisy(fox, s)) for s in NOISE]
    assert strictly_increasing(noised), noised


def test_blur_and_noise_raise_niqe_on_a_held_out_real_frame(re10k_frame: np.ndarray) -> None:
    g = gray_of(re10k_frame)
    # A 384x256 H.264 frame is already soft and blocky: a 1-pixel blur changes its NIQE by ~1% either way
    # (5.73 -> 5.65 here, it also removes blocking), so the chain starts at sigma 2.
    assert strictly_increasing([niqe(g)] + [niqe(gaussian_filter(g, s)) for s in (2.0, 4.0)])
    # Only 8 blocks: at sigma 20 and 40 the score saturates (58.7 vs 58.3), both far above the clean 5.7.
    noised = [niqe(g)] + [niqe(noisy(g, s)) for s in NOISE]
    assert strictly_increasing(noised[:4]) and noised[4] > 5 * noised[0], noised


def test_blur_and_noise_raise_niqe_on_a_rendered_frame(rendered: np.ndarray) -> None:
    g = gray_of(rendered)
    # The ray-cast frame is aliased (one ray per pixel): a 1-pixel blur acts as anti-aliasing and LOWERS its
    # NIQE, so monotonicity holds from sigma 1 on, and the clean frame still beats the sigma-4 blur.
    blurred = [niqe(gaussian_filter(g, s)) for s in (1.0, 2.0, 4.0)]
    assert strictly_increasing(blurred), blurred
    assert niqe(g) < blurred[-1]
    assert strictly_increasing([niqe(g)] + [niqe(noisy(g, s)) for s in NOISE])


def test_natural_images_score_far_better_than_white_noise(fox: np.ndarray, rendered: np.ndarray) -> None:
    white = np.random.default_rng(1).uniform(0, 255, (480, 480))
    assert 3 * niqe(fox) < niqe(white)
    assert 3 * niqe(rendered) < niqe(white)


def test_rgb_input_is_scored_as_its_matlab_grey(rendered: np.ndarray) -> None:
    g = gray_of(rendered)
    assert niqe(rendered) == pytest.approx(niqe(g), abs=1e-9)
    # A grey image given as three equal channels is that grey image (the weights sum to 1).
    g8 = g.astype(np.uint8)
    assert niqe(np.repeat(g8[..., None], 3, axis=2)) == pytest.approx(niqe(g8.astype(np.float64)), abs=1e-9)


def test_rows_and_columns_past_the_last_whole_block_are_ignored(fox: np.ndarray) -> None:
    # The reference crops to whole 96-pixel blocks BEFORE filtering, so extra pixels change nothing.
    assert niqe(fox[:460, :470]) == pytest.approx(niqe(fox[:384, :384]), abs=1e-9)


def test_a_tiled_copy_scores_close_to_the_original(fox: np.ndarray) -> None:
    # Same blocks four times over: same feature mean and nearly the same covariance (only the seams differ).
    crop = fox[:384, :384]
    a, b = niqe(crop), niqe(np.tile(crop, (2, 2)))
    assert abs(a - b) < 0.1 * a, (a, b)


def test_flat_images_raise_a_clear_error_and_half_flat_ones_are_scored(rendered: np.ndarray) -> None:
    with pytest.raises(ValueError, match="too little texture"):
        niqe(np.full((256, 256), 128.0))
    half = gray_of(rendered)[:192, :288].copy()
    half[:, :96] = 40.0  # one flat column of blocks: their features are NaN and dropped, the rest still score
    assert np.isfinite(niqe(half))


def test_images_under_two_blocks_per_side_are_refused() -> None:
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match="192x192"):
        niqe(rng.uniform(0, 255, (191, 400)))
    with pytest.raises(ValueError, match="192x192"):
        niqe(rng.integers(0, 255, (400, 150, 3), dtype=np.uint8))
    assert np.isfinite(niqe(rng.uniform(0, 255, (192, 192))))
    with pytest.raises(ValueError, match="uint8"):
        niqe(rng.uniform(0, 255, (200, 200, 3)))


def test_niqe_many_is_the_mean_over_frames(rendered: np.ndarray, fox: np.ndarray) -> None:
    assert niqe_many([rendered, fox]) == pytest.approx((niqe(rendered) + niqe(fox)) / 2)
    with pytest.raises(ValueError, match="at least one"):
        niqe_many([])


@pytest.mark.parametrize(("alpha", "left", "right"), [(2.0, 1.0, 1.0), (0.8, 1.0, 1.0), (1.4, 0.5, 1.5)])
def test_aggd_fit_recovers_the_parameters_of_sampled_data(alpha: float, left: float, right: float) -> None:
    # AGGD samples: the left side (scale `left`) carries mass left / (left + right), the right side the rest.
    rng = np.random.default_rng(3)
    size = np.abs(gennorm.rvs(alpha, size=(4, 200_000), random_state=rng))
    x = np.where(rng.uniform(size=size.shape) < left / (left + right), -left * size, right * size)
    a, bl, br = aggd_fit(x)
    assert np.allclose(a, alpha, rtol=0.05), a
    assert np.allclose(bl, left, rtol=0.05) and np.allclose(br, right, rtol=0.05), (bl, br)


def test_pristine_model_is_a_valid_gaussian_from_real_captures_only() -> None:
    mean, cov = pristine_model()
    assert mean.shape == (36,) and cov.shape == (36, 36) and np.isfinite(cov).all()
    assert np.allclose(cov, cov.T) and np.linalg.eigvalsh(cov).min() > -1e-9
    from importlib import resources

    with resources.files("wonderverse").joinpath("data", "niqe_pristine.npz").open("rb") as f, np.load(f) as z:
        meta = json.loads(str(z["metadata"]))
    assert set(meta["sources"]) <= {"instant_ngp_fox", "viewcrafter_re10k_bedroom", "cameractrl_re10k"}
    assert meta["n_blocks"] > 10 * 36  # many more blocks than features: a full-rank covariance


# ---------------------------------------------------------------- CLIP-S and Q-Align on tiny random models


@pytest.fixture(scope="module")
def models(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("tiny_quality")
    return {
        "clip": write_tiny_clip(root / "clip", seed=1),  # seed 1: positive cosines for these texts
        "clip_mixed": write_tiny_clip(root / "clip_mixed", seed=2),  # seed 2: some negative cosines
        "llava": write_tiny_llava(root / "llava"),
    }


@pytest.fixture(scope="module")
def images() -> np.ndarray:
    return np.random.default_rng(5).integers(0, 256, (5, 40, 56, 3), dtype=np.uint8)


TEXTS = ["a photo of a cat", "a dog", "a house with a tree", "a quiet village", "a room"]


def independent_clip_s(path: Path, images: np.ndarray, texts: list[str]) -> np.ndarray:
    """2.5 max(cos, 0) through the model's get_*_features, one pair at a time (not the scorer's code path)."""
    import torch
    from PIL import Image
    from transformers import AutoProcessor, CLIPModel

    model, proc = CLIPModel.from_pretrained(path).eval(), AutoProcessor.from_pretrained(path)
    out = []
    for im, t in zip(images, texts, strict=True):
        with torch.no_grad():
            f_i = model.get_image_features(**proc(images=[Image.fromarray(im)], return_tensors="pt"))
            f_t = model.get_text_features(**proc(text=[t], return_tensors="pt"))
        f_i, f_t = (getattr(f, "pooler_output", f)[0].double() for f in (f_i, f_t))
        out.append(2.5 * max(float(f_i @ f_t / (f_i.norm() * f_t.norm())), 0.0))
    return np.array(out)


def test_clip_s_is_hessels_definition_per_pair(models: dict[str, Path], images: np.ndarray) -> None:
    from wonderverse.quality import ClipScorer

    for name in ("clip", "clip_mixed"):
        s = ClipScorer(models[name], device="cpu").score(images, TEXTS)
        assert s.shape == (5,) and ((s >= 0) & (s <= 2.5)).all()
        assert np.allclose(s, independent_clip_s(models[name], images, TEXTS), atol=1e-5)
    mixed = ClipScorer(models["clip_mixed"], device="cpu").score(images, TEXTS)
    assert (mixed == 0).any() and (mixed > 0).any()  # the clamp at 0 is exercised


def test_clip_s_is_deterministic_batch_independent_and_text_dependent(
    models: dict[str, Path], images: np.ndarray
) -> None:
    from wonderverse.quality import ClipScorer

    batched = ClipScorer(models["clip"], device="cpu", batch_size=8)
    single = ClipScorer(models["clip"], device="cpu", batch_size=1)
    a = batched.score(images, TEXTS)
    assert np.array_equal(a, batched.score(images, TEXTS))
    assert np.allclose(a, single.score(images, TEXTS), atol=1e-5)
    cat, village = batched.score(images, "a photo of a cat"), batched.score(images, "a quiet village")
    assert np.abs(cat - village).min() > 1e-4
    long_text = " ".join(["a quiet village with a house and a tree"] * 40)  # > 77 tokens: truncated, not an error
    assert np.isfinite(batched.score(images[:1], long_text)).all()
    with pytest.raises(ValueError, match="5 images but 2 texts"):
        batched.score(images, TEXTS[:2])


def test_q_align_reads_the_five_level_words_and_weights_them(models: dict[str, Path], images: np.ndarray) -> None:
    from wonderverse.quality import QAlignScorer

    q = QAlignScorer(models["llava"], device="cpu", scale="unit")
    assert q.processor.tokenizer.convert_ids_to_tokens(q.level_ids) == list(LEVELS)
    p = q.level_probabilities(images)
    assert p.shape == (5, 5) and np.allclose(p.sum(1), 1.0) and (p > 0).all()
    unit = q.score(images)
    assert unit.shape == (5,) and ((unit >= 0) & (unit <= 1)).all()
    assert np.allclose(unit, p @ [1.0, 0.75, 0.5, 0.25, 0.0])
    five = QAlignScorer(models["llava"], device="cpu").score(images)  # default: the paper's 1..5 scale
    assert np.allclose(five, 1 + 4 * unit, atol=1e-6) and ((five >= 1) & (five <= 5)).all()
    assert np.array_equal(unit, q.score(images))
    one_by_one = QAlignScorer(models["llava"], device="cpu", scale="unit", batch_size=1).score(images)
    assert np.allclose(unit, one_by_one, atol=1e-5)


def test_q_align_follows_constructed_level_logits(models: dict[str, Path], images: np.ndarray) -> None:
    import torch

    from wonderverse.quality import QAlignScorer

    q = QAlignScorer(models["llava"], device="cpu", scale="unit")
    before = q.score(images)
    head = q.model.lm_head.weight
    ids = q.level_ids
    with torch.no_grad():
        # Swapping excellent<->bad and good<->poor mirrors the weights: the score must become 1 - score.
        head[[ids[0], ids[4], ids[1], ids[3]]] = head[[ids[4], ids[0], ids[3], ids[1]]].clone()
        assert np.allclose(q.score(images), 1 - before, atol=1e-6)
        # Equal rows for the five words: equal logits, uniform over the five, whatever the rest of the vocabulary.
        head[ids] = head[ids[2]].clone()
        assert np.allclose(q.level_probabilities(images), 0.2) and np.allclose(q.score(images), 0.5)


def test_images_are_padded_to_a_square_with_the_mean_colour() -> None:
    img = np.full((2, 4, 3), 200, dtype=np.uint8)
    sq = expand_to_square(img, np.array([10.0, 20.0, 30.0]))
    assert sq.shape == (4, 4, 3)
    assert (sq[1:3] == 200).all() and (sq[0] == [10, 20, 30]).all() and (sq[3] == [10, 20, 30]).all()


def test_missing_model_folders_and_bad_settings_are_user_errors(tmp_path: Path) -> None:
    from wonderverse.quality import ClipScorer, QAlignScorer

    with pytest.raises(WonderError, match="not a directory"):
        ClipScorer(tmp_path / "absent")
    with pytest.raises(WonderError, match="could not be loaded"):
        QAlignScorer(tmp_path)  # an empty folder: nothing to load, and nothing is downloaded
    assert QualityParams().clip_model is None and QualityParams().qalign_scale == "five_point"
    with pytest.raises(ValidationError):
        QualityParams(clip_weight=0)
    with pytest.raises(ValidationError):
        QualityParams(niqe_model="x")  # extra fields are refused


def test_score_views_gathers_the_configured_metrics(models: dict[str, Path], rendered: np.ndarray) -> None:
    """What the outputs step stores: NIQE always (None under two blocks per side), CLIP-S against the prompt and
    Q-Align only with weights."""
    from wonderverse.quality import ClipScorer, score_views

    frames = [rendered, np.ascontiguousarray(rendered[:, ::-1])]
    bare = score_views(frames, "a quiet village", QualityParams())
    assert bare == {"niqe": pytest.approx(niqe_many(frames)), "clip_s": None, "q_align": None}
    assert score_views([rendered[:150]], "x", QualityParams())["niqe"] is None  # 150 rows < 2 x 96

    params = QualityParams(clip_model=str(models["clip"]), qalign_model=str(models["llava"]), device="cpu")
    full = score_views(frames, "a quiet village", params)
    clip = ClipScorer(models["clip"], device="cpu").score(frames, ["a quiet village"] * 2)
    assert full["clip_s"] == pytest.approx(float(np.mean(clip)))
    assert 1.0 <= full["q_align"] <= 5.0 and full["niqe"] == bare["niqe"]

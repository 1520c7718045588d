"""Tiny, randomly initialised diffusers video pipelines, saved with `save_pretrained` for offline tests.

Every component is a real diffusers/transformers class (CogVideoX, Wan, Wan VACE) with a few layers and a few
channels, so a CPU run of a couple of denoising steps takes well under a second. The tokenizer is a
byte-level BPE trained here on a few sentences (no sentencepiece file can be downloaded), wrapped in
`PreTrainedTokenizerFast`; it can encode any text, so different prompts give different token ids.
The weights are random: the frames are noise-like, only shapes, determinism and conditioning are testable.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

SEED = 0
TEXT_DIM = 32
# CogVideoX transformers size their text positions to this; the pipelines pad prompts to it.
COGVIDEOX_TEXT_TOKENS = 226
_CORPUS = [
    "aerial shot, soft lighting, around left, realistic, high-quality, displaying a mountain village.",
    "aerial shot, soft lighting, around right, realistic, high-quality, displaying a coastal city at dusk.",
    "a quiet forest lake, green trees, blue water, a wooden pier and distant snowy peaks",
]


def tiny_tokenizer() -> Any:
    """A T5-like fast tokenizer (pad id 0, `</s>` appended) built offline from a byte-level BPE."""
    from tokenizers import Tokenizer, decoders, models, pre_tokenizers, processors, trainers
    from transformers import PreTrainedTokenizerFast

    tok = Tokenizer(models.BPE(unk_token="<unk>"))
    tok.pre_tokenizer = pre_tokenizers.ByteLevel(add_prefix_space=False)
    tok.decoder = decoders.ByteLevel()
    trainer = trainers.BpeTrainer(
        vocab_size=320,
        special_tokens=["<pad>", "</s>", "<unk>"],
        initial_alphabet=pre_tokenizers.ByteLevel.alphabet(),
        show_progress=False,
    )
    tok.train_from_iterator(_CORPUS, trainer=trainer)
    eos = tok.token_to_id("</s>")
    tok.post_processor = processors.TemplateProcessing(single="$A </s>", special_tokens=[("</s>", eos)])
    return PreTrainedTokenizerFast(
        tokenizer_object=tok, pad_token="<pad>", eos_token="</s>", unk_token="<unk>", model_max_length=512
    )


def _t5_encoder(vocab_size: int, umt5: bool) -> Any:
    import torch
    from transformers import T5Config, T5EncoderModel, UMT5Config, UMT5EncoderModel

    torch.manual_seed(SEED)
    kw = dict(vocab_size=vocab_size, d_model=TEXT_DIM, d_kv=8, d_ff=37, num_layers=2, num_heads=4)
    if umt5:
        return UMT5EncoderModel(UMT5Config(**kw)).eval()
    return T5EncoderModel(T5Config(**kw)).eval()


def cogvideox_components(image_to_video: bool) -> dict[str, Any]:
    """Components of a tiny CogVideoX (1.0-style: sin-cos positions, DDIM): VAE 8x spatial, 4x temporal."""
    import torch
    from diffusers import AutoencoderKLCogVideoX, CogVideoXDDIMScheduler, CogVideoXTransformer3DModel

    tokenizer = tiny_tokenizer()
    text_encoder = _t5_encoder(len(tokenizer), umt5=False)
    torch.manual_seed(SEED)
    latent = 4
    transformer = CogVideoXTransformer3DModel(
        num_attention_heads=2,
        attention_head_dim=8,
        # the image-to-video transformer sees the noisy latents and the reference's latents stacked
        in_channels=2 * latent if image_to_video else latent,
        out_channels=latent,
        time_embed_dim=4,
        text_embed_dim=TEXT_DIM,
        num_layers=1,
        sample_width=8,
        sample_height=8,
        sample_frames=9,
        patch_size=2,
        temporal_compression_ratio=4,
        max_text_seq_length=COGVIDEOX_TEXT_TOKENS,
    ).eval()
    torch.manual_seed(SEED)
    vae = AutoencoderKLCogVideoX(
        down_block_types=("CogVideoXDownBlock3D",) * 4,
        up_block_types=("CogVideoXUpBlock3D",) * 4,
        block_out_channels=(8, 8, 8, 8),
        latent_channels=latent,
        layers_per_block=1,
        norm_num_groups=2,
        temporal_compression_ratio=4,
    ).eval()
    scheduler = CogVideoXDDIMScheduler()
    return dict(tokenizer=tokenizer, text_encoder=text_encoder, vae=vae, transformer=transformer, scheduler=scheduler)


def wan_components(image_to_video: bool) -> dict[str, Any]:
    """Components of a tiny Wan (2.2-style image-to-video: no CLIP image encoder, 36 input channels)."""
    import torch
    from diffusers import AutoencoderKLWan, FlowMatchEulerDiscreteScheduler, WanTransformer3DModel

    tokenizer = tiny_tokenizer()
    text_encoder = _t5_encoder(len(tokenizer), umt5=True)
    torch.manual_seed(SEED)
    z = 16  # AutoencoderKLWan's latent statistics have 16 entries
    transformer = WanTransformer3DModel(
        patch_size=(1, 2, 2),
        num_attention_heads=2,
        attention_head_dim=12,
        # image-to-video: noisy latents + 4 mask channels + the reference's latents
        in_channels=2 * z + 4 if image_to_video else z,
        out_channels=z,
        text_dim=TEXT_DIM,
        freq_dim=32,
        ffn_dim=32,
        num_layers=1,
        rope_max_seq_len=32,
    ).eval()
    torch.manual_seed(SEED)
    vae = AutoencoderKLWan(
        base_dim=4, z_dim=z, dim_mult=[1, 1, 1, 1], num_res_blocks=1, temperal_downsample=[False, True, True]
    ).eval()
    scheduler = FlowMatchEulerDiscreteScheduler(shift=3.0)
    return dict(tokenizer=tokenizer, text_encoder=text_encoder, vae=vae, transformer=transformer, scheduler=scheduler)


def wan_vace_components() -> dict[str, Any]:
    """Components of a tiny Wan 2.1 VACE: the tiny Wan VAE and text encoder, and a one-layer VACE transformer whose
    control branch reads 96 channels per latent pixel (the known and unknown parts' latents, 2 x 16, and the mask
    folded from the VAE's 8x8 pixel cells, 64)."""
    import torch
    from diffusers import AutoencoderKLWan, WanVACETransformer3DModel

    parts = wan_components(image_to_video=False)
    z = 16
    # the same tiny VAE, with latent statistics measured on it (mean ~0, std ~0.1 for inputs in [-1, 1]) instead of
    # the real Wan VAE's: normalised by the real ones, the encoded guide frames would barely vary with their pixels
    torch.manual_seed(SEED)
    parts["vae"] = AutoencoderKLWan(
        base_dim=4,
        z_dim=z,
        dim_mult=[1, 1, 1, 1],
        num_res_blocks=1,
        temperal_downsample=[False, True, True],
        latents_mean=[0.0] * z,
        latents_std=[0.1] * z,
    ).eval()
    torch.manual_seed(SEED)
    parts["transformer"] = WanVACETransformer3DModel(
        patch_size=(1, 2, 2),
        num_attention_heads=2,
        attention_head_dim=12,
        in_channels=z,
        out_channels=z,
        text_dim=TEXT_DIM,
        freq_dim=32,
        ffn_dim=32,
        num_layers=1,
        rope_max_seq_len=32,
        vace_layers=[0],
        vace_in_channels=2 * z + 8 * 8,
    ).eval()
    return parts


# the modes each family's tiny pipelines are saved for (folder `<family>-<mode>`)
FAMILY_MODES: dict[str, tuple[str, ...]] = {"cogvideox": ("t2v", "i2v"), "wan": ("t2v", "i2v"), "wan_vace": ("guided",)}


def plain_wan_as_guided(folder: Path, prompt: str) -> dict[str, Any]:
    """A run config asking the `wan_vace` family of weights that are a plain Wan text-to-video pipeline (it takes
    no mask), saved to `folder`: a guided run with it must stop with one error line."""
    from diffusers import WanPipeline

    WanPipeline(**wan_components(False)).save_pretrained(folder)
    options = {"family": "wan_vace", "guided_model": str(folder), "steps": 2, "device": "cpu"}
    video = {"backend": "diffusers", "width": 48, "height": 32, "frames_per_segment": 9, "options": options}
    return {
        "preset": "preview",
        "scene": {"prompt": prompt, "video": video},
        "steps": {"priors": {"models": {"depth_backend": "depth_anything"}}},
    }


def save_tiny_pipelines(root: Path, families: tuple[str, ...] = ("cogvideox", "wan")) -> dict[str, dict[str, Path]]:
    """Save each family's pipelines under `root`: text-to-video and image-to-video for cogvideox and wan, the
    guided pipeline for wan_vace.

    Returns {family: {mode: folder}} (modes as in FAMILY_MODES); each folder loads with `from_pretrained`.
    """
    from diffusers import (
        CogVideoXImageToVideoPipeline,
        CogVideoXPipeline,
        WanImageToVideoPipeline,
        WanPipeline,
        WanVACEPipeline,
    )

    builders: dict[str, dict[str, tuple[Any, Any]]] = {
        "cogvideox": {
            "t2v": (lambda: cogvideox_components(False), CogVideoXPipeline),
            "i2v": (lambda: cogvideox_components(True), CogVideoXImageToVideoPipeline),
        },
        "wan": {
            "t2v": (lambda: wan_components(False), WanPipeline),
            "i2v": (lambda: wan_components(True), WanImageToVideoPipeline),
        },
        "wan_vace": {"guided": (wan_vace_components, WanVACEPipeline)},
    }
    out: dict[str, dict[str, Path]] = {}
    for family in families:
        out[family] = {}
        for mode in FAMILY_MODES[family]:
            build, cls = builders[family][mode]
            folder = Path(root) / f"{family}-{mode}"
            cls(**build()).save_pretrained(folder)
            out[family][mode] = folder
    return out


if __name__ == "__main__":
    import sys

    print(save_tiny_pipelines(Path(sys.argv[1] if len(sys.argv) > 1 else "tiny-pipelines")))

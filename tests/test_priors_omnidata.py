"""Omnidata DPT-hybrid normal backend: a tiny randomly initialised transformers DPT-hybrid is written out
under the ORIGINAL (isl-org DPT / Omnidata) parameter names, as a bare state dict and as a Lightning
checkpoint, and loaded back through the user's code path."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pytest

from wonderverse.camera import intrinsics
from wonderverse.errors import WonderError
from wonderverse.priors import PriorsParams, make_normal_model

torch = pytest.importorskip("torch")
pytest.importorskip("transformers")

from wonderverse.priors.omnidata import (  # noqa: E402
    OmnidataNormals,
    config_from_state_dict,
    network_size,
    omnidata_to_transformers,
)

N_LAYERS = 4
DEPTHS = (1, 2, 1)


def tiny_transformers_dpt(seed: int = 0, head_bias: tuple[float, float, float] | None = None):
    """A ~1.7M-parameter DPT-hybrid (BiT stem + 4-block ViT) with a 3-channel head, in transformers."""
    from torch import nn
    from transformers import BitConfig, DPTConfig, DPTForDepthEstimation

    bit = BitConfig(
        embedding_size=32,
        hidden_sizes=[128, 256, 512, 1024],
        depths=list(DEPTHS),
        layer_type="bottleneck",
        global_padding="same",
        embedding_dynamic_padding=True,
        out_features=["stage1", "stage2", "stage3"],
    )
    cfg = DPTConfig(
        is_hybrid=True,
        backbone_config=bit,
        hidden_size=64,
        num_hidden_layers=N_LAYERS,
        num_attention_heads=1,
        intermediate_size=128,
        image_size=64,
        patch_size=16,
        backbone_out_indices=[0, 1, 2, 3],
        backbone_featmap_shape=[1, 512, 4, 4],
        neck_hidden_sizes=[128, 256, 64, 64],
        reassemble_factors=[1, 1, 1, 0.5],
        fusion_hidden_size=64,
        layer_norm_eps=1e-6,
    )
    torch.manual_seed(seed)
    model = DPTForDepthEstimation(cfg).eval()
    model.head.head[4] = nn.Conv2d(32, 3, kernel_size=1)
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.02 * torch.randn_like(p))
        if head_bias is not None:  # a constant prediction: the last conv sees nothing, only its bias
            model.head.head[4].weight.zero_()
            model.head.head[4].bias.copy_(torch.tensor(head_bias))
        else:
            model.head.head[4].bias.fill_(0.5)  # keep the ReLU of the head from zeroing everything
    return model


def to_original_names(model) -> dict[str, torch.Tensor]:
    """The state dict Omnidata's DPTDepthModel(backbone="vitb_rn50_384", num_channels=3) would hold.

    Written from the original modules (timm ViT hybrid + ResNetV2 stem, DPT act_postprocess/scratch),
    independently of the library's renaming table.
    """
    sd = {k: v.clone() for k, v in model.state_dict().items()}
    out: dict[str, torch.Tensor] = {}

    def take(src: str, dst: str) -> None:
        out[dst] = sd.pop(src)

    e = "dpt.embeddings."
    take(e + "cls_token", "pretrained.model.cls_token")
    take(e + "position_embeddings", "pretrained.model.pos_embed")
    take(e + "projection.weight", "pretrained.model.patch_embed.proj.weight")
    take(e + "projection.bias", "pretrained.model.patch_embed.proj.bias")
    rn = "pretrained.model.patch_embed.backbone."
    take(e + "backbone.bit.embedder.convolution.weight", rn + "stem.conv.weight")
    for p in ("weight", "bias"):
        take(e + f"backbone.bit.embedder.norm.{p}", rn + f"stem.norm.{p}")
    for s, depth in enumerate(DEPTHS):
        for b in range(depth):
            src = e + f"backbone.bit.encoder.stages.{s}.layers.{b}."
            dst = rn + f"stages.{s}.blocks.{b}."
            for part in ("conv1", "conv2", "conv3", "downsample.conv"):
                if src + part + ".weight" in sd:
                    take(src + part + ".weight", dst + part + ".weight")
            for part in ("norm1", "norm2", "norm3", "downsample.norm"):
                for p in ("weight", "bias"):
                    if src + f"{part}.{p}" in sd:
                        take(src + f"{part}.{p}", dst + f"{part}.{p}")
    for i in range(N_LAYERS):
        src, dst = f"dpt.encoder.layer.{i}.", f"pretrained.model.blocks.{i}."
        for p in ("weight", "bias"):
            take(src + f"layernorm_before.{p}", dst + f"norm1.{p}")
            take(src + f"layernorm_after.{p}", dst + f"norm2.{p}")
            qkv = [sd.pop(src + f"attention.attention.{n}.{p}") for n in ("query", "key", "value")]
            out[dst + f"attn.qkv.{p}"] = torch.cat(qkv, dim=0)  # timm's fused layout: q, k, v rows
            take(src + f"attention.output.dense.{p}", dst + f"attn.proj.{p}")
            take(src + f"intermediate.dense.{p}", dst + f"mlp.fc1.{p}")
            take(src + f"output.dense.{p}", dst + f"mlp.fc2.{p}")
    for p in ("weight", "bias"):
        take(f"dpt.layernorm.{p}", f"pretrained.model.norm.{p}")
        # hybrid: act_postprocess1/2 are identities; 3 and 4 have readout [0], 1x1 conv [3], 4 also resize [4]
        take(f"neck.reassemble_stage.readout_projects.2.0.{p}", f"pretrained.act_postprocess3.0.project.0.{p}")
        take(f"neck.reassemble_stage.readout_projects.3.0.{p}", f"pretrained.act_postprocess4.0.project.0.{p}")
        take(f"neck.reassemble_stage.layers.2.projection.{p}", f"pretrained.act_postprocess3.3.{p}")
        take(f"neck.reassemble_stage.layers.3.projection.{p}", f"pretrained.act_postprocess4.3.{p}")
        take(f"neck.reassemble_stage.layers.3.resize.{p}", f"pretrained.act_postprocess4.4.{p}")
        for i in (0, 2, 4):
            take(f"head.head.{i}.{p}", f"scratch.output_conv.{i}.{p}")
    for k in range(1, 5):
        take(f"neck.convs.{k - 1}.weight", f"scratch.layer{k}_rn.weight")
        layer = f"neck.fusion_stage.layers.{4 - k}."  # refinenet4 runs first
        for p in ("weight", "bias"):
            take(layer + f"projection.{p}", f"scratch.refinenet{k}.out_conv.{p}")
            for j in (1, 2):
                for c in (1, 2):
                    take(
                        layer + f"residual_layer{j}.convolution{c}.{p}",
                        f"scratch.refinenet{k}.resConfUnit{j}.conv{c}.{p}",
                    )
    assert not sd, f"unexported parameters: {list(sd)[:5]}"
    # timm's ImageNet classifier is in the original checkpoints and unused by DPT
    out["pretrained.model.head.weight"] = torch.zeros(1000, 64)
    out["pretrained.model.head.bias"] = torch.zeros(1000)
    return out


@pytest.fixture(scope="module")
def tiny(tmp_path_factory: pytest.TempPathFactory):
    model = tiny_transformers_dpt()
    d = tmp_path_factory.mktemp("omnidata")
    bare = d / "omnidata_normal_dpt_hybrid.pth"
    torch.save(to_original_names(model), bare)
    lightning = d / "omnidata_dpt_normal_v2.ckpt"
    torch.save({"state_dict": {"model." + k: v for k, v in to_original_names(model).items()}, "epoch": 7}, lightning)
    return model, bare, lightning


def params(path: Path, **kw) -> PriorsParams:
    return PriorsParams(
        **{"normal_backend": "dpt", "normal_model": str(path), "normal_input_size_px": 64, "device": "cpu", **kw}
    )


def test_renaming_matches_the_reference_conversion() -> None:
    """Anchors from transformers' own DPT-hybrid conversion script (convert_dpt_hybrid_to_pytorch.py)."""
    sd = to_original_names(tiny_transformers_dpt())
    conv = omnidata_to_transformers(sd)
    pairs = {
        "scratch.refinenet4.out_conv.weight": "neck.fusion_stage.layers.0.projection.weight",
        "scratch.refinenet1.resConfUnit2.conv1.bias": "neck.fusion_stage.layers.3.residual_layer2.convolution1.bias",
        "scratch.layer3_rn.weight": "neck.convs.2.weight",
        "pretrained.act_postprocess4.4.weight": "neck.reassemble_stage.layers.3.resize.weight",
        "pretrained.act_postprocess3.0.project.0.weight": "neck.reassemble_stage.readout_projects.2.0.weight",
        "pretrained.model.patch_embed.backbone.stem.conv.weight": (
            "dpt.embeddings.backbone.bit.embedder.convolution.weight"
        ),
        "pretrained.model.patch_embed.backbone.stages.1.blocks.0.downsample.conv.weight": (
            "dpt.embeddings.backbone.bit.encoder.stages.1.layers.0.downsample.conv.weight"
        ),
        "pretrained.model.blocks.3.mlp.fc2.weight": "dpt.encoder.layer.3.output.dense.weight",
        "scratch.output_conv.4.bias": "head.head.4.bias",
    }
    for orig, new in pairs.items():
        assert torch.equal(conv[new], sd[orig]), (orig, new)
    qkv = sd["pretrained.model.blocks.2.attn.qkv.weight"]
    assert torch.equal(conv["dpt.encoder.layer.2.attention.attention.query.weight"], qkv[:64])
    assert torch.equal(conv["dpt.encoder.layer.2.attention.attention.value.weight"], qkv[128:])
    assert not any(k.startswith("pretrained.") or k.startswith("scratch.") for k in conv)


def test_config_is_read_off_the_tensors() -> None:
    cfg = config_from_state_dict(to_original_names(tiny_transformers_dpt()))
    assert cfg.is_hybrid and cfg.hidden_size == 64 and cfg.num_hidden_layers == N_LAYERS
    assert cfg.num_attention_heads == 1 and cfg.image_size == 64
    assert list(cfg.backbone_config.depths) == list(DEPTHS)
    assert list(cfg.neck_hidden_sizes) == [128, 256, 64, 64] and cfg.fusion_hidden_size == 64
    assert list(cfg.backbone_out_indices)[2:] == [2, 3]


@pytest.mark.parametrize("which", ["bare", "lightning"])
def test_loaded_network_reproduces_the_original(tiny, which: str) -> None:
    model, bare, lightning = tiny
    net = make_normal_model(params(bare if which == "bare" else lightning))
    assert isinstance(net, OmnidataNormals)
    x = torch.rand(2, 3, 64, 64, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        expected = model(pixel_values=x).predicted_depth  # transformers' own forward (square input only)
    got = net.raw(x)
    assert got.shape == (2, 3, 64, 64)
    torch.testing.assert_close(got, expected, rtol=1e-5, atol=1e-6)
    assert expected.std() > 1e-3  # the comparison is not between two constant maps


def test_predict_shapes_units_orientation_batching(tiny) -> None:
    _, bare, _ = tiny
    rng = np.random.default_rng(0)
    frames = np.repeat(np.repeat(rng.integers(0, 256, (3, 10, 15, 3)), 4, 1), 4, 2).astype(np.uint8)
    K = intrinsics(60, 40, 60.0)
    net = make_normal_model(params(bare, batch_size=3))
    pred = net.predict(frames, K=K)
    n = pred.normals
    assert n.shape == (3, 40, 60, 3) and n.dtype == np.float32 and pred.confidence is None
    assert np.isfinite(n).all()
    np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1.0, atol=1e-5)
    u, v = np.meshgrid(np.arange(60) + 0.5, np.arange(40) + 0.5)
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    assert ((n * rays).sum(-1) <= 1e-6).all()
    singles = np.concatenate(
        [make_normal_model(params(bare, batch_size=1)).predict(frames[i : i + 1], K=K).normals for i in range(3)]
    )
    np.testing.assert_allclose(n, singles, atol=1e-4)  # float32 batched vs single convolutions
    np.testing.assert_array_equal(net.predict(frames, K=K).normals, n)
    assert network_size(40, 60, 64) == (64, 96)


def test_output_decoding_and_axes(tmp_path: Path) -> None:
    # Constant network output c = (0.8, 0.5, 0.1) encodes n = 2c - 1 = (0.6, 0, -0.8) in the checkpoint's axes.
    path = tmp_path / "const.pth"
    torch.save(to_original_names(tiny_transformers_dpt(head_bias=(0.8, 0.5, 0.1))), path)
    frames = np.full((1, 32, 32, 3), 128, dtype=np.uint8)
    K = intrinsics(32, 32, 60.0)
    centre = (16, 16)
    as_cv = make_normal_model(params(path, normal_output_axes="opencv")).predict(frames, K=K).normals[0]
    np.testing.assert_allclose(as_cv[centre], [0.6, 0.0, -0.8], atol=1e-4)  # already faces the camera
    as_gl = make_normal_model(params(path, normal_output_axes="opengl")).predict(frames, K=K).normals[0]
    # OpenGL (x, y up, z to viewer) -> OpenCV (0.6, 0, 0.8), which faces away: flipped to (-0.6, 0, -0.8)
    np.testing.assert_allclose(as_gl[centre], [-0.6, 0.0, -0.8], atol=1e-4)


def test_checkpoint_errors(tmp_path: Path, tiny) -> None:
    with pytest.raises(WonderError, match="normal_model"):
        make_normal_model(PriorsParams(normal_backend="dpt", device="cpu"))
    with pytest.raises(WonderError, match="does not exist"):
        make_normal_model(params(tmp_path / "missing.ckpt"))
    _, bare, _ = tiny
    sd = torch.load(bare, weights_only=True)
    sd["decoder.something.weight"] = torch.zeros(3)
    torch.save(sd, tmp_path / "odd.pth")
    with pytest.raises(WonderError, match="not those of an Omnidata"):
        make_normal_model(params(tmp_path / "odd.pth"))
    # A Lightning checkpoint that pickles objects: refused unless the user trusts it.
    pickled = tmp_path / "pickled.ckpt"
    sd = torch.load(bare, weights_only=True)
    torch.save({"state_dict": {"model." + k: v for k, v in sd.items()}, "hparams": argparse.Namespace(lr=1)}, pickled)
    with pytest.raises(WonderError, match="allow_unsafe_pickle"):
        make_normal_model(params(pickled))
    assert isinstance(make_normal_model(params(pickled, allow_unsafe_pickle=True)), OmnidataNormals)


@pytest.mark.gpu
def test_cuda_fp16_matches_cpu(tiny) -> None:
    if not torch.cuda.is_available():
        pytest.skip("no CUDA device")
    _, bare, _ = tiny
    rng = np.random.default_rng(1)
    frames = np.repeat(np.repeat(rng.integers(0, 256, (4, 10, 15, 3)), 4, 1), 4, 2).astype(np.uint8)
    K = intrinsics(60, 40, 60.0)
    cpu = make_normal_model(params(bare)).predict(frames, K=K).normals
    gpu_model = make_normal_model(params(bare, device="cuda", fp16=True, batch_size=2))
    assert next(gpu_model.model.parameters()).dtype == torch.float16
    gpu = gpu_model.predict(frames, K=K).normals
    assert gpu.dtype == np.float32 and np.isfinite(gpu).all()
    cos = np.clip((gpu * cpu).sum(-1), -1.0, 1.0)
    assert np.degrees(np.arccos(cos)).mean() < 1.0

"""Omnidata DPT-hybrid surface normals (the paper's normal prior) on transformers' DPT implementation.

The checkpoint is the plain torch state dict of Omnidata's `DPTDepthModel(backbone="vitb_rn50_384",
num_channels=3)` (isl-org DPT code: timm ViT-B/16 on a ResNet-50 (BiT) stem, 4 fusion blocks, a 3-channel
head): `omnidata_dpt_normal_v2.ckpt` (a Lightning checkpoint, keys under "state_dict" with a "model."
prefix) or its re-upload `omnidata_normal_dpt_hybrid.pth` (the bare state dict). Keys are renamed onto
`transformers.DPTForDepthEstimation` with `is_hybrid=True` and the head's last conv widened to 3 outputs;
the architecture (widths, depths, number of blocks) is read off the tensors, so smaller or larger
variants of the same family load too. The network takes RGB in [0,1] and predicts (n+1)/2 per channel.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from wonderverse.errors import WonderError
from wonderverse.priors.base import NormalPrediction, check_frames
from wonderverse.priors.from_depth import orient_towards_camera
from wonderverse.priors.params import PriorsParams
from wonderverse.priors.runtime import resolve_device

WHAT = "Omnidata DPT normal checkpoint"
# Every input side is a multiple of this: the BiT stem and the ViT patches have stride 16, and the last
# reassemble stage halves once more, so the fusion blocks line up exactly (as in the original code).
SIDE_MULTIPLE_PX = 32
# timm ViT-B/L heads are 64 wide; the head count cannot be read off the tensors.
HEAD_DIM = 64

# Original (isl-org DPT / Omnidata) name -> transformers DPT-hybrid name, first match wins.
_RENAMES: list[tuple[str, str]] = [
    (r"^pretrained\.model\.cls_token$", "dpt.embeddings.cls_token"),
    (r"^pretrained\.model\.pos_embed$", "dpt.embeddings.position_embeddings"),
    (r"^pretrained\.model\.patch_embed\.proj\.", "dpt.embeddings.projection."),
    (r"^pretrained\.model\.patch_embed\.backbone\.stem\.conv\.", "dpt.embeddings.backbone.bit.embedder.convolution."),
    (r"^pretrained\.model\.patch_embed\.backbone\.stem\.norm\.", "dpt.embeddings.backbone.bit.embedder.norm."),
    (
        r"^pretrained\.model\.patch_embed\.backbone\.stages\.(\d+)\.blocks\.(\d+)\.",
        r"dpt.embeddings.backbone.bit.encoder.stages.\1.layers.\2.",
    ),
    (r"^pretrained\.model\.blocks\.(\d+)\.norm1\.", r"dpt.encoder.layer.\1.layernorm_before."),
    (r"^pretrained\.model\.blocks\.(\d+)\.norm2\.", r"dpt.encoder.layer.\1.layernorm_after."),
    (r"^pretrained\.model\.blocks\.(\d+)\.attn\.proj\.", r"dpt.encoder.layer.\1.attention.output.dense."),
    (r"^pretrained\.model\.blocks\.(\d+)\.mlp\.fc1\.", r"dpt.encoder.layer.\1.intermediate.dense."),
    (r"^pretrained\.model\.blocks\.(\d+)\.mlp\.fc2\.", r"dpt.encoder.layer.\1.output.dense."),
    (r"^pretrained\.model\.norm\.", "dpt.layernorm."),
    # act_postprocessN (N = 3, 4): [0] readout projection, [3] 1x1 projection, [4] stride-2 resize (N = 4).
    (r"^pretrained\.act_postprocess([34])\.0\.project\.0\.", r"neck.reassemble_stage.readout_projects.<\1>.0."),
    (r"^pretrained\.act_postprocess([34])\.3\.", r"neck.reassemble_stage.layers.<\1>.projection."),
    (r"^pretrained\.act_postprocess4\.4\.", "neck.reassemble_stage.layers.3.resize."),
    (r"^scratch\.layer([1-4])_rn\.", r"neck.convs.<\1>."),
    # refinenet4 fuses first: it is fusion layer 0, refinenet1 is layer 3.
    (r"^scratch\.refinenet([1-4])\.out_conv\.", r"neck.fusion_stage.layers.{\1}.projection."),
    (
        r"^scratch\.refinenet([1-4])\.resConfUnit([12])\.conv([12])\.",
        r"neck.fusion_stage.layers.{\1}.residual_layer\2.convolution\3.",
    ),
    (r"^scratch\.output_conv\.([024])\.", r"head.head.\1."),
]
# Present in the original checkpoints, unused by the dense prediction (ImageNet classifier heads).
_IGNORED = re.compile(r"^pretrained\.model\.(head|patch_embed\.backbone\.head|fc_norm|pre_logits)\.")
_QKV = re.compile(r"^pretrained\.model\.blocks\.(\d+)\.attn\.qkv\.(weight|bias)$")


def _rename(key: str) -> str | None:
    for pattern, repl in _RENAMES:
        if re.search(pattern, key):
            new = re.sub(pattern, repl, key)
            new = re.sub(r"<(\d)>", lambda m: str(int(m.group(1)) - 1), new)  # 1-based -> 0-based
            return re.sub(r"\{(\d)\}", lambda m: str(4 - int(m.group(1))), new)  # refinenetK -> layer 4-K
    return None


def omnidata_to_transformers(sd: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Rename an original DPT-hybrid state dict onto transformers' DPTForDepthEstimation (is_hybrid=True).

    The fused attention qkv (rows: query, key, value) is split into three linears. Raises WonderError
    naming the first unknown keys when the dict is not a DPT-hybrid (vitb_rn50_384-style) checkpoint.
    """
    out: dict[str, torch.Tensor] = {}
    unknown: list[str] = []
    for key, val in sd.items():
        m = _QKV.match(key)
        if m:
            layer, kind = m.groups()
            q, k, v = val.chunk(3, dim=0)
            base = f"dpt.encoder.layer.{layer}.attention.attention"
            out[f"{base}.query.{kind}"], out[f"{base}.key.{kind}"], out[f"{base}.value.{kind}"] = q, k, v
            continue
        if _IGNORED.match(key):
            continue
        new = _rename(key)
        if new is None:
            unknown.append(key)
        else:
            out[new] = val
    if unknown:
        raise WonderError(
            f"{WHAT}: {len(unknown)} keys are not those of an Omnidata/DPT hybrid (vitb_rn50_384) model, "
            f"e.g. {unknown[:3]}"
        )
    return out


def read_state_dict(path: str | Path, allow_unsafe_pickle: bool = False) -> dict[str, torch.Tensor]:
    """The original-named tensors of a checkpoint file: .safetensors, or a torch file holding the state
    dict itself or a Lightning checkpoint ({"state_dict": {"model.<name>": ...}}).

    Torch files are read with weights_only=True; a Lightning checkpoint that pickles other objects needs
    allow_unsafe_pickle (it runs code from the file: only for files you trust).
    """
    p = Path(path).expanduser()
    if not p.is_file():
        raise WonderError(f"{WHAT} {p} does not exist (set priors.normal_model to the downloaded file)")
    if p.suffix == ".safetensors":
        from safetensors.torch import load_file

        obj: object = load_file(str(p))
    else:
        try:
            obj = torch.load(p, map_location="cpu", weights_only=True)
        except Exception as err:
            if not allow_unsafe_pickle:
                raise WonderError(
                    f"{WHAT} {p} holds more than tensors ({type(err).__name__}); if you trust the file, set "
                    "priors.allow_unsafe_pickle=true to load it"
                ) from None
            obj = torch.load(p, map_location="cpu", weights_only=False)
    if isinstance(obj, dict) and isinstance(obj.get("state_dict"), dict):
        obj = obj["state_dict"]
    if not isinstance(obj, dict) or not obj:
        raise WonderError(f"{WHAT} {p} does not contain a state dict")
    sd = {str(k): v for k, v in obj.items() if isinstance(v, torch.Tensor)}
    # Lightning wraps the network as `self.model`: keep those tensors, without the prefix.
    if any(k.startswith("model.pretrained.") for k in sd):
        sd = {k[len("model.") :]: v for k, v in sd.items() if k.startswith("model.")}
    return sd


def config_from_state_dict(sd: dict[str, torch.Tensor]):  # -> transformers.DPTConfig
    """DPTConfig (is_hybrid=True) of an original-named DPT-hybrid state dict, read off its tensor shapes.

    For Omnidata's checkpoints: ViT-B (768 wide, 12 blocks, 12 heads), BiT stem 64 wide with stages of
    3/4/9 blocks, neck widths 256/512/768/768, fusion 256, 384x384 position grid, 3 outputs.
    """
    from transformers import BitConfig, DPTConfig

    def shape(key: str) -> tuple[int, ...]:
        if key not in sd:
            raise WonderError(f"{WHAT}: missing {key}; not an Omnidata/DPT hybrid checkpoint")
        return tuple(sd[key].shape)

    hidden = shape("pretrained.model.pos_embed")[-1]
    grid = round((shape("pretrained.model.pos_embed")[1] - 1) ** 0.5)
    n_layers = 1 + max(int(m.group(1)) for k in sd if (m := re.match(r"pretrained\.model\.blocks\.(\d+)\.", k)))
    stage_re = re.compile(r"pretrained\.model\.patch_embed\.backbone\.stages\.(\d+)\.blocks\.(\d+)\.")
    depths: dict[int, int] = {}
    for k in sd:
        if m := stage_re.match(k):
            s, b = int(m.group(1)), int(m.group(2))
            depths[s] = max(depths.get(s, 0), b + 1)
    if sorted(depths) != [0, 1, 2]:
        raise WonderError(f"{WHAT}: expected a 3-stage ResNet stem, found stages {sorted(depths)}")
    stage_out = [shape(f"pretrained.model.patch_embed.backbone.stages.{s}.blocks.0.conv3.weight")[0] for s in range(3)]
    neck = [shape(f"scratch.layer{i}_rn.weight")[1] for i in range(1, 5)]
    fusion = shape("scratch.layer1_rn.weight")[0]
    bit = BitConfig(
        embedding_size=shape("pretrained.model.patch_embed.backbone.stem.conv.weight")[0],
        hidden_sizes=[*stage_out, 2 * stage_out[-1]],
        depths=[depths[0], depths[1], depths[2]],
        layer_type="bottleneck",
        global_padding="same",
        embedding_dynamic_padding=True,
        out_features=["stage1", "stage2", "stage3"],
    )
    return DPTConfig(
        is_hybrid=True,
        backbone_config=bit,
        hidden_size=hidden,
        num_hidden_layers=n_layers,
        num_attention_heads=max(1, hidden // HEAD_DIM),
        intermediate_size=shape("pretrained.model.blocks.0.mlp.fc1.weight")[0],
        image_size=grid * 16,
        patch_size=16,
        # hooks of vitb_rn50_384 are blocks 8 and 11 of 12: three quarters in and the last one
        backbone_out_indices=[0, 1, (3 * n_layers) // 4 - 1, n_layers - 1],
        backbone_featmap_shape=[1, stage_out[-1], grid, grid],
        neck_hidden_sizes=neck,
        reassemble_factors=[1, 1, 1, 0.5],
        fusion_hidden_size=fusion,
        readout_type="project",
        use_batch_norm_in_fusion_residual=False,
        layer_norm_eps=1e-6,  # timm's ViT LayerNorm
        hidden_act="gelu",
    )


def build_model(sd_original: dict[str, torch.Tensor]) -> nn.Module:
    """transformers DPTForDepthEstimation (hybrid, n-channel head) holding the checkpoint's weights."""
    from transformers import DPTForDepthEstimation

    config = config_from_state_dict(sd_original)
    out_channels = int(sd_original["scratch.output_conv.4.weight"].shape[0])
    converted = omnidata_to_transformers(sd_original)
    with torch.device("meta"):
        model = DPTForDepthEstimation(config)
        model.head.head[4] = nn.Conv2d(model.head.head[4].in_channels, out_channels, kernel_size=1)
    try:
        model.load_state_dict(converted, strict=True, assign=True)
    except RuntimeError as err:
        raise WonderError(f"{WHAT}: weights do not fit the inferred architecture: {str(err).splitlines()[0]}") from None
    return model.float().eval()


def dense_forward(model: nn.Module, pixel_values: torch.Tensor) -> torch.Tensor:
    """Raw head output (B,C,H,W) of a hybrid DPTForDepthEstimation for any H, W that are multiples of 32.

    transformers' own forward accepts only the configured square size; this follows the original DPT
    `forward_flex`: interpolated position embeddings and a non-square token grid, same modules.
    """
    cfg = model.config
    h, w = pixel_values.shape[-2:]
    emb = model.dpt.embeddings(pixel_values, interpolate_pos_encoding=True)
    feats = list(emb.intermediate_activations)  # BiT stages 1 and 2
    hidden = emb.last_hidden_states
    wanted = set(cfg.backbone_out_indices[2:])
    for i, layer in enumerate(model.dpt.encoder.layer):
        hidden = layer(hidden)
        if i in wanted:
            feats.append(hidden)
    fused = model.neck(feats, h // cfg.patch_size, w // cfg.patch_size)
    head = model.head
    x = fused[cfg.head_in_index]
    if head.projection is not None:
        x = torch.relu(head.projection(x))
    return head.head(x)


def network_size(h: int, w: int, short_side_px: int) -> tuple[int, int]:
    """Input size keeping the aspect ratio: short side ~= short_side_px, both multiples of SIDE_MULTIPLE_PX."""
    s = short_side_px / min(h, w)
    m = SIDE_MULTIPLE_PX
    return max(m, round(h * s / m) * m), max(m, round(w * s / m) * m)


class OmnidataNormals:
    """NormalModel running an Omnidata DPT-hybrid normal checkpoint (local file), batched, CPU or CUDA.

    Output convention: the checkpoint's axes (params.normal_output_axes; "opengl" = x right, y up,
    z towards the viewer) are converted to OpenCV camera axes, then normals are flipped to face the
    camera (using K when given, else the optical axis). No confidence.
    """

    def __init__(self, params: PriorsParams) -> None:
        if not params.normal_model:
            raise WonderError("normal prior 'dpt' needs priors.normal_model: the path of an Omnidata normal checkpoint")
        self.params = params
        self.device, self.dtype = resolve_device(params.device, params.fp16)
        sd = read_state_dict(params.normal_model, params.allow_unsafe_pickle)
        self.model = build_model(sd).to(device=self.device, dtype=self.dtype)

    @torch.inference_mode()
    def raw(self, pixel_values: torch.Tensor) -> torch.Tensor:
        """The network's (B,3,h,w) float32 output for RGB in [0,1] (h, w multiples of 32), before clamping."""
        x = pixel_values.to(device=self.device, dtype=self.dtype)
        return dense_forward(self.model, x).float()

    @torch.inference_mode()
    def predict(
        self, frames: np.ndarray, K: np.ndarray | None = None, depth: np.ndarray | None = None
    ) -> NormalPrediction:
        """(B,H,W,3) float32 unit normals, OpenCV camera axes, facing the camera. depth is not used."""
        b, h, w = check_frames(frames)
        hn, wn = network_size(h, w, self.params.normal_input_size_px)
        out = np.empty((b, h, w, 3), dtype=np.float32)
        for start in range(0, b, self.params.batch_size):
            chunk = torch.from_numpy(frames[start : start + self.params.batch_size]).to(self.device)
            x = chunk.permute(0, 3, 1, 2).float() / 255.0
            x = F.interpolate(x, size=(hn, wn), mode="bilinear", align_corners=False, antialias=True)
            y = self.raw(x).clamp(0.0, 1.0) * 2.0 - 1.0
            y = F.interpolate(y, size=(h, w), mode="bilinear", align_corners=False)
            out[start : start + len(chunk)] = y.permute(0, 2, 3, 1).cpu().numpy()
        if self.params.normal_output_axes == "opengl":
            out[..., 1:] *= -1.0  # (x, y up, z to viewer) -> (x, y down, z forward)
        norm = np.linalg.norm(out, axis=-1, keepdims=True)
        out = np.where(norm > 1e-6, out / np.maximum(norm, 1e-6), 0.0).astype(np.float32)
        orient_towards_camera(out, K)
        return NormalPrediction(normals=out)

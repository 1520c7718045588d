"""Depth Anything V2 through transformers (AutoModelForDepthEstimation + AutoImageProcessor).

Weights: any transformers-format Depth Anything checkpoint, as a local directory written by
`save_pretrained` (model and image processor) or a hub id such as
"depth-anything/Depth-Anything-V2-Small-hf" (also -Base-hf, -Large-hf). The relative models predict an
affine-invariant disparity (larger = nearer, unknown scale and shift), reported as kind="inverse_depth";
the Metric-* models (config.depth_estimation_type == "metric") predict metric depth, kind="depth".
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from wonderverse.errors import WonderError
from wonderverse.priors.base import DepthKind, DepthPrediction, check_frames
from wonderverse.priors.params import PriorsParams
from wonderverse.priors.runtime import hub_error, local_dir_or_hub_id, resolve_device

WHAT = "Depth Anything weights"


class DepthAnythingV2:
    """DepthModel backed by a transformers Depth Anything (V1 or V2) checkpoint; batched, CPU or CUDA."""

    def __init__(self, params: PriorsParams) -> None:
        from transformers import AutoImageProcessor, AutoModelForDepthEstimation

        self.params = params
        self.device, self.dtype = resolve_device(params.device, params.fp16)
        where, local = local_dir_or_hub_id(params.depth_model, WHAT)
        only_local = local or not params.allow_download
        try:
            self.processor = AutoImageProcessor.from_pretrained(where, local_files_only=only_local)
            model = AutoModelForDepthEstimation.from_pretrained(where, local_files_only=only_local)
        except Exception as err:  # transformers raises OSError/ValueError/HTTP errors; all mean "not loadable"
            if local:
                first = str(err).strip().splitlines()[0] if str(err).strip() else ""
                raise WonderError(f"{WHAT} in {where} could not be loaded: {type(err).__name__}: {first}") from None
            raise hub_error(where, WHAT, params.allow_download, err) from None
        self.model = model.to(device=self.device, dtype=self.dtype).eval()
        est = getattr(model.config, "depth_estimation_type", "relative")
        self.kind: DepthKind = "depth" if est == "metric" else "inverse_depth"

    def _pixel_values(self, frames: np.ndarray) -> torch.Tensor:
        kwargs = {}
        if self.params.depth_input_size_px is not None:
            s = self.params.depth_input_size_px
            kwargs["size"] = {"height": s, "width": s}
        inputs = self.processor(images=list(frames), return_tensors="pt", **kwargs)
        return inputs["pixel_values"].to(device=self.device, dtype=self.dtype)

    @torch.inference_mode()
    def predict(self, frames: np.ndarray) -> DepthPrediction:
        """(B,H,W) float32 prediction at the frames' size (bilinear resize of the network output).

        kind="inverse_depth" for relative checkpoints: disparity-like, >= 0, scale and shift unknown.
        """
        b, h, w = check_frames(frames)
        out = np.empty((b, h, w), dtype=np.float32)
        for start in range(0, b, self.params.batch_size):
            chunk = frames[start : start + self.params.batch_size]
            pred = self.model(pixel_values=self._pixel_values(chunk)).predicted_depth  # (b,h',w')
            pred = F.interpolate(pred[:, None].float(), size=(h, w), mode="bilinear", align_corners=False)[:, 0]
            out[start : start + len(chunk)] = pred.cpu().numpy()
        np.nan_to_num(out, copy=False, nan=0.0, posinf=0.0, neginf=0.0)
        return DepthPrediction(depth=out, kind=self.kind)

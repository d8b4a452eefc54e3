"""segment-anything as a multi-level segmenter (LangSplat's recipe, docs/method.md §4).

SAM's three multimask outputs are LangSplat's levels s, m and l, by index
(`level_order = "index"`, as LangSplat, which relies on SAM's trained tokens
coming out subpart, part, whole); the automatic generator loop (point grid, filters, box and mask
NMS, painting) is `ptovs.segment.generator.MaskGenerator`, shared with SAM 2
(`ptovs.segment.sam2`), and equals segment-anything's `SamAutomaticMaskGenerator`
run per output (tests/test_segment.py). This module supplies vanilla SAM's model,
predictor (through `SamPoints`) and `utils.amg` helpers.

The model comes from a local checkpoint (`sam_checkpoint`, ViT-H in the paper);
tests pass a tiny randomly initialised `Sam` as `model=`.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ptovs.compat import import_backend
from ptovs.segment.generator import (
    LEVEL_OUTPUTS,
    MaskGenerator,
    default_points_per_batch,
    local_checkpoint,
)

log = logging.getLogger(__name__)


def load_sam(checkpoint: str | Path, model_type: str = "vit_h", device: str = "cpu"):
    """Build SAM `model_type` and load a local state dict (weights_only)."""
    sa = import_backend("segment_anything")
    path = local_checkpoint(checkpoint, "sam", "sam_vit_h_4b8939.pth")
    if model_type not in sa.sam_model_registry:
        raise ValueError(
            f"sam_model {model_type!r}: choose from {sorted(sa.sam_model_registry)}"
        )
    model = sa.sam_model_registry[model_type](checkpoint=None)
    state = torch.load(path, map_location="cpu", weights_only=True)
    model.load_state_dict(state)
    return model.to(device).eval()


class SamPoints:
    """SAM's `SamPredictor` as the generator's `PointPredictor`, called as
    `SamAutomaticMaskGenerator._process_batch` calls it (float64 coordinates)."""

    def __init__(self, predictor: Any):
        self.predictor = predictor
        self.mask_threshold = predictor.model.mask_threshold
        self.size: tuple[int, int] = (0, 0)

    def set_image(self, image: np.ndarray) -> None:
        self.predictor.set_image(image)
        self.size = image.shape[:2]

    def predict(self, points: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        pred = self.predictor
        pts = pred.transform.apply_coords(points, self.size)
        pts_t = torch.as_tensor(pts, device=pred.device)
        labels = torch.ones(len(pts), dtype=torch.int, device=pts_t.device)
        logits, iou, _ = pred.predict_torch(
            pts_t[:, None, :],
            labels[:, None],
            multimask_output=True,
            return_logits=True,
        )
        return logits, iou

    def reset(self) -> None:
        self.predictor.reset_image()


class SamSegmenter(MaskGenerator):
    """SAM from `checkpoint` (or `model=`); `options` are `MaskGenerator`'s
    (levels, points_per_side, crop_n_layers, the filters' thresholds,
    level_order: "index" by default, as LangSplat)."""

    name = "sam"

    def __init__(
        self,
        checkpoint: str | Path = "",
        model_type: str = "vit_h",
        device: str = "cpu",
        model: Any = None,
        **options: Any,
    ):
        self.sa = import_backend("segment_anything")
        self.model = (
            model.to(device).eval()
            if model is not None
            else load_sam(checkpoint, model_type, device)
        )
        self.predictor = self.sa.SamPredictor(self.model)
        amg = import_backend("segment_anything.utils.amg")
        options.setdefault("points_per_batch", default_points_per_batch(device))
        super().__init__(SamPoints(self.predictor), amg, **options)


def tiny_sam(seed: int = 0, img_size: int = 256):
    """A randomly initialised, tiny SAM (for tests; ~0.5 M parameters)."""
    sa = import_backend("segment_anything")
    from functools import partial

    modeling = sa.modeling
    torch.manual_seed(seed)
    embed = 32
    prompt_dim = 32
    grid = img_size // 16
    model = modeling.Sam(
        image_encoder=modeling.ImageEncoderViT(
            depth=2,
            embed_dim=embed,
            img_size=img_size,
            mlp_ratio=2,
            norm_layer=partial(torch.nn.LayerNorm, eps=1e-6),
            num_heads=2,
            patch_size=16,
            qkv_bias=True,
            use_rel_pos=True,
            global_attn_indexes=(1,),
            window_size=4,
            out_chans=prompt_dim,
        ),
        prompt_encoder=modeling.PromptEncoder(
            embed_dim=prompt_dim,
            image_embedding_size=(grid, grid),
            input_image_size=(img_size, img_size),
            mask_in_chans=8,
        ),
        mask_decoder=modeling.MaskDecoder(
            num_multimask_outputs=3,
            transformer=modeling.TwoWayTransformer(
                depth=1, embedding_dim=prompt_dim, mlp_dim=64, num_heads=2
            ),
            transformer_dim=prompt_dim,
            iou_head_depth=2,
            iou_head_hidden_dim=32,
        ),
        pixel_mean=[123.675, 116.28, 103.53],
        pixel_std=[58.395, 57.12, 57.375],
    )
    return model.eval()


__all__ = ["LEVEL_OUTPUTS", "SamPoints", "SamSegmenter", "load_sam", "tiny_sam"]

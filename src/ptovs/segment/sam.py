"""segment-anything as a multi-level segmenter (LangSplat's recipe, docs/method.md §4).

LangSplat runs a fork of SAM whose automatic mask generator keeps SAM's three
multimask outputs apart: s, m and l are outputs 0, 1 and 2, "default" pools all
three. Vanilla `segment_anything` flattens them, and its generator calls
torchvision's compiled `batched_nms`, which does not load on our CPU torch. So the
generator loop is ours, built on vanilla SAM's model, predictor and `utils.amg`
helpers: point grid over the image and its crops, multimask prediction, the
predicted-IoU and stability filters, box NMS within and across crops (pure torch,
`ptovs.segment.masks.box_nms`), small-region clean-up, then LangSplat's per-level
mask NMS (`mask_nms`, vectorised) and painting in list order.

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
from ptovs.segment.levels import Level, check_levels
from ptovs.segment.masks import box_nms, mask_nms, paint

log = logging.getLogger(__name__)

LEVEL_OUTPUTS = {"s": (0,), "m": (1,), "l": (2,), "default": (0, 1, 2)}


def load_sam(checkpoint: str | Path, model_type: str = "vit_h", device: str = "cpu"):
    """Build SAM `model_type` and load a local state dict (weights_only)."""
    sa = import_backend("segment_anything")
    path = Path(checkpoint)
    if not str(checkpoint):
        raise ValueError(
            "segmenter = 'sam' needs sam_checkpoint = a local SAM checkpoint "
            "(e.g. sam_vit_h_4b8939.pth); nothing is downloaded"
        )
    if not path.is_file():
        raise FileNotFoundError(f"sam_checkpoint {path} does not exist")
    if model_type not in sa.sam_model_registry:
        raise ValueError(
            f"sam_model {model_type!r}: choose from {sorted(sa.sam_model_registry)}"
        )
    model = sa.sam_model_registry[model_type](checkpoint=None)
    state = torch.load(path, map_location="cpu", weights_only=True)
    model.load_state_dict(state)
    return model.to(device).eval()


class SamSegmenter:
    name = "sam"

    def __init__(
        self,
        checkpoint: str | Path = "",
        model_type: str = "vit_h",
        levels: tuple[str, ...] = ("s", "m", "l"),
        points_per_side: int = 32,
        points_per_batch: int = 64,
        pred_iou_thresh: float = 0.7,
        stability_score_thresh: float = 0.85,
        stability_score_offset: float = 1.0,
        box_nms_thresh: float = 0.7,
        crop_n_layers: int = 1,
        crop_overlap_ratio: float = 512 / 1500,
        crop_n_points_downscale_factor: int = 1,
        crop_nms_thresh: float = 0.7,
        min_mask_region_area: int = 100,
        device: str = "cpu",
        model: Any = None,
    ):
        self.sa = import_backend("segment_anything")
        self.amg = import_backend("segment_anything.utils.amg")
        self.levels = check_levels(levels)
        self.model = (
            model.to(device).eval()
            if model is not None
            else load_sam(checkpoint, model_type, device)
        )
        self.predictor = self.sa.SamPredictor(self.model)
        self.points_per_batch = points_per_batch
        self.pred_iou_thresh = pred_iou_thresh
        self.stability_score_thresh = stability_score_thresh
        self.stability_score_offset = stability_score_offset
        self.box_nms_thresh = box_nms_thresh
        self.crop_n_layers = crop_n_layers
        self.crop_overlap_ratio = crop_overlap_ratio
        self.crop_nms_thresh = crop_nms_thresh
        self.min_mask_region_area = min_mask_region_area
        self.point_grids = self.amg.build_all_layer_point_grids(
            points_per_side, crop_n_layers, crop_n_points_downscale_factor
        )

    # ------------------------------------------------------------------ masks
    @torch.inference_mode()
    def _crop_masks(self, image: np.ndarray, crop_box: list[int], layer: int) -> dict:
        """{output index: dict of masks/iou/stability/boxes} for one crop."""
        amg = self.amg
        h, w = image.shape[:2]
        x0, y0, x1, y1 = crop_box
        crop = image[y0:y1, x0:x1]
        self.predictor.set_image(crop)
        scale = np.array(crop.shape[:2])[None, ::-1]
        points_all = self.point_grids[layer] * scale
        out: dict[int, list[dict]] = {0: [], 1: [], 2: []}
        thr = self.model.mask_threshold
        for (points,) in amg.batch_iterator(self.points_per_batch, points_all):
            pts = self.predictor.transform.apply_coords(points, crop.shape[:2])
            pts_t = torch.as_tensor(
                pts, dtype=torch.float32, device=self.predictor.device
            )
            labels = torch.ones(len(pts), dtype=torch.int64, device=pts_t.device)
            logits, iou, _ = self.predictor.predict_torch(
                pts_t[:, None, :],
                labels[:, None],
                multimask_output=True,
                return_logits=True,
            )
            for k in range(3):
                lg, ip = logits[:, k], iou[:, k]
                keep = ip > self.pred_iou_thresh
                lg, ip = lg[keep], ip[keep]
                stab = amg.calculate_stability_score(
                    lg, thr, self.stability_score_offset
                )
                keep = stab >= self.stability_score_thresh
                lg, ip, stab = lg[keep], ip[keep], stab[keep]
                if not len(lg):
                    continue
                masks = lg > thr
                boxes = amg.batched_mask_to_box(masks)
                keep = ~amg.is_box_near_crop_edge(boxes, crop_box, [0, 0, w, h])
                if not keep.any():
                    continue
                masks = amg.uncrop_masks(masks[keep], crop_box, h, w)
                out[k].append(
                    dict(
                        masks=masks.cpu(),
                        iou=ip[keep].float().cpu(),
                        stability=stab[keep].float().cpu(),
                        boxes=amg.uncrop_boxes_xyxy(boxes[keep], crop_box)
                        .float()
                        .cpu(),
                    )
                )
        self.predictor.reset_image()
        merged = {}
        for k, parts in out.items():
            if not parts:
                continue
            data = {key: torch.cat([p[key] for p in parts]) for key in parts[0]}
            keep = box_nms(data["boxes"], data["iou"], self.box_nms_thresh)
            data = {key: v[keep] for key, v in data.items()}
            data["crop_area"] = torch.full(
                (len(keep),), float((x1 - x0) * (y1 - y0)), dtype=torch.float32
            )
            merged[k] = data
        return merged

    def _postprocess_small_regions(self, data: dict) -> dict:
        # SAM's clean-up: remove small holes and islands, prefer unchanged masks
        amg = self.amg
        area = self.min_mask_region_area
        if area <= 0 or not len(data["masks"]):
            return data
        new_masks, scores = [], []
        for m in data["masks"].numpy():
            m, changed = amg.remove_small_regions(m, area, mode="holes")
            unchanged = not changed
            m, changed = amg.remove_small_regions(m, area, mode="islands")
            unchanged = unchanged and not changed
            new_masks.append(torch.as_tensor(m))
            scores.append(float(unchanged))
        masks = torch.stack(new_masks)
        boxes = amg.batched_mask_to_box(masks).float()
        keep = box_nms(boxes, torch.as_tensor(scores), self.box_nms_thresh)
        data = {k: v[keep] for k, v in data.items()}
        data["masks"] = masks[keep]
        data["boxes"] = boxes[keep]
        return data

    def masks(self, image: np.ndarray) -> dict[str, dict]:
        """Per level: the filtered masks (SAM filters, then LangSplat's mask NMS)."""
        amg = self.amg
        h, w = image.shape[:2]
        crop_boxes, layer_idxs = amg.generate_crop_boxes(
            (h, w), self.crop_n_layers, self.crop_overlap_ratio
        )
        per_output: dict[int, list[dict]] = {0: [], 1: [], 2: []}
        for box, layer in zip(crop_boxes, layer_idxs, strict=True):
            for k, data in self._crop_masks(image, box, layer).items():
                per_output[k].append(data)
        levels = {}
        for level in self.levels:
            parts = [d for k in LEVEL_OUTPUTS[level] for d in per_output[k]]
            parts = [p for p in parts if len(p["masks"])]
            if not parts:
                levels[level] = dict(masks=torch.zeros(0, h, w, dtype=torch.bool))
                continue
            data = {key: torch.cat([p[key] for p in parts]) for key in parts[0]}
            if len(crop_boxes) > 1:  # across crops prefer masks from smaller crops
                keep = box_nms(
                    data["boxes"], 1.0 / data["crop_area"], self.crop_nms_thresh
                )
                keep = torch.sort(keep).values
                data = {key: v[keep] for key, v in data.items()}
            data = self._postprocess_small_regions(data)
            keep = torch.sort(
                mask_nms(data["masks"], data["stability"] * data["iou"])
            ).values
            levels[level] = {key: v[keep] for key, v in data.items()}
        return levels

    def segment(self, image: np.ndarray) -> list[Level]:
        if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
            raise ValueError(
                f"expected uint8 [H, W, 3], got {image.dtype} {image.shape}"
            )
        per_level = self.masks(image)
        out = []
        for level in self.levels:
            masks = [m.numpy() for m in per_level[level]["masks"]]
            labels, kept = paint(masks, image.shape[:2])  # later masks overwrite
            out.append(Level(labels, [masks[i] for i in kept]))
        return out


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

"""The automatic multi-level mask generator shared by `sam` and `sam2`
(LangSplat's recipe, docs/method.md §4).

LangSplat runs a fork of SAM whose automatic mask generator keeps SAM's three
multimask outputs apart: s, m and l are outputs 0, 1 and 2, "default" pools all
three. Vanilla `segment_anything` (and `sam2`) flatten them, and their generators
call torchvision's compiled `batched_nms`, which does not load on our CPU torch. So
the generator loop is ours: point grid over the image and its crops, multimask
prediction, the predicted-IoU and stability filters, box NMS within and across
crops (pure torch, `ptovs.segment.masks.box_nms`), small-region clean-up, then
LangSplat's per-level mask NMS (`mask_nms`, vectorised) and painting in list order.

The model enters through a `PointPredictor` adapter (`set_image`, `predict` a batch
of points, `reset`); `amg` is the backend's `utils.amg` module (SAM's and SAM 2's
are the same helpers).
"""

from __future__ import annotations

from pathlib import Path
from types import ModuleType
from typing import Protocol

import numpy as np
import torch

from ptovs.segment.levels import Level, check_levels
from ptovs.segment.masks import box_nms, mask_nms, paint

LEVEL_OUTPUTS = {"s": (0,), "m": (1,), "l": (2,), "default": (0, 1, 2)}


def local_checkpoint(checkpoint: str | Path, segmenter: str, example: str) -> Path:
    """The `sam_checkpoint` file of `segmenter` (nothing is downloaded)."""
    if not str(checkpoint):
        raise ValueError(
            f"segmenter = {segmenter!r} needs sam_checkpoint = a local checkpoint "
            f"(e.g. {example}); nothing is downloaded"
        )
    path = Path(checkpoint).expanduser()
    if not path.is_file():
        raise FileNotFoundError(f"sam_checkpoint {path} does not exist")
    return path


class PointPredictor(Protocol):
    """A promptable model with one image set at a time."""

    mask_threshold: float

    def set_image(self, image: np.ndarray) -> None:
        """Embed an RGB uint8 image [h, w, 3] (one crop of the photo)."""
        ...

    def predict(self, points: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        """One foreground point each ([N, 2] xy, pixels of the image set): the
        three multimask logits [N, 3, h, w] at the image's size and their
        predicted IoUs [N, 3]."""
        ...

    def reset(self) -> None:
        """Drop the image's embedding."""
        ...


class MaskGenerator:
    """Point-grid automatic masks, kept per level; subclasses set the predictor."""

    name = ""

    def __init__(
        self,
        points: PointPredictor,
        amg: ModuleType,
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
    ):
        self.points = points
        self.amg = amg
        self.levels = check_levels(levels)
        self.points_per_batch = points_per_batch
        self.pred_iou_thresh = pred_iou_thresh
        self.stability_score_thresh = stability_score_thresh
        self.stability_score_offset = stability_score_offset
        self.box_nms_thresh = box_nms_thresh
        self.crop_n_layers = crop_n_layers
        self.crop_overlap_ratio = crop_overlap_ratio
        self.crop_nms_thresh = crop_nms_thresh
        self.min_mask_region_area = min_mask_region_area
        self.point_grids = amg.build_all_layer_point_grids(
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
        self.points.set_image(crop)
        scale = np.array(crop.shape[:2])[None, ::-1]
        points_all = self.point_grids[layer] * scale
        out: dict[int, list[dict]] = {0: [], 1: [], 2: []}
        thr = self.points.mask_threshold
        for (points,) in amg.batch_iterator(self.points_per_batch, points_all):
            logits, iou = self.points.predict(points)
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
        self.points.reset()
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


__all__ = ["LEVEL_OUTPUTS", "MaskGenerator", "PointPredictor", "local_checkpoint"]

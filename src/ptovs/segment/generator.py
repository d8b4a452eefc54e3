"""The automatic multi-level mask generator shared by `sam` and `sam2`
(LangSplat's recipe, docs/method.md §4).

LangSplat runs a fork of SAM's `SamAutomaticMaskGenerator` that keeps SAM's three
multimask outputs apart: s, m and l are outputs 0, 1 and 2, "default" pools all
three, and each of the four lists runs upstream's whole pipeline on its own. This
module is that fork, step for step: point grid over the image and its crops,
multimask prediction, the predicted-IoU and stability filters (each off at a
threshold ≤ 0, as upstream), box NMS within each crop, box NMS across crops
preferring smaller crops, SAM-1's small-region clean-up (holes and islands below
`min_mask_region_area`, then box NMS at max(box, crop) thresholds), and masks kept
in the order those steps leave them. Then LangSplat's per-level mask NMS
(`mask_nms`, vectorised), its survivors kept in list order, and painting in list
order (later masks win).

tests/test_segment.py and tests/test_sam2.py show that, for each level, the masks
before LangSplat's filter are upstream's own generator's (`SamAutomaticMaskGenerator`,
`SAM2AutomaticMaskGenerator`) mask for mask and in the same order, on seeded random
weights, when upstream's predictor answers with that level's output.

Why not upstream's generator itself: it flattens the three outputs into one list
(a fourth pass per level would cost three more encoder runs per crop), and it
calls torchvision's compiled `batched_nms`, which does not load on our CPU torch;
`ptovs.segment.masks.box_nms` is the same greedy NMS in plain torch (ties kept in
input order, as torchvision's CPU kernel's stable sort).

Which output is which level (`level_order`): "index" takes output k as level k
(LangSplat on SAM 1, which relies on SAM's trained tokens coming out subpart,
part, whole); "area" sorts each prompt's three outputs by mask area first (SAM
2.1's default: its decoder's three multimask tokens are learned slots that
nothing in the head orders by size).

The model enters through a `PointPredictor` adapter (`set_image`, `predict` a batch
of points, `reset`); `amg` is the backend's `utils.amg` module (SAM's and SAM 2's
are the same helpers).
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import os
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType
from typing import Protocol

import numpy as np
import torch
from torch import Tensor

from ptovs.segment.levels import Level, check_levels
from ptovs.segment.masks import box_nms, mask_nms, paint

LEVEL_OUTPUTS = {"s": (0,), "m": (1,), "l": (2,), "default": (0, 1, 2)}
"""Level → the multimask outputs it takes (after `level_order`), as LangSplat."""

LEVEL_ORDERS = ("index", "area")


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

    def predict(self, points: np.ndarray) -> tuple[Tensor, Tensor]:
        """One foreground point each ([N, 2] xy, pixels of the image set): the
        three multimask logits [N, 3, h, w] at the image's size and their
        predicted IoUs [N, 3]."""
        ...

    def reset(self) -> None:
        """Drop the image's embedding."""
        ...


def order_by_area(
    logits: Tensor,  # [N, 3, h, w]
    iou: Tensor,  # [N, 3]
    threshold: float,
) -> tuple[Tensor, Tensor]:
    """Each prompt's outputs sorted by mask area (pixels above `threshold`),
    smallest first; equal areas keep their output order.

    Returns:
        logits [N, 3, h, w] and iou [N, 3], permuted alike per prompt.
    """
    area = (logits > threshold).sum((-2, -1))
    order = torch.argsort(area, dim=1, stable=True)
    if bool((order == torch.arange(order.shape[1])).all()):
        return logits, iou  # already sorted: no copy of the logits
    rows = torch.arange(len(order))[:, None]
    return logits[rows, order], iou[rows, order]


_LIBC = None
_DEFAULT_MMAP_MAX = 65536  # glibc's DEFAULT_MMAP_MAX
_MMAP_THRESHOLD_MAX = 32 << 20  # glibc's DEFAULT_MMAP_THRESHOLD_MAX on 64-bit
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD, M_MMAP_MAX = -1, -3, -4


def _glibc():
    """glibc's handle (mallopt, malloc_trim), or None elsewhere or when the user
    tuned malloc through the environment (their settings stand)."""
    global _LIBC
    if _LIBC is None:
        _LIBC = False
        tuned = "malloc" in os.environ.get("GLIBC_TUNABLES", "") or any(
            k.startswith("MALLOC_") for k in os.environ
        )
        name = ctypes.util.find_library("c")
        if not tuned and name:
            try:
                libc = ctypes.CDLL(name)
                if hasattr(libc, "mallopt") and hasattr(libc, "malloc_trim"):
                    _LIBC = libc
            except OSError:
                pass
    return _LIBC or None


@contextlib.contextmanager
def reuse_freed_memory() -> Iterator[None]:
    """While segmenting, freed tensors stay in the process for the next one.

    SAM's mask decoder gives every prompt its own copy of the image embedding, so
    one batch of 64 prompts allocates about a dozen [64, 4096, 256] float32 tensors
    (268 MB each) and frees them again. glibc serves anything above its mmap
    threshold (32 MiB at most) with a fresh mmap and unmaps it on free, so the
    kernel zero-fills every page of every such tensor anew: on 2 cores about 3
    million page faults and a third of the CPU time spent in the kernel per image.
    Here those tensors come from the heap, which is not trimmed, so later batches
    reuse the same pages (not all: torch allocates 64-byte aligned, and glibc's
    aligned path parks a small chunk between a freed tensor and the heap's top, so
    the heap grows past the live peak; hence `default_points_per_batch`'s 32 on a
    CPU). On exit mmap is back on, at the thresholds glibc itself
    settles at once a large tensor has been freed (mmap from 32 MiB, trim above
    64 MiB), and the heap is trimmed: nothing stays held after `segment` returns.
    Elsewhere than glibc, or when the user tuned malloc (MALLOC_*, GLIBC_TUNABLES),
    this does nothing.
    """
    libc = _glibc()
    if libc is None:
        yield
        return
    libc.mallopt(M_MMAP_MAX, 0)
    libc.mallopt(M_TRIM_THRESHOLD, -1)  # -1: never trim (mallopt(3))
    try:
        yield
    finally:
        libc.mallopt(M_MMAP_MAX, _DEFAULT_MMAP_MAX)
        libc.mallopt(M_MMAP_THRESHOLD, _MMAP_THRESHOLD_MAX)
        libc.mallopt(M_TRIM_THRESHOLD, 2 * _MMAP_THRESHOLD_MAX)
        libc.malloc_trim(0)


def default_points_per_batch(device: str | torch.device) -> int:
    """Prompts decoded at once: upstream's 64 on a GPU, 32 on a CPU.

    The masks do not depend on it (SAM 2.1's logits are bitwise the same in
    batches of 16, 32 or 64). On a CPU under `reuse_freed_memory`, 32 keeps the
    heap below what 64 grows it to (SAM 2.1 tiny, 8 x 8 prompts, a 700 x 525
    photo: peak 2.6 GB against 4.3 GB) for about 9 % more decoder time."""
    return 64 if torch.device(device).type == "cuda" else 32


def _cat(parts: list[dict]) -> dict:
    return {key: torch.cat([p[key] for p in parts]) for key in parts[0]}


def _take(data: dict, keep: Tensor) -> dict:
    return {key: v[keep] for key, v in data.items()}


class MaskGenerator:
    """Point-grid automatic masks, kept per level; subclasses set the predictor.

    The options are `SamAutomaticMaskGenerator`'s, with LangSplat's values as
    defaults (segment-anything's own: pred_iou_thresh 0.88, stability 0.95,
    crop_n_layers 0, min_mask_region_area 0; sam2's: 0.8, 0.95, 0, 0), plus
    `levels` and `level_order` ("index" or "area", see the module's docstring).
    """

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
        level_order: str = "index",
    ):
        if level_order not in LEVEL_ORDERS:
            raise ValueError(
                f"level_order {level_order!r}: choose from {list(LEVEL_ORDERS)}"
            )
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
        self.level_order = level_order
        self.point_grids = amg.build_all_layer_point_grids(
            points_per_side, crop_n_layers, crop_n_points_downscale_factor
        )

    # ------------------------------------------------------------------ masks
    def _filter_batch(
        self, logits: Tensor, iou: Tensor, crop_box: list[int], hw: tuple[int, int]
    ) -> dict | None:
        """Upstream's `_process_batch` on one level's logits [M, h, w]."""
        amg, thr = self.amg, self.points.mask_threshold
        if self.pred_iou_thresh > 0.0:
            keep = iou > self.pred_iou_thresh
            logits, iou = logits[keep], iou[keep]
        stab = amg.calculate_stability_score(logits, thr, self.stability_score_offset)
        if self.stability_score_thresh > 0.0:
            keep = stab >= self.stability_score_thresh
            logits, iou, stab = logits[keep], iou[keep], stab[keep]
        if not len(logits):
            return None
        masks = logits > thr
        boxes = amg.batched_mask_to_box(masks)
        keep = ~amg.is_box_near_crop_edge(boxes, crop_box, [0, 0, hw[1], hw[0]])
        if not keep.any():
            return None
        return dict(
            masks=amg.uncrop_masks(masks[keep], crop_box, *hw).cpu(),
            iou=iou[keep].float().cpu(),
            stability=stab[keep].float().cpu(),
            boxes=boxes[keep].float().cpu(),  # crop frame until the crop's NMS
        )

    @torch.inference_mode()
    def _crop_masks(
        self, image: np.ndarray, crop_box: list[int], layer: int
    ) -> dict[str, dict]:
        """{level: masks/iou/stability/boxes/crop_area} of one crop, after the
        crop's box NMS (upstream's `_process_crop`, once per level)."""
        amg = self.amg
        x0, y0, x1, y1 = crop_box
        crop = image[y0:y1, x0:x1]
        self.points.set_image(crop)
        scale = np.array(crop.shape[:2])[None, ::-1]
        points_all = self.point_grids[layer] * scale
        out: dict[str, list[dict]] = {level: [] for level in self.levels}
        for (points,) in amg.batch_iterator(self.points_per_batch, points_all):
            logits, iou = self.points.predict(points)
            if self.level_order == "area":
                logits, iou = order_by_area(logits, iou, self.points.mask_threshold)
            for level in self.levels:
                a, b = LEVEL_OUTPUTS[level][0], LEVEL_OUTPUTS[level][-1] + 1
                part = self._filter_batch(
                    logits[:, a:b].flatten(0, 1),  # point-major, as upstream
                    iou[:, a:b].flatten(0, 1),
                    crop_box,
                    image.shape[:2],
                )
                if part is not None:
                    out[level].append(part)
            del logits
        self.points.reset()
        merged = {}
        for level, parts in out.items():
            if not parts:
                continue
            data = _cat(parts)
            data = _take(data, box_nms(data["boxes"], data["iou"], self.box_nms_thresh))
            data["boxes"] = amg.uncrop_boxes_xyxy(data["boxes"], crop_box)
            data["crop_area"] = torch.full(
                (len(data["iou"]),), float((x1 - x0) * (y1 - y0)), dtype=torch.float32
            )
            merged[level] = data
        return merged

    def _postprocess_small_regions(self, data: dict) -> dict:
        # SAM-1's clean-up (LangSplat's generator runs it on every list): remove
        # small holes and islands, prefer unchanged masks in the box NMS that follows
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
        thresh = max(self.box_nms_thresh, self.crop_nms_thresh)  # as upstream
        keep = box_nms(boxes, torch.as_tensor(scores), thresh)
        data = _take(data, keep)
        data["masks"] = masks[keep]
        data["boxes"] = boxes[keep]
        return data

    def candidates(self, image: np.ndarray) -> dict[str, dict]:
        """Per level, SAM's automatic masks before LangSplat's filter, in
        upstream's order: {level: {"masks" [M, H, W] bool, "iou" [M],
        "stability" [M], "boxes" [M, 4] xyxy, "crop_area" [M]}} (M may be 0)."""
        amg = self.amg
        h, w = image.shape[:2]
        crop_boxes, layer_idxs = amg.generate_crop_boxes(
            (h, w), self.crop_n_layers, self.crop_overlap_ratio
        )
        per_level: dict[str, list[dict]] = {level: [] for level in self.levels}
        for box, layer in zip(crop_boxes, layer_idxs, strict=True):
            for level, data in self._crop_masks(image, box, layer).items():
                per_level[level].append(data)
        out = {}
        for level, parts in per_level.items():
            if not parts:
                out[level] = dict(
                    masks=torch.zeros(0, h, w, dtype=torch.bool),
                    iou=torch.zeros(0),
                    stability=torch.zeros(0),
                    boxes=torch.zeros(0, 4),
                    crop_area=torch.zeros(0),
                )
                continue
            data = _cat(parts)
            if len(crop_boxes) > 1:  # across crops prefer masks from smaller crops
                data = _take(
                    data,
                    box_nms(data["boxes"], 1 / data["crop_area"], self.crop_nms_thresh),
                )
            out[level] = self._postprocess_small_regions(data)
        return out

    def masks(self, image: np.ndarray) -> dict[str, dict]:
        """Per level: the candidates LangSplat's mask NMS keeps, in list order."""
        out = {}
        for level, data in self.candidates(image).items():
            # LangSplat's masks_update keeps the survivors in list order
            keep = torch.sort(
                mask_nms(data["masks"], data["stability"] * data["iou"])
            ).values
            out[level] = _take(data, keep)
        return out

    def segment(self, image: np.ndarray) -> list[Level]:
        """Segment an RGB uint8 image [H, W, 3]: one `Level` per entry of
        `levels`; a level with no masks is all `NO_SEGMENT` (n == 0)."""
        if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
            raise ValueError(
                f"expected uint8 [H, W, 3], got {image.dtype} {image.shape}"
            )
        with reuse_freed_memory():
            per_level = self.masks(image)
        out = []
        for level in self.levels:
            masks = [m.numpy() for m in per_level[level]["masks"]]
            labels, kept = paint(masks, image.shape[:2])  # later masks overwrite
            out.append(Level(labels, [masks[i] for i in kept]))
        return out


__all__ = [
    "LEVEL_ORDERS",
    "LEVEL_OUTPUTS",
    "MaskGenerator",
    "PointPredictor",
    "local_checkpoint",
    "order_by_area",
    "default_points_per_batch",
    "reuse_freed_memory",
]

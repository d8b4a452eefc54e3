"""SAM 2.1 as a multi-level segmenter: the same recipe as `ptovs.segment.sam`
(LangSplat's thresholds and SAM-1 clean-up, LangSplat's mask NMS) with SAM 2.1's
hierarchical (Hiera) image encoder, which is cheaper than SAM's ViT on a CPU
(docs/results.md, "Encoders and segmenters").

Levels: SAM 2.1's mask decoder returns its mask tokens 1..3 for a multimask
prompt (`MaskDecoder.forward`: `masks[:, 1:]`), three learned slots that nothing
in the head orders by size, so ptovs sorts each prompt's three masks by area
(`level_order = "area"`): s is the smallest, l the largest.

Where it departs from sam2's own `SAM2AutomaticMaskGenerator` (whose defaults are
pred_iou_thresh 0.8, stability 0.95, no crops, no clean-up), on purpose: LangSplat's
SAM-1 settings (0.7, 0.85, one crop layer, 100 px), for comparability with the
paper, and SAM-1's clean-up of small holes and islands on the full-size masks
(OpenCV) instead of sam2's hole filling on the low-resolution logits, which needs
sam2's CUDA extension and is skipped with a warning on a CPU build anyway. With
the same settings the masks equal sam2's generator's (tests/test_sam2.py).

The `sam2` package (extra `[sam2]`; pyproject says how to install it without a
CUDA torch) supplies the model, `SAM2ImagePredictor` and `utils.amg`; the
generator loop is `ptovs.segment.generator.MaskGenerator`, driven through
`Sam2Points`, which calls the predictor's point path exactly as sam2's own
automatic mask generator does (its `_transforms` and `_predict`).

The model is built from sam2's own config (`SAM2_MODELS`: tiny, small, base_plus,
large) on `device` and loaded from a local checkpoint (`sam_checkpoint`; sam2's
checkpoints hold {"model": state_dict}) by `ptovs.encoders.weights.read_state_dict`;
nothing is downloaded.

`runtime` runs the Hiera image encoder in PyTorch, ONNX Runtime or OpenVINO, or
"auto" (decided on the first image), as SAM's (`ptovs.segment.sam.EncoderRuntime`):
its dict output travels through the export as a tuple (`flat_outputs`) and is
rebuilt (`dict_outputs`).

`Sam2Backend` is how extract-features builds it from its config, and how
preflight checks that the checkpoint loads and fits `sam2_model` (a SAM 1, SAM
2.0 or another size's checkpoint is refused, naming its fix).
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ptovs.compat import import_backend
from ptovs.encoders import runtimes
from ptovs.encoders.weights import read_state_dict, readable_state, state_mismatch
from ptovs.errors import InputError
from ptovs.segment.generator import (
    MaskGenerator,
    default_points_per_batch,
    local_checkpoint,
)
from ptovs.segment.sam import EncoderRuntime, RuntimeOf, SamBackend, require_checkpoint

SAM2_MODELS = {
    "tiny": "sam2.1_hiera_t.yaml",
    "small": "sam2.1_hiera_s.yaml",
    "base_plus": "sam2.1_hiera_b+.yaml",
    "large": "sam2.1_hiera_l.yaml",
}
"""sam2_model → sam2's config (configs/sam2.1/); the checkpoints Meta publishes are
sam2.1_hiera_tiny.pt, _small.pt, _base_plus.pt and _large.pt."""


SAM2_TRUNKS = {
    (96, 12): "tiny",
    (96, 16): "small",
    (112, 24): "base_plus",
    (144, 48): "large",
}
"""(Hiera trunk width, blocks) → sam2_model, from sam2's configs (embed_dim, stages)."""

SAM21_ONLY = (
    "no_obj_embed_spatial",
    "obj_ptr_tpos_proj.weight",
    "obj_ptr_tpos_proj.bias",
)
"""Tensors SAM 2.1 added to SAM 2.0 (same names and shapes otherwise): the video
memory's no-object embedding and object-pointer projection. Their absence tells a
SAM 2.0 checkpoint (sam2_hiera_*.pt) from a SAM 2.1 one."""


def sam2_kind(state: dict) -> tuple[str, str] | None:
    """("2.0" or "2.1", sam2_model or "") of a SAM 2 state dict, None if it
    holds no Hiera trunk."""
    trunk = "image_encoder.trunk."
    patch = state.get(trunk + "patch_embed.proj.weight")
    if patch is None or not hasattr(patch, "shape"):
        return None
    blocks = {
        k[len(trunk) :].split(".")[1] for k in state if k.startswith(trunk + "blocks.")
    }
    size = SAM2_TRUNKS.get((int(patch.shape[0]), len(blocks)), "")
    return ("2.1" if all(k in state for k in SAM21_ONLY) else "2.0"), size


def build_sam2_model(model_type: str = "tiny", device: str = "cpu") -> Any:
    """SAM 2.1 `model_type`, randomly initialised, in eval mode on `device`."""
    if model_type not in SAM2_MODELS:
        raise ValueError(f"sam2_model {model_type!r}: choose from {list(SAM2_MODELS)}")
    import_backend("sam2")  # torchvision's stub first, then sam2's hydra configs
    build = import_backend("sam2.build_sam").build_sam2
    return build(f"configs/sam2.1/{SAM2_MODELS[model_type]}", None, device=device)


def load_sam2(
    checkpoint: str | Path, model_type: str = "tiny", device: str = "cpu"
) -> Any:
    """Build SAM 2.1 `model_type` and load a local checkpoint (weights_only)."""
    path = local_checkpoint(checkpoint, "sam2", "sam2.1_hiera_tiny.pt")
    model = build_sam2_model(model_type, "cpu")
    model.load_state_dict(read_state_dict(path))
    return model.to(device).eval()


def flat_outputs(out: dict) -> tuple[torch.Tensor, ...]:
    """SAM 2.1's `ImageEncoder` output as a tuple: the FPN levels, then their
    position encodings ("vision_features" is the last level: not repeated)."""
    fpn, pos = out["backbone_fpn"], out["vision_pos_enc"]
    return (*fpn, *pos)


def dict_outputs(ys: tuple[torch.Tensor, ...]) -> dict:
    """`flat_outputs`' tuple back as `ImageEncoder` returns it (new lists: the
    model's `forward_image` replaces levels in them)."""
    n = len(ys) // 2
    fpn, pos = list(ys[:n]), list(ys[n:])
    return {"vision_features": fpn[-1], "vision_pos_enc": pos, "backbone_fpn": fpn}


class Sam2Points:
    """sam2's `SAM2ImagePredictor` as the generator's `PointPredictor` (built
    without hole filling: `max_hole_area` = `max_sprinkle_area` = 0)."""

    def __init__(self, predictor: Any):
        self.predictor = predictor
        self.mask_threshold = predictor.mask_threshold

    def set_image(self, image: np.ndarray) -> None:
        self.predictor.set_image(image)

    def predict(self, points: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        pred = self.predictor
        pts = torch.as_tensor(points, dtype=torch.float32, device=pred.device)
        pts = pred._transforms.transform_coords(
            pts, normalize=True, orig_hw=pred._orig_hw[0]
        )
        labels = torch.ones(len(pts), dtype=torch.int, device=pts.device)
        logits, iou, _ = pred._predict(
            pts[:, None, :], labels[:, None], multimask_output=True, return_logits=True
        )
        return logits, iou

    def reset(self) -> None:
        self.predictor.reset_predictor()


class Sam2Segmenter(RuntimeOf, MaskGenerator):
    """SAM 2.1 from `checkpoint` (or `model=`, a built `SAM2Base`); `options` are
    `MaskGenerator`'s (levels, points_per_side, crop_n_layers, the filters,
    level_order: "area" by default). `runtime` runs the image encoder: "torch",
    "onnxruntime", "openvino" or "auto" (`EncoderRuntime`)."""

    name = "sam2"

    def __init__(
        self,
        checkpoint: str | Path = "",
        model_type: str = "tiny",
        device: str = "cpu",
        model: Any = None,
        runtime: str = "torch",
        **options: Any,
    ):
        self.model = (
            model.to(device).eval()
            if model is not None
            else load_sam2(checkpoint, model_type, device)
        )
        encoder = self.model.image_encoder
        size = int(self.model.image_size)
        checkpoint = "" if model is not None else str(checkpoint)

        def key() -> dict[str, Any]:
            """What decides the exported encoder's arithmetic: the weights (the
            checkpoint file's digest; a model given: its tensors'), model, size."""
            weights = (runtimes.file_digest(checkpoint) if checkpoint
                       else runtimes.tensors_digest(encoder.state_dict()))  # fmt: skip
            return {"net": "sam2.1 image encoder", "weights": weights,
                    "model": model_type if checkpoint else "given",
                    "size": size}  # fmt: skip

        self.encoder_runtime = EncoderRuntime(
            encoder, size, key, device, runtime, flat_outputs, dict_outputs
        )
        predictor_cls = import_backend("sam2.sam2_image_predictor").SAM2ImagePredictor
        self.predictor = predictor_cls(self.model)
        amg = import_backend("sam2.utils.amg")
        options.setdefault("level_order", "area")
        options.setdefault("points_per_batch", default_points_per_batch(device))
        super().__init__(Sam2Points(self.predictor), amg, **options)


@functools.lru_cache(maxsize=4)
def _sam2_shapes(model: str) -> dict:
    """{name: shape} of SAM 2.1 `model`'s tensors (built once, randomly)."""
    return {k: v.shape for k, v in build_sam2_model(model).state_dict().items()}


@functools.lru_cache(maxsize=8)
def _sam2_fits(model: str, path: str, size: int, mtime_ns: int) -> None:
    """Load the checkpoint the way the segmenter will and compare it with the
    model's tensors: names, shapes, and none left over (a strict load). A SAM 2.0
    checkpoint, or SAM 2.1 of another size, is named as such with its fix."""
    state = readable_state("sam_checkpoint", path)
    missing, wrong, extra = state_mismatch(state, _sam2_shapes(model), extra=True)
    if not (missing or wrong or extra):
        return
    version, size = sam2_kind(state) or ("", "")
    if size and (version == "2.0" or size != model):
        if version == "2.0":  # SAM 2.1 only added SAM21_ONLY's tensors
            raise InputError(
                f"sam_checkpoint {path} is a SAM 2.0 {size} checkpoint (it lacks SAM "
                "2.1's no_obj_embed_spatial and obj_ptr_tpos_proj); ptovs builds SAM "
                f"2.1: give Meta's sam2.1_hiera_{size}.pt"
                + (
                    f" and set extract-features.sam2_model = {size!r}"
                    if size != model
                    else ""
                )
            )
        raise InputError(
            f"sam_checkpoint {path} is a SAM 2.1 {size} checkpoint, not {model}: set "
            f"extract-features.sam2_model = {size!r} (or give sam2.1_hiera_{model}.pt)"
        )
    what = wrong[:2] or missing[:2] or extra[:2]
    sam1 = any(k.startswith("prompt_encoder.") for k in state)  # SAM 1's names
    raise InputError(
        f"sam_checkpoint {path} is not a SAM 2.1 {model} checkpoint: "
        f"{len(missing)} tensors missing, {len(wrong)} of another shape, "
        f"{len(extra)} left over (e.g. {what}); give sam2.1_hiera_{model}.pt, "
        + (
            "or set extract-features.segmenter = 'sam' (this is a SAM 1 "
            "checkpoint) and sam_model"
            if sam1
            else "or set extract-features.sam2_model to the checkpoint's model"
        )
    )


class Sam2Backend(SamBackend):
    """SAM 2.1 from a local checkpoint (extra [sam2]): SAM's recipe and config,
    with `sam2_model` for `sam_model`."""

    name = "sam2"
    extra = "sam2"
    model_key = "sam2_model"
    config_keys = ("sam_checkpoint", "sam2_model", "sam_points_per_side",
                   "sam_crop_n_layers", "device", "runtime")  # fmt: skip

    def segmenter_class(self) -> type:
        return Sam2Segmenter

    def check(self, config: Any) -> None:
        """`sam2_model` is one, and the checkpoint exists, loads and fits it."""
        if config.sam2_model not in SAM2_MODELS:
            raise InputError(
                f"extract-features.sam2_model {config.sam2_model!r}: choose from "
                f"{list(SAM2_MODELS)}"
            )
        file = f"sam2.1_hiera_{config.sam2_model}.pt"
        ckpt = require_checkpoint(config, "a local SAM 2.1 checkpoint", file)
        st = ckpt.stat()
        _sam2_fits(config.sam2_model, str(ckpt), st.st_size, st.st_mtime_ns)


__all__ = [
    "SAM21_ONLY",
    "SAM2_MODELS",
    "SAM2_TRUNKS",
    "Sam2Backend",
    "Sam2Points",
    "Sam2Segmenter",
    "build_sam2_model",
    "dict_outputs",
    "flat_outputs",
    "load_sam2",
    "sam2_kind",
]

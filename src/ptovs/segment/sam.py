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

`runtime` runs the image encoder (the part of SAM a runtime can take) in PyTorch,
ONNX Runtime or OpenVINO (`ptovs.encoders.runtimes`), or "auto": decided on the
first image (`EncoderRuntime`). The prompt encoder and mask decoder stay in
PyTorch.

`SamBackend` is how extract-features builds it from its config and preflight
checks its checkpoint (`ptovs.segment.backend`); SAM 2.1's backend shares its
checkpoint check (`require_checkpoint`), key and causes.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ptovs.compat import import_backend
from ptovs.encoders import runtimes
from ptovs.encoders.runtimes.choose import relative_diff
from ptovs.encoders.runtimes.tower import Tower
from ptovs.encoders.weights import read_state_dict, where
from ptovs.errors import MissingInputError
from ptovs.segment.backend import SegmenterBackend
from ptovs.segment.generator import (
    LEVEL_OUTPUTS,
    MaskGenerator,
    default_points_per_batch,
    local_checkpoint,
)

log = logging.getLogger(__name__)

# segment-anything's sam_model -> Meta's file (dl.fbaipublicfiles.com/segment_anything)
SAM_FILES = {
    "vit_h": "sam_vit_h_4b8939.pth",
    "vit_l": "sam_vit_l_0b3195.pth",
    "vit_b": "sam_vit_b_01ec64.pth",
}
SAM_GENERATOR = "2"
"""The SAM/SAM 2.1 generator's version: 2 equals upstream's generators mask for mask
and orders SAM 2.1's outputs by area (its features differ from version 1's)."""


def load_sam(checkpoint: str | Path, model_type: str = "vit_h", device: str = "cpu"):
    """Build SAM `model_type` and load a local state dict (weights_only)."""
    sa = import_backend("segment_anything")
    path = local_checkpoint(checkpoint, "sam", "sam_vit_h_4b8939.pth")
    if model_type not in sa.sam_model_registry:
        raise ValueError(
            f"sam_model {model_type!r}: choose from {sorted(sa.sam_model_registry)}"
        )
    model = sa.sam_model_registry[model_type](checkpoint=None)
    model.load_state_dict(read_state_dict(path))
    return model.to(device).eval()


class _OwnForward(torch.nn.Module):
    """What the tower runs and exports: the encoder's own (class) forward, its
    instance's being the runtime's; `flat` makes a dict output a tuple."""

    def __init__(self, encoder: torch.nn.Module, flat: Callable | None = None):
        super().__init__()
        self.encoder = encoder
        self.flat = flat

    def forward(self, x: torch.Tensor) -> Any:
        y = type(self.encoder).forward(self.encoder, x)
        return y if self.flat is None else self.flat(y)


class EncoderRuntime:
    """SAM's (or SAM 2.1's) image encoder run through a `Tower` in `runtime`.

    The encoder stays in the model (its state dict, the attributes the predictor
    reads: `img_size`); only its `forward` is replaced on the instance, as sam2
    does for torch.compile. PyTorch runs the encoder's own forward, untouched;
    another runtime runs the export of `_OwnForward` (`flat`: a dict output as a
    tuple, `rebuild`: the tuple back as the dict the caller reads).

    "auto" is decided on the first image the encoder sees (the segmenter's first
    `set_image`): the fastest installed runtime whose outputs agree with
    PyTorch's on it (max |Δ| / max |PyTorch| ≤ 1e-4, `choose.relative_diff`)
    and that is MIN_SPEEDUP faster, else PyTorch. `report` says which and why
    (None before the first image)."""

    def __init__(
        self,
        encoder: torch.nn.Module,
        size: int,
        key: Callable[[], Mapping[str, Any]],
        device: str | torch.device,
        runtime: str = "torch",
        flat: Callable | None = None,
        rebuild: Callable | None = None,
    ):
        self.own = _OwnForward(encoder, flat)
        self.tower = Tower(self.own, (3, size, size), key, device, runtime)
        self.rebuild = rebuild or (lambda y: y)
        self.report: dict[str, Any] | None = None
        encoder.forward = self.forward

    @property
    def name(self) -> str:
        """The runtime the encoder runs in now."""
        return self.tower.name

    def decide(self, x: torch.Tensor) -> dict[str, Any]:
        """The runtime report, "auto" decided on the input batch `x`."""
        if self.tower.wanted != "auto":
            return {"runtime": self.tower.wanted, "reason": "asked for"}
        report = self.tower.without_sample() or self.tower.check(
            x, compare=relative_diff, unit="images"
        )
        log.info("segmenter: image encoder runtime = %s (auto: %s)",
                 report["runtime"], report["reason"])  # fmt: skip
        return report

    def use(self, report: Mapping[str, Any]) -> None:
        """Run as `report` (one made earlier, e.g. kept in a partial artifact's
        notes) says, without deciding again."""
        self.tower.use(report["runtime"])
        self.report = dict(report)

    def forward(self, x: torch.Tensor) -> Any:
        if self.report is None:
            self.report = self.decide(x)
        if self.tower.name == "torch":
            return type(self.own.encoder).forward(self.own.encoder, x)
        return self.rebuild(self.tower(x))


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


class RuntimeOf:
    """`runtime` and `runtime_report` of a segmenter holding an `EncoderRuntime`
    (`self.encoder_runtime`): SAM's and SAM 2.1's."""

    encoder_runtime: EncoderRuntime

    @property
    def runtime(self) -> str:
        """The runtime the image encoder runs in now."""
        return self.encoder_runtime.name

    @property
    def runtime_report(self) -> dict[str, Any] | None:
        """Which runtime runs the image encoder and why (JSON-serialisable; "auto":
        the figures it was decided on); None before the first image."""
        return self.encoder_runtime.report

    def use_runtime(self, report: Mapping[str, Any]) -> None:
        """Run the image encoder as `report` says (`runtime_report` of an earlier
        run): a resumed run does not decide again."""
        self.encoder_runtime.use(report)


class SamSegmenter(RuntimeOf, MaskGenerator):
    """SAM from `checkpoint` (or `model=`); `options` are `MaskGenerator`'s
    (levels, points_per_side, crop_n_layers, the filters' thresholds,
    level_order: "index" by default, as LangSplat). `runtime` runs the image
    encoder: "torch", "onnxruntime", "openvino" or "auto" (`EncoderRuntime`)."""

    name = "sam"

    def __init__(
        self,
        checkpoint: str | Path = "",
        model_type: str = "vit_h",
        device: str = "cpu",
        model: Any = None,
        runtime: str = "torch",
        **options: Any,
    ):
        self.sa = import_backend("segment_anything")
        self.model = (
            model.to(device).eval()
            if model is not None
            else load_sam(checkpoint, model_type, device)
        )
        encoder = self.model.image_encoder
        checkpoint = "" if model is not None else str(checkpoint)

        def key() -> dict[str, Any]:
            """What decides the exported encoder's arithmetic: the weights (the
            checkpoint file's digest; a model given: its tensors'), type, size."""
            weights = (runtimes.file_digest(checkpoint) if checkpoint
                       else runtimes.tensors_digest(encoder.state_dict()))  # fmt: skip
            return {"net": "sam image encoder", "weights": weights,
                    "model": model_type if checkpoint else "given",
                    "size": int(encoder.img_size)}  # fmt: skip

        self.encoder_runtime = EncoderRuntime(
            encoder, int(encoder.img_size), key, device, runtime
        )
        self.predictor = self.sa.SamPredictor(self.model)
        amg = import_backend("segment_anything.utils.amg")
        options.setdefault("points_per_batch", default_points_per_batch(device))
        super().__init__(SamPoints(self.predictor), amg, **options)


def require_checkpoint(config: Any, what: str, file: str) -> Path:
    """segmenter "sam" or "sam2": the local `sam_checkpoint`, or a
    MissingInputError naming `what` it must be and the publisher's `file`."""
    ckpt = Path(str(config.sam_checkpoint)).expanduser()
    if not str(config.sam_checkpoint) or not ckpt.is_file():
        raise MissingInputError(
            f"segmenter = {config.segmenter!r} needs sam_checkpoint = {what} "
            f"({str(ckpt) if str(config.sam_checkpoint) else 'none given'}); "
            "--set extract-features.sam_checkpoint=FILE"
            + where(file, "Meta" if file else "")
        )
    return ckpt


class SamBackend(SegmenterBackend):
    """segment-anything from a local checkpoint (extra [sam])."""

    name = "sam"
    extra = "sam"
    model_key = "sam_model"
    config_keys = ("sam_checkpoint", "sam_model", "sam_points_per_side",
                   "sam_crop_n_layers", "device", "runtime")  # fmt: skip

    def build(self, config: Any, levels: tuple, scene_root: Path | None) -> Any:
        return self.segmenter_class()(
            checkpoint=config.sam_checkpoint,
            model_type=getattr(config, self.model_key),
            levels=levels,
            points_per_side=config.sam_points_per_side,
            crop_n_layers=config.sam_crop_n_layers,
            device=config.device,
            runtime=config.runtime,
        )

    def segmenter_class(self) -> type:
        return SamSegmenter

    def check(self, config: Any) -> None:
        """The checkpoint exists."""
        file = SAM_FILES.get(str(getattr(config, "sam_model", "")), "")
        require_checkpoint(config, "a local SAM checkpoint", file)

    def extra_key(self, config: Any) -> dict[str, str]:
        return {"sam_generator": SAM_GENERATOR}

    def empty_causes(self, config: Any) -> list[str]:
        model = getattr(config, self.model_key)
        return [
            f"a wrong or randomly initialised checkpoint (sam_checkpoint = "
            f"{config.sam_checkpoint!r} for segmenter {config.segmenter!r}, model "
            f"{model!r})",
            f"prompts too sparse (sam_points_per_side = {config.sam_points_per_side}"
            f", sam_crop_n_layers = {config.sam_crop_n_layers})",
        ]


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


__all__ = [
    "LEVEL_OUTPUTS",
    "SAM_FILES",
    "SAM_GENERATOR",
    "EncoderRuntime",
    "SamBackend",
    "SamPoints",
    "SamSegmenter",
    "require_checkpoint",
    "load_sam",
    "tiny_sam",
]

"""OpenCLIP as the image/text encoder (extra `[clip]`; docs/method.md §4).

The paper uses `ViT-B-16` / `laion2b_s34b_b88k`. Nothing is downloaded: the
weights come from a local checkpoint file (`clip_checkpoint`), loaded with
`weights_only=True`. Crops arrive as LangSplat prepares them (masked, bbox crop,
square pad, 224², RGB in [0, 1]); here they are normalised with CLIP's mean and
std, encoded in batches (fp16 autocast on CUDA, fp32 on CPU) and L2-normalised.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ptovs.compat import import_backend

log = logging.getLogger(__name__)

CLIP_MEAN = (0.48145466, 0.4578275, 0.40821073)
CLIP_STD = (0.26862954, 0.26130258, 0.27577711)
TINY = "ptovs-tiny-test"
TINY_CONFIG = dict(
    embed_dim=64,
    vision_cfg=dict(image_size=224, layers=2, width=64, patch_size=32, head_width=32),
    text_cfg=dict(context_length=77, vocab_size=49408, width=64, heads=2, layers=2),
)


def register_tiny() -> str:
    """Register a 3.6 M-parameter OpenCLIP config for tests (docs/environment.md §5)."""
    oc = import_backend("open_clip")
    oc.factory._MODEL_CONFIGS[TINY] = TINY_CONFIG  # private API: open_clip 3.3 pinned
    return TINY


def _state_dict(path: Path) -> dict[str, torch.Tensor]:
    obj = torch.load(path, map_location="cpu", weights_only=True)
    if isinstance(obj, dict) and "state_dict" in obj:
        obj = obj["state_dict"]
    if not isinstance(obj, dict):
        raise ValueError(f"clip_checkpoint {path}: not a state dict")
    return {k.removeprefix("module."): v for k, v in obj.items()}


class OpenClipEncoder:
    name = "openclip"

    def __init__(
        self,
        model: str = "ViT-B-16",
        checkpoint: str | Path = "",
        device: str = "cpu",
        batch_size: int = 64,
        random_weights: bool = False,
    ):
        """Args:
        model: OpenCLIP architecture name (`open_clip.list_models()`).
        checkpoint: local state dict of that model (required unless random_weights).
        device: "cpu" or "cuda".
        batch_size: crops per forward pass.
        random_weights: build untrained (tests only).
        """
        oc = import_backend("open_clip")
        if model not in oc.list_models():
            raise ValueError(f"clip_model {model!r} unknown to open_clip")
        self.model_name = model
        net = oc.create_model(model, pretrained=None)
        if not random_weights:
            path = Path(checkpoint)
            if not str(checkpoint):
                raise ValueError(
                    "encoder = 'openclip' needs clip_checkpoint = a local OpenCLIP "
                    "state dict (the paper: ViT-B-16 laion2b_s34b_b88k); nothing is "
                    "downloaded"
                )
            if not path.is_file():
                raise FileNotFoundError(f"clip_checkpoint {path} does not exist")
            missing, unexpected = net.load_state_dict(_state_dict(path), strict=False)
            if missing:
                raise ValueError(
                    f"clip_checkpoint {path} does not fit {model}: missing "
                    f"{missing[:3]}{'...' if len(missing) > 3 else ''}"
                )
            if unexpected:
                log.warning("clip_checkpoint: %d unused tensors", len(unexpected))
        self.device = torch.device(device)
        self.net: Any = net.to(self.device).eval()
        self.tokenizer = oc.get_tokenizer(model)
        self.batch_size = int(batch_size)
        self.dim = int(self.net.visual.output_dim)
        size = self.net.visual.image_size  # int or (H, W)
        self.size = int(size[0] if isinstance(size, (tuple, list)) else size)
        self._mean = torch.tensor(CLIP_MEAN, device=self.device).view(1, 3, 1, 1)
        self._std = torch.tensor(CLIP_STD, device=self.device).view(1, 3, 1, 1)

    def _autocast(self):
        if self.device.type == "cuda":
            return torch.autocast("cuda", dtype=torch.float16)
        return torch.autocast("cpu", enabled=False)

    @torch.inference_mode()
    def encode_images(self, crops: np.ndarray) -> np.ndarray:
        crops = np.asarray(crops)
        if crops.ndim != 4 or crops.shape[-1] != 3:
            raise ValueError(f"crops must be [B, S, S, 3], got {crops.shape}")
        out = np.zeros((len(crops), self.dim), np.float32)
        for i in range(0, len(crops), self.batch_size):
            x = torch.from_numpy(np.ascontiguousarray(crops[i : i + self.batch_size]))
            x = x.to(self.device, torch.float32).permute(0, 3, 1, 2)
            if x.shape[-1] != self.size:
                x = torch.nn.functional.interpolate(
                    x, size=(self.size, self.size), mode="bicubic", align_corners=False
                )
            x = (x - self._mean) / self._std
            with self._autocast():
                f = self.net.encode_image(x)
            f = torch.nn.functional.normalize(f.float(), dim=-1)
            out[i : i + len(f)] = f.cpu().numpy()
        return out

    @torch.inference_mode()
    def encode_texts(self, texts: list[str]) -> np.ndarray:
        if not texts:
            return np.zeros((0, self.dim), np.float32)
        tokens = self.tokenizer(list(texts)).to(self.device)
        with self._autocast():
            f = self.net.encode_text(tokens)
        return torch.nn.functional.normalize(f.float(), dim=-1).cpu().numpy()

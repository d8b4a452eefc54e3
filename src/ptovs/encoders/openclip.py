"""OpenCLIP as the image/text encoder (extra `[clip]`; docs/guide.md).

Any open_clip model name works, with its weights from a local checkpoint file
(`clip_checkpoint`, loaded with `weights_only=True`; nothing is downloaded). The
image side is fed the way the trained model expects: its pretrained tag's
preprocessing (mean, std, resize mode and interpolation: OpenAI's statistics for
CLIP, mean 0 / std 1 for MobileCLIP, 0.5 / 0.5 for SigLIP), at its own input
size. Models whose towers train with re-parameterisable branches (MobileCLIP's
FastViT) are folded for inference with timm's `reparameterize_model`.

Crops arrive as LangSplat prepares them (masked, bbox crop, square pad, RGB in
[0, 1]). A crop already at the model's input size needs no resizing (the
upstream transform would be the identity on it) and is normalised as a batch; a
crop of any other size goes through open_clip's own transform.

Precision: "fp32" (the reference), "bf16" (a bfloat16 copy of the image tower,
several times faster on CPUs with AVX-512 BF16 or AMX) or "auto": extract-features
encodes a sample of the scene's own crops both ways and keeps bf16 only if it
agrees with fp32 (`check_precision`). Texts are always encoded in fp32.
"""

from __future__ import annotations

import contextlib
import copy
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ptovs.compat import import_backend

log = logging.getLogger(__name__)

PRECISIONS = ("fp32", "bf16", "auto")
TINY = "ptovs-tiny-test"
TINY_CONFIG = dict(
    embed_dim=64,
    vision_cfg=dict(image_size=224, layers=2, width=64, patch_size=32, head_width=32),
    text_cfg=dict(context_length=77, vocab_size=49408, width=64, heads=2, layers=2),
)
# The bar a reduced-precision image tower must clear on the scene's own crops.
MIN_CENTRED_COSINE = 0.995
MIN_TOP1_AGREEMENT = 0.98
# Phrases for the top-1 agreement check (any fixed list of things in landmark photos).
CHECK_PHRASES = (
    "column", "arch", "statue", "window", "door", "roof", "dome", "tower",
    "stairs", "fountain", "wall", "sky", "tree", "person", "water", "sculpture",
    "relief", "balcony", "clock", "flag", "car", "bench", "lamp", "gate",
)  # fmt: skip


def register_tiny() -> str:
    """Register a 3.6 M-parameter OpenCLIP config for tests (docs/environment.md §5)."""
    oc = import_backend("open_clip")
    oc.factory._MODEL_CONFIGS[TINY] = TINY_CONFIG  # private API: open_clip 3.3 pinned
    return TINY


@contextlib.contextmanager
def _quiet_open_clip():
    """Drop open_clip's "No pretrained weights loaded ... initialized randomly":
    the weights are loaded right after, from the user's checkpoint."""

    def keep(record: logging.LogRecord) -> bool:
        return "No pretrained weights loaded" not in record.getMessage()

    root = logging.getLogger()
    root.addFilter(keep)
    try:
        yield
    finally:
        root.removeFilter(keep)


@dataclass(frozen=True)
class Preprocess:
    """What the trained model expects of an image (open_clip's per-tag config)."""

    size: int
    mean: tuple[float, float, float]
    std: tuple[float, float, float]
    interpolation: str
    resize_mode: str
    tag: str  # the pretrained tag it came from ("" = open_clip's defaults)


def model_config(model: str) -> dict:
    """open_clip's config of `model`, or ValueError naming the choices."""
    oc = import_backend("open_clip")
    cfg = oc.get_model_config(model)
    if cfg is None:
        raise ValueError(
            f"clip_model {model!r} is not an OpenCLIP model (e.g. ViT-B-32, "
            "ViT-B-16, MobileCLIP2-S0, ViT-B-16-SigLIP2; `open_clip.list_models()`)"
        )
    return cfg


def preprocess_for(model: str, tag: str = "") -> Preprocess:
    """The preprocessing of `model`'s pretrained tag `tag`.

    Without a tag: the tags' shared preprocessing when every tag of the model
    agrees (ViT-B-16's openai, laion2b_*, datacomp_* ... all use OpenAI's
    statistics), open_clip's defaults for a model with no tags, and a ValueError
    naming the tags when they disagree."""
    oc = import_backend("open_clip")
    cfg = model_config(model)
    vision = cfg.get("vision_cfg", {})
    size = vision.get("image_size", 224)
    size = int(size[0] if isinstance(size, (tuple, list)) else size)
    keys = ("mean", "std", "interpolation", "resize_mode")
    default = oc.transform.PreprocessCfg()
    tags = oc.list_pretrained_tags_by_model(model)
    if tag:
        if tag not in tags:
            raise ValueError(
                f"clip_pretrained {tag!r} is not a tag of {model} "
                f"(tags: {', '.join(tags) or 'none'})"
            )
        chosen = [tag]
    else:
        chosen = tags
    found = {
        tuple(tuple(v) if isinstance(v, list) else v for v in
              (oc.get_pretrained_cfg(model, t).get(k, getattr(default, k))
               for k in keys))
        for t in chosen
    }  # fmt: skip
    if not found:
        values = tuple(getattr(default, k) for k in keys)
    elif len(found) == 1:
        values = next(iter(found))
    else:
        raise ValueError(
            f"{model}'s pretrained tags preprocess differently ({', '.join(tags)}); "
            "set clip_pretrained to the tag of your checkpoint"
        )
    mean, std, interp, mode = values
    return Preprocess(
        size, tuple(map(float, mean)), tuple(map(float, std)), interp, mode,
        tag or (chosen[0] if len(chosen) == 1 else ""),
    )  # fmt: skip


def _state_dict(path: Path) -> dict[str, torch.Tensor]:
    """A checkpoint's tensors: a `.safetensors` file (as the model hubs ship
    open_clip weights) or a torch file read with weights_only=True."""
    path = Path(path)
    if path.suffix == ".safetensors":
        from safetensors.torch import load_file

        return {k.removeprefix("module."): v for k, v in load_file(path).items()}
    obj = torch.load(path, map_location="cpu", weights_only=True)
    if isinstance(obj, dict) and "state_dict" in obj:
        obj = obj["state_dict"]
    if not isinstance(obj, dict):
        raise ValueError(f"clip_checkpoint {path}: not a state dict")
    return {k.removeprefix("module."): v for k, v in obj.items()}


def build_net(model: str, checkpoint: str | Path | None) -> Any:
    """open_clip's `model` with the checkpoint's weights (None: random, tests)."""
    oc = import_backend("open_clip")
    model_config(model)
    with _quiet_open_clip():
        net = oc.create_model(model, pretrained=None)
    if checkpoint is not None:
        path = Path(checkpoint)
        if not str(checkpoint):
            raise ValueError(
                "encoder = 'openclip' needs clip_checkpoint = a local OpenCLIP "
                "state dict (e.g. MobileCLIP2-S0 dfndr2b, ViT-B-16 "
                "laion2b_s34b_b88k); nothing is downloaded"
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
    return net.eval()


def reparameterize(net: Any) -> Any:
    """Fold re-parameterisable branches (MobileCLIP's FastViT blocks) for
    inference; a model without them is returned as it is."""
    if not any(hasattr(m, "reparameterize") for m in net.modules()):
        return net
    from timm.utils import reparameterize_model

    return reparameterize_model(net)


def _tokenizer(model: str, tokenizer: str | Path) -> Any:
    oc = import_backend("open_clip")
    text = model_config(model).get("text_cfg", {})
    if not text.get("hf_tokenizer_name"):
        return oc.get_tokenizer(model)
    if not str(tokenizer):
        raise ValueError(
            f"{model} uses the Hugging Face tokenizer {text['hf_tokenizer_name']!r}, "
            "which would be downloaded; give its local folder as clip_tokenizer "
            "(and install transformers)"
        )
    path = Path(tokenizer)
    if not path.is_dir():
        raise FileNotFoundError(f"clip_tokenizer {path} is not a folder")
    return oc.tokenizer.HFTokenizer(
        str(path),
        context_length=text.get("context_length", 77),
        **text.get("tokenizer_kwargs", {}),
    )


def centred_agreement(
    ref: np.ndarray, fast: np.ndarray, text: np.ndarray
) -> dict[str, float]:
    """How far reduced-precision image features `fast` stray from `ref` (fp32).

    worst_centred_cosine: the smallest cosine between a crop's two features after
    both have the sample's fp32 mean subtracted (CLIP features share a large
    common direction that makes raw cosines near 1 whatever the error);
    top1_agreement: the share of crops whose best phrase among `text` is the same.
    """
    ref = np.asarray(ref, np.float64)
    fast = np.asarray(fast, np.float64)
    mu = ref.mean(axis=0, keepdims=True)
    a, b = ref - mu, fast - mu
    na, nb = np.linalg.norm(a, axis=1), np.linalg.norm(b, axis=1)
    ok = (na > 1e-12) & (nb > 1e-12)
    cos = np.ones(len(ref))
    cos[ok] = (a[ok] * b[ok]).sum(1) / (na[ok] * nb[ok])
    cos[~ok] = np.where(np.abs(na - nb)[~ok] < 1e-6, 1.0, 0.0)
    if not np.isfinite(fast).all():
        cos[:] = -1.0
    t = np.asarray(text, np.float64)
    top = float(np.mean((ref @ t.T).argmax(1) == (fast @ t.T).argmax(1)))
    return {"worst_centred_cosine": float(cos.min()), "top1_agreement": top}


class OpenClipEncoder:
    name = "openclip"

    def __init__(
        self,
        model: str = "ViT-B-16",
        checkpoint: str | Path = "",
        device: str = "cpu",
        batch_size: int = 64,
        random_weights: bool = False,
        pretrained: str = "",
        tokenizer: str | Path = "",
        precision: str = "fp32",
    ):
        """Args:
        model: OpenCLIP architecture name (`open_clip.list_models()`).
        checkpoint: local state dict of that model (required unless random_weights).
        device: "cpu" or "cuda".
        batch_size: crops per forward pass.
        random_weights: build untrained (tests only).
        pretrained: the checkpoint's open_clip tag (e.g. "dfndr2b"), which
            decides the preprocessing; needed only where a model's tags differ.
        tokenizer: local folder of a Hugging Face tokenizer (SigLIP models only).
        precision: "fp32", "bf16" or "auto" (fp32 until `check_precision`
            clears bf16 on the scene's crops).
        """
        if precision not in PRECISIONS:
            raise ValueError(f"precision {precision!r}: choose from {PRECISIONS}")
        self.model_name = model
        self.pre = preprocess_for(model, pretrained)
        net = build_net(model, None if random_weights else checkpoint)
        self.device = torch.device(device)
        self.net: Any = reparameterize(net).to(self.device).eval()
        self._tokenizer_path = tokenizer
        self._tok: Any = None
        self.batch_size = int(batch_size)
        self.dim = int(model_config(model)["embed_dim"])
        self.size = self.pre.size  # the crop side the model reads
        self._mean = torch.tensor(self.pre.mean, device=self.device).view(1, 3, 1, 1)
        self._std = torch.tensor(self.pre.std, device=self.device).view(1, 3, 1, 1)
        self._transform: Any = None
        self.precision_wanted = precision
        self.precision = "bf16" if precision == "bf16" else "fp32"
        self._fast: Any = None

    # ------------------------------------------------------------ preprocessing
    def _upstream_transform(self) -> Any:
        if self._transform is None:
            oc = import_backend("open_clip")
            cfg = oc.transform.PreprocessCfg(
                size=self.size, mean=self.pre.mean, std=self.pre.std,
                interpolation=self.pre.interpolation,
                resize_mode=self.pre.resize_mode,
            )  # fmt: skip
            self._transform = oc.transform.image_transform_v2(cfg, is_train=False)
        return self._transform

    def preprocess(self, crops: np.ndarray) -> torch.Tensor:
        """Crops [B, S, S, 3] RGB in [0, 1] (or uint8) → the model's input batch."""
        crops = np.asarray(crops)
        if crops.ndim != 4 or crops.shape[-1] != 3:
            raise ValueError(f"crops must be [B, S, S, 3], got {crops.shape}")
        if crops.dtype != np.uint8:
            if not np.isfinite(crops).all():
                raise ValueError("crops hold non-finite values")
            crops = np.clip(np.rint(crops * 255.0), 0, 255).astype(np.uint8)
        if crops.shape[1:3] == (self.size, self.size):
            x = torch.from_numpy(np.ascontiguousarray(crops)).to(self.device)
            x = x.permute(0, 3, 1, 2).to(torch.float32) / 255.0
            return (x - self._mean) / self._std
        from PIL import Image

        tf = self._upstream_transform()
        x = torch.stack([tf(Image.fromarray(c)) for c in crops])
        return x.to(self.device)

    # ------------------------------------------------------------ precision
    def _fast_tower(self) -> Any:
        if self._fast is None:
            self._fast = copy.deepcopy(self.net.visual).to(torch.bfloat16).eval()
        return self._fast

    @torch.inference_mode()
    def _forward(self, x: torch.Tensor, precision: str) -> torch.Tensor:
        if precision == "bf16":
            f = self._fast_tower()(x.to(torch.bfloat16)).float()
        elif self.device.type == "cuda":
            with torch.autocast("cuda", dtype=torch.float16):
                f = self.net.encode_image(x).float()
        else:
            f = self.net.encode_image(x)
        return torch.nn.functional.normalize(f.float(), dim=-1)

    def check_precision(self, crops: np.ndarray) -> dict:
        """Encode `crops` (a sample of the scene's own) in fp32 and bf16 and keep
        bf16 only if the worst centred cosine is at least MIN_CENTRED_COSINE and
        the phrases' top-1 agreement at least MIN_TOP1_AGREEMENT; otherwise fp32.

        Returns the report stored with the features (precision kept, the two
        figures, the bar, the sample size)."""
        ref = self._encode(crops, "fp32")
        fast = self._encode(crops, "bf16")
        fig = centred_agreement(ref, fast, self.encode_texts(list(CHECK_PHRASES)))
        ok = (
            fig["worst_centred_cosine"] >= MIN_CENTRED_COSINE
            and fig["top1_agreement"] >= MIN_TOP1_AGREEMENT
        )
        self.precision = "bf16" if ok else "fp32"
        if not ok:
            self._fast = None
        return {
            "precision": self.precision,
            "checked": "bf16",
            "crops": int(len(crops)),
            **fig,
            "bar": {
                "worst_centred_cosine": MIN_CENTRED_COSINE,
                "top1_agreement": MIN_TOP1_AGREEMENT,
            },
        }

    # ------------------------------------------------------------ encoding
    def _encode(self, crops: np.ndarray, precision: str) -> np.ndarray:
        crops = np.asarray(crops)
        out = np.zeros((len(crops), self.dim), np.float32)
        for i in range(0, len(crops), self.batch_size):
            x = self.preprocess(crops[i : i + self.batch_size])
            f = self._forward(x, precision)
            out[i : i + len(f)] = f.cpu().numpy()
        return out

    def encode_images(self, crops: np.ndarray) -> np.ndarray:
        return self._encode(crops, self.precision)

    @torch.inference_mode()
    def encode_texts(self, texts: list[str]) -> np.ndarray:
        if not texts:
            return np.zeros((0, self.dim), np.float32)
        if self._tok is None:
            self._tok = _tokenizer(self.model_name, self._tokenizer_path)
        tokens = self._tok(list(texts)).to(self.device)
        if self.device.type == "cuda":
            with torch.autocast("cuda", dtype=torch.float16):
                f = self.net.encode_text(tokens)
        else:
            f = self.net.encode_text(tokens)
        return torch.nn.functional.normalize(f.float(), dim=-1).cpu().numpy()

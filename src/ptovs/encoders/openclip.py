"""OpenCLIP as the image/text encoder (extra `[clip]`; docs/guide.md). The model,
its preprocessing and tokenizer are built in `ptovs.encoders.openclip_net`.

Any built-in open_clip model name works, with its weights from a local checkpoint
file (`clip_checkpoint`); nothing is downloaded. The features are those upstream
open_clip 3.3 computes with the same file, model and pretrained tag, that is
`create_model_and_transforms(model, pretrained=tag)` with the tag's table entry
pointed at the file, and with QuickGELU where the tag was trained with it (the
`<model>-quickgelu` name; upstream itself only warns when the activation and the
tag disagree). What is honoured, and what is refused in one line:

- The tag (`clip_pretrained`, normalised as upstream: lower case, '-' → '_')
  decides the preprocessing (mean, std, interpolation, resize mode, input size)
  and the activation (`quick_gelu`: OpenAI's, DFN's and MetaCLIP's ViT-B-16 and
  ViT-B-32, laion400m's ViT-B-32, ...). Without a tag, the model's tags must agree
  on both; where they do not (ViT-B-16: openai is QuickGELU, laion2b is not) the
  encoder refuses, naming the tags, the setting and `<model>-quickgelu`.
- The checkpoint loads through upstream's `load_checkpoint` (its key
  conversions), read with `weights_only=True`; a tensor missing or left over is
  refused (upstream loads strictly).
- Crops at the model's input size are normalised as a batch (the upstream
  transform is the identity on them up to ToTensor + Normalize); a crop of any
  other size goes through open_clip's own eval transform. Square crops resized
  by `prepare_crop(..., resample=encoder.resample)` (PIL, the tag's
  interpolation) equal the upstream transform of the square-padded crop at its
  native resolution: for a square image every resize mode (shortest, squash,
  longest) is that one PIL resize.
- Re-parameterisable towers (MobileCLIP's FastViT) are folded for inference with
  timm's `reparameterize_model` (upstream's outputs, up to float rounding).
- CoCa models work: encode_image / encode_text are the model's own.
- A Hugging Face text tower (`text_cfg.hf_model_name`: roberta, xlm-roberta, mT5,
  NLLB) is built from its config in the local folder `clip_tokenizer` (config.json
  and tokenizer files of that HF model; its weights come from the checkpoint),
  never from the hub; without that folder, or without transformers, the encoder
  refuses. Names with an `hf-hub:` or `local-dir:` schema are refused.

Precision: "fp32" is fp32 on every device (no autocast) and texts are always
fp32. "bf16" is upstream's `precision="pure_bf16"`: a bfloat16 copy of the model,
its own `encode_image` on a bfloat16 input, normalised in fp32. "auto" asks
`bf16_is_fast` (CPU capability and flags, a short matmul probe) and, only where
bf16 can be faster, encodes a sample of the scene's own crops both ways
(`check_precision`); bf16 is kept only where it agrees with fp32 within the bars
below and was faster on it. `precision_without_sample` asks first, so where bf16
cannot be faster no sample is segmented at all.
"""

from __future__ import annotations

import copy
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ptovs.compat import import_backend
from ptovs.encoders import runtimes
from ptovs.encoders.openclip_net import (
    TINY,
    TINY_CONFIG,
    Preprocess,
    _tokenizer,
    build_net,
    clean_tag,
    hf_text_tower,
    model_config,
    preprocess_for,
    register_tiny,
    reparameterize,
)
from ptovs.encoders.runtimes.tower import Tower

log = logging.getLogger(__name__)

PRECISIONS = ("fp32", "bf16", "auto")
RESAMPLES = ("bilinear", "bicubic")
# The bars a reduced-precision image tower must clear on the scene's own crops.
# A relevancy score is min_j sigmoid(τ(p − n_j)), p and n_j a feature's cosines
# with the query q and canonical phrase t_j (ptovs.field.relevancy), so a feature
# error δ moves it by at most (τ/4)·|δ·(q − t_j)| ≤ (τ/4)·‖δ‖·‖q − t_j‖. The
# centred cosine c bounds ‖δ‖ ≈ ‖f − μ‖·sqrt(2(1 − c)) only relative to the
# sample's spread ‖f − μ‖ (a tight sample of one facade scores low for the same
# δ), and c = 0.995 alone would allow |Δr| up to 0.25·‖f − μ‖·‖q − t‖ ≈ 0.1 with
# the error along q − t: so c is a floor against gross failure, and the bar that
# bounds the maps is MAX_RELEVANCY_CHANGE, measured directly on the sample with
# the 24 check phrases as queries against the canonical phrases. 0.01 moves a
# relative-threshold mask's normalised score by at most 2·0.01/R (R the map's
# range, ≥ 0.3 where it holds an object): ≤ 0.07 on the 0.7 cut, worst case.
MIN_CENTRED_COSINE = 0.995
MIN_TOP1_AGREEMENT = 0.98
MAX_RELEVANCY_CHANGE = 0.01
RELEVANCY_TEMPERATURE = 10.0  # τ of ptovs.field.relevancy.relevancy
# ptovs.field.relevancy.CANONICAL (copied: encoders sit below field)
CANONICAL = ("object", "things", "scene", "sky", "building")
# bf16 must beat fp32 by this factor on the probe before any model runs in it
MIN_PROBE_SPEEDUP = 1.3
# x86: AVX-512 BF16 or AMX instructions; aarch64: the BF16 extension
BF16_FLAGS = ("avx512_bf16", "amx_bf16", "bf16")
# Phrases for the top-1 agreement check (any fixed list of things in landmark photos).
CHECK_PHRASES = (
    "column", "arch", "statue", "window", "door", "roof", "dome", "tower",
    "stairs", "fountain", "wall", "sky", "tree", "person", "water", "sculpture",
    "relief", "balcony", "clock", "flag", "car", "bench", "lamp", "gate",
)  # fmt: skip


# ------------------------------------------------------------------ bf16 or not


def _cpu_flags() -> set[str]:
    """The CPU's feature flags (/proc/cpuinfo's flags or Features; empty where
    there is none)."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return set()
    flags: set[str] = set()
    for line in text.splitlines():
        key, _, value = line.partition(":")
        if key.strip() in ("flags", "Features"):
            flags.update(value.split())
    return flags


def _matmul_probe(width: int) -> dict[str, float]:
    """Best-of-3 seconds of a [256, width] x [width, 4·width] matmul (an MLP
    layer of a tower that wide) in fp32 and in bf16."""
    g = torch.Generator().manual_seed(0)
    x = torch.randn(256, width, generator=g)
    w = torch.randn(width, 4 * width, generator=g)
    out = {}
    for name, dtype in (("fp32_s", torch.float32), ("bf16_s", torch.bfloat16)):
        a, b = x.to(dtype), w.to(dtype)
        a @ b  # warm-up: the first call picks and builds the kernel
        best = float("inf")
        for _ in range(3):
            t0 = time.perf_counter()
            a @ b
            best = min(best, time.perf_counter() - t0)
        out[name] = best
    out["speedup"] = out["fp32_s"] / max(out["bf16_s"], 1e-12)
    return out


def bf16_is_fast(device: str | torch.device, width: int = 768) -> tuple[bool, dict]:
    """Whether bf16 can be faster than fp32 on `device`, decided in well under a
    second (no model runs).

    CUDA: bf16 supported → True. CPU: a candidate only where the CPU has bf16
    instructions (flags avx512_bf16 or amx_bf16, aarch64's bf16); then a matmul
    of the model's width must run at least MIN_PROBE_SPEEDUP× faster in bf16.
    Plain AVX2 or AVX-512 CPUs emulate bf16 (14× slower measured on MobileCLIP2-S0's
    image tower), so there no bf16 work is done at all.

    Args:
        device: "cpu", "cuda" or a torch.device.
        width: the tower's width (the probe's matmul size).

    Returns:
        (fast, evidence): evidence is JSON-serialisable (capability, bf16 flags
        found, probe times or None, the rule).
    """
    dev = torch.device(device)
    if dev.type == "cuda":
        ok = bool(torch.cuda.is_available() and torch.cuda.is_bf16_supported())
        return ok, {"device": "cuda", "bf16_supported": ok, "rule": "CUDA bf16"}
    capability = str(torch.backends.cpu.get_cpu_capability())
    found = sorted(_cpu_flags() & set(BF16_FLAGS))
    evidence: dict[str, Any] = {
        "device": dev.type,
        "capability": capability,
        "bf16_flags": found,
        "probe": None,
        "rule": f"bf16 CPU flags and a matmul >= {MIN_PROBE_SPEEDUP}x faster",
    }
    if dev.type != "cpu" or not found:
        return False, evidence
    probe = _matmul_probe(int(width))
    evidence["probe"] = {"width": int(width), **probe}
    return bool(probe["speedup"] >= MIN_PROBE_SPEEDUP), evidence


def centred_agreement(
    ref: np.ndarray,
    fast: np.ndarray,
    text: np.ndarray,
    canonical: np.ndarray | None = None,
) -> dict[str, float]:
    """How far reduced-precision image features `fast` stray from `ref` (fp32).

    worst_centred_cosine: the smallest cosine between a crop's two features after
    both have the sample's fp32 mean subtracted (CLIP features share a large
    common direction that makes raw cosines near 1 whatever the error);
    top1_agreement: the share of crops whose best phrase among `text` is the same;
    worst_feature_distance: the largest ‖ref − fast‖ of a crop; with `canonical`
    (phrase embeddings), worst_relevancy_change: the largest change of a crop's
    relevancy score (field.relevancy: min over canonical phrases of
    sigmoid(τ(p − n)), τ = 10) for each phrase of `text` as the query.
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
    finite = bool(np.isfinite(fast).all())
    if not finite:
        cos[:] = -1.0
    t = np.asarray(text, np.float64)
    top = float(np.mean((ref @ t.T).argmax(1) == (fast @ t.T).argmax(1)))
    out = {
        "worst_centred_cosine": float(cos.min()),
        "top1_agreement": top,
        "worst_feature_distance": float(np.linalg.norm(ref - fast, axis=1).max())
        if finite
        else 2.0,
    }
    if canonical is not None:
        c = np.asarray(canonical, np.float64)

        def rel(f: np.ndarray) -> np.ndarray:  # [B, Q]
            d = (f @ t.T)[:, :, None] - (f @ c.T)[:, None, :]
            return (1.0 / (1.0 + np.exp(-RELEVANCY_TEMPERATURE * d))).min(-1)

        change = np.abs(rel(ref) - rel(fast)).max() if finite else 1.0
        out["worst_relevancy_change"] = float(change)
    return out


class _ImageTower(torch.nn.Module):
    """The image side as one module (what a runtime exports): encode_image."""

    def __init__(self, net: Any):
        super().__init__()
        self.net = net

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net.encode_image(x)


class OpenClipEncoder:
    name = "openclip"

    def __init__(
        self,
        model: str = "ViT-B-16",
        checkpoint: str | Path = "",
        device: str = "cpu",
        batch_size: int = 0,
        random_weights: bool = False,
        pretrained: str = "",
        tokenizer: str | Path = "",
        precision: str = "fp32",
        runtime: str = "torch",
    ):
        """Args:
        model: OpenCLIP architecture name (`open_clip.list_models()`).
        checkpoint: local state dict of that model (required unless random_weights).
        device: "cpu" or "cuda".
        batch_size: crops per forward pass (0: the runtime's own, `Tower.batch`).
        random_weights: build untrained (tests only).
        pretrained: the checkpoint's open_clip tag (e.g. "dfndr2b"), which
            decides the preprocessing and QuickGELU; needed only where a
            model's tags differ.
        tokenizer: local folder of a Hugging Face tokenizer (SigLIP models), or
            of a Hugging Face text tower's config and tokenizer (roberta, ...).
        precision: "fp32", "bf16" or "auto" (fp32 until `check_precision`
            clears bf16 on the scene's crops).
        runtime: what runs the image tower in fp32: "torch", "onnxruntime",
            "openvino" or "auto" (PyTorch until `check_runtime` decides on the
            scene's crops; `ptovs.encoders.runtimes`).
        """
        if precision not in PRECISIONS:
            raise ValueError(f"precision {precision!r}: choose from {PRECISIONS}")
        self.model_name = model
        self.pre = preprocess_for(model, pretrained)
        net = build_net(
            model,
            None if random_weights else checkpoint,
            quick_gelu=self.pre.quick_gelu,
            hf_folder=tokenizer,
        )
        self.device = torch.device(device)
        self.net: Any = reparameterize(net).to(self.device).eval()
        self._tokenizer_path = tokenizer
        self._tok: Any = None
        self.batch_size = int(batch_size)
        cfg = model_config(model)
        self.dim = int(cfg["embed_dim"])
        self.width = int(cfg.get("vision_cfg", {}).get("width", self.dim))
        self.size = self.pre.size  # the crop side the model reads
        # how `prepare_crop` should resize crops to `size`: the tag's interpolation
        self.resample = self.pre.interpolation
        self._mean = torch.tensor(self.pre.mean, device=self.device).view(1, 3, 1, 1)
        self._std = torch.tensor(self.pre.std, device=self.device).view(1, 3, 1, 1)
        self._transform: Any = None
        self.precision_wanted = precision
        self.precision = "bf16" if precision == "bf16" else "fp32"
        self._fast: Any = None
        self._checkpoint = "" if random_weights else str(checkpoint)
        self.tower = Tower(_ImageTower(self.net), (3, self.size, self.size),
                           self._runtime_key, self.device, runtime)  # fmt: skip
        self.runtime_wanted = runtime

    def _runtime_key(self) -> dict[str, Any]:
        """What decides the exported tower's arithmetic: the weights (the
        checkpoint file's digest; random weights: the tensors'), model, tag, size."""
        weights = (runtimes.file_digest(self._checkpoint) if self._checkpoint
                   else runtimes.tensors_digest(self.net.visual.state_dict()))  # fmt: skip
        return {"model": self.model_name, "pretrained": self.pre.tag,
                "quick_gelu": self.pre.quick_gelu, "size": self.size,
                "weights": weights, "net": "openclip image tower"}  # fmt: skip

    @property
    def runtime(self) -> str:
        """The runtime the fp32 image tower runs in now."""
        return self.tower.name

    def runtime_without_sample(self) -> dict | None:
        """`Tower.without_sample`: the "auto" report where nothing can beat
        PyTorch here (nothing encoded), else None."""
        return self.tower.without_sample()

    def check_runtime(self, crops: np.ndarray) -> dict:
        """Decide runtime "auto" on `crops` (a sample of the scene's own): the
        fastest runtime whose unit features are within 1e-4 of PyTorch's fp32
        ones, timed against PyTorch in the precision kept. A runtime kept runs
        fp32, so it also replaces a kept bf16 (`precision` becomes "fp32")."""
        x = self.preprocess(np.asarray(crops))
        precision = self.precision

        def torch_run(a: np.ndarray) -> np.ndarray:
            return self._forward(torch.from_numpy(a), precision, eager=True).numpy()

        report = self.tower.check(x, torch_run)
        if report["runtime"] != "torch" and self.precision != "fp32":
            self.precision, self._fast = "fp32", None
        return report

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
            # upstream's ToTensor + Normalize, batched (its resize is the identity)
            x = torch.from_numpy(np.ascontiguousarray(crops)).to(self.device)
            x = x.permute(0, 3, 1, 2).to(torch.float32) / 255.0
            return (x - self._mean) / self._std
        from PIL import Image

        tf = self._upstream_transform()
        x = torch.stack([tf(Image.fromarray(c)) for c in crops])
        return x.to(self.device)

    # ------------------------------------------------------------ precision
    def _fast_model(self) -> Any:
        """Upstream's precision "pure_bf16": the whole model in bfloat16."""
        if self._fast is None:
            self._fast = copy.deepcopy(self.net).to(torch.bfloat16).eval()
        return self._fast

    @torch.inference_mode()
    def _forward(
        self, x: torch.Tensor, precision: str, eager: bool = False
    ) -> torch.Tensor:
        """Unit features of a preprocessed batch: bf16 in PyTorch, fp32 in the
        tower's runtime (`eager`: in PyTorch whatever the runtime)."""
        if precision == "bf16":
            f = self._fast_model().encode_image(x.to(torch.bfloat16))
        elif eager:
            f = self.tower.torch_forward(x)
        else:
            f = self.tower(x)
        return torch.nn.functional.normalize(f.float(), dim=-1)

    def _timed_encode(self, crops: np.ndarray, precision: str):
        """(features, seconds) of encoding `crops` in `precision`."""
        t0 = time.perf_counter()
        out = self._encode(crops, precision)
        return out, time.perf_counter() - t0

    def _precision_report(self, crops: int, evidence: dict) -> dict[str, Any]:
        """The fields every precision report has: what was checked, on how many
        crops, `bf16_is_fast`'s evidence and the bar."""
        return {
            "checked": "bf16",
            "crops": int(crops),
            "bf16_probe": evidence,
            "bar": {
                "worst_centred_cosine": MIN_CENTRED_COSINE,
                "top1_agreement": MIN_TOP1_AGREEMENT,
                "worst_relevancy_change": MAX_RELEVANCY_CHANGE,
            },
        }

    def _not_faster(self, crops: int, evidence: dict) -> dict[str, Any]:
        """fp32 kept where `bf16_is_fast` says no: nothing run in bf16."""
        self.precision, self._fast = "fp32", None
        where = "this CPU" if self.device.type == "cpu" else "this device"
        return {"precision": "fp32", "reason": f"bf16 not faster on {where}",
                **self._precision_report(crops, evidence)}  # fmt: skip

    def precision_without_sample(self) -> dict | None:
        """`check_precision`'s fp32 report where `bf16_is_fast` says bf16 cannot
        be faster here (`crops` 0: no sample is needed, so none is segmented);
        None where it may be faster, and a sample must decide."""
        fast, evidence = bf16_is_fast(self.device, self.width)
        return None if fast else self._not_faster(0, evidence)

    def check_precision(self, crops: np.ndarray) -> dict:
        """Decide precision "auto" on `crops` (a sample of the scene's own).

        1. `bf16_is_fast`: where bf16 cannot be faster (no bf16 instructions, or
           the matmul probe says no), fp32, with nothing run in bf16.
        2. A short trial: one warm-up crop, then up to 8 crops in each precision;
           bf16 slower there (a conv-heavy tower) → fp32.
        3. The whole sample in both: bf16 is kept only if the worst centred
           cosine is at least MIN_CENTRED_COSINE, the phrases' top-1 agreement
           at least MIN_TOP1_AGREEMENT, the worst relevancy change at most
           MAX_RELEVANCY_CHANGE, and bf16 was faster on the sample.

        Returns:
            The JSON-serialisable report stored with the features: "precision"
            kept, "reason", "checked" ("bf16"), "crops", "bf16_probe" (the
            evidence of `bf16_is_fast`), "bar", and, where bf16 ran, "seconds"
            ({"fp32", "bf16"} per stage) and the agreement figures.
        """
        crops = np.asarray(crops)
        fast, evidence = bf16_is_fast(self.device, self.width)
        if not fast:
            return self._not_faster(len(crops), evidence)
        report = self._precision_report(len(crops), evidence)
        self.precision, self._fast = "fp32", None
        trial = crops[: min(8, len(crops))]
        seconds: dict[str, Any] = {}
        for p in ("fp32", "bf16"):
            self._encode(trial[:1], p)  # warm-up (and the bf16 copy)
            seconds[f"trial_{p}"] = self._timed_encode(trial, p)[1]
        report["seconds"] = seconds
        if seconds["trial_bf16"] >= seconds["trial_fp32"]:
            self._fast = None
            return {"precision": "fp32",
                    "reason": "bf16 slower than fp32 on a trial of the sample",
                    **report}  # fmt: skip
        ref, seconds["fp32"] = self._timed_encode(crops, "fp32")
        low, seconds["bf16"] = self._timed_encode(crops, "bf16")
        fig = centred_agreement(
            ref, low, self.encode_texts(list(CHECK_PHRASES)),
            self.encode_texts(list(CANONICAL)),
        )  # fmt: skip
        agrees = (
            fig["worst_centred_cosine"] >= MIN_CENTRED_COSINE
            and fig["top1_agreement"] >= MIN_TOP1_AGREEMENT
            and fig["worst_relevancy_change"] <= MAX_RELEVANCY_CHANGE
        )
        faster = seconds["bf16"] < seconds["fp32"]
        if agrees and faster:
            self.precision, reason = "bf16", "bf16 agrees with fp32 and is faster"
        else:
            self._fast = None
            reason = ("bf16 disagrees with fp32" if not agrees
                      else "bf16 agrees but was not faster on the sample")  # fmt: skip
        return {"precision": self.precision, "reason": reason, **report, **fig}

    # ------------------------------------------------------------ encoding
    def _encode(self, crops: np.ndarray, precision: str) -> np.ndarray:
        crops = np.asarray(crops)
        out = np.zeros((len(crops), self.dim), np.float32)
        step = self.tower.batch(self.batch_size)
        for i in range(0, len(crops), step):
            x = self.preprocess(crops[i : i + step])
            f = self._forward(x, precision)
            out[i : i + len(f)] = f.cpu().numpy()
        return out

    def encode_images(self, crops: np.ndarray) -> np.ndarray:
        """Crops [B, S, S, 3] RGB in [0, 1] → [B, dim] unit rows, in the kept
        precision."""
        return self._encode(crops, self.precision)

    @torch.inference_mode()
    def encode_texts(self, texts: list[str]) -> np.ndarray:
        """Phrases → [Q, dim] unit rows, always in fp32."""
        if not texts:
            return np.zeros((0, self.dim), np.float32)
        if self._tok is None:
            self._tok = _tokenizer(self.model_name, self._tokenizer_path)
        tokens = self._tok(list(texts)).to(self.device)
        f = self.net.encode_text(tokens)
        return torch.nn.functional.normalize(f.float(), dim=-1).cpu().numpy()


__all__ = [  # the net's builders are `openclip_net`'s, named here too
    "CHECK_PHRASES",
    "PRECISIONS",
    "TINY",
    "TINY_CONFIG",
    "OpenClipEncoder",
    "Preprocess",
    "bf16_is_fast",
    "build_net",
    "centred_agreement",
    "clean_tag",
    "hf_text_tower",
    "model_config",
    "preprocess_for",
    "register_tiny",
]

"""OpenCLIP as an encoder backend (`ptovs.encoders.backend`): the config it reads,
how extract-features builds it, what query needs to embed texts like it, and the
preflight check that the model/tag can be driven exactly and the checkpoint
exists, loads, fits the model and encodes a crop and a phrase in every
precision it may use (extra [clip]).
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Any

from ptovs.encoders.backend import EncoderBackend
from ptovs.encoders.weights import readable_state, state_mismatch, where
from ptovs.errors import InputError, MissingInputError

# The file as its publisher names it, for the models the shipped configs use:
# (clip_model, clean pretrained tag; "" = any) -> (file, where from).
CLIP_FILES = {
    ("MobileCLIP2-S0", ""): (
        "open_clip_model.safetensors",
        "Hugging Face timm/MobileCLIP2-S0-OpenCLIP",
    ),
    ("ViT-B-16", "laion2b_s34b_b88k"): (
        "open_clip_pytorch_model.bin",
        "Hugging Face laion/CLIP-ViT-B-16-laion2B-s34B-b88K",
    ),
}


class OpenClipBackend(EncoderBackend):
    """Any open_clip model from a local checkpoint (`ptovs.encoders.openclip`)."""

    name = "openclip"
    extra = "clip"
    config_keys = ("clip_model", "clip_checkpoint", "clip_pretrained",
                   "clip_tokenizer", "precision", "runtime", "device",
                   "batch_size")  # fmt: skip

    def build(self, config: Any, scene_root: Path | None) -> Any:
        from ptovs.encoders.openclip import OpenClipEncoder

        return OpenClipEncoder(
            model=config.clip_model,
            checkpoint=config.clip_checkpoint,
            device=config.device,
            batch_size=config.batch_size,
            pretrained=config.clip_pretrained,
            tokenizer=config.clip_tokenizer,
            precision=config.precision,
            runtime=config.runtime,
        )

    def spec(self, config: Any) -> dict:
        """The model and checkpoint, as query rebuilds the encoder for texts."""
        return {
            "name": "openclip",
            "model": config.clip_model,
            "checkpoint": str(config.clip_checkpoint),
            "pretrained": config.clip_pretrained,
            "tokenizer": str(config.clip_tokenizer),
        }

    def check(self, config: Any) -> None:
        """A runtime asked for by name can run here, and `check_openclip`."""
        runtime = getattr(config, "runtime", "auto")
        if runtime != "auto":  # asked by name: the backend says whether it can run
            from ptovs.encoders.runtimes import require

            require(runtime)
        check_openclip(
            config.clip_model,
            config.clip_checkpoint,
            getattr(config, "clip_pretrained", ""),
            getattr(config, "clip_tokenizer", ""),
            getattr(config, "precision", "fp32"),
            getattr(config, "device", "cpu"),
        )


def clip_file(model: str, pretrained: str) -> tuple[str, str]:
    """(file, where from) of `model`'s checkpoint where the table knows it."""
    tag = str(pretrained).lower().replace("-", "_")  # as open_clip matches tags
    return CLIP_FILES.get((model, tag)) or CLIP_FILES.get((model, ""), ("", ""))


def check_openclip(
    model: str,
    checkpoint: str | Path,
    pretrained: str = "",
    tokenizer: str = "",
    precision: str = "fp32",
    device: str = "cpu",
) -> None:
    """The model/tag can be driven exactly, and the OpenCLIP checkpoint exists,
    loads, fits `model` and encodes a crop and a phrase (the crop in every
    precision `precision` may use)."""
    if not str(checkpoint):
        raise InputError(
            "encoder = 'openclip' needs clip_checkpoint = a local OpenCLIP state dict; "
            "nothing is downloaded: --set extract-features.clip_checkpoint=FILE"
            + where(*clip_file(model, pretrained))
        )
    path = Path(checkpoint).expanduser()
    if not path.is_file():
        raise MissingInputError(
            f"clip_checkpoint {path} does not exist; give the local OpenCLIP state "
            "dict with --set extract-features.clip_checkpoint=FILE"
            + where(*clip_file(model, pretrained))
        )
    st = path.stat()
    openclip_fits(
        model, str(path), st.st_size, st.st_mtime_ns, pretrained, str(tokenizer),
        precision, str(device),
    )  # fmt: skip


@functools.lru_cache(maxsize=8)
def openclip_fits(
    model: str,
    path: str,
    size: int,
    mtime_ns: int,
    pretrained: str,
    tokenizer: str,
    precision: str,
    device: str,
) -> None:
    """Refuse a model/tag the wrapper cannot drive exactly (tags that disagree on
    preprocessing or QuickGELU, a Hugging Face tower with no local folder), load
    the checkpoint the way the encoder will, compare it with the model's tensors,
    names and shapes, then run one crop and one phrase through the encoder built
    from it, in the precision it will use (cached by the file's size and time)."""
    from ptovs.encoders.openclip_net import (
        build_net,
        clip_state_dict,
        model_config,
        preprocess_for,
    )

    try:
        model_config(model)
    except ValueError as exc:
        raise InputError(f"{exc}; see docs/guide.md") from None
    try:
        pre = preprocess_for(model, pretrained)
    except ValueError as exc:
        raise InputError(f"{exc}: --set extract-features.clip_pretrained=TAG") from None
    try:
        want = build_net(model, None, pre.quick_gelu, tokenizer).state_dict()
    except (ValueError, FileNotFoundError) as exc:
        raise InputError(
            f"{exc}: --set extract-features.clip_tokenizer=FOLDER"
        ) from None
    state = readable_state("clip_checkpoint", path, clip_state_dict)
    missing, wrong, _ = state_mismatch(state, want, extra=False)
    if missing or wrong:
        what = wrong[:2] or missing[:2]
        raise InputError(
            f"clip_checkpoint {path} is not a {model} state dict: {len(missing)} "
            f"tensors missing, {len(wrong)} of another shape (e.g. {what}); give "
            f"{model}'s checkpoint, or set clip_model to the checkpoint's model"
        )
    del want, state
    _try_encoder(model, path, pretrained, tokenizer, precision, device)


def _try_encoder(
    model: str,
    path: str,
    pretrained: str,
    tokenizer: str,
    precision: str = "fp32",
    device: str = "cpu",
) -> None:
    """One crop and one phrase through the encoder extract-features will build,
    the crop also in bf16 where bf16 will or may be used ("bf16"; "auto" where
    `bf16_is_fast` lets the check run): a model the wrapper cannot drive fails
    here, in one line."""
    import numpy as np

    from ptovs.encoders import openclip

    try:
        enc = openclip.OpenClipEncoder(
            model, path, pretrained=pretrained, tokenizer=tokenizer, batch_size=1,
            device=device,
        )  # fmt: skip
        crop = np.full((1, enc.size, enc.size, 3), 0.5, np.float32)
        runs = ["fp32"]
        if precision == "bf16" or (
            precision == "auto" and openclip.bf16_is_fast(enc.device, enc.width)[0]
        ):
            runs.append("bf16")
        imgs = [enc._encode(crop, p) for p in runs]
        txt = enc.encode_texts(["a photo of a building"])
    except Exception as exc:  # noqa: BLE001 - whatever it is, it would fail hours in
        first = (str(exc).splitlines() or [""])[0][:200]
        raise InputError(
            f"clip_model {model} with clip_checkpoint {path} could not encode a "
            f"test crop and phrase ({type(exc).__name__}: {first})"
        ) from None
    for img in imgs:
        if img.shape != (1, enc.dim) or txt.shape != (1, enc.dim):
            raise InputError(
                f"clip_model {model}: a test crop and phrase gave features "
                f"{img.shape} and {txt.shape}, not [1, {enc.dim}]"
            )
        if not (np.isfinite(img).all() and np.isfinite(txt).all()):
            raise InputError(
                f"clip_checkpoint {path}: {model} gives non-finite features for a "
                "test crop or phrase (a damaged checkpoint?)"
            )


__all__ = ["CLIP_FILES", "OpenClipBackend", "check_openclip", "clip_file"]

"""Checks that run before the first stage of a chain: a mistake that
would fail hours in (a missing or mismatched checkpoint, a phrase the encoder does
not know, a view that does not exist, a label file that does not parse) fails in
seconds instead, as one line naming the file and the fix, and leaves nothing
behind: no stage has started, so no `.parts`, `.lock` or artifact exists.

Only the stages that will run are checked (a cached stage needs nothing).
"""

from __future__ import annotations

import functools
import logging
from pathlib import Path
from typing import Any

from ptovs.errors import InputError, MissingInputError

log = logging.getLogger(__name__)

# Where a missing checkpoint's error sends the user: the guide's table of each
# model's source, file and checksum (tests/test_preflight.py checks the heading).
CHECKPOINT_TABLE = "docs/guide.md, 'Checkpoints: where each comes from'"
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
# segment-anything's sam_model -> Meta's file (dl.fbaipublicfiles.com/segment_anything)
SAM_FILES = {
    "vit_h": "sam_vit_h_4b8939.pth",
    "vit_l": "sam_vit_l_0b3195.pth",
    "vit_b": "sam_vit_b_01ec64.pth",
}


def _where(file: str = "", source: str = "") -> str:
    """The tail of a missing-checkpoint error: the expected file, where known,
    and the guide's table."""
    take = f" (take {file}" + (f" from {source}" if source else "") + ")"
    return (take if file else "") + f"; where to download it: {CHECKPOINT_TABLE}"


def _clip_file(model: str, pretrained: str) -> tuple[str, str]:
    """(file, where from) of `model`'s checkpoint where the table knows it."""
    tag = str(pretrained).lower().replace("-", "_")  # as open_clip matches tags
    return CLIP_FILES.get((model, tag)) or CLIP_FILES.get((model, ""), ("", ""))


def _read_state(field: str, path: str, read: Any) -> dict:
    """`read(path)` (a state dict); a torch/pickle error becomes one line naming
    the file."""
    try:
        return read(Path(path))
    except Exception as exc:  # a torch/pickle error: one line, naming the file
        raise InputError(
            f"{field} {path} could not be read as a state dict "
            f"({type(exc).__name__}: {str(exc).splitlines()[0][:160]})"
        ) from None


def _state_mismatch(
    state: dict, want: dict, extra: bool
) -> tuple[list[str], list[str], list[str]]:
    """Tensors of `want` (tensors or shapes) missing from `state`, of another
    shape there, and (when `extra`) tensors of `state` that `want` does not have."""

    def shape(v: Any) -> tuple:
        return tuple(getattr(v, "shape", v))

    missing = [k for k in want if k not in state]
    wrong = [k for k in want if k in state and shape(state[k]) != shape(want[k])]
    unexpected = [k for k in state if k not in want] if extra else []
    return missing, wrong, unexpected


@functools.lru_cache(maxsize=8)
def _openclip_fits(
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
    from ptovs.encoders.openclip import build_net, model_config, preprocess_for

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
    from ptovs.encoders.openclip import _state_dict

    state = _read_state("clip_checkpoint", path, _state_dict)
    missing, wrong, _ = _state_mismatch(state, want, extra=False)
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

    from ptovs.encoders.openclip import OpenClipEncoder, bf16_is_fast

    try:
        enc = OpenClipEncoder(
            model, path, pretrained=pretrained, tokenizer=tokenizer, batch_size=1,
            device=device,
        )  # fmt: skip
        crop = np.full((1, enc.size, enc.size, 3), 0.5, np.float32)
        runs = ["fp32"]
        if precision == "bf16" or (
            precision == "auto" and bf16_is_fast(enc.device, enc.width)[0]
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


@functools.lru_cache(maxsize=4)
def _sam2_shapes(model: str) -> dict:
    """{name: shape} of SAM 2.1 `model`'s tensors (built once, randomly)."""
    from ptovs.segment.sam2 import build_sam2_model

    return {k: v.shape for k, v in build_sam2_model(model).state_dict().items()}


@functools.lru_cache(maxsize=8)
def _sam2_fits(model: str, path: str, size: int, mtime_ns: int) -> None:
    """Load the checkpoint the way the segmenter will and compare it with the
    model's tensors: names, shapes, and none left over (a strict load). A SAM 2.0
    checkpoint, or SAM 2.1 of another size, is named as such with its fix."""
    from ptovs.segment.sam2 import sam2_kind, sam2_state_dict

    state = _read_state("sam_checkpoint", path, sam2_state_dict)
    missing, wrong, extra = _state_mismatch(state, _sam2_shapes(model), extra=True)
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
            + _where(*_clip_file(model, pretrained))
        )
    path = Path(checkpoint).expanduser()
    if not path.is_file():
        raise MissingInputError(
            f"clip_checkpoint {path} does not exist; give the local OpenCLIP state "
            "dict with --set extract-features.clip_checkpoint=FILE"
            + _where(*_clip_file(model, pretrained))
        )
    st = path.stat()
    _openclip_fits(
        model, str(path), st.st_size, st.st_mtime_ns, pretrained, str(tokenizer),
        precision, str(device),
    )  # fmt: skip


def _encoder(config: Any, synthetic: bool) -> str:
    """extract-features' encoder: "auto" is the stand-in on synthetic scenes."""
    if config.encoder != "auto":
        return config.encoder
    return "synthetic" if synthetic else "openclip"


def check_extract_config(config: Any, synthetic: bool = False) -> None:
    """What extract-features needs that no scene decides: the encoder's and the
    segmenter's checkpoints (a folder of unposed photos is never synthetic, so
    this runs before SfM poses it)."""
    if config.import_dir:
        if not Path(config.import_dir).is_dir():
            raise MissingInputError(
                f"extract-features.import_dir {config.import_dir} is not a folder"
            )
        return
    if _encoder(config, synthetic) == "openclip":
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
    if config.segmenter in ("sam", "sam2"):
        check_sam_checkpoint(config)


def check_sam_checkpoint(config: Any) -> None:
    """segmenter "sam" or "sam2": the checkpoint exists; for "sam2" it also loads
    and fits `sam2_model` (a SAM 1 or another size's checkpoint is refused)."""
    sam2 = config.segmenter == "sam2"
    if sam2:
        from ptovs.segment.sam2 import SAM2_MODELS

        if config.sam2_model not in SAM2_MODELS:
            raise InputError(
                f"extract-features.sam2_model {config.sam2_model!r}: choose from "
                f"{list(SAM2_MODELS)}"
            )
    what = "a local SAM 2.1 checkpoint" if sam2 else "a local SAM checkpoint"
    ckpt = Path(str(config.sam_checkpoint)).expanduser()
    if not str(config.sam_checkpoint) or not ckpt.is_file():
        if sam2:
            file = f"sam2.1_hiera_{config.sam2_model}.pt"
        else:
            file = SAM_FILES.get(str(getattr(config, "sam_model", "")), "")
        raise MissingInputError(
            f"segmenter = {config.segmenter!r} needs sam_checkpoint = {what} "
            f"({str(ckpt) if str(config.sam_checkpoint) else 'none given'}); "
            "--set extract-features.sam_checkpoint=FILE"
            + _where(file, "Meta" if file else "")
        )
    if sam2:
        st = ckpt.stat()
        _sam2_fits(config.sam2_model, str(ckpt), st.st_size, st.st_mtime_ns)


def _extract(config: Any, scene: Any) -> None:
    check_extract_config(config, scene.synthetic)
    if config.import_dir or _encoder(config, scene.synthetic) == "openclip":
        return
    if not (Path(scene.root) / "synthetic" / "vocabulary.json").is_file():
        raise MissingInputError(
            f"encoder 'synthetic' (the stand-in) needs {scene.root}/synthetic/"
            "vocabulary.json, which only synthetic scenes have; set "
            'extract-features.encoder = "openclip" and clip_checkpoint for real photos'
        )


def _query(config: Any, scene: Any) -> None:
    from ptovs.field.query import encoder_name, resolve_queries, resolve_views

    queries = resolve_queries(config, scene)  # parses the labels when no texts
    resolve_views(config, scene)
    if encoder_name(config, scene) == "synthetic" and scene.synthetic:
        from ptovs.encoders import scene_encoder
        from ptovs.field.query import check_vocabulary

        check_vocabulary(scene_encoder(scene.root), queries)


def preflight(chain: Any, stages: list[str]) -> None:
    """Check what `stages` (those not yet done) will need, before any runs.
    Nothing is written unless every check passes (not even the photos'
    fingerprint cache)."""
    from ptovs.keys import flush_fingerprints, read_only

    ok = False
    try:
        with read_only():
            _preflight(chain, stages)
        ok = True
    finally:
        flush_fingerprints(write=ok)


def _preflight(chain: Any, stages: list[str]) -> None:
    todo = [s for s in stages if chain.state(s)[0] != "done"]
    if not todo:
        return
    scene = chain.scene.load()
    if "extract-features" in todo:
        _extract(chain.config("extract-features"), scene)
    if "query" in todo:
        _query(chain.config("query"), scene)
    log.debug("preflight: %s checked", ", ".join(todo))


__all__ = [
    "check_extract_config",
    "check_openclip",
    "check_sam_checkpoint",
    "preflight",
]

"""Building an OpenCLIP model the way upstream open_clip 3.3 does, from local
files only (extra `[clip]`; the encoder is `ptovs.encoders.openclip`).

`preprocess_for` reads the pretrained tag's preprocessing and activation (or
refuses a tag-less model whose tags disagree), `build_net` builds the model and
loads a local checkpoint through upstream's `load_checkpoint`, `_tokenizer` gives
the model's tokenizer (a Hugging Face one from a local folder only), and
`register_tiny` adds a tiny config for tests. Nothing is downloaded.
"""

from __future__ import annotations

import contextlib
import copy
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ptovs.compat import import_backend
from ptovs.encoders.weights import read_state_dict

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
    """What the trained model expects (open_clip's per-tag config): the image's
    preprocessing and the activation it was trained with."""

    size: int
    mean: tuple[float, float, float]
    std: tuple[float, float, float]
    interpolation: str
    resize_mode: str
    tag: str  # the pretrained tag it came from ("" = open_clip's defaults)
    quick_gelu: bool = False  # QuickGELU, as the tag (or model config) says


def clean_tag(tag: str) -> str:
    """A pretrained tag as open_clip looks it up (`pretrained._clean_tag`)."""
    return str(tag).lower().replace("-", "_")


def model_config(model: str) -> dict:
    """open_clip's built-in config of `model`, or ValueError naming the choices."""
    oc = import_backend("open_clip")
    if ":" in str(model):
        raise ValueError(
            f"clip_model {model!r}: give a built-in OpenCLIP name (e.g. ViT-B-16) "
            "and the weights as clip_checkpoint; hf-hub:/local-dir: names would "
            "read or download the model's config, and are not supported"
        )
    cfg = oc.get_model_config(model) if model in oc.list_models() else None
    if cfg is None:
        raise ValueError(
            f"clip_model {model!r} is not an OpenCLIP model (e.g. ViT-B-32, "
            "ViT-B-16, MobileCLIP2-S0, ViT-B-16-SigLIP2; `open_clip.list_models()`)"
        )
    return cfg


def _quick_name(model: str) -> str:
    """`<model>-quickgelu` where open_clip has it, for the refusal's fix."""
    oc = import_backend("open_clip")
    name = f"{model}-quickgelu"
    return f" (or clip_model = {name})" if name in oc.list_models() else ""


def preprocess_for(model: str, tag: str = "") -> Preprocess:
    """The preprocessing and activation of `model`'s pretrained tag `tag`.

    Without a tag: what every tag of the model agrees on (MobileCLIP2-S0's one
    tag, ViT-B-32-quickgelu's tags, ...), open_clip's defaults for a model with
    no tags, and a ValueError naming the tags when they preprocess differently
    or disagree on QuickGELU (ViT-B-16: openai and dfn2b are QuickGELU,
    laion2b_s34b_b88k is not). The activation is QuickGELU where the model's
    config or the tag says so (as `force_quick_gelu`: upstream never turns a
    config's QuickGELU off)."""
    oc = import_backend("open_clip")
    cfg = model_config(model)
    vision = cfg.get("vision_cfg", {})
    size = vision.get("image_size", 224)
    size = int(size[0] if isinstance(size, (tuple, list)) else size)
    keys = ("mean", "std", "interpolation", "resize_mode")
    default = oc.transform.PreprocessCfg()
    tags = oc.list_pretrained_tags_by_model(model)
    tag = clean_tag(tag) if tag else ""
    if tag:
        if tag not in tags:
            raise ValueError(
                f"clip_pretrained {tag!r} is not a tag of {model} "
                f"(tags: {', '.join(tags) or 'none'})"
            )
        chosen = [tag]
    else:
        chosen = tags
    model_quick = bool(cfg.get("quick_gelu", False))

    def recipe(t: str) -> tuple:
        pc = oc.get_pretrained_cfg(model, t)
        values = (pc.get(k, getattr(default, k)) for k in keys)
        return tuple(tuple(v) if isinstance(v, list) else v for v in values)

    def quick(t: str) -> bool:
        return model_quick or bool(oc.get_pretrained_cfg(model, t).get("quick_gelu"))

    found = {recipe(t) for t in chosen}
    if not found:
        values = tuple(getattr(default, k) for k in keys)
    elif len(found) == 1:
        values = next(iter(found))
    else:
        raise ValueError(
            f"{model}'s pretrained tags preprocess differently ({', '.join(tags)}); "
            "set clip_pretrained to the tag of your checkpoint"
        )
    acts = {t: quick(t) for t in chosen}
    if len(set(acts.values())) > 1:
        q = ", ".join(t for t, v in acts.items() if v)
        g = ", ".join(t for t, v in acts.items() if not v)
        raise ValueError(
            f"{model}'s pretrained tags were trained with different activations "
            f"(QuickGELU: {q}; GELU: {g}); set clip_pretrained to the tag of your "
            f"checkpoint{_quick_name(model)}"
        )
    quick_gelu = next(iter(acts.values())) if acts else model_quick
    mean, std, interp, mode = values
    return Preprocess(
        size, tuple(map(float, mean)), tuple(map(float, std)), interp, mode,
        tag or (chosen[0] if len(chosen) == 1 else ""), bool(quick_gelu),
    )  # fmt: skip


def clip_state_dict(path: str | Path) -> dict[str, Any]:
    """A checkpoint's tensors (`weights.read_state_dict`: a `.safetensors` file, as
    the model hubs ship open_clip weights, or a torch file read with
    weights_only=True); OpenAI's TorchScript archives are refused."""
    path = Path(path)
    import zipfile

    if path.suffix != ".safetensors" and zipfile.is_zipfile(path):
        with zipfile.ZipFile(path) as z:  # OpenAI's own .pt files are TorchScript
            if any(n.endswith("/constants.pkl") for n in z.namelist()):
                raise ValueError(
                    f"clip_checkpoint {path} is a TorchScript archive (OpenAI's own "
                    "ViT-*.pt), which ptovs does not execute; take the same weights "
                    "as a state dict: the model hub's open_clip_model.safetensors of "
                    "the tag (docs/guide.md, Checkpoints)"
                )
    return read_state_dict(path, "clip_checkpoint")


def hf_text_tower(model: str) -> str:
    """The Hugging Face model of `model`'s text tower ("" for open_clip's own)."""
    return str(model_config(model).get("text_cfg", {}).get("hf_model_name") or "")


def _hf_text_cfg(model: str, folder: str | Path) -> dict:
    """`model`'s text_cfg with its Hugging Face tower read from the local `folder`
    (config.json) and never from the hub; ValueError in one line otherwise."""
    oc = import_backend("open_clip")
    hf = hf_text_tower(model)
    if not str(folder):
        raise ValueError(
            f"{model}'s text tower is the Hugging Face model {hf!r}, whose config "
            "would be downloaded; give its local folder (config.json and tokenizer "
            "files) as clip_tokenizer, and install transformers"
        )
    path = Path(folder).expanduser()
    if not (path / "config.json").is_file():
        raise FileNotFoundError(
            f"clip_tokenizer {path} holds no config.json; {model}'s text tower "
            f"needs the local folder of the Hugging Face model {hf!r}"
        )
    if oc.hf_model.transformers is None:
        raise ValueError(
            f"{model}'s text tower is the Hugging Face model {hf!r}: "
            "pip install transformers"
        )
    text = copy.deepcopy(model_config(model)["text_cfg"])
    text.update(hf_model_name=str(path), hf_model_pretrained=False)
    return text


def build_net(
    model: str,
    checkpoint: str | Path | None,
    quick_gelu: bool = False,
    hf_folder: str | Path = "",
) -> Any:
    """open_clip's `model` with the checkpoint's weights (None: random, tests).

    Args:
        model: a built-in open_clip model name.
        checkpoint: local state dict (torch or .safetensors), loaded through
            upstream's `load_checkpoint`; every tensor must fit.
        quick_gelu: build with QuickGELU (`force_quick_gelu`), as the tag says.
        hf_folder: local folder of a Hugging Face text tower's config (models
            with `text_cfg.hf_model_name` only).

    Returns:
        The model in eval mode, on the CPU, in fp32.
    """
    oc = import_backend("open_clip")
    model_config(model)
    kwargs: dict[str, Any] = {}
    if hf_text_tower(model):
        kwargs["text_cfg"] = _hf_text_cfg(model, hf_folder)
    with _quiet_open_clip():
        # pretrained_text / pretrained_image False: no tower weights fetched
        net = oc.create_model(
            model, pretrained=None, force_quick_gelu=quick_gelu,
            pretrained_image=False, pretrained_text=False, **kwargs,
        )  # fmt: skip
    if checkpoint is None:
        return net.eval()
    path = Path(checkpoint)
    if not str(checkpoint):
        raise ValueError(
            "encoder = 'openclip' needs clip_checkpoint = a local OpenCLIP "
            "state dict (e.g. MobileCLIP2-S0 dfndr2b, ViT-B-16 "
            "laion2b_s34b_b88k); nothing is downloaded"
        )
    if not path.is_file():
        raise FileNotFoundError(f"clip_checkpoint {path} does not exist")
    # upstream's loader: its key conversions, then a load we check ourselves
    keys = oc.factory.load_checkpoint(net, str(path), strict=False, weights_only=True)
    missing, unexpected = list(keys.missing_keys), list(keys.unexpected_keys)
    if missing or unexpected:
        what = missing[:3] or unexpected[:3]
        raise ValueError(
            f"clip_checkpoint {path} does not fit {model}: {len(missing)} tensors "
            f"missing, {len(unexpected)} left over (e.g. {what}); give {model}'s "
            "checkpoint, or set clip_model to the checkpoint's model"
        )
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

"""A torch module exported to ONNX once, kept where every scene finds it.

    path = onnx_file(tower, example, key)   # <cache>/onnx/<digest>.onnx

The file's name is the sha256 of `key` (what decides the network's arithmetic:
the weights' digest, the model, the input size) with the exporter's version and
opset, so a new checkpoint, a new torch or a new opset exports anew, and an
export made for one scene serves every other. Written atomically: a killed
export leaves no file another run could take for a whole one. The legacy
(TorchScript) exporter is used: it needs no onnxscript and exports OpenCLIP's
towers, SAM's and SAM 2.1's image encoders with a dynamic batch side.

A module returning one tensor has one output, "y"; one returning a tuple of
tensors (SAM 2.1's encoder, flattened) has "y0".."yk", in the tuple's order.

Over 2 GB of weights (SAM's ViT-H encoder) ONNX keeps the tensors outside the
file: the exporter writes each to its own file beside the model, named by the
tensor, names every export of that network shares, so it exports into a folder
of its own and the tensors are gathered into one `<digest>.<random>.data` beside
the model before the model is renamed into place.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import secrets
import shutil
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch

from ptovs.atomic import atomic_file, create_temp, fsync_file
from ptovs.encoders.runtimes import cache_dir

log = logging.getLogger(__name__)

OPSET = 17


def export_key(key: Mapping[str, Any]) -> str:
    """The export's file name: sha256 of `key`, torch's version and the opset."""
    payload = {**dict(key), "exporter": f"torch {torch.__version__}", "opset": OPSET}
    text = json.dumps(payload, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()


def output_names(module: torch.nn.Module, example: torch.Tensor) -> list[str]:
    """["y"] for a module returning one tensor, ["y0", .., "yk"] for a tuple (one
    forward pass of `example`: the exporter needs a name per output)."""
    with torch.no_grad():
        y = module(example)
    if isinstance(y, torch.Tensor):
        return ["y"]
    return [f"y{i}" for i in range(len(y))]


def onnx_file(module: torch.nn.Module, example: torch.Tensor, key: Mapping) -> Path:
    """The ONNX file of `module` (input "x" [B, C, H, W], outputs `output_names`),
    exported on first use. `example` is one input batch; its batch side becomes
    dynamic."""
    folder = cache_dir() / "onnx"
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{export_key(key)}.onnx"
    if path.is_file():
        return path
    log.info("exporting %s to ONNX (once; kept in %s)", key.get("model", "a network"),
             folder)  # fmt: skip
    names = output_names(module.eval(), example)
    own = create_temp(path, folder=True)
    try:
        with atomic_file(path, durable=True) as tmp, warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the legacy exporter's deprecation notice
            torch.onnx.export(
                module, (example,), str(own / "model.onnx"), opset_version=OPSET,
                input_names=["x"], output_names=names,
                dynamic_axes={n: {0: "batch"} for n in ["x", *names]}, dynamo=False,
            )  # fmt: skip
            _settle(own / "model.onnx", tmp, f"{path.stem}.{secrets.token_hex(6)}.data")
    finally:
        shutil.rmtree(own, ignore_errors=True)
    return path


def _settle(exported: Path, tmp: Path, data: str) -> None:
    """Move the exported model onto `tmp`; where its tensors were written to files
    of their own (over 2 GB), into one file `data` beside `tmp` (a name no other
    export uses: two runs exporting at once never write the same file)."""
    if [f.name for f in exported.parent.iterdir()] == [exported.name]:
        os.replace(exported, tmp)
        return
    import onnx

    model = onnx.load(str(exported))  # with its tensors' files
    onnx.save_model(model, str(tmp), save_as_external_data=True,
                    all_tensors_to_one_file=True, location=data)  # fmt: skip
    if (tmp.parent / data).exists():  # (tensors under 1 kB stay in the model)
        fsync_file(tmp.parent / data)  # on disk before the model naming it is


__all__ = ["OPSET", "export_key", "onnx_file", "output_names"]

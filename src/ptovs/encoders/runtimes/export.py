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
"""

from __future__ import annotations

import hashlib
import json
import logging
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch

from ptovs.atomic import atomic_file
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
    with atomic_file(path, durable=True) as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the legacy exporter's deprecation notice
        torch.onnx.export(
            module, (example,), str(tmp), opset_version=OPSET,
            input_names=["x"], output_names=names,
            dynamic_axes={n: {0: "batch"} for n in ["x", *names]}, dynamo=False,
        )  # fmt: skip
    return path


__all__ = ["OPSET", "export_key", "onnx_file", "output_names"]

"""PyTorch eager: the module as it is (the reference every other runtime meets).
A module returning a tuple of tensors runs to a list of arrays, as the exported
runtimes answer."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import torch


class TorchEager:
    name = "torch"
    extra = ""

    def missing(self) -> str | None:
        return None

    def version(self) -> str:
        return torch.__version__

    def cannot_win(self, device: str) -> str | None:
        return None

    def load(self, module: Any, example: Any, key: Mapping[str, Any], threads: int):
        dev = next(iter(module.parameters())).device

        @torch.inference_mode()
        def run(x: np.ndarray) -> np.ndarray:
            y = module(torch.from_numpy(np.ascontiguousarray(x)).to(dev))
            if isinstance(y, torch.Tensor):
                return y.float().cpu().numpy()
            return [t.float().cpu().numpy() for t in y]

        return run

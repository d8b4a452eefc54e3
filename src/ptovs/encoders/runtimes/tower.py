"""One network's image side under a chosen runtime: what an encoder holds.

    tower = Tower(module, input_shape=(3, 256, 256), key=lambda: {...}, device="cpu")
    tower.use("onnxruntime")              # or decide: tower.check(x, torch_run)
    y = tower(x)                          # torch float32 in, torch float32 out

`module` maps a float32 batch to a float32 array, or to a tuple of them (SAM
2.1's encoder, flattened: the tower then answers a tuple); `key()` (called only
when a runtime other than PyTorch is loaded) names what decides its arithmetic
(the weights' digest, the model, the input size), so the export is cached across
scenes.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
import torch

from ptovs.encoders.runtimes import RUNTIMES, require
from ptovs.encoders.runtimes.choose import choose, screen

log = logging.getLogger(__name__)

BATCH = {"torch": 8, "onnxruntime": 8, "openvino": 16}
"""Crops a call, by runtime, where the config leaves it to the runtime (0): the
fastest of 1-64 measured on MobileCLIP2-S0's tower at 2 threads (a batch of 64
ran PyTorch at half the rate of 8: its activations leave the cache)."""


class Tower:
    def __init__(
        self,
        module: torch.nn.Module,
        input_shape: tuple[int, ...],
        key: Callable[[], Mapping[str, Any]],
        device: str | torch.device = "cpu",
        wanted: str = "torch",
    ):
        if wanted not in RUNTIMES:
            raise ValueError(f"runtime {wanted!r}: choose from {list(RUNTIMES)}")
        self.module = module.eval()
        self.input_shape = tuple(input_shape)
        self._key = key
        self.device = torch.device(device)
        self.wanted = wanted
        self.name = "torch"
        self._run: Callable[[np.ndarray], np.ndarray] | None = None
        self._loaded: dict[str, Callable[[np.ndarray], np.ndarray]] = {}
        if wanted not in ("auto", "torch"):
            self.use(wanted)

    def batch(self, asked: int = 0) -> int:
        """Crops a call: `asked`, or (0) the runtime's own."""
        return int(asked) if asked else BATCH.get(self.name, 8)

    def _load(self, name: str) -> Callable[[np.ndarray], np.ndarray]:
        if name not in self._loaded:
            backend = require(name)
            example = torch.zeros((1, *self.input_shape), dtype=torch.float32)
            cpu = self.device.type == "cpu"
            module = self.module if cpu else _cpu_copy(self.module)
            threads = torch.get_num_threads()
            self._loaded[name] = backend.load(module, example, self._key(), threads)
        return self._loaded[name]

    def use(self, name: str) -> None:
        """Run with runtime `name` from now on (raises a one-line InputError where
        it is not installed)."""
        self._run = None if name == "torch" else self._load(name)
        self.name = name

    @torch.inference_mode()
    def torch_forward(self, x: torch.Tensor) -> Any:
        y = self.module(x.to(self.device))
        return y.float() if isinstance(y, torch.Tensor) else tuple(t.float() for t in y)

    def __call__(self, x: torch.Tensor) -> Any:
        if self._run is None:
            return self.torch_forward(x)
        y = self._run(x.detach().cpu().numpy().astype(np.float32, copy=False))
        if isinstance(y, np.ndarray):
            return torch.from_numpy(y).to(self.device)
        return tuple(torch.from_numpy(t).to(self.device) for t in y)

    def without_sample(self) -> dict | None:
        """The report of `wanted` = "auto" where no runtime besides PyTorch is worth
        trying here (none installed, or none can win on this device): nothing is
        encoded. None where a sample must decide."""
        candidates, skipped = screen(str(self.device.type), "auto")
        if candidates:
            return None
        return choose(np.zeros((0,)), _never, _never, _never, [], skipped)

    def check(
        self,
        x: torch.Tensor,
        torch_run: Callable | None = None,
        compare: Callable | None = None,
        unit: str = "crops",
    ) -> dict:
        """Decide runtime "auto" on the preprocessed sample `x` and use the winner.

        `torch_run` (batch → features as extract-features would compute them with
        PyTorch, e.g. in bf16) is the speed to beat; the features to agree with are
        always PyTorch's float32 ones, compared by `compare` (`choose.choose`'s:
        unit features by default) and reported in `unit`."""
        candidates, skipped = screen(str(self.device.type), "auto")
        xs = x.detach().cpu().numpy().astype(np.float32, copy=False)

        def eager(a: np.ndarray) -> Any:
            y = self.torch_forward(torch.from_numpy(a))
            if isinstance(y, torch.Tensor):
                return y.cpu().numpy()
            return [t.cpu().numpy() for t in y]

        def batched(run: Callable, batch: int) -> Callable:
            def go(a: np.ndarray) -> Any:
                parts = [run(a[i : i + batch]) for i in range(0, len(a), batch)]
                if isinstance(parts[0], np.ndarray):
                    return np.concatenate(parts)
                return [np.concatenate(ys) for ys in zip(*parts, strict=True)]

            return go

        report = choose(
            xs,
            batched(torch_run or eager, BATCH["torch"]),
            batched(eager, BATCH["torch"]),
            lambda n: batched(self._load(n), BATCH.get(n, 8)),
            candidates,
            skipped,
            **({"compare": compare} if compare is not None else {}),
            unit=unit,
        )
        self.use(report["runtime"])
        return report


def _never(*_: Any) -> np.ndarray:  # pragma: no cover - never called without crops
    raise AssertionError("no runtime runs without crops")


def _cpu_copy(module: torch.nn.Module) -> torch.nn.Module:
    import copy

    return copy.deepcopy(module).cpu().float().eval()


__all__ = ["BATCH", "Tower"]

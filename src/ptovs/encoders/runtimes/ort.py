"""ONNX Runtime's CPU execution provider, float32, all graph optimisations. One
output ("y") runs to one array, several ("y0".."yk") to a list in their order."""

from __future__ import annotations

import importlib.util
from collections.abc import Mapping
from typing import Any

import numpy as np

from ptovs.encoders.runtimes import refusal
from ptovs.encoders.runtimes.export import onnx_file


class OnnxRuntime:
    name = "onnxruntime"
    extra = "clip"

    def missing(self) -> str | None:
        for pkg in ("onnxruntime", "onnx"):
            if importlib.util.find_spec(pkg) is None:
                return refusal(self.name, pkg, self.extra)
        return None

    def version(self) -> str:
        import onnxruntime

        return onnxruntime.__version__

    def cannot_win(self, device: str) -> str | None:
        if not str(device).startswith("cpu"):
            return "ptovs runs ONNX Runtime on the CPU only"
        return None

    def load(self, module: Any, example: Any, key: Mapping[str, Any], threads: int):
        import onnxruntime as ort

        path = onnx_file(module, example, key)
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = max(1, int(threads))
        opts.inter_op_num_threads = 1
        opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        opts.log_severity_level = 3  # warnings of unused initialisers: not ours
        session = ort.InferenceSession(
            str(path), opts, providers=["CPUExecutionProvider"]
        )

        one = [o.name for o in session.get_outputs()] == ["y"]

        def run(x: np.ndarray) -> np.ndarray | list[np.ndarray]:
            x = np.ascontiguousarray(x, np.float32)
            ys = [np.asarray(y, np.float32) for y in session.run(None, {"x": x})]
            return ys[0] if one else ys

        return run

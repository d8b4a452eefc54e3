"""OpenVINO on the CPU, float32 (its hint says so: on a CPU with bf16
instructions OpenVINO's own default is bf16), subnormals flushed to zero, latency
mode, `threads` threads.
Its compiled model is cached by OpenVINO under the runtimes' cache, one folder
per OpenVINO version. A model imported from that cache does not flush subnormals
by itself (2026.4: MobileCLIP2-S0's tower ran 44 crops/s from its blob, 60
compiled), so a one-operation model is compiled with the same properties first,
which sets the flush on OpenVINO's threads (60 again). One output ("y") runs to
one array, several ("y0".."yk") to a list in their order."""

from __future__ import annotations

import importlib.util
from collections.abc import Mapping
from typing import Any

import numpy as np

from ptovs.encoders.runtimes import cache_dir, refusal
from ptovs.encoders.runtimes.export import onnx_file


class OpenVino:
    name = "openvino"
    extra = "clip"

    def missing(self) -> str | None:
        for pkg in ("openvino", "onnx"):
            if importlib.util.find_spec(pkg) is None:
                return refusal(self.name, pkg, self.extra)
        return None

    def version(self) -> str:
        import openvino

        return openvino.__version__

    def cannot_win(self, device: str) -> str | None:
        if not str(device).startswith("cpu"):
            return "ptovs runs OpenVINO on the CPU only"
        return None

    def load(self, module: Any, example: Any, key: Mapping[str, Any], threads: int):
        import openvino as ov

        path = onnx_file(module, example, key)
        core = ov.Core()
        # the compiled blob does not follow the properties: a folder per setting
        blobs = cache_dir() / f"openvino-{self.version().replace('/', '_')}-f32-ftz"
        blobs.mkdir(parents=True, exist_ok=True)
        props = {
            "INFERENCE_PRECISION_HINT": "f32",
            "PERFORMANCE_HINT": "LATENCY",
            "INFERENCE_NUM_THREADS": max(1, int(threads)),
            # subnormal floats as zero: a crop's black padding drives a tower's
            # activations there, which ran 2.6x slower (rows unchanged at 1e-7)
            "CPU_DENORMALS_OPTIMIZATION": True,
        }
        _flush_subnormals(core, props)
        compiled = core.compile_model(
            str(path), "CPU", {**props, "CACHE_DIR": str(blobs)}
        )
        request = compiled.create_infer_request()
        outputs = list(compiled.outputs)
        one = len(outputs) == 1 and "y" in outputs[0].get_names()

        def run(x: np.ndarray) -> np.ndarray | list[np.ndarray]:
            x = np.ascontiguousarray(x, np.float32)
            out = request.infer({0: x})
            ys = [np.array(out[o], np.float32) for o in outputs]
            return ys[0] if one else ys

        return run


def _flush_subnormals(core: Any, props: Mapping[str, Any]) -> None:
    """Compile and run a one-operation model under `props` (no cache): it sets
    the subnormal flush on OpenVINO's threads, which a model imported from the
    compiled cache leaves unset."""
    import openvino as ov
    import openvino.opset13 as ops

    x = ops.parameter([1, 4], np.float32)
    tiny = ov.Model([ops.relu(x)], [x])
    core.compile_model(tiny, "CPU", dict(props)).create_infer_request().infer(
        {0: np.ones((1, 4), np.float32)}
    )

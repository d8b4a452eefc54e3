"""Differentiable 3D Gaussian rasterizer (docs/rasterizer.md).

Stages import only from here.

```python
from ptovs.raster import Camera, Gaussians, render
out = render(gaussians, camera, colors, background=None)  # colors [N, D]
out.image  # [H, W, D]   out.alpha  # [H, W, 1]   out.depth  # [H, W, 1]
```

`render` validates its inputs once, projects (`_common.project`), bins the splats into
tiles (`_common.intersect`) and hands compositing to a backend: "torch" (the pure
PyTorch reference and oracle, `_reference`) or "cpu" (compiled, `_cpu`, which also
projects and bins in its kernel). Both give the same image up to float rounding.

This file is the package's face; the modules behind it are private to the package
(imported by each other and by tests, never by the rest of ptovs):

- `_common`: Camera, Gaussians, projection, tile binning, constants
- `_reference`: the pure-PyTorch compositing (the oracle, float64-capable)
- `_cpu`: the compiled C++ kernel (built on first use) and its autograd glue
- `_team`: the kernels' thread count, `kernels_only_parallel`, `set_deterministic`
- `_backends`: which backends exist, work here, and which one a call gets
- `_render`: `render` and its one-time input validation
- `_blend`: frozen-geometry blend weights as sparse matrices (docs/rasterizer.md §9)
- `_sh`: real spherical harmonics up to degree 3
"""

from __future__ import annotations

from ptovs.raster._backends import available_backends
from ptovs.raster._blend import BlendWeights, blend_weights, csr_matmul
from ptovs.raster._common import Camera, Gaussians
from ptovs.raster._render import RenderOutput, render
from ptovs.raster._sh import SH_C0, eval_sh
from ptovs.raster._team import deterministic, kernels_only_parallel, set_deterministic

__all__ = [
    "SH_C0",
    "VERSION",
    "BlendWeights",
    "Camera",
    "Gaussians",
    "RenderOutput",
    "available_backends",
    "blend_weights",
    "csr_matmul",
    "deterministic",
    "eval_sh",
    "kernels_only_parallel",
    "render",
    "set_deterministic",
]

VERSION = 2  # bump when rendered values change (constants, rules, conventions)

"""Import shims for the optional model backends (extras `[clip]`, `[sam]`, `[sam2]`).

torchvision 0.28.0 on PyPI is a CUDA build whose compiled ops cannot register
against the CPU torch wheel; `import torchvision` then fails in
`torchvision._meta_registrations` ("operator torchvision::nms does not exist").
Its pure-Python parts (transforms, box utilities) work once that module is
stubbed (docs/environment.md §4). Every backend imports torchvision, open_clip or
segment_anything through `import_backend`, so the stub is installed exactly once,
before the first import. ptovs never calls torchvision's C++ ops (nms,
roi_align); `ptovs.segment.masks` has its own box NMS.
"""

from __future__ import annotations

import importlib
import sys
import types
from typing import Any

_STUB = "torchvision._meta_registrations"

EXTRA_OF = {
    "open_clip": "clip",
    "segment_anything": "sam",
    "sam2": "sam2",
    "torchvision": "clip",
}

# sam2 is an sdist whose build requires torch: pip would fetch a CUDA torch into an
# isolated build environment, so it is built against the installed one (pyproject)
SAM2_INSTALL = (
    "SAM2_BUILD_CUDA=0 pip install --no-build-isolation --no-deps sam2==1.1.0 && "
    "pip install -e '.[sam2]'"
)


def _stub_meta_registrations() -> None:
    if "torchvision" in sys.modules or _STUB in sys.modules:
        return
    try:
        import torch

        if torch.cuda.is_available():  # a CUDA torch: the real module works
            return
    except ImportError:  # pragma: no cover - torch is a core dependency
        return
    sys.modules[_STUB] = types.ModuleType(_STUB)


def import_backend(module: str) -> Any:
    """Import an optional backend module, with a clear error naming the extra.

    Args:
        module: "open_clip", "segment_anything", "sam2" or "torchvision" (or
            one of their submodules).

    Returns:
        The imported module.

    Raises:
        ImportError: the extra is not installed (the message gives the command).
    """
    _stub_meta_registrations()
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        extra = EXTRA_OF.get(module.split(".")[0], "clip")
        how = (
            SAM2_INSTALL
            if extra == "sam2"
            else f"pip install torchvision==0.28.0 -e '.[{extra}]'"
        )
        raise ImportError(
            f"{module} is not installed ({exc}); install the extra with: {how} "
            "(pin torchvision to your torch; see README, 'Model backends')"
        ) from exc


def available(module: str) -> bool:
    """Whether an optional backend imports (never raises)."""
    try:
        import_backend(module)
    except Exception:  # noqa: BLE001 - any failure means "not usable here"
        return False
    return True

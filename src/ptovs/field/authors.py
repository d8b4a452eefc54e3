"""Import of the authors' released WE-GS models (docs/method.md §2, `import_dir`).

A release folder holds some of:

- `chkpnt<iter>.pth`: the 3DGS capture `((sh_degree, xyz, f_dc, f_rest, log-scales,
  wxyz quats, opacity logits, max_radii2D, grad accum, denom, optimiser state,
  spatial_lr_scale), iteration)`;
- `chkpnt_ae_<iter>.pth`: f_α and f_γ weights; `chkpnt_te_<iter>.pth`: f_β weights;
- a degree-5 3DGS PLY (`point_cloud/iteration_<iter>/point_cloud.ply` or any `*.ply`).

Every file is read with `torch.load(weights_only=True)`: a file that needs more than
tensors and plain containers to unpickle is refused. Network weights are matched to
the `authors` preset of `ptovs.nets.WildNets` by parameter name suffix when the names
agree, else by the order and shapes of the tensors (the layer sequence of
docs/method.md §2); a file whose tensors do not fit is refused naming the network.
"""

from __future__ import annotations

import logging
import pickle
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from ptovs.errors import InputError, MissingInputError
from ptovs.field.ply import read_ply
from ptovs.nets import WildNets

log = logging.getLogger(__name__)

_CKPT = re.compile(r"^chkpnt(\d+)\.pth$")


@dataclass
class ImportedField:
    """Raw 3DGS parameters (torch) plus the networks, if the release has them."""

    raw: dict[str, Tensor]  # means, quats, log_scales, opacity_logits, sh [N, K, 3]
    sh_degree: int
    nets: WildNets | None
    sources: list[str] = field(default_factory=list)


def load_trusted(path: Path) -> Any:
    """torch.load with weights_only=True; a refusal becomes a clear InputError."""
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        raise InputError(
            f"{path} needs more than tensors and plain containers to load "
            f"(weights_only=True refused it: {str(exc).splitlines()[0]}); ptovs does not "
            "unpickle arbitrary objects. Re-save it as a plain state dict."
        ) from None
    except (OSError, RuntimeError, EOFError, ValueError) as exc:
        raise InputError(f"{path} is not a readable torch checkpoint ({exc})") from None


def _pick(folder: Path, iteration: int) -> int | None:
    its = sorted(
        int(m.group(1)) for p in folder.iterdir() if (m := _CKPT.match(p.name))
    )
    if not its:
        return None
    if iteration < 0:
        return its[-1]
    if iteration not in its:
        raise MissingInputError(
            f"{folder} has no chkpnt{iteration}.pth (found iterations {its}); set "
            "import_iteration to one of them or -1 for the latest"
        )
    return iteration


def _geometry_from_capture(path: Path) -> tuple[dict[str, Tensor], int]:
    blob = load_trusted(path)
    params = blob[0] if isinstance(blob, (tuple, list)) and len(blob) == 2 else blob
    if not isinstance(params, (tuple, list)) or len(params) != 12:
        raise InputError(
            f"{path} is not a 3DGS capture: expected (12-tuple, iteration), got "
            f"{type(params).__name__} of length {len(params) if hasattr(params, '__len__') else '?'}"
        )
    degree, xyz, f_dc, f_rest, scaling, rotation, opacity = params[:7]
    tensors = dict(
        xyz=xyz,
        f_dc=f_dc,
        f_rest=f_rest,
        scaling=scaling,
        rotation=rotation,
        opacity=opacity,
    )
    for name, t in tensors.items():
        if not isinstance(t, Tensor):
            raise InputError(f"{path}: capture entry {name} is not a tensor")
    n = xyz.shape[0]
    shapes_ok = (
        xyz.shape == (n, 3)
        and f_dc.shape == (n, 1, 3)
        and f_rest.ndim == 3
        and f_rest.shape[0] == n
        and f_rest.shape[2] == 3
        and scaling.shape == (n, 3)
        and rotation.shape == (n, 4)
        and opacity.reshape(-1).shape == (n,)
    )
    if not shapes_ok:
        raise InputError(
            f"{path}: capture shapes do not fit 3DGS ({ {k: list(v.shape) for k, v in tensors.items()} })"
        )
    sh = torch.cat((f_dc, f_rest), 1).float()
    raw = {
        "means": xyz.float(),
        "quats": rotation.float(),
        "log_scales": scaling.float(),
        "opacity_logits": opacity.reshape(-1).float(),
        "sh": sh,
    }
    k = sh.shape[1]
    max_degree = int(round(k**0.5)) - 1
    if (max_degree + 1) ** 2 != k:
        raise InputError(f"{path}: {k} SH coefficients is not (d+1)^2")
    return raw, max_degree if not isinstance(degree, int) else max(int(degree), 0)


def _flatten(obj: Any, prefix: str = "") -> list[tuple[str, Tensor]]:
    if isinstance(obj, Tensor):
        return [(prefix, obj)]
    out: list[tuple[str, Tensor]] = []
    if isinstance(obj, Mapping):
        for k, v in obj.items():
            out += _flatten(v, f"{prefix}.{k}" if prefix else str(k))
    elif isinstance(obj, (list, tuple)):
        for i, v in enumerate(obj):
            out += _flatten(v, f"{prefix}.{i}" if prefix else str(i))
    return out


def _assign(
    module: nn.Module,
    what: str,
    tensors: list[tuple[str, Tensor]],
    used: set[int],
    source: Path,
) -> None:
    """Load `module` from the file's tensors: by name suffix, else by order and shape."""
    targets = [
        (k, v)
        for k, v in module.state_dict().items()
        if not k.endswith("num_batches_tracked")
    ]
    chosen: dict[str, int] = {}
    for k, v in targets:  # 1. names: the file's key ends with ours, same shape
        hits = [
            i
            for i, (name, t) in enumerate(tensors)
            if i not in used
            and (name == k or name.endswith("." + k))
            and tuple(t.shape) == tuple(v.shape)
        ]
        if len(hits) != 1:
            chosen = {}
            break
        chosen[k] = hits[0]
    if not chosen:  # 2. the layer sequence: in order, skipping what does not fit
        pos = 0
        for k, v in targets:
            while pos < len(tensors) and (
                pos in used or tuple(tensors[pos][1].shape) != tuple(v.shape)
            ):
                pos += 1
            if pos == len(tensors):
                raise InputError(
                    f"{source}: its tensors do not match the authors' {what} layers "
                    f"(no tensor of shape {list(v.shape)} for {k} in order); is it a "
                    "WE-GS release checkpoint?"
                )
            chosen[k] = pos
            pos += 1
    state = {k: tensors[i][1].float() for k, i in chosen.items()}
    module.load_state_dict(state, strict=False)
    used.update(chosen.values())


def import_released(folder: str | Path, iteration: int = -1) -> ImportedField:
    """Load a released WE-GS model (geometry, and networks when present).

    Args:
        folder: the release folder.
        iteration: which chkpnt<iter> set to use; -1 = the highest.

    Returns:
        The imported field.
    """
    folder = Path(folder).expanduser()
    if not folder.is_dir():
        raise MissingInputError(
            f"import_dir {folder} does not exist; point it at the folder holding "
            "chkpnt<iter>.pth / chkpnt_ae_<iter>.pth / chkpnt_te_<iter>.pth or the PLY"
        )
    it = _pick(folder, iteration)
    sources = []
    if it is not None:
        path = folder / f"chkpnt{it}.pth"
        raw, degree = _geometry_from_capture(path)
        sources.append(path.name)
    else:
        plys = sorted(folder.rglob("*.ply"))
        if not plys:
            raise MissingInputError(
                f"{folder} holds neither chkpnt<iter>.pth nor a *.ply; nothing to import"
            )
        best = plys[-1]
        data = read_ply(best)
        raw = {k: torch.from_numpy(np.ascontiguousarray(v)) for k, v in data.items()}
        degree = int(round(raw["sh"].shape[1] ** 0.5)) - 1
        sources.append(str(best.relative_to(folder)))
        it = _iteration_of(best)

    nets = None
    ae = folder / f"chkpnt_ae_{it}.pth" if it is not None else None
    te = folder / f"chkpnt_te_{it}.pth" if it is not None else None
    have_ae = ae is not None and ae.is_file()
    have_te = te is not None and te.is_file()
    if have_ae != have_te:
        missing = te if have_ae else ae
        raise MissingInputError(
            f"{missing} is missing: the appearance networks need both "
            f"chkpnt_ae_{it}.pth (f_α, f_γ) and chkpnt_te_{it}.pth (f_β)"
        )
    if have_ae:
        nets = WildNets(
            "authors", raw["sh"].shape[1], mask_concat="input", background=False
        )
        tensors = _flatten(load_trusted(ae))
        used: set[int] = set()
        _assign(nets.f_alpha, "f_α (appearance encoder)", tensors, used, ae)
        _assign(nets.f_gamma, "f_γ (colour MLP)", tensors, used, ae)
        _assign(
            nets.f_beta, "f_β (transient U-Net)", _flatten(load_trusted(te)), set(), te
        )
        nets.eval()
        sources += [ae.name, te.name]
    else:
        log.warning(
            "%s: no network checkpoints; importing the geometry only "
            "(a plain field without appearance embeddings)",
            folder,
        )
    for name, t in raw.items():
        if not torch.isfinite(t).all():
            raise InputError(f"{folder}: imported {name} contains NaN or Inf")
    log.info(
        "imported %d Gaussians (SH degree %d) from %s",
        raw["means"].shape[0],
        degree,
        ", ".join(sources),
    )
    return ImportedField(raw, degree, nets, sources)


def _iteration_of(path: Path) -> int | None:
    m = re.search(r"iteration_(\d+)", str(path))
    return int(m.group(1)) if m else None

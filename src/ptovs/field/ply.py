"""The standard 3DGS PLY (Inria layout), written and read with plyfile.

Vertex properties, all float32: x y z, nx ny nz (zeros), f_dc_0..2, f_rest_0..M-1,
opacity (logit), scale_0..2 (log), rot_0..3 (wxyz, unnormalised). f_rest holds the
SH coefficients beyond the DC term channel-major: f_rest_{c·(K−1)+k} is channel c
of coefficient k+1, as Inria's `save_ply` flattens `features_rest.transpose(1, 2)`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from plyfile import PlyData, PlyElement, PlyParseError

from ptovs.errors import InputError


def write_ply(
    path: str | Path,
    means: np.ndarray,  # [N, 3]
    sh: np.ndarray,  # [N, K, 3]
    opacity_logits: np.ndarray,  # [N]
    log_scales: np.ndarray,  # [N, 3]
    quats: np.ndarray,  # [N, 4] wxyz
) -> Path:
    """Write Gaussians as a standard 3DGS PLY (binary little-endian), atomically."""
    path = Path(path)
    n, k = sh.shape[0], sh.shape[1]
    if k not in (1, 4, 9, 16, 25, 36):
        raise ValueError(f"sh must have (d+1)^2 coefficients, got {k}")
    rest = np.asarray(sh[:, 1:, :]).transpose(0, 2, 1).reshape(n, -1)
    cols = (
        [("x", means[:, 0]), ("y", means[:, 1]), ("z", means[:, 2])]
        + [(f"n{a}", np.zeros(n)) for a in "xyz"]
        + [(f"f_dc_{c}", sh[:, 0, c]) for c in range(3)]
        + [(f"f_rest_{j}", rest[:, j]) for j in range(rest.shape[1])]
        + [("opacity", opacity_logits)]
        + [(f"scale_{j}", log_scales[:, j]) for j in range(3)]
        + [(f"rot_{j}", quats[:, j]) for j in range(4)]
    )
    data = np.empty(n, dtype=[(name, "<f4") for name, _ in cols])
    for name, values in cols:
        data[name] = np.asarray(values, np.float32)
    if not all(np.isfinite(data[name]).all() for name, _ in cols):
        raise ValueError("refusing to write non-finite Gaussian parameters to a PLY")
    from ptovs.outputs import OutputError, output_file

    def verify(tmp: Path) -> None:  # read back: a full disk can truncate silently
        try:
            back = PlyData.read(str(tmp))["vertex"].count
        except (OSError, ValueError, KeyError, IndexError, PlyParseError):
            back = -1
        if back != n:
            raise OutputError(
                f"{path}: the PLY written does not read back ({n} Gaussians "
                "written); is the disk full?"
            )

    with output_file(path, verify) as tmp:
        PlyData([PlyElement.describe(data, "vertex")], text=False).write(str(tmp))
    return path


def read_ply(path: str | Path) -> dict[str, np.ndarray]:
    """Read a 3DGS PLY: means, sh [N, K, 3], opacity_logits, log_scales, quats.

    Raises:
        InputError: not a PLY, or properties missing (the message names them).
    """
    path = Path(path)
    try:
        ply = PlyData.read(str(path))
        v = ply["vertex"]
    except (OSError, ValueError, KeyError, IndexError, PlyParseError) as exc:
        raise InputError(f"{path} is not a readable Gaussian PLY ({exc})") from None
    names = {p.name for p in v.properties}
    need = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity"]
    need += [f"scale_{j}" for j in range(3)] + [f"rot_{j}" for j in range(4)]
    missing = [p for p in need if p not in names]
    if missing:
        raise InputError(
            f"{path} lacks the 3DGS vertex properties {missing}; it is not a "
            "Gaussian-splat PLY"
        )
    n_rest = len([p for p in names if p.startswith("f_rest_")])
    k = 1 + n_rest // 3
    if n_rest % 3 or k not in (1, 4, 9, 16, 25, 36):
        raise InputError(f"{path}: {n_rest} f_rest properties is not 3·((d+1)²−1)")

    def col(name: str) -> np.ndarray:
        return np.asarray(v[name], np.float32)

    n = len(v.data)
    sh = np.zeros((n, k, 3), np.float32)
    sh[:, 0] = np.stack([col(f"f_dc_{c}") for c in range(3)], 1)
    if n_rest:
        rest = np.stack([col(f"f_rest_{j}") for j in range(n_rest)], 1)
        sh[:, 1:] = rest.reshape(n, 3, k - 1).transpose(0, 2, 1)
    return {
        "means": np.stack([col(a) for a in "xyz"], 1),
        "sh": sh,
        "opacity_logits": col("opacity"),
        "log_scales": np.stack([col(f"scale_{j}") for j in range(3)], 1),
        "quats": np.stack([col(f"rot_{j}") for j in range(4)], 1),
    }


def sh_degree_of(sh: np.ndarray) -> int:
    return int(round(np.sqrt(sh.shape[1]))) - 1

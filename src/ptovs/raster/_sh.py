"""Real spherical harmonics up to degree 3 (3DGS order and signs)."""

from __future__ import annotations

import torch
from torch import Tensor

# --- spherical harmonics ----------------------------------------------------

SH_C0 = 0.28209479177387814
_SH_C1 = 0.4886025119029199
_SH_C2 = (
    1.0925484305920792,
    -1.0925484305920792,
    0.31539156525252005,
    -1.0925484305920792,
    0.5462742152960396,
)
_SH_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def _sh_basis(degree: int, d: Tensor) -> Tensor:
    """Real SH basis (3DGS order and signs) at unit directions d [N, 3] -> [N, K]."""
    x, y, z = d.unbind(-1)
    out = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        out += [-_SH_C1 * y, _SH_C1 * z, -_SH_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [
            _SH_C2[0] * x * y,
            _SH_C2[1] * y * z,
            _SH_C2[2] * (2 * zz - xx - yy),
            _SH_C2[3] * x * z,
            _SH_C2[4] * (xx - yy),
        ]
    if degree >= 3:
        out += [
            _SH_C3[0] * y * (3 * xx - yy),
            _SH_C3[1] * x * y * z,
            _SH_C3[2] * y * (4 * zz - xx - yy),
            _SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            _SH_C3[4] * x * (4 * zz - xx - yy),
            _SH_C3[5] * z * (xx - yy),
            _SH_C3[6] * x * (xx - 3 * yy),
        ]
    return torch.stack(out, -1)


def eval_sh(degree: int, coeffs: Tensor, dirs: Tensor) -> Tensor:
    """View-dependent colour from spherical harmonics (3DGS convention), differentiable.

    Args:
        degree: SH degree, 0 to 3.
        coeffs: [N, K, 3] with K >= (degree + 1)**2; only the first (degree + 1)**2
            are used (3DGS keeps 16 while the active degree grows).
        dirs: [N, 3] view directions, unnormalised (means - camera centre).

    Returns:
        [N, 3] colour max(SH . basis + 0.5, 0).
    """
    if isinstance(degree, bool) or degree not in (0, 1, 2, 3):
        raise ValueError(f"degree must be 0, 1, 2 or 3, got {degree!r}")
    k = (degree + 1) ** 2
    if not isinstance(coeffs, Tensor) or coeffs.ndim != 3 or coeffs.shape[2] != 3:
        raise ValueError("coeffs must have shape [N, K, 3]")
    if coeffs.shape[1] < k:
        raise ValueError(f"coeffs must have K >= {k} for degree {degree}")
    if not isinstance(dirs, Tensor) or dirs.shape != (coeffs.shape[0], 3):
        raise ValueError(f"dirs must have shape [{coeffs.shape[0]}, 3]")
    # clamp under the root: a zero direction gives a zero vector, not NaN.
    d = dirs * torch.rsqrt(dirs.square().sum(-1, keepdim=True).clamp_min(1e-24))
    basis = _sh_basis(degree, d.to(coeffs.dtype))  # [N, k]
    return torch.clamp((basis[:, :, None] * coeffs[:, :k]).sum(1) + 0.5, min=0.0)

"""Frozen geometry (docs/rasterizer.md §9): per-pixel blend weights as a sparse matrix,
so a feature field renders by one sparse product per view.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ptovs.raster import _reference
from ptovs.raster._backends import cpu_module, resolve_backend
from ptovs.raster._common import (
    FAR,
    NEAR,
    Camera,
    Gaussians,
    sparse_csr,
)
from ptovs.raster._render import project_and_bin, validate

# --- frozen geometry: sparse blend weights (docs/rasterizer.md §9) ----------------


class _SpMM(torch.autograd.Function):
    """W @ f with backward WT @ g (W constant)."""

    @staticmethod
    def forward(ctx, f, w, wt):  # noqa: D102
        ctx.wt = wt
        return torch.sparse.mm(w, f)

    @staticmethod
    def backward(ctx, grad):  # noqa: D102
        return torch.sparse.mm(ctx.wt, grad.contiguous()), None, None


def _csr_pair(
    crow: Tensor, cols: Tensor, values: Tensor, n_rows: int, n_cols: int
) -> tuple[Tensor, Tensor]:
    """W = CSR(crow, cols, values) [n_rows, n_cols] and its transpose (sorted rows)."""
    mat = sparse_csr(crow, cols, values, (n_rows, n_cols))
    rows = torch.repeat_interleave(
        torch.arange(n_rows, device=crow.device), torch.diff(crow).long()
    )
    order = torch.sort(cols, stable=True).indices  # rows ascend within each column
    crow_t = torch.zeros(n_cols + 1, dtype=torch.int64, device=crow.device)
    crow_t[1:] = torch.cumsum(torch.bincount(cols.long(), minlength=n_cols), 0)
    mat_t = sparse_csr(crow_t, rows[order], values[order], (n_cols, n_rows))
    return mat, mat_t


class BlendWeights:
    """The frozen-geometry render as a sparse linear map: image = W @ f.

    W [H*W, N] holds alpha_i * T_i for every contributing (pixel, Gaussian) pair; there
    is no background term. `apply` is differentiable w.r.t. f (backward WT @ g). Each
    row of W may list its Gaussians front to back rather than by id.
    """

    def __init__(
        self,
        W: Tensor,  # noqa: N803
        WT: Tensor,  # noqa: N803
        height: int,
        width: int,
        csr: tuple | None = None,
    ) -> None:
        self.W = W  # sparse CSR [H*W, N]
        self.WT = WT  # sparse CSR [N, H*W]
        self.height = height
        self.width = width
        # int32 CSR triples of (W, WT) when the compiled backend built them: `apply`
        # then multiplies with its OpenMP spmm (faster than torch.sparse.mm here)
        self._csr = csr

    @classmethod
    def from_pairs(
        cls,
        pix: Tensor,  # [P] int64 flat pixel index y * W + x
        gid: Tensor,  # [P] int64 Gaussian id
        weights: Tensor,  # [P] alpha * T
        height: int,
        width: int,
        n: int,
    ) -> BlendWeights:
        """Build both CSR directions from distinct (pixel, Gaussian, weight) triples.

        Args:
            pix: flat pixel indices, in any order.
            gid: Gaussian ids.
            weights: blend weights alpha_i * T_i.
            height: image height.
            width: image width.
            n: number of Gaussians.

        Returns:
            The blend weights.
        """
        n_pix = height * width
        pix, gid, weights = pix.long(), gid.long(), weights.detach()
        order = torch.sort(pix, stable=True).indices
        crow = torch.zeros(n_pix + 1, dtype=torch.int64, device=pix.device)
        crow[1:] = torch.cumsum(torch.bincount(pix, minlength=n_pix), 0)
        mat, mat_t = _csr_pair(crow, gid[order], weights[order], n_pix, n)
        return cls(mat, mat_t, height, width)

    @classmethod
    def from_csr(
        cls, w: tuple, wt: tuple, height: int, width: int, n: int
    ) -> BlendWeights:
        """Wrap CSR triples (indptr, indices, values) of W and W^T, e.g. as cached."""
        n_pix = height * width
        mat, mat_t = sparse_csr(*w, (n_pix, n)), sparse_csr(*wt, (n, n_pix))
        csr = (tuple(w), tuple(wt)) if w[0].dtype == torch.int32 else None
        return cls(mat, mat_t, height, width, csr)

    def csr(self) -> tuple[tuple[Tensor, ...], tuple[Tensor, ...]]:
        """(W, W^T) as CSR triples (indptr, indices, values), e.g. to cache them."""
        if self._csr is not None:
            return tuple(self._csr[0]), tuple(self._csr[1])
        return tuple(
            (m.crow_indices(), m.col_indices(), m.values()) for m in (self.W, self.WT)
        )

    @property
    def nnz(self) -> int:
        return int(self.W.values().numel())

    @property
    def nbytes(self) -> int:
        """Bytes held by both directions (indptr, indices and values)."""
        return sum(t.numel() * t.element_size() for pair in self.csr() for t in pair)

    def seen(self) -> Tensor:
        """[N] bool: the Gaussian contributes to at least one pixel of this view."""
        indptr = self.csr()[1][0]
        return torch.diff(indptr.long()) > 0

    @property
    def n_gaussians(self) -> int:
        return self.W.shape[1]

    def apply(self, f: Tensor) -> Tensor:
        """Render per-Gaussian values through the frozen weights.

        Args:
            f: values [N, D] (same dtype as the weights), differentiable.

        Returns:
            image [H, W, D] = W @ f, with no background.
        """
        if not isinstance(f, Tensor) or f.ndim != 2 or f.shape[0] != self.n_gaussians:
            raise ValueError(f"f must have shape [{self.n_gaussians}, D]")
        if f.dtype != self.W.dtype:
            raise ValueError(f"f must be {self.W.dtype}, got {f.dtype}")
        if (
            self._csr is not None
            and f.device.type == "cpu"
            and f.dtype == torch.float32
        ):
            cpu = cpu_module()
            if cpu is not None:
                out = cpu.apply(*self._csr, f.contiguous())
                return out.reshape(self.height, self.width, f.shape[1])
        out = _SpMM.apply(f.contiguous(), self.W, self.WT)
        return out.reshape(self.height, self.width, f.shape[1])


def csr_matmul(csr: tuple[Tensor, Tensor, Tensor], n_cols: int, x: Tensor) -> Tensor:
    """A CSR matrix (indptr, indices, values) [rows, n_cols] times x [n_cols, D].

    The compiled OpenMP kernel for int32 float32 CPU triples, else torch.sparse.mm.
    No autograd: frozen-geometry training calls it for W·f and for Wᵀ·g.
    """
    indptr, indices, values = csr
    if x.shape[0] != n_cols:
        raise ValueError(f"x has {x.shape[0]} rows, the matrix {n_cols} columns")
    if (
        indptr.dtype == torch.int32
        and indices.dtype == torch.int32
        and values.dtype == torch.float32
        and x.dtype == torch.float32
        and x.device.type == "cpu"
    ):
        cpu = cpu_module()
        if cpu is not None:
            return cpu.spmm(indptr, indices, values, x.contiguous())
    mat = sparse_csr(indptr, indices, values.to(x.dtype), (indptr.numel() - 1, n_cols))
    return torch.sparse.mm(mat, x.contiguous())


def blend_weights(
    gaussians: Gaussians,
    camera: Camera,
    *,
    tile: int = 16,
    near: float = NEAR,
    far: float = FAR,
    antialias: bool = False,
    backend: str = "auto",
) -> BlendWeights:
    """The sparse weights W (alpha_i T_i) of one view for frozen geometry.

    `blend_weights(g, cam).apply(f)` equals `render(g, cam, f).image` without a
    background, and its backward is W^T @ grad.

    Args:
        gaussians: N Gaussians (frozen: no gradient flows to them).
        camera: the view.
        tile: tile edge in pixels (4, 8, 16 or 32).
        near: cull Gaussians with camera z <= near.
        far: cull Gaussians with camera z >= far.
        antialias: Mip-Splatting opacity compensation.
        backend: as in `render`; "cpu" builds W in the compiled kernel.

    Returns:
        The blend weights, W [H*W, N] and WT [N, H*W] in the Gaussians' dtype.
    """
    validate(gaussians, camera, None, None, tile, near, far, backend)
    dtype, device = gaussians.means.dtype, gaussians.means.device
    name = resolve_backend(backend, dtype, device)
    width, height = camera.width, camera.height
    with torch.no_grad():
        p, isect = project_and_bin(gaussians, camera, tile, near, far, antialias, name)
        geometry = (p.means2d, p.conics, p.opacities, isect, width, height)
        n, n_pix = len(gaussians), width * height
        cpu = cpu_module() if name == "cpu" else None
        csr = None
        if cpu is not None:
            csr = cpu.build_blend_weights(*geometry)  # CSR triples, built in row order
            w, wt = csr
            mat, mat_t = sparse_csr(*w, (n_pix, n)), sparse_csr(*wt, (n, n_pix))
        else:
            pairs = _reference.contributors(*geometry, weights=True)
            mat, mat_t = _csr_pair(pairs.crow, pairs.gid, pairs.weights, n_pix, n)
    return BlendWeights(mat, mat_t, height, width, csr)

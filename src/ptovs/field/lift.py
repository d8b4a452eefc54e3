"""The `lift` recipe's sums: no optimiser, each Gaussian's feature is the mean of
the segment features of the pixels it covers, weighted by its blending weight and
the pixel's mask weight (`ptovs.field.language.mask_weights`), summed view by view.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor

from ptovs.features import tuple_ids


@torch.no_grad()
def feature_lift_sums(
    wt_csr: tuple[Tensor, Tensor, Tensor],  # Wᵀ [P, HW] as CSR (indptr, pixels, w)
    segs: Sequence[np.ndarray],  # per slot [L, H, W] rows of feats[a] (−1: none)
    feats: Sequence[np.ndarray],  # per slot [n_a, D] segment features
    m: np.ndarray,  # [HW, L, A] mask weights (`mask_weights`)
    out: Tensor | None = None,  # [P, L, A, D] float32 to add into
) -> Tensor:
    """Adds one view's Σ_x W[x, k] m[x, ℓ, a] F_a[seg_a[ℓ, x]] for every Gaussian k
    to `out` ([P, L, A, D] float32, zeros if None) and returns it.

    Sparse products and no per-pixel D-vector: Wᵀ [P, HW] times S [HW, K], the
    mask-weighted pixel-to-segment map of every (level, slot) at once (segments
    numbered across slots; a slot's rows are already distinct across levels), gives
    the (Gaussian, segment) weights (through the pixels' segment tuples where the
    weights allow, `_by_tuples`); those, rows ordered as `out`'s (Gaussian, level,
    slot), multiply the stacked segment tables, added into `out` in place.
    """
    indptr, pix, val = wt_csr
    n = len(indptr) - 1
    n_lv, n_app, dim = segs[0].shape[0], len(segs), feats[0].shape[1]
    if out is None:
        out = torch.zeros(n, n_lv, n_app, dim)
    hw = m.shape[0]
    sizes = [len(f) for f in feats]
    offset = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    n_cols = int(offset[-1])
    if n_cols == 0 or len(pix) == 0:
        return out
    table = torch.from_numpy(np.concatenate([np.asarray(f, np.float32) for f in feats]))
    level_of = np.zeros(n_cols, np.int64)  # each column's level and slot
    slot_of = np.repeat(np.arange(n_app), sizes)
    cols = np.empty((hw, n_lv * n_app), np.int64)  # S [HW, K]: a pixel's segments
    wts = np.empty((hw, n_lv * n_app), np.float32)
    for a, seg in enumerate(segs):
        flat = seg.reshape(n_lv, -1).astype(np.int64)
        for lv in range(n_lv):
            c = flat[lv]
            level_of[c[c >= 0] + offset[a]] = lv
            cols[:, a * n_lv + lv] = np.maximum(c, 0) + offset[a]
            wts[:, a * n_lv + lv] = np.where(c >= 0, m[:, lv, a], 0.0)
    gs = _by_tuples(indptr, pix, val, cols, wts, n, n_cols)
    if gs is None:  # the weights differ between a pixel's segments: the general path
        gs = _by_product(indptr, pix, val, cols, wts, n, n_cols)
    g_of, c_of = gs.indices().numpy()  # coalesced: row-major, distinct pairs
    vals = gs.values().numpy()
    row = (g_of * n_lv + level_of[c_of]) * n_app + slot_of[c_of]
    order = np.argsort(row * n_cols + c_of)  # rows, then columns (sorted CSR)
    ptr = np.zeros(n * n_lv * n_app + 1, np.int64)  # CSR over every output row
    ptr[1:] = np.cumsum(np.bincount(row, minlength=n * n_lv * n_app))
    a_mat = torch.sparse_csr_tensor(
        torch.from_numpy(ptr), torch.from_numpy(c_of[order].astype(np.int64)),
        torch.from_numpy(vals[order].astype(np.float32)),
        size=(n * n_lv * n_app, n_cols), check_invariants=True,
    )  # fmt: skip
    out.view(-1, dim).addmm_(a_mat, table)  # accumulates in place
    return out


def _coo(rows: np.ndarray, cols: np.ndarray, vals: np.ndarray, size) -> Tensor:
    """A sparse COO tensor of the given entries (duplicates summed on coalesce)."""
    idx = torch.from_numpy(np.stack((rows, cols)).astype(np.int64))
    return torch.sparse_coo_tensor(
        idx, torch.from_numpy(vals), size=size, check_invariants=True
    )


def _by_product(indptr, pix, val, cols, wts, n, n_cols) -> Tensor:
    """(Gaussian, segment) weights [P, K], coalesced: Wᵀ [P, HW] times S [HW, K], the
    mask-weighted pixel-to-segment map, as one sparse product (L·A entries a pixel).
    In COO, not CSR: torch's CPU product of two sparse CSR tensors keeps ~16 MB a call
    at 153k Gaussians (torch 2.13; measured, docs/findings.md), which killed a
    2,934-photo lift at 23.7 GB."""
    hw = len(cols)
    keep = wts > 0
    s_ptr = np.zeros(hw + 1, np.int64)
    s_ptr[1:] = np.cumsum(keep.sum(1))
    s_mat = torch.sparse_csr_tensor(
        torch.from_numpy(s_ptr), torch.from_numpy(cols[keep]),
        torch.from_numpy(wts[keep]), size=(hw, n_cols), check_invariants=True,
    )  # fmt: skip
    w_mat = torch.sparse_csr_tensor(
        indptr.long(), pix.long(), val.float(), size=(n, hw), check_invariants=True
    )
    return torch.sparse.mm(w_mat.to_sparse_coo(), s_mat.to_sparse_coo()).coalesce()


def _by_tuples(indptr, pix, val, cols, wts, n, n_cols) -> Tensor | None:
    """The same product when each pixel's weight is one number q(x) for all its
    segments (the paper's loss: (1 − U_A)(1 − U_T)); None otherwise.

    Pixels are grouped by their tuple of segments (a view has thousands among 10⁵–10⁶
    pixels): Wᵀ's entries, scaled by q and relabelled by tuple, are summed per
    (Gaussian, tuple), first along runs (a Gaussian's pixels come in image order, so
    neighbours mostly share a tuple) and then exactly; that small [P, U] matrix times
    the tuples' [U, K] segment map is the product, with L·A times fewer terms than
    multiplying Wᵀ by S directly."""
    q = wts.max(1)
    if not np.array_equal(wts, np.where(wts > 0, q[:, None], 0.0)):
        return None
    w_rows = np.repeat(np.arange(n), np.diff(indptr.numpy()))  # Wᵀ's row of each entry
    pix, val = pix.numpy(), val.float().numpy()
    key = np.where(wts > 0, cols + 1, 0)  # 0: no segment there
    first, tup = tuple_ids(key)
    u = tup[pix]
    v = val * q[pix]
    run = np.ones(len(u), bool)
    run[1:] = (u[1:] != u[:-1]) | (w_rows[1:] != w_rows[:-1])
    at = np.flatnonzero(run)
    h_mat = _coo(w_rows[at], u[at], np.add.reduceat(v, at).astype(np.float32),
                 (n, len(first))).coalesce()  # fmt: skip
    t_key = key[first]  # [U, L·A]: each tuple's segments
    t_row, t_j = np.nonzero(t_key)
    t_mat = _coo(t_row, t_key[t_row, t_j] - 1, np.ones(len(t_row), np.float32),
                 (len(first), n_cols)).coalesce()  # fmt: skip
    return torch.sparse.mm(h_mat, t_mat).coalesce()

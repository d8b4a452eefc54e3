"""Pure-torch compositing: the oracle for every backend (docs/rasterizer.md §3).

Two passes, no Python loop over Gaussians or pixels:

1. `contributors` (no gradients) finds the CONTRIBUTING (pixel, Gaussian) pairs under
   the skip rules (sigma < 0, alpha < 1/255) and the exclusive early stop (the pair
   whose next_T <= 1e-4 ends the pixel and is not composited). Each tile list is
   split into 4x4-pixel sub-tile lists: an entry joins the sub-tiles that the box of
   its pre-exp-cull ellipse sigma <= ln(255 o) + 1e-3 touches. Pixels outside that
   box would be skipped anyway, so the result equals a literal walk of the tile lists.
   The sub-tile lists are walked front to back in rounds of B entries, dense over
   [sub-tile, B, 16 pixels], carrying each pixel's T as a float64 sequential product
   (as a per-pixel loop computes it, so even the exact boundary next_T = (1 - 0.99)^2
   is decided alike); a sub-tile leaves once all its pixels have stopped.
2. `composite` recomputes sigma and alpha of the contributing pairs with autograd, T
   as a differentiable segmented exclusive product (exp of a float64 cumsum of
   log(1 - alpha); 1 - alpha >= 0.01 keeps the log finite), and blends with a sparse
   [H*W, N] matrix of weights alpha * T (`_Blend`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ptovs.raster._common import (
    ALPHA_THRESHOLD,
    MAX_ALPHA,
    PRE_EXP_CULL_MARGIN,
    TRANSMITTANCE_THRESHOLD,
    Isect,
    sparse_csr,
)

SUB = 4  # sub-tile edge (divides every allowed tile size)
ROUND_SLOTS = 1 << 20  # dense (entry, pixel) slots per round: bounds pass-1 memory
MIN_ROUND = 16  # entries per sub-tile per round, at least


@dataclass
class Contributors:
    """Contributing pairs sorted by pixel, each pixel's pairs front to back."""

    pix: Tensor  # [P] int64 flat pixel index y * W + x, ascending
    gid: Tensor  # [P] int64 Gaussian id
    crow: Tensor  # [H*W + 1] int64 CSR offsets of each pixel's pairs
    weights: Tensor | None  # [P] alpha * T (no gradient), when asked for


def _take(x: Tensor, idx: Tensor) -> Tensor:
    """x[idx] for 1D x and any-shaped idx (index_select is several times faster)."""
    return torch.index_select(x, 0, idx.reshape(-1)).view(idx.shape)


def _sigma(dx: Tensor, dy: Tensor, a: Tensor, b: Tensor, c: Tensor) -> Tensor:
    # The same operation order as the compiled kernels.
    return 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy


def _alpha(sig: Tensor, o: Tensor) -> Tensor:
    return torch.clamp(o * torch.exp(-sig), max=MAX_ALPHA)


def _sub_tile_lists(
    means2d: Tensor,
    conics: Tensor,
    level: Tensor,
    isect: Isect,
    width: int,
    height: int,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Split the tile lists into per-sub-tile lists, keeping front-to-back order.

    Returns row_g [R] (Gaussian id of each row, rows grouped by sub-tile),
    gstart [G], gsize [G], gx0 [G], gy0 [G] (first row, row count, pixel origin).
    """
    device = means2d.device
    i64 = dict(dtype=torch.int64, device=device)
    tile, tw, n_tiles = isect.tile, isect.tw, isect.n_tiles
    ids = isect.flatten_ids.to(torch.int64)
    counts = torch.diff(isect.tile_offsets.to(torch.int64))
    entry_tile = torch.repeat_interleave(torch.arange(n_tiles, **i64), counts)

    # Box of the pre-exp-cull ellipse sigma <= L: |dx| <= sqrt(2 L (A^-1)_00), in
    # float64, padded for float32 rounding; an ill-conditioned conic takes the tile.
    a, b, c = conics.double().unbind(-1)
    det_a = a * c - b * b
    two_l = 2.0 * level.double().clamp_min(0)
    ext_x = torch.sqrt(two_l * c / det_a) * 1.001 + 0.01
    ext_y = torch.sqrt(two_l * a / det_a) * 1.001 + 0.01
    bad = ~(det_a > 0) | ~torch.isfinite(ext_x) | ~torch.isfinite(ext_y)
    ext_x = _take(torch.where(bad, torch.inf, ext_x), ids)
    ext_y = _take(torch.where(bad, torch.inf, ext_y), ids)
    live = _take(level >= 0, ids)  # o < 1/255 never reaches the threshold

    # Per entry, the range of sub-tile columns k (rows j) in its tile whose pixel
    # centres [x0 + 0.5, x0 + SUB - 0.5] overlap [u - ext, u + ext].
    ns = tile // SUB
    tx0 = ((entry_tile % tw) * tile).double()
    ty0 = ((entry_tile // tw) * tile).double()
    gu = _take(means2d[:, 0].double(), ids)
    gv = _take(means2d[:, 1].double(), ids)

    def sub_range(
        lo: Tensor, hi: Tensor, t0: Tensor, size: int
    ) -> tuple[Tensor, Tensor]:
        k_lo = torch.ceil((lo - t0 - (SUB - 0.5)) / SUB).clamp(0, ns)
        k_hi = torch.floor((hi - t0 - 0.5) / SUB)
        k_hi = torch.minimum(k_hi, torch.floor((size - 1 - t0) / SUB)).clamp(-1, ns - 1)
        return k_lo.to(torch.int16)[None, :], k_hi.to(torch.int16)[None, :]

    kx_lo, kx_hi = sub_range(gu - ext_x, gu + ext_x, tx0, width)
    ky_lo, ky_hi = sub_range(gv - ext_y, gv + ext_y, ty0, height)
    ky_hi = torch.where(live[None, :], ky_hi, -1)
    s_off = torch.arange(ns * ns, **i64)
    s_col = (s_off % ns).to(torch.int16)[:, None]  # [S, 1]
    s_row = (s_off // ns).to(torch.int16)[:, None]
    touch = (s_col >= kx_lo) & (s_col <= kx_hi) & (s_row >= ky_lo) & (s_row <= ky_hi)
    s_dx, s_dy = (s_off % ns) * SUB, (s_off // ns) * SUB  # [S]
    # touch is [S, M]: its nonzero orders rows by (sub-tile slot, tile, depth), so
    # each sub-tile's rows are contiguous and front to back, without a sort.
    flat = torch.nonzero(touch.view(-1)).squeeze(1)
    n_entries = ids.shape[0]
    row_s, row_e = flat // n_entries, flat % n_entries
    key = row_s * n_tiles + _take(entry_tile, row_e)
    new = torch.ones_like(key, dtype=torch.bool)
    new[1:] = key[1:] != key[:-1]
    gstart = torch.nonzero(new).squeeze(1)
    gsize = torch.diff(gstart, append=gstart.new_tensor([key.shape[0]]))
    gkey = _take(key, gstart)
    gs, gt = gkey // n_tiles, gkey % n_tiles
    gx0 = (gt % tw) * tile + _take(s_dx, gs)
    gy0 = (gt // tw) * tile + _take(s_dy, gs)
    return _take(ids, row_e), gstart, gsize, gx0, gy0


@torch.no_grad()
def contributors(
    means2d: Tensor,  # [N, 2]
    conics: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    isect: Isect,
    width: int,
    height: int,
    *,
    weights: bool = False,
) -> Contributors:
    """Pass 1: the contributing pairs, with the skip rules and the exclusive stop.

    Args:
        means2d: splat centres in pixels.
        conics: (a, b, c) inverse 2D covariances.
        opacities: splat opacities (compensated when antialiasing).
        isect: tile lists from `intersect`.
        width: image width.
        height: image height.
        weights: also return each pair's blend weight alpha * T.

    Returns:
        The pairs sorted by pixel, front to back within a pixel.
    """
    device, dtype = means2d.device, means2d.dtype
    i64 = dict(dtype=torch.int64, device=device)
    n_pix = width * height
    means2d, conics, opacities = means2d.detach(), conics.detach(), opacities.detach()
    # Pre-exp-cull level: sigma > L means alpha < 1/255 for sure (-inf for o = 0).
    level = torch.log(255.0 * opacities) + PRE_EXP_CULL_MARGIN
    row_g, gstart, gsize, gx0, gy0 = _sub_tile_lists(
        means2d, conics, level, isect, width, height
    )
    n_rows = row_g.shape[0]
    u, v = means2d[:, 0].contiguous(), means2d[:, 1].contiguous()
    a, b, c = (x.contiguous() for x in conics.unbind(-1))

    lx = torch.arange(SUB * SUB, **i64) % SUB  # [16] pixel offsets in a sub-tile
    ly = torch.arange(SUB * SUB, **i64) // SUB
    n_groups = gstart.shape[0]
    gpx = gx0[:, None] + lx  # [G, 16] pixel coordinates of every sub-tile
    gpy = gy0[:, None] + ly
    g_pix = gpy * width + gpx
    done = (gpx >= width) | (gpy >= height)  # off-image pixels never composite
    # Pixel centres; a finished pixel's centre moves to infinity, which makes its
    # sigma inf or NaN, so it fails the skip rules without a separate mask.
    cx = (gpx.to(dtype) + 0.5).masked_fill_(done, torch.inf)
    cy = gpy.to(dtype) + 0.5
    trans = torch.ones(n_groups, SUB * SUB, dtype=torch.float64, device=device)
    count = torch.zeros(n_groups, SUB * SUB, dtype=torch.int32, device=device)

    total = torch.zeros(n_pix, **i64)  # contributors per pixel
    out_pix, out_pos, out_gid, out_w = [], [], [], []
    rank0 = 0
    while gstart.shape[0]:
        n_alive = gstart.shape[0]
        n_b = max(MIN_ROUND, ROUND_SLOTS // (n_alive * SUB * SUB))
        n_b = min(n_b, int(gsize.max()) - rank0)  # no round past the longest list
        j = torch.arange(n_b, **i64)
        valid = j < (gsize - rank0)[:, None]  # [Ga, B] real rows, not padding
        rows = (gstart[:, None] + rank0 + j).clamp_max(max(n_rows - 1, 0))
        g = _take(row_g, rows)  # [Ga, B]

        def take(x: Tensor, g: Tensor = g) -> Tensor:  # per-row values as [Ga, B, 1]
            return _take(x, g)[:, :, None]

        # sigma and alpha dense over [Ga, B, 16] with d = mean2d - pixel centre, in
        # the operation order of _sigma and _alpha (in place to spare allocations).
        dx = take(u) - cx[:, None, :]
        dy = take(v) - cy[:, None, :]
        sig = (dx * take(a)).mul_(dx).add_((dy * take(c)).mul_(dy)).mul_(0.5)
        sig.add_((dx * take(b)).mul_(dy))
        del dx, dy
        o_row = torch.where(valid, _take(opacities, g), 0.0)  # padding: alpha = 0
        alpha = torch.exp(-sig).mul_(o_row[:, :, None]).clamp_(max=MAX_ALPHA)
        # Skip rules (the pre-exp cull only saves exp calls, so dense code skips it).
        keep = (sig >= 0).logical_and_(alpha >= ALPHA_THRESHOLD)
        del sig
        # next_T as the sequential float64 product T * (1 - a1) * (1 - a2) ... in
        # depth order, exactly as a per-pixel loop computes it (skips multiply by 1).
        factor = torch.where(keep, alpha, 0.0).double().neg_().add_(1.0)
        factor[:, 0, :] *= trans
        next_t = torch.cumprod(factor, 1)
        # Exclusive stop: the pair whose next_T <= 1e-4 ends the pixel, uncomposited.
        # T only decreases, so every later pair of that pixel fails the test too.
        comp = keep.logical_and_(next_t > TRANSMITTANCE_THRESHOLD)
        ccount = torch.cumsum(comp, 1, dtype=torch.int32)

        flat = torch.nonzero(comp.view(-1)).squeeze(1)
        slot = flat // (n_b * SUB * SUB) * (SUB * SUB) + flat % (SUB * SUB)  # [Ga*16]
        pix = _take(g_pix.view(-1), slot)
        total += torch.bincount(pix, minlength=n_pix)
        out_pix.append(pix)
        out_pos.append(_take(count.view(-1), slot) + _take(ccount.view(-1), flat) - 1)
        out_gid.append(_take(g.view(-1), flat // (SUB * SUB)))
        if weights:
            a_i = _take(alpha.view(-1), flat)
            t_i = _take(next_t.view(-1), flat) / (1.0 - a_i.double())  # 1 - a >= 0.01
            out_w.append(a_i * t_i.to(dtype))

        trans = next_t[:, -1, :]
        count += ccount[:, -1, :]
        newly = trans <= TRANSMITTANCE_THRESHOLD
        done |= newly
        cx.masked_fill_(newly, torch.inf)
        rank0 += n_b
        still = torch.nonzero((gsize > rank0) & ~done.all(1)).squeeze(1)
        gstart, gsize = _take(gstart, still), _take(gsize, still)
        g_pix, cx, cy, done, trans, count = (
            torch.index_select(x, 0, still) for x in (g_pix, cx, cy, done, trans, count)
        )

    return _pixel_order(
        total, out_pix, out_pos, out_gid, out_w if weights else None, means2d.dtype
    )


def _pixel_order(
    total: Tensor,
    out_pix: list[Tensor],
    out_pos: list[Tensor],
    out_gid: list[Tensor],
    out_w: list[Tensor] | None,
    dtype: torch.dtype,
) -> Contributors:
    """Counting sort of the rounds' pairs into pixel order: a pair's slot is the
    first slot of its pixel (the CSR row start) plus its rank in the pixel."""
    i64 = dict(dtype=torch.int64, device=total.device)
    n_pix = total.shape[0]
    crow = torch.zeros(n_pix + 1, **i64)
    crow[1:] = torch.cumsum(total, 0)
    n_pairs = int(crow[-1])
    gid = torch.empty(n_pairs, **i64)
    w = (
        torch.empty(n_pairs, dtype=dtype, device=total.device)
        if out_w is not None
        else None
    )
    for r, (pix, pos) in enumerate(zip(out_pix, out_pos, strict=True)):
        dest = _take(crow, pix) + pos
        gid.scatter_(0, dest, out_gid[r])
        if w is not None:
            w.scatter_(0, dest, out_w[r])
    pix = torch.repeat_interleave(torch.arange(n_pix, **i64), total)
    return Contributors(pix=pix, gid=gid, crow=crow, weights=w)


def _csr(crow: Tensor, cols: Tensor, values: Tensor, n_cols: int) -> Tensor:
    return sparse_csr(crow, cols, values, (crow.shape[0] - 1, n_cols))


class _Blend(torch.autograd.Function):
    """image = W @ colors with W [H*W, N] sparse CSR of the pair weights w.

    W's rows are pixels and its column indices run front to back, not ascending; the
    CSR kernels only sum products, so the order does not matter. Backward: grad_w is
    the sampled product (G @ colors^T) at W's pattern, grad_colors = W^T @ G.
    """

    @staticmethod
    def forward(ctx, w, colors, crow, pix, gid):  # noqa: D102
        mat = _csr(crow, gid, w, colors.shape[0])
        ctx.save_for_backward(w, colors, crow, pix, gid)
        return torch.sparse.mm(mat, colors.contiguous())

    @staticmethod
    def backward(ctx, grad):  # noqa: D102
        w, colors, crow, pix, gid = ctx.saved_tensors
        grad = grad.contiguous()
        grad_w = grad_c = None
        if ctx.needs_input_grad[0]:
            mat = _csr(crow, gid, torch.ones_like(w), colors.shape[0])
            grad_w = torch.sparse.sampled_addmm(
                mat, grad, colors.T.contiguous(), beta=0.0
            ).values()
        if ctx.needs_input_grad[1]:
            n = colors.shape[0]
            order = torch.sort(gid.to(torch.int32)).indices  # int32 sorts faster
            crow_t = torch.zeros(n + 1, dtype=torch.int64, device=gid.device)
            crow_t[1:] = torch.cumsum(torch.bincount(gid, minlength=n), 0)
            mat_t = _csr(crow_t, _take(pix, order), _take(w, order), grad.shape[0])
            grad_c = torch.sparse.mm(mat_t, grad)
        return grad_w, grad_c, None, None, None


def composite(
    means2d: Tensor,  # [N, 2]
    conics: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    colors: Tensor,  # [N, D]
    background: Tensor | None,  # [D]
    isect: Isect,
    width: int,
    height: int,
) -> tuple[Tensor, Tensor, Tensor]:
    """Alpha-composite splats front to back, differentiable (docs/rasterizer.md §3).

    Gradients flow to means2d, conics, opacities, colors and background.

    Args:
        means2d: splat centres in pixels.
        conics: (a, b, c) inverse 2D covariances.
        opacities: splat opacities.
        colors: values to blend (RGB, features, depth...).
        background: added as T_final * background; None for no background.
        isect: tile lists from `intersect`.
        width: image width.
        height: image height.

    Returns:
        image [H, W, D], alpha [H, W, 1] (1 - T_final) and n_contrib [H, W] int32,
        the number of composited Gaussians per pixel.
    """
    pairs = contributors(means2d, conics, opacities, isect, width, height)
    pix, gid, crow = pairs.pix, pairs.gid, pairs.crow

    # Pass 2: recompute alpha and T for the contributing pairs, with autograd.
    params = torch.cat(
        (means2d, conics, opacities[:, None]), 1
    ).T.contiguous()  # [6, N]
    u, v, a, b, c, o = (torch.index_select(x, 0, gid) for x in params)
    dtype, device = means2d.dtype, means2d.device
    centre_x = torch.arange(width, dtype=dtype, device=device).add_(0.5).repeat(height)
    centre_y = torch.arange(height, dtype=dtype, device=device).add_(0.5)
    dx = u - torch.index_select(centre_x, 0, pix)  # d = mean2d - pixel centre
    dy = v - torch.index_select(centre_y.repeat_interleave(width), 0, pix)
    alpha = _alpha(_sigma(dx, dy, a, b, c), o)
    log1m = torch.log1p(-alpha.double())  # 1 - alpha >= 0.01
    # Segmented exclusive sum in float64: log T_i = (sum of log1m over pairs < i)
    # minus the same sum over all earlier pixels' pairs (a cumsum over pixels).
    n_pix = width * height
    log_t_final = log1m.new_zeros(n_pix).index_add(0, pix, log1m)  # [H*W]
    before = torch.cumsum(log_t_final, 0) - log_t_final
    log_t = torch.cumsum(log1m, 0) - log1m - torch.index_select(before, 0, pix)
    w = alpha * torch.exp(log_t).to(alpha.dtype)  # alpha_i T_i

    image = _Blend.apply(w, colors, crow, pix, gid)  # [H*W, D]
    t_final = torch.exp(log_t_final).to(colors.dtype)
    if background is not None:
        image = image + t_final[:, None] * background
    n_contrib = torch.diff(crow).to(torch.int32)
    return (
        image.reshape(height, width, -1),
        (1.0 - t_final).reshape(height, width, 1),
        n_contrib.reshape(height, width),
    )

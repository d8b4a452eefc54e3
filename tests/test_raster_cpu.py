"""The compiled CPU compositing kernel (`ptovs.raster._cpu`) against the torch oracle.

Tolerances. Both backends apply the same skip and stop rules, but not bit-identically:
the kernel computes sigma with FMAs, exp with a polynomial (about 1 ulp) and T as a
float32 product, the oracle exp(cumsum(log1p(-alpha))) in float64. Smooth values
therefore agree to ~1e-7 relative (measured: 5e-8 to 4e-7 on every output). A pair
whose alpha sits within an ulp of 1/255, or whose next_T sits within an ulp of 1e-4,
can be decided differently and move one pixel (and its gradients) by up to ~1/255.
`_assert_close` therefore demands a relative L2 error <= 1e-5 on every tensor and
elementwise agreement to 1e-4 of the tensor's scale, except for at most `outliers`
elements (the boundary band). With the seeds below no element falls in the band.
"""

from __future__ import annotations

import math

import pytest
import torch

from conftest import has_compiler, need_system
from ptovs.raster import _common, _reference, _team

need_system("g++", has_compiler(), module=True)  # else the kernel cannot be built

from ptovs.raster import _cpu  # noqa: E402

REL_L2 = 1e-5
REL_ELEM = 1e-4


@pytest.fixture(scope="module", autouse=True)
def _built() -> None:
    assert _cpu.available(), "a C++ compiler exists, so the CPU kernel must build"


def _assert_close(name, actual, expected, outliers=0, rel_l2=REL_L2, rel_elem=REL_ELEM):
    assert actual.shape == expected.shape, name
    assert bool(torch.isfinite(actual).all()), f"{name}: non-finite values"
    a, e = actual.double(), expected.double()
    scale = e.abs().max().item()
    if scale == 0.0:
        assert a.abs().max().item() == 0.0, f"{name}: expected all zeros"
        return
    diff = (a - e).abs()
    bad = int((diff > rel_elem * scale).sum())
    assert bad <= outliers, f"{name}: {bad} elements off by > {rel_elem} x {scale:.3g}"
    l2 = ((a - e).norm() / e.norm()).item()
    assert l2 <= rel_l2 or bad > 0, f"{name}: relative L2 error {l2:.2e}"


def _gaussians(n, width, height, seed, opacity=(0.1, 0.9)):
    """Scene of docs/rasterizer.md §7: camera at the origin, down +z, fx = fy = W."""
    g = torch.Generator().manual_seed(seed)
    z = torch.rand(n, generator=g) * 4.0 + 2.0
    x = (torch.rand(n, generator=g) - 0.5) * z
    y = (torch.rand(n, generator=g) - 0.5) * height / width * z
    log_s = torch.rand(n, 3, generator=g) * math.log(6.0) + math.log(0.01)
    o = torch.rand(n, generator=g) * (opacity[1] - opacity[0]) + opacity[0]
    gs = _common.Gaussians(
        means=torch.stack((x, y, z), 1),
        quats=torch.randn(n, 4, generator=g),
        scales=log_s.exp(),
        opacities=o,
    )
    fx = float(width)
    K = torch.tensor([[fx, 0.0, width / 2], [0.0, fx, height / 2], [0.0, 0.0, 1.0]])
    return gs, _common.Camera(torch.eye(4), K, width, height)


def _splats(n, width, height, tile, seed):
    gs, cam = _gaussians(n, width, height, seed)
    with torch.no_grad():
        p = _common.project(gs, cam)
    return p, _common.intersect(p, width, height, tile)


def _run(composite, inputs, isect, width, height, v_image, v_alpha):
    """Composite, backprop <image, v_image> + <alpha, v_alpha>; outputs and grads."""
    leaves = [
        None if t is None else t.detach().clone().requires_grad_() for t in inputs
    ]
    image, alpha, n_contrib = composite(*leaves, isect, width, height)
    loss = (image * v_image).sum()
    if v_alpha is not None:
        loss = loss + (alpha * v_alpha).sum()
    loss.backward()
    grads = [None if t is None else t.grad for t in leaves]
    return image.detach(), alpha.detach(), n_contrib, grads


GRAD_NAMES = ("means2d", "conics", "opacities", "colors", "background")


def _compare(p, isect, width, height, d, seed, background=True, alpha_grad=True):
    g = torch.Generator().manual_seed(seed)
    n = p.means2d.shape[0]
    colors = torch.rand(n, d, generator=g)
    bg = torch.rand(d, generator=g) if background else None
    v_image = torch.randn(height, width, d, generator=g)
    v_alpha = torch.randn(height, width, 1, generator=g) if alpha_grad else None
    inputs = (p.means2d, p.conics, p.opacities, colors, bg)
    ref = _run(_reference.composite, inputs, isect, width, height, v_image, v_alpha)
    cpu = _run(_cpu.composite, inputs, isect, width, height, v_image, v_alpha)
    _assert_close("image", cpu[0], ref[0])
    _assert_close("alpha", cpu[1], ref[1])
    assert cpu[2].dtype == torch.int32
    assert torch.equal(cpu[2], ref[2]), "n_contrib"
    for name, gc, gr in zip(GRAD_NAMES, cpu[3], ref[3], strict=True):
        if gr is None:
            assert gc is None, name
        else:
            _assert_close(f"grad {name}", gc, gr)
    return cpu


@pytest.mark.parametrize(
    ("d", "tile", "width", "height", "n"),
    [
        (1, 8, 37, 29, 400),
        (3, 16, 50, 45, 600),
        (12, 8, 61, 35, 1500),
        (12, 16, 61, 35, 1500),
        (32, 16, 40, 33, 800),
        (3, 4, 23, 18, 150),
        (15, 8, 45, 38, 900),
        (12, 16, 130, 97, 20000),
    ],
)
def test_matches_reference(d, tile, width, height, n):
    p, isect = _splats(n, width, height, tile, seed=d * 100 + tile)
    out = _compare(p, isect, width, height, d, seed=7)
    assert (
        int(out[2].sum()) > 2 * width * height
    )  # overlapping splats, not a sparse toy


@pytest.mark.parametrize("d", [2, 4, 8, 16])
def test_no_background_and_no_alpha_grad(d):
    p, isect = _splats(500, 45, 31, 8, seed=3)
    out = _compare(p, isect, 45, 31, d, seed=8, background=False, alpha_grad=False)
    assert out[3][4] is None  # no background -> no background gradient


def test_pixel_centre_convention():
    # One isotropic splat centred on pixel (row 1, col 2), i.e. at (2.5, 1.5).
    means2d = torch.tensor([[2.5, 1.5]])
    conics = torch.tensor([[0.5, 0.0, 0.5]])
    opac = torch.tensor([0.8])
    p = _common.Projected(means2d, conics, opac, torch.ones(1), torch.full((1, 2), 4))
    isect = _common.intersect(p, 5, 4, 4)
    image, alpha, _ = _cpu.composite(
        means2d, conics, opac, torch.ones(1, 1), None, isect, 5, 4
    )
    assert image[1, 2, 0].item() == pytest.approx(0.8, rel=1e-6)  # sigma = 0 there
    side = 0.8 * math.exp(-0.25)  # one pixel away: sigma = 0.5 * 0.5 * 1
    for i, j in ((0, 2), (2, 2), (1, 1), (1, 3)):
        assert image[i, j, 0].item() == pytest.approx(side, rel=1e-6)
    assert torch.allclose(alpha[..., 0], image[..., 0], rtol=1e-6, atol=1e-7)


def _sequential(means2d, conics, opac, colors, isect, width, x, y):
    """A literal float32 walk over one pixel's tile list (docs/rasterizer.md §3)."""
    f32 = torch.float32
    tile_id = (y // isect.tile) * isect.tw + x // isect.tile
    s, e = int(isect.tile_offsets[tile_id]), int(isect.tile_offsets[tile_id + 1])
    t = torch.tensor(1.0, dtype=f32)
    out = torch.zeros(colors.shape[1], dtype=f32)
    count = 0
    for gid in isect.flatten_ids[s:e].tolist():
        dx = means2d[gid, 0] - (x + 0.5)
        dy = means2d[gid, 1] - (y + 0.5)
        a, b, c = conics[gid]
        sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
        if sigma < 0:
            continue
        alpha = torch.clamp(opac[gid] * torch.exp(-sigma), max=0.99)
        if alpha < 1 / 255:
            continue
        next_t = t * (1 - alpha)
        if next_t <= 1e-4:  # exclusive stop
            break
        out += colors[gid] * alpha * t
        t = next_t
        count += 1
    return out, t, count


def test_saturation_stack():
    # 16 opaque splats within 1e-3 px of one spot: the 0.99 clamp fires, T collapses.
    g = torch.Generator().manual_seed(5)
    n, width, height = 16, 13, 11
    means2d = torch.tensor([6.3, 5.6]) + (torch.rand(n, 2, generator=g) - 0.5) * 1e-3
    conics = torch.tensor([0.4, 0.05, 0.3]).repeat(n, 1)
    opac = torch.ones(n)
    depths = torch.arange(n, dtype=torch.float32) + 1.0
    p = _common.Projected(means2d, conics, opac, depths, torch.full((n, 2), 6))
    for tile in (4, 8, 16):
        isect = _common.intersect(p, width, height, tile)
        out = _compare(p, isect, width, height, 3, seed=tile)
        image, alpha, n_contrib, grads = out
        assert alpha.max().item() > 0.99
        for grad in grads:
            assert bool(torch.isfinite(grad).all())
        colors = torch.rand(n, 3, generator=torch.Generator().manual_seed(tile))
        with torch.no_grad():
            img2, alpha2, nc2 = _cpu.composite(
                means2d, conics, opac, colors, None, isect, width, height
            )
        for x, y in ((6, 5), (5, 5), (7, 6), (0, 0), (12, 10)):
            c, t, count = _sequential(means2d, conics, opac, colors, isect, width, x, y)
            assert int(nc2[y, x]) == count
            assert torch.allclose(img2[y, x], c, rtol=1e-5, atol=1e-6)
            assert alpha2[y, x, 0].item() == pytest.approx(1 - t.item(), abs=1e-6)
        assert int(nc2[5, 6]) < n  # the stop fired before the stack ran out


def test_threads_agree_bit_for_bit():
    """Forward and backward give the same bits at 1, 2, 3 and 5 threads: the
    backward sums its gradients in fixed slices of tiles, not one per thread, so a
    run's answer does not depend on --threads (a field trained on 1 thread and on 2
    used to part within a few steps)."""
    p, isect = _splats(2000, 70, 50, 8, seed=11)
    g = torch.Generator().manual_seed(2)
    colors = torch.rand(2000, 12, generator=g)
    bg = torch.rand(12, generator=g)
    v_image = torch.randn(50, 70, 12, generator=g)
    v_alpha = torch.randn(50, 70, 1, generator=g)
    inputs = (p.means2d, p.conics, p.opacities, colors, bg)
    before = torch.get_num_threads()
    runs = []
    try:
        for threads in (1, 2, 3, 5):
            torch.set_num_threads(threads)
            runs.append(_run(_cpu.composite, inputs, isect, 70, 50, v_image, v_alpha))
    finally:
        torch.set_num_threads(before)
    one = runs[0]
    for other in runs[1:]:
        for a, b in zip(one[:3], other[:3], strict=True):
            assert torch.equal(a, b)
        for name, a, b in zip(GRAD_NAMES, one[3], other[3], strict=True):
            assert (a is None and b is None) or torch.equal(a, b), name


def test_backward_is_bitwise_reproducible():
    """Every slice sums its tiles in tile order and the slices are added in slice
    order: the same gradients bit for bit on every run, even with more threads than
    cores and threads taking slices first-come."""
    p, isect = _splats(3000, 96, 64, 8, seed=5)
    g = torch.Generator().manual_seed(3)
    colors = torch.rand(3000, 12, generator=g)
    v_image = torch.randn(64, 96, 12, generator=g)
    v_alpha = torch.randn(64, 96, 1, generator=g)
    inputs = (p.means2d, p.conics, p.opacities, colors, None)
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(4)
        runs = [_run(_cpu.composite, inputs, isect, 96, 64, v_image, v_alpha)[3]
                for _ in range(8)]  # fmt: skip
    finally:
        torch.set_num_threads(before)
    for other in runs[1:]:
        for name, a, b in zip(GRAD_NAMES, runs[0], other, strict=True):
            assert (a is None and b is None) or torch.equal(a, b), name


def test_render_end_to_end():
    from ptovs.raster import render

    gs, cam = _gaussians(800, 48, 36, seed=21)
    g = torch.Generator().manual_seed(4)
    colors = torch.rand(800, 4, generator=g)
    bg = torch.rand(4, generator=g)
    v_image = torch.randn(36, 48, 4, generator=g)
    v_alpha = torch.randn(36, 48, 1, generator=g)
    results = {}
    for backend in ("torch", "cpu"):
        leaves = [
            t.clone().requires_grad_()
            for t in (gs.means, gs.quats, gs.scales, gs.opacities, colors, bg)
        ]
        out = render(
            _common.Gaussians(*leaves[:4]), cam, leaves[4], background=leaves[5],
            backend=backend, tile=8, depth=False,
        )  # fmt: skip
        ((out.image * v_image).sum() + (out.alpha * v_alpha).sum()).backward()
        results[backend] = (
            out.image.detach(),
            out.alpha.detach(),
            [t.grad for t in leaves],
        )
    ref, cpu = results["torch"], results["cpu"]
    _assert_close("image", cpu[0], ref[0])
    _assert_close("alpha", cpu[1], ref[1])
    names = ("means", "quats", "scales", "opacities", "colors", "background")
    for name, a, b in zip(names, cpu[2], ref[2], strict=True):
        _assert_close(f"grad {name}", a, b)


def _empty_isect(width, height, tile):
    tw, th = -(-width // tile), -(-height // tile)
    return _common.Isect(
        tile_offsets=torch.zeros(tw * th + 1, dtype=torch.int32),
        flatten_ids=torch.zeros(0, dtype=torch.int32),
        tw=tw, th=th, tile=tile,
    )  # fmt: skip


@pytest.mark.parametrize("case", ["n0", "culled", "1x1"])
def test_empty(case):
    width, height, tile = (1, 1, 8) if case == "1x1" else (19, 13, 8)
    if case == "culled":  # splats exist but none passes 1/255 (and none is binned)
        n = 5
        means2d = torch.rand(n, 2) * 10
        conics = torch.tensor([[0.5, 0.0, 0.5]]).repeat(n, 1)
        opac = torch.full((n,), 1e-3)
    else:
        n = 0
        means2d, conics, opac = torch.zeros(0, 2), torch.zeros(0, 3), torch.zeros(0)
    isect = _empty_isect(width, height, tile)
    colors = torch.rand(n, 3)
    bg = torch.tensor([0.2, 0.5, 0.7])
    v_image = torch.ones(height, width, 3)
    out = _run(
        _cpu.composite,
        (means2d, conics, opac, colors, bg),
        isect,
        width,
        height,
        v_image,
        None,
    )
    image, alpha, n_contrib, grads = out
    assert torch.equal(image, bg.expand(height, width, 3))
    assert torch.equal(alpha, torch.zeros(height, width, 1))
    assert torch.equal(n_contrib, torch.zeros(height, width, dtype=torch.int32))
    assert torch.equal(grads[4], torch.full((3,), float(width * height)))
    for grad in grads[:4]:
        assert grad.shape[0] == n and not bool(grad.any())


def test_culled_but_binned_matches_reference():
    # Binned splats whose opacity is below 1/255 everywhere: nothing composites.
    p, isect = _splats(300, 33, 21, 8, seed=9)
    p.opacities = torch.full_like(p.opacities, 0.9 / 255)
    out = _compare(p, isect, 33, 21, 3, seed=1)
    assert int(out[2].sum()) == 0


def test_degenerate_splats_in_every_tile():
    # Every tile lists every splat (a worst case for the bounding boxes): far-away,
    # zero, indefinite, needle-thin and ordinary conics, in id order.
    width, height, tile = 29, 22, 8
    means2d = torch.tensor(
        [[1e20, 5.0], [10.0, -1e19], [7.3, 8.1], [15.2, 11.7], [20.5, 3.3],
         [3.1, 17.9], [12.0, 12.0], [25.5, 19.5]]
    )  # fmt: skip
    conics = torch.tensor(
        [[0.5, 0.0, 0.5], [0.5, 0.0, 0.5], [0.0, 0.0, 0.0], [0.3, 0.9, 0.2],
         [50.0, 0.0, 0.01], [1e-6, 0.0, 1e-6], [0.25, 0.1, 0.6], [1.0, 0.999, 1.0]]
    )  # fmt: skip
    opac = torch.tensor([0.9, 0.9, 0.02, 0.5, 0.8, 0.3, 0.7, 0.95])
    n = means2d.shape[0]
    tw, th = -(-width // tile), -(-height // tile)
    isect = _common.Isect(
        tile_offsets=(torch.arange(tw * th + 1) * n).int(),
        flatten_ids=torch.arange(n, dtype=torch.int32).repeat(tw * th),
        tw=tw, th=th, tile=tile,
    )  # fmt: skip
    p = _common.Projected(means2d, conics, opac, torch.ones(n), torch.ones(n, 2))
    out = _compare(p, isect, width, height, 3, seed=5)
    assert int(out[2].max()) >= 2


def test_one_pixel_image():
    p, isect = _splats(50, 1, 1, 16, seed=2)
    p.means2d = torch.rand(50, 2, generator=torch.Generator().manual_seed(0))
    isect = _common.intersect(p, 1, 1, 16)
    out = _compare(p, isect, 1, 1, 3, seed=3)
    assert int(out[2][0, 0]) > 0


def test_rejects_bad_input():
    p, isect = _splats(10, 16, 16, 8, seed=0)
    colors = torch.rand(10, 3)
    with pytest.raises(ValueError, match="float32"):
        _cpu.composite(
            p.means2d.double(), p.conics, p.opacities, colors, None, isect, 16, 16
        )
    with pytest.raises(ValueError, match="does not cover"):
        _cpu.composite(p.means2d, p.conics, p.opacities, colors, None, isect, 40, 16)
    bad = _common.Isect(
        isect.tile_offsets, isect.flatten_ids + 100, isect.tw, isect.th, 8
    )
    if bad.flatten_ids.numel():
        with pytest.raises(ValueError, match="out of range"):
            _cpu.composite(p.means2d, p.conics, p.opacities, colors, None, bad, 16, 16)


# --- frozen geometry: blend weights (docs/rasterizer.md §9) -------------------------


def _dense(csr, rows, cols):
    indptr, indices, values = csr
    row = torch.repeat_interleave(torch.arange(rows), torch.diff(indptr).long())
    out = torch.zeros(rows, cols)
    out.index_put_((row, indices.long()), values, accumulate=True)
    return out


@pytest.mark.parametrize("tile", [8, 16])
def test_blend_weights(tile):
    width, height, n, d = 53, 41, 1200, 12
    p, isect = _splats(n, width, height, tile, seed=30 + tile)
    w, wt = _cpu.build_blend_weights(
        p.means2d, p.conics, p.opacities, isect, width, height
    )
    indptr, indices, values = w
    assert (
        indptr.dtype == indices.dtype == torch.int32 and values.dtype == torch.float32
    )
    assert indptr.shape == (width * height + 1,) and wt[0].shape == (n + 1,)

    g = torch.Generator().manual_seed(0)
    f = torch.rand(n, d, generator=g)
    with torch.no_grad():
        image, alpha, n_contrib = _cpu.composite(
            p.means2d, p.conics, p.opacities, f, None, isect, width, height
        )
    # W f is the feature render without background; rows hold the contributors.
    assert torch.equal(torch.diff(indptr), n_contrib.reshape(-1))
    _assert_close("W f", _cpu.spmm(*w, f).reshape(height, width, d), image, rel_l2=1e-6)
    row_sums = torch.zeros(width * height).index_add_(
        0,
        torch.repeat_interleave(
            torch.arange(width * height), torch.diff(indptr).long()
        ),
        values,
    )
    _assert_close("sum of weights", row_sums, alpha.reshape(-1), rel_l2=1e-6)

    # W^T g is the colors gradient of the render; apply() is differentiable.
    v = torch.randn(height, width, d, generator=g)
    leaf = f.clone().requires_grad_()
    img, _, _ = _cpu.composite(
        p.means2d, p.conics, p.opacities, leaf, None, isect, width, height
    )
    (img * v).sum().backward()
    f2 = f.clone().requires_grad_()
    out = _cpu.apply(w, wt, f2)
    (out * v.reshape(-1, d)).sum().backward()
    _assert_close("W^T g", f2.grad, leaf.grad)
    _assert_close("W^T g (spmm)", _cpu.spmm(*wt, v.reshape(-1, d)), leaf.grad)

    # Both directions hold the same matrix (dense check), WT rows sorted by pixel.
    dense_w = _dense((indptr, indices, values), width * height, n)
    assert torch.equal(dense_w.T, _dense(wt, n, width * height))
    rows = torch.repeat_interleave(torch.arange(n), torch.diff(wt[0]).long())
    key = rows.long() * (width * height) + wt[1].long()
    assert bool((torch.diff(key) > 0).all())

    # COO: sorted by pixel, same triples as W.
    pix, gid, wgt = _cpu.blend_weights_coo(
        p.means2d, p.conics, p.opacities, isect, width, height
    )
    assert bool((torch.diff(pix) >= 0).all())
    assert torch.equal(gid, indices) and torch.equal(wgt, values)


def test_blend_weights_match_reference_pairs():
    p, isect = _splats(700, 40, 30, 8, seed=44)
    pairs = _reference.contributors(
        p.means2d, p.conics, p.opacities, isect, 40, 30, weights=True
    )
    pix, gid, wgt = _cpu.blend_weights_coo(
        p.means2d, p.conics, p.opacities, isect, 40, 30
    )
    assert torch.equal(pix, pairs.pix) and torch.equal(gid.long(), pairs.gid)
    _assert_close("weights", wgt, pairs.weights)


def test_spmm_general_shapes():
    # D beyond one 32-column block and a tail; empty rows; int32 CSR from torch.
    g = torch.Generator().manual_seed(1)
    dense = torch.rand(37, 23, generator=g) * (torch.rand(37, 23, generator=g) < 0.2)
    dense[5] = 0.0
    csr = dense.to_sparse_csr()
    indptr, indices = csr.crow_indices().int(), csr.col_indices().int()
    for d in (1, 3, 8, 13, 32, 45):
        f = torch.rand(23, d, generator=g)
        _assert_close(
            f"spmm D={d}",
            _cpu.spmm(indptr, indices, csr.values(), f),
            dense @ f,
            rel_l2=1e-6,
        )
    wt = _cpu.csr_transpose((indptr, indices, csr.values()), 23)
    assert torch.equal(_dense(wt, 23, 37), dense.T)


# --- compiled projection and tile binning (docs/rasterizer.md §1, §2) ----------------
#
# The kernel mirrors `_common.project` but does its per-Gaussian algebra in float64
# (rounded to float32 once), so it is compared with `_common.project` run in float64
# on the same float32 inputs (it sits within float32 rounding: measured <= 6e-8
# elementwise forward, <= 8e-8 of each gradient's scale) and with the float32 torch
# graph, whose own float32 error reaches ~2e-5 of a gradient's scale on wide scenes
# (hence the default 1e-4 elementwise, 1e-5 L2). Radii are compared exactly with the
# float32 graph.

F64 = torch.float64
PROJ_OUT = ("means2d", "conics", "opacities", "depths")
PROJ_IN = ("means", "quats", "scales", "opacities")


def _posed_camera(width, height, seed):
    """A rotated, translated camera with an off-centre principal point."""
    g = torch.Generator().manual_seed(seed)
    w = (torch.rand(3, generator=g, dtype=F64) - 0.5) * 0.2
    skew = torch.tensor(
        [[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]], dtype=F64
    )
    pose = torch.eye(4, dtype=F64)
    pose[:3, :3] = torch.linalg.matrix_exp(skew)
    pose[:3, 3] = (torch.rand(3, generator=g, dtype=F64) - 0.5) * 0.2
    K = torch.tensor(
        [[0.9 * width, 0.0, 0.45 * width], [0.0, 1.1 * width, 0.55 * height],
         [0.0, 0.0, 1.0]]
    )  # fmt: skip
    return _common.Camera(pose.float(), K, width, height)


def _wide_scene(n, width, height, seed):
    """§7 scene widened to 1.6x the frustum (off-image culls, clamped Jacobians)."""
    g = torch.Generator().manual_seed(seed)
    z = torch.rand(n, generator=g) * 5.0 + 0.5
    x = (torch.rand(n, generator=g) - 0.5) * 1.6 * z
    y = (torch.rand(n, generator=g) - 0.5) * 1.6 * height / width * z
    log_s = torch.rand(n, 3, generator=g) * math.log(30.0) + math.log(0.005)
    return _common.Gaussians(
        means=torch.stack((x, y, z), 1),
        quats=torch.randn(n, 4, generator=g),
        scales=log_s.exp(),
        opacities=torch.rand(n, generator=g),
    )


def _hard_gaussians():
    """docs/rasterizer.md §6 case 3 (float32), opacity 0.1."""
    means = torch.tensor(
        [
            [0.1, 0.0, 3.0],  # 0 zero scale on one axis
            [-0.2, 0.1, 3.0],  # 1 zero scale on all axes
            [0.0, -0.1, 3.5],  # 2 zero quaternion
            [0.0, 0.0, -2.0],  # 3 behind the camera
            [0.0, 0.0, 0.01],  # 4 exactly at the near plane (culled)
            [0.0, 0.0, 0.0100001],  # 5 just past the near plane
            [50.0, 0.0, 3.0],  # 6 far off-screen (FOV clamp, culled)
            [-2.5, 0.0, 3.0],  # 7 off-screen, clamped J, overlapping the image
            [0.0, 0.0, 5.0],  # 8 huge, covers the image
            [0.05, 0.05, 4.0],  # 9 anisotropy 1e4:1
            [0.0, 0.0, 1e11],  # 10 beyond far
            [0.0, 0.0, 0.0],  # 11 at the camera centre
            [0.1, 0.1, 2.0],  # 12 tiny quaternion (below the eps clamp)
            [0.0, 3.0, 3.0],  # 13 off-screen in y, clamped J, overlapping
        ]
    )
    n = means.shape[0]
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]] * n)
    quats[2] = 0.0
    quats[9] = torch.tensor([0.9, 0.1, 0.2, 0.3])
    quats[12] = torch.tensor([1e-30, 0.0, 0.0, 0.0])
    quats[13] = torch.tensor([0.3, -0.5, 0.2, 0.7])
    scales = torch.full((n, 3), 0.05)
    scales[0, 2] = 0.0
    scales[1] = 0.0
    scales[7] = torch.tensor([1.0, 0.3, 0.3])
    scales[8] = 100.0
    scales[9] = torch.tensor([1.0, 1e-4, 1e-4])
    scales[13] = torch.tensor([0.2, 1.5, 0.4])
    return _common.Gaussians(means, quats, scales, torch.full((n,), 0.1))


HARD_CULLED = (3, 4, 6, 10, 11)


def _project_vjp(project, gs, cam, dtype, seed, antialias):
    """Projection outputs and the VJP of random cotangents (float64-drawn)."""
    leaves = [
        t.detach().to(dtype).requires_grad_()
        for t in (gs.means, gs.quats, gs.scales, gs.opacities)
    ]
    p = project(_common.Gaussians(*leaves), cam, antialias=antialias)
    outs = [getattr(p, name) for name in PROJ_OUT]
    g = torch.Generator().manual_seed(seed)
    cots = [torch.randn(o.shape, generator=g, dtype=F64).to(dtype) for o in outs]
    grads = torch.autograd.grad(
        outs, leaves, cots, allow_unused=True, materialize_grads=True
    )
    return [o.detach() for o in outs], p.radii, list(grads)


def _check_projection(gs, cam, antialias, seed=0):
    cpu = _project_vjp(_cpu.project, gs, cam, torch.float32, seed, antialias)
    t32 = _project_vjp(_common.project, gs, cam, torch.float32, seed, antialias)
    t64 = _project_vjp(_common.project, gs, cam, F64, seed, antialias)
    assert cpu[1].dtype == torch.int32
    assert torch.equal(cpu[1], t32[1]), "radii"
    for name, a, e32, e64 in zip(PROJ_OUT, cpu[0], t32[0], t64[0], strict=True):
        assert a.dtype == torch.float32 and bool(torch.isfinite(a).all()), name
        torch.testing.assert_close(a.double(), e64, rtol=1e-6, atol=1e-30, msg=name)
        _assert_close(name, a, e32)
    for name, a, e32, e64 in zip(PROJ_IN, cpu[2], t32[2], t64[2], strict=True):
        assert a.dtype == torch.float32, name
        _assert_close(f"grad {name} (f64)", a, e64, rel_l2=1e-6, rel_elem=1e-6)
        _assert_close(f"grad {name}", a, e32)
    return cpu


@pytest.mark.parametrize("antialias", [False, True])
@pytest.mark.parametrize(
    ("n", "width", "height", "seed", "posed"),
    [(3000, 97, 61, 0, False), (3000, 64, 64, 1, True), (5000, 45, 80, 2, True)],
)
def test_project_matches_common(n, width, height, seed, posed, antialias):
    gs = _wide_scene(n, width, height, seed)
    cam = (
        _posed_camera(width, height, seed)
        if posed
        else _gaussians(1, width, height, 0)[1]
    )
    radii = _check_projection(gs, cam, antialias, seed)[1]
    kept = (radii > 0).all(1)
    assert 0.3 * n < int(kept.sum()) < n  # some culled, most kept


@pytest.mark.parametrize("antialias", [False, True])
def test_project_hard_cases(antialias):
    gs = _hard_gaussians()
    cam = _gaussians(1, 10, 8, 0)[1]
    outs, radii, grads = _check_projection(gs, cam, antialias)
    culled = (radii == 0).all(1)
    assert culled.nonzero().flatten().tolist() == list(HARD_CULLED)
    for grad in grads:
        assert bool(torch.isfinite(grad).all())
    # Zero cotangents on the culled Gaussians (what `render` sends): zero gradients.
    leaves = [t.clone().requires_grad_() for t in (gs.means, gs.quats, gs.scales)]
    opac = gs.opacities.clone().requires_grad_()
    p = _cpu.project(_common.Gaussians(*leaves, opac), cam, antialias=antialias)
    keep = (~culled).float()
    loss = sum(
        (getattr(p, name) * keep.reshape(-1, *[1] * (getattr(p, name).ndim - 1))).sum()
        for name in PROJ_OUT
    )
    loss.backward()
    for t in (*leaves, opac):
        assert bool(torch.isfinite(t.grad).all())
        assert not bool(t.grad[culled].any())
        assert bool(t.grad[~culled].any())


def test_project_clamped_axis_sends_gradient_to_z_only():
    cam = _gaussians(1, 8, 6, 0)[1]
    gs = _common.Gaussians(
        torch.tensor([[-3.0, 0.2, 3.0]]),
        torch.tensor([[1.0, 0.0, 0.0, 0.0]]),
        torch.full((1, 3), 0.5),
        torch.tensor([0.5]),
    )
    means = gs.means.clone().requires_grad_()
    p = _cpu.project(_common.Gaussians(means, gs.quats, gs.scales, gs.opacities), cam)
    assert (p.radii > 0).all()
    (grad,) = torch.autograd.grad(p.conics.sum(), means)
    assert grad[0, 0] == 0 and grad[0, 1] != 0 and grad[0, 2] != 0


def test_project_empty_and_threads():
    cam = _gaussians(1, 16, 12, 0)[1]
    empty = _common.Gaussians(
        torch.zeros(0, 3, requires_grad=True), torch.zeros(0, 4), torch.zeros(0, 3),
        torch.zeros(0),
    )  # fmt: skip
    p = _cpu.project(empty, cam)
    assert p.means2d.shape == (0, 2) and p.radii.shape == (0, 2)
    p.means2d.sum().backward()
    assert empty.means.grad.shape == (0, 3)
    isect = _cpu.intersect(p, 16, 12, 8)
    assert isect.tile_offsets.tolist() == [0] * 5 and isect.flatten_ids.numel() == 0

    gs = _wide_scene(4000, 53, 41, 5)
    before = torch.get_num_threads()
    results = []
    try:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            outs, radii, grads = _project_vjp(
                _cpu.project, gs, cam, torch.float32, 3, True
            )
            p = _cpu.project(gs, cam)
            isect = _cpu.intersect(p, 53, 41, 8)
            results.append(
                [*outs, radii, *grads, isect.tile_offsets, isect.flatten_ids]
            )
    finally:
        torch.set_num_threads(before)
    for a, b in zip(*results, strict=True):  # per Gaussian: bit-identical
        assert torch.equal(a, b)


def test_project_falls_back_for_camera_gradients_and_float64():
    gs = _wide_scene(300, 40, 30, 7)
    cam = _posed_camera(40, 30, 7)
    pose = cam.cam_from_world.clone().requires_grad_()
    posed = _common.Camera(pose, cam.K, 40, 30)
    p = _cpu.project(gs, posed)
    (p.means2d.sum() + p.conics.sum()).backward()
    assert pose.grad is not None and bool(pose.grad.any())
    g64 = gs.to(F64)
    p64 = _cpu.project(g64, cam)
    assert p64.means2d.dtype == F64
    ref = _common.project(g64, cam)
    assert torch.equal(p64.conics, ref.conics) and torch.equal(p64.radii, ref.radii)


def _assert_same_isect(a, b):
    assert (a.tw, a.th, a.tile) == (b.tw, b.th, b.tile)
    assert a.tile_offsets.dtype == b.tile_offsets.dtype == torch.int32
    assert a.flatten_ids.dtype == b.flatten_ids.dtype == torch.int32
    assert torch.equal(a.tile_offsets, b.tile_offsets)
    assert torch.equal(a.flatten_ids, b.flatten_ids)


@pytest.mark.parametrize("tile", [4, 8, 16, 32])
@pytest.mark.parametrize(("width", "height"), [(97, 61), (64, 64), (33, 17), (1, 1)])
def test_intersect_matches_common(tile, width, height):
    # Projected scenes (posed camera, some culled) ...
    gs = _wide_scene(3000, width, height, tile)
    with torch.no_grad():
        p = _cpu.project(gs, _posed_camera(width, height, tile))
    _assert_same_isect(
        _cpu.intersect(p, width, height, tile),
        _common.intersect(p, width, height, tile),
    )
    # ... and arbitrary splats: boxes cut by every edge, radii (0, r), huge radii,
    # depth ties (exact and after float32 narrowing), signed zeros, negative depths.
    g = torch.Generator().manual_seed(tile * 1000 + width)
    n = 4000
    means2d = torch.rand(n, 2, generator=g) * torch.tensor(
        [width + 80.0, height + 80.0]
    )
    means2d -= 40.0
    radii = torch.randint(0, 40, (n, 2), generator=g, dtype=torch.int32)
    radii[::97] = 2**31 - 1
    radii[1::53, 0] = 0
    pool = torch.tensor(
        [1.0, 2.0, 2.0000001, 3.5, 0.0, -0.0, -1.0, 1e-30, 1e30, float("inf")]
    )
    depths = pool[torch.randint(0, len(pool), (n,), generator=g)]
    depths[::3] = torch.rand(n, generator=g)[::3] * 5.0
    p = _common.Projected(
        means2d, torch.zeros(n, 3), torch.zeros(n), depths.double().float(), radii
    )
    a = _cpu.intersect(p, width, height, tile)
    _assert_same_isect(a, _common.intersect(p, width, height, tile))
    assert a.flatten_ids.numel() > 0


@pytest.mark.parametrize("antialias", [False, True])
def test_render_end_to_end_posed_with_depth(antialias):
    from ptovs.raster import render

    width, height, n, d = 57, 43, 1500, 12
    gs = _wide_scene(n, width, height, 12)
    cam = _posed_camera(width, height, 12)
    g = torch.Generator().manual_seed(5)
    colors = torch.rand(n, d, generator=g)
    bg = torch.rand(d, generator=g)
    v_image = torch.randn(height, width, d, generator=g)
    v_alpha = torch.randn(height, width, 1, generator=g)
    v_depth = torch.randn(height, width, 1, generator=g)
    results = {}
    for backend in ("torch", "cpu"):
        leaves = [
            t.clone().requires_grad_()
            for t in (gs.means, gs.quats, gs.scales, gs.opacities, colors, bg)
        ]
        out = render(
            _common.Gaussians(*leaves[:4]), cam, leaves[4], background=leaves[5],
            backend=backend, tile=16, antialias=antialias,
        )  # fmt: skip
        loss = (out.image * v_image).sum() + (out.alpha * v_alpha).sum()
        (loss + (out.depth * v_depth).sum()).backward()
        results[backend] = (
            [out.image.detach(), out.alpha.detach(), out.depth.detach()],
            out.radii,
            [t.grad for t in leaves],
        )
    ref, cpu = results["torch"], results["cpu"]
    assert torch.equal(cpu[1], ref[1]), "radii"
    for name, a, b in zip(("image", "alpha", "depth"), cpu[0], ref[0], strict=True):
        _assert_close(name, a, b)
    names = ("means", "quats", "scales", "opacities", "colors", "background")
    culled = (cpu[1] == 0).all(1)
    assert bool(culled.any())
    for name, a, b in zip(names, cpu[2], ref[2], strict=True):
        _assert_close(f"grad {name}", a, b)
        if name != "background":
            assert not bool(a[culled].any()), name  # culled: exactly zero


def test_render_hard_cases_cpu():
    from ptovs.raster import render

    gs = _hard_gaussians()
    cam = _gaussians(1, 10, 8, 0)[1]
    g = torch.Generator().manual_seed(0)
    colors = torch.rand(len(gs), 3, generator=g)
    v = torch.randn(8, 10, 3, generator=g)
    results = {}
    for backend in ("torch", "cpu"):
        leaves = [
            t.clone().requires_grad_()
            for t in (gs.means, gs.quats, gs.scales, gs.opacities, colors)
        ]
        out = render(_common.Gaussians(*leaves[:4]), cam, leaves[4], backend=backend)
        ((out.image * v).sum() + out.alpha.sum() + out.depth.sum()).backward()
        results[backend] = (out, [t.grad for t in leaves])
    (out, grads), (ref, ref_grads) = results["cpu"], results["torch"]
    assert out.alpha.max() < 1 - 0.9**8 + 1e-6  # no NaN turned into MAX_ALPHA
    _assert_close("image", out.image, ref.image)
    for grad, ref_grad in zip(grads, ref_grads, strict=True):
        assert bool(torch.isfinite(grad).all())
        assert not bool(grad[list(HARD_CULLED)].any())
        _assert_close("grad", grad, ref_grad)


@pytest.mark.parametrize(
    "value",
    ["native -fplugin=x.so", "$(touch /tmp/p)", "a b", "-O0", "x" * 80, "v3;ls"],
)
def test_march_refuses_what_is_not_a_target_name(monkeypatch, value):
    from ptovs.raster import _cpu_build

    monkeypatch.setenv("PTOVS_MARCH", value)
    with pytest.raises(ValueError, match="PTOVS_MARCH"):
        _cpu_build.march()


def test_march_defaults_to_native_and_names_the_build(monkeypatch):
    from ptovs.raster import _cpu_build

    monkeypatch.delenv("PTOVS_MARCH", raising=False)
    assert _cpu_build.march() == "native"
    monkeypatch.setenv("PTOVS_MARCH", " ")
    assert _cpu_build.march() == "native"
    native = _cpu_build._flag_sets()
    monkeypatch.setenv("PTOVS_MARCH", "x86-64-v3")
    v3 = _cpu_build._flag_sets()
    assert "-march=x86-64-v3" in v3[0][0] and "-march=native" in native[0][0]
    # another target is another library: never one built for the other loaded
    assert _cpu_build._build_name(*v3[0]) != _cpu_build._build_name(*native[0])


_AVX2_SCRIPT = """
import sys, numpy as np, torch
sys.path.insert(0, {tests!r})
from test_raster_cpu import _gaussians
from ptovs.raster import _cpu, render
assert _cpu.available(), "the kernel did not build"
gs, cam = _gaussians(600, 40, 30, seed=5)
cols = torch.rand(600, 3, generator=torch.Generator().manual_seed(6))
np.save({out!r}, render(gs, cam, cols, backend="cpu", depth=False).image.numpy())
"""


def test_an_avx2_build_renders_what_the_native_one_does(tmp_path):
    """PTOVS_MARCH=x86-64-v3 builds the kernel as for an AVX2 CPU (a process and a
    cache of its own): the same image within float32 rounding."""
    import os
    import platform
    import subprocess
    import sys
    from pathlib import Path

    import numpy as np

    from ptovs.raster import render

    if platform.machine() not in ("x86_64", "AMD64"):
        pytest.skip("x86-64 targets only")
    out = tmp_path / "img.npy"
    script = _AVX2_SCRIPT.format(tests=str(Path(__file__).parent), out=str(out))
    env = dict(os.environ, PTOVS_MARCH="x86-64-v3", PTOVS_CACHE_DIR=str(tmp_path / "c"))
    subprocess.run([sys.executable, "-c", script], check=True, env=env, timeout=600)
    gs, cam = _gaussians(600, 40, 30, seed=5)
    cols = torch.rand(600, 3, generator=torch.Generator().manual_seed(6))
    ours = render(gs, cam, cols, backend="cpu", depth=False).image.numpy()
    assert list((tmp_path / "c").rglob("*.so")), "no library built under the new cache"
    np.testing.assert_allclose(np.load(out), ours, rtol=0, atol=1e-5)


def test_nondeterministic_leaves_torch_its_threads(tmp_path):
    """`--nondeterministic`: inside the context torch keeps every thread (the team as
    before); the setting is recorded in provenance; the default is restored by the
    next command."""
    from click.testing import CliRunner

    from ptovs.artifacts import provenance
    from ptovs.cli import main

    before = torch.get_num_threads()
    try:
        r = CliRunner().invoke(main, ["--work-dir", str(tmp_path), "--threads", "3",
                                      "synth-scene", "--nondeterministic", "--help"])  # fmt: skip
        assert r.exit_code == 0, r.output
        assert not _team.deterministic() and provenance()["deterministic"] == "False"
        with _team.kernels_only_parallel():
            assert (torch.get_num_threads(), _team.threads()) == (3, 3)
        r = CliRunner().invoke(
            main, ["--work-dir", str(tmp_path), "synth-scene", "--help"]
        )
        assert r.exit_code == 0, r.output
        assert _team.deterministic() and provenance()["deterministic"] == "True"
    finally:
        _team.set_deterministic(True)
        torch.set_num_threads(before)


def test_kernels_only_parallel_keeps_the_team_and_restores():
    """Inside, torch runs on one thread and the kernels on the count it was entered
    with; afterwards (also after an error) both are as before."""
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(3)
        with pytest.raises(RuntimeError, match="boom"), _team.kernels_only_parallel():
            assert torch.get_num_threads() == 1
            assert _team.threads() == 3
            with _team.kernels_only_parallel():  # nested: the same team
                assert (torch.get_num_threads(), _team.threads()) == (1, 3)
            assert (torch.get_num_threads(), _team.threads()) == (1, 3)
            raise RuntimeError("boom")
        assert (torch.get_num_threads(), _team.threads()) == (3, 3)
    finally:
        torch.set_num_threads(before)

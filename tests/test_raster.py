"""The pure-torch rasterizer (the oracle) and the public API of `ptovs.raster`.

The reference is checked against a literal per-pixel float64 loop (`loop_composite`),
torch.autograd.gradcheck, and the hard cases of docs/rasterizer.md §6.
"""

from __future__ import annotations

import math
import warnings
from types import SimpleNamespace

import numpy as np
import pytest
import torch

import ptovs.raster as raster
from conftest import has_compiler, need_system
from ptovs.raster import (
    BlendWeights,
    Camera,
    Gaussians,
    available_backends,
    blend_weights,
    eval_sh,
    render,
)
from ptovs.raster import _backends as raster_backends
from ptovs.raster import _reference as ref
from ptovs.raster._common import Projected, intersect, project

F64 = torch.float64
F32 = torch.float32
TOL = {F32: dict(rtol=1e-4, atol=1e-5), F64: dict(rtol=1e-10, atol=1e-12)}


# --- helpers -----------------------------------------------------------------


def make_camera(width: int, height: int, dtype=F32, f=None, cx=None, cy=None) -> Camera:
    """Camera at the origin looking down +z (docs/rasterizer.md §7)."""
    f = float(width) if f is None else f
    cx = width / 2 if cx is None else cx
    cy = height / 2 if cy is None else cy
    K = torch.tensor([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]], dtype=dtype)
    return Camera(torch.eye(4, dtype=dtype), K, width, height)


def random_scene(n: int, width: int, height: int, seed: int = 0, dtype=F32, d: int = 3):
    """The §7 benchmark recipe, scaled to small images (sigma of a few pixels)."""
    g = torch.Generator().manual_seed(seed)
    z = torch.rand(n, generator=g, dtype=F64) * 4 + 2
    x = (torch.rand(n, generator=g, dtype=F64) - 0.5) * z * 1.1
    y = (torch.rand(n, generator=g, dtype=F64) - 0.5) * z * 1.1 * height / width
    log_s = torch.rand(n, 3, generator=g, dtype=F64) * math.log(6) + math.log(0.01)
    gauss = Gaussians(
        means=torch.stack((x, y, z), 1).to(dtype),
        quats=torch.randn(n, 4, generator=g, dtype=F64).to(dtype),
        scales=(torch.exp(log_s) * 64 / width).to(dtype),
        opacities=(torch.rand(n, generator=g, dtype=F64) * 0.8 + 0.1).to(dtype),
    )
    colors = torch.rand(n, d, generator=g, dtype=F64).to(dtype)
    return gauss, make_camera(width, height, dtype), colors


def stack_at(points, dtype=F64, scale=0.01, opacity=0.5) -> Gaussians:
    """Small isotropic Gaussians at the given camera-frame points."""
    means = torch.tensor(points, dtype=dtype)
    n = means.shape[0]
    quats = torch.zeros(n, 4, dtype=dtype)
    quats[:, 0] = 1
    opac = torch.as_tensor(opacity, dtype=dtype).expand(n).clone()
    return Gaussians(means, quats, torch.full((n, 3), scale, dtype=dtype), opac)


def loop_composite(p: Projected, colors, background, width: int, height: int):
    """The compositing rules of docs/rasterizer.md §3, literally, one pixel at a time.

    Every unculled Gaussian is visited in (float32 depth, id) order; no tiles. sigma
    and alpha are computed in the input dtype, T as a float64 running product.
    """
    dt = np.float32 if p.means2d.dtype == F32 else np.float64
    m = p.means2d.detach().numpy()
    con = p.conics.detach().numpy()
    o = p.opacities.detach().numpy()
    col = colors.detach().double().numpy()
    bg = None if background is None else background.detach().double().numpy()
    depth32 = p.depths.detach().float().numpy()
    alive = (p.radii > 0).all(1).numpy()
    order = sorted(
        (i for i in range(len(o)) if alive[i]), key=lambda i: (depth32[i], i)
    )
    half, max_alpha, threshold = dt(0.5), dt(0.99), dt(1 / 255)
    image = np.zeros((height, width, col.shape[1]))
    alpha = np.zeros((height, width, 1))
    n_contrib = np.zeros((height, width), np.int32)
    stopped = np.zeros((height, width), bool)
    for i in range(height):
        for j in range(width):
            t, acc, n = 1.0, np.zeros(col.shape[1]), 0
            for k in order:
                dx, dy = m[k, 0] - dt(j + 0.5), m[k, 1] - dt(i + 0.5)
                a, b, c = con[k]
                sigma = half * (a * dx * dx + c * dy * dy) + b * dx * dy
                if sigma < 0:
                    continue
                al = min(max_alpha, o[k] * np.exp(-sigma))
                if al < threshold:
                    continue
                next_t = t * (1.0 - float(al))
                if next_t <= 1e-4:  # exclusive stop
                    stopped[i, j] = True
                    break
                acc += col[k] * float(al) * t
                t, n = next_t, n + 1
            image[i, j] = acc + (t * bg if bg is not None else 0)
            alpha[i, j] = 1 - t
            n_contrib[i, j] = n
    return image, alpha, n_contrib, stopped


def reference_vs_loop(gauss, camera, colors, background, tile=16, **kw):
    """Run project -> intersect -> _reference.composite and the loop oracle."""
    p = project(gauss, camera, **kw)
    isect = intersect(p, camera.width, camera.height, tile)
    out = ref.composite(
        p.means2d, p.conics, p.opacities, colors, background, isect, camera.width,
        camera.height,
    )  # fmt: skip
    return out, loop_composite(p, colors, background, camera.width, camera.height)


def assert_matches_loop(out, loop, dtype):
    image, alpha, n_contrib = out
    np.testing.assert_allclose(image.detach().double().numpy(), loop[0], **TOL[dtype])
    np.testing.assert_allclose(alpha.detach().double().numpy(), loop[1], **TOL[dtype])
    np.testing.assert_array_equal(n_contrib.numpy(), loop[2])


def all_finite(*tensors) -> bool:
    return all(bool(torch.isfinite(t).all()) for t in tensors if t is not None)


def loss_and_grads(gauss, camera, colors, background=None, seed=0, **kw):
    """<image, v> + <alpha, v_a> + <depth, v_d> and its gradients w.r.t. everything."""
    leaves = [
        t.detach().clone().requires_grad_()
        for t in (gauss.means, gauss.quats, gauss.scales, gauss.opacities, colors)
    ]
    bg = None if background is None else background.detach().clone().requires_grad_()
    out = render(Gaussians(*leaves[:4]), camera, leaves[4], background=bg, **kw)
    g = torch.Generator().manual_seed(seed)
    loss = sum(
        (x * torch.rand(x.shape, generator=g, dtype=x.dtype)).sum()
        for x in (out.image, out.alpha, out.depth)
        if x is not None
    )
    grads = torch.autograd.grad(loss, leaves + ([bg] if bg is not None else []))
    return out, grads


# --- gradcheck -----------------------------------------------------------------


def gradcheck_scene(n: int = 4):
    torch.manual_seed(0)
    means = torch.stack(
        (
            (torch.rand(n, dtype=F64) - 0.5) * 2.0,
            (torch.rand(n, dtype=F64) - 0.5) * 1.5,
            torch.rand(n, dtype=F64) * 2 + 3,
        ),
        1,
    )
    quats = torch.randn(n, 4, dtype=F64)
    scales = torch.rand(n, 3, dtype=F64) * 0.3 + 0.2
    opac = torch.rand(n, dtype=F64) * 0.5 + 0.3
    colors = torch.rand(n, 3, dtype=F64)
    background = torch.rand(3, dtype=F64)
    camera = make_camera(8, 6, F64, f=8.0)
    return camera, (means, quats, scales, opac, colors, background)


@pytest.mark.parametrize("antialias", [False, True])
def test_gradcheck_render(antialias):
    camera, inputs = gradcheck_scene()

    def fn(means, quats, scales, opac, colors, background):
        out = render(
            Gaussians(means, quats, scales, opac), camera, colors,
            background=background, backend="torch", antialias=antialias,
        )  # fmt: skip
        return out.image, out.alpha, out.depth

    leaves = [t.clone().requires_grad_() for t in inputs]
    out = fn(*leaves)
    assert out[0].shape == (6, 8, 3) and out[1].shape == (6, 8, 1)
    assert (render(Gaussians(*inputs[:4]), camera, inputs[4]).n_contrib > 1).any()
    # The full Jacobian once; random projections (fast_mode) for the variant.
    assert torch.autograd.gradcheck(
        fn, leaves, eps=1e-6, atol=1e-6, rtol=1e-4, fast_mode=antialias
    )


def test_gradcheck_fov_clamp_path():
    """A splat centred left of the image (J clamped in x) but overlapping it."""
    camera = make_camera(8, 6, F64, f=8.0)
    # x/z = -1.0 < -lim_x- = -(0.5 + 0.3 * 0.5): the clamp is active.
    means = torch.tensor([[-3.0, 0.2, 3.0], [0.3, -0.1, 4.0]], dtype=F64)
    quats = torch.tensor([[0.9, 0.1, 0.3, -0.2], [1.0, 0.0, 0.0, 0.0]], dtype=F64)
    scales = torch.tensor([[1.5, 0.4, 0.6], [0.3, 0.2, 0.25]], dtype=F64)
    opac = torch.tensor([0.6, 0.5], dtype=F64)
    colors = torch.rand(2, 3, dtype=F64, generator=torch.Generator().manual_seed(1))
    out = render(Gaussians(means, quats, scales, opac), camera, colors)
    assert (out.radii[0] > 0).all() and out.image.abs().sum() > 0

    def fn(means, scales):
        out = render(Gaussians(means, quats, scales, opac), camera, colors)
        return out.image, out.alpha

    leaves = [means.clone().requires_grad_(), scales.clone().requires_grad_()]
    assert torch.autograd.gradcheck(fn, leaves, eps=1e-6, atol=1e-6, rtol=1e-4)


def test_fov_clamp_sends_gradient_to_z_only():
    """In the 2D covariance a clamped axis depends on z only (docs/rasterizer.md §1)."""
    camera = make_camera(8, 6, F64, f=8.0)
    g = stack_at([[-3.0, 0.2, 3.0]], scale=0.5)
    means = g.means.clone().requires_grad_()
    p = project(Gaussians(means, g.quats, g.scales, g.opacities), camera)
    (grad,) = torch.autograd.grad(p.conics.sum(), means)
    assert grad[0, 0] == 0  # x clamped: no gradient into x through the covariance
    assert grad[0, 1] != 0 and grad[0, 2] != 0


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_gradcheck_eval_sh(degree):
    g = torch.Generator().manual_seed(degree)
    k = (degree + 1) ** 2
    coeffs = (torch.randn(5, k, 3, generator=g, dtype=F64) * 0.2).requires_grad_()
    dirs = torch.randn(5, 3, generator=g, dtype=F64).requires_grad_()
    assert torch.autograd.gradcheck(lambda c, d: eval_sh(degree, c, d), (coeffs, dirs))


# --- the loop oracle -------------------------------------------------------------


@pytest.mark.parametrize("dtype", [F64, F32])
@pytest.mark.parametrize(
    ("n", "width", "height", "tile"),
    [(200, 21, 17, 4), (200, 21, 17, 16), (1200, 24, 19, 8), (60, 13, 7, 32)],
)
def test_reference_matches_loop(dtype, n, width, height, tile):
    gauss, camera, colors = random_scene(n, width, height, seed=n + tile, dtype=dtype)
    background = torch.rand(3, dtype=dtype, generator=torch.Generator().manual_seed(2))
    out, loop = reference_vs_loop(gauss, camera, colors, background, tile=tile)
    assert loop[2].max() > 2  # several layers per pixel
    assert_matches_loop(out, loop, dtype)


def test_dense_scene_hits_the_stop():
    gauss, camera, colors = random_scene(1500, 12, 10, seed=3, dtype=F64)
    gauss = Gaussians(
        gauss.means, gauss.quats, gauss.scales * 2, gauss.opacities.clamp(min=0.5)
    )
    out, loop = reference_vs_loop(gauss, camera, colors, None, tile=8)
    assert loop[3].mean() > 0.5  # most pixels stopped
    assert_matches_loop(out, loop, F64)


@pytest.mark.parametrize("dtype", [F64, F32])
@pytest.mark.parametrize("above", [True, False])
def test_exclusive_stop_boundary(dtype, above):
    """next_T of the 4th Gaussian just above / below 1e-4 at the centre pixel."""
    delta = 1e-9 if dtype == F64 else 1e-3
    # Centre pixel (2, 2) of a 5x5 image; splats exactly at its centre: alpha = o.
    camera = make_camera(5, 5, dtype, f=5.0, cx=2.5, cy=2.5)
    t3 = 0.2**3  # after three splats of opacity 0.8
    o4 = 1 - 1e-4 * (1 + (delta if above else -delta)) / t3
    gauss = stack_at(
        [[0, 0, 3.0], [0, 0, 4.0], [0, 0, 5.0], [0, 0, 6.0]],
        dtype=dtype, scale=1e-4, opacity=[0.8, 0.8, 0.8, o4],
    )  # fmt: skip
    colors = torch.eye(4, dtype=dtype)
    out, loop = reference_vs_loop(gauss, camera, colors, None)
    assert_matches_loop(out, loop, dtype)
    image, alpha, n_contrib = out
    assert n_contrib[2, 2] == (4 if above else 3)
    assert (image[2, 2, 3] > 0) == above
    if not above:  # exclusive: the stopping splat is not composited at all
        assert alpha[2, 2, 0] == pytest.approx(1 - t3, rel=1e-6)


def test_pixel_centre_convention():
    """A splat centred on (j + 0.5, i + 0.5) peaks at pixel (i, j), symmetrically."""
    camera = make_camera(7, 5, F64, f=7.0, cx=3.5, cy=2.5)
    out = render(
        stack_at([[0.0, 0.0, 4.0]], scale=0.05), camera, torch.ones(1, 1, dtype=F64)
    )
    img = out.image[..., 0]
    assert torch.argmax(img).item() == 2 * 7 + 3
    assert img[2, 2] == pytest.approx(img[2, 4].item(), rel=1e-12)
    assert img[1, 3] == pytest.approx(img[3, 3].item(), rel=1e-12)
    assert img[2, 2] > 0 and img[1, 3] > 0


def test_tile_size_invariance():
    gauss, camera, colors = random_scene(800, 37, 29, seed=5)
    outs = [
        render(gauss, camera, colors, tile=t, backend="torch") for t in (4, 8, 16, 32)
    ]
    for out in outs[1:]:
        assert torch.equal(out.image, outs[0].image)
        assert torch.equal(out.alpha, outs[0].alpha)
        assert torch.equal(out.depth, outs[0].depth)
        assert torch.equal(out.n_contrib, outs[0].n_contrib)


def test_intersect_matches_naive_binning():
    gauss, camera, _ = random_scene(300, 40, 24, seed=7)
    p = project(gauss, camera)
    for tile in (4, 8, 16, 32):  # 10x6, 5x3, 3x2, 2x1 tiles: includes a power of two
        isect = intersect(p, 40, 24, tile)
        tw, th = math.ceil(40 / tile), math.ceil(24 / tile)
        depth32 = p.depths.float()
        lists: list[list[int]] = [[] for _ in range(tw * th)]
        for i in range(len(gauss)):
            rx, ry = p.radii[i].tolist()
            if rx == 0:
                continue
            u, v = p.means2d[i].tolist()
            x0, x1 = (
                max(0, math.floor((u - rx) / tile)),
                min(tw, math.ceil((u + rx) / tile)),
            )
            y0, y1 = (
                max(0, math.floor((v - ry) / tile)),
                min(th, math.ceil((v + ry) / tile)),
            )
            for ty in range(y0, y1):
                for tx in range(x0, x1):
                    lists[ty * tw + tx].append(i)
        offsets = [0]
        for ids in lists:
            ids.sort(key=lambda i: (depth32[i].item(), i))
            offsets.append(offsets[-1] + len(ids))
        assert isect.tile_offsets.dtype == torch.int32
        assert isect.flatten_ids.dtype == torch.int32
        assert isect.tile_offsets.tolist() == offsets
        assert isect.flatten_ids.tolist() == [i for ids in lists for i in ids]


def test_depth_ties_after_narrowing_are_broken_by_id():
    """float64 depths equal in float32: order by Gaussian id, deterministically."""
    camera = make_camera(6, 6, F64, f=6.0)
    z = 4.0
    z2 = z + 1e-12  # the same float32 value
    assert np.float32(z) == np.float32(z2) and z != z2
    gauss = stack_at([[0.0, 0.0, z2], [0.0, 0.0, z], [0.02, 0.0, z]], scale=0.3)
    colors = torch.eye(3, dtype=F64)
    out, loop = reference_vs_loop(gauss, camera, colors, None)
    assert_matches_loop(out, loop, F64)  # the loop sorts by (float32 depth, id)
    isect = intersect(project(gauss, camera), 6, 6, 4)
    start, end = isect.tile_offsets[0].item(), isect.tile_offsets[1].item()
    assert isect.flatten_ids[start:end].tolist() == [0, 1, 2]
    again = render(gauss, camera, colors, backend="torch")
    assert torch.equal(
        again.image, render(gauss, camera, colors, backend="torch").image
    )


def test_projection_matches_direct_formula():
    gauss, camera, _ = random_scene(20, 32, 24, seed=11, dtype=F64)
    gauss = Gaussians(gauss.means, gauss.quats, gauss.scales * 3, gauss.opacities)
    pose = torch.eye(4, dtype=F64)
    pose[:3, :3] = torch.linalg.matrix_exp(
        torch.tensor([[0, -0.1, 0.05], [0.1, 0, -0.02], [-0.05, 0.02, 0]], dtype=F64)
    )
    pose[:3, 3] = torch.tensor([0.1, -0.2, 0.3], dtype=F64)
    camera = Camera(pose, camera.K, camera.width, camera.height)
    p = project(gauss, camera)
    K, R, t = camera.K.numpy(), pose[:3, :3].numpy(), pose[:3, 3].numpy()
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    for i in range(len(gauss)):
        w, x, y, z = (gauss.quats[i] / gauss.quats[i].norm()).tolist()
        rot = np.array(
            [
                [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
            ]
        )
        m = rot @ np.diag(gauss.scales[i].numpy())
        mc = R @ gauss.means[i].numpy() + t
        cov = R @ m @ m.T @ R.T
        tx = mc[2] * np.clip(
            mc[0] / mc[2], -(cx / fx + 0.3 * 16 / fx), (32 - cx) / fx + 0.3 * 16 / fx
        )
        ty = mc[2] * np.clip(
            mc[1] / mc[2], -(cy / fy + 0.3 * 12 / fy), (24 - cy) / fy + 0.3 * 12 / fy
        )
        jac = np.array(
            [
                [fx / mc[2], 0, -fx * tx / mc[2] ** 2],
                [0, fy / mc[2], -fy * ty / mc[2] ** 2],
            ]
        )
        cov2d = jac @ cov @ jac.T + 0.3 * np.eye(2)
        inv = np.linalg.inv(cov2d)
        np.testing.assert_allclose(
            p.conics[i].numpy(), [inv[0, 0], inv[0, 1], inv[1, 1]], rtol=1e-9
        )
        uv = [fx * mc[0] / mc[2] + cx, fy * mc[1] / mc[2] + cy]
        np.testing.assert_allclose(p.means2d[i].numpy(), uv, rtol=1e-12)
        assert p.depths[i].item() == pytest.approx(mc[2], rel=1e-12)
        radii = np.ceil(3.33 * np.sqrt(np.diag(cov2d)))
        if (p.radii[i] > 0).all():
            np.testing.assert_array_equal(p.radii[i].numpy(), radii)


# --- hard cases (docs/rasterizer.md §6) -----------------------------------------------


@pytest.mark.parametrize("dtype", [F64, F32])
def test_saturation_sixteen_opaque_stacked(dtype):
    g = torch.Generator().manual_seed(0)
    offsets = (torch.rand(16, 3, generator=g, dtype=F64) - 0.5) * 1e-3
    points = (offsets + torch.tensor([0.0, 0.0, 4.0], dtype=F64)).tolist()
    gauss = stack_at(points, dtype=dtype, scale=0.2, opacity=1.0)
    camera = make_camera(9, 7, dtype, f=9.0)
    colors = torch.rand(16, 4, generator=g, dtype=F64).to(dtype)
    background = torch.rand(4, generator=g, dtype=F64).to(dtype)
    out, loop = reference_vs_loop(gauss, camera, colors, background)
    assert_matches_loop(out, loop, dtype)
    assert out[1].max() > 0.99  # the MAX_ALPHA clamp fired
    # Two hits at 0.99 give next_T = (1 - 0.99)^2, the threshold itself: in float64
    # 1.0000000000000018e-4 (composited), in float32 9.99998e-5 (the stop).
    assert out[2][3, 4] == (2 if dtype == F64 else 1)
    res, grads = loss_and_grads(gauss, camera, colors, background)
    assert all_finite(res.image, res.alpha, res.depth, *grads)


def degenerate_gaussians(dtype=F64) -> Gaussians:
    """Zero scales, zero quaternion, behind camera, near plane, off-screen, huge..."""
    means = torch.tensor(
        [
            [0.1, 0.0, 3.0],  # 0 zero scale on one axis
            [-0.2, 0.1, 3.0],  # 1 zero scale on all axes
            [0.0, -0.1, 3.5],  # 2 zero quaternion
            [0.0, 0.0, -2.0],  # 3 behind the camera
            [0.0, 0.0, 0.01],  # 4 exactly at the near plane (culled: z <= near)
            [0.0, 0.0, 0.0100001],  # 5 just past the near plane
            [50.0, 0.0, 3.0],  # 6 far off-screen (FOV clamp, culled)
            [-2.5, 0.0, 3.0],  # 7 off-screen, clamped J, overlapping the image
            [0.0, 0.0, 5.0],  # 8 huge, covers the image
            [0.05, 0.05, 4.0],  # 9 anisotropy 1e4:1
            [0.0, 0.0, 1e11],  # 10 beyond far
        ],
        dtype=dtype,
    )
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]] * 11, dtype=dtype)
    quats[2] = 0
    quats[9] = torch.tensor([0.9, 0.1, 0.2, 0.3], dtype=dtype)
    scales = torch.full((11, 3), 0.05, dtype=dtype)
    scales[0, 2] = 0
    scales[1] = 0
    scales[7] = torch.tensor([1.0, 0.3, 0.3], dtype=dtype)
    scales[8] = 100.0
    scales[9] = torch.tensor([1.0, 1e-4, 1e-4], dtype=dtype)
    return Gaussians(means, quats, scales, torch.full((11,), 0.1, dtype=dtype))


@pytest.mark.parametrize("dtype", [F64, F32])
def test_degenerate_gaussians_are_finite(dtype):
    gauss = degenerate_gaussians(dtype)
    camera = make_camera(10, 8, dtype, f=10.0)
    colors = torch.rand(11, 3, generator=torch.Generator().manual_seed(0)).to(dtype)
    background = torch.tensor([0.2, 0.4, 0.6], dtype=dtype)
    out, grads = loss_and_grads(gauss, camera, colors, background)
    assert all_finite(out.image, out.alpha, out.depth, *grads)
    culled = (out.radii == 0).all(1).tolist()
    assert [culled[i] for i in (3, 4, 6, 10)] == [True] * 4
    assert not any(culled[i] for i in (0, 1, 2, 5, 7, 8, 9))
    # Opacity 0.1 everywhere: a NaN turned into MAX_ALPHA would show as alpha 0.99.
    assert out.alpha.max() < 1 - 0.9**8 + 1e-6
    out_ref, loop = reference_vs_loop(gauss, camera, colors, background)
    assert_matches_loop(out_ref, loop, dtype)
    # Culled Gaussians get exactly zero gradient, not NaN.
    for grad in grads[:5]:
        assert (grad[[3, 4, 6, 10]] == 0).all()


def test_one_huge_gaussian_covers_image():
    gauss = stack_at([[0.0, 0.0, 2.0]], scale=50.0, opacity=0.7)
    camera = make_camera(11, 9, F64, f=11.0)
    out, grads = loss_and_grads(gauss, camera, torch.ones(1, 2, dtype=F64))
    assert torch.allclose(out.alpha, torch.full_like(out.alpha, 0.7), rtol=1e-3)
    assert (out.n_contrib == 1).all() and all_finite(*grads)


@pytest.mark.parametrize("n_kind", ["empty", "all_culled"])
def test_empty_render_is_background(n_kind):
    camera = make_camera(7, 5, F64, f=7.0)
    if n_kind == "empty":
        gauss = Gaussians(
            *(torch.zeros(0, k, dtype=F64) for k in (3, 4, 3)),
            torch.zeros(0, dtype=F64),
        )
    else:
        gauss = stack_at([[0.0, 0.0, -1.0], [0.0, 0.0, 0.001], [1e3, 0.0, 1.0]])
    n = len(gauss)
    colors = torch.rand(n, 3, dtype=F64)
    background = torch.tensor([0.1, 0.5, 0.9], dtype=F64, requires_grad=True)
    leaves = [
        t.clone().requires_grad_()
        for t in (gauss.means, gauss.quats, gauss.scales, gauss.opacities, colors)
    ]
    out = render(Gaussians(*leaves[:4]), camera, leaves[4], background=background)
    assert torch.equal(out.image, background.detach().expand(5, 7, 3))
    assert (
        (out.alpha == 0).all() and (out.depth == 0).all() and (out.n_contrib == 0).all()
    )
    (out.image.sum() + out.alpha.sum()).backward()
    assert torch.equal(background.grad, torch.full((3,), 35.0, dtype=F64))
    for leaf in leaves:
        assert leaf.grad is not None and (leaf.grad == 0).all()


def test_one_pixel_image():
    camera = make_camera(1, 1, F64, f=1.0)
    gauss = stack_at([[0.0, 0.0, 2.0], [0.1, 0.0, 3.0]], scale=0.5)
    colors = torch.tensor([[1.0, 0.0], [0.0, 1.0]], dtype=F64)
    out, loop = reference_vs_loop(gauss, camera, colors, None)
    assert_matches_loop(out, loop, F64)
    res, grads = loss_and_grads(gauss, camera, colors)
    assert res.image.shape == (1, 1, 2) and all_finite(*grads)


# --- channels --------------------------------------------------------------------


def test_joint_rgb_and_features_equal_separate_passes():
    gauss, camera, rgb = random_scene(60, 23, 17, seed=9)
    feats = torch.rand(60, 12, generator=torch.Generator().manual_seed(1))
    bg = torch.tensor([0.3, 0.6, 0.9])
    joint = render(
        gauss,
        camera,
        torch.cat((rgb, feats), 1),
        background=torch.cat((bg, torch.zeros(12))),
    )
    sep_rgb = render(gauss, camera, rgb, background=bg)
    sep_feat = render(gauss, camera, feats, background=None)
    torch.testing.assert_close(joint.image[..., :3], sep_rgb.image, **TOL[F32])
    torch.testing.assert_close(joint.image[..., 3:], sep_feat.image, **TOL[F32])
    # Features carry no background: empty pixels stay exactly zero.
    empty = sep_feat.n_contrib == 0
    assert empty.any() and (sep_feat.image[empty] == 0).all()
    assert (sep_rgb.image[empty] == bg).all()


def test_normalised_feature_chunks_have_finite_gradients_at_zero():
    gauss, camera, _ = random_scene(50, 16, 12, seed=4)
    codes = torch.rand(50, 12)
    codes[:10] = 0  # x / (|x| + 1e-9) at x = 0
    codes.requires_grad_()
    chunks = codes.view(50, 4, 3)
    normed = (chunks / (chunks.norm(dim=-1, keepdim=True) + 1e-9)).view(50, 12)
    out = render(gauss, camera, normed, depth=False)
    (grad,) = torch.autograd.grad((out.image * out.image).sum(), codes)
    assert all_finite(grad) and grad[10:].abs().sum() > 0


# --- frozen geometry ---------------------------------------------------------------


@pytest.mark.parametrize(
    "backend,dtype", [("torch", F32), ("torch", F64), ("cpu", F32)]
)
def test_blend_weights_apply_equals_render(backend, dtype):
    if backend not in available_backends():
        need_system("g++", has_compiler())  # fails in CI, else skips, when missing
        pytest.skip("the compiled backend is unavailable (see its build log)")
    gauss, camera, _ = random_scene(500, 29, 21, seed=12, dtype=dtype)
    f = torch.rand(500, 12, generator=torch.Generator().manual_seed(3)).to(dtype)
    bw = blend_weights(gauss, camera, backend=backend)
    assert (bw._csr is not None) == (backend == "cpu")  # the compiled spmm is used
    assert isinstance(bw, BlendWeights) and bw.W.layout == torch.sparse_csr
    assert bw.W.shape == (29 * 21, 500) and bw.WT.shape == (500, 29 * 21)
    leaf = f.clone().requires_grad_()
    img = bw.apply(leaf)
    leaf_r = f.clone().requires_grad_()
    out = render(gauss, camera, leaf_r, background=None, depth=False, backend="torch")
    torch.testing.assert_close(img, out.image, rtol=1e-5, atol=1e-5)
    v = torch.rand(img.shape, generator=torch.Generator().manual_seed(4)).to(dtype)
    (g_apply,) = torch.autograd.grad((img * v).sum(), leaf)
    (g_render,) = torch.autograd.grad((out.image * v).sum(), leaf_r)
    torch.testing.assert_close(g_apply, g_render, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(g_apply, bw.WT @ v.reshape(-1, 12), rtol=1e-6, atol=1e-6)
    if dtype == F64:
        assert torch.autograd.gradcheck(bw.apply, (f[:, :2].clone().requires_grad_(),))


def test_blend_weights_from_pairs_any_order():
    gauss, camera, _ = random_scene(200, 16, 12, seed=13)
    p = project(gauss, camera)
    pairs = ref.contributors(
        p.means2d, p.conics, p.opacities, intersect(p, 16, 12, 16), 16, 12, weights=True
    )
    perm = torch.randperm(
        pairs.pix.shape[0], generator=torch.Generator().manual_seed(0)
    )
    bw = BlendWeights.from_pairs(
        pairs.pix[perm], pairs.gid[perm], pairs.weights[perm], 12, 16, 200
    )
    f = torch.rand(200, 3)
    out = render(gauss, camera, f, depth=False, backend="torch")
    torch.testing.assert_close(bw.apply(f), out.image, rtol=1e-5, atol=1e-6)


# --- spherical harmonics --------------------------------------------------------------


def real_sh(l: int, m: int, d: np.ndarray) -> np.ndarray:  # noqa: E741
    """Real SH with the Condon-Shortley phase from associated Legendre recursions."""
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    theta, phi = np.arccos(np.clip(z, -1, 1)), np.arctan2(y, x)
    am = abs(m)
    ct, st = np.cos(theta), np.sin(theta)
    pmm = (-1) ** am * math.prod(range(1, 2 * am, 2)) * st**am  # P_m^m
    if l == am:
        plm = pmm
    else:
        p_prev, plm = pmm, ct * (2 * am + 1) * pmm
        for ll in range(am + 2, l + 1):
            p_prev, plm = (
                plm,
                ((2 * ll - 1) * ct * plm - (ll + am - 1) * p_prev) / (ll - am),
            )
    norm = math.sqrt(
        (2 * l + 1) / (4 * math.pi) * math.factorial(l - am) / math.factorial(l + am)
    )
    if m == 0:
        return norm * plm
    trig = np.cos(am * phi) if m > 0 else np.sin(am * phi)
    return math.sqrt(2) * norm * trig * plm


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_eval_sh_matches_direct_formula(degree):
    g = torch.Generator().manual_seed(10 + degree)
    coeffs = torch.randn(64, 16, 3, generator=g, dtype=F64) * 0.3
    dirs = torch.randn(64, 3, generator=g, dtype=F64) * 5
    unit = (dirs / dirs.norm(dim=1, keepdim=True)).numpy()
    expect = np.zeros((64, 3))
    for l in range(degree + 1):  # noqa: E741
        for m in range(-l, l + 1):
            expect += real_sh(l, m, unit)[:, None] * coeffs[:, l * l + l + m].numpy()
    expect = np.maximum(expect + 0.5, 0)
    np.testing.assert_allclose(
        eval_sh(degree, coeffs, dirs).numpy(), expect, atol=1e-12
    )
    # K larger than needed: only the first (degree + 1)**2 coefficients count.
    trimmed = coeffs[:, : (degree + 1) ** 2]
    assert torch.equal(eval_sh(degree, coeffs, dirs), eval_sh(degree, trimmed, dirs))


def test_eval_sh_zero_direction_is_finite():
    coeffs = torch.randn(2, 16, 3, dtype=F64, requires_grad=True)
    dirs = torch.zeros(2, 3, dtype=F64, requires_grad=True)
    out = eval_sh(3, coeffs, dirs)
    out.sum().backward()
    assert all_finite(out, coeffs.grad, dirs.grad)
    with pytest.raises(ValueError, match="degree"):
        eval_sh(4, coeffs, dirs)
    with pytest.raises(ValueError, match="coeffs"):
        eval_sh(3, coeffs[:, :9], dirs)


# --- API ------------------------------------------------------------------------


def test_available_backends_and_auto():
    names = available_backends()
    assert names[0] == "torch"
    assert isinstance(raster.VERSION, int) and raster.VERSION >= 1
    gauss, camera, colors = random_scene(50, 12, 10, seed=1)
    out = render(gauss, camera, colors)  # auto: whichever backend, same contract
    assert out.image.shape == (10, 12, 3) and out.image.dtype == F32
    assert out.radii.dtype == torch.int32 and out.radii.shape == (50, 2)
    assert out.n_contrib.dtype == torch.int32 and out.depth.shape == (10, 12, 1)
    assert render(gauss, camera, colors, depth=False).depth is None


def test_unavailable_backend_warns_once_and_falls_back(monkeypatch):
    monkeypatch.setitem(raster_backends.BACKENDS, "cpu", lambda: None)
    monkeypatch.setattr(raster_backends, "_warned", set())
    gauss, camera, colors = random_scene(30, 8, 6, seed=2)
    with pytest.warns(RuntimeWarning, match="unavailable"):
        out = render(gauss, camera, colors, backend="cpu")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        render(gauss, camera, colors, backend="cpu")
    expect = render(gauss, camera, colors, backend="torch")
    assert torch.equal(out.image, expect.image)


def test_camera_from_view():
    view = SimpleNamespace(
        cam_from_world=np.eye(4),
        K=np.array([[10.0, 0, 5], [0, 10, 4], [0, 0, 1]]),
        width=10,
        height=8,
    )
    cam = Camera.from_view(view)
    assert cam.cam_from_world.dtype == F32 and cam.K.dtype == F32
    assert (cam.width, cam.height) == (10, 8)
    assert cam.to(F64).K.dtype == F64


def bad_inputs():
    gauss, camera, colors = random_scene(5, 8, 6, seed=0)
    nan_means = gauss.means.clone()
    nan_means[1, 0] = float("nan")
    inf_colors = colors.clone()
    inf_colors[0, 0] = float("inf")
    g = gauss
    return [
        (dict(gaussians=Gaussians(nan_means, g.quats, g.scales, g.opacities)), "means"),
        (dict(colors=inf_colors), "colors"),
        (
            dict(gaussians=Gaussians(g.means, g.quats[:, :3], g.scales, g.opacities)),
            "quats",
        ),
        (
            dict(gaussians=Gaussians(g.means, g.quats, g.scales.double(), g.opacities)),
            "scales",
        ),
        (
            dict(gaussians=Gaussians(g.means, g.quats, g.scales, g.opacities * 2)),
            "opacities",
        ),
        (dict(gaussians=Gaussians(g.means, g.quats, -g.scales, g.opacities)), "scales"),
        (dict(colors=colors[:, :0]), "colors"),
        (dict(colors=colors[:4]), "colors"),
        (dict(background=torch.zeros(4)), "background"),
        (dict(camera=Camera(camera.cam_from_world, camera.K, 0, 6)), "width"),
        (dict(camera=Camera(camera.cam_from_world, camera.K, 8, 6.0)), "height"),
        (dict(tile=5), "tile"),
        (dict(near=-1.0), "near"),
        (dict(backend="cuda9"), "backend"),
    ], (gauss, camera, colors)


def test_bad_inputs_raise_value_error_naming_the_argument():
    cases, (gauss, camera, colors) = bad_inputs()
    for override, name in cases:
        kw = dict(gaussians=gauss, camera=camera, colors=colors) | override
        with pytest.raises(ValueError, match=name):
            render(kw.pop("gaussians"), kw.pop("camera"), kw.pop("colors"), **kw)


@pytest.mark.parametrize("backend", ["torch", "cpu"])
@pytest.mark.parametrize("what", ["scale", "mean"])
def test_huge_values_give_finite_gradients(backend, what):
    # Overflowing float32 arithmetic (det of a 1e20-scale splat, a mean at 1e30) culls
    # the Gaussian; its zero upstream gradients must not become 0 * inf = NaN.
    if backend not in available_backends():
        need_system("g++", has_compiler())  # fails in CI, else skips, when missing
        pytest.skip("the compiled backend is unavailable (see its build log)")
    gauss, camera, colors = random_scene(6, 16, 12, seed=21)
    means, scales = gauss.means.detach().clone(), gauss.scales.detach().clone()
    for k, big in enumerate((1e10, 1e20, 3e38)):
        if what == "scale":
            scales[k] = big
        else:
            means[k] = torch.tensor([big, -big, big])
    leaves = [
        t.requires_grad_()
        for t in (
            means,
            gauss.quats.detach().clone(),
            scales,
            gauss.opacities.detach().clone(),
            colors.detach().clone(),
        )
    ]
    g = Gaussians(*leaves[:4])
    out = render(g, camera, leaves[4], backend=backend)
    (out.image.sum() + out.alpha.sum() + out.depth.sum()).backward()
    assert (out.radii[:3] == 0).all()  # beyond float32: culled, not NaN
    assert all_finite(out.image) and all_finite(out.alpha) and all_finite(out.depth)
    for t in leaves:
        assert all_finite(t.grad)
    for t in leaves[:4]:
        assert (t.grad[:3] == 0).all()  # culled: exactly zero gradient

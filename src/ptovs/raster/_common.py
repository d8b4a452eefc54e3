"""Geometry shared by every rasterizer backend (docs/rasterizer.md §1, §2 and §5).

`project` is the differentiable EWA projection (plain torch autograd) and `intersect`
the vectorised, gradient-free tile binning. Every backend calls both and differs only
in its compositing, so their images agree up to the compositing arithmetic.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import torch
from torch import Tensor

# docs/rasterizer.md §5. Changing any of these changes rendered images: bump VERSION.
ALPHA_THRESHOLD = 1.0 / 255.0  # skip a pair below it
MAX_ALPHA = 0.99  # Inria, LangSplat and gsplat HEAD (gsplat <= 1.5.3: 0.999)
TRANSMITTANCE_THRESHOLD = 1e-4  # exclusive stop: next_T <= 1e-4
MIN_ONE_MINUS_ALPHA = 1e-6  # backward T recovery (compiled kernels)
EPS2D = 0.3  # low-pass dilation of the 2D covariance diagonal
GAUSSIAN_EXTEND = 3.33  # per-axis box: exp(-0.5 * 3.33**2) < 1/255
MIN_COMPENSATION = 0.005  # antialiasing only
FOV_MARGIN = 0.3  # Jacobian clamp: 0.3 * tan_fov beyond each image edge
DET_CLAMP = 1e-10  # inverse only; cull on det <= 0
QUAT_EPS = 1e-12
PRE_EXP_CULL_MARGIN = 1e-3  # skip when sigma > ln(255 * o) + 1e-3 (alpha < 1/255 sure)
NEAR = 0.01
FAR = 1e10
TILE_SIZES = (4, 8, 16, 32)
_MAX_RADIUS = 2**31 - 1  # int32 radii


@dataclass(frozen=True, eq=False)
class Gaussians:
    """3D Gaussians with activated parameters.

    Quaternions may have any norm: they are normalised inside (eps 1e-12), so a zero
    quaternion is the identity rotation.
    """

    means: Tensor  # [N, 3] world frame
    quats: Tensor  # [N, 4] wxyz
    scales: Tensor  # [N, 3] activated, >= 0
    opacities: Tensor  # [N] activated, in [0, 1]

    def __len__(self) -> int:
        return self.means.shape[0]

    def covariances(self) -> Tensor:
        """[N, 3, 3] world-frame covariances R·diag(s²)·Rᵀ (what splat viewers take)."""
        m = _quat_to_rotmat(self.quats) * self.scales[:, None, :]
        cov = m @ m.transpose(1, 2)
        return 0.5 * (cov + cov.transpose(1, 2))  # symmetric to the last bit

    def to(self, *args: Any, **kwargs: Any) -> Gaussians:
        """Return a copy with every tensor passed through `Tensor.to(*args, **kwargs)`."""
        return Gaussians(
            means=self.means.to(*args, **kwargs),
            quats=self.quats.to(*args, **kwargs),
            scales=self.scales.to(*args, **kwargs),
            opacities=self.opacities.to(*args, **kwargs),
        )


@dataclass(frozen=True, eq=False)
class Camera:
    """A pinhole camera: world-to-camera pose, intrinsics and image size in pixels."""

    cam_from_world: Tensor  # [4, 4]
    K: Tensor  # [3, 3]
    width: int
    height: int

    @classmethod
    def from_view(
        cls,
        view: Any,
        *,
        dtype: torch.dtype = torch.float32,
        device: torch.device | str | None = None,
    ) -> Camera:
        """Build a camera from an object with `.cam_from_world`, `.K`, `.width`, `.height`.

        Args:
            view: typically a `ptovs.scene.View` (numpy [4, 4] and [3, 3] arrays).
            dtype: tensor dtype (float32 by default).
            device: tensor device (CPU by default).

        Returns:
            The camera, with tensors of `dtype` on `device`.
        """
        return cls(
            cam_from_world=torch.tensor(
                np.array(view.cam_from_world), dtype=dtype, device=device
            ),
            K=torch.tensor(np.array(view.K), dtype=dtype, device=device),
            width=int(view.width),
            height=int(view.height),
        )

    def to(self, *args: Any, **kwargs: Any) -> Camera:
        """Return a copy with both tensors passed through `Tensor.to(*args, **kwargs)`."""
        return replace(
            self,
            cam_from_world=self.cam_from_world.to(*args, **kwargs),
            K=self.K.to(*args, **kwargs),
        )


@dataclass
class Projected:
    """Per-Gaussian screen-space splats. Culled Gaussians have radii (0, 0)."""

    means2d: Tensor  # [N, 2] pixel coordinates (x right, y down)
    conics: Tensor  # [N, 3] (a, b, c) of the inverse dilated 2D covariance
    opacities: Tensor  # [N] times the compensation when antialiasing
    depths: Tensor  # [N] camera-space z
    radii: Tensor  # [N, 2] int32 per-axis box half-sizes in pixels


@dataclass
class Isect:
    """Tile lists in CSR form, each sorted front to back by float32 depth, then id."""

    tile_offsets: Tensor  # [n_tiles + 1] int32; tile id = ty * tw + tx
    flatten_ids: Tensor  # [M] int32 Gaussian ids
    tw: int
    th: int
    tile: int

    @property
    def n_tiles(self) -> int:
        return self.tw * self.th


def _quat_to_rotmat(quats: Tensor) -> Tensor:
    """wxyz quaternions of any norm -> rotation matrices [N, 3, 3]."""
    # clamp under the square root: a zero quaternion gives R = I and zero gradients.
    q = quats * torch.rsqrt(quats.square().sum(-1, keepdim=True).clamp_min(QUAT_EPS**2))
    w, x, y, z = q.unbind(-1)
    rows = (
        1 - 2 * (y * y + z * z),
        2 * (x * y - w * z),
        2 * (x * z + w * y),
        2 * (x * y + w * z),
        1 - 2 * (x * x + z * z),
        2 * (y * z - w * x),
        2 * (x * z - w * y),
        2 * (y * z + w * x),
        1 - 2 * (x * x + y * y),
    )
    return torch.stack(rows, -1).reshape(-1, 3, 3)


def project(
    g: Gaussians,
    cam: Camera,
    *,
    near: float = NEAR,
    far: float = FAR,
    antialias: bool = False,
    tile: int = 16,
) -> Projected:
    """Differentiable EWA projection of Gaussians to splats (docs/rasterizer.md §1).

    The camera is cast to the Gaussians' dtype and device. Culled Gaussians (depth
    outside (near, far), det <= 0 or non-finite, box off the image) get radii (0, 0)
    and finite values everywhere; their gradients are exactly zero.

    Args:
        g: the Gaussians (N of them).
        cam: the camera.
        near: cull when z <= near.
        far: cull when z >= far.
        antialias: multiply opacities by the Mip-Splatting compensation.
        tile: accepted for a uniform backend signature; the radius rule ignores it.

    Returns:
        Projected splats: means2d [N, 2], conics [N, 3], opacities [N], depths [N],
        radii [N, 2] int32.
    """
    del tile
    p = _project(g, cam, near, far, antialias)
    with torch.no_grad():
        overflow = ~(
            torch.isfinite(p.means2d).all(-1)
            & torch.isfinite(p.conics).all(-1)
            & torch.isfinite(p.depths)
        )
    if not overflow.any():
        return p
    # Huge but finite inputs (scales ~1e19, means ~1e38) overflow float arithmetic.
    # Such Gaussians are culled, but inf intermediates would turn their zero upstream
    # gradients into NaN (0 * inf). Recompute with those rows replaced by constants.
    rows = overflow[:, None]
    safe = Gaussians(
        means=torch.where(rows, torch.zeros_like(g.means).detach(), g.means),
        quats=torch.where(rows, torch.ones_like(g.quats).detach(), g.quats),
        scales=torch.where(rows, torch.zeros_like(g.scales).detach(), g.scales),
        opacities=g.opacities,
    )
    p = _project(safe, cam, near, far, antialias)
    p.radii = torch.where(rows, 0, p.radii).to(torch.int32)
    return p


def _project(
    g: Gaussians, cam: Camera, near: float, far: float, antialias: bool
) -> Projected:
    dtype, device = g.means.dtype, g.means.device
    viewmat = cam.cam_from_world.to(dtype=dtype, device=device)
    K = cam.K.detach().to(torch.float64).cpu()
    fx, fy, cx, cy = (float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))
    width, height = cam.width, cam.height

    rot = _quat_to_rotmat(g.quats)  # [N, 3, 3]
    m = rot * g.scales[:, None, :]  # M = R diag(s)
    covar = m @ m.transpose(1, 2)  # [N, 3, 3]

    r_cw, t_cw = viewmat[:3, :3], viewmat[:3, 3]
    mean_c = g.means @ r_cw.T + t_cw  # [N, 3]
    cov_c = r_cw @ covar @ r_cw.T  # [N, 3, 3]
    x, y, z = mean_c.unbind(-1)

    in_depth = (z > near) & (z < far)
    # where before any division: culled depths never reach 1/z (forward or backward).
    zs = torch.where(in_depth, z, torch.ones_like(z))
    inv_z = 1.0 / zs

    # Clamped Jacobian (the 1.3x frustum guard); the 2D mean below uses the raw point.
    tan_fovx, tan_fovy = 0.5 * width / fx, 0.5 * height / fy
    lim_xp = (width - cx) / fx + FOV_MARGIN * tan_fovx
    lim_xn = cx / fx + FOV_MARGIN * tan_fovx
    lim_yp = (height - cy) / fy + FOV_MARGIN * tan_fovy
    lim_yn = cy / fy + FOV_MARGIN * tan_fovy
    tx = zs * torch.clamp(x * inv_z, -lim_xn, lim_xp)
    ty = zs * torch.clamp(y * inv_z, -lim_yn, lim_yp)
    zero = torch.zeros_like(zs)
    jac = torch.stack(
        (
            fx * inv_z,
            zero,
            -fx * tx * inv_z * inv_z,
            zero,
            fy * inv_z,
            -fy * ty * inv_z * inv_z,
        ),
        -1,
    ).reshape(-1, 2, 3)
    cov2d = jac @ cov_c @ jac.transpose(1, 2)  # [N, 2, 2]

    c00, c01, c11 = cov2d[:, 0, 0], cov2d[:, 0, 1], cov2d[:, 1, 1]
    det_orig = c00 * c11 - c01 * c01
    c00 = c00 + EPS2D  # low-pass dilation: every splat is >= ~1 px wide
    c11 = c11 + EPS2D
    det = c00 * c11 - c01 * c01
    valid = in_depth & (det > 0) & torch.isfinite(det)  # NaN det fails det > 0
    det_safe = torch.where(valid, det, torch.ones_like(det)).clamp_min(DET_CLAMP)
    inv_det = 1.0 / det_safe
    conics = torch.stack((c11 * inv_det, -c01 * inv_det, c00 * inv_det), -1)

    opacities = g.opacities
    if antialias:
        ratio = torch.where(valid, det_orig, torch.ones_like(det_orig)) * inv_det
        opacities = opacities * torch.sqrt(ratio.clamp_min(MIN_COMPENSATION**2))

    u = fx * x * inv_z + cx
    v = fy * y * inv_z + cy
    means2d = torch.stack((u, v), -1)

    with torch.no_grad():
        ext = GAUSSIAN_EXTEND * torch.sqrt(torch.stack((c00, c11), -1).clamp_min(0))
        radii = torch.ceil(ext.to(torch.float64)).nan_to_num(0.0).clamp(0, _MAX_RADIUS)
        u64, v64 = u.to(torch.float64), v.to(torch.float64)
        inside = (
            (u64 + radii[:, 0] > 0)
            & (u64 - radii[:, 0] < width)
            & (v64 + radii[:, 1] > 0)
            & (v64 - radii[:, 1] < height)
        )
        keep = valid & inside & (radii > 0).all(-1)
        radii = torch.where(keep[:, None], radii, 0.0).to(torch.int32)

    return Projected(
        means2d=means2d, conics=conics, opacities=opacities, depths=z, radii=radii
    )


def _depth_sort_key(depths: Tensor) -> Tensor:
    """float32 depths -> int64 keys in [0, 2**32) with the same order (any sign)."""
    bits = depths.to(torch.float32).contiguous().view(torch.int32).to(torch.int64)
    magnitude = bits & 0x7FFFFFFF
    return torch.where(bits >= 0, bits + 2**31, 2**31 - 1 - magnitude)


@torch.no_grad()
def intersect(p: Projected, width: int, height: int, tile: int) -> Isect:
    """Bin splats into tiles (docs/rasterizer.md §2), fully vectorised, no gradients.

    A Gaussian covers tiles [floor((u - r_x) / tile), ceil((u + r_x) / tile)) clamped
    to the grid (the same in y). Within a tile, ids are sorted by float32 depth, ties
    by Gaussian id.

    Args:
        p: projected splats; radii (0, 0) are skipped.
        width: image width in pixels.
        height: image height in pixels.
        tile: tile edge in pixels.

    Returns:
        The tile lists: `tile_offsets` [n_tiles + 1] int32 and `flatten_ids` [M] int32.
    """
    device = p.means2d.device
    tw, th = math.ceil(width / tile), math.ceil(height / tile)
    n_tiles = tw * th
    n = p.means2d.shape[0]
    means = p.means2d.detach().to(torch.float64)
    radii = p.radii.to(torch.float64)
    valid = (p.radii > 0).all(-1)

    x0 = torch.floor((means[:, 0] - radii[:, 0]) / tile).clamp(0, tw).to(torch.int64)
    x1 = torch.ceil((means[:, 0] + radii[:, 0]) / tile).clamp(0, tw).to(torch.int64)
    y0 = torch.floor((means[:, 1] - radii[:, 1]) / tile).clamp(0, th).to(torch.int64)
    y1 = torch.ceil((means[:, 1] + radii[:, 1]) / tile).clamp(0, th).to(torch.int64)
    span_x = (x1 - x0).clamp_min(0)
    count = torch.where(valid, span_x * (y1 - y0).clamp_min(0), 0)  # [N]

    gid = torch.repeat_interleave(torch.arange(n, device=device), count)  # [M]
    first = torch.cumsum(count, 0) - count
    k = torch.arange(gid.shape[0], device=device) - first[gid]
    span = span_x[gid]
    tile_id = (y0[gid] + k // span) * tw + x0[gid] + k % span

    key = (tile_id << 32) | _depth_sort_key(p.depths.detach())[gid]
    # gid ascends in generation order, so a stable sort breaks depth ties by id.
    order = torch.sort(key, stable=True).indices
    flatten_ids = gid[order].to(torch.int32)
    counts = torch.bincount(tile_id, minlength=n_tiles)
    tile_offsets = torch.zeros(n_tiles + 1, dtype=torch.int64, device=device)
    tile_offsets[1:] = torch.cumsum(counts, 0)
    return Isect(
        tile_offsets=tile_offsets.to(torch.int32),
        flatten_ids=flatten_ids,
        tw=tw,
        th=th,
        tile=tile,
    )


def sparse_csr(
    crow: Tensor, cols: Tensor, values: Tensor, shape: tuple[int, int]
) -> Tensor:
    """A sparse CSR matrix without invariant checks (and without torch's beta warning).

    Column indices need not be sorted within a row: torch's CSR @ dense kernels only
    sum products, and ptovs relies on that for rows kept in depth order.
    """
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Sparse CSR tensor support")
        return torch.sparse_csr_tensor(
            crow, cols, values, size=shape, check_invariants=False
        )

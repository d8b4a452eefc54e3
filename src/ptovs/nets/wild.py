"""The in-the-wild appearance networks of WE-GS as the paper uses them.

Layers, sizes and the paper's and authors' choices: docs/method.md §2.

- f_α `AppearanceEncoder`: image (+ transient mask) -> appearance embedding l ∈ R^32.
- f_β `TransientNet`: image -> transient mask M in [0, 1] (U-Lite-style axial U-Net).
- f_γ `ColorNet`: per Gaussian (flattened SH, PE(μ), l) -> ΔSH, tanh-bounded.
  `delta_scale` multiplies the tanh: the authors' 1 bounds the DC colour change
  at ±C0 = ±0.28, too little to turn a sunlit façade into a night photo; ptovs
  trains with a larger bound by default (stage option `delta_sh_scale`).
- or, with `appearance="affine"`, `AffineColorNet`: per Gaussian (learned
  embedding g, l, base colour) -> a per-channel affine colour map (WildGaussians'
  form), written as the ΔSH it equals.
- or, with `appearance="shading"`, `ShadingColorNet`: a per-channel gain
  exp(A(l) + g·B(l)), bilinear in the per-Gaussian embedding g and the image's l
  (low-rank shading: sun direction and strength against each surface), also
  written as the ΔSH it equals.

Two presets with the same structure: `authors` (exactly the released layer sizes:
256² inputs, widths 128…512, FC256; needed to import their checkpoints) and `cpu`
(64² inputs and narrower layers, about 100× fewer FLOPs per step; see
docs/findings.md for what it loses at equal iterations). The sky head
(`SkyNet`, `WildNets.background`) is ours: the authors render on black, which leaves
the sky to floaters; with an imported model it is absent and the background is black.

`learned=False` is the colour rung between plain 3DGS and the full model: no f_α,
f_β or f_γ; a photo's embedding is its fixed colour statistics alone, and it drives
the sky head and the photo-wide colour map. It models exposure, tint and sky, not
occluders or light that changes across a surface, at about a plain field's cost.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor, nn
from torch.nn import functional as F  # noqa: N812

from ptovs.raster import SH_C0
from ptovs.scene.images import resize_photo

APPEARANCES = ("delta-sh", "affine", "shading")
GAUSS_DIM = 16  # per-Gaussian embedding of the affine and shading appearances
SKY_STRIDE = 4  # the colour rung evaluates its sky once per 4 × 4 pixels


@dataclass(frozen=True)
class NetPreset:
    """Layer sizes of the three networks."""

    alpha_res: int  # f_α input side (images are resized to a square)
    alpha_widths: tuple[int, ...]  # stem, then one per stride-2 block
    beta_res: int  # f_β input side (a multiple of 2**(len(beta_widths) - 1))
    beta_widths: tuple[int, ...]  # stem, then one per encoder block
    gamma_width: int
    gamma_head: int
    embed_dim: int = 32
    pe_octaves: int = 4


PRESETS: dict[str, NetPreset] = {
    "authors": NetPreset(
        alpha_res=256,
        alpha_widths=(128, 256, 512, 512, 512),
        beta_res=256,
        beta_widths=(16, 32, 64, 128, 256, 512),
        gamma_width=256,
        gamma_head=128,
    ),
    "cpu": NetPreset(
        alpha_res=64,
        alpha_widths=(16, 32, 64, 64, 64),
        beta_res=64,
        beta_widths=(8, 16, 32, 32, 64, 64),
        gamma_width=32,
        gamma_head=32,
    ),
}


def linear_of_concat(
    layer: nn.Linear, parts: tuple[Tensor, ...], shared: Tensor | None = None
) -> Tensor:
    """`layer(cat(parts + (shared repeated on every row,), 1))` without the cat.

    The weight is applied block by block, and the shared row's product (an image
    embedding, the same for every Gaussian or pixel) is computed once and folded
    into the bias: the same function and parameters as the concatenation, about
    a third fewer multiply-adds and no [n, width] copies.
    """
    w = layer.weight
    k = sum(p.shape[1] for p in parts)
    if k + (0 if shared is None else shared.numel()) != w.shape[1]:
        raise ValueError(f"inputs of width {k} (+ shared) do not fit {layer}")
    bias = layer.bias
    if shared is not None:
        bias = bias + w[:, k:] @ shared.reshape(-1)
    out, o = bias, 0
    for p in parts:
        out = torch.addmm(out, p, w[:, o : o + p.shape[1]].T)
        o += p.shape[1]
    return out


def positional_encoding(x: Tensor, octaves: int) -> Tensor:
    """[x, sin(2^k x), cos(2^k x) for k < octaves] -> [n, 3 + 6 * octaves]."""
    out = [x]
    for k in range(octaves):
        out += [torch.sin(x * 2.0**k), torch.cos(x * 2.0**k)]
    return torch.cat(out, -1)


class AppearanceEncoder(nn.Module):
    """f_α: ReflPad3 + Conv7 + ReLU, stride-2 Conv4 blocks, pooling, Conv1x1 -> l."""

    def __init__(self, widths: tuple[int, ...], embed_dim: int, mask_concat: str):
        super().__init__()
        if mask_concat not in ("features", "input"):
            raise ValueError(f"mask_concat must be features or input: {mask_concat!r}")
        self.mask_concat = mask_concat
        c_in = 4 if mask_concat == "input" else 3
        layers: list[nn.Module] = [
            nn.ReflectionPad2d(3),
            nn.Conv2d(c_in, widths[0], 7),
            nn.ReLU(inplace=True),
        ]
        for a, b in zip(widths[:-1], widths[1:], strict=True):
            layers += [nn.ReflectionPad2d(1), nn.Conv2d(a, b, 4, 2), nn.ReLU(True)]
        self.features = nn.Sequential(*layers)
        extra = 1 if mask_concat == "features" else 0
        self.head = nn.Conv2d(widths[-1] + extra, embed_dim, 1)

    def forward(self, image: Tensor, mask: Tensor) -> Tensor:
        """image [B, 3, S, S], mask [B, 1, s, s] (any s) -> l [B, embed_dim]."""
        if self.mask_concat == "input":
            m = F.interpolate(mask, size=image.shape[-2:], mode="bilinear")
            feat = self.features(torch.cat((image, m), 1))
        else:  # the paper's reading: concatenate with the CNN's last feature map
            feat = self.features(image)
            m = F.adaptive_avg_pool2d(mask, feat.shape[-2:])
            feat = torch.cat((feat, m), 1)
        return self.head(F.adaptive_avg_pool2d(feat, 1)).flatten(1)


class _AxialDW(nn.Module):
    """x + depthwise (k x 1) + depthwise (1 x k), optionally dilated."""

    def __init__(self, c: int, k: int, dilation: int = 1):
        super().__init__()
        pad = dilation * (k - 1) // 2
        self.dw_h = nn.Conv2d(
            c, c, (k, 1), padding=(pad, 0), groups=c, dilation=dilation
        )
        self.dw_w = nn.Conv2d(
            c, c, (1, k), padding=(0, pad), groups=c, dilation=dilation
        )

    def forward(self, x: Tensor) -> Tensor:
        return x + self.dw_h(x) + self.dw_w(x)


class _Down(nn.Module):
    def __init__(self, c_in: int, c_out: int):
        super().__init__()
        self.dw = _AxialDW(c_in, 7)
        self.bn = nn.BatchNorm2d(c_in)
        self.pw = nn.Conv2d(c_in, c_out, 1)

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor]:
        skip = self.bn(self.dw(x))
        return F.gelu(F.max_pool2d(self.pw(skip), 2)), skip


class _Bottleneck(nn.Module):
    def __init__(self, c: int):
        super().__init__()
        g = max(1, c // 4)
        self.pw1 = nn.Conv2d(c, g, 1)
        self.dws = nn.ModuleList(_AxialDW(g, 3, d) for d in (1, 2, 3))
        self.bn = nn.BatchNorm2d(4 * g)
        self.pw2 = nn.Conv2d(4 * g, c, 1)

    def forward(self, x: Tensor) -> Tensor:
        x = self.pw1(x)
        x = torch.cat([x] + [dw(x) for dw in self.dws], 1)
        return F.gelu(self.pw2(self.bn(x)))


class _Up(nn.Module):
    def __init__(self, c_in: int, c_out: int):
        super().__init__()
        self.pw = nn.Conv2d(c_in + c_out, c_out, 1)
        self.bn = nn.BatchNorm2d(c_out)
        self.dw = _AxialDW(c_out, 7)
        self.pw2 = nn.Conv2d(c_out, c_out, 1)

    def forward(self, x: Tensor, skip: Tensor) -> Tensor:
        x = F.interpolate(x, size=skip.shape[-2:], mode="nearest")
        x = self.pw(torch.cat((x, skip), 1))
        return F.gelu(self.pw2(self.dw(self.bn(x))))


class TransientNet(nn.Module):
    """f_β: a U-Lite-style U-Net (axial depthwise blocks) -> M in [0, 1], 1 = transient."""

    def __init__(self, widths: tuple[int, ...]):
        super().__init__()
        self.stem = nn.Conv2d(3, widths[0], 7, padding=3)
        pairs = list(zip(widths[:-1], widths[1:], strict=True))
        self.down = nn.ModuleList(_Down(a, b) for a, b in pairs)
        self.mid = _Bottleneck(widths[-1])
        self.up = nn.ModuleList(_Up(b, a) for a, b in reversed(pairs))
        self.out = nn.Conv2d(widths[0], 1, 1)

    def forward(self, image: Tensor) -> Tensor:
        """image [B, 3, S, S] -> M [B, 1, S, S]."""
        x = self.stem(image)
        skips = []
        for block in self.down:
            x, skip = block(x)
            skips.append(skip)
        x = self.mid(x)
        for block, skip in zip(self.up, reversed(skips), strict=True):
            x = block(x, skip)
        return torch.sigmoid(self.out(x))


class ColorNet(nn.Module):
    """f_γ: (SH, PE(μ), l) -> ΔSH via 3 FC, concat input, 3 FC, concat SH, FC, FC, tanh."""

    def __init__(
        self,
        n_coeffs: int,
        preset: NetPreset,
        delta_scale: float = 1.0,
        embed_dim: int | None = None,
    ):
        super().__init__()
        self.n_coeffs = n_coeffs
        self.delta_scale = float(delta_scale)
        self.octaves = preset.pe_octaves
        sh = 3 * n_coeffs
        d = preset.embed_dim if embed_dim is None else embed_dim
        inp = sh + 3 + 6 * preset.pe_octaves + d
        w, head = preset.gamma_width, preset.gamma_head
        self.block1 = nn.ModuleList(
            [nn.Linear(inp, w), nn.Linear(w, w), nn.Linear(w, w)]
        )
        self.block2 = nn.ModuleList(
            [nn.Linear(w + inp, w), nn.Linear(w, w), nn.Linear(w, w)]
        )
        self.head = nn.Linear(w + sh, head)
        self.out = nn.Linear(head, sh)

    def forward(self, sh: Tensor, means: Tensor, embedding: Tensor) -> Tensor:
        """sh [n, K, 3], means [n, 3], embedding [D] -> ΔSH [n, K, 3] in (-1, 1)."""
        n = sh.shape[0]
        flat = sh.reshape(n, -1)
        pe = positional_encoding(means, self.octaves)
        # the input x0 = (SH, PE(μ), l) enters block1 and block2; l is the same
        # for every Gaussian, so it is folded into those layers' biases
        x = F.relu(linear_of_concat(self.block1[0], (flat, pe), embedding))
        for layer in self.block1[1:]:
            x = F.relu(layer(x))
        x = F.relu(linear_of_concat(self.block2[0], (x, flat, pe), embedding))
        for layer in self.block2[1:]:
            x = F.relu(layer(x))
        x = F.relu(linear_of_concat(self.head, (x, flat)))
        delta = torch.tanh(self.out(x)) * self.delta_scale
        return delta.reshape(n, self.n_coeffs, 3)


N_STATS = 8


def image_stats(image: Tensor) -> Tensor:
    """[B, 3, S, S] in [0, 1] -> [B, 8] fixed colour statistics, about unit scale:
    mean RGB, spread RGB, chroma (0 for black-and-white) and the top third's
    brightness (the sky). Appended to the learned embedding (`image_stats`), they
    tell f_γ, the sky and the colour map the photo's exposure, tint and filter
    from the first step, before f_α has learned anything."""
    mean = image.mean((2, 3))
    spread = image.std((2, 3))
    chroma = (image.max(1).values - image.min(1).values).mean((1, 2))
    top = image[:, :, : max(1, image.shape[2] // 3)].mean((1, 2, 3))
    return torch.cat(
        (2 * mean - 1, 4 * spread, 4 * chroma[:, None], 2 * top[:, None] - 1), 1
    )


class AffineColorNet(nn.Module):
    """Appearance as a per-channel affine colour map (after WildGaussians).

    Per Gaussian k: (a_k, b_k) = MLP(g_k, l, c̄_k) with g_k a learned per-Gaussian
    embedding, l the image's embedding and c̄_k the Gaussian's base (DC) colour;
    the colour under l is (1 + a_k)·c_k + b_k. Exposure, tint and white balance
    are one shared multiplication, which ΔSH must learn colour by colour; g_k lets
    shading (sun direction) vary over the surface. The last layer starts at zero:
    identity at the start. As ΔSH of the same map: a·SH, plus (a/2 + b)/C0 on the
    DC term (colour = SH·basis + 1/2), so it bakes exactly into a PLY.
    """

    def __init__(self, embed_dim: int, gauss_dim: int, width: int):
        super().__init__()
        self.fc1 = nn.Linear(gauss_dim + embed_dim + 3, width)
        self.fc2 = nn.Linear(width, width)
        self.out = nn.Linear(width, 6)

    def forward(
        self, sh: Tensor, means: Tensor, embedding: Tensor, gauss: Tensor
    ) -> Tensor:
        """sh [n, K, 3], gauss [n, G], embedding [D] -> ΔSH [n, K, 3]."""
        n = sh.shape[0]
        base = sh[:, 0] * SH_C0 + 0.5
        x = torch.cat((gauss, embedding.reshape(1, -1).expand(n, -1), base), 1)
        x = self.out(F.relu(self.fc2(F.relu(self.fc1(x)))))
        return gain_as_delta_sh(sh, 1.0 + x[:, :3], x[:, 3:])


def gain_as_delta_sh(sh: Tensor, gain: Tensor, offset: Tensor | None = None) -> Tensor:
    """ΔSH [n, K, 3] whose colour is gain·colour + offset (gain, offset [n, 3]).

    colour = SH·basis + 1/2, so gain·colour + offset = (gain·SH)·basis + 1/2 +
    ((gain − 1)/2 + offset): every coefficient times (gain − 1), and the constant
    through the DC basis value C0. Exact after `eval_sh`, so it bakes into a PLY.
    """
    a = gain - 1.0
    dc_shift = 0.5 * a if offset is None else 0.5 * a + offset
    delta = sh * a[:, None, :]
    return torch.cat((delta[:, :1] + (dc_shift / SH_C0)[:, None], delta[:, 1:]), 1)


class ShadingColorNet(nn.Module):
    """Appearance as low-rank shading: colour_k(l) = exp(u_k(l)) · colour_k.

    u_k(l) = A(l) + g_k·B(l) per channel, with A [3] and B [G, 3] one linear map
    of the image's embedding l and g_k [G] a learned per-Gaussian embedding. A is
    the photo's exposure and tint; g_k·B is how surface k answers this photo's
    light (a Lambertian surface under a sun and sky is, to a few per cent, linear
    in 9 lighting coefficients; G = 16 leaves room). No per-Gaussian MLP: one
    [n, G] × [G, 3] product a view, against f_γ's six layers. The log-gain is
    bounded (±`bound`, tanh) and starts at 0: identity at the start. `scale`
    multiplies the map's output so that its steps at f_γ's learning rate move
    colours as ΔSH's do.
    """

    def __init__(
        self, embed_dim: int, gauss_dim: int, scale: float = 4.0, bound: float = 4.0
    ):
        super().__init__()
        self.gauss_dim = gauss_dim
        self.scale = float(scale)
        self.bound = float(bound)
        self.out = nn.Linear(embed_dim, 3 * (1 + gauss_dim))

    def log_gain(self, embedding: Tensor, gauss: Tensor) -> Tensor:
        """[n, 3] log-gain of n Gaussians (embeddings [n, G]) under l [D]."""
        h = self.out(embedding.reshape(-1)) * self.scale
        u = torch.addmm(h[:3], gauss, h[3:].reshape(self.gauss_dim, 3))
        return torch.tanh(u / self.bound) * self.bound

    def forward(
        self, sh: Tensor, means: Tensor, embedding: Tensor, gauss: Tensor
    ) -> Tensor:
        """sh [n, K, 3], gauss [n, G], embedding [D] -> ΔSH [n, K, 3]."""
        return gain_as_delta_sh(sh, torch.exp(self.log_gain(embedding, gauss)))


class SkyNet(nn.Module):
    """Sky colour per pixel from the ray direction and the embedding (ours).

    Photos of a landmark are mostly sky and ground around it; the sky changes with
    every photo and is not a surface, so Gaussians model it badly (floaters). A
    small MLP on (PE(direction), l) paints what the Gaussians leave transparent:
    image = render + T_final · sky.
    """

    def __init__(self, embed_dim: int, width: int = 32, octaves: int = 2):
        super().__init__()
        self.octaves = octaves
        self.fc1 = nn.Linear(3 + 6 * octaves + embed_dim, width)
        self.fc2 = nn.Linear(width, 3)

    def forward(self, dirs: Tensor, embedding: Tensor) -> Tensor:
        """dirs [..., 3] unit, embedding [D] -> RGB [..., 3] in (0, 1)."""
        shape = dirs.shape[:-1]
        d = dirs.reshape(-1, 3)
        x = linear_of_concat(
            self.fc1, (positional_encoding(d, self.octaves),), embedding
        )
        return torch.sigmoid(self.fc2(F.relu(x))).reshape(*shape, 3)


class WildNets(nn.Module):
    """f_α, f_β, f_γ and the background head, with their image preprocessing."""

    def __init__(
        self,
        preset: str | NetPreset,
        n_coeffs: int,
        *,
        mask_concat: str = "features",
        background: bool = True,
        delta_scale: float = 1.0,
        appearance: str = "delta-sh",
        color_map: bool = False,
        stats: bool = False,
        learned: bool = True,
        sky_stride: int = 0,
    ):
        super().__init__()
        if sky_stride < 0:
            raise ValueError(
                f"sky_stride must be 0 (the model's own) or more: {sky_stride}"
            )
        self.preset = PRESETS[preset] if isinstance(preset, str) else preset
        p = self.preset
        if p.beta_res % 2 ** (len(p.beta_widths) - 1):
            raise ValueError("beta_res must be divisible by 2**(len(beta_widths) - 1)")
        if appearance not in APPEARANCES:
            raise ValueError(f"appearance must be one of {APPEARANCES}: {appearance!r}")
        self.learned = bool(learned)
        self.appearance = appearance
        # the colour rung: the statistics are the whole embedding, the map its use
        self.stats = bool(stats) or not self.learned
        color_map = bool(color_map) or not self.learned
        self.f_alpha: AppearanceEncoder | None = None
        self.f_beta: TransientNet | None = None
        self.f_gamma: nn.Module | None = None
        d = (p.embed_dim if self.learned else 0) + (N_STATS if self.stats else 0)
        if self.learned:
            self.f_alpha = AppearanceEncoder(p.alpha_widths, p.embed_dim, mask_concat)
            self.f_beta = TransientNet(p.beta_widths)
            if appearance == "affine":
                self.f_gamma = AffineColorNet(d, GAUSS_DIM, 2 * p.gamma_width)
            elif appearance == "shading":
                self.f_gamma = ShadingColorNet(d, GAUSS_DIM, delta_scale)
            else:
                self.f_gamma = ColorNet(n_coeffs, p, delta_scale, d)
            nn.init.zeros_(self.f_gamma.out.weight)  # ΔSH = 0 at the start
            nn.init.zeros_(self.f_gamma.out.bias)
        self.sky = SkyNet(d) if background else None
        # the sky once per `sky_stride` × `sky_stride` pixels, bilinear between: a
        # smooth function of the direction; per pixel it costs the colour rung as
        # much as f_α and f_β, and the learned model 14 % of its step (bench).
        # 0: the model's own, per pixel for the learned model, SKY_STRIDE for the rung
        self.sky_stride = int(sky_stride) or (1 if self.learned else SKY_STRIDE)
        self.f_map = nn.Linear(d, 12) if color_map else None
        if self.f_map is not None:  # the identity map at the start
            nn.init.zeros_(self.f_map.weight)
            nn.init.zeros_(self.f_map.bias)

    @property
    def embed_dim(self) -> int:
        """Length of an image's embedding (learned part + fixed statistics)."""
        return (self.preset.embed_dim if self.learned else 0) + (
            N_STATS if self.stats else 0
        )

    def prepare(self, image: np.ndarray) -> tuple[Tensor, Tensor]:
        """RGB [H, W, 3] in [0, 1] -> (f_α input [3, S, S], f_β input [3, s, s])."""
        out = []
        for res in (self.preset.alpha_res, self.preset.beta_res):
            small = resize_photo(image, (res, res))  # in [0, 1] at any factor
            out.append(torch.from_numpy(np.ascontiguousarray(small)).permute(2, 0, 1))
        return out[0].float(), out[1].float()

    def transient(self, beta_in: Tensor) -> Tensor | None:
        """[B, 3, s, s] -> M [B, 1, s, s] (None for the colour rung: no f_β)."""
        return None if self.f_beta is None else self.f_beta(beta_in)

    def embed(self, alpha_in: Tensor, mask: Tensor | None) -> Tensor:
        """[B, 3, S, S] and M [B, 1, s, s] -> l [B, D] (f_α, then the statistics)."""
        if self.f_alpha is None:
            return image_stats(alpha_in)
        learned = self.f_alpha(alpha_in, mask)
        if not self.stats:
            return learned
        return torch.cat((learned, image_stats(alpha_in)), 1)

    def background(self, dirs: Tensor, embedding: Tensor) -> Tensor:
        """Ray directions [H, W, 3] and l [D] -> RGB background [H, W, 3].

        Black without the sky head (imported models: the authors render on black).
        """
        if self.sky is None:
            return dirs.new_zeros(dirs.shape)
        s = self.sky_stride
        if s == 1 or dirs.ndim != 3 or min(dirs.shape[:2]) < 2 * s:
            return self.sky(dirs, embedding)
        # mean direction of each s × s block, the sky there, bilinear back up
        grid = dirs.permute(2, 0, 1)[None]
        small = F.normalize(F.avg_pool2d(grid, s, ceil_mode=True), dim=1)
        sky = self.sky(small[0].permute(1, 2, 0), embedding).permute(2, 0, 1)[None]
        full = F.interpolate(sky, size=dirs.shape[:2], mode="bilinear")
        return full[0].permute(1, 2, 0)

    def color_matrix(self, embedding: Tensor) -> tuple[Tensor, Tensor] | None:
        """The image's colour map (M [3, 3], t [3]): colour -> M·colour + t, or None.

        A linear map of every Gaussian's colour and of the sky is the same map
        of the rendered image (the blend weights and T sum to 1), so it applies
        to images after compositing and bakes exactly into SH. One 3×3 matrix
        holds exposure, tint and black-and-white or sepia filters.
        """
        if self.f_map is None:
            return None
        x = self.f_map(embedding.reshape(-1))
        eye = torch.eye(3, dtype=x.dtype, device=x.device)
        return eye + x[:9].reshape(3, 3), x[9:]

    def map_colors(self, rgb: Tensor, embedding: Tensor) -> Tensor:
        """[..., 3] colours through the image's colour map (unchanged without one)."""
        mt = self.color_matrix(embedding)
        if mt is None:
            return rgb
        m, t = mt
        return rgb @ m.T + t

    def map_parameters(self) -> list[nn.Parameter]:
        """The colour map's parameters (none without one)."""
        return [] if self.f_map is None else list(self.f_map.parameters())

    @property
    def gauss_dim(self) -> int:
        """Width of the per-Gaussian embedding the appearance needs (0: none)."""
        if self.f_gamma is None:
            return 0
        return GAUSS_DIM if self.appearance in ("affine", "shading") else 0

    def delta_sh(
        self, sh: Tensor, means: Tensor, embedding: Tensor, gauss: Tensor | None = None
    ) -> Tensor:
        """ΔSH [n, K, 3] for n Gaussians under embedding [D]; `gauss` [n, G] are
        the per-Gaussian embeddings (needed by the affine and shading appearances);
        zeros for the colour rung (no f_γ)."""
        if self.f_gamma is None:
            return torch.zeros_like(sh)
        if self.gauss_dim:
            if gauss is None or gauss.shape != (sh.shape[0], GAUSS_DIM):
                raise ValueError(
                    f"the {self.appearance} appearance needs per-Gaussian embeddings "
                    f"[{sh.shape[0]}, {GAUSS_DIM}]"
                )
            return self.f_gamma(sh, means, embedding, gauss)
        return self.f_gamma(sh, means, embedding)

    @torch.no_grad()
    def embed_image(self, image: np.ndarray) -> tuple[Tensor, Tensor]:
        """(l [D], M [1, 1, s, s]) of one image, in eval mode."""
        was = self.training
        self.eval()
        a, b = self.prepare(image)
        mask = self.transient(b[None])
        emb = self.embed(a[None], mask)[0]
        self.train(was)
        return emb, mask

"""Text queries against rendered language codes (docs/method.md §8).

The chain for one view and one query, all of it here so that `query`, `select`
and the tests share it:

1. `PhraseDecoder`: rendered 3-d codes → cosine of the decoded CLIP feature with
   each phrase embedding. Exactly (the AE decoder per pixel) or through a table:
   the decoder is a fixed function of a 3-vector, so its cosine with each phrase
   is tabulated once per call on a grid over the ball ‖c‖ ≤ 1 and looked up by
   trilinear interpolation. Rendered codes are blends of unit codes and are not
   renormalised (§8, as the authors' code), so their norm lies in [0, 1]: the
   table spans the ball, not only the sphere.
2. `relevancy`: min over canonical phrases of exp(τa)/(exp(τa)+exp(τb)), written
   as sigmoid(τ(a − b)): no exponential of a large number is ever formed.
3. `background`: the paper's filter (sky and background against the query), the
   authors' code form (sky against the image's queries and itself) or off.
4. `fuse`: the post-ensemble over appearances (the paper's image-level max
   weighting by default, the Table 3 modes as options).
5. `finish`: mean-filter smoothing, level choice, threshold (relative rule by
   default; "stable" as an option), majority filter.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

CANONICAL = ("object", "things", "scene", "sky", "building")
"""The supplement's canonical phrases (docs/method.md §8)."""
BACKGROUND_PHRASES = ("sky", "background")
FUSIONS = ("weighted", "imglvlmax", "pixmax", "pixavg", "pixweighted")
BACKGROUND_FILTERS = ("paper", "code", "off")
DIV_EPS = 1e-9


# ----------------------------------------------------------------- decoding --


class PhraseDecoder:
    """Cosines of decoded codes with K phrase embeddings.

    Args:
        decode: [n, 3] codes → [n, D] unit features (the AE decoder).
        phrases: [K, D] unit phrase embeddings.
        mode: "exact" (decode every code) or "table" (trilinear lookup in a
            grid of `size`³ points over [-1, 1]³, decoded once).
        size: table points per axis.
        chunk: codes decoded at once on the exact path (bounds memory:
            chunk × D floats).
    """

    def __init__(
        self,
        decode,
        phrases: Tensor,
        mode: Literal["exact", "table"] = "table",
        size: int = 64,
        chunk: int = 65536,
    ) -> None:
        if mode not in ("exact", "table"):
            raise ValueError(f"decode mode must be exact or table, got {mode!r}")
        if size < 2:
            raise ValueError(f"table size must be >= 2, got {size}")
        self.decode = decode
        self.phrases = phrases.float()
        self.mode = mode
        self.size = int(size)
        self.chunk = int(chunk)
        self._table: Tensor | None = None

    @torch.no_grad()
    def exact(self, codes: Tensor, phrases: Tensor | None = None) -> Tensor:
        """[..., 3] → [..., K] cosines by decoding every code (with `phrases`
        [K, D] instead of this decoder's own, if given)."""
        phrases = self.phrases if phrases is None else phrases.float()
        lead = codes.shape[:-1]
        flat = codes.reshape(-1, codes.shape[-1]).float()
        out = torch.empty(len(flat), len(phrases))
        for a in range(0, len(flat), self.chunk):
            feats = self.decode(flat[a : a + self.chunk])
            out[a : a + self.chunk] = feats @ phrases.T
        return out.reshape(*lead, len(phrases))

    def _grid_table(self, phrases: Tensor) -> Tensor:
        axis = torch.linspace(-1.0, 1.0, self.size)
        grid = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), -1)
        return self.exact(grid, phrases).permute(3, 0, 1, 2).contiguous()

    @property
    def table(self) -> Tensor:
        """[K, G, G, G] cosines at grid point (c0, c1, c2) = table[:, i0, i1, i2]."""
        if self._table is None:
            self._table = self._grid_table(self.phrases)
        return self._table

    @torch.no_grad()
    def add_phrases(self, phrases: Tensor) -> None:
        """Append unit phrase embeddings [k, D]: existing indices keep their meaning,
        and a built table grows by the new phrases' cosines only (one decode of the
        grid, not K)."""
        phrases = phrases.float()
        if self._table is not None:
            self._table = torch.cat((self._table, self._grid_table(phrases)))
        self.phrases = torch.cat((self.phrases, phrases))

    def truncate(self, n: int) -> None:
        """Keep the first `n` phrases (and their table rows), forget the rest."""
        self.phrases = self.phrases[:n]
        if self._table is not None:
            self._table = self._table[:n]

    @torch.no_grad()
    def lookup(self, codes: Tensor, table: Tensor | None = None) -> Tensor:
        """[..., 3] → [..., C] by trilinear interpolation in a table.

        Args:
            codes: rendered codes; outside [-1, 1]³ (impossible for blends of
                unit codes) they are clamped to the cube.
            table: [C, G, G, G] values on this decoder's grid (default: the
                cosines with every phrase, C = K); e.g. a query's relevancy,
                tabulated once, so a pixel costs one C = 1 lookup.
        """
        table = self.table if table is None else table
        lead = codes.shape[:-1]
        flat = codes.reshape(-1, 3).float().clamp(-1.0, 1.0)
        n = len(flat)
        # grid_sample parallelises over the batch only: split the points into
        # 2 × threads batches against the same (expanded, not copied) table
        b = max(1, min(2 * torch.get_num_threads(), n // 4096))
        per = -(-n // b) if n else 0
        if per * b > n:
            flat = torch.cat([flat, flat.new_zeros(per * b - n, 3)])
        # grid_sample's last grid axis indexes the table's last dimension: (c2, c1, c0)
        grid = flat.flip(-1).reshape(b, 1, 1, per, 3)
        out = F.grid_sample(
            table[None].expand(b, -1, -1, -1, -1),
            grid,
            mode="bilinear",
            align_corners=True,
        )  # [b, C, 1, 1, per]
        out = out[:, :, 0, 0].permute(0, 2, 1).reshape(-1, len(table))[:n]
        return out.reshape(*lead, len(table))

    @property
    def grid_cosines(self) -> Tensor:
        """[G, G, G, K]: the table with phrases last (for functions of one pixel)."""
        return self.table.permute(1, 2, 3, 0)

    def __call__(self, codes: Tensor) -> Tensor:
        return self.lookup(codes) if self.mode == "table" else self.exact(codes)


# ---------------------------------------------------------------- relevancy --


def relevancy(pos: Tensor, neg: Tensor, temperature: float = 10.0) -> Tensor:
    """min_j exp(τ·pos)/(exp(τ·pos) + exp(τ·neg_j)), finite for any input.

    Args:
        pos: [...] cosines with the query.
        neg: [..., C] cosines with each canonical phrase (C >= 1).
        temperature: τ (10 in LERF, LangSplat and the authors' code).

    Returns:
        [...] in [0, 1]. Written as sigmoid(τ(pos − neg)); NaN inputs count as a
        tie (0.5), infinities saturate.
    """
    if neg.shape[-1] == 0:
        raise ValueError("relevancy needs at least one canonical phrase")
    d = torch.nan_to_num(pos.unsqueeze(-1) - neg, nan=0.0, posinf=1e4, neginf=-1e4)
    return torch.sigmoid(float(temperature) * d.clamp(-1e4, 1e4)).amin(-1)


def background_per_map(
    cos: Tensor,
    query: int,
    bg: list[int],
    mode: str,
    temperature: float = 10.0,
    image_queries: list[int] | None = None,
) -> Tensor | None:
    """The background probability of each map's pixel, before the max over maps.

    A function of one pixel's cosines only (so it can be tabulated). "paper": the
    max over p ∈ bg (sky, background) of p's relevancy against {query}; "code":
    sky's relevancy against the image's queries and sky itself (≤ 0.5); "off": None.
    """
    if mode == "off":
        return None
    if mode == "paper":
        pos = cos[..., bg]  # [..., P]
        neg = cos[..., query][..., None].expand_as(pos)[..., None]
        return relevancy(pos, neg, temperature).amax(-1)
    if mode == "code":
        sky = bg[0]
        negs = list(dict.fromkeys([*(image_queries or [query]), sky]))
        return relevancy(cos[..., sky], cos[..., negs], temperature)
    raise ValueError(f"background filter must be one of {BACKGROUND_FILTERS}")


def reduce_background(b: Tensor | None, mode: str) -> Tensor | None:
    """[L, N, H, W] per-map background → paper: max over appearances [L, H, W];
    code: max over every map [1, H, W]."""
    if b is None:
        return None
    return b.amax(1) if mode == "paper" else b.amax(dim=(0, 1))[None]


def background(
    cos: Tensor,
    query: int,
    bg: list[int],
    mode: str,
    temperature: float = 10.0,
    image_queries: list[int] | None = None,
) -> Tensor | None:
    """The background probability b (score_B = 1 − b), or None when off.

    Args:
        cos: [L, N, H, W, K] cosines (levels, appearances, pixels, phrases).
        query: phrase index of the query.
        bg: phrase indices of "sky" and "background" (paper) or of "sky" (code).
        mode: "paper": b_ℓ(x) = max over appearances and p ∈ bg of p's
            relevancy against {query}, per level → [L, H, W]. "code": the
            authors' `--sky_filter`: sky's relevancy against the image's
            queries and sky itself (so b ≤ 0.5), max over every level and
            appearance → [1, H, W]. "off": None.
        image_queries: the image's query phrase indices (code form).
    """
    per_map = background_per_map(cos, query, bg, mode, temperature, image_queries)
    return reduce_background(per_map, mode)


def fuse(scores: Tensor, mode: str = "weighted") -> Tensor:
    """Post-ensemble over appearances: [L, N, H, W] → [L, H, W].

    Modes (docs/method.md §8): "weighted" (the paper's: w_i = max_x s_i / Σ_j
    max_x s_j, then Σ_i w_i s_i), "imglvlmax" (per level the appearance map with
    the largest max; the level choice then picks among all N × L maps),
    "pixmax", "pixavg", "pixweighted" (w_i(x) ∝ 1/((s_i − mean_i s_i)² + 1e-6)).
    With N = 1 every mode returns the single map.
    """
    if mode == "weighted":
        peak = scores.amax(dim=(2, 3), keepdim=True)  # [L, N, 1, 1]
        total = peak.sum(1, keepdim=True)
        n = scores.shape[1]
        w = torch.where(total > 0, peak / total.clamp_min(DIV_EPS), 1.0 / n)
        return (w * scores).sum(1)
    if mode == "imglvlmax":
        best = scores.amax(dim=(2, 3)).argmax(1)  # [L]
        return scores[torch.arange(len(scores)), best]
    if mode == "pixmax":
        return scores.amax(1)
    if mode == "pixavg":
        return scores.mean(1)
    if mode == "pixweighted":
        w = 1.0 / ((scores - scores.mean(1, keepdim=True)) ** 2 + 1e-6)
        return (w * scores).sum(1) / w.sum(1)
    raise ValueError(f"fusion must be one of {FUSIONS}, got {mode!r}")


# ---------------------------------------------------------------- finishing --


def smooth(
    score: np.ndarray, kernel: int, damp: np.ndarray | None = None
) -> np.ndarray:
    """Ŝ = 0.5·(Box_k ∗ S ⊙ (1 − damp) + S); box filter with reflect-101 border.

    `damp` is the code-form background b (None: no factor). kernel <= 1: Ŝ = S.
    """
    s = np.ascontiguousarray(score, np.float32)
    if kernel <= 1:
        return s.copy()
    box = cv2.blur(s, (int(kernel), int(kernel)), borderType=cv2.BORDER_REFLECT_101)
    if damp is not None:
        box = box * (1.0 - damp)
    return 0.5 * (box + s)


STABLE_WINDOW, STABLE_STEP, STABLE_H = 0.2, 0.02, 0.05  # "stable": cuts, step, h


def threshold(
    s: np.ndarray,
    tau: float = 0.4,
    mode: Literal["relative", "absolute", "stable"] = "relative",
    top: float | None = None,
) -> np.ndarray:
    """Mask of a smoothed map: relative (min-max rescale n, clip(2n − 1) > τ), Ŝ ≥ τ
    (absolute), or stable (the relative rule at `stable_cut`'s cut). `top` replaces
    the maximum in the rescale (a robust peak, `peak_of`); above it, n = 1."""
    if mode == "absolute":
        return s >= tau
    if mode not in ("relative", "stable"):
        raise ValueError(f"threshold mode: relative, absolute or stable, not {mode!r}")
    if not s.size:
        return np.zeros(s.shape, bool)
    lo = float(s.min())
    hi = float(s.max()) if top is None else max(float(top), lo)
    n = (s - lo) / (hi - lo + DIV_EPS)
    v = np.clip(2.0 * n - 1.0, 0.0, 1.0)
    return v > (stable_cut(v, tau) if mode == "stable" else tau)


def stable_cut(v: np.ndarray, tau: float) -> float:
    """The cut t within ± `STABLE_WINDOW` of τ where the area above it changes
    least (A(t − h) − A(t + h), pixels; the nearest to τ among equals, so an even
    ramp keeps τ): a plateau with steep sides, which nearby maps share, instead of
    a fixed cut through a gentle slope (maximally stable thresholds, as in MSER)."""
    x = np.sort(np.asarray(v, np.float64).reshape(-1))
    k = int(round(STABLE_WINDOW / STABLE_STEP))
    cuts = tau + STABLE_STEP * np.arange(-k, k + 1)
    cuts = cuts[(cuts >= 0.0) & (cuts < 1.0)]
    if cuts.size == 0:
        return float(tau)
    lo, hi = (np.searchsorted(x, cuts + d, side="right") for d in (-STABLE_H, STABLE_H))
    change = hi - lo  # pixels between the two cuts
    best = np.flatnonzero(change == change.min())
    return float(cuts[best[np.argmin(np.abs(cuts[best] - tau))]])


def peak_of(values: np.ndarray, quantile: float = 1.0) -> float:
    """A map's peak: its maximum (`quantile` ≥ 1, the paper's), else that quantile
    of its values (float64; 0 for an empty map). One pixel or Gaussian decides a
    maximum; a high quantile is a property of the map's top and moves less."""
    v = np.asarray(values).reshape(-1)
    if v.size == 0:
        return 0.0
    if quantile >= 1.0:
        return float(v.max())
    return float(np.quantile(v.astype(np.float64), max(0.0, quantile)))


def choose_level(peaks: np.ndarray, softness: float = 0.0) -> tuple[int, np.ndarray]:
    """(ℓ*, weights [L]): ℓ* = argmax of the peaks; the weights are one-hot at ℓ*
    (`softness` ≤ 0, the paper's choice) or softmax(peaks / softness): levels whose
    peaks nearly tie are blended, so a near-tie moves the answer a little."""
    p = np.asarray(peaks, np.float64)
    level = int(np.argmax(p))
    if softness <= 0 or len(p) < 2:
        w = np.zeros(len(p))
        w[level] = 1.0
        return level, w
    e = np.exp((p - p[level]) / softness)
    return level, e / e.sum()


def _chosen_map(
    maps: np.ndarray, peaks: np.ndarray, settings: QuerySettings
) -> tuple[int, np.ndarray, float | None]:
    """(ℓ*, the map the threshold cuts, its robust top or None for the maximum)
    from [L, ...] maps and their peaks under the settings' level rule."""
    level, w = choose_level(peaks, settings.level_softness)
    one = w[level] == 1.0
    m = maps[level] if one else np.tensordot(w, maps.astype(np.float64), 1)
    m = m.astype(np.float32, copy=False)
    if settings.peak_quantile >= 1.0:
        return level, m, None
    return level, m, float(peaks[level]) if one else peak_of(m, settings.peak_quantile)


def majority(mask: np.ndarray, size: int = 7, exact: bool = False) -> np.ndarray:
    """A pixel is on when more than half of its size×size window is on (ties off).

    The window is clipped at the image border. `exact` replicates the authors'
    `smooth()`: rows and columns [i − r, min(i + r + 1, n − 1)), so the last row
    and column are never counted.
    """
    if size <= 1 or mask.size == 0:
        return mask.copy()
    r = size // 2
    h, w = mask.shape
    ii = np.zeros((h + 1, w + 1), np.int64)
    ii[1:, 1:] = mask.astype(np.int64).cumsum(0).cumsum(1)
    cap_h, cap_w = (h - 1, w - 1) if exact else (h, w)
    y0 = np.clip(np.arange(h) - r, 0, None)
    y1 = np.minimum(np.arange(h) + r + 1, cap_h)
    x0 = np.clip(np.arange(w) - r, 0, None)
    x1 = np.minimum(np.arange(w) + r + 1, cap_w)
    y1 = np.maximum(y1, y0)
    x1 = np.maximum(x1, x0)
    count = ii[y1][:, x1] - ii[y0][:, x1] - ii[y1][:, x0] + ii[y0][:, x0]  # [h, w]
    area = (y1 - y0)[:, None] * (x1 - x0)[None, :]
    return 2 * count > area


@dataclass(frozen=True)
class QuerySettings:
    """The knobs of one query (the `query` stage's config passes them through)."""

    temperature: float = 10.0
    background_filter: str = "paper"
    fusion: str = "weighted"
    smooth_kernel: int = 20
    threshold: float = 0.4
    threshold_mode: str = "relative"
    majority: int = 7
    majority_exact: bool = False
    filter_ref: float = 0.0  # short side the two sizes are given at (0: fixed px)
    peak_quantile: float = 1.0  # a map's peak: this quantile (1: its maximum)
    level_softness: float = 0.0  # 0: the level of the highest peak; else a blend

    def __post_init__(self) -> None:
        if not 0.0 < self.peak_quantile <= 1.0:
            raise ValueError(
                f"query.peak_quantile = {self.peak_quantile}: give 0 < q ≤ 1"
            )
        if not (np.isfinite(self.level_softness) and self.level_softness >= 0.0):
            raise ValueError(
                f"query.level_softness = {self.level_softness}: give a number ≥ 0"
            )

    def filter_sizes(self, height: int, width: int) -> tuple[int, int]:
        """(box kernel, majority window) in pixels for an image of this size: the
        configured sizes, scaled by short side / filter_ref when filter_ref > 0
        (the window to the nearest odd size; 1 = off)."""
        if self.filter_ref <= 0:
            return int(self.smooth_kernel), int(self.majority)
        f = min(height, width) / self.filter_ref
        kernel = max(1, round(self.smooth_kernel * f)) if self.smooth_kernel > 1 else 1
        maj = 1
        if self.majority > 1:
            maj = max(1, 2 * round((self.majority * f - 1) / 2) + 1)
        return kernel, maj


@dataclass
class QueryResult:
    smoothed: np.ndarray  # [L, H, W] float32: Ŝ per level
    level: int  # ℓ*
    score: float  # max Ŝ at ℓ*
    mask: np.ndarray  # [H, W] bool


def score_maps(
    cos: Tensor,
    query: int,
    canonical: list[int],
    bg: list[int],
    settings: QuerySettings,
    image_queries: list[int] | None = None,
) -> tuple[Tensor, Tensor | None]:
    """(relevancy, per-map background) of every pixel: functions of its cosines."""
    s = relevancy(cos[..., query], cos[..., canonical], settings.temperature)
    b = background_per_map(
        cos, query, bg, settings.background_filter, settings.temperature, image_queries
    )
    return s, b


def finish(
    s: Tensor,
    b: Tensor | None,
    settings: QuerySettings,
    support: Tensor | None = None,
) -> QueryResult:
    """Background filter, fusion, smoothing, level, threshold, majority filter.

    Args:
        s: [L, N, H, W] relevancy of each map.
        b: [L, N, H, W] per-map background probability, or None (filter off).
        settings: the query knobs.
        support: [H, W] weight per pixel (1 where the field has a surface, 0 where
            it is empty), multiplied into every relevancy map; None: all 1.
    """
    if support is not None:
        s = s * support
    b = reduce_background(b, settings.background_filter)
    damp = None
    if b is not None and settings.background_filter == "paper":
        s = s * (1.0 - b)[:, None]
    elif b is not None:
        damp = b[0].numpy().astype(np.float32)
    fused = fuse(s, settings.fusion).numpy()
    kernel, window = settings.filter_sizes(*fused.shape[-2:])
    sm = np.stack([smooth(m, kernel, damp) for m in fused])
    peaks = np.array([peak_of(m, settings.peak_quantile) for m in sm])
    level, chosen, top = _chosen_map(sm, peaks, settings)
    mask = threshold(chosen, settings.threshold, settings.threshold_mode, top)
    mask = majority(mask, window, settings.majority_exact)
    if not np.all(np.isfinite(sm)):
        raise FloatingPointError("query: a smoothed score map is not finite")
    return QueryResult(sm, level, float(peaks[level]), mask)


@dataclass
class Selection:
    scores: np.ndarray  # [L, P] float32: fused S_ℓ per Gaussian (0 where invalid)
    level: int  # ℓ*
    score: float  # max S at ℓ*
    mask: np.ndarray  # [P] bool: the selected Gaussians


def select(
    s: Tensor,
    b: Tensor | None,
    settings: QuerySettings,
    valid: Tensor | None = None,
    neighbors: Tensor | None = None,
) -> Selection:
    """The 3-D query (docs/method.md §10.1): per Gaussian instead of per pixel.

    The same background filter, fusion and level choice as `finish`, with the
    Gaussians in place of pixels (weights w_a from the max over Gaussians), no
    smoothing and no majority filter (Gaussians have no grid), then the
    threshold rule over the valid Gaussians. In the code form of the background
    filter, whose 2-D form damps the box-filtered term, the factor (1 − b)
    multiplies the score directly.

    Args:
        s: [L, N, P] relevancy of each Gaussian's code per level and appearance.
        b: [L, N, P] per-code background probability, or None (filter off).
        settings: the query knobs (temperature is already applied in s and b).
        valid: [P] bool, Gaussians that may be selected (trained and opaque
            enough); the others score 0 and are never selected. None: all.
        neighbors: [P, k] int64, each Gaussian's k nearest (itself included):
            the fused score is averaged over them before the level choice, the
            3-D counterpart of the 2-D mean filter. None: no smoothing.
    """
    L, N, P = s.shape  # noqa: N806
    if valid is None:
        valid = torch.ones(P, dtype=torch.bool)
    if P == 0 or not bool(valid.any()):
        return Selection(np.zeros((L, P), np.float32), 0, 0.0, np.zeros(P, bool))
    s = s * valid
    if b is not None:  # [L, P] (paper) or [1, P] (code): broadcast over appearances
        b = reduce_background(b[..., None], settings.background_filter)[..., 0]
        s = s * (1.0 - b)[:, None]
    fused_t = fuse(s[..., None], settings.fusion)[..., 0]
    if neighbors is not None:
        if neighbors.shape[0] != P:
            raise ValueError(
                f"neighbors has {neighbors.shape[0]} rows for {P} Gaussians"
            )
        fused_t = fused_t[:, neighbors].mean(-1)
    fused = fused_t.numpy().astype(np.float32)
    v = valid.numpy()
    peaks = np.array([peak_of(f[v], settings.peak_quantile) for f in fused])
    level, chosen, top = _chosen_map(fused[:, v], peaks, settings)
    mask = np.zeros(P, bool)
    mask[v] = threshold(chosen, settings.threshold, settings.threshold_mode, top)
    if not np.all(np.isfinite(fused)):
        raise FloatingPointError("select: a fused score is not finite")
    return Selection(fused, level, float(peaks[level]), mask)


def answer(
    cos: Tensor,
    query: int,
    canonical: list[int],
    bg: list[int],
    settings: QuerySettings,
    image_queries: list[int] | None = None,
    support: Tensor | None = None,
) -> QueryResult:
    """Everything after decoding for one (view, query).

    Args:
        cos: [L, N, H, W, K] cosines of the decoded codes with every phrase.
        query: the query's phrase index; canonical: the canonical phrases'
            indices; bg: "sky" (and "background") indices.
        settings: the query knobs.
        image_queries: every query of this image (the code-form sky filter).
        support: see `finish`.
    """
    s, b = score_maps(cos, query, canonical, bg, settings, image_queries)
    return finish(s, b, settings, support)


__all__ = [
    "BACKGROUND_FILTERS",
    "BACKGROUND_PHRASES",
    "CANONICAL",
    "FUSIONS",
    "PhraseDecoder",
    "QueryResult",
    "QuerySettings",
    "answer",
    "background",
    "background_per_map",
    "choose_level",
    "finish",
    "reduce_background",
    "score_maps",
    "fuse",
    "majority",
    "peak_of",
    "relevancy",
    "select",
    "Selection",
    "smooth",
    "threshold",
]

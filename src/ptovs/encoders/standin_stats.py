"""The image statistics of the stand-in for CLIP, version 5, and the plain
reading of them that the synthetic generator screens version-5 worlds with.

A crop is reduced by area to 112 x 112 (exact black is outside the mask) and
described by groups of statistics (`raw_features`), each standardised against a
fixed bank of random swatches, clipped to +-3 and weighted (`standardised`):
- silhouette: occupancy of the mask on a 4 x 4 grid, its fill, elongation and
  orientation (the shape cue, untouched by light and colour);
- fine texture, on the contrast-normalised luminance: Gabor energy shares at
  wavelengths 2.5 and 5 px and six orientations (pooled well inside the mask, so
  the mask's own edge does not count), an orientation histogram of the gradient,
  its mean magnitude, and the histogram of the normalised values;
- coarse texture: Gabor energy shares at 10 and 20 px (filtered at half
  resolution, where the same kernels cost a quarter);
- colour, a little: the hue of the mean opponent colour, the spread of colours
  about it, a saturation-weighted hue histogram, all blind to saturation;
- (luminance level and a 4 x 4 luminance layout are computed, weighted 0: they
  follow the light, not the part);
- two auxiliary columns, not projected: how well chroma edges follow luminance
  edges, and how strong the chroma edges are.

`PARAMS` holds the weights, the contrast floor and the perturbation's
calibration with the four reading options off; version 5 (`synthetic_v5.STATS`)
turns them on: "rim" (px) measures the luminance statistics that far inside the
mask's edge; "robust" takes their level and spread as the median and
interquartile range; "core_texture" filters the texture on that core only;
"clip_ln" clips the normalised luminance to +- that many spreads.

Each crop also gets a fixed pseudo-random perturbation keyed by its own coarse
content (`_key`: a hash of its 8 x 8 colour grid, quantised): the same pixels
always get the same error, another light or view another one. Its size grows
with the crop's `distortion`: its blur deficit (`blur_deficit`, the detail it
lacks at the two finest scales against a sharp render) plus its chroma
decoupling (`chroma_decoupling`, chroma edges where the luminance has none, as
strong JPEG and sensor noise make them).

`content` is the plain reading, options off: the perturbed standardised
statistics projected to 512-d with a seeded Gaussian matrix and normalised. The
generator's answerability screen reads version-5 worlds with it
(`standin_text.CategoryEncoder`), so a seed's photos do not depend on version 5's
learnt projection.

Deterministic on one machine: float64 numpy and per-crop OpenCV filters and
resizes (bit for bit across batch sizes and runs).
"""

from __future__ import annotations

import functools
import hashlib
import math

import cv2
import numpy as np

from ptovs.encoders import synthetic as v1

DIM = v1.DIM
SEED = 20261126
_R = 112
WAVELENGTHS = (2.5, 5.0, 10.0, 20.0)  # Gabor wavelengths, pixels at _R (x2 at 224)
N_FINE = 2  # the first N_FINE wavelengths are the "fine" group
THETAS = tuple(np.arange(6) * (np.pi / 6))
N_HUE = 6
ZCLIP = 3.0  # standardised statistics are clipped: no one cell of a grid dominates
LN_BINS = np.linspace(-2.0, 2.0, 9)  # histogram of the normalised luminance

# calibrated on crops of calibration seeds 300-305 (bench/standin_profile.py).
# The reading options ("rim", "robust", "core_texture", "clip_ln") are absent
# here, so off: version 5 sets them (`synthetic_v5.STATS`, module docstring)
PARAMS: dict[str, float] = {
    "w_colour": 0.7,  # hue and colour spread (blind to saturation and contrast)
    "w_lum": 0.0,  # mean and spread of luminance: off (lighting, not identity)
    "w_silhouette": 0.8,
    "w_layout": 0.0,  # luminance on a 4 x 4 grid: off (it follows the light's side)
    "w_fine": 2.5,  # Gabor energies at 2.5 and 5 px, orientations, value histogram
    "w_coarse": 1.0,  # Gabor energies at 10 and 20 px
    "floor": 0.001,  # contrast normalisation: (L - mean) / (sd + floor)
    "noise": 0.25,  # the keyed perturbation's norm, relative to the features'
    "t1": -1.3,  # blur_deficit's thresholds and gains
    "t2": -0.9,
    "k1": 1.0,
    "k2": 6.0,
    "t3": 0.6,  # chroma_decoupling's threshold and gain
    "k3": 20.0,
    "c0": 0.01,  # the chroma gradient below which a crop counts as colourless
}
_GROUPS = (  # (name, size)
    ("colour", 2 + 2 + 6),
    ("lum", 2),
    ("silhouette", 16 + 4),
    ("layout", 16),
    ("fine", N_FINE * len(THETAS) + 6 + 1 + len(LN_BINS)),
    ("coarse", (len(WAVELENGTHS) - N_FINE) * len(THETAS)),
)
N_FEATURES = sum(n for _, n in _GROUPS)
N_AUX = 2  # raw_features' last columns, not projected: chroma-luma edge coupling


def _area(x: np.ndarray, n: int) -> np.ndarray:
    return cv2.resize(x, (n, n), interpolation=cv2.INTER_AREA).astype(np.float64)


def _level(i: int) -> int:
    """Downsampling factor wavelength i is filtered at: the coarse group at half
    resolution (the same kernel in half the pixels, a quarter of the cost)."""
    return 1 if i < N_FINE else 2


@functools.lru_cache(maxsize=1)
def _gabors() -> list[list[tuple[np.ndarray, np.ndarray]]]:
    """(even, odd) Gabor kernels per wavelength and orientation, zero-mean, unit
    L2, float32, at the resolution `_level` filters that wavelength at."""
    out = []
    for i, lam in enumerate(WAVELENGTHS):
        lam = lam / _level(i)
        sigma = 0.56 * lam
        k = 2 * int(math.ceil(2.5 * sigma)) + 1
        row = []
        for th in THETAS:
            pair = []
            for psi in (0.0, math.pi / 2):
                g = cv2.getGaborKernel((k, k), sigma, th, lam, 1.0, psi, cv2.CV_64F)
                g = g - g.mean()
                pair.append((g / np.sqrt((g * g).sum())).astype(np.float32))
            row.append((pair[0], pair[1]))
        out.append(row)
    return out


def _grid(v: np.ndarray, m: np.ndarray, g: int) -> np.ndarray:
    """Masked means of v over a g x g grid (0 where a cell is empty)."""
    n = v.shape[0] // g
    vs = (v * m).reshape(g, n, g, n).sum(axis=(1, 3))
    ms = m.reshape(g, n, g, n).sum(axis=(1, 3))
    return np.where(ms > 0, vs / np.maximum(ms, 1e-9), 0.0).ravel()


def _one(crop: np.ndarray, p: dict) -> np.ndarray:
    """The statistics of one crop under the options of `p` (`PARAMS`)."""
    floor, rim = p["floor"], int(p.get("rim", 0))
    core_texture = bool(p.get("core_texture", 0))
    clip_ln = float(p.get("clip_ln", 0.0))
    x = np.ascontiguousarray(crop, dtype=np.float32)
    valid = (cv2.cvtColor(x, cv2.COLOR_RGB2GRAY) > 0).astype(np.float32)
    w = _area(valid, _R)
    col = _area(x, _R)
    m = (w >= 0.5).astype(np.float64)
    msum = m.sum() + 1e-9
    c = np.clip(col / np.maximum(w, 1e-6)[..., None], 0.0, 1.0)
    L = 0.299 * c[..., 0] + 0.587 * c[..., 1] + 0.114 * c[..., 2]

    def pool(v, mm=m, s=msum):
        return float((v * mm).sum() / s)

    out: list[float] = []
    # colour: the hue of the crop's mean opponent colour and a saturation-weighted
    # hue histogram, both blind to how saturated (contrasty) the colour is
    o1 = c[..., 0] - c[..., 1]
    o2 = 0.5 * (c[..., 0] + c[..., 1]) - c[..., 2]
    sat = np.sqrt(o1 * o1 + o2 * o2) + 1e-9
    mo1, mo2 = pool(o1), pool(o2)
    e_hue, e_sat = 1e-3, 0.02  # keep a grey crop's hue and spread finite
    ms = np.sqrt(mo1 * mo1 + mo2 * mo2) + e_hue
    out += [mo1 / ms, mo2 / ms]
    # how far the colours spread about their mean (two-colour patterns), relative
    # to the mean saturation: also blind to contrast
    msat = pool(sat)
    out += [
        np.sqrt(pool((o1 - mo1) ** 2)) / (msat + e_sat),
        np.sqrt(pool((o2 - mo2) ** 2)) / (msat + e_sat),
    ]
    hue = np.arctan2(o2, o1)
    wsat = (sat * m).sum() + 1e-9
    for k in range(N_HUE):
        d = np.cos(hue - 2 * math.pi * k / N_HUE)
        out.append(float((np.maximum(d, 0.0) ** 2 * sat * m).sum() / wsat))
    # the luminance's level and spread; with `rim`, measured `rim` px inside the
    # mask's edge, where the crop's resize has not mixed the part with the black
    # outside (that dark ring is a constant step however faint the part is)
    core, csum = m, msum
    if rim:
        k = np.ones((2 * rim + 1, 2 * rim + 1), np.uint8)
        eroded = cv2.erode(m.astype(np.uint8), k).astype(np.float64)
        if eroded.sum() >= 8:
            core, csum = eroded, eroded.sum() + 1e-9
    mu = pool(L, core, csum)
    sd = np.sqrt(pool((L - mu) ** 2, core, csum))
    lum = [mu, sd]
    if p.get("robust", 0) and core.sum() > 0:
        # the level and spread of the bulk of the core, which a ring deeper than
        # `rim` (a small part upsampled) moves little; the "lum" group (weighted 0)
        # then holds the median and the 5-95 % range (`faintness` reads it)
        q = np.percentile(L[core > 0], (5, 25, 50, 75, 95))
        mu, sd = float(q[2]), float(q[3] - q[1]) / 1.349
        lum = [mu, float(q[4] - q[0])]
    out += lum
    # silhouette: occupancy grid and the mask's second moments
    out += list(_grid(m, np.ones_like(m), 4))
    yy, xx = np.mgrid[0:_R, 0:_R] / (_R - 1.0) - 0.5
    my, mx = pool(yy), pool(xx)
    cyy, cxx = pool((yy - my) ** 2), pool((xx - mx) ** 2)
    cxy = pool((yy - my) * (xx - mx))
    tr = cyy + cxx + 1e-9
    out += [
        msum / (_R * _R),
        np.sqrt((cxx - cyy) ** 2 + 4 * cxy**2) / tr,
        (cxx - cyy) / tr,
        2 * cxy / tr,
    ]
    # layout and texture on the contrast-normalised luminance
    Ln = (L - mu) / (sd + floor) * m
    if clip_ln:
        Ln = np.clip(Ln, -clip_ln, clip_ln)
    out += list(_grid(Ln, m, 4))
    m8 = m.astype(np.uint8)
    tm = m
    if core_texture:
        # texture read on the core only: the rim and the outside stand at the
        # core's mean (0), so the mask's edge is no step the filters answer to
        tm = core
        Ln = Ln * core
    half_m = (_area(tm.astype(np.float32), _R // 2) >= 0.5).astype(np.float64)
    levels = {  # factor -> (luminance, mask) at that resolution
        1: (Ln.astype(np.float32), tm),
        2: (_area(Ln.astype(np.float32), _R // 2).astype(np.float32), half_m),
    }
    energy = np.zeros((len(WAVELENGTHS), len(THETAS)))
    for i, lam in enumerate(WAVELENGTHS):
        f = _level(i)
        img, ml = levels[f]
        r = int(math.ceil(1.4 * lam)) if i < N_FINE else max(1, int(round(lam / 2)))
        r = max(1, int(round(r / f)))
        kernel = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
        mi = cv2.erode(ml.astype(np.uint8), kernel).astype(np.float64)
        if mi.sum() < 4:
            mi = ml
        si = mi.sum() + 1e-9
        for j, (even, odd) in enumerate(_gabors()[i]):
            re = cv2.filter2D(img, cv2.CV_32F, even, borderType=cv2.BORDER_REPLICATE)
            im = cv2.filter2D(img, cv2.CV_32F, odd, borderType=cv2.BORDER_REPLICATE)
            e = re.astype(np.float64) ** 2 + im.astype(np.float64) ** 2
            # a unit-L2 kernel at 1/f resolution has 1/f^2 the taps: x f^2 keeps
            # the energies of all wavelengths on one scale
            energy[i, j] = pool(e, mi, si) * f * f
    total = energy.sum() + 1e-9
    share = energy / total
    coarse = list(share[N_FINE:].ravel())
    out += list(share[:N_FINE].ravel())
    gy, gx = np.gradient(Ln)
    mag2 = gx * gx + gy * gy
    c2 = (gx * gx - gy * gy) / (mag2 + 1e-12)
    s2 = 2.0 * gx * gy / (mag2 + 1e-12)
    mi = cv2.erode(core.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(np.float64)
    wm = mi * np.sqrt(mag2)
    ws = wm.sum() + 1e-9
    for phi in np.arange(6) * (np.pi / 6):
        b = np.maximum(c2 * np.cos(2 * phi) + s2 * np.sin(2 * phi), 0.0) ** 4
        out.append(float((b * wm).sum() / ws))
    out.append(pool(np.sqrt(mag2), mi, mi.sum() + 1e-9))
    # the pattern's value distribution (two-tone stripes against noise)
    zn = (L - mu) / (sd + floor)
    for k in range(len(LN_BINS)):
        out.append(pool(v1._hat(zn, LN_BINS, k), core, csum))
    out += coarse  # the order of _GROUPS: ..., fine, coarse
    # aux (not projected): how well chroma edges follow luminance edges, and how
    # strong the chroma edges are
    gLy, gLx = np.gradient(L)
    g1y, g1x = np.gradient(o1)
    g2y, g2x = np.gradient(o2)
    inner = cv2.erode(m8, np.ones((5, 5), np.uint8)).astype(bool)
    if inner.sum() < 8:
        inner = m > 0
    gl = np.sqrt(gLx * gLx + gLy * gLy)[inner]
    gc = np.sqrt(g1x * g1x + g1y * g1y + g2x * g2x + g2y * g2y)[inner]
    if gl.size >= 2 and gl.std() > 1e-9 and gc.std() > 1e-9:
        corr = float(np.corrcoef(gl, gc)[0, 1])
    else:
        corr = 1.0  # no edges of one kind: nothing decoupled
    out += [corr, float(gc.mean()) if gc.size else 0.0]
    return np.asarray(out, np.float64)


def _key(crop: np.ndarray) -> int:
    """Seed of a crop's perturbation: its 8 x 8 colour grid, quantised to 1/16."""
    g = cv2.resize(
        np.ascontiguousarray(crop, np.float32), (8, 8), interpolation=cv2.INTER_AREA
    )
    q = np.floor(np.clip(g, 0.0, 1.0) * 16.0).astype(np.uint8)
    return int.from_bytes(hashlib.sha256(q.tobytes()).digest()[:8], "little")


def raw_features(crops: np.ndarray, params: dict | None = None) -> np.ndarray:
    """[B, N_FEATURES + N_AUX] float64 statistics of crops [B, S, S, 3] in [0, 1]."""
    p = PARAMS if params is None else params
    out = np.stack([_one(c, p) for c in crops])
    assert out.shape[1] == N_FEATURES + N_AUX
    return out


@functools.lru_cache(maxsize=1)
def _bank() -> np.ndarray:
    return raw_features(np.stack(v1._bank_swatches()), PARAMS)


@functools.lru_cache(maxsize=1)
def _projection() -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(SEED + 3)
    P = rng.standard_normal((N_FEATURES, DIM)) / np.sqrt(DIM)
    return P, v1._fixed()[4]


def _offset(group: str) -> int:
    out = 0
    for name, n in _GROUPS:
        if name == group:
            return out
        out += n
    raise KeyError(group)


def blur_deficit(raw: np.ndarray, params: dict | None = None) -> np.ndarray:
    """How much finer detail a crop lacks than a sharp photo has, >= 0 per crop.

    From the spectral slope at the two finest scales: log10 of the Gabor energy
    at wavelength 2.5 px over that at 5 px, and of 5 px over 10 px (at _R). A
    sharp render sits near -1.0 and -0.8; blur, a low-resolution source and an
    upsampled small crop fall below the thresholds. CLIP's features drift off
    their manifold on such crops (its accuracy halves near blur sigma 5 px); here
    the crop's keyed perturbation grows with the deficit.
    """
    p = PARAMS if params is None else params
    nt = len(THETAS)
    f, c = _offset("fine"), _offset("coarse")
    e1 = raw[:, f : f + nt].sum(axis=1)
    e2 = raw[:, f + nt : f + 2 * nt].sum(axis=1)
    e3 = raw[:, c : c + nt].sum(axis=1)
    l1 = np.log10((e1 + 1e-9) / (e2 + 1e-9))
    l2 = np.log10((e2 + 1e-9) / (e3 + 1e-9))
    return p["k1"] * np.maximum(p["t1"] - l1, 0.0) + p["k2"] * np.maximum(
        p["t2"] - l2, 0.0
    )


def chroma_decoupling(raw: np.ndarray, params: dict | None = None) -> np.ndarray:
    """How far a crop's chroma edges have come loose from its luminance edges, >= 0.

    In a photograph, colour changes where the surface changes, so chroma and
    luminance edges coincide (their gradient magnitudes correlate at 0.9 on clean
    renders). Block artefacts of strong JPEG (chroma subsampled and quantised in
    8 x 8 blocks) and sensor noise put chroma edges where the surface has none
    (correlation near 0.3). CLIP loses half its accuracy or more to such
    corruption; here the crop's keyed perturbation grows with this measure.
    Gated by the strength of the chroma edges (`c0`): a colourless or
    low-contrast crop has no chroma edges to decouple.
    """
    p = PARAMS if params is None else params
    corr, strength = raw[:, N_FEATURES], raw[:, N_FEATURES + 1]
    gate = np.minimum(strength / p["c0"], 1.0)
    return p["k3"] * gate * np.maximum(p["t3"] - corr, 0.0)


def distortion(raw: np.ndarray, params: dict | None = None) -> np.ndarray:
    """The size of a crop's keyed perturbation, relative to a clean crop's: blur
    deficit plus chroma decoupling."""
    return blur_deficit(raw, params) + chroma_decoupling(raw, params)


@functools.lru_cache(maxsize=8)
def _bank_for(items: tuple) -> np.ndarray:
    return raw_features(np.stack(v1._bank_swatches()), dict(items))


def standardised(
    raw: np.ndarray, params: dict | None = None
) -> tuple[np.ndarray, float]:
    """Statistics [B, N_FEATURES + N_AUX] standardised against the swatch bank,
    clipped and group-weighted [B, N_FEATURES]; and their nominal norm (the unit
    of the keyed perturbation)."""
    p = PARAMS if params is None else params
    bank = _bank() if params is None else _bank_for(tuple(sorted(p.items())))
    mean, scale = bank.mean(axis=0), np.maximum(bank.std(axis=0), 1e-3)
    gw = np.concatenate(
        [np.full(n, p[f"w_{name}"] / np.sqrt(n)) for name, n in _GROUPS]
    )
    z = np.clip((raw - mean) / scale, -ZCLIP, ZCLIP)[:, :N_FEATURES] * gw
    return z, float(np.sqrt((gw * gw).sum()))


def content(crops: np.ndarray) -> np.ndarray:
    """Unit content vectors [B, 512] float64 of crops [B, S, S, 3]: the plain
    reading (options off) the generator screens version-5 worlds with."""
    raw = raw_features(crops)
    z, norm = standardised(raw)
    amp = PARAMS["noise"] * (1.0 + distortion(raw))
    for b, crop in enumerate(crops):
        e = np.random.default_rng(_key(crop)).standard_normal(N_FEATURES)
        z[b] += amp[b] * norm * e / np.sqrt(N_FEATURES)
    P, _ = _projection()
    acc = np.zeros((len(z), DIM))
    for k in range(N_FEATURES):  # fixed-order projection, batch independent
        acc += z[:, k : k + 1] * P[k]
    return v1._normalise(acc)

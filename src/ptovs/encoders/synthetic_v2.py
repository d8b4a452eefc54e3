"""The stand-in for CLIP, version 2: it fails the way CLIP fails (issue 41).

Version 1 (`ptovs.encoders.synthetic`) reads mostly colour statistics and matches a
crop against one texture swatch of its part under neutral light: greyscale and
sepia cost it half its accuracy, blur, low resolution and noise almost nothing, and
its shape bias is 0.03. Version 2 is calibrated on crops only, against the targets
registered in docs/benchmarks.md from CLIP's published figures:

Image side, a fixed function of pixels. The crop is reduced by area to 112 x 112
(exact black is outside the mask) and described by groups of statistics, each
standardised against a fixed bank of random swatches, clipped to +-3 and weighted
(`PARAMS`):
- silhouette: occupancy of the mask on a 4 x 4 grid, its fill, elongation and
  orientation (the shape cue, untouched by light and colour);
- fine texture, on the contrast-normalised luminance: Gabor energy shares at
  wavelengths 2.5 and 5 px and six orientations (pooled well inside the mask, so
  the mask's own edge does not count), an orientation histogram of the gradient,
  its mean magnitude, and the histogram of the normalised values (two-tone stripes
  against noise): what blur, low resolution, noise and JPEG take away;
- coarse texture: Gabor energy shares at 10 and 20 px (filtered at half
  resolution, where the same kernels cost a quarter);
- colour, a little: the hue of the mean opponent colour, the spread of colours
  about it, a saturation-weighted hue histogram, all blind to saturation (so to
  contrast); greyscale and a colour cast cost a little, not half;
- (luminance level and a 4 x 4 luminance layout are computed, weighted 0: they
  follow the light, not the part);
- a fixed pseudo-random perturbation keyed by the crop's own coarse content (a hash
  of its 8 x 8 colour grid, quantised): the same pixels always get the same error,
  another light or another view gets another one, so appearances err differently.
  Its size grows with the crop's distortion (`distortion`): its blur deficit
  (`blur_deficit`: the detail the crop lacks at the two finest scales compared
  with a sharp render), as CLIP's features drift on blurred and upsampled crops,
  plus its chroma decoupling (`chroma_decoupling`: chroma edges where the
  luminance has none, as strong JPEG and sensor noise make them).
The statistics are projected to 512-d with a seeded Gaussian matrix and normalised;
the modality offset is version 1's.

Text side, a category description, not one instance's template: a part's phrase
embeds as the normalised mean content of its part rendered alone (masked and cut
as a segment crop) from the views where it shows, under several ordinary daylight
appearances, and in several instances of its category (its own texture and
variants with other colours, frequencies and offsets of the same pattern).
Generic phrases, "sky", styles and unknown phrases behave as in version 1.

Version 3 (`SyntheticEncoderV3`, docs/benchmarks.md "Amendment 4") is version 2
with one change of the text side: "building", one of the pipeline's canonical
phrases, is the *average word* of the scene's part phrases (LERF chose its canonical
phrases as "average" words for the queries users make, so that a relevancy of 0.5
means "as relevant as an average word"). Version 2 kept version 1's square swatches
for the canonical phrases, which lie far from every masked part crop, so every
part's phrase won the relevancy on every part.

Deterministic on one machine: float64 numpy and per-crop OpenCV filters and
resizes (bit for bit across batch sizes and runs).
"""

from __future__ import annotations

import functools
import hashlib
import json
import math
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from ptovs.encoders import synthetic as v1
from ptovs.synthetic.world import (
    World,
    neutral_appearance,
    render,
    render_swatch,
    sky_swatch,
)
from ptovs.synthetic.world.appearance import Appearance, sample_appearance
from ptovs.synthetic.world.swatches import landmark_camera
from ptovs.synthetic.world.textures import Texture

DIM = v1.DIM
SEED = 20261126
VERSION = 2
_R = 112
WAVELENGTHS = (2.5, 5.0, 10.0, 20.0)  # Gabor wavelengths, pixels at _R (x2 at 224)
N_FINE = 2  # the first N_FINE wavelengths are the "fine" group
THETAS = tuple(np.arange(6) * (np.pi / 6))
N_HUE = 6
ZCLIP = 3.0  # standardised statistics are clipped: no one cell of a grid dominates
LN_BINS = np.linspace(-2.0, 2.0, 9)  # histogram of the normalised luminance

# calibrated on crops of calibration seeds 300-305 (bench/standin_profile.py).
# Optional keys, absent (off) in versions 2 to 4 and set by version 5
# (`synthetic_v5.STATS`): "rim" (px) measures the luminance statistics that far
# inside the mask's edge; "robust" takes their level and spread as the median and
# interquartile range; "core_texture" filters the texture on that core only;
# "clip_ln" clips the normalised luminance to +- that many spreads
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
    """Version 2's statistics of one crop under the options of `p` (`PARAMS`)."""
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


def content(crops: np.ndarray, params: dict | None = None) -> np.ndarray:
    """Unit content vectors [B, 512] float64 of crops [B, S, S, 3]."""
    p = PARAMS if params is None else params
    raw = raw_features(crops, p)
    z, norm = standardised(raw, params)
    amp = p["noise"] * (1.0 + distortion(raw, p))
    for b, crop in enumerate(crops):
        e = np.random.default_rng(_key(crop)).standard_normal(N_FEATURES)
        z[b] += amp[b] * norm * e / np.sqrt(N_FEATURES)
    P, _ = _projection()
    acc = np.zeros((len(z), DIM))
    for k in range(N_FEATURES):  # fixed-order projection, batch independent
        acc += z[:, k : k + 1] * P[k]
    return v1._normalise(acc)


# ------------------------------------------------------------- text side --

TEXT_AZIMUTHS = tuple(range(-150, 181, 30))
TEXT_VIEWS = 3  # the part's best views (most pixels) among TEXT_AZIMUTHS
TEXT_PX = 256
N_INSTANCES = 3  # the part's own texture and this many variants
N_DAYLIGHT = 3


@functools.lru_cache(maxsize=1)
def daylight_appearances() -> tuple[Appearance, ...]:
    """The text side's ordinary lights: neutral and N_DAYLIGHT - 1 fixed draws."""
    rng = np.random.default_rng(SEED + 5)
    out = [neutral_appearance()]
    while len(out) < N_DAYLIGHT:
        a = sample_appearance(rng)
        if a.sky in ("day", "overcast") and not a.hard:
            out.append(a)
    return tuple(out)


def instances(tex: Texture, part_id: int) -> list[Texture]:
    """The part's texture and N_INSTANCES variants of the same pattern."""
    rng = np.random.default_rng([SEED + 6, part_id])
    out = [tex]
    for k in range(N_INSTANCES):
        jit = rng.uniform(0.8, 1.2, 3) * rng.uniform(0.85, 1.15)
        out.append(
            replace(
                tex,
                base=tuple(
                    float(np.clip(c * j, 0.02, 1.0))
                    for c, j in zip(tex.base, jit, strict=True)
                ),
                accent=tuple(
                    float(np.clip(c * j, 0.02, 1.0))
                    for c, j in zip(tex.accent, jit[::-1], strict=True)
                ),
                freq=float(tex.freq * rng.uniform(0.8, 1.25)),
                offset=tuple(float(x) for x in rng.uniform(0.0, 3.0, 3)),
                seed=int(tex.seed) + 101 * (k + 1),
            )
        )
    return out


_PART_CONTENT: dict[str, np.ndarray] = {}  # bounded: cleared past 256 entries


def part_content(world: World, part_id: int, fn=None) -> np.ndarray:
    """Mean content of `part_crops` under the image side `fn` (default: this
    version's `content`), cached by what those crops depend on: the world's
    geometry and this part's texture (other parts' textures never show in this
    part's pixels), so a screen that redraws one part re-renders one."""
    fn = content if fn is None else fn
    d = world.to_dict()
    for q in d["parts"]:
        if q["id"] != part_id:
            q.pop("texture", None)
            q["name"] = q["query"] = ""
    tag = [VERSION] if fn is content else [VERSION, fn.__module__, fn.__qualname__]
    key = hashlib.sha256(
        json.dumps([d, part_id, *tag, TEXT_PX], sort_keys=True).encode()
    ).hexdigest()
    if key not in _PART_CONTENT:
        if len(_PART_CONTENT) >= 256:
            _PART_CONTENT.clear()
        out = fn(np.stack(part_crops(world, part_id))).mean(axis=0)
        out.flags.writeable = False
        _PART_CONTENT[key] = out
    return _PART_CONTENT[key]


def part_crops(world: World, part_id: int) -> list[np.ndarray]:
    """The part alone, as segment crops: best views x daylight x instances."""
    from ptovs.crop import prepare_crop

    views = []
    for az in TEXT_AZIMUTHS:
        cam = landmark_camera(world, float(az), TEXT_PX)
        v = render(world, cam, neutral_appearance(), aa=1, shadows=False)
        n = int((v.part_id == part_id).sum())
        if n >= 16:
            views.append((n, az, cam))
    views = sorted(views, key=lambda t: (-t[0], t[1]))[:TEXT_VIEWS]
    part = next(p for p in world.parts if p.id == part_id)
    crops = []
    for tex in instances(part.texture, part_id):
        w = replace(
            world,
            parts=[
                replace(p, texture=tex) if p.id == part_id else p for p in world.parts
            ],
        )
        for _, _, cam in views:
            for app in daylight_appearances():
                v = render(w, cam, app, aa=1)
                m = v.part_id == part_id
                img = np.maximum(v.image.astype(np.float32) / 255.0, 1.0 / 255.0)
                crops.append(prepare_crop(img, m))
    return crops


class SyntheticEncoderV2(v1.SyntheticEncoder):
    """Stand-in for CLIP, version 2 (module docstring). The vocabulary is version 1's
    plus "world" (the World dict) and "parts" ({phrase: [part ids]}): a listed
    phrase embeds as its parts' category description (`part_crops`)."""

    name = "synthetic-v2"
    image_side = staticmethod(content)  # crops [B, S, S, 3] -> unit [B, 512]

    def __init__(self, vocabulary: str | Path | dict | None = None) -> None:
        super().__init__(vocabulary)
        vocab = self._vocab
        self._world = World.from_dict(vocab["world"]) if "world" in vocab else None
        self._parts: dict[str, list[int]] = {
            k.strip().lower(): list(v) for k, v in vocab.get("parts", {}).items()
        }

    def encode_images(self, crops: np.ndarray) -> np.ndarray:
        crops = np.asarray(crops)
        if crops.ndim != 4 or crops.shape[-1] != 3:
            raise ValueError(f"crops must be [B, S, S, 3], got {crops.shape}")
        if len(crops) == 0:
            return np.zeros((0, DIM), np.float32)
        return v1._embed(self.image_side(crops), 0)

    def _text_content(self, phrase: str) -> np.ndarray:
        key = phrase.strip().lower()
        if self._world is not None and key in self._parts:
            acc = sum(
                part_content(self._world, pid, self.image_side)
                for pid in self._parts[key]
            )
            return v1._normalise(acc)
        if key == "sky" or key in self._generic or key in self._lower:
            return self._v2_swatch(phrase)
        return super()._text_content(phrase)

    def _v2_swatch(self, phrase: str) -> np.ndarray:
        key = phrase.strip()
        desc = self._phrases.get(key, self._lower.get(key.lower()))
        items = (
            [{"weight": 1.0, "swatch": desc}]
            if desc is not None
            else self._generic.get(
                key.lower(), [{"weight": 1.0, "swatch": sky_swatch()}]
            )
        )
        acc = np.zeros(DIM)
        for it in items:
            key = json.dumps(it["swatch"], sort_keys=True)
            acc = acc + float(it["weight"]) * _swatch_content(key, self.image_side)
        return v1._normalise(acc)


@functools.lru_cache(maxsize=1024)
def _swatch_content(key: str, fn=content) -> np.ndarray:
    """Content under the image side `fn` of a swatch (its description as
    canonical JSON), shared by every encoder of the process, as in version 1."""
    out = fn(render_swatch(json.loads(key))[None])[0]
    out.flags.writeable = False
    return out


AVERAGE_WORDS = ("building",)
"""Version 3's canonical phrases that embed as the average of the part phrases."""


class SyntheticEncoderV3(SyntheticEncoderV2):
    """Stand-in for CLIP, version 3: version 2 whose "building" is the average word
    of the scene's part phrases (module docstring; issue 41, amendment 4)."""

    name = "synthetic-v3"
    average_words = AVERAGE_WORDS

    def _text_content(self, phrase: str) -> np.ndarray:
        key = phrase.strip().lower()
        if key in AVERAGE_WORDS and self._world is not None and self._parts:
            return self._average_word(key)
        return super()._text_content(phrase)

    def _average_word(self, key: str) -> np.ndarray:
        """m + sqrt(1 - |m|^2) n: m the mean content of the part phrases, n a fixed
        seeded unit vector orthogonal to m. Its cosine with any content c is
        c.m (the mean of the part phrases' cosines with c) plus n's chance
        cosine with c, about N(0, (1 - |m|^2) / 512)."""
        parts = sorted(self._parts)
        m = np.mean([SyntheticEncoderV2._text_content(self, p) for p in parts], axis=0)
        n = np.random.default_rng([SEED + 7, *key.encode()]).standard_normal(DIM)
        mm = float(m @ m)
        if mm > 0:
            n = n - (n @ m) / mm * m
        n = n / np.sqrt(n @ n)
        return m + np.sqrt(max(0.0, 1.0 - mm)) * n

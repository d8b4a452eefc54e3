"""The stand-in for CLIP (docs/standin.md).

Image side: a fixed function of pixels. A crop is reduced to 32 x 32 (area
average; pixels that are exactly black count as outside the mask), and pooled
statistics are taken over the inside: colour (mean RGB, chromaticity, an
opponent-colour histogram, a luminance histogram) and texture on the
contrast-normalised luminance (six seeded random 3 x 3 filters at two scales
with |.| and ReLU, an orientation histogram, fine-scale energy). The statistics
are standardised with fixed means and scales (measured once on a seeded bank of
random swatches), weighted per group, projected to 512-d with a seeded Gaussian
matrix and L2-normalised: the "content" vector.

Text side: `vocabulary.json` maps a phrase to a canonical swatch (a texture under
neutral light, or the neutral sky); its content is the image side's content of
the rendered swatch. Generic phrases ("object", "things", ...) are fixed weighted
mixtures of swatches, and any other phrase is a seeded random unit vector (seed
from sha256 of the phrase).

Like CLIP, the two modalities sit apart: embedding = normalise(GAP * u_m + content)
with u_image and u_text fixed unit vectors orthogonal to every content vector. So
image-text cosines lie in about [-0.3, 0.3] and image-image cosines in [0.7, 1],
which keeps softmax relevancy at temperature 10 in CLIP's regime. Rankings of
texts for an image are unchanged by the offset.

Everything runs in float64 numpy with explicit, fixed-order sums (no BLAS), and
per-crop OpenCV resizes, so outputs are bitwise identical across runs, processes
and batch sizes.
"""

from __future__ import annotations

import functools
import hashlib
import json
import logging
from pathlib import Path

import cv2
import numpy as np

from ptovs.synthetic.world import (
    Texture,
    neutral_light,
    random_texture,
    render_swatch,
    sky_swatch,
)

logger = logging.getLogger(__name__)

DIM = 512
SEED = 20250101
GAP = 1.5  # weight of the modality offset
GENERIC_PHRASES = (
    "object",
    "things",
    "stuff",
    "texture",
    "scene",
    "building",
    "background",
)
_R = 32  # internal resolution
_CHUNK = 32  # small chunks keep the [B, 32, 32] temporaries in cache
_N_FILT = 6
_OPP = np.linspace(-0.8, 0.8, 5)
_LBIN = np.linspace(0.05, 0.95, 6)
_ORI = np.arange(6) * (np.pi / 6)
# (name, size, weight): weights set how much each group moves the embedding
_GROUPS = (
    ("rgb", 3, 1.0),
    ("lum", 2, 0.6),
    ("chroma", 3, 1.2),
    ("opponent_hist", 25, 1.5),
    ("lum_hist", 6, 0.6),
    ("filters", 4 * _N_FILT, 1.0),
    ("orientation", 7, 0.8),
    ("fine", 3, 0.5),
)
N_FEATURES = sum(g[1] for g in _GROUPS)


# ---------------------------------------------------------------- features --


def _block_mean(x: np.ndarray) -> np.ndarray:
    """Area average of one [S, S(, C)] image to [_R, _R(, C)], float64."""
    S = x.shape[0]
    if S % _R or x.shape[1] != S:
        return cv2.resize(x, (_R, _R), interpolation=cv2.INTER_AREA).astype(np.float64)
    f = S // _R
    c = x.shape[2] if x.ndim == 3 else 1
    # fixed-order float32 block sums (numpy reduces non-last axes sequentially)
    y1 = x.reshape(_R, f, S * c).sum(axis=1).reshape(_R, _R, f, c)
    y = y1[:, :, 0]
    for k in range(1, f):  # numpy is slow reducing a short middle axis
        y = y + y1[:, :, k]
    y = y.astype(np.float64) / (f * f)
    return y if x.ndim == 3 else y[..., 0]


def _downsample(crops: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    B = len(crops)
    col = np.empty((B, _R, _R, 3))
    w = np.empty((B, _R, _R))
    for b in range(B):
        x = np.ascontiguousarray(crops[b], dtype=np.float32)
        # inside unless exactly black: for channels in [0, 1], gray > 0 iff any
        # channel > 0 (cv2 is much faster than a numpy max over 3 channels)
        valid = (cv2.cvtColor(x, cv2.COLOR_RGB2GRAY) > 0).astype(np.float32)
        col[b] = _block_mean(x)
        w[b] = _block_mean(valid)
    return col, w


def _shift_pad(x: np.ndarray, r: int) -> np.ndarray:
    return np.pad(x, ((0, 0), (r, r), (r, r)), mode="edge")


def _erode(m: np.ndarray) -> np.ndarray:
    p = np.pad(m, ((0, 0), (1, 1), (1, 1)))
    n = m.shape[1]
    out = m.copy()
    for dy in range(3):
        for dx in range(3):
            out = np.minimum(out, p[:, dy : dy + n, dx : dx + n])
    return out


@functools.lru_cache(maxsize=1)
def _filters() -> np.ndarray:
    k = np.random.default_rng(SEED).standard_normal((_N_FILT, 3, 3))
    k -= k.mean(axis=(1, 2), keepdims=True)
    return k / np.sqrt((k * k).sum(axis=(1, 2), keepdims=True))


def _hat(x: np.ndarray, centres: np.ndarray, k: int) -> np.ndarray:
    """Linear-interpolation weight of bin k (bins partition unity after clipping)."""
    step = centres[1] - centres[0]
    xc = np.clip(x, centres[0], centres[-1])
    return np.maximum(1.0 - np.abs(xc - centres[k]) / step, 0.0)


def _pool(v: np.ndarray, m: np.ndarray, msum: np.ndarray) -> np.ndarray:
    return (v * m).sum(axis=(1, 2)) / msum


def _texture_feats(Ln: np.ndarray, mi: np.ndarray) -> list[np.ndarray]:
    """Random-filter responses (|r| and relu(r)) pooled over the interior."""
    n = Ln.shape[1]
    msum = mi.sum(axis=(1, 2)) + 1e-9
    p = _shift_pad(Ln, 1)
    out_abs, out_pos = [], []
    for k in _filters():
        r = np.zeros_like(Ln)
        for dy in range(3):
            for dx in range(3):
                r = r + k[dy, dx] * p[:, dy : dy + n, dx : dx + n]
        out_abs.append(_pool(np.abs(r), mi, msum))
        out_pos.append(_pool(np.maximum(r, 0.0), mi, msum))
    return out_abs + out_pos


def _box3(x: np.ndarray) -> np.ndarray:
    n = x.shape[1]
    p = _shift_pad(x, 1)
    acc = np.zeros_like(x)
    for dy in range(3):
        for dx in range(3):
            acc = acc + p[:, dy : dy + n, dx : dx + n]
    return acc / 9.0


def _half(x: np.ndarray) -> np.ndarray:
    B, n = x.shape[0], x.shape[1] // 2
    return x.reshape(B, n, 2, n, 2).mean(axis=(2, 4))


def raw_features(crops: np.ndarray) -> np.ndarray:
    """Unstandardised pixel statistics of crops.

    Args:
        crops: [B, S, S, 3] float RGB in [0, 1]; exact black is outside the mask.

    Returns:
        [B, N_FEATURES] float64.
    """
    col, w = _downsample(crops)
    m = (w >= 0.5).astype(np.float64)
    msum = m.sum(axis=(1, 2)) + 1e-9
    c = np.clip(col / np.maximum(w, 1e-6)[..., None], 0.0, 1.0)  # undo the edge bleed
    L = 0.299 * c[..., 0] + 0.587 * c[..., 1] + 0.114 * c[..., 2]
    feats: list[np.ndarray] = []
    feats += [_pool(c[..., k], m, msum) for k in range(3)]
    mu = _pool(L, m, msum)
    sd = np.sqrt(_pool((L - mu[:, None, None]) ** 2, m, msum))
    feats += [mu, sd]
    s = c[..., 0] + c[..., 1] + c[..., 2] + 0.06
    feats += [_pool(c[..., k] / s, m, msum) for k in range(3)]
    # opponent colour, divided by luminance: a 5 x 5 histogram with linear
    # (hat) binning, and a 6-bin luminance histogram
    o1 = (c[..., 0] - c[..., 1]) / (L + 0.05)
    o2 = (0.5 * (c[..., 0] + c[..., 1]) - c[..., 2]) / (L + 0.05)
    B, nb = len(c), len(_OPP)
    g1 = np.stack([_hat(o1, _OPP, k) * m for k in range(nb)], 1).reshape(B, nb, -1)
    g2 = np.stack([_hat(o2, _OPP, k) for k in range(nb)], 1).reshape(B, nb, -1)
    # einsum without optimize runs numpy's own loops: fixed order, no BLAS
    h = np.einsum("bip,bjp->bij", g1, g2).reshape(B, nb * nb) / msum[:, None]
    feats += list(h.T)
    feats += [_pool(_hat(L, _LBIN, k), m, msum) for k in range(len(_LBIN))]
    # texture: contrast-normalised luminance over the eroded interior
    mi = _erode((w >= 0.99).astype(np.float64))
    few = mi.sum(axis=(1, 2)) < 6
    mi[few] = m[few]
    Ln = (L - mu[:, None, None]) / (sd[:, None, None] + 0.04) * m
    mi2 = _erode((_half(mi) >= 0.99).astype(np.float64))
    few2 = mi2.sum(axis=(1, 2)) < 3
    mi2[few2] = (_half(m) > 0)[few2]
    Ln2 = _half(Ln)
    ta, tb = _texture_feats(Ln, mi), _texture_feats(Ln2, mi2)
    feats += ta[:_N_FILT] + tb[:_N_FILT] + ta[_N_FILT:] + tb[_N_FILT:]
    p = _shift_pad(Ln, 1)
    n = _R
    gx = 0.5 * (p[:, 1 : n + 1, 2:] - p[:, 1 : n + 1, :-2])
    gy = 0.5 * (p[:, 2:, 1 : n + 1] - p[:, :-2, 1 : n + 1])
    mag2 = gx * gx + gy * gy
    mag = np.sqrt(mag2)
    # orientation from the doubled angle: no atan2, cos(2(theta - phi)) directly
    c2 = (gx * gx - gy * gy) / (mag2 + 1e-12)
    s2 = 2.0 * gx * gy / (mag2 + 1e-12)
    msum_i = mi.sum(axis=(1, 2)) + 1e-9
    wm = mi * mag
    wsum = wm.sum(axis=(1, 2)) + 1e-9
    for phi in _ORI:
        b = np.maximum(c2 * np.cos(2 * phi) + s2 * np.sin(2 * phi), 0.0)
        b = b * b
        b = b * b
        feats.append((b * wm).sum(axis=(1, 2)) / wsum)
    feats.append(_pool(mag, mi, msum_i))
    feats.append(_pool(np.abs(Ln - _box3(Ln)), mi, msum_i))
    feats.append(_pool(np.abs(Ln2 - _box3(Ln2)), mi2, mi2.sum(axis=(1, 2)) + 1e-9))
    feats.append(sd / (mu + 0.05))
    out = np.stack(feats, axis=1)
    assert out.shape[1] == N_FEATURES
    return out


# ------------------------------------------------------------ fixed params --


def _bank_swatches() -> list[np.ndarray]:
    """Seeded random swatches, some masked to crop-like shapes."""
    rng = np.random.default_rng(SEED + 2)
    out = []
    yy, xx = np.mgrid[0:224, 0:224] / 223.0 - 0.5
    for k in range(96):
        tex = random_texture(rng, 1.0, sat=(0.0, 0.8), val=(0.2, 0.95))
        desc = {
            "kind": "texture",
            "texture": tex.to_dict(),
            "origin": [0.0, 0.0, 0.0],
            "e1": [1.0, 0.0, 0.0],
            "e2": [0.0, 0.0, -1.0],
            "extent": float(rng.uniform(0.5, 2.0)),
            "light": float(rng.uniform(0.3, 1.2)),
            "gamma": float(rng.uniform(1.9, 2.5)),
            "render_px": int(rng.choice([16, 24, 32, 48, 64])),
        }
        img = render_swatch(desc)
        if k % 2:
            a, b = rng.uniform(0.15, 0.5, 2)
            img = img * ((xx / a) ** 2 + (yy / b) ** 2 <= 1)[..., None]
        out.append(img.astype(np.float32))
    for _ in range(8):
        out.append(render_swatch(sky_swatch()) * np.float32(rng.uniform(0.3, 1.0)))
    return out


@functools.lru_cache(maxsize=1)
def _fixed() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Standardisation (mean, scale), group weights, projection and modality offsets."""
    f = raw_features(np.stack(_bank_swatches()))
    mean = f.mean(axis=0)
    scale = np.maximum(f.std(axis=0), 1e-3)
    gw = np.concatenate([np.full(n, wt / np.sqrt(n)) for _, n, wt in _GROUPS])
    rng = np.random.default_rng(SEED + 3)
    P = rng.standard_normal((N_FEATURES, DIM)) / np.sqrt(DIM)
    basis: list[np.ndarray] = []
    for row in P:  # Gram-Schmidt, explicit sums
        v = row.copy()
        for b in basis:
            v = v - (v * b).sum() * b
        basis.append(v / np.sqrt((v * v).sum()))
    offsets = []
    for _ in range(2):
        v = rng.standard_normal(DIM)
        for b in basis + offsets:
            v = v - (v * b).sum() * b
        offsets.append(v / np.sqrt((v * v).sum()))
    return mean, scale, gw, P, np.stack(offsets)


def _normalise(x: np.ndarray) -> np.ndarray:
    return x / np.sqrt((x * x).sum(axis=-1, keepdims=True)).clip(1e-12)


def content(crops: np.ndarray) -> np.ndarray:
    """Modality-free unit content vectors of crops [B, S, S, 3]; returns [B, 512] float64."""
    mean, scale, gw, P, _ = _fixed()
    out = np.empty((len(crops), DIM))
    for s in range(0, len(crops), _CHUNK):
        z = (raw_features(crops[s : s + _CHUNK]) - mean) / scale * gw
        acc = np.zeros((len(z), DIM))
        for k in range(N_FEATURES):  # fixed-order projection, batch independent
            acc += z[:, k : k + 1] * P[k]
        out[s : s + _CHUNK] = _normalise(acc)
    return out


def _embed(c: np.ndarray, modality: int) -> np.ndarray:
    u = _fixed()[4][modality]
    return _normalise(GAP * u + c).astype(np.float32)


@functools.lru_cache(maxsize=1024)
def _swatch_content(key: str) -> np.ndarray:
    """Content of a swatch (its description as canonical JSON), shared by every
    encoder of the process: a swatch is a pure function of its description."""
    out = content(render_swatch(json.loads(key))[None])[0]
    out.flags.writeable = False
    return out


def phrase_seed(phrase: str) -> int:
    """Stable seed of a phrase (sha256; never Python's salted hash())."""
    return int.from_bytes(hashlib.sha256(phrase.encode("utf-8")).digest()[:8], "little")


# --------------------------------------------------------------- vocabulary --


def _ground_default() -> dict:
    tex = Texture("noise", (0.55, 0.53, 0.5), (0.42, 0.4, 0.38), 1.0, seed=7)
    return {
        "kind": "texture",
        "texture": tex.to_dict(),
        "origin": [0.0, 0.0, 0.0],
        "e1": [1.0, 0.0, 0.0],
        "e2": [0.0, 1.0, 0.0],
        "extent": 6.0,
        "light": neutral_light(),
        "gamma": 2.2,
        "render_px": 48,
    }


def generic_vocabulary(
    sky: dict | None = None, ground: dict | None = None, render_px: int = 48
) -> dict[str, list[dict]]:
    """Fixed mixtures for generic phrases ("object", "things", "stuff", ...).

    Args:
        sky: the scene's sky swatch (default: the neutral sky).
        ground: the scene's ground swatch (default: grey paving).
        render_px: swatch resolution of the fixed bank.

    Returns:
        phrase -> list of {"weight": w, "swatch": description}.
    """
    sky = sky or sky_swatch()
    ground = ground or _ground_default()
    rng = np.random.default_rng(SEED + 1)
    bank = []
    for k in range(8):
        stone = k >= 4
        tex = random_texture(
            rng,
            2.0,
            hue=float(k * 45.0 + 10.0),
            sat=(0.05, 0.2) if stone else (0.25, 0.6),
            val=(0.55, 0.8) if stone else (0.4, 0.85),
        )
        bank.append(
            {
                "kind": "texture",
                "texture": tex.to_dict(),
                "origin": [0.0, 0.0, 0.0],
                "e1": [1.0, 0.0, 0.0],
                "e2": [0.0, 0.0, -1.0],
                "extent": 2.0,
                "light": neutral_light(),
                "gamma": 2.2,
                "render_px": render_px,
            }
        )

    def mix(items: list[dict]) -> list[dict]:
        return [{"weight": 1.0, "swatch": s} for s in items]

    return {
        "object": mix(bank[0:6]),
        "things": mix(bank[2:8]),
        "stuff": mix(bank[0::2] + [ground]),
        "texture": mix(bank[1::2]),
        "scene": mix([sky, ground] + bank[0:2]),
        "building": mix(bank[4:8]),
        "background": mix([sky, ground]),
    }


class SyntheticEncoder:
    """Deterministic stand-in for CLIP that sees only pixels.

    Args:
        vocabulary: path to vocabulary.json, its dict ({"phrases": {phrase:
            swatch}, "generic": {phrase: [{"weight", "swatch"}]}, "styles":
            {style: [{"weight", "swatch"}]}}), or None
            (generic phrases and "sky" only; other phrases are random).
    """

    name = "synthetic"
    dim = DIM

    def __init__(self, vocabulary: str | Path | dict | None = None) -> None:
        if vocabulary is None:
            vocab: dict = {"phrases": {}}
        elif isinstance(vocabulary, dict):
            vocab = vocabulary
        else:
            path = Path(vocabulary)
            if not path.is_file():
                raise FileNotFoundError(f"vocabulary {path} not found")
            vocab = json.loads(path.read_text())
        if not isinstance(vocab.get("phrases", {}), dict):
            raise ValueError(
                "vocabulary['phrases'] must map phrase -> swatch description"
            )
        self._vocab = vocab  # as read: version 5 reads its world and parts from it
        self._phrases: dict[str, dict] = dict(vocab.get("phrases", {}))
        self._lower = {k.strip().lower(): v for k, v in self._phrases.items()}
        generic = vocab.get("generic") or generic_vocabulary()
        self._generic = {k.strip().lower(): v for k, v in generic.items()}
        self._styles: dict[str, list[dict]] = dict(vocab.get("styles", {}))
        # a style embeds like a generic phrase: a normalised mixture of swatches
        self._generic.update({k.strip().lower(): v for k, v in self._styles.items()})

    @property
    def phrases(self) -> list[str]:
        """Phrases with a canonical swatch."""
        return list(self._phrases)

    @property
    def styles(self) -> list[str]:
        """The scene's candidate style names (`synthetic.generate.scene_styles`)."""
        return list(self._styles)

    def knows(self, phrase: str) -> bool:
        """Whether the phrase has a swatch (vocabulary, generic mixture or "sky").

        Any other phrase embeds as a seeded random vector, which no image
        matches: `query` refuses such phrases instead of returning noise.
        """
        key = phrase.strip()
        return (
            key in self._phrases
            or key.lower() in self._lower
            or key.lower() in self._generic
            or key.lower() == "sky"
        )

    def encode_images(self, crops: np.ndarray) -> np.ndarray:
        """Embed crops.

        Args:
            crops: [B, S, S, 3] float32 RGB in [0, 1] (prepare_crop output).

        Returns:
            [B, 512] float32 unit rows.
        """
        crops = np.asarray(crops)
        if crops.ndim != 4 or crops.shape[-1] != 3:
            raise ValueError(f"crops must be [B, S, S, 3], got {crops.shape}")
        if len(crops) == 0:
            return np.zeros((0, DIM), np.float32)
        return _embed(content(crops), 0)

    def encode_texts(self, texts: list[str]) -> np.ndarray:
        """Embed raw phrases.

        Args:
            texts: Q phrases (no prompt template).

        Returns:
            [Q, 512] float32 unit rows.
        """
        if isinstance(texts, str):
            raise ValueError("texts must be a list of phrases, not a single string")
        if len(texts) == 0:
            return np.zeros((0, DIM), np.float32)
        return _embed(np.stack([self._text_content(t) for t in texts]), 1)

    def _swatch_content(self, desc: dict) -> np.ndarray:
        return _swatch_content(json.dumps(desc, sort_keys=True))

    def _text_content(self, phrase: str) -> np.ndarray:
        key = phrase.strip()
        desc = self._phrases.get(key, self._lower.get(key.lower()))
        if desc is not None:
            return self._swatch_content(desc)
        if key.lower() in self._generic:
            acc = np.zeros(DIM)
            for item in self._generic[key.lower()]:
                acc = acc + float(item["weight"]) * self._swatch_content(item["swatch"])
            return _normalise(acc)
        if key.lower() == "sky":
            return self._swatch_content(sky_swatch())
        rng = np.random.default_rng(phrase_seed(phrase))
        return _normalise(rng.standard_normal(DIM))

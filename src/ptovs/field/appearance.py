"""Choosing the novel appearances a scene is rendered under (docs/method.md §3).

The paper picks N−1 target images j under two constraints: their self-render is
good (‖f_render(I_j, l_j) − I_j‖ < ε_q) and they are diverse (Manhattan distance of
embeddings > ε_d for every selected pair); it gives no values. ptovs derives both
from the scene: ε_q is the `quality_quantile` quantile of the per-pixel mean L1 of
every train image's self-render, ε_d starts at the median pairwise L1 distance of
the candidates' embeddings and is lowered by deciles (logged) until N−1 targets
exist; with fewer than N−1 candidates, all candidates are used and the report says
so. The authors' hard-coded ids for the seven PT-OVS scenes are `PAPER_TARGETS`.

Which error ε_q thresholds is `QUALITY_METRICS`: the paper's words give an absolute
L1 error, and an absolute error is smallest on dark and colourless photos (little
signal, little error), so those qualify first whatever their render's fidelity.
"l1-relative" divides by the photo's mean intensity; "dssim" (1 − SSIM of the
luminance) ignores brightness and contrast both.
"""

from __future__ import annotations

import hashlib
import logging
import re

import numpy as np

log = logging.getLogger(__name__)

# Supplement / authors' code (in_the_wild_renderer), novel 1..3 per scene.
PAPER_TARGETS = {
    "brandenburg": (
        "15080601_1551250100",
        "01738801_5114523193",
        "59826471_8014732885",
    ),
    "trevi": ("15457887_10227170235", "45182190_511249303", "80288369_2336500045"),
    "buckingham": ("04781012_3416228976", "11220321_6429817645", "42080522_204096736"),
    "notredame": ("73272860_3039447416", "03158689_7322662838", "72005271_4157221941"),
    "pantheon": ("00318896_2265892479", "02882184_6968792622", "04938646_2803242734"),
    "tajmahal": ("75255818_297567547", "76552970_5828212829", "86954812_2533844894"),
    "todaiji": ("08855480_12135166146", "10449189_312833816", "36907783_8321442187"),
}
DIVERSITY_DECILES = (0.5, 0.4, 0.3, 0.2, 0.1, 0.0)
QUALITY_METRICS = ("l1", "l1-relative", "dssim")
ORDERS = ("draw", "names")
_SSIM_C1, _SSIM_C2 = 0.01**2, 0.03**2  # Wang et al. 2004, for values in [0, 1]


def _luma(img: np.ndarray) -> np.ndarray:
    x = np.asarray(img, np.float64)
    return x @ np.array([0.299, 0.587, 0.114]) if x.ndim == 3 else x


def ssim(a: np.ndarray, b: np.ndarray, sigma: float = 1.5) -> float:
    """Mean SSIM of two images' luminance ([H, W, 3] or [H, W], values in [0, 1]),
    Gaussian window of `sigma` px, float64. 1 for identical images, constant
    ones included."""
    import cv2

    x, y = _luma(a), _luma(b)
    if x.shape != y.shape:
        raise ValueError(f"ssim: shapes differ, {x.shape} and {y.shape}")
    if x.size == 0:
        raise ValueError("ssim: empty image")

    def blur(v: np.ndarray) -> np.ndarray:
        return cv2.GaussianBlur(v, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)

    mx, my = blur(x), blur(y)
    vx = np.maximum(blur(x * x) - mx * mx, 0.0)
    vy = np.maximum(blur(y * y) - my * my, 0.0)
    cxy = blur(x * y) - mx * my
    s = ((2 * mx * my + _SSIM_C1) * (2 * cxy + _SSIM_C2)) / (
        (mx * mx + my * my + _SSIM_C1) * (vx + vy + _SSIM_C2)
    )
    return float(s.mean())


def render_error(render: np.ndarray, photo: np.ndarray, metric: str = "l1") -> float:
    """How far a self-render is from its photo (lower is better), by `metric`
    (`QUALITY_METRICS`): "l1" the mean absolute error (the paper's ε_q),
    "l1-relative" that over the photo's mean intensity, "dssim" 1 − SSIM."""
    r = np.asarray(render, np.float64)
    p = np.asarray(photo, np.float64)
    if r.shape != p.shape:
        raise ValueError(f"render and photo differ in shape: {r.shape}, {p.shape}")
    if metric == "l1":
        return float(np.abs(r - p).mean())
    if metric == "l1-relative":
        return float(np.abs(r - p).mean() / max(float(p.mean()), 1.0 / 255.0))
    if metric == "dssim":
        return 1.0 - ssim(r, p)
    raise ValueError(f"quality metric {metric!r}: expected one of {QUALITY_METRICS}")


def paper_targets(scene_name: str) -> tuple[str, ...] | None:
    """The paper's ids if the scene name names one of the seven PT-OVS scenes."""
    key = re.sub(r"[^a-z]", "", scene_name.lower())
    for name, ids in PAPER_TARGETS.items():
        if key.startswith(name):
            return ids
    return None


def pairwise_l1(emb: np.ndarray) -> np.ndarray:
    """[M, M] Manhattan distances between embedding rows (float64)."""
    e = np.asarray(emb, np.float64)
    return np.abs(e[:, None, :] - e[None, :, :]).sum(-1)


def min_pairwise_l1(emb: np.ndarray) -> float | None:
    """Smallest Manhattan distance between two rows (None for fewer than 2)."""
    if len(emb) < 2:
        return None
    d = pairwise_l1(emb)
    return float(d[~np.eye(len(d), dtype=bool)].min())


def _greedy(dist: np.ndarray, order: np.ndarray, eps: float, k: int) -> list[int]:
    chosen: list[int] = []
    for j in order:
        if all(dist[j, c] > eps for c in chosen):
            chosen.append(int(j))
            if len(chosen) == k:
                break
    return chosen


def name_order(names: list[str], seed: int, attempt: int) -> np.ndarray:
    """Indices of `names` sorted by a seeded hash of each name: a photo's place
    depends on its own name only, not on which other photos are candidates."""
    keys = [
        hashlib.blake2b(f"{seed}:{attempt}:{n}".encode(), digest_size=8).digest()
        for n in names
    ]
    return np.array(sorted(range(len(names)), key=keys.__getitem__), dtype=np.int64)


def select_targets(
    names: list[str],
    quality: np.ndarray,  # [M] per-pixel mean L1 of each image's self-render
    embeddings: np.ndarray,  # [M, D]
    k: int,
    quality_quantile: float = 0.25,
    seed: int = 0,
    tries: int = 200,
    use_quality: bool = True,
    use_diversity: bool = True,
    order: str = "draw",
) -> tuple[list[str], dict]:
    """Pick up to k target images by render quality and embedding diversity.

    Args:
        names: train image names, aligned with quality and embeddings.
        quality: q_j (lower is better).
        embeddings: l_j.
        k: targets wanted (N − 1).
        quality_quantile: ε_q = this quantile of q.
        seed: seeds the rejection sampling.
        tries: random orders tried per ε_d level.
        use_quality: False drops ε_q: every image is a candidate (Table 4).
        use_diversity: False drops ε_d: a seeded random draw among the
            candidates (Table 4).
        order: the order the greedy draw visits candidates in: "draw" a seeded
            permutation of the candidates (one photo entering or leaving them
            reorders all), "names" a seeded hash of each name (`name_order`: a
            photo crossing ε_q changes the choice only where it wins a place).

    Returns:
        The chosen names (≤ k) and a report: ε_q, candidates, the ε_d levels
        tried, the final ε_d, each target's q and the minimum pairwise distance.
    """
    q = np.asarray(quality, np.float64)
    if order not in ORDERS:
        raise ValueError(f"order {order!r}: expected one of {ORDERS}")
    if len(names) != len(q) or len(q) != len(embeddings):
        raise ValueError("names, quality and embeddings must align")
    if k < 0:
        raise ValueError(f"k must be >= 0, got {k}")
    report: dict = {
        "k_requested": k,
        "quality_quantile": quality_quantile if use_quality else None,
        "diversity": use_diversity,
        "order": order,
    }
    if k == 0 or len(q) == 0:
        report.update(chosen=[], eps_q=None, candidates=0, note="nothing to choose")
        return [], report
    if use_quality:
        eps_q = float(np.quantile(q, quality_quantile))
        cand = np.flatnonzero(q < eps_q)
        if cand.size == 0:  # ties (e.g. every render equally good): take the ties
            cand = np.flatnonzero(q <= eps_q)
    else:
        eps_q, cand = None, np.arange(len(q))
    dist = pairwise_l1(np.asarray(embeddings)[cand])
    off = dist[~np.eye(len(cand), dtype=bool)]
    if use_diversity:
        levels = [float(np.quantile(off, d)) for d in DIVERSITY_DECILES if off.size]
        levels = (levels or [0.0]) + [0.0]  # last: any two distinct embeddings
    else:
        levels, tries = [-1.0], 1  # any candidates: one seeded random order
    rng = np.random.default_rng(seed)
    best: list[int] = []
    best_eps = levels[0]
    tried = []
    want = min(k, len(cand))
    cand_names = [names[c] for c in cand]
    named: dict[int, np.ndarray] = {}  # an attempt's name order, the same at every ε_d
    for eps in levels:
        tried.append(round(eps, 6))
        for attempt in range(tries):
            if order == "names":
                if attempt not in named:
                    named[attempt] = name_order(cand_names, seed, attempt)
                visit = named[attempt]
            else:
                visit = rng.permutation(len(cand))
            got = _greedy(dist, visit, eps, want)
            if len(got) > len(best):
                best, best_eps = got, eps
            if len(got) == want:
                break
        if len(best) == want:
            break
        log.info("target selection: no %d targets at ε_d = %.4g, lowering", want, eps)
    chosen = [names[cand[i]] for i in best]
    min_d = min_pairwise_l1(np.asarray(embeddings)[cand[best]])
    report.update(
        eps_q=eps_q,
        candidates=int(cand.size),
        eps_d_tried=tried,
        eps_d=best_eps if use_diversity else None,
        chosen=chosen,
        quality={n: float(q[cand[i]]) for n, i in zip(chosen, best, strict=True)},
        min_pairwise_l1=min_d,
    )
    if len(chosen) < k:
        report["note"] = (
            f"only {len(chosen)} of {k} novel appearances pass the quality "
            f"constraint ({cand.size} candidates"
            + (f" below ε_q = {eps_q:.4g}" if eps_q is not None else "")
            + "); using what passes"
        )
        log.warning("%s", report["note"])
    return chosen, report

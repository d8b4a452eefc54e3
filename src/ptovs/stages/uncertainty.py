"""Transient and appearance uncertainty per training view (docs/method.md §5).

Reads extract-features. Per pixel and level, with F the segment feature there:

    U_T = mean_c (F_self − F_orig)²                       (transient: the render
                                                          cannot show occluders)
    U_A = mean_c mean_m (F_m − F̄)²,  m ∈ members          (appearance spread)

members = the N−1 novel renders and the self render (the paper; `ua_members =
"novel"` is the authors' code). Each is averaged over the levels valid at the
pixel: a level counts only where every image involved has a segment there
(`seg_invalid = "last_row"` reproduces the code reading the table's last row).
Computed per unique tuple of segment ids, never on dense 512-d maps:
mean_c (a − b)² = (‖a‖² + ‖b‖² − 2a·b)/D and mean_m ‖F_m − F̄‖² = mean_m ‖F_m‖² − ‖F̄‖².

Both maps are min–max normalised per scene over every train view's valid pixels
(two passes: the range first, then the maps; constant maps become 0, never NaN).
Pixels with no valid level are set to 1 (fully uncertain: no weight downstream).
Per view: `u_t`, `u_a` [H, W] float16. Root: `range_json`. PNG previews of the
first `previews` views go beside the artifact (`<key>.previews/`).
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from ptovs.artifacts import Artifact, json_dataset
from ptovs.checkpoint import Checkpoint
from ptovs.features import SegmentFeatures, tuple_ids, view_apps
from ptovs.registry import upstream
from ptovs.stage import stage_command

log = logging.getLogger(__name__)

NAME = "uncertainty"
VERSION = 1
TINY_RANGE = 1e-12  # below this the scene's maps are constant: normalise to 0


@dataclass(frozen=True)
class Config:
    ua_members: Literal["novel+self", "novel"] = "novel+self"
    """Which renders enter U_A: the paper's "novel+self" or the authors' "novel"."""
    seg_invalid: Literal["exclude", "last_row"] = "exclude"
    """Pixels no segment covers: excluded, or the authors' bug (the table's last row)."""
    previews: int = 4
    """PNG previews written for this many views (0: none)."""


@dataclass(frozen=True)
class Inputs:
    features: Artifact = upstream("extract-features")


def _rows(f: SegmentFeatures, level: int, seg_invalid: str) -> np.ndarray:
    s = f.seg[level].astype(np.int64).ravel()
    if seg_invalid == "last_row" and len(f.table):
        s = np.where(s < 0, len(f.table) - 1, s)  # the code's table[-1]
    return s


def _sq_norms(table: np.ndarray) -> np.ndarray:
    t = table.astype(np.float32)
    return (t * t).sum(1)


def level_maps(
    feats: dict[str, SegmentFeatures], members: list[str], level: int, seg_invalid: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """U_T, U_A and their validity at one level, flat [H·W] float32 / bool."""
    fo, fs = feats["orig"], feats["self"]
    d = fo.table.shape[1]
    ro, rs = _rows(fo, level, seg_invalid), _rows(fs, level, seg_invalid)
    ok_t = (ro >= 0) & (rs >= 0)
    ut = np.zeros(ro.shape, np.float32)
    if ok_t.any():  # Eq. U_T per unique (orig row, self row) pair
        both = np.stack((ro[ok_t], rs[ok_t]), 1)
        first, inv = tuple_ids(both)
        pairs = both[first]
        a = fo.table[pairs[:, 0]].astype(np.float32)
        b = fs.table[pairs[:, 1]].astype(np.float32)
        sq = _sq_norms(a) + _sq_norms(b) - 2.0 * (a * b).sum(1)
        ut[ok_t] = np.maximum(sq, 0.0)[inv.ravel()] / d
    ua = np.zeros(ro.shape, np.float32)
    if not members:  # nothing varies the appearance: no appearance uncertainty
        return ut, ua, ok_t, ro >= 0
    rows = np.stack([_rows(feats[m], level, seg_invalid) for m in members], 1)  # [P, M]
    ok_a = (rows >= 0).all(1)
    if ok_a.any():  # Eq. U_A per unique tuple of member rows
        first, inv = tuple_ids(rows[ok_a])
        tuples = rows[ok_a][first]
        f = np.stack(
            [
                feats[m].table[tuples[:, j]].astype(np.float32)
                for j, m in enumerate(members)
            ],
            1,
        )  # [T, M, D]
        mean = f.mean(1)
        var = (f * f).sum(2).mean(1) - (mean * mean).sum(1)
        ua[ok_a] = np.maximum(var, 0.0)[inv.ravel()] / d
    return ut, ua, ok_t, ok_a


def raw_maps(
    view: dict[str, np.ndarray], config: Config
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Level-averaged U_T, U_A [H, W] float32 and validity [H, W] bool for one view."""
    apps = view_apps(view)
    if "orig" not in apps or "self" not in apps:
        raise ValueError(
            f"uncertainty needs features of the original and the self render, have "
            f"{apps}; run extract-features with images = 'all'"
        )
    feats = {a: SegmentFeatures.from_view(view, a) for a in apps}
    novel = [a for a in apps if a not in ("orig", "self")]
    members = novel + (["self"] if config.ua_members == "novel+self" else [])
    n_levels, h, w = feats["orig"].seg.shape
    sums = np.zeros((2, h * w), np.float64)
    counts = np.zeros((2, h * w), np.int32)
    for lv in range(n_levels):
        ut, ua, ok_t, ok_a = level_maps(feats, members, lv, config.seg_invalid)
        sums[0] += np.where(ok_t, ut, 0.0)
        sums[1] += np.where(ok_a, ua, 0.0)
        counts[0] += ok_t
        counts[1] += ok_a
    mean = sums / np.maximum(counts, 1)
    valid = counts > 0
    return (
        mean[0].reshape(h, w).astype(np.float32),
        mean[1].reshape(h, w).astype(np.float32),
        valid[0].reshape(h, w),
        valid[1].reshape(h, w),
    )


def normalise(u: np.ndarray, valid: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """(u − lo)/(hi − lo) on valid pixels, 1 elsewhere; float16, finite, in [0, 1]."""
    span = hi - lo
    if not np.isfinite(span) or span <= TINY_RANGE:  # constant over the scene
        out = np.zeros(u.shape, np.float32)
    else:
        out = np.clip((u.astype(np.float64) - lo) / span, 0.0, 1.0).astype(np.float32)
    out[~valid] = 1.0
    return out.astype(np.float16)


def scene_range(art: Artifact, config: Config) -> dict:
    """Pass 1: min and max of U_T and U_A over all views' valid pixels."""
    lo, hi = [np.inf, np.inf], [-np.inf, -np.inf]
    n_valid = [0, 0]
    for name in art.names():
        maps = raw_maps(art[name], config)
        for i in range(2):
            vals = maps[i][maps[2 + i]]
            if vals.size:
                lo[i] = min(lo[i], float(vals.min()))
                hi[i] = max(hi[i], float(vals.max()))
                n_valid[i] += int(vals.size)
    return {
        "u_t": [lo[0], hi[0]] if n_valid[0] else [0.0, 0.0],
        "u_a": [lo[1], hi[1]] if n_valid[1] else [0.0, 0.0],
        "valid_pixels": n_valid,
    }


def run(
    inputs: Inputs, config: Config, skip=frozenset(), ckpt: Checkpoint | None = None
) -> Iterator[tuple[str | None, dict]]:
    """Yield each train view's normalised U_T and U_A."""
    art = inputs.features
    state = ckpt.load() if ckpt is not None else None
    if state is not None and "range" in state:
        rng = state["range"]
    else:
        rng = scene_range(art, config)
        if ckpt is not None:
            ckpt.save({"range": rng})
    log.info("uncertainty range: U_T %s, U_A %s", rng["u_t"], rng["u_a"])
    for name in art.names():
        if name in skip:
            continue
        ut, ua, ok_t, ok_a = raw_maps(art[name], config)
        yield (
            name,
            {
                "u_t": normalise(ut, ok_t, *rng["u_t"]),
                "u_a": normalise(ua, ok_a, *rng["u_a"]),
            },
        )
    yield None, {"range_json": json_dataset(dict(rng, ua_members=config.ua_members))}


def write_previews(art: Artifact, folder: Path, n: int) -> list[Path]:
    """Side-by-side colour maps (U_T | U_A) of the first n views as PNGs."""
    import cv2

    out = []
    names = art.names()[: max(0, n)]
    if names:
        folder.mkdir(parents=True, exist_ok=True)
    for name in names:
        view = art[name]
        tiles = []
        for key in ("u_t", "u_a"):
            u8 = (np.clip(view[key].astype(np.float32), 0, 1) * 255 + 0.5).astype(
                np.uint8
            )
            tiles.append(cv2.applyColorMap(u8, cv2.COLORMAP_INFERNO))
        gap = np.full((tiles[0].shape[0], 4, 3), 255, np.uint8)
        path = folder / f"{Path(name).stem}_ut_ua.png"
        cv2.imwrite(str(path), np.hstack((tiles[0], gap, tiles[1])))
        out.append(path)
    return out


def _previews(art: Artifact) -> None:
    n = int(art.config.get("previews", 0))
    folder = art.path.with_suffix(".previews")
    if n and not folder.is_dir():
        paths = write_previews(art, folder, n)
        log.info("wrote %d previews to %s", len(paths), folder)


def _count(inputs: Inputs, config: Config) -> int:
    return len(inputs.features.names())


command = stage_command(
    NAME, VERSION, Config, Inputs, run, count=_count, after=_previews
)

__all__ = ["Config", "Inputs", "command", "normalise", "raw_maps", "run", "scene_range"]

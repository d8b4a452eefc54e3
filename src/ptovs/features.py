"""Multi-level segment features of one image: an id map plus a table of rows.

docs/method.md §1.3. For each image (an original photo or a render) and each level
ℓ, segments are numbered by GLOBAL table row: level ℓ's rows follow the rows of the
levels before it, so

    seg   [L, H, W] int16   row of the segment covering the pixel, or NO_SEGMENT (-1)
    table [n, D]    float16 unit rows, level blocks in order (counts [L] give sizes)

and the dense feature of level ℓ at pixel x is `table[seg[ℓ, x]]` wherever
`seg[ℓ, x] >= 0`. NO_SEGMENT marks "no segment here": `dense()` returns zeros and a
False validity mask there and never indexes the table with it (the authors' code
reads the last row instead). A level with no segment has zero rows and an all -1
map. Every row is referenced by its level's map (checked by `validate`).

Stored in an extract-features view as `seg_<app>`, `feat_<app>`, `nseg_<app>`,
app ∈ {orig, nov1, .., self}. LangSplat's npy folders (`<id>_f.npy` float32
[n, 512] and `<id>_s.npy` int [4, H, W] over levels default/s/m/l; renders
`<id>_f_ma_<k>.npy`, k = 0.. novel, last = self) are read by `read_langsplat` with
allow_pickle off and written by `write_langsplat`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ptovs.segment import LEVEL_NAMES, NO_SEGMENT, Level

MAX_ROWS = 32767  # int16 ids


@dataclass
class SegmentFeatures:
    seg: np.ndarray  # [L, H, W] int16, global rows or NO_SEGMENT
    table: np.ndarray  # [n, D] float16
    counts: np.ndarray  # [L] int32, rows per level

    @property
    def levels(self) -> int:
        return self.seg.shape[0]

    def offsets(self) -> np.ndarray:
        """[L + 1] first row of each level (and the total)."""
        return np.concatenate(([0], np.cumsum(self.counts))).astype(np.int64)

    def level_table(self, level: int) -> np.ndarray:
        o = self.offsets()
        return self.table[o[level] : o[level + 1]]

    def local(self, level: int) -> np.ndarray:
        """[H, W] int32 ids local to the level's block (NO_SEGMENT kept)."""
        s = self.seg[level].astype(np.int32)
        return np.where(s >= 0, s - int(self.offsets()[level]), NO_SEGMENT)

    def valid(self) -> np.ndarray:
        """[L, H, W] bool: a segment covers the pixel at that level."""
        return self.seg >= 0

    def dense(self, level: int) -> tuple[np.ndarray, np.ndarray]:
        """Dense features [H, W, D] float32 (zeros where invalid) and validity [H, W]."""
        s = self.seg[level]
        ok = s >= 0
        out = np.zeros((*s.shape, self.table.shape[1]), np.float32)
        out[ok] = self.table[s[ok].astype(np.int64)]
        return out, ok

    def validate(self, what: str = "features") -> None:
        """Raise ValueError unless ids, counts and rows are consistent."""
        if self.seg.ndim != 3 or self.table.ndim != 2:
            raise ValueError(f"{what}: seg must be [L, H, W] and table [n, D]")
        if len(self.counts) != self.levels or int(self.counts.sum()) != len(self.table):
            raise ValueError(
                f"{what}: counts {self.counts.tolist()} do not add up to "
                f"{len(self.table)} rows over {self.levels} levels"
            )
        o = self.offsets()
        for lv in range(self.levels):
            s = self.seg[lv]
            if (s < NO_SEGMENT).any():
                raise ValueError(f"{what}: level {lv} holds ids below {NO_SEGMENT}")
            used = np.unique(s[s >= 0])
            if used.size and (used[0] < o[lv] or used[-1] >= o[lv + 1]):
                raise ValueError(
                    f"{what}: level {lv} refers to rows outside its block "
                    f"[{o[lv]}, {o[lv + 1]})"
                )
            if used.size != self.counts[lv]:
                raise ValueError(
                    f"{what}: level {lv} has {self.counts[lv]} rows but its map "
                    f"references {used.size}"
                )

    # ------------------------------------------------------------ building
    @classmethod
    def from_levels(
        cls, levels: list[Level], feats: list[np.ndarray], dim: int
    ) -> SegmentFeatures:
        """Stack per-level local label maps and their feature rows [n_ℓ, D]."""
        counts = np.array([lv.n for lv in levels], np.int32)
        total = int(counts.sum())
        if total > MAX_ROWS:
            raise ValueError(f"{total} segments exceed the int16 id range")
        seg, offset = [], 0
        for lv, n in zip(levels, counts, strict=True):
            s = lv.labels.astype(np.int32)
            seg.append(np.where(s >= 0, s + offset, NO_SEGMENT).astype(np.int16))
            offset += int(n)
        rows = [np.asarray(f, np.float32).reshape(-1, dim) for f in feats]
        table = np.concatenate(rows) if rows else np.zeros((0, dim), np.float32)
        if not np.isfinite(table).all():
            raise FloatingPointError("encoder returned non-finite features")
        return cls(np.stack(seg), table.astype(np.float16), counts)

    def datasets(self, app: str) -> dict[str, np.ndarray]:
        return {
            f"seg_{app}": self.seg,
            f"feat_{app}": self.table,
            f"nseg_{app}": self.counts,
        }

    @classmethod
    def from_view(cls, view: dict[str, np.ndarray], app: str) -> SegmentFeatures:
        """Read one image's features from an extract-features view."""
        try:
            return cls(view[f"seg_{app}"], view[f"feat_{app}"], view[f"nseg_{app}"])
        except KeyError:
            have = sorted(k[4:] for k in view if k.startswith("seg_"))
            raise KeyError(
                f"no features for appearance {app!r} (have {have})"
            ) from None


def _densify(code: np.ndarray, bound: int) -> tuple[np.ndarray, int]:
    """Codes in [0, bound) renumbered 0..n−1 in increasing order: a lookup table
    (linear in pixels) while `bound` is small, a sort past that."""
    if bound <= max(4 * len(code), 1 << 16):
        seen = np.zeros(bound, bool)
        seen[code] = True
        remap = np.cumsum(seen, dtype=np.int64) - 1
        return remap[code], int(remap[-1]) + 1 if bound else 0
    uniq, inv = np.unique(code, return_inverse=True)
    return inv.ravel().astype(np.int64), len(uniq)


def tuple_ids(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unique rows of a non-negative int id matrix [P, M]: (an index of each, inverse [P]).

    Folds one column at a time into a dense code (code·(max+1) + column, then
    renumbered 0..n−1), so codes never overflow int64, and renumbers through a
    lookup table rather than a sort while the codes are few (a view's segment
    tuples are: thousands among 10⁵–10⁶ pixels), ~10× faster than np.unique.
    The unique rows come in lexicographic order, as np.unique(axis=0) gives them.
    """
    code = np.zeros(len(rows), np.int64)
    n = 1
    for j in range(rows.shape[1]):
        col = rows[:, j].astype(np.int64)
        span = int(col.max(initial=0)) + 1
        code, n = _densify(code * span + col, n * span)
    first = np.empty(n, np.int64)
    first[code] = np.arange(len(code))  # any index of a code will do: equal rows
    return first, code


def view_apps(view: dict[str, np.ndarray]) -> list[str]:
    """Appearance slots stored in an extract-features view ("orig" first)."""
    apps = sorted(k[4:] for k in view if k.startswith("seg_"))
    return sorted(apps, key=lambda a: (a != "orig", a == "self", a))


# ------------------------------------------------------------ LangSplat npy


def langsplat_suffix(app: str, novel_slots: list[str]) -> str:
    """File suffix of an appearance slot: "" (orig), "_ma_<k>" (novel k, self last)."""
    if app == "orig":
        return ""
    if app == "self":
        return f"_ma_{len(novel_slots)}"
    return f"_ma_{novel_slots.index(app)}"


def write_langsplat(
    folder: Path,
    stem: str,
    feats: SegmentFeatures,
    level_names: tuple[str, ...],
    suffix: str,
) -> None:
    """Write `<stem>_f<suffix>.npy` / `_s<suffix>.npy` in LangSplat's 4-level layout."""
    folder.mkdir(parents=True, exist_ok=True)
    _, h, w = feats.seg.shape
    seg = np.full((len(LEVEL_NAMES), h, w), NO_SEGMENT, np.int32)
    rows, offset = [], 0
    for name in LEVEL_NAMES:  # LangSplat's order: default, s, m, l
        if name not in level_names:
            continue
        lv = level_names.index(name)
        local = feats.local(lv)
        seg[LEVEL_NAMES.index(name)] = np.where(local >= 0, local + offset, NO_SEGMENT)
        block = feats.level_table(lv).astype(np.float32)
        rows.append(block)
        offset += len(block)
    table = (
        np.concatenate(rows)
        if rows
        else np.zeros((0, feats.table.shape[1]), np.float32)
    )
    np.save(folder / f"{stem}_f{suffix}.npy", table)
    np.save(folder / f"{stem}_s{suffix}.npy", seg)


def read_langsplat(
    folder: Path, stem: str, level_names: tuple[str, ...], suffix: str = ""
) -> SegmentFeatures:
    """Read LangSplat's `<stem>_f<suffix>.npy` and `_s<suffix>.npy` (no pickles).

    Levels are picked by name from the 4-level file and renumbered; rows no level
    references are dropped. Raises FileNotFoundError / ValueError naming the file.
    """
    fpath = folder / f"{stem}_f{suffix}.npy"
    spath = folder / f"{stem}_s{suffix}.npy"
    for p in (fpath, spath):
        if not p.is_file():
            raise FileNotFoundError(
                f"{p} not found: a LangSplat feature folder holds <id>_f.npy and "
                "<id>_s.npy per image (renders: _f_ma_<k>.npy)"
            )
    try:
        table = np.load(fpath, allow_pickle=False)
        seg = np.load(spath, allow_pickle=False)
    except ValueError as exc:
        raise ValueError(
            f"{fpath.parent}/{stem}: not a plain npy array ({exc})"
        ) from None
    if table.ndim != 2 or seg.ndim != 3 or seg.shape[0] != len(LEVEL_NAMES):
        raise ValueError(
            f"{fpath}: expected table [n, D] and seg [4, H, W], got "
            f"{table.shape} and {seg.shape}"
        )
    if seg.size and (seg.max() >= len(table) or seg.min() < NO_SEGMENT):
        raise ValueError(f"{spath}: ids outside [-1, {len(table)})")
    levels, feats = [], []
    for name in level_names:
        s = seg[LEVEL_NAMES.index(name)].astype(np.int64)
        used, inv = np.unique(s, return_inverse=True)
        inv = inv.reshape(s.shape)
        has_none = used.size and used[0] < 0
        rows = used[1:] if has_none else used
        local = (inv - 1 if has_none else inv).astype(np.int32)
        local[s < 0] = NO_SEGMENT
        levels.append(Level(local))
        feats.append(table[rows])
    return SegmentFeatures.from_levels(levels, feats, table.shape[1])

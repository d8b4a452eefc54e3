"""Truth segments of a synthetic photo: the instrument's perfect segmenter.

For a synthetic scene the generator stores each photo's part ids (`truth/<stem>.npz`:
part id per pixel, -1 sky, -2 ground, and the transient occluders' mask). The levels
are cut from them as SAM's levels are meant to be:

    s   finer pieces: each connected piece of a part (one column of a colonnade)
    m   the parts
    l   the whole landmark
    default   the parts (as m)

Sky, ground and every connected occluder are segments of their own at every level
(renders have no occluders: pass `transient=None`). Every pixel gets a segment. This
is an instrument, never a method: `extract-features` refuses it on a scene without
synthetic truth.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ptovs.errors import InputError
from ptovs.segment.levels import Level, check_levels

SKY, GROUND = -1, -2


def _relabel(labels: np.ndarray) -> np.ndarray:
    """Ids 0..n-1 in order of first appearance (row-major), int32."""
    _, first, inv = np.unique(labels.ravel(), return_index=True, return_inverse=True)
    order = np.argsort(np.argsort(first))
    return order[inv].reshape(labels.shape).astype(np.int32)


def _components(mask: np.ndarray) -> tuple[int, np.ndarray]:
    n, lab = cv2.connectedComponents(mask.astype(np.uint8), connectivity=8)
    return n - 1, lab  # 0 is the background of the mask


def truth_levels(
    part_id: np.ndarray,
    transient: np.ndarray | None,
    levels: tuple[str, ...] = ("s", "m", "l"),
) -> list[Level]:
    """The truth segments of one image at each level (see the module docstring).

    Args:
        part_id: [H, W] int: part ids (>= 0), SKY (-1) or GROUND (-2).
        transient: [H, W] bool occluder mask of a photo, or None (a render).
        levels: level names, from "default", "s", "m", "l".
    """
    levels = check_levels(levels)
    pid = np.asarray(part_id).astype(np.int64)
    if pid.ndim != 2:
        raise ValueError(f"part_id must be [H, W], got {pid.shape}")
    big = int(pid.max(initial=0)) + 3  # room for codes past every part id
    out = []
    for name in levels:
        code = pid.copy()
        if name == "l":
            code[pid >= 0] = 0  # the landmark as one
        elif name == "s":
            nxt = big
            for p in np.unique(pid[pid >= 0]):
                n, lab = _components(pid == p)
                for k in range(2, n + 1):  # the first piece keeps the part's id
                    code[lab == k] = nxt
                    nxt += 1
            big = max(big, nxt)
        if transient is not None:
            tr = np.asarray(transient, bool)
            if tr.shape != pid.shape:
                raise ValueError(
                    f"transient mask {tr.shape} does not match part ids {pid.shape}"
                )
            n, lab = _components(tr)
            for k in range(1, n + 1):
                code[lab == k] = big + k
        out.append(Level(_relabel(code)))
    return out


def truth_ids(part_id: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """Part ids with the ground told from the sky (the generator stores -1 for
    both; the ground has a finite depth)."""
    pid = np.asarray(part_id).astype(np.int32)
    return np.where((pid < 0) & np.isfinite(depth), GROUND, pid).astype(np.int32)


class TruthSegmenter:
    """Segments a synthetic view from its stored truth (see `truth_levels`).

    `select(stem, photo)` names the view the next `segment` call is for (a photo
    has its occluders, a render of the same camera has none); `segment(image)`
    checks the image's size against the truth and returns its levels.
    """

    name = "truth"

    def __init__(self, scene_root: Path, levels: tuple[str, ...] = ("s", "m", "l")):
        self.root = Path(scene_root) / "synthetic" / "truth"
        if not (self.root / "parts.json").is_file():
            raise InputError(
                f"segmenter 'truth' needs a synthetic scene's truth ({self.root} "
                "has none): it is the accuracy instrument's, not a method; use "
                "'graph', 'hier' or 'sam'"
            )
        self.levels = check_levels(levels)
        self._view: tuple[str, bool] | None = None

    def select(self, stem: str, photo: bool) -> None:
        self._view = (stem, photo)

    def segment(self, image: np.ndarray) -> list[Level]:
        if self._view is None:
            raise RuntimeError("TruthSegmenter.segment before select(stem, photo)")
        stem, photo = self._view
        path = self.root / f"{stem}.npz"
        if not path.is_file():
            raise FileNotFoundError(f"no truth for view {stem}: {path}")
        with np.load(path) as z:
            pid, tr = truth_ids(z["part_id"], z["depth"]), z["transient"]
        h, w = image.shape[:2]
        if pid.shape != (h, w):  # a downscaled scene: nearest, as labels are
            near = cv2.INTER_NEAREST
            pid = cv2.resize(pid.astype(np.int32), (w, h), interpolation=near)
            tr = cv2.resize(tr.astype(np.uint8), (w, h), interpolation=near) > 0
        return truth_levels(pid, tr if photo else None, self.levels)


__all__ = ["GROUND", "SKY", "TruthSegmenter", "truth_ids", "truth_levels"]

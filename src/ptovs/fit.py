"""The scene-fitted recipe: what a scene needs, decided from its own photos.

A config value `"auto"` in one of the fields of `FITTED` is decided here, before
the chain is keyed (`ptovs.chain.Chain.config`): the decided value replaces
`"auto"` in the stage's config, so it is part of the key (a scene fitted to
`wild = false` shares its artifacts with a run that set `wild=false` by hand), it is
stored in the artifact with the rest of the config, and one line names it with
its evidence. A value given with `--set` (or in a config file) is never
touched. `configs/auto.toml` turns every decision on; `configs/paper.toml` keeps
the paper's fixed recipe.

The evidence (`photo_evidence`) is measured on the scene's own sparse points as
the train photos see them (docs/guide.md, "The scene-fitted recipe"): every
point is projected into up to `MAX_VIEWS` train photos; per photo, the median
log-ratio of its colour at the points to each point's median colour over the
photos is the photo's exposure-and-tint gain. Their spread over the photos says
whether the photos share one appearance. Nothing is trained; it takes a few
seconds, and it is cached by the scene's content key in `<work>/<scene>/fit.json`
(written once a command's checks pass; never by `ptovs status`).

Missing evidence is never a decision: where the spread cannot be measured (no
sparse points, or fewer than two photos seeing MIN_OBSERVATIONS of them), each
appearance decision keeps the paper's value (the stage's default) and says so in
a warning naming what was missing and the `--set` that chooses by hand.

Decisions:
- `reconstruct.wild`: the in-the-wild model (appearance embedding, transient
  masks) when the photos' appearance spread exceeds `WILD_SPREAD`, else plain
  3DGS (same code, no networks: about 2.5× faster a step); unmeasured: the
  paper's in-the-wild model.
- `render-appearances.n_appearances`: 1 (the self render only) when the photos
  share one appearance; else (or unmeasured) the paper's N = 4.
  extract-features then encodes the photo and its self render alone (2 images
  a view instead of N + 1 = 5).
- `extract-features.images` is decided in the stage, not here: it needs the
  renders (`appearance_sensitivity`, `images_decision`; kept in the artifact).
- `extract-features.sam_points_per_side`: a prompt every `SAM_PITCH_PX` pixels of
  the working short side, 8 to 32 a side (SAM-class segmenters only); with no
  photos, the paper's 32.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

EVIDENCE_VERSION = 2  # 2: `read` (photos read) added
MAX_VIEWS = 48
"""Train photos the evidence reads (evenly spaced by name): enough for a spread."""
MAX_POINTS = 4000
"""Sparse points projected (a seeded draw): medians over thousands are stable."""
MIN_OBSERVATIONS = 30
"""A photo seeing fewer points than this gives no gain (too few to be robust)."""
WILD_SPREAD = 0.05
"""Appearance spread (robust standard deviation over photos of the log gain,
luminance and tint together) above which a scene gets the in-the-wild model.
A plain field fits one colour per surface: a 5 % exposure spread around it is an
error of about 0.02 on a mid-grey pixel, the size of a well-fitted field's own
error (PSNR 30 dB), so above it an appearance model pays for its cost."""
SAM_PITCH_PX = 64
"""One SAM prompt per this many pixels of the working short side (8 to 32)."""

FITTED: dict[str, tuple[str, ...]] = {
    "reconstruct": ("wild",),
    "render-appearances": ("n_appearances",),
    "extract-features": ("sam_points_per_side",),
}
"""The fields a config may set to "auto", per stage."""


# ------------------------------------------------------------------ evidence --
def _gain_spread(gains: np.ndarray) -> float:
    """Robust standard deviation (1.4826·MAD) of per-photo log gains [V, 3],
    the channels' spreads combined as one: sqrt(mean over channels of MAD²)."""
    if len(gains) < 2:
        return 0.0
    mad = np.median(np.abs(gains - np.median(gains, 0)), 0) * 1.4826
    return float(np.sqrt(np.mean(np.square(mad))))


def photo_gains(
    colours: np.ndarray, eps: float = 0.02
) -> tuple[np.ndarray, np.ndarray, float]:
    """Per-photo log gains from the colours photos see at shared points.

    Args:
        colours: [V, P, 3] float in [0, 1], NaN where photo v does not see point p.
        eps: added before the log (dark pixels' noise stays small).

    Returns:
        (gains [V', 3] of the photos with at least MIN_OBSERVATIONS points,
        their indices [V'], the share of observations off their photo's gain by
        more than 0.4 (a factor of 1.5): occluders, reflections, occlusion).
    """
    logc = np.log(np.asarray(colours, np.float64) + eps)
    seen = np.isfinite(logc).all(-1)  # [V, P]
    counts = seen.sum(0)
    logc = logc[:, counts >= 2]  # a point seen once says nothing about gains
    seen = seen[:, counts >= 2]
    if logc.shape[1] == 0:
        return np.zeros((0, 3)), np.zeros(0, np.int64), 0.0
    ref = np.nanmedian(logc, 0)  # [P, 3]: each point's median colour
    dev = logc - ref[None]
    keep = seen.sum(1) >= MIN_OBSERVATIONS
    idx = np.flatnonzero(keep)
    gains = np.stack([np.median(dev[v][seen[v]], 0) for v in idx]) if len(idx) else (
        np.zeros((0, 3))
    )  # fmt: skip
    if len(idx) == 0:
        return gains, idx, 0.0
    resid = np.abs(dev[idx] - gains[:, None, :]).max(-1)  # [V', P]
    off = float((resid[seen[idx]] > 0.4).mean())
    return gains, idx, off


def _project(view: Any, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates [P, 2] of world points in `view` and whether each lies
    in front of the camera and inside the image."""
    pc = xyz @ view.cam_from_world[:3, :3].T + view.cam_from_world[:3, 3]
    z = pc[:, 2]
    front = z > 1e-6
    uv = (pc[:, :2] / np.where(front, z, 1.0)[:, None]) @ view.K[:2, :2].T + view.K[
        :2, 2
    ]
    inside = (
        front
        & (uv[:, 0] >= 0)
        & (uv[:, 0] <= view.width - 1)
        & (uv[:, 1] >= 0)
        & (uv[:, 1] <= view.height - 1)
    )
    return uv, inside


def photo_evidence(scene: Any, seed: int = 0) -> dict[str, Any]:
    """What the scene's photos say about it (see the module docstring).

    Returns a JSON-ready dict: `photos` (train photos in the scene), `read`
    (photos read, at most MAX_VIEWS), `views` (of those, the photos that give a
    gain: MIN_OBSERVATIONS or more points seen), `points` (sparse points
    projected), `appearance_spread` (the robust spread of the log gains over
    photos; 0 when fewer than two photos give one), `outliers` (share of
    observations off their photo's gain by a factor of 1.5), `short_side` (median
    working short side, px).
    """
    import cv2

    train = scene.train_views()
    step = max(1, math.ceil(len(train) / MAX_VIEWS))
    views = train[::step][:MAX_VIEWS]
    xyz = np.asarray(scene.points_xyz, np.float64).reshape(-1, 3)
    if len(xyz) > MAX_POINTS:
        pick = np.random.default_rng(seed).choice(len(xyz), MAX_POINTS, replace=False)
        xyz = xyz[np.sort(pick)]
    colours = np.full((len(views), len(xyz), 3), np.nan, np.float32)
    for k, view in enumerate(views):
        image = scene.load_image(view)
        # a 3×3 mean: a point's colour, not one pixel's noise or edge
        image = cv2.blur(np.asarray(image, np.float32), (3, 3))
        uv, inside = _project(view, xyz)
        px = np.rint(uv[inside]).astype(np.int64)
        colours[k, inside] = image[px[:, 1], px[:, 0]]
    gains, _, off = photo_gains(colours)
    shorts = [min(v.width, v.height) for v in train] or [0]
    return {
        "version": EVIDENCE_VERSION,
        "photos": len(train),
        "read": len(views),
        "views": int(len(gains)),
        "points": int(len(xyz)),
        "appearance_spread": round(_gain_spread(gains), 4),
        "outliers": round(off, 4),
        "short_side": int(np.median(shorts)),
    }


_MEASURED: dict[str, dict[str, Any]] = {}
"""Evidence measured in this process, by scene key: the decisions of one command
(read-only checks first, then the stages) read the photos once."""


def cached_evidence(scene_ref: Any) -> dict[str, Any]:
    """`photo_evidence` of the scene, cached in `<work>/<scene>/fit.json` by the
    scene's content key. Under `ptovs.keys.read_only` (a command's checks, `ptovs
    status`) the file is written only once the checks pass
    (`ptovs.keys.write_when_checked`), so `status` writes nothing."""
    from ptovs.artifacts import write_atomic
    from ptovs.keys import READ_ONLY, write_when_checked

    key = scene_ref.key()
    path = Path(scene_ref.work_dir) / scene_ref.name / "fit.json"
    try:
        blob = json.loads(path.read_text())
        if blob.get("scene_key") == key and blob.get("version") == EVIDENCE_VERSION:
            return dict(blob["evidence"])
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        pass
    if key not in _MEASURED:
        _MEASURED[key] = photo_evidence(scene_ref.load())
    evidence = dict(_MEASURED[key])
    blob = {"version": EVIDENCE_VERSION, "scene_key": key, "evidence": evidence}
    if READ_ONLY.get():
        write_when_checked(path, json.dumps(blob))
    else:
        write_atomic(path, json.dumps(blob))
    return evidence


# ----------------------------------------------------------------- decisions --
def shared_appearance(evidence: dict[str, Any]) -> bool:
    """Whether the photos share one appearance (spread at most WILD_SPREAD)."""
    return evidence["appearance_spread"] <= WILD_SPREAD


def paper_value(stage: str, field: str) -> Any:
    """The paper's value of a fitted field: the stage Config's default (the value
    configs/paper.toml pins)."""
    from ptovs.registry import get_stage

    fields = dataclasses.fields(get_stage(stage).config_cls)
    return next(f.default for f in fields if f.name == field)


MEASURES = {
    ("reconstruct", "wild"): ("the photos' appearance spread", "false"),
    ("render-appearances", "n_appearances"): ("the photos' appearance spread", "1"),
    ("extract-features", "sam_points_per_side"): ("the working short side", "N"),
}
"""Per fitted field: what its evidence measures, and the value a warning offers to
set by hand where that evidence is missing (the cheaper choice)."""


def missing(stage: str, field: str, evidence: dict[str, Any]) -> str | None:
    """What the evidence lacks for this decision, in words; None when it has it.

    The appearance decisions need a spread: sparse points, and at least two
    photos that each see MIN_OBSERVATIONS of them. The SAM grid needs a photo.
    """
    photos = evidence.get("photos")
    if photos == 0:
        return "no train photos in the scene"
    if (stage, field) == ("extract-features", "sam_points_per_side"):
        return None
    points = evidence.get("points")
    if points == 0:
        return "no sparse points in the scene's model"
    seen = evidence["views"]
    if seen < 2:
        read = evidence.get("read", photos)
        return (
            f"only {seen} of {read} photos {'sees' if seen == 1 else 'see'} "
            f"{MIN_OBSERVATIONS} or more of the {points} sparse points"
        )
    return None


def decide(stage: str, field: str, evidence: dict[str, Any]) -> tuple[Any, str]:
    """The value of `stage.field` under "auto", and the evidence in words.

    Where the evidence is missing (`missing`), the paper's value, and why."""
    if (stage, field) not in MEASURES:
        raise KeyError(f"{stage}.{field} cannot be 'auto'")
    gap = missing(stage, field, evidence)
    if gap is not None:  # missing evidence is not "no appearance change"
        what, by_hand = MEASURES[stage, field]
        return paper_value(stage, field), (
            f"{gap}, so {what} cannot be measured: kept the paper's value; "
            f"choose by hand with --set {stage}.{field}={by_hand}"
        )
    if (stage, field) == ("extract-features", "sam_points_per_side"):
        side = evidence["short_side"]
        n = int(min(32, max(8, round(side / SAM_PITCH_PX))))
        return n, f"working short side {side} px, a prompt every {SAM_PITCH_PX} px"
    spread = evidence["appearance_spread"]
    why = (
        f"appearance spread {spread:.3f} "
        f"{'≤' if spread <= WILD_SPREAD else '>'} {WILD_SPREAD} over "
        f"{evidence['views']} photos"
    )
    one = shared_appearance(evidence)
    if (stage, field) == ("reconstruct", "wild"):
        return (not one), why
    return (1 if one else paper_value(stage, field)), why


def resolve(stage: str, config: Any, scene_ref: Any) -> Any:
    """`config` with every "auto" of `FITTED[stage]` decided for this scene (one
    line each, on the log: a warning where the evidence is missing); `config`
    itself when it has none."""
    fields = [f for f in FITTED.get(stage, ()) if getattr(config, f, None) == "auto"]
    if not fields:
        return config
    evidence = cached_evidence(scene_ref)
    changes = {}
    for f in fields:
        value, why = decide(stage, f, evidence)
        changes[f] = value
        if _matters(stage, f, config):
            level = logging.WARNING if missing(stage, f, evidence) else logging.INFO
            log.log(level, "%s: %s = %s (auto: %s)", stage, f, json.dumps(value), why)
    return dataclasses.replace(config, **changes)


def _matters(stage: str, field: str, config: Any) -> bool:
    """Whether the decision changes what the stage does (SAM's grid is decided,
    and keyed, for every segmenter, but only a SAM-class one reads it: no line)."""
    if (stage, field) == ("extract-features", "sam_points_per_side"):
        return getattr(config, "segmenter", "sam") in ("sam", "sam2")
    return True


# ---------------------------------------------- extract-features: which images --
SENSITIVITY = 0.15
"""images = "auto" encodes the novel appearances when a segment's feature moves
between the self render and a novel render by more than this fraction of the
distance between two segments of the same image (`appearance_sensitivity`):
below it, a phrase that tells two segments apart tells them apart under every
appearance, and the novel renders add cost without changing an answer."""


def _unit(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, np.float64)
    return x / np.maximum(np.linalg.norm(x, axis=-1, keepdims=True), 1e-12)


def appearance_sensitivity(
    probes: list[tuple[np.ndarray, list[np.ndarray]]],
) -> dict[str, float]:
    """How much the encoder's features move with the appearance, against how much
    they differ between segments.

    Args:
        probes: per view, the self render's segment features [n, D] and each novel
            render's features of the same segments (row-aligned).

    Returns:
        `change`: mean over segments and novel renders of 1 − cos(self, novel);
        `contrast`: mean over pairs of different segments of a view of
        1 − cos (self render); `ratio` = change / contrast (0 when there is no
        contrast or nothing to compare); `segments`: rows compared.
    """
    change, n_change, contrast, n_pairs = 0.0, 0, 0.0, 0
    for own, others in probes:
        a = _unit(own)
        if len(a) == 0:
            continue
        for other in others:
            b = _unit(other)
            if b.shape != a.shape:
                continue  # not row-aligned: nothing to compare
            d = 1.0 - np.sum(a * b, -1)
            ok = np.isfinite(d)
            change += float(d[ok].sum())
            n_change += int(ok.sum())
        if len(a) >= 2:
            g = 1.0 - a @ a.T
            iu = np.triu_indices(len(a), 1)
            vals = g[iu][np.isfinite(g[iu])]
            contrast += float(vals.sum())
            n_pairs += int(vals.size)
    c = change / n_change if n_change else 0.0
    k = contrast / n_pairs if n_pairs else 0.0
    return {  # significant digits: a random-weight encoder's are ~1e-6
        "change": float(f"{c:.4g}"),
        "contrast": float(f"{k:.4g}"),
        "ratio": round(c / k, 4) if k > 1e-12 else 0.0,
        "segments": n_change,
    }


def images_decision(probes: list[tuple[np.ndarray, list[np.ndarray]]]) -> dict:
    """extract-features' images under "auto", with its evidence in words."""
    s = appearance_sensitivity(probes)
    if s["segments"] == 0:
        return {"images": "all", "why": "no segment to probe: every image kept", **s}
    moved = s["ratio"] > SENSITIVITY
    why = (
        f"features move with the appearance by {s['ratio']:.3f} of the distance "
        f"between segments ({'>' if moved else '≤'} {SENSITIVITY}; "
        f"{s['segments']} segment renders on {len(probes)} views)"
    )
    return {"images": "all" if moved else "orig+self", "why": why, **s}


__all__ = [
    "FITTED",
    "SAM_PITCH_PX",
    "SENSITIVITY",
    "appearance_sensitivity",
    "images_decision",
    "WILD_SPREAD",
    "cached_evidence",
    "decide",
    "missing",
    "paper_value",
    "photo_evidence",
    "photo_gains",
    "resolve",
]

"""Answerable queries: the generator's screen of every query part.

A query is answerable when its phrase, on clean crops of its own part, wins the
pipeline's relevancy rule against every negative phrase the pipeline compares it
with: the canonical phrases ("object", "things", "scene", "sky", "building") and
the background phrases ("sky", "background"). With the stand-in encoder some
part textures collide with a negative (a blue dome with "sky", a grey pediment
with "building"); such a query scores about 0 for every method, the oracle
included, and only adds noise to the benchmark.

The rule, for a part and its phrase q: render each evaluation camera under the
neutral appearance without occluders (one sample per pixel), cut each labelled instance of the part
(its truth mask, as the label encodes it) into a segment crop exactly as the
pipeline crops segments (`ptovs.crop.prepare_crop`), embed it with the
stand-in encoder and take its margin

    m = cos(crop, q) − max_j cos(crop, n_j)   over the negatives n_j,

so that the relevancy min_j sigmoid(τ(cos q − cos n_j)) = sigmoid(τ m). An
*average word* of the stand-in (version 5's "building": the mean of the part
phrases, so close to every part by definition) is only to be beaten, relevancy
above 0.5: against it the margin counts MARGIN more. The
part passes when its median crop has m ≥ MARGIN (= 1/τ: relevancy ≥ sigmoid(1)
= 0.73, odds e : 1) and at least MIN_WIN of its crops have m > 0 (the phrase
wins there at all). A part that fails gets a new texture, drawn from its own
seeded stream (`redraw_texture`, attempt k = 1, 2, ...), at most REDRAWS times;
a part that still fails keeps its original texture and is not a query. What
happened to every part is recorded in truth/parts.json ("screen").

The screen sees only the world, the cameras and the encoder: never any
method's output. It does not change the encoder or the negatives.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass, replace

import numpy as np

from ptovs.synthetic.world import (
    Camera,
    Texture,
    World,
    neutral_appearance,
    random_texture,
    render,
)

MARGIN = 0.1
"""Median crop margin a query phrase needs over its strongest negative (cosine
units; 1/τ at the pipeline's temperature 10)."""
MIN_WIN = 0.9
"""Share of a part's crops on which the phrase must beat every negative."""
REDRAWS = 8
"""New textures tried for a failing part before it stops being a query."""
NEGATIVES = ("object", "things", "scene", "sky", "building", "background")
"""The pipeline's canonical phrases plus its background phrases (`ptovs.field.
relevancy.CANONICAL` + `BACKGROUND_PHRASES`), kept in one place here; a test
checks the two stay equal."""
_STREAM = 9  # the generator's random stream for redrawn textures


@dataclass(frozen=True)
class PartScreen:
    """The screen's verdict on one part."""

    query: str
    crops: int  # labelled instances in the evaluation views
    median: float | None  # median crop margin (None without crops)
    win: float  # share of crops with a positive margin
    attempt: int  # 0: the original texture; k: the k-th redraw
    status: str  # "pass", "redrawn", "dropped" or "unseen"

    @property
    def answerable(self) -> bool:
        return self.status in ("pass", "redrawn")


def passes(margins: np.ndarray) -> bool:
    """The screen's rule on one part's crop margins."""
    m = np.asarray(margins, float)
    return bool(len(m)) and (
        float(np.median(m)) >= MARGIN and float((m > 0).mean()) >= MIN_WIN
    )


def redraw_texture(seed: int, part_id: int, attempt: int, size: float) -> Texture:
    """The texture of a part's k-th redraw (any hue and pattern), seeded."""
    rng = np.random.default_rng([seed, _STREAM, part_id, attempt])
    return random_texture(rng, size)


def crop_margins(
    world: World,
    cams: list[Camera],
    truths: list[np.ndarray],
    vocabulary: dict,
    part_ids: list[int],
    mask_of: Callable[[np.ndarray, int, Camera], np.ndarray | None],
) -> dict[int, np.ndarray]:
    """Margins of every labelled crop of each part under neutral light.

    Each camera is rendered once, one sample per pixel, and only over the box
    around the parts' label masks (a window of the camera casts exactly that
    box's rays): a crop never sees the pixels outside its mask. Against the
    five-sample photos the median margins differ by about 0.002.

    Args:
        world: the world (its current textures).
        cams: the evaluation cameras.
        truths: their part-id maps (`render_truth`; textures do not change them).
        vocabulary: the scene vocabulary of this world (`scene_vocabulary`).
        part_ids: the parts to measure.
        mask_of: (part-id map, part id, camera) -> the part's label mask in
            that view, or None when the view does not label it.

    Returns:
        {part id: [n] float64 margins}, one per labelled instance.
    """
    from ptovs.crop import prepare_crop

    enc = screen_encoder(vocabulary)
    by_id = {p.id: p for p in world.parts}
    text = enc.encode_texts([by_id[k].query for k in part_ids]).astype(np.float64)
    average = tuple(getattr(enc, "average_words", ()))
    negs = enc.encode_texts(list(NEGATIVES)).astype(np.float64)
    crops: list[np.ndarray] = []
    owner: list[int] = []
    for cam, truth in zip(cams, truths, strict=True):
        masks = {k: mask_of(truth, k, cam) for k in part_ids}
        masks = {k: m for k, m in masks.items() if m is not None}
        if not masks:
            continue
        rows = np.flatnonzero(np.any([m.any(1) for m in masks.values()], 0))
        cols = np.flatnonzero(np.any([m.any(0) for m in masks.values()], 0))
        i0, i1, j0, j1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
        view = render(world, cam.window(i0, i1, j0, j1), neutral_appearance(), aa=1)
        for k, m in masks.items():
            crops.append(prepare_crop(view.image, m[i0:i1, j0:j1]))
            owner.append(k)
    out = {k: np.zeros(0) for k in part_ids}
    if not crops:
        return out
    emb = enc.encode_images(np.stack(crops)).astype(np.float64)
    neg = emb @ negs.T
    owner_a = np.asarray(owner)
    for j, k in enumerate(part_ids):
        sel = owner_a == k
        out[k] = margins(emb[sel] @ text[j], neg[sel], average)
    return out


def screen_encoder(vocabulary: dict):
    """The stand-in the screen reads a world with: version 1 for a version-1
    vocabulary; for a version-5 one, the category text rules over the plain
    reading of version 5's statistics (`encoders.standin_text.CategoryEncoder`),
    so that a seed's photos do not depend on version 5's learnt projection."""
    version = vocabulary.get("version", 1)
    if version == 1:
        from ptovs.encoders.synthetic import SyntheticEncoder

        return SyntheticEncoder(vocabulary)
    if version == 5:
        from ptovs.encoders.standin_text import CategoryEncoder

        return CategoryEncoder(vocabulary)
    raise ValueError(f"the screen reads stand-in versions 1 and 5, not {version!r}")


def margins(
    own: np.ndarray, negatives: np.ndarray, average: tuple[str, ...] = ()
) -> np.ndarray:
    """Crop margins from the cosines with the query phrase [n] and with each of
    NEGATIVES [n, len(NEGATIVES)]: own minus the strongest negative, where an
    average word (in `average`) is only to be beaten, so its cosine counts
    MARGIN less."""
    lift = np.array([MARGIN if n in average else 0.0 for n in NEGATIVES])
    return np.asarray(own, np.float64) - (np.asarray(negatives) - lift).max(1)


def screen_world(
    world: World,
    seed: int,
    cams: list[Camera],
    truths: list[np.ndarray],
    part_ids: list[int],
    vocabulary_of: Callable[[World], dict],
    mask_of: Callable[[np.ndarray, int, Camera], np.ndarray | None],
) -> tuple[World, dict[int, PartScreen]]:
    """Screen the candidate query parts, redrawing the textures of failing ones.

    Args:
        world: the drawn world.
        seed: the scene's seed (seeds the redraws).
        cams: the evaluation cameras.
        truths: their part-id maps.
        part_ids: candidate query parts (seen in some evaluation view).
        vocabulary_of: world -> its scene vocabulary.
        mask_of: see `crop_margins`.

    Returns:
        The world with redrawn textures where they passed, and the verdict per
        part (every part of the world; parts not in `part_ids` are "unseen").
    """
    original = {p.id: p.texture for p in world.parts}
    verdict: dict[int, PartScreen] = {}
    todo = list(part_ids)
    first: dict[int, np.ndarray] = {}
    for attempt in range(REDRAWS + 1):
        if not todo:
            break
        if attempt:
            world = _with_textures(
                world,
                {
                    k: redraw_texture(seed, k, attempt, _part(world, k).size)
                    for k in todo
                },
            )
        margins = crop_margins(world, cams, truths, vocabulary_of(world), todo, mask_of)
        still = []
        for k in todo:
            m = margins[k]
            if attempt == 0:
                first[k] = m
            if passes(m):
                verdict[k] = _verdict(world, k, m, attempt)
            else:
                still.append(k)
        todo = still
    # parts that never passed keep their original texture and are not queries
    world = _with_textures(world, {k: original[k] for k in todo})
    for k in todo:
        verdict[k] = replace(_verdict(world, k, first[k], 0), status="dropped")
    for p in world.parts:
        if p.id not in verdict:
            verdict[p.id] = PartScreen(p.query, 0, None, 0.0, 0, "unseen")
    return world, dict(sorted(verdict.items()))


def _part(world: World, k: int):
    return next(p for p in world.parts if p.id == k)


def _verdict(world: World, k: int, m: np.ndarray, attempt: int) -> PartScreen:
    return PartScreen(
        query=_part(world, k).query,
        crops=len(m),
        median=round(float(np.median(m)), 6) if len(m) else None,
        win=round(float((m > 0).mean()), 6) if len(m) else 0.0,
        attempt=attempt,
        status="pass" if attempt == 0 else "redrawn",
    )


def _with_textures(world: World, textures: dict[int, Texture]) -> World:
    parts = [replace(p, texture=textures.get(p.id, p.texture)) for p in world.parts]
    return replace(world, parts=parts)


def screen_record(verdict: dict[int, PartScreen]) -> dict:
    """The JSON record of a screen (truth/parts.json "screen")."""
    return {
        "rule": (
            "median crop margin >= margin and a positive margin on >= min_win of "
            "the crops; margin = cos(crop, query) - max cos(crop, negative)"
        ),
        "margin": MARGIN,
        "min_win": MIN_WIN,
        "redraws": REDRAWS,
        "negatives": list(NEGATIVES),
        "parts": {str(k): asdict(v) for k, v in verdict.items()},
    }


__all__ = [
    "MARGIN",
    "MIN_WIN",
    "NEGATIVES",
    "REDRAWS",
    "PartScreen",
    "crop_margins",
    "margins",
    "passes",
    "redraw_texture",
    "screen_encoder",
    "screen_record",
    "screen_world",
]

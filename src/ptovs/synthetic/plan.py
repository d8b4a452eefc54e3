"""The plan of a synthetic scene: world, cameras, evaluation views and the
screened queries, decided before any photo is rendered."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ptovs.synthetic.labels import isat_label, label_mask
from ptovs.synthetic.presets import PRESETS, Preset, _min_px, _rng, _world
from ptovs.synthetic.screen import PartScreen, screen_world
from ptovs.synthetic.vocabulary import scene_vocabulary
from ptovs.synthetic.world import (
    DISTRACTORS,
    Camera,
    World,
    render_truth,
    sample_camera,
)


def _choose_eval(
    world: World, preset: Preset, cand: list[int], cams: list[Camera]
) -> tuple[list[int], dict[int, np.ndarray]]:
    """Evaluation views, from a truth-only pass over the candidate cameras.

    First a view for each part seen (>= 1 % of an image) in some candidate, in
    part order, then the candidates that see the most parts; `preset.n_eval` in
    all (so on `tiny` a third part may be labelled in no view, and is then no
    query). Returns the views and the candidates' part-id maps.
    """
    counts, truths = {}, {}
    for i in cand:
        pid, _ = render_truth(world, cams[i])
        truths[i] = pid
        m = _min_px(cams[i], 0.01, 12)
        counts[i] = {p.id: int((pid == p.id).sum()) >= m for p in world.parts}
    seen = [p.id for p in world.parts if any(counts[i][p.id] for i in cand)]
    if not seen:
        raise RuntimeError("no part is visible in any evaluation candidate")
    chosen: list[int] = []
    for q in seen:  # every part seen gets at least one evaluation view
        for i in cand:
            if counts[i][q] and i not in chosen:
                chosen.append(i)
                break
    score = sorted(cand, key=lambda i: -sum(counts[i][q] for q in seen))
    for i in score:
        if len(chosen) >= preset.n_eval:
            break
        if i not in chosen and any(counts[i][q] for q in seen):
            chosen.append(i)
    return sorted(chosen[: preset.n_eval]), truths


@dataclass(frozen=True)
class ScenePlan:
    """Everything about a seed's scene decided before any photo is rendered."""

    world: World  # with the screen's redrawn textures
    test_ids: set[int]
    stems: list[str]
    cams: list[Camera]
    eval_ids: list[int]
    queries: dict[str, list[int]]  # query phrase -> part ids (screened)
    distractor: str
    screen: dict[int, PartScreen]  # the screen's verdict on every part


def plan_scene(preset: str, seed: int, standin: int = 1, extra: int = 0) -> ScenePlan:
    """The plan of (preset, seed): world, cameras, evaluation views, screened queries.

    Renders only truth maps and the screen's neutral crops, so every preset's
    queries and labels can be checked over many seeds cheaply. `extra` train
    photos past the preset's (up to its max_train) come after them, each drawn
    from its own index's streams: the rest of the plan is the same with or
    without them.
    """
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; choose from {sorted(PRESETS)}")
    if standin not in (1, 5):
        raise ValueError(
            f"stand-in version {standin!r} is not available (only 1 and 5 are); "
            "use standin=1 or standin=5"
        )
    cfg = PRESETS[preset]
    world = _world(cfg, seed)
    n_img = cfg.n_train + cfg.n_test
    draw = _rng(seed, 1)
    test_ids = set(draw.choice(n_img, cfg.n_test, replace=False).tolist())
    train_ids = [i for i in range(n_img) if i not in test_ids]
    n_cand = min(len(train_ids), cfg.n_cand)
    cand = sorted(draw.choice(train_ids, n_cand, replace=False).tolist())
    stems = [
        f"{seed:02d}{i:06d}_{int(draw.integers(10**9, 10**10))}" for i in range(n_img)
    ]
    cams = [
        sample_camera(_rng(seed, 2, i), world, cfg.long_side, frontal=i in cand)
        for i in range(n_img)
    ]
    if not 0 <= extra <= cfg.train_limit - cfg.n_train:
        raise PhotoCountError(
            f"preset {preset!r} holds at most {cfg.train_limit} train photos; "
            f"{cfg.n_train + extra} asked"
        )
    for i in range(n_img, n_img + extra):
        own = _rng(seed, 9, i)
        stems.append(f"{seed:02d}{i:06d}_{int(own.integers(10**9, 10**10))}")
        cams.append(
            sample_camera(_rng(seed, 2, i), world, cfg.long_side, frontal=False)
        )
    eval_ids, cand_truths = _choose_eval(world, cfg, cand, cams)
    eval_cams = [cams[i] for i in eval_ids]
    truths = [cand_truths[i] for i in eval_ids]
    labelled = [
        p.id
        for p in world.parts
        if any(
            label_mask(t, p.id, c) is not None
            for t, c in zip(truths, eval_cams, strict=True)
        )
    ]
    world, verdict = screen_world(
        world,
        seed,
        eval_cams,
        truths,
        labelled,
        lambda w: scene_vocabulary(w, cfg, [], standin),
        label_mask,
    )
    queries = {p.query: [p.id] for p in world.parts if verdict[p.id].answerable}
    if not queries:
        raise RuntimeError(
            f"seed {seed}: no part's phrase passes the answerability screen"
        )
    used = {p.query for p in world.parts}
    distractors = [d for d in DISTRACTORS if d not in used]
    distractor = distractors[int(draw.integers(len(distractors)))]
    cams = [c.scaled(cfg.scale) for c in cams]  # after the screen: as at scale 1
    return ScenePlan(
        world, test_ids, stems, cams, eval_ids, queries, distractor, verdict
    )


class PhotoCountError(ValueError):
    """`--photos N` outside what the preset holds (the message says the range)."""


def photo_subset(plan: ScenePlan, preset: str, photos: int | None) -> list[int]:
    """The images a scene of `photos` train photos keeps, as indices into the plan:
    every test and evaluation view, then the other train views in order. So the
    same world, test split and labelled views come at every size, and a smaller
    collection's photos are a subset of a larger one's (the same pixels)."""
    cfg = PRESETS[preset]
    n_img = cfg.n_train + cfg.n_test
    if photos is None or photos == cfg.n_train:
        return list(range(n_img))
    evals = [i for i in plan.eval_ids if i not in plan.test_ids]
    if not len(evals) <= photos <= cfg.train_limit:
        raise PhotoCountError(
            f"preset {preset!r} takes {len(evals)} to "
            f"{cfg.train_limit} train photos (its {len(evals)} labelled views are train "
            "photos)"
        )
    if photos > cfg.n_train:  # every photo of the plan, then the extra ones
        if len(plan.cams) < n_img + photos - cfg.n_train:
            raise ValueError("plan_scene(extra=...) planned fewer photos than asked")
        return list(range(n_img + photos - cfg.n_train))
    keep = set(plan.test_ids) | set(evals)
    others = [i for i in range(n_img) if i not in keep]
    return sorted(keep | set(others[: photos - len(evals)]))


def eval_labels(preset: str, seed: int) -> list[dict]:
    """The ISAT labels `generate_scene` writes for (preset, seed), without the rest.

    Renders only the evaluation views (labels do not depend on appearance), so
    every preset's labels can be checked over many seeds cheaply.
    """
    plan = plan_scene(preset, seed)
    world, stems, cams, queries = plan.world, plan.stems, plan.cams, plan.queries
    out = []
    for i in plan.eval_ids:
        part_id, _ = render_truth(world, cams[i])
        out.append(
            isat_label(
                part_id,
                queries,
                f"{stems[i]}.jpg",
                f"label/{preset}_s{seed}",
                _min_px(cams[i], 0.002, 12),
            )
        )
    return out

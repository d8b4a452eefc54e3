"""Render every training view under N appearances (docs/method.md §3).

Reads reconstruct. Chooses N−1 novel target appearances (the paper's ids for the
seven PT-OVS scenes, else by render quality and embedding diversity, or an explicit
id list), then renders each train view i under the targets' embeddings and its own
(Ĩ_i^j = f_render(I_i, l_j), Ĩ_i^i), clamped RGB, one view at a time.

Per train view: `rgb [E, H, W, 3]` uint8 (slots nov1..nov{N−1}, then self) and
`l1_self` (per-pixel mean L1 of the self render). Root: `slots_json` (slot names
and target ids) and `selection_json` (ε_q, ε_d, candidates, each target's quality,
the minimum pairwise distance). A plain (not in-the-wild) field has no
appearances: only the self render is made.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import torch

from ptovs.artifacts import Artifact, json_dataset
from ptovs.checkpoint import Checkpoint
from ptovs.field.appearance import (
    ORDERS,
    QUALITY_METRICS,
    min_pairwise_l1,
    paper_targets,
    render_error,
    select_targets,
)
from ptovs.field.render import WildField
from ptovs.raster import VERSION as RASTER_VERSION
from ptovs.raster import Camera, kernels_only_parallel
from ptovs.registry import scene_input, upstream
from ptovs.stage import stage_command

log = logging.getLogger(__name__)
SELECTIONS = ("quality+diversity", "quality", "diversity", "random")

NAME = "render-appearances"
VERSION = 1 + 100 * RASTER_VERSION


@dataclass(frozen=True)
class Config:
    n_appearances: int | Literal["auto"] = 4
    """N: N−1 novel appearances plus the self appearance (Table 4 explores 2–6);
    "auto": 1 when the photos share one appearance, else 4 (ptovs.fit)."""
    targets: str | tuple[str, ...] = "auto"
    """"auto" (the paper's ids on the seven PT-OVS scenes, else "select"), "paper",
    "select", "same" (every novel slot uses the view's own embedding: Table 4's
    ablation), or a list of N−1 train image ids."""
    quality_quantile: float = 0.25
    """ε_q = this quantile of the self-render error over the train images."""
    quality_metric: Literal["l1", "l1-relative", "dssim"] = "l1"
    """The self-render error ε_q thresholds: "l1" (the paper's words: mean absolute
    error; dark and colourless photos have the smallest), "l1-relative" (over the
    photo's mean intensity) or "dssim" (1 − SSIM of the luminance: blind to
    brightness and contrast)."""
    selection: Literal["quality+diversity", "quality", "diversity", "random"] = (
        "quality+diversity"
    )
    """Which of the paper's two constraints "select" applies (Table 4):
    "quality+diversity" (both), "quality" (no ε_d: a seeded random draw among the
    good renders), "diversity" (no ε_q), "random" (neither)."""
    seed: int = 0
    """Seeds the diversity sampling (Table 4 re-draws targets with 5 seeds)."""
    order: Literal["draw", "names"] = "draw"
    """The order the diversity sampling visits the good renders in: "draw" a
    seeded permutation of them (one photo crossing ε_q reorders every other), or
    "names" a seeded hash of each photo's name (a photo crossing ε_q changes the
    targets only where it wins a place)."""
    bgr_swap_renders: bool = False
    """Reproduce the authors' bug: store renders with R and B swapped."""
    backend: str = "auto"


@dataclass(frozen=True)
class Inputs:
    scene: Any = scene_input()
    field: Artifact = upstream("reconstruct")


def _as_uint8(rgb: torch.Tensor) -> np.ndarray:
    return (rgb.clamp(0, 1) * 255.0 + 0.5).to(torch.uint8).numpy()


def _resolve_ids(targets: Any, scene, k: int) -> list[str] | None:
    """Explicit or paper ids as train image names; None = select."""
    if isinstance(targets, str) and targets in ("select", "same"):
        return None
    if isinstance(targets, str) and targets in ("auto", "paper"):
        ids = paper_targets(scene.name)
        if ids is None:
            if targets == "paper":
                raise ValueError(
                    f"targets = 'paper': scene {scene.name!r} is not one of the seven "
                    "PT-OVS scenes; use targets = 'select' or a list of ids"
                )
            return None
    elif isinstance(targets, str):
        ids = tuple(t.strip() for t in targets.split(",") if t.strip())
    else:
        ids = tuple(targets)
    train = {v.name: v for v in scene.train_views()}
    train.update({v.stem: v for v in scene.train_views()})
    missing = [i for i in ids if i not in train]
    if missing:
        if targets == "auto":
            log.info("paper targets %s are not all train views: selecting", missing)
            return None
        raise ValueError(
            f"targets {missing} are not train images of {scene.name}; give train "
            "image names or stems (see `ptovs status` / the split TSV)"
        )
    if len(ids) != k:
        log.warning(
            "%d explicit targets for N - 1 = %d: using %d", len(ids), k, len(ids)
        )
    return [train[i].name for i in ids]


def _quality(
    field: WildField, scene, views, backend: str, metric: str = "l1"
) -> np.ndarray:
    from tqdm import tqdm

    q = np.zeros(len(views))
    for i, v in enumerate(
        tqdm(views, desc="self-render quality", leave=False, disable=None)
    ):
        rgb = field.render(
            Camera.from_view(v), field.embeddings_of([v.name]), backend=backend
        )[0]
        q[i] = render_error(rgb.numpy(), scene.load_image(v), metric)
    return q


def run(
    inputs: Inputs, config: Config, skip=frozenset(), ckpt: Checkpoint | None = None
) -> Iterator[tuple[str | None, dict]]:
    """Choose the targets, then yield each train view's renders."""
    # the same renders at any --threads (ptovs.raster.kernels_only_parallel)
    with kernels_only_parallel():
        yield from _run(inputs, config, skip, ckpt)


def _run(
    inputs: Inputs, config: Config, skip=frozenset(), ckpt: Checkpoint | None = None
) -> Iterator[tuple[str | None, dict]]:
    if config.n_appearances < 1:
        raise ValueError(f"n_appearances must be >= 1, got {config.n_appearances}")
    if config.quality_metric not in QUALITY_METRICS:
        raise ValueError(
            f"render-appearances.quality_metric = {config.quality_metric!r}: "
            f"expected one of {', '.join(QUALITY_METRICS)}"
        )
    if config.order not in ORDERS:
        raise ValueError(
            f"render-appearances.order = {config.order!r}: expected one of "
            f"{', '.join(ORDERS)}"
        )
    if config.selection not in SELECTIONS:
        raise ValueError(
            f"render-appearances.selection = {config.selection!r}: expected one of "
            f"{', '.join(SELECTIONS)}"
        )
    scene = inputs.scene
    field = WildField.from_artifact(inputs.field)
    views = scene.train_views()
    if not views:
        raise ValueError(f"scene {scene.name} has no train views")
    k = config.n_appearances - 1
    state = ckpt.load() if ckpt is not None else None
    if state is not None and "slots" in state:  # resume: the same choice
        slots, targets, report = state["slots"], state["targets"], state["report"]
    else:
        report: dict = {
            "mode": config.targets if isinstance(config.targets, str) else "list"
        }
        if not field.wild:
            log.warning(
                "%s: plain field, no appearances to vary: self render only", scene.name
            )
            targets: list[str | None] = []
            report["note"] = "plain (not in-the-wild) field: self render only"
        elif config.targets == "same" or k == 0:
            targets = [None] * k  # None = the view's own embedding
        else:
            ids = _resolve_ids(config.targets, scene, k)
            if ids is None:
                q = _quality(field, scene, views, config.backend, config.quality_metric)
                emb = field.embeddings_of([v.name for v in views]).numpy()
                ids, sel = select_targets(
                    [v.name for v in views],
                    q,
                    emb,
                    k,
                    config.quality_quantile,
                    config.seed,
                    use_quality="quality" in config.selection.split("+"),
                    use_diversity="diversity" in config.selection.split("+"),
                    order=config.order,
                )
                report.update(sel)
                report["mode"] = "select"
                report["quality_metric"] = config.quality_metric
            else:
                report["mode"] = "list"
                report["chosen"] = ids
                emb = field.embeddings_of(ids).numpy()
                report["min_pairwise_l1"] = min_pairwise_l1(emb)
            targets = list(ids)
        slots = [f"nov{i + 1}" for i in range(len(targets))] + ["self"]
        log.info("%s: appearance slots %s <- targets %s", scene.name, slots, targets)
        if ckpt is not None:
            ckpt.save({"slots": slots, "targets": targets, "report": report})

    for v in views:
        if v.name in skip:
            continue
        cam = Camera.from_view(v)
        if field.wild:
            names = [t if t is not None else v.name for t in targets] + [v.name]
            rgb = field.render(cam, field.embeddings_of(names), backend=config.backend)
        else:
            rgb = field.render(cam, backend=config.backend)
        img = torch.from_numpy(scene.load_image(v))
        l1 = float((rgb[-1] - img).abs().mean())
        out = _as_uint8(rgb)
        if config.bgr_swap_renders:  # the authors' bug, on request
            out = out[..., ::-1].copy()
        yield v.name, {"rgb": out, "l1_self": np.float32(l1)}
    report["slots"] = slots
    report["targets"] = targets
    yield (
        None,
        {
            "slots_json": json_dataset({"slots": slots, "targets": targets}),
            "selection_json": json_dataset(report),
        },
    )


def _count(inputs: Inputs, config: Config) -> int:
    return len(inputs.scene.train_views())


command = stage_command(NAME, VERSION, Config, Inputs, run, count=_count)

__all__ = ["Config", "Inputs", "command", "run"]

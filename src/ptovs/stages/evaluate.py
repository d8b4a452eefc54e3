"""Score the query masks against the scene's labels: mIoU, mPA, mP (docs/method.md §9).

    ptovs evaluate --data data/bench_s0 [--variant male --variant langsplat ...]

Pairs are (labelled image, category of that image's label); each is scored at the
level the query chose. Ground truth: the label's polygons filled at full size,
OR-ed per category, resized to the render size (nearest by default). Per pair:
IoU = |P∧G|/|P∨G|; PA = (TP + TN)/(H·W) (binary pixel accuracy, background
included); P = TP/(TP + FP). mIoU, mPA and mP are the means over all pairs of the
scene (images with more categories weigh more).

Conventions (recorded in the results): an empty prediction gives IoU = 0 and P = 0;
a pair whose ground truth is empty at the render size is skipped with a warning;
a label category the query stage was not asked about is an error.

The stage runs `query` with its default texts (every label category) on the
labelled views; the command runs whatever of the chain is missing first (so
`--variant langsplat` trains that baseline), prints a Markdown table with one row
per variant and writes it with the per-pair JSON (see --out).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from ptovs.artifacts import Artifact, json_dataset
from ptovs.errors import InputError
from ptovs.field.query import read_results
from ptovs.metrics import (
    CONVENTIONS,
    markdown_table,
    pair_metrics,
    read_metrics,
    summarise,
    write_report,
)
from ptovs.registry import scene_input, upstream
from ptovs.stage import CommandExtras, stage_command

log = logging.getLogger(__name__)

NAME = "evaluate"
VERSION = 1


@dataclass(frozen=True)
class Config:
    gt_resize: Literal["nearest", "bilinear"] = "nearest"


@dataclass(frozen=True)
class Inputs:
    scene: Any = scene_input()
    query: Artifact = upstream("query")


def run(inputs: Inputs, config: Config) -> dict:
    from ptovs.scene import load_labels

    scene = inputs.scene
    meta, views = read_results(inputs.query, ("mask", "level"))
    queries = list(meta["queries"])
    labelled = {v.name for v in scene.labelled_views()} if scene.labels_dir else set()
    pairs: list[dict] = []
    for name, data in views.items():
        if name not in labelled:
            continue
        view = scene.view(name)
        h, w = data["mask"].shape[1:]
        gts = load_labels(scene, view, (h, w), gt_resize=config.gt_resize)
        for cat, gt in gts.items():
            if cat not in queries:
                raise InputError(
                    f"evaluate: label category {cat!r} in "
                    f"{scene.labels_dir / (view.stem + '.json')} (image {name}) was not "
                    f"queried (queries: {', '.join(queries[:8])}"
                    f"{', ...' if len(queries) > 8 else ''}); rerun query with its "
                    "default texts (every label category), or fix the category's name"
                )
            if not gt.any():
                log.warning(
                    "evaluate: %s %r has an empty ground truth: skipped", name, cat
                )
                continue
            qi = queries.index(cat)
            pred = data["mask"][qi].astype(bool)
            rec = {
                "view": name,
                "query": cat,
                "level": meta["levels"][int(data["level"][qi])],
            }
            rec.update(pair_metrics(pred, gt))
            rec.update(pred_pixels=int(pred.sum()), gt_pixels=int(gt.sum()))
            pairs.append(rec)
    if not pairs:
        raise InputError(
            f"evaluate: no labelled (image, category) pair among the {len(views)} "
            f"queried views of {scene.name}; the scene needs label/<scene>/*.json"
        )
    summary = summarise(pairs)
    summary["conventions"] = CONVENTIONS
    log.info(
        "evaluate %s: mIoU %.3f mPA %.3f mP %.3f over %d pairs",
        scene.name, summary["miou"], summary["mpa"], summary["mp"], len(pairs),
    )  # fmt: skip
    return {
        "pairs_json": json_dataset(pairs),
        "metrics_json": json_dataset(summary),
    }


def _report(ctx: Any, ref: Any, arts: dict[str, Artifact], *, out: Path | None) -> None:
    """evaluate.md and evaluate.json (one row per variant), and the table."""
    import click

    rows = {variant: {ref.name: read_metrics(art)[0]} for variant, art in arts.items()}
    paths = {variant: str(art.path) for variant, art in arts.items()}
    folder = out or ctx.work_dir / ref.name
    write_report(folder, rows, {"artifacts": paths, "conventions": CONVENTIONS})
    click.echo(markdown_table(rows))
    click.echo(f"evaluate: {folder / 'evaluate.md'}")


def _options() -> tuple:
    import click

    return (
        click.option(
            "--out",
            type=click.Path(path_type=Path),
            default=None,
            help="Folder for evaluate.md and evaluate.json (default: <work>/<scene>).",
        ),
    )


def label_key(config: Config, scene_ref: Any) -> dict[str, str]:
    """The ground truth is the label files: evaluate is keyed by their content
    (the scene fingerprint leaves labels out, so label edits retrain nothing)."""
    from ptovs.scene import labels_digest

    return {"labels": labels_digest(scene_ref.load())}


command = stage_command(
    NAME,
    VERSION,
    Config,
    Inputs,
    run,
    kind="single",
    extra_key=label_key,
    extras=CommandExtras(
        options=_options(),
        variant="many",
        upstream=True,
        force_also=("query",),
        report=_report,
        force_help="Recompute query and evaluate.",
    ),
)

__all__ = ["Config", "Inputs", "command", "run"]

"""Open-vocabulary queries: text in, per-view relevancy maps and masks out (docs/method.md §8).

    ptovs query --data data/bench_s0 "Dome" "Ionic Column" [--views 00000003 ...]

For each view, the language field is rendered once (every level × appearance code,
one pass of the rasterizer) and decoded against the queries, the canonical phrases
("object", "things", "scene", "sky", "building") and the background phrases; each
query then gets relevancy at temperature 10 (in a sigmoid form that never
overflows), the background filter, the post-ensemble over appearances, the mean
filter (k = 20), the level with the highest score, the threshold τ = 0.4 under the
relative rule (min-max rescale, then clip(2n − 1) > τ, i.e. n > 0.7) and a 7×7
majority filter. See `ptovs.field.relevancy` for each step and its options.

Decoding (`decode`): "table" tabulates the decoder's cosine with each phrase once
per call on a `table_size`³ grid over the ball of rendered codes, turns it into
each query's relevancy and background tables, and interpolates those per pixel;
"exact" decodes every pixel. docs/findings.md gives the table's error and how
often it changes a mask pixel.

Defaults: `queries` empty = every category of the scene's labels; `views` empty =
the labelled views (every train view when the scene has no labels). The stage
writes, per view, `smoothed` [Q, L, H, W] float16, `mask` [Q, H, W] uint8,
`level` [Q] and `score` [Q]; the `ptovs query` command also writes a heatmap, a mask
and an overlay PNG per (view, query) and a results JSON (see --out).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ptovs.artifacts import Artifact, json_dataset, write_atomic
from ptovs.field.query import (
    Querier,
    QueryConfig,
    encoder_name,
    read_results,
    resolve_queries,
    resolve_views,
)
from ptovs.registry import scene_input, upstream
from ptovs.stage import CommandExtras, stage_command

log = logging.getLogger(__name__)

NAME = "query"
VERSION = 2  # 2: per-query relevancy tables

Config = QueryConfig  # the [query] section (ptovs.field.query, which Querier reads)


@dataclass(frozen=True)
class Inputs:
    scene: Any = scene_input()
    reconstruct: Artifact = upstream("reconstruct")
    ae: Artifact = upstream("train-ae")
    male: Artifact = upstream("train-male")


def run(inputs: Inputs, config: Config, skip: frozenset = frozenset()) -> Iterator:
    scene = inputs.scene
    queries = resolve_queries(config, scene)
    views = resolve_views(config, scene)
    querier = Querier(inputs, config, queries)
    log.info(
        "query: %d texts on %d views (%d levels × %d appearances, decode %s)",
        len(queries), len(views), len(querier.levels), len(querier.apps), config.decode,
    )  # fmt: skip
    yield (
        None,
        {
            "meta_json": json_dataset(
                {
                    "queries": queries,
                    "views": [v.name for v in views],
                    "levels": querier.levels,
                    "apps": querier.apps,
                    "phrases": querier.phrases,
                }
            )
        },
    )
    for view in views:
        if view.name in skip:
            continue
        t0 = time.perf_counter()
        results = querier.answer_view(view)
        yield (
            view.name,
            {
                "smoothed": np.stack([r.smoothed for r in results]).astype(np.float16),
                "mask": np.stack([r.mask for r in results]).astype(np.uint8),
                "level": np.array([r.level for r in results], np.int8),
                "score": np.array([r.score for r in results], np.float32),
                "seconds": np.array([time.perf_counter() - t0], np.float64),
            },
        )


def _count(inputs: Inputs, config: Config) -> int:
    return len(resolve_views(config, inputs.scene))


def text_key(config: Config, scene_ref: Any) -> dict[str, str]:
    """What query reads outside the scene fingerprint: the label files (its
    default texts and views) and the stand-in encoder's vocabulary (the text
    embeddings come from it)."""
    from ptovs.scene import labels_digest

    scene = scene_ref.load()
    keys = {"labels": labels_digest(scene)}
    if encoder_name(config, scene) != "synthetic":
        return keys  # the checkpoint (its content digest) keys through the features
    import hashlib

    path = Path(scene.root) / "synthetic" / "vocabulary.json"
    if not path.is_file():
        return keys | {"vocabulary": "missing"}  # the stage says what is wrong
    return keys | {"vocabulary": hashlib.sha256(path.read_bytes()).hexdigest()}


PICTURES = ("mask", "heatmap", "overlay")


def clear_previous(out: Path) -> int:
    """Remove the pictures an earlier run listed in `out`/results.json, so that a
    folder always holds one run: its results.json and exactly its pictures.

    The old results.json is read as untrusted: only files inside `out` named
    `*_{mask,heatmap,overlay}.png` are removed (then their emptied folders); other
    files stay. Returns how many pictures were removed.
    """
    import json

    path = out / "results.json"
    if not path.is_file():
        return 0
    try:
        records = json.loads(path.read_text()).get("results", [])
    except (OSError, ValueError, AttributeError):
        return 0
    root = out.resolve()
    removed = 0
    for rec in records if isinstance(records, list) else []:
        for kind in PICTURES:
            p = rec.get(kind) if isinstance(rec, dict) else None
            if not isinstance(p, str) or not p.endswith(f"_{kind}.png"):
                continue
            q = Path(p).resolve()
            if q.is_relative_to(root) and q.is_file() and not Path(p).is_symlink():
                q.unlink()
                removed += 1
                if q.parent != root and not any(q.parent.iterdir()):
                    q.parent.rmdir()
    path.unlink()
    return removed


def write_outputs(
    art: Artifact, scene: Any, out: Path, pictures: bool = True
) -> tuple[Path, list[dict]]:
    """Heatmap, mask and overlay PNGs per (view, query) and results.json under `out`.

    Returns the results JSON path and its records: one per (view, query) with the
    score, the level, the mask's pixel count and the picture paths.
    """
    import json

    from ptovs.visual import heatmap, overlay, slug, write_png

    keys = ("mask", "level", "score", "seconds")
    meta, views = read_results(art, (*keys, "smoothed") if pictures else keys)
    if clear_previous(out):
        log.info("%s: replaced the pictures of the previous run", out)
    records = []
    for name, data in views.items():
        view = scene.view(name)
        photo = scene.load_image(view) if pictures else None
        for qi, text in enumerate(meta["queries"]):
            level = int(data["level"][qi])
            mask = data["mask"][qi].astype(bool)
            rec = {
                "view": name,
                "query": text,
                "score": round(float(data["score"][qi]), 5),
                "level": meta["levels"][level],
                "mask_pixels": int(mask.sum()),
                "seconds": round(float(data["seconds"][0]), 4),
            }
            if pictures:
                base = out / view.stem / slug(text)
                smoothed = data["smoothed"][qi, level].astype(np.float32)
                write_png(
                    base.with_name(base.name + "_mask.png"), mask.astype(np.uint8) * 255
                )
                write_png(
                    base.with_name(base.name + "_heatmap.png"), heatmap(smoothed, photo)
                )
                write_png(
                    base.with_name(base.name + "_overlay.png"),
                    overlay(photo, mask, text, rec["score"]),
                )
                rec.update(
                    {k: str(base.with_name(f"{base.name}_{k}.png")) for k in PICTURES}
                )
            records.append(rec)
    path = out / "results.json"
    write_atomic(
        path, json.dumps({"artifact": str(art.path), "results": records}, indent=1)
    )
    return path, records


def _overrides(extra: dict[str, Any]) -> dict[str, Any]:
    """The command's texts and --views → the [query] section's queries and views."""
    over: dict[str, Any] = {}
    if extra["texts"]:
        over["queries"] = list(extra["texts"])
    if extra["view_names"]:
        over["views"] = list(extra["view_names"])
    return over


def _report(
    ctx: Any,
    ref: Any,
    arts: dict[str, Artifact],
    *,
    texts: tuple[str, ...],
    view_names: tuple[str, ...],
    out: Path | None,
    no_pictures: bool,
) -> None:
    """PNGs and results.json under --out, and one line per (view, query)."""
    import click

    ((variant, art),) = arts.items()
    folder = out or ctx.work_dir / ref.name / "query-out" / variant
    path, records = write_outputs(art, ref.load(), folder, pictures=not no_pictures)
    for r in records:
        click.echo(
            f"{r['view']}  {r['query']!r}: score {r['score']:.3f} "
            f"level {r['level']}, {r['mask_pixels']} px"
        )
    click.echo(f"query: {art.path}")
    click.echo(f"results: {path}")


def _options() -> tuple:
    import click

    return (
        click.argument("texts", nargs=-1),
        click.option(
            "--views",
            "view_names",
            multiple=True,
            metavar="NAME",
            help="A view (image name or stem) to query; repeatable (default: the "
            "labelled views, else every train view).",
        ),
        click.option(
            "--out",
            type=click.Path(path_type=Path),
            default=None,
            help="Folder for the PNGs and results.json (default: "
            "<work>/<scene>/query-out/<variant>).",
        ),
        click.option("--no-pictures", is_flag=True, help="Write results.json only."),
    )


command = stage_command(
    NAME,
    VERSION,
    Config,
    Inputs,
    run,
    count=_count,
    extra_key=text_key,
    extras=CommandExtras(
        options=_options(),
        variant="one",
        overrides=_overrides,
        report=_report,
        force_help="Recompute even if cached.",
    ),
)

__all__ = ["Config", "Inputs", "command", "run", "text_key", "write_outputs"]

"""Architectural-style recognition by voting over views (docs/method.md §10.2).

    ptovs style --data data/bench_s0 --candidates "Neoclassical,Georgian,Palladian"

Each candidate style is queried on sampled train views exactly as `query` answers
a text (relevancy, background filter, fusion over appearances, smoothing). Each
view votes for one style ("max_score": the style with the highest smoothed
score over levels and pixels, ties to the first listed; "pixel_count": the most
pixels predicted positive summed over the levels, the authors' evaluation
script), and the style with most votes wins (ties to the first listed). The
heatmap of each style on a view shows where it finds that style.

On a synthetic scene the default candidates are the scene's style vocabulary
(`synthetic.generate.scene_styles`); elsewhere --candidates is required.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import click
import numpy as np

from ptovs.apps import close_inputs, trained_chain
from ptovs.errors import InputError
from ptovs.field.relevancy import threshold
from ptovs.options import chain_options
from ptovs.settings import RunContext


def sample_views(scene, n: int, seed: int, which: str = "random") -> list:
    """`n` train views drawn without replacement (seeded), in scene order; or the
    labelled views ("eval")."""
    if which == "eval":
        views = scene.labelled_views()
        if not views:
            raise InputError(f"style: scene {scene.name} has no labelled views")
        return views[:n] if n > 0 else views
    views = scene.train_views()
    if not views:
        raise InputError(f"style: scene {scene.name} has no train views")
    if n <= 0 or n >= len(views):
        return views
    pick = np.random.default_rng(seed).choice(len(views), n, replace=False)
    return [views[i] for i in sorted(pick)]


def vote_of(results, styles: list[str], vote: str, config) -> tuple[str, list[float]]:
    """One view's vote and the per-style values it compared."""
    if vote == "max_score":
        values = [r.score for r in results]
    elif vote == "pixel_count":
        values = [
            float(
                sum(
                    threshold(m, config.threshold, config.threshold_mode).sum()
                    for m in r.smoothed
                )
            )
            for r in results
        ]
    else:
        raise ValueError(f"vote must be max_score or pixel_count, got {vote!r}")
    return styles[int(np.argmax(values))], values  # argmax: ties to the first


def recognise(
    chain, styles: list[str], views: list, vote: str = "max_score", on_view=None
) -> dict:
    """Vote over views; returns the record written as style.json.

    Args:
        chain: a chain with train-male built.
        styles: the candidate style texts.
        views: scene views to vote on.
        vote: "max_score" or "pixel_count".
        on_view: called as on_view(view, results) after each view (pictures).
    """
    from tqdm import tqdm

    from ptovs.field.query import Querier

    inputs = chain.inputs("query")
    config = chain.config("query")
    try:
        querier = Querier(inputs, config, styles)
        per_view, votes = [], dict.fromkeys(styles, 0)
        t0 = time.perf_counter()
        for view in tqdm(views, desc="style", unit="view", leave=False):
            results = querier.answer_view(view, styles)
            winner, values = vote_of(results, styles, vote, config)
            votes[winner] += 1
            per_view.append(
                {"view": view.name, "vote": winner,
                 "values": {s: round(v, 5) for s, v in zip(styles, values, strict=True)}}
            )  # fmt: skip
            if on_view is not None:
                on_view(view, results)
        seconds = time.perf_counter() - t0
    finally:
        close_inputs(inputs)
    ranking = sorted(styles, key=lambda s: (-votes[s], styles.index(s)))
    return {
        "winner": ranking[0],
        "ranking": ranking,
        "votes": votes,
        "vote": vote,
        "views": per_view,
        "seconds": round(seconds, 3),
    }


def vote_table(record: dict) -> str:
    n = len(record["views"])
    lines = ["| style | votes | share |", "|---|---|---|"]
    for s in record["ranking"]:
        v = record["votes"][s]
        lines.append(f"| {s} | {v} | {v / max(n, 1):.2f} |")
    return "\n".join(lines) + "\n"


def style_panel(
    photo: np.ndarray, results, styles: list[str], winner: str
) -> np.ndarray:
    """The photo and each style's heatmap side by side, labelled underneath."""
    import cv2

    from ptovs.visual import heatmap, to_uint8

    tiles = [to_uint8(photo)] + [heatmap(r.smoothed[r.level], photo) for r in results]
    names = ["photo"] + [
        f"{s}{' (vote)' if s == winner else ''}: {r.score:.3f}"
        for s, r in zip(styles, results, strict=True)
    ]
    h, w = tiles[0].shape[:2]
    font, fs = cv2.FONT_HERSHEY_SIMPLEX, max(0.35, w / 600)
    bar = max(18, int(28 * fs / 0.45))
    out = []
    for tile, name in zip(tiles, names, strict=True):
        strip = np.full((bar, w, 3), 24, np.uint8)
        cv2.putText(strip, name, (4, bar - 8), font, fs, (255, 255, 255), 1,
                    cv2.LINE_AA)  # fmt: skip
        out.append(np.vstack((tile, strip)))
    return np.hstack(out)


def check_styles(scene, styles: list[str]) -> None:
    """On a synthetic scene the stand-in knows its own style names only (any other
    embeds as noise): refuse the others, listing the styles (not the parts)."""
    if not scene.synthetic:
        return
    from ptovs.encoders import scene_encoder

    enc = scene_encoder(scene.root)
    unknown = [s for s in styles if not enc.knows(s)]
    if unknown:
        raise InputError(
            f"style: {unknown} not among the synthetic scene's styles; its "
            f'candidates: --candidates "{",".join(enc.styles)}" (the stand-in knows '
            "only those; real scenes use OpenCLIP, which takes any text)"
        )


def default_candidates(scene) -> list[str]:
    if scene.synthetic:
        from ptovs.encoders import scene_encoder

        styles = scene_encoder(scene.root).styles
        if styles:
            return styles
    raise InputError(
        "style: give the candidate styles, e.g. --candidates "
        '"Neoclassical,Georgian,Victorian Gothic,Palladian,Edwardian Baroque" '
        "(the paper asks an LLM for five per scene)"
    )


@click.command(name="style")
@chain_options(variant="one", force=None)
@click.option(
    "--candidates",
    default=None,
    help='Comma-separated style names, e.g. "Gothic,Baroque,Renaissance" '
    "(synthetic scenes: default their style vocabulary).",
)
@click.option("--images", "n_images", type=int, default=20, show_default=True,
              help="Views that vote (0: all).")  # fmt: skip
@click.option("--from", "which", type=click.Choice(["random", "eval"]),
              default="random", show_default=True,
              help="random: seeded sample of train views; eval: the labelled views "
              "(the authors' script).")  # fmt: skip
@click.option("--seed", type=int, default=0, show_default=True,
              help="Seed of the view sample.")  # fmt: skip
@click.option("--vote", type=click.Choice(["max_score", "pixel_count"]),
              default="max_score", show_default=True,
              help="What a view votes by (see the module doc).")  # fmt: skip
@click.option("--pictures", type=int, default=3, show_default=True,
              help="Views for which the per-style heatmaps are saved.")  # fmt: skip
@click.option("--out", type=click.Path(path_type=Path), default=None,
              help="Folder for style.json, style.md and the heatmaps (default: "
              "<work>/<scene>/style-out/<variant>).")  # fmt: skip
@click.pass_obj
def command(
    obj: RunContext,
    scene_name: str | None,
    data: Path | None,
    candidates: str | None,
    n_images: int,
    which: str,
    seed: int,
    vote: str,
    pictures: int,
    out: Path | None,
    variant: str,
    sets: tuple[str, ...],
) -> None:
    """Recognise a landmark's architectural style by voting over views.

    Each candidate style is queried on sampled views like `ptovs query`; each
    view votes for the style it scores highest, and the most-voted style wins.
    Prints the vote table; writes style.json (votes, per-view values), style.md
    and, for the first --pictures views, the photo beside each style's heatmap.
    Runs any missing stage of the chain first.
    """
    from ptovs.artifacts import write_atomic
    from ptovs.outputs import check_output_dir
    from ptovs.visual import heatmap, slug, write_png

    if out is not None:
        check_output_dir("--out", out)
    chain, ref = trained_chain(obj, scene_name, data, variant, sets)
    scene = ref.load()
    if candidates:
        styles = list(
            dict.fromkeys(c.strip() for c in candidates.split(",") if c.strip())
        )
    else:
        styles = default_candidates(scene)
    if len(styles) < 2:
        raise InputError("style: give at least two candidate styles")
    check_styles(scene, styles)
    views = sample_views(scene, n_images, seed, which)
    folder = out or obj.work_dir / ref.name / "style-out" / variant
    saved: list[tuple] = []

    def keep(view, results):
        if len(saved) < pictures:
            saved.append((view, results))

    record = recognise(chain, styles, views, vote, keep)
    pics = []
    for view, results in saved:
        photo = scene.load_image(view)
        winner = next(v["vote"] for v in record["views"] if v["view"] == view.name)
        path = folder / f"{view.stem}_styles.png"
        write_png(path, style_panel(photo, results, styles, winner))
        pics.append(str(path))
        for s, r in zip(styles, results, strict=True):
            write_png(folder / view.stem / f"{slug(s)}_heatmap.png",
                      heatmap(r.smoothed[r.level], photo))  # fmt: skip
    record.update(scene=ref.name, variant=variant, candidates=styles, pictures=pics)
    write_atomic(folder / "style.json", json.dumps(record, indent=1))
    table = vote_table(record)
    write_atomic(folder / "style.md", table)
    click.echo(table)
    click.echo(
        f"style: {record['winner']} ({record['votes'][record['winner']]} of "
        f"{len(views)} views, {record['seconds']:.1f} s) -> {folder / 'style.json'}"
    )

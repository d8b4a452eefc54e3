"""Open-vocabulary queries: text in, per-view relevancy maps and masks out (PAPER_SPEC.md §8).

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
"exact" decodes every pixel. docs/benchmarks.md gives the table's error and how
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
from typing import Any, Literal

import numpy as np
import torch

from ptovs.artifacts import Artifact, json_dataset, read_json_dataset, write_atomic
from ptovs.encoders import Encoder, get_encoder
from ptovs.errors import InputError
from ptovs.field.language import CODE_DIM
from ptovs.field.relevancy import (
    BACKGROUND_PHRASES,
    CANONICAL,
    PhraseDecoder,
    QuerySettings,
    Selection,
    finish,
    score_maps,
    select,
)
from ptovs.field.render import WildField
from ptovs.raster import Camera, render
from ptovs.stage import scene_input, stage_command, upstream
from ptovs.stages.train_ae import load_autoencoder
from ptovs.stages.train_male import load_codes

log = logging.getLogger(__name__)

NAME = "query"
VERSION = 2  # 2: per-query relevancy tables


@dataclass(frozen=True)
class Config:
    queries: tuple[str, ...] = ()
    """Query texts (empty: every category of the scene's labels)."""
    views: tuple[str, ...] = ()
    """Views by name or stem (empty: the labelled views, else every train view)."""
    appearances: tuple[str, ...] = ()
    """Slots used, e.g. ("orig",) (empty: every slot train-male trained)."""
    canonical: tuple[str, ...] = CANONICAL
    temperature: float = 10.0
    background_filter: Literal["paper", "code", "off"] = "paper"
    fusion: Literal["weighted", "imglvlmax", "pixmax", "pixavg", "pixweighted"] = (
        "weighted"
    )
    smooth_kernel: int = 20
    threshold: float = 0.4
    threshold_mode: Literal["relative", "absolute"] = "relative"
    majority: int = 7
    """Majority-filter window (0 or 1: off)."""
    majority_exact: bool = False
    """Replicate the authors' window, which never counts the last row and column."""
    min_alpha: float = 0.5
    """Pixels where the field's accumulated opacity is below this score 0: no
    surface there, so the rendered code (a near-zero blend) means nothing. The
    authors' scenes carry sky Gaussians; a field without them answers every query
    in the sky with the decoder's response to the zero code. 0 = off."""
    decode: Literal["table", "exact"] = "table"
    table_size: int = 64
    encoder: Literal["auto", "synthetic", "openclip"] = "auto"
    """Text encoder: "auto" = the stand-in on synthetic scenes, OpenCLIP elsewhere
    (it must be the one extract-features used)."""
    clip_model: str = "ViT-B-16"
    clip_checkpoint: str = ""
    device: str = "cpu"
    backend: str = "auto"

    def settings(self) -> QuerySettings:
        return QuerySettings(
            temperature=self.temperature,
            background_filter=self.background_filter,
            fusion=self.fusion,
            smooth_kernel=self.smooth_kernel,
            threshold=self.threshold,
            threshold_mode=self.threshold_mode,
            majority=self.majority,
            majority_exact=self.majority_exact,
        )


@dataclass(frozen=True)
class Inputs:
    scene: Any = scene_input()
    reconstruct: Artifact = upstream("reconstruct")
    ae: Artifact = upstream("train-ae")
    male: Artifact = upstream("train-male")


def encoder_name(config: Config, scene: Any) -> str:
    """ "synthetic" or "openclip": the text encoder `config.encoder` means here."""
    if config.encoder == "auto":
        return "synthetic" if scene.synthetic else "openclip"
    return config.encoder


def text_encoder(config: Config, scene: Any) -> Encoder:
    if encoder_name(config, scene) == "synthetic":
        from ptovs.encoders.synthetic import SyntheticEncoder

        return SyntheticEncoder.from_scene(scene.root)
    return get_encoder(
        "openclip",
        model=config.clip_model,
        checkpoint=config.clip_checkpoint,
        device=config.device,
    )


def resolve_queries(config: Config, scene: Any) -> list[str]:
    if config.queries:
        queries = [q.strip() for q in config.queries]
    else:
        from ptovs.scene import label_categories

        if scene.labels_dir is None or not scene.labelled_views():
            raise InputError(
                f"query: no texts given and scene {scene.name} has no labels; "
                'pass texts: ptovs query --data ... "Dome" "Column"'
            )
        queries = label_categories(scene)
    if any(not q for q in queries):
        raise InputError("query: empty query text")
    return list(dict.fromkeys(queries))


def resolve_views(config: Config, scene: Any) -> list:
    if config.views:
        out = []
        for name in config.views:
            try:
                out.append(scene.view(name))
            except (KeyError, InputError) as exc:
                raise InputError(
                    f"query: no view {name!r} in {scene.root}; give an image name "
                    "or stem from dense/images"
                ) from exc
        return out
    return scene.labelled_views() or scene.train_views()


def check_vocabulary(encoder: Encoder, phrases: list[str]) -> None:
    """The stand-in encoder embeds unknown phrases as noise: refuse them clearly."""
    knows = getattr(encoder, "knows", None)
    if knows is None:
        return
    unknown = [p for p in phrases if not knows(p)]
    if unknown:
        vocab = ", ".join(repr(p) for p in encoder.phrases)  # type: ignore[attr-defined]
        raise InputError(
            f"query: {unknown} not in the synthetic scene's vocabulary "
            f"(synthetic/vocabulary.json: {vocab}, plus the generic phrases); the "
            "stand-in encoder knows only those. Real scenes use OpenCLIP, which "
            "takes any text."
        )


class Querier:
    """Renders a view's code maps and answers queries on them (shared by select)."""

    def __init__(self, inputs: Inputs, config: Config, queries: list[str]):
        self.config = config
        self.queries = queries
        codes, meta = load_codes(inputs.male)  # [P, L, A, 3]
        apps = list(meta["apps"])
        if config.appearances:
            missing = [a for a in config.appearances if a not in apps]
            if missing:
                raise InputError(
                    f"query: appearances {missing} not trained (have {apps})"
                )
            idx = [apps.index(a) for a in config.appearances]
            codes, apps = codes[:, :, idx], list(config.appearances)
        self.levels, self.apps = list(meta["levels"]), apps
        self.colors = codes.reshape(len(codes), -1).contiguous()
        self.field = WildField.from_artifact(inputs.reconstruct)
        self.gaussians = self.field.gaussians
        if len(self.gaussians) != len(codes):
            raise InputError(
                f"query: train-male holds {len(codes)} Gaussians, reconstruct "
                f"{len(self.gaussians)}; rerun train-male"
            )
        encoder = text_encoder(config, inputs.scene)
        phrases = list(
            dict.fromkeys([*queries, *config.canonical, *BACKGROUND_PHRASES])
        )
        check_vocabulary(encoder, phrases)
        self.phrases = phrases
        self.index = {p: i for i, p in enumerate(phrases)}
        emb = torch.from_numpy(np.asarray(encoder.encode_texts(phrases), np.float32))
        ae = load_autoencoder(inputs.ae)
        ae.eval()
        self.decoder = PhraseDecoder(
            ae.decode, emb, mode=config.decode, size=config.table_size
        )
        self.settings = config.settings()
        bg = list(BACKGROUND_PHRASES)
        if config.background_filter == "code":
            bg = ["sky"]
        self.bg = [self.index[p] for p in bg]
        self.canonical = [self.index[p] for p in config.canonical]
        self._tables: dict[tuple, torch.Tensor] = {}

    @torch.no_grad()
    def code_maps(self, view) -> tuple[torch.Tensor, torch.Tensor]:
        """[L, A, H, W, 3] rendered codes (not renormalised, PAPER_SPEC.md §8) and
        the [H, W] accumulated opacity, for a scene view or a `Camera`."""
        out = render(
            self.gaussians,
            view if isinstance(view, Camera) else Camera.from_view(view),
            self.colors,
            depth=False,
            backend=self.config.backend,
        )
        h, w = out.image.shape[:2]
        img = out.image.reshape(h, w, len(self.levels), len(self.apps), CODE_DIM)
        return img.permute(2, 3, 0, 1, 4), out.alpha[..., 0]

    def query_table(self, query: int, image_queries: tuple[int, ...]) -> torch.Tensor:
        """[C, G, G, G]: a query's relevancy (and per-map background) on the grid.

        Both are functions of one pixel's code, so the table path looks up C ≤ 2
        values per pixel instead of K cosines; cached per (query, image queries).
        """
        key = (query, image_queries)
        if key not in self._tables:
            s, b = score_maps(
                self.decoder.grid_cosines,
                query,
                self.canonical,
                self.bg,
                self.settings,
                list(image_queries),
            )
            self._tables[key] = torch.stack([s] if b is None else [s, b]).contiguous()
        return self._tables[key]

    @torch.no_grad()
    def select(self, query: str, min_opacity: float = 0.0) -> Selection:
        """The 3-D query: decode every Gaussian's codes (no rendering) and select.

        Gaussians train-male never saw (zero codes) and those less opaque than
        `min_opacity` are never selected; see `ptovs.field.relevancy.select`.
        """
        q = self.index[query]
        n = len(self.colors)
        codes = self.colors.reshape(n, len(self.levels), len(self.apps), CODE_DIM)
        valid = codes.flatten(1).abs().amax(1) > 0
        if min_opacity > 0:
            valid &= self.gaussians.opacities.reshape(-1) >= min_opacity
        s, b = self.scores(codes.permute(1, 2, 0, 3), q, (q,))  # [L, A, P]
        return select(s, b, self.settings, valid)

    def scores(
        self,
        codes: torch.Tensor,
        query: int,
        image_queries: tuple[int, ...],
        cos: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """(relevancy, per-code background or None) of codes [..., 3] for a query,
        through the table or exactly (`cos`: the codes' cosines, if decoded already)."""
        if self.config.decode == "exact":
            cos = self.decoder(codes) if cos is None else cos
            return score_maps(
                cos, query, self.canonical, self.bg, self.settings, list(image_queries)
            )
        vals = self.decoder.lookup(codes, self.query_table(query, image_queries))
        return vals[..., 0], (vals[..., 1] if vals.shape[-1] > 1 else None)

    def answer_view(self, view, queries: list[str] | None = None):
        codes, alpha = self.code_maps(view)
        support = None
        if self.config.min_alpha > 0:
            support = (alpha >= self.config.min_alpha).float()
        queries = queries or self.queries
        qidx = tuple(self.index[q] for q in queries)
        # exact decoding: every phrase's cosine once for all the queries
        cos = self.decoder(codes) if self.config.decode == "exact" else None
        return [
            finish(*self.scores(codes, q, qidx, cos), self.settings, support)
            for q in qidx
        ]


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


def read_results(
    art: Artifact, keys: tuple[str, ...] | None = None
) -> tuple[dict, dict[str, dict[str, np.ndarray]]]:
    """(meta, {view name: its datasets}) of a query artifact (only `keys` if given)."""
    meta = read_json_dataset(art.root()["meta_json"])
    return meta, {
        name: art[name] if keys is None else art.read(name, keys)
        for name in meta["views"]
        if name in art
    }


def text_key(config: Config, scene_ref: Any) -> dict[str, str]:
    """The stand-in encoder's vocabulary is outside the scene fingerprint, but
    the text embeddings come from it: key query artifacts by its content."""
    scene = scene_ref.load()
    if encoder_name(config, scene) != "synthetic":
        return {}  # the checkpoint path is in the config
    import hashlib

    path = Path(scene.root) / "synthetic" / "vocabulary.json"
    if not path.is_file():
        return {"vocabulary": "missing"}  # the stage itself says what is wrong
    return {"vocabulary": hashlib.sha256(path.read_bytes()).hexdigest()}


stage_cmd = stage_command(
    NAME, VERSION, Config, Inputs, run, count=_count, extra_key=text_key
)


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
                    {
                        k: str(base.with_name(f"{base.name}_{k}.png"))
                        for k in ("mask", "heatmap", "overlay")
                    }
                )
            records.append(rec)
    path = out / "results.json"
    write_atomic(
        path, json.dumps({"artifact": str(art.path), "results": records}, indent=1)
    )
    return path, records


def _command():

    import click

    from ptovs.config import merge
    from ptovs.stage import Chain, RunContext, execute, resolve_scene, scene_options
    from ptovs.variants import VARIANTS

    @click.command(name=NAME, help=stage_cmd.help)
    @click.argument("texts", nargs=-1)
    @scene_options
    @click.option(
        "--views",
        "view_names",
        multiple=True,
        metavar="NAME",
        help="A view (image name or stem) to query; repeatable (default: the "
        "labelled views, else every train view).",
    )
    @click.option(
        "--variant",
        type=click.Choice(list(VARIANTS)),
        default="male",
        show_default=True,
        help="Which trained field to query (see `ptovs train --variant`).",
    )
    @click.option(
        "--set",
        "sets",
        multiple=True,
        metavar="STAGE.KEY=VALUE",
        help="Override a config value of any stage (repeatable), e.g. "
        "query.fusion=pixmax.",
    )
    @click.option(
        "--out",
        type=click.Path(path_type=Path),
        default=None,
        help="Folder for the PNGs and results.json (default: "
        "<work>/<scene>/query-out/<variant>).",
    )
    @click.option("--no-pictures", is_flag=True, help="Write results.json only.")
    @click.option("--force", is_flag=True, help="Recompute even if cached.")
    @click.pass_obj
    def command(
        obj: RunContext,
        texts: tuple[str, ...],
        scene_name: str | None,
        data: Path | None,
        view_names: tuple[str, ...],
        variant: str,
        sets: tuple[str, ...],
        out: Path | None,
        no_pictures: bool,
        force: bool,
    ) -> None:
        from ptovs.cli import ALL_STAGES, _split_sets
        from ptovs.variants import variant_sets

        over: dict[str, Any] = {}
        if texts:
            over["queries"] = list(texts)
        if view_names:
            over["views"] = list(view_names)
        ctx = RunContext(obj.work_dir, merge(obj.config, {NAME: over}), obj.force)
        ref = resolve_scene(ctx, scene_name, data)
        split = _split_sets(sets, (*ALL_STAGES, NAME))
        chain = Chain(ctx, ref, variant_sets(variant, split))
        art = execute(chain, NAME, force=force or obj.force)
        try:
            folder = out or obj.work_dir / ref.name / "query-out" / variant
            path, records = write_outputs(
                art, ref.load(), folder, pictures=not no_pictures
            )
            for r in records:
                click.echo(
                    f"{r['view']}  {r['query']!r}: score {r['score']:.3f} "
                    f"level {r['level']}, {r['mask_pixels']} px"
                )
            click.echo(f"query: {art.path}")
            click.echo(f"results: {path}")
        finally:
            art.close()

    return command


command = _command()

__all__ = [
    "Config",
    "Inputs",
    "Querier",
    "read_results",
    "resolve_queries",
    "resolve_views",
    "run",
]

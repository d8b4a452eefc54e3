"""Answering text queries on a trained language field (docs/method.md §8).

The readers of the language chain's artifacts that more than one command uses: the
`query` stage, `evaluate`, the applications (`select`, `style`, `roam`) and the
benchmarks. A `Querier` holds a trained field (reconstruct geometry, train-male
codes, the train-ae decoder) and a text encoder, and answers queries on rendered
views (`answer_view`) or on the Gaussians themselves (`select`). `QueryConfig` is
the `[query]` config section; `read_results` reads a query artifact back.

How the codes are decoded (`decode`: "table" or "exact") is decided in one place,
`Querier.scorer`; `ptovs.field.relevancy` has each step and its options.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import torch

from ptovs.artifacts import Artifact, read_json_dataset
from ptovs.encoders import Encoder, get_encoder
from ptovs.errors import InputError
from ptovs.field.language import CODE_DIM, load_codes
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
from ptovs.nets.autoencoder import load_autoencoder
from ptovs.raster import Camera, blend_weights, render


@dataclass(frozen=True)
class QueryConfig:
    """The `[query]` section: which texts and views, and every relevancy knob."""

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
    threshold_mode: Literal["relative", "absolute", "stable"] = "relative"
    """"relative": clip(2n − 1) > threshold on the min-max rescaled map n (the
    authors'); "absolute": Ŝ ≥ threshold; "stable": the relative rule at the cut
    within ± 0.2 of threshold where the mask's area changes least with the cut."""
    peak_quantile: float = 1.0
    """A map's peak (for the level choice, the relative threshold's top and the
    score): this quantile of its smoothed scores, or of the Gaussians' scores in
    `select`; 1 = the maximum, as the paper. Below 1 the peak is a property of the
    map's top, not of one pixel or one Gaussian (docs/guide.md, "How steady the
    answers are")."""
    level_softness: float = 0.0
    """0: the level with the highest peak, as the paper. > 0: the levels' maps blended
    with weights softmax(peak / this) before the threshold, so levels whose peaks
    nearly tie give a mask between theirs instead of one or the other."""
    majority: int = 7
    """Majority-filter window (0 or 1: off)."""
    majority_exact: bool = False
    """Replicate the authors' window, which never counts the last row and column."""
    filter_ref: float = 680.0
    """The image short side (px) at which `smooth_kernel` and `majority` are given;
    both scale with each image's short side (the majority window to the nearest
    odd size). 680 (chosen on the accuracy instrument's dev seeds): 20 px and 7 px
    at 680 px, 10 and 3 at the authors' 340-px photos. 340 = the authors' pixel
    values at their r = 2 size, exactly. 0 = fixed pixel sizes whatever the image."""
    min_alpha: float = 0.5
    """Pixels where the field's accumulated opacity is below this score 0: no
    surface there, so the rendered code (a near-zero blend) means nothing. The
    authors' scenes carry sky Gaussians; a field without them answers every query
    in the sky with the decoder's response to the zero code. 0 = off."""
    decode: Literal["table", "exact"] = "table"
    table_size: int = 64
    encoder: Literal["auto", "synthetic", "openclip"] = "auto"
    """Text encoder: "auto" = the one extract-features made the features with
    (recorded in them; before that record: the stand-in on synthetic scenes,
    OpenCLIP elsewhere). One that cannot match the features is refused."""
    clip_model: str = ""
    """OpenCLIP model ("" = the features'; else it must equal theirs)."""
    clip_checkpoint: str = ""
    """OpenCLIP checkpoint ("" = the features'; else it must equal theirs)."""
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
            filter_ref=self.filter_ref,
            peak_quantile=self.peak_quantile,
            level_softness=self.level_softness,
        )


@dataclass(frozen=True)
class SelectOptions:
    """The 3-D selection's own knobs (`ptovs select`, `ptovs roam`): the 2-D path's
    support mask and mean filter have no grid to work on, so the selection gets
    a visibility gate and a smoothing over nearest Gaussians instead."""

    min_opacity: float = 0.0
    """Never select Gaussians less opaque than this."""
    min_visibility: float = 0.0
    """Never select Gaussians whose largest blend weight (α·T) in any train view
    is below this: hidden or faint ones, which no photo constrains."""
    smooth: int = 0
    """Average each Gaussian's fused score over its this many nearest selectable
    Gaussians (itself included) before thresholding; 0 or 1: off."""


def nearest_gaussians(means: torch.Tensor, valid: torch.Tensor, k: int) -> torch.Tensor:
    """[P, k] int64: each valid Gaussian's k nearest valid Gaussians by centre
    (itself first; exact, OpenCV's single k-d tree); invalid rows point at
    themselves. Fewer than k valid Gaussians: k shrinks to their count."""
    import cv2

    n = len(means)
    out = torch.arange(n)[:, None].repeat(1, max(k, 1))
    idx = torch.nonzero(valid).squeeze(1)
    if len(idx) == 0:
        return out
    k_eff = min(k, len(idx))
    pts = np.ascontiguousarray(means[idx].detach().numpy(), np.float32)
    if not np.isfinite(pts).all():
        raise FloatingPointError("select: a Gaussian centre is not finite")
    tree = cv2.flann_Index(pts, {"algorithm": 4, "leaf_max_size": 10})
    nn, _ = tree.knnSearch(pts, k_eff, params={})
    near = idx[torch.from_numpy(nn.astype(np.int64))]
    out = out[:, :k_eff].clone()
    out[idx] = near
    return out


def encoder_name(config: QueryConfig, scene: Any) -> str:
    """ "synthetic" or "openclip": the text encoder `config.encoder` means here."""
    if config.encoder == "auto":
        return "synthetic" if scene.synthetic else "openclip"
    return config.encoder


def resolve_text_encoder(
    config: QueryConfig, scene: Any, recorded: dict | None
) -> dict:
    """{"name", "model", "checkpoint"} of the text encoder query uses: the one
    the features were made with (`recorded`, from extract-features through
    train-ae), where the [query] section leaves it open; an explicit choice that
    differs from the record is an InputError (texts and features would live in
    different spaces, and every mask would be noise)."""
    rec = recorded or {}
    family = None
    if rec.get("name"):
        family = "openclip" if rec["name"] == "openclip" else "synthetic"
    name = family or encoder_name(config, scene)
    if config.encoder != "auto" and family and config.encoder != family:
        raise InputError(
            f"query.encoder = {config.encoder!r}, but the features were made with "
            f'{rec["name"]!r}; leave query.encoder at "auto" (it follows them) or '
            "rerun extract-features with that encoder"
        )
    out = {"name": name, "model": "", "checkpoint": ""}
    if name == "openclip":
        out["pretrained"] = rec.get("pretrained") or ""
        out["tokenizer"] = rec.get("tokenizer") or ""
        for key, given in (("model", config.clip_model),
                           ("checkpoint", config.clip_checkpoint)):  # fmt: skip
            was = rec.get(key) or ""
            if given and was and given != was:
                raise InputError(
                    f"query.clip_{key} = {given!r}, but the features were made with "
                    f"{was!r} (extract-features.clip_{key}); leave query.clip_{key} "
                    "empty: query follows the features"
                )
            out[key] = given or was
        out["model"] = out["model"] or "ViT-B-16"
    return out


def text_encoder(
    config: QueryConfig, scene: Any, recorded: dict | None = None
) -> Encoder:
    spec = resolve_text_encoder(config, scene, recorded)
    if spec["name"] == "synthetic":
        from ptovs.encoders import scene_encoder

        return scene_encoder(scene.root)
    return get_encoder(
        "openclip",
        model=spec["model"],
        checkpoint=spec["checkpoint"],
        device=config.device,
        pretrained=spec.get("pretrained", ""),
        tokenizer=spec.get("tokenizer", ""),
    )


def resolve_queries(config: QueryConfig, scene: Any) -> list[str]:
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


def resolve_views(config: QueryConfig, scene: Any) -> list:
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
        from ptovs.config import did_you_mean

        phrases = list(encoder.phrases)  # type: ignore[attr-defined]
        vocab = ", ".join(repr(p) for p in phrases)
        hint = did_you_mean(unknown[0], phrases)
        raise InputError(
            f"query: {unknown} not in the synthetic scene's vocabulary{hint} "
            f"(synthetic/vocabulary.json: {vocab}, plus the generic phrases); the "
            "stand-in encoder knows only those. Real scenes use OpenCLIP, which "
            "takes any text."
        )


class Querier:
    """Renders a view's code maps and answers queries on them, or selects Gaussians."""

    def __init__(self, inputs: Any, config: QueryConfig, queries: list[str]):
        """
        Args:
            inputs: the query stage's inputs: `.scene` (a loaded scene) and the
                `.reconstruct`, `.ae` (train-ae) and `.male` (train-male) artifacts.
            config: the `[query]` section.
            queries: the texts this querier answers by default.
        """
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
        ae_meta = read_json_dataset(inputs.ae.root()["meta_json"])
        encoder = text_encoder(config, inputs.scene, ae_meta.get("encoder_spec"))
        phrases = list(
            dict.fromkeys([*queries, *config.canonical, *BACKGROUND_PHRASES])
        )
        check_vocabulary(encoder, phrases)
        self.encoder = encoder
        self.phrases = phrases
        self.base = len(phrases)  # the phrases `truncate` never forgets
        self.index = {p: i for i, p in enumerate(phrases)}
        emb = torch.from_numpy(np.asarray(encoder.encode_texts(phrases), np.float32))
        ae = load_autoencoder(inputs.ae)
        ae.eval()
        self.decoder = PhraseDecoder(
            ae.decode, emb, mode=config.decode, size=config.table_size
        )
        try:
            self.settings = config.settings()
        except ValueError as exc:  # a knob out of range: the user's config
            raise InputError(str(exc)) from None
        bg = list(BACKGROUND_PHRASES)
        if config.background_filter == "code":
            bg = ["sky"]
        self.bg = [self.index[p] for p in bg]
        self.canonical = [self.index[p] for p in config.canonical]
        self._tables: dict[tuple, torch.Tensor] = {}
        self.scene = inputs.scene
        self._visibility: torch.Tensor | None = None

    def add_queries(self, texts: list[str]) -> list[str]:
        """Make texts answerable after construction (an interactive session): the
        new ones are checked against the encoder's vocabulary (InputError names
        the unknown), embedded and appended to the decoder. Returns the texts,
        stripped."""
        texts = [t.strip() for t in texts]
        if any(not t for t in texts):
            raise InputError("query: empty query text")
        new = [t for t in dict.fromkeys(texts) if t not in self.index]
        if new:
            check_vocabulary(self.encoder, new)
            emb = np.asarray(self.encoder.encode_texts(new), np.float32)
            self.decoder.add_phrases(torch.from_numpy(emb))
            for t in new:
                self.index[t] = len(self.phrases)
                self.phrases.append(t)
        return texts

    def truncate(self, n: int) -> None:
        """Forget every phrase added after the first `n` (with its decoder rows and
        cached tables): an interactive session's memory stays bounded. The
        queries given at construction are never forgotten."""
        n = max(n, self.base)
        if n >= len(self.phrases):
            return
        for t in self.phrases[n:]:
            del self.index[t]
        del self.phrases[n:]
        self.decoder.truncate(n)
        self._tables = {
            k: v
            for k, v in self._tables.items()
            if k[0] < n and all(q < n for q in k[1])
        }

    @torch.no_grad()
    def code_maps(self, view) -> tuple[torch.Tensor, torch.Tensor]:
        """[L, A, H, W, 3] rendered codes (not renormalised, docs/method.md §8) and
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
    def select(self, query: str, options: SelectOptions | None = None) -> Selection:
        """The 3-D query: decode every Gaussian's codes (no rendering) and select.

        Gaussians train-male never saw (zero codes), those less opaque than
        `options.min_opacity` and those whose largest blend weight in any train
        view is below `options.min_visibility` are never selected; the fused
        score is averaged over each Gaussian's `options.smooth` nearest selectable
        Gaussians. See `ptovs.field.relevancy.select`.
        """
        opt = options or SelectOptions()
        q = self.index[query]
        n = len(self.colors)
        codes = self.colors.reshape(n, len(self.levels), len(self.apps), CODE_DIM)
        valid = codes.flatten(1).abs().amax(1) > 0
        if opt.min_opacity > 0:
            valid &= self.gaussians.opacities.reshape(-1) >= opt.min_opacity
        if opt.min_visibility > 0:
            valid &= self.visibility() >= opt.min_visibility
        neighbors = None
        if opt.smooth > 1:
            neighbors = nearest_gaussians(self.gaussians.means, valid, opt.smooth)
        s, b = self.scorer(codes.permute(1, 2, 0, 3), (q,))(q)  # [L, A, P]
        return select(s, b, self.settings, valid, neighbors)

    @torch.no_grad()
    def visibility(self) -> torch.Tensor:
        """[P] each Gaussian's largest blend weight α·T over the pixels of the
        train views (0: no train view shows it); computed once."""
        if self._visibility is None:
            best = torch.zeros(len(self.gaussians))
            for view in self.scene.train_views():
                bw = blend_weights(
                    self.gaussians, Camera.from_view(view), backend=self.config.backend
                )
                indptr, _, vals = bw.csr()[1]
                rows = torch.repeat_interleave(
                    torch.arange(len(best)), torch.diff(indptr.long())
                )
                best.scatter_reduce_(0, rows, vals.float(), "amax")
            self._visibility = best
        return self._visibility

    def scorer(
        self, codes: torch.Tensor, image_queries: tuple[int, ...]
    ) -> Callable[[int], tuple[torch.Tensor, torch.Tensor | None]]:
        """query index → (relevancy, per-code background or None) of codes [..., 3].

        The one place `decode` is decided: "exact" decodes every phrase's cosine
        once for all the queries; "table" looks each query's relevancy (and
        background) up in its own table.
        """
        if self.config.decode == "exact":
            cos = self.decoder.exact(codes)
            return lambda q: score_maps(
                cos, q, self.canonical, self.bg, self.settings, list(image_queries)
            )

        def lookup(q: int) -> tuple[torch.Tensor, torch.Tensor | None]:
            vals = self.decoder.lookup(codes, self.query_table(q, image_queries))
            return vals[..., 0], (vals[..., 1] if vals.shape[-1] > 1 else None)

        return lookup

    def answer_view(self, view, queries: list[str] | None = None):
        codes, alpha = self.code_maps(view)
        support = None
        if self.config.min_alpha > 0:
            support = (alpha >= self.config.min_alpha).float()
        queries = queries or self.queries
        qidx = tuple(self.index[q] for q in queries)
        score = self.scorer(codes, qidx)
        return [finish(*score(q), self.settings, support) for q in qidx]


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


__all__ = [
    "QueryConfig",
    "Querier",
    "SelectOptions",
    "check_vocabulary",
    "encoder_name",
    "nearest_gaussians",
    "read_results",
    "resolve_queries",
    "resolve_views",
    "text_encoder",
]

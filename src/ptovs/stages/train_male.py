"""Train the multi-appearance language Gaussians on frozen geometry (docs/method.md §7):
by the training-free lift (default) or the paper's optimiser (`mode = "optimise"`).

Reads reconstruct (the Gaussians, frozen), train-ae (3-d codes of every table),
extract-features (each slot's segment maps) and uncertainty (unless `use_ut` and
`use_ua` are both off). Per level (all the features hold; s, m, l by default) each
Gaussian carries N × 3 codes: the original slot and the N − 1 novel appearances
(`appearances = "orig"`: the original only, LangSplat's recipe). All levels train
together in one sparse product; the losses are independent per level, so this is
exactly one model per level (see `ptovs.field.language`).

Loss `loss_variant = "paper"` (default): (1 − U_A)(1 − U_T)-weighted L1 over every
slot; `"code"`: the authors' code (U_A on the original only, 3:1 weighting). Pixels
a slot has no segment at are masked out. Adam (lr 0.0025, eps 1e-15), one view per
iteration from a seeded shuffled stack. Codes start from each Gaussian's weighted
mean target (`init = "data"`); `init = "zero"` is the authors' start.

Rendering: `renderer = "sparse"` (default) builds each view's blend weights W_v
once (kept in RAM up to `cache_mb`, spilled to memory-mapped files beyond it), so a
step is W_v · normalize(f) and W_vᵀ · g; `"raster"` rasterises every step.

Lift (`mode = "lift"`, the default: as accurate as the optimiser on
the accuracy benchmark, a quarter of its time): no optimisation; each Gaussian's feature
per level and slot is its blend- and mask-weighted mean 512-d segment feature over the
train views, Σ_v W_vᵀ (m_v ⊙ F_v[seg_v]) with the same weights m as the loss (so U_T
and U_A apply where `use_ut` / `use_ua` say), normalised and encoded by the AE. Per
view the weights are summed per (Gaussian, segment) and multiply the segment table
once, so no per-pixel 512-vector is formed. `mode = "lift-codes"` takes the same mean
over the 3-d target codes instead (the optimiser's starting point, `init = "data"`);
docs/findings.md measures both against the optimiser.

Stopping: up to `iterations` (30k, the paper's); with `stop = "plateau"` (default)
training ends once the epoch-mean loss (one pass over all views) has stayed above
(1 − `stop_rel`) × its best for `stop_patience` epochs. Checkpoints every
`checkpoint_every` iterations; a killed run resumes there.

Writes root datasets: `codes` [P_seen, L, N·3] float16 (normalised, as rendered)
for the Gaussians some train view sees, `seen_bits` (np.packbits of the [P] mask),
`meta_json` (levels, slots, P), `metrics_json` (iterations, time, final loss per
level, bytes per Gaussian; with the lift, the loss is over the first `loss_views`
views whose data fit `LIFT_LOSS_MB`, so memory and scratch stay flat as the
collection grows) and `log_epoch_loss`.
"""

from __future__ import annotations

import logging
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from tqdm import tqdm

from ptovs.artifacts import Artifact, json_dataset, read_json_dataset
from ptovs.checkpoint import Checkpoint
from ptovs.field.language import (
    CODE_DIM,
    MaleConfig,
    ViewStore,
    evaluate_loss,
    mask_weights,
    normalize_chunks,
    prepare_view,
    train_male,
    untrained,
)
from ptovs.field.lift import feature_lift_sums
from ptovs.field.render import WildField
from ptovs.memory import release
from ptovs.nets.autoencoder import load_autoencoder
from ptovs.raster import Camera, Gaussians, blend_weights
from ptovs.registry import scene_input, upstream
from ptovs.stage import stage_command

log = logging.getLogger(__name__)

NAME = "train-male"
VERSION = 3  # 3: the lift's loss over the views within LIFT_LOSS_MB (no spill)
LIFT_LOSS_MB = 1024
"""RAM for the views the lift's reported loss is taken over (at most cache_mb): the
first train views whose data fit (a 700×470 view's is 0.1-0.3 GB). The loss is a
figure only; the codes never depend on it."""


def _needs_uncertainty(c: Config) -> bool:
    return c.use_ut or c.use_ua


@dataclass(frozen=True)
class Config:
    appearances: Literal["all", "orig"] = "all"
    """Slots trained: the original and every novel render ("all"), or the original
    only ("orig": LangSplat's single-appearance field)."""
    mode: Literal["optimise", "lift", "lift-codes"] = "lift"
    """How codes are fitted. "lift" (default: it matches the
    optimiser on the accuracy benchmark in a fraction of the time): no training,
    each Gaussian's blend- and mask-weighted mean 512-d segment feature over the
    train views, normalised and encoded by the AE; "optimise": Adam on the loss
    (the paper; `--variant optimise` or `paper`); "lift-codes": the lift's mean over
    the 3-d target codes, normalize(Σ_v W_vᵀ (m ⊙ G_v)), which is the optimiser's
    data init (`--variant lift-codes`)."""
    loss_variant: Literal["paper", "code"] = "paper"
    use_ut: bool = True
    """Weight by (1 − U_T); off = factor 1 (Table 3 ablations)."""
    use_ua: bool = True
    """Weight by (1 − U_A); off = factor 1."""
    levels: tuple[str, ...] = ()
    """Levels to train (empty: every level extract-features stored)."""
    init: Literal["data", "zero"] = "data"
    """Start codes: "data" = each Gaussian's weighted mean target code (one sparse
    pass); "zero" = the authors' zero init, whose first gradient through
    x/(‖x‖+1e-9) is ~1e9 and stalls Adam for thousands of steps (docs/design.md)."""
    lr: float = 0.0025
    adam_eps: float = 1e-15
    iterations: int = 30000
    """The paper's count; the upper bound when `stop = "plateau"`."""
    stop: Literal["plateau", "fixed"] = "plateau"
    stop_rel: float = 1e-3
    """Plateau: an epoch counts as progress if its mean loss beats the best by this."""
    stop_patience: int = 3
    """Plateau: epochs without progress before stopping."""
    renderer: Literal["sparse", "raster"] = "sparse"
    cache_mb: int = 4096
    """RAM for the per-view blend weights; the rest is memory-mapped from disk."""
    backend: str = "auto"
    seed: int = 0
    checkpoint_every: int = 1000


@dataclass(frozen=True)
class Inputs:
    scene: Any = scene_input()
    reconstruct: Artifact = upstream("reconstruct")
    ae: Artifact = upstream("train-ae")
    features: Artifact = upstream("extract-features")
    uncertainty: Artifact | None = upstream("uncertainty", when=_needs_uncertainty)


def resolve_slots(
    meta: dict, ae_meta: dict, config: Config
) -> tuple[list[str], list[str], list[int]]:
    """(levels trained, slots trained, their indices in the feature levels)."""
    have = list(meta["levels"])
    levels = list(config.levels) or have
    missing = [lv for lv in levels if lv not in have]
    if missing:
        raise ValueError(
            f"train-male: levels {missing} are not in extract-features (has {have})"
        )
    apps = [a for a in meta["apps"] if a != "self"]
    if config.appearances == "orig":
        apps = ["orig"]
    absent = [a for a in apps if a not in ae_meta["apps"]]
    if absent or "orig" not in apps:
        raise ValueError(
            f"train-male: train-ae has no codes for {absent or ['orig']} "
            f"(has {ae_meta['apps']})"
        )
    return levels, apps, [have.index(lv) for lv in levels]


def prepare_views(
    inputs: Inputs,
    views: list,
    gaussians: Gaussians,
    apps: list[str],
    level_idx: list[int],
    config: Config,
    store: ViewStore | None,
    lift: torch.Tensor | None = None,
    rows: tuple[int, int] | None = None,
) -> torch.Tensor:
    """Blend weights and targets of every view into `store` (None: skipped);
    returns seen [P] bool. With `lift` ([p1 − p0, L, A, D]), also adds each view's
    weighted segment features of the Gaussians `rows` = (p0, p1) (default: all) to
    it (`mode = "lift"`)."""
    seen = torch.zeros(len(gaussians), dtype=torch.bool)
    for view in tqdm(
        views, desc="train-male views", unit="view", leave=False, disable=None
    ):
        name = view.name
        seg = inputs.features.read(name, [f"seg_{a}" for a in apps])
        codes = inputs.ae.read(name, [f"code_{a}" for a in apps])
        u_t = u_a = None
        if inputs.uncertainty is not None:
            u = inputs.uncertainty.read(name, ("u_t", "u_a"))
            u_t = u["u_t"] if config.use_ut else None
            u_a = u["u_a"] if config.use_ua else None
        segs = [seg[f"seg_{a}"][level_idx] for a in apps]
        if segs[0].shape[1:] != (view.height, view.width):
            raise ValueError(
                f"train-male: features of {name} are {segs[0].shape[2]}x"
                f"{segs[0].shape[1]}, the view is {view.width}x{view.height}; "
                "rerun extract-features"
            )
        bw = blend_weights(gaussians, Camera.from_view(view), backend=config.backend)
        seen |= bw.seen()
        if lift is not None:
            feats = inputs.features.read(name, [f"feat_{a}" for a in apps])
            valid = np.stack([s.reshape(len(s), -1).T >= 0 for s in segs], axis=-1)
            feature_lift_sums(
                _csr_rows(bw.csr()[1], *(rows or (0, len(gaussians)))),
                segs,
                [feats[f"feat_{a}"] for a in apps],
                mask_weights(valid, u_t, u_a, config.loss_variant),
                out=lift,
            )
        release()  # the view's freed buffers back to the system (ptovs.memory)
        if store is None:
            continue
        if store.full:  # not built: the sample is complete
            store.skip()
            continue
        store.add(
            prepare_view(
                bw,
                segs,
                [codes[f"code_{a}"] for a in apps],
                u_t,
                u_a,
                config.loss_variant,
            )
        )
    return seen


def _csr_rows(csr: tuple, p0: int, p1: int) -> tuple:
    """Rows p0..p1 of a CSR triple (indptr, indices, values)."""
    indptr, idx, val = csr
    a, b = int(indptr[p0]), int(indptr[p1])
    return indptr[p0 : p1 + 1] - indptr[p0], idx[a:b], val[a:b]


def _encode_lift(
    lift: torch.Tensor, model: torch.nn.Module
) -> tuple[torch.Tensor, dict, dict]:
    """Codes [P, L·A·3] of the lifted features [P, L, A, D]: each sum normalised to
    a unit feature and encoded by the AE `model` (zero sums stay zero codes)."""
    t0 = time.perf_counter()
    n, n_lv, n_app, dim = lift.shape
    x = lift.reshape(-1, dim)
    norm = x.norm(dim=1)
    reached = norm > 0
    codes = torch.zeros(len(x), CODE_DIM)
    with torch.no_grad():
        for start in range(0, len(x), 65536):
            sl = slice(start, start + 65536)
            hit = reached[sl]
            if hit.any():
                part = x[sl][hit] / norm[sl][hit, None]
                codes[start : start + len(hit)][hit] = model.encode(part)
    f = codes.reshape(n, n_lv * n_app * CODE_DIM)
    return f, *untrained(
        "lift: weighted mean segment feature per Gaussian, encoded",
        time.perf_counter() - t0,
    )


def run(inputs: Inputs, config: Config, ckpt: Checkpoint | None = None) -> dict:
    """Train the codes; return the root datasets."""
    scene = inputs.scene
    meta = read_json_dataset(inputs.features.root()["levels_json"])
    ae_meta = read_json_dataset(inputs.ae.root()["meta_json"])
    levels, apps, level_idx = resolve_slots(meta, ae_meta, config)
    views = [v for v in scene.train_views() if v.name in inputs.features]
    if not views:
        raise ValueError("train-male: extract-features holds no train view")
    cams = [Camera.from_view(v) for v in views]
    g = WildField.from_artifact(inputs.reconstruct).gaussians
    n_ch = len(levels) * len(apps) * CODE_DIM
    log.info(
        "train-male: %d views, %d Gaussians, levels %s, slots %s (%d channels)",
        len(views), len(g), levels, apps, n_ch,
    )  # fmt: skip
    male = MaleConfig(
        **{
            k: v
            for k, v in asdict(config).items()
            if k in MaleConfig.__dataclass_fields__
        }
    )
    with tempfile.TemporaryDirectory(prefix="ptovs-male-") as tmp:
        scratch = (ckpt.folder if ckpt is not None else Path(tmp)) / "views"
        # the lift needs the views only for its reported loss: the first that fit
        # LIFT_LOSS_MB, never a spill or a store that grows with the collection
        lift = config.mode == "lift"
        budget = (
            min(int(config.cache_mb), LIFT_LOSS_MB) if lift else int(config.cache_mb)
        )
        store = ViewStore(budget << 20, scratch, sample=lift)
        if lift:
            # the [P, L, A, D] sums within cache_mb: Gaussians in ranges, one pass
            # over the views each (the first also stores the views for the loss)
            dim = int(
                inputs.features.read(views[0].name, ["feat_orig"])["feat_orig"].shape[1]
            )
            chunk = max(
                1, (int(config.cache_mb) << 20) // (len(levels) * len(apps) * dim * 4)
            )
            starts = range(0, len(g), chunk)
            if len(starts) > 1:
                log.info("train-male: the lift's sums exceed cache_mb = %d: %d passes "
                         "over the views", config.cache_mb, len(starts))  # fmt: skip
            f = torch.zeros(len(g), n_ch)
            model = load_autoencoder(inputs.ae).eval()
            t_lift = time.perf_counter()
            for i, p0 in enumerate(starts):
                p1 = min(len(g), p0 + chunk)
                acc = torch.zeros(p1 - p0, len(levels), len(apps), dim)
                s = prepare_views(inputs, views, g, apps, level_idx, config,
                                  store if i == 0 else None, acc, (p0, p1))  # fmt: skip
                if i == 0:
                    seen = s
                f[p0:p1], metrics, hist = _encode_lift(acc, model)
                del acc
            metrics.update(train_seconds=round(time.perf_counter() - t_lift, 3),
                           lift_passes=len(starts))  # fmt: skip
        else:
            seen = prepare_views(inputs, views, g, apps, level_idx, config, store)
        log.info(
            "train-male: view data %.0f MB in RAM, %.0f MB memory-mapped",
            store.ram_bytes / 2**20,
            store.disk_bytes / 2**20,
        )
        if config.mode != "lift":  # the optimiser, or the codes' lift
            f, metrics, hist = train_male(
                store, n_ch, male, g, cams,
                load=(ckpt.load if ckpt else lambda: None),
                save=(ckpt.save if ckpt else lambda s: None),
            )  # fmt: skip
        final, per_level = evaluate_loss(f, store, config.loss_variant)
        if len(store) == 0:  # no view's data fit the budget: no loss to report
            final, per_level = None, [None] * len(levels)
        metrics.update(loss_views=len(store), loss_views_dropped=store.dropped)
        del store
    codes = normalize_chunks(f).reshape(len(g), len(levels), len(apps) * CODE_DIM)
    if not torch.isfinite(codes).all():
        raise FloatingPointError("train-male: codes are not finite")
    stored = codes[seen].numpy().astype(np.float16)
    bits = np.packbits(seen.numpy())
    per_gaussian = stored.nbytes / max(int(seen.sum()), 1)
    metrics.update(
        final_loss=final,
        final_loss_per_level=dict(zip(levels, per_level, strict=True)),
        gaussians=len(g),
        gaussians_seen=int(seen.sum()),
        bytes_per_gaussian=round(per_gaussian, 3),
        seen_mask_bytes=int(bits.nbytes),
        views=len(views),
    )
    log.info(
        "train-male: %d iterations (%.1f epochs, %s) in %.1f s; final loss %s",
        metrics["iterations"], metrics["epochs"], metrics["stop"],
        metrics["train_seconds"], "–" if final is None else f"{final:.5f}",
    )  # fmt: skip
    return {
        "codes": stored,
        "seen_bits": bits,
        "meta_json": json_dataset(
            {
                "levels": levels,
                "apps": apps,
                "gaussians": len(g),
                "code_dim": CODE_DIM,
                "layout": "codes[k, level, slot*3 + xyz] for the k-th seen Gaussian",
            }
        ),
        "metrics_json": json_dataset(metrics),
        "log_epoch_loss": np.asarray(hist["epoch_loss"], np.float64),
        "log_epoch_seconds": np.asarray(hist["epoch_seconds"], np.float64),
    }


command = stage_command(NAME, VERSION, Config, Inputs, run, kind="single")

__all__ = ["Config", "Inputs", "command", "resolve_slots", "run"]

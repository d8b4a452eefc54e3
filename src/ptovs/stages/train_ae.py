"""Train the transient-aware language autoencoder 512 → 3 → 512 (docs/method.md §6).

Reads extract-features (and uncertainty, unless `weighting = "none"` and
`tau_u = 1`). Samples are the ORIGINAL images' segment rows at every stored level
(not the renders: the paper's Table 5). Each segment s gets ū_T(s), the mean
normalised U_T over its pixels; segments with ū_T > `tau_u` are transient and left
out, the others are weighted by p = 1 − ū_T:

    "loss_only"  (code, default) L = MSE(p·D(E(x)), p·x) + λ(1 − cos)
    "input_and_target" (paper)  L = MSE(D(E(p·x)), p·x) + λ(1 − cos)
    "none"        (LangSplat)   L = MSE(D(E(x)), x) + λ(1 − cos)

The paper's form trains the encoder on p·x but every code is encoded from x; the
authors' code's form does not have that mismatch and scores higher on the accuracy
benchmark's test seeds, so it is the default; `--variant paper` keeps
the paper's. With λ = 0.001 and the cosine per sample (`cos_axis = "batch"`: the code's quirk).
Adam (lr 1e-4), batch 64, up to 100 epochs, seeded. A held-out split of segments
(`heldout_fraction`) is scored after every epoch; training stops when its loss has
not improved by `min_delta` (relative) for `patience` epochs, and the best held-out
epoch is kept (`select = "last"` keeps the last, `"best_last9"` the code's choice).

Streaming: a first pass copies the kept rows (float16) to a scratch file beside the
checkpoint; epochs read it in shuffled windows of `window_rows` rows, so RAM holds
one window, never the whole table. Checkpoints every epoch; a killed run resumes.

Writes, per train view, `code_<app>` [n, 3] float32 for every table (the original,
every novel render and the self render), encoded from the unweighted features;
root: the network (`net.*`), `metrics_json` (held-out cosine, epochs, set sizes),
`meta_json` and the per-epoch log (`log_*`).
"""

from __future__ import annotations

import logging
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from torch.nn import functional as F  # noqa: N812
from tqdm import tqdm

from ptovs.artifacts import Artifact, json_dataset, read_json_dataset
from ptovs.checkpoint import Checkpoint
from ptovs.nets.autoencoder import LanguageAE
from ptovs.registry import upstream
from ptovs.stage import stage_command
from ptovs.threads import torch_threads

log = logging.getLogger(__name__)

NAME = "train-ae"
VERSION = 1
CHUNK = 4096  # rows read together from the scratch file
EVAL_BATCH = 8192


def _needs_uncertainty(c: Config) -> bool:
    return c.weighting != "none" or c.tau_u < 1.0


@dataclass(frozen=True)
class Config:
    weighting: Literal["input_and_target", "loss_only", "none"] = "loss_only"
    """Where p = 1 − ū_T enters: "loss_only" (the authors' code, the default: the
    encoder learns the unweighted features it later encodes), the paper's text
    "input_and_target" (`--variant paper`), or "none" (LangSplat: no uncertainty).
    The accuracy benchmark's test seeds put loss_only +0.051 mIoU [+0.014, +0.094]
    above input_and_target (docs/findings.md)."""
    tau_u: float = 0.9
    """Segments with mean U_T above this are left out (1.0: none, as the code)."""
    cos_axis: Literal["sample", "batch"] = "sample"
    """Cosine term per sample, or along the batch axis (the code's quirk)."""
    cos_lambda: float = 0.001
    lr: float = 1e-4
    batch_size: int = 64
    epochs: int = 100
    """Upper bound; early stopping usually ends sooner."""
    early_stop: bool = True
    patience: int = 5
    """Epochs without a `min_delta` relative gain in held-out loss before stopping."""
    min_delta: float = 1e-3
    select: Literal["best", "last", "best_last9"] = "best"
    """Kept weights: best held-out epoch, last epoch, or the code's best of the last
    nine epochs by training loss."""
    heldout_fraction: float = 0.05
    seed: int = 0
    checkpoint_every: int = 5
    """Epochs between in-stage checkpoints."""
    window_rows: int = 131072
    """Rows shuffled together in RAM (float32: 256 MB at 512-d)."""


@dataclass(frozen=True)
class Inputs:
    features: Artifact = upstream("extract-features")
    uncertainty: Artifact | None = upstream("uncertainty", when=_needs_uncertainty)


# ---------------------------------------------------------------- the samples


def segment_uncertainty(seg: np.ndarray, n_rows: int, u: np.ndarray) -> np.ndarray:
    """ū [n] of every table row: mean of `u` over the pixels its segment covers.

    `seg` [L, H, W] holds global rows (−1: none); a row covering no pixel gets 0.
    """
    sums = np.zeros(n_rows, np.float64)
    counts = np.zeros(n_rows, np.int64)
    uf = u.astype(np.float64).ravel()
    for lv in range(seg.shape[0]):
        s = seg[lv].ravel().astype(np.int64)
        ok = s >= 0
        sums += np.bincount(s[ok], weights=uf[ok], minlength=n_rows)[:n_rows]
        counts += np.bincount(s[ok], minlength=n_rows)[:n_rows]
    return np.where(counts > 0, sums / np.maximum(counts, 1), 0.0)


def sample_weights(
    seg: np.ndarray, n_rows: int, u_t: np.ndarray | None, config: Config
) -> tuple[np.ndarray, np.ndarray]:
    """(keep [n] bool, p [n] float32) for one view's original table."""
    if u_t is None:
        ubar = np.zeros(n_rows)
    else:
        ubar = segment_uncertainty(seg, n_rows, u_t)
    keep = ubar <= config.tau_u if config.tau_u < 1.0 else np.ones(n_rows, bool)
    p = (1.0 - ubar) if config.weighting != "none" else np.ones(n_rows)
    return keep, p.astype(np.float32)


@dataclass
class Samples:
    """The kept original rows in a scratch file, their weights and the split."""

    rows: np.ndarray  # memmap [N, D] float16
    weights: np.ndarray  # [N] float32
    train: np.ndarray  # [N_train] int64, ascending
    heldout: np.ndarray  # [N_held] int64, ascending
    stats: dict


def collect_samples(
    feats: Artifact, unc: Artifact | None, config: Config, scratch: Path
) -> Samples:
    """Pass over the feature artifact: kept rows to `scratch`, weights, split."""
    path = scratch / "rows.f16"
    weights, n_total, n_excluded, dim = [], 0, 0, None
    with path.open("wb") as fh:
        for name in tqdm(
            feats.names(), desc="train-ae rows", leave=False, disable=None
        ):
            v = feats.read(name, ("seg_orig", "feat_orig"))
            table = v["feat_orig"]
            dim = table.shape[1]
            u_t = unc.read(name, ("u_t",))["u_t"] if unc is not None else None
            keep, p = sample_weights(v["seg_orig"], len(table), u_t, config)
            n_total += len(table)
            n_excluded += int((~keep).sum())
            fh.write(np.ascontiguousarray(table[keep], np.float16).tobytes())
            weights.append(p[keep])
    n = n_total - n_excluded
    if dim is None or n < 2:
        raise ValueError(
            f"train-ae: {n} usable segments (of {n_total}; {n_excluded} above "
            f"tau_u = {config.tau_u}); need at least 2"
        )
    rows = np.memmap(path, np.float16, "r", shape=(n, dim))
    w = np.concatenate(weights).astype(np.float32)
    rng = np.random.default_rng(config.seed)
    n_held = min(n - 1, max(1, round(config.heldout_fraction * n)))
    held = np.zeros(n, bool)
    held[rng.choice(n, n_held, replace=False)] = True
    stats = {
        "segments": n_total,
        "excluded_tau_u": n_excluded,
        "train": int((~held).sum()),
        "heldout": n_held,
        "mean_weight": round(float(w.mean()), 4),
        "dim": dim,
    }
    return Samples(rows, w, np.flatnonzero(~held), np.flatnonzero(held), stats)


def windows(
    idx: np.ndarray, window_rows: int, rng: np.random.Generator
) -> Iterator[np.ndarray]:
    """Shuffled index windows: chunk order permuted, rows shuffled within a window."""
    chunks = [idx[i : i + CHUNK] for i in range(0, len(idx), CHUNK)]
    order = rng.permutation(len(chunks))
    per = max(1, window_rows // CHUNK)
    for start in range(0, len(order), per):
        w = np.concatenate([chunks[j] for j in order[start : start + per]])
        yield w[rng.permutation(len(w))]


def _read(rows: np.ndarray, idx: np.ndarray) -> torch.Tensor:
    order = np.argsort(idx, kind="stable")  # sorted reads from the scratch file
    block = np.empty((len(idx), rows.shape[1]), np.float32)
    block[order] = rows[idx[order]]
    return torch.from_numpy(block)


# ---------------------------------------------------------------- training


def objective(
    model: LanguageAE, x: torch.Tensor, p: torch.Tensor, config: Config
) -> torch.Tensor:
    """The configured AE loss on a batch x [B, D] with weights p [B]."""
    pw = p[:, None]
    if config.weighting == "input_and_target":
        target = x * pw
        pred = model(target)
    elif config.weighting == "loss_only":
        target = x * pw
        pred = model(x) * pw
    else:
        target, pred = x, model(x)
    mse = F.mse_loss(pred, target)
    dim = 1 if config.cos_axis == "sample" else 0
    cos = F.cosine_similarity(pred, target, dim=dim, eps=1e-8).mean()
    return mse + config.cos_lambda * (1.0 - cos)


@torch.no_grad()
def score(
    model: LanguageAE, s: Samples, idx: np.ndarray, config: Config
) -> dict[str, float]:
    """Loss, unweighted cosine (what `query` decodes) and p-weighted cosine."""
    model.eval()
    loss_sum = cos_sum = wcos_sum = w_sum = 0.0
    for start in range(0, len(idx), EVAL_BATCH):
        sub = idx[start : start + EVAL_BATCH]
        x = _read(s.rows, sub)
        p = torch.from_numpy(s.weights[sub])
        loss_sum += float(objective(model, x, p, config)) * len(sub)
        cos = F.cosine_similarity(model(x), x, dim=1, eps=1e-8)
        cos_sum += float(cos.sum())
        wcos_sum += float((cos * p).sum())
        w_sum += float(p.sum())
    n = max(len(idx), 1)
    return {
        "loss": loss_sum / n,
        "cos": cos_sum / n,
        "cos_weighted": wcos_sum / max(w_sum, 1e-12),
    }


def _state(model: LanguageAE) -> dict[str, torch.Tensor]:
    return {k: v.detach().clone() for k, v in model.state_dict().items()}


def train_ae(
    s: Samples, config: Config, ckpt: Checkpoint | None = None, desc: str = NAME
) -> tuple[LanguageAE, dict, dict[str, list[float]]]:
    """Train (resuming from `ckpt`); returns the selected model, metrics, history.

    Runs on one thread: a 64-row batch through a 0.4M-parameter MLP is too small
    for torch's intra-op threads, whose hand-offs cost more than they save (and
    far more when another process holds the other core).
    """
    with torch_threads(1):
        return _train_ae(s, config, ckpt, desc)


def _train_ae(
    s: Samples, config: Config, ckpt: Checkpoint | None, desc: str
) -> tuple[LanguageAE, dict, dict[str, list[float]]]:
    torch.manual_seed(config.seed)
    model = LanguageAE(s.rows.shape[1])
    opt = torch.optim.Adam(model.parameters(), lr=config.lr)
    hist: dict[str, list[float]] = {
        k: [] for k in ("train_loss", "heldout_loss", "heldout_cos", "seconds")
    }
    epoch, best, bad, best_state, best_epoch, stop = 0, np.inf, 0, None, -1, ""
    state = ckpt.load() if ckpt is not None else None
    if state is not None and "model" in state:
        model.load_state_dict(state["model"])
        opt.load_state_dict(state["opt"])
        hist = {k: list(v) for k, v in state["hist"].items()}
        epoch, best, bad = state["step"], state["best"], state["bad"]
        best_state, best_epoch = state["best_state"], state["best_epoch"]
        stop = state["stop"]
        log.info("train-ae: resuming after epoch %d", epoch)
    last9: list[tuple[float, int, dict]] = list(state.get("last9", [])) if state else []
    bar = tqdm(
        total=config.epochs, initial=epoch, desc=desc, unit="epoch", leave=False,
        disable=None,
    )  # fmt: skip
    while epoch < config.epochs and not stop:
        t0 = time.perf_counter()
        model.train()
        rng = np.random.default_rng([config.seed, epoch])
        total, count = 0.0, 0
        for win in windows(s.train, config.window_rows, rng):
            block = _read(s.rows, win)
            pw = torch.from_numpy(s.weights[win])
            for start in range(0, len(win), config.batch_size):
                sl = slice(start, start + config.batch_size)
                if len(block[sl]) < 2:  # BatchNorm needs two samples
                    continue
                loss = objective(model, block[sl], pw[sl], config)
                if not torch.isfinite(loss):
                    raise FloatingPointError(f"train-ae: loss {loss} at epoch {epoch}")
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
                total += loss.item() * len(block[sl])
                count += len(block[sl])
        held = score(model, s, s.heldout, config)
        epoch += 1
        hist["train_loss"].append(total / max(count, 1))
        hist["heldout_loss"].append(held["loss"])
        hist["heldout_cos"].append(held["cos"])
        hist["seconds"].append(time.perf_counter() - t0)
        if held["loss"] < best * (1.0 - config.min_delta):
            best, bad, best_state, best_epoch = held["loss"], 0, _state(model), epoch
        else:
            bad += 1
            if config.early_stop and bad >= config.patience:
                stop = f"held-out loss flat for {bad} epochs"
        if config.select == "best_last9":
            last9 = [*last9, (hist["train_loss"][-1], epoch, _state(model))][-9:]
        bar.update(1)
        bar.set_postfix(cos=f"{held['cos']:.3f}")
        if ckpt is not None and epoch % config.checkpoint_every == 0:
            ckpt.save(
                {
                    "step": epoch, "model": _state(model), "opt": opt.state_dict(),
                    "hist": hist, "best": best, "bad": bad, "best_state": best_state,
                    "best_epoch": best_epoch, "stop": stop, "last9": last9,
                }
            )  # fmt: skip
    bar.close()
    if config.select == "best" and best_state is not None:
        model.load_state_dict(best_state)
        kept = best_epoch
    elif config.select == "best_last9" and last9:
        _, kept, sd = min(last9, key=lambda t: t[0])
        model.load_state_dict(sd)
    else:
        kept = epoch
    model.eval()
    final = score(model, s, s.heldout, config)
    metrics = dict(
        s.stats,
        epochs_run=epoch,
        epoch_kept=kept,
        stop=stop or f"reached {config.epochs} epochs",
        heldout_cos=round(final["cos"], 5),
        heldout_cos_weighted=round(final["cos_weighted"], 5),
        heldout_loss=float(final["loss"]),
        train_seconds=round(sum(hist["seconds"]), 2),
    )
    return model, metrics, hist


# ---------------------------------------------------------------- the stage


def run(
    inputs: Inputs, config: Config, skip=frozenset(), ckpt: Checkpoint | None = None
) -> Iterator[tuple[str | None, dict]]:
    """Train on the original tables, then encode every table of every view."""
    feats = inputs.features
    meta = read_json_dataset(feats.root()["levels_json"])
    state = ckpt.load() if ckpt is not None else None
    if state is not None and "final" in state:  # trained before an interruption
        model = LanguageAE.from_state(state["final"])
        metrics, hist = state["metrics"], state["final_hist"]
    else:
        with tempfile.TemporaryDirectory(prefix="ptovs-ae-") as tmp:
            scratch = ckpt.folder if ckpt is not None else Path(tmp)
            scratch.mkdir(parents=True, exist_ok=True)
            samples = collect_samples(feats, inputs.uncertainty, config, scratch)
            log.info("train-ae: %s", samples.stats)
            model, metrics, hist = train_ae(samples, config, ckpt)
            del samples
            (scratch / "rows.f16").unlink(missing_ok=True)
        if ckpt is not None:
            ckpt.save(
                {"step": metrics["epochs_run"], "final": _state(model),
                 "metrics": metrics, "final_hist": hist}
            )  # fmt: skip
    log.info(
        "train-ae: held-out cosine %.4f after %d epochs (kept %d; %s)",
        metrics["heldout_cos"],
        metrics["epochs_run"],
        metrics["epoch_kept"],
        metrics["stop"],
    )
    apps = meta["apps"]
    with torch.no_grad():
        for name in feats.names():
            if name in skip:
                continue
            v = feats.read(name, [f"feat_{a}" for a in apps])
            yield (
                name,
                {
                    f"code_{a}": model.encode(
                        torch.from_numpy(v[f"feat_{a}"].astype(np.float32))
                    ).numpy()
                    if len(v[f"feat_{a}"])
                    else np.zeros((0, model.code_dim), np.float32)
                    for a in apps
                },
            )
    root: dict = {f"net.{k}": v.numpy() for k, v in model.state_dict().items()}
    root["metrics_json"] = json_dataset(metrics)
    root["meta_json"] = json_dataset(
        {
            "apps": apps,
            "levels": meta["levels"],
            "code_dim": model.code_dim,
            "encoder_spec": meta.get("encoder_spec"),  # query embeds texts with it
        }
    )
    for k, v in hist.items():
        root[f"log_{k}"] = np.asarray(v, np.float64)
    yield None, root


def _count(inputs: Inputs, config: Config) -> int:
    return len(inputs.features.names())


command = stage_command(NAME, VERSION, Config, Inputs, run, count=_count)

__all__ = [
    "Config",
    "Inputs",
    "collect_samples",
    "command",
    "objective",
    "run",
    "sample_weights",
    "segment_uncertainty",
    "train_ae",
]

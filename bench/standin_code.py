"""The stand-in profile's scene-code row (bench/standin_profile.py): a seed's crops
read through the chain's own 3-d autoencoder (`ptovs.stages.train_ae`, its
defaults), their closed-set accuracy and relevancy against the same crops read raw,
and that row over seeds with a cluster-bootstrap interval.
"""

from __future__ import annotations

import numpy as np

# the scene code's training crops (and every piece row), and the crops read through it
CODE_FIT = ("clean", "daylight", "daylight-b", "night", "bw", "sepia")
CODE_EVAL = ("clean", "daylight", "daylight-b")


def relevancies(cos: np.ndarray, canon: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """[n, 2]: each crop's relevancy of its own phrase and the median relevancy of
    the other phrases, from its cosines with the phrases [n, K] and with the
    canonical phrases [n, C] (the pipeline's rule: `ptovs.field.relevancy`)."""
    import torch

    from ptovs.field.relevancy import QuerySettings, relevancy

    rel = relevancy(
        torch.from_numpy(cos), torch.from_numpy(canon)[:, None, :],
        QuerySettings().temperature,
    ).numpy()  # fmt: skip
    own = rel[np.arange(len(rel)), truth]
    others = np.ma.masked_array(rel, np.eye(rel.shape[1], dtype=bool)[truth])
    return np.stack([own, np.ma.median(others, axis=1).filled(np.nan)], 1)


def fit_code(x: np.ndarray, seed: int = 0):
    """The chain's 512 -> 3 -> 512 autoencoder trained on rows x [n, 512] with the
    stage's defaults (uniform weights: no uncertainty here); returns (model,
    held-out cosine)."""
    from ptovs.stages.train_ae import Config, Samples, train_ae

    cfg = Config(seed=seed)
    order = np.random.default_rng(seed).permutation(len(x))
    n_held = max(2, int(round(cfg.heldout_fraction * len(x))))
    s = Samples(
        rows=x.astype(np.float16), weights=np.ones(len(x), np.float32),
        train=np.sort(order[n_held:]), heldout=np.sort(order[:n_held]), stats={},
    )  # fmt: skip
    model, metrics, _ = train_ae(s, cfg, desc="scene code")
    return model, float(metrics["heldout_cos"])


def through_code(model, x: np.ndarray) -> np.ndarray:
    """Rows x [n, 512] encoded to the 3-d code and decoded (unit rows)."""
    import torch

    with torch.no_grad():
        return model(torch.from_numpy(x.astype(np.float32))).double().numpy()


def code_rows(embs: dict, truths: dict, text: np.ndarray, canon: np.ndarray) -> dict:
    """The scene's crops through its own 3-d code. Per evaluated crop
    [truth, pred raw, pred code, own and other relevancy raw, the same through the
    code], and the code's held-out cosine."""
    fit = np.concatenate(
        [e for r, e in embs.items() if r in CODE_FIT or r.startswith("piece-")]
    )
    model, cos = fit_code(fit)
    rows = [r for r in CODE_EVAL if r in embs]
    if not rows:
        return {"heldout_cos": cos, "crops": []}
    raw = np.concatenate([embs[r] for r in rows])
    truth = np.concatenate([truths[r] for r in rows])
    reads = (raw, through_code(model, raw))
    preds = [np.argmax(x @ text.T, axis=1)[:, None] for x in reads]
    rels = [relevancies(x @ text.T, x @ canon.T, truth) for x in reads]
    table = np.concatenate([truth[:, None], *preds, *rels], axis=1)
    return {"heldout_cos": cos, "n_fit": len(fit), "crops": table.tolist()}


def ratio_interval(
    t: np.ndarray, cluster: np.ndarray, n_boot: int = 2000, seed: int = 0
) -> list[float]:
    """95 % cluster-bootstrap interval of accuracy through the code over accuracy
    raw, minus 1, from crop rows [truth, pred raw, pred code, ...] and their
    clusters (seed, part phrase)."""
    ids, inv = np.unique(cluster, axis=0, return_inverse=True)
    inv = inv.ravel()
    raw = np.bincount(inv, t[:, 0] == t[:, 1], len(ids))
    code = np.bincount(inv, t[:, 0] == t[:, 2], len(ids))
    rng = np.random.default_rng(seed)
    pick = rng.integers(0, len(ids), (n_boot, len(ids)))
    r = code[pick].sum(1) / np.maximum(raw[pick].sum(1), 1e-12) - 1.0
    return [float(np.percentile(r, 2.5)), float(np.percentile(r, 97.5))]


def summarise_code(results: list[dict]) -> dict:
    """The scene code's rows over seeds."""
    pairs = [
        (res["seed"], c)
        for res in results
        for c in res.get("code", {}).get("crops", [])
    ]
    if not pairs:
        return {}
    t = np.array([c for _, c in pairs])
    cluster = np.array([(seed, c[0]) for seed, c in pairs])
    acc_raw, acc_code = (
        float(np.mean(t[:, 0] == t[:, 1])),
        float(np.mean(t[:, 0] == t[:, 2])),
    )
    return {
        "n": len(t),
        "accuracy_raw": acc_raw,
        "accuracy_code": acc_code,
        "relative": acc_code / acc_raw - 1.0 if acc_raw > 0 else float("nan"),
        "relative_ci": ratio_interval(t, cluster),
        "relevancy_own_raw": float(np.median(t[:, 3])),
        "relevancy_other_raw": float(np.nanmedian(t[:, 4])),
        "relevancy_own_code": float(np.median(t[:, 5])),
        "relevancy_other_code": float(np.nanmedian(t[:, 6])),
        "heldout_cos": [
            round(r["code"]["heldout_cos"], 4) for r in results if "code" in r
        ],
    }

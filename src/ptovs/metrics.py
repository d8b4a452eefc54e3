"""Segmentation metrics and their tables (docs/method.md §9): per pair, per scene.

Per (image, category) pair: IoU = |P∧G|/|P∨G|; PA = (TP + TN)/(H·W) (binary pixel
accuracy, background included); P = TP/(TP + FP). A scene's mIoU, mPA and mP are
the means over its pairs. Used by the `evaluate` stage, `ptovs table` and the
benchmarks; `read_metrics` reads an evaluate artifact back.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from ptovs.artifacts import read_json_dataset, write_atomic

CONVENTIONS = {
    "empty_prediction": "IoU = 0, P = 0 (PA as usual)",
    "empty_ground_truth": "pair skipped with a warning",
    "averaging": "arithmetic mean over all (image, category) pairs of the scene",
    "level": "the level the query chose (highest smoothed score)",
}


def pair_metrics(pred: np.ndarray, gt: np.ndarray) -> dict[str, float]:
    """IoU, PA, P (and recall) of one binary prediction against its ground truth."""
    p, g = pred.astype(bool), gt.astype(bool)
    tp = int((p & g).sum())
    fp = int((p & ~g).sum())
    fn = int((~p & g).sum())
    tn = int(p.size - tp - fp - fn)
    union = tp + fp + fn
    return {
        "iou": tp / union if union else 0.0,
        "pa": (tp + tn) / p.size if p.size else 0.0,
        "p": tp / (tp + fp) if tp + fp else 0.0,
        "recall": tp / (tp + fn) if tp + fn else 0.0,
    }


def summarise(pairs: list[dict]) -> dict[str, Any]:
    """Scene means over pairs, plus per-query means."""
    if not pairs:
        return {"pairs": 0, "miou": None, "mpa": None, "mp": None}
    out: dict[str, Any] = {"pairs": len(pairs)}
    for key, name in (("iou", "miou"), ("pa", "mpa"), ("p", "mp"), ("recall", "mr")):
        out[name] = float(np.mean([r[key] for r in pairs]))
    per_query: dict[str, list[float]] = {}
    for r in pairs:
        per_query.setdefault(r["query"], []).append(r["iou"])
    out["per_query_miou"] = {q: float(np.mean(v)) for q, v in per_query.items()}
    out["empty_predictions"] = sum(1 for r in pairs if r["pred_pixels"] == 0)
    return out


def read_metrics(art: Any) -> tuple[dict, list[dict]]:
    """(scene summary, per-pair records) of an evaluate artifact."""
    root = art.root()
    return read_json_dataset(root["metrics_json"]), read_json_dataset(
        root["pairs_json"]
    )


def markdown_table(
    rows: dict[str, dict[str, dict | None]], scenes: list[str] | None = None
) -> str:
    """Rows {variant: {scene: summary or None}} → Markdown, with a mean column.

    A scene whose summary is None (failed) shows as "failed", a scene of
    `scenes` absent from a row as "–" (not run); the mean is over the scenes
    that have numbers, marked with * when some are missing.
    """
    if scenes is None:
        scenes = list(dict.fromkeys(s for r in rows.values() for s in r))
    head = "| variant | " + " | ".join(scenes) + " | mean |"
    lines = [
        "mIoU / mPA / mP per scene (pairs: (image, category); empty prediction: "
        "IoU = P = 0)",
        "",
        head,
        "|" + "---|" * (len(scenes) + 2),
    ]
    for variant, per_scene in rows.items():
        cells, got = [], []
        for s in scenes:
            m = per_scene.get(s)
            if m is None or m.get("miou") is None:
                cells.append("failed" if s in per_scene else "–")
                continue
            got.append(m)
            cells.append(f"{m['miou']:.3f} / {m['mpa']:.3f} / {m['mp']:.3f}")
        if got:
            mean = "/".join(
                f"{np.mean([m[k] for m in got]):.3f}" for k in ("miou", "mpa", "mp")
            ).replace("/", " / ")
            if len(got) < len(scenes):
                mean += " *"
        else:
            mean = "–"
        lines.append(f"| {variant} | " + " | ".join(cells) + f" | {mean} |")
    return "\n".join(lines) + "\n"


def write_report(
    out: Path, rows: dict[str, dict[str, dict | None]], extra: dict
) -> None:
    """evaluate.md and evaluate.json under `out`, atomically."""
    write_atomic(out / "evaluate.md", markdown_table(rows))
    write_atomic(
        out / "evaluate.json", json.dumps({"results": rows, **extra}, indent=1)
    )


__all__ = [
    "CONVENTIONS",
    "markdown_table",
    "pair_metrics",
    "read_metrics",
    "summarise",
    "write_report",
]

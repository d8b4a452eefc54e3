"""runtime = "auto": measure each runtime on the scene's own crops, keep the fastest
that gives PyTorch's features.

1. `screen` (nothing runs): a runtime that is not installed, or that cannot be
   faster on this device (`Backend.cannot_win`: ptovs runs ONNX Runtime and
   OpenVINO on the CPU only, so on CUDA PyTorch stays), is not tried.
2. A trial: every runtime left encodes the same few crops twice (the first a
   warm-up: OpenVINO compiles for each new batch shape); one not faster than
   PyTorch on the second is dropped.
3. The whole sample, PyTorch and each runtime that passed the trial, fastest of
   two passes each: the fastest runtime whose unit features agree with
   PyTorch's float32 ones (max |Δ| ≤ MAX_ABS_DIFF) and that beat PyTorch by
   MIN_SPEEDUP is kept; otherwise PyTorch.

Outputs that are not unit features (SAM's image embeddings) are compared
relative to their size instead (`compare=relative_diff`: max |Δ| / max |PyTorch|,
the same bar). The report says why in one line (`report["reason"]`) and carries
the figures.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np

from ptovs.encoders.runtimes import BACKENDS, get_backend

MAX_ABS_DIFF = 1e-4
"""The largest difference a runtime's unit features may have from PyTorch's (or,
with `relative_diff`, its outputs relative to PyTorch's largest)."""
MIN_SPEEDUP = 1.10
"""A runtime replaces PyTorch only where it was at least this much faster on the
sample (within timing noise it could be slower: PyTorch is kept)."""
TRIAL = 8
"""Crops of the trial pass."""


def screen(device: str, wanted: str = "auto") -> tuple[list[str], dict[str, str]]:
    """(runtimes worth trying besides torch, {runtime: why not tried})."""
    names = [n for n in BACKENDS if n != "torch"] if wanted == "auto" else [wanted]
    keep, why = [], {}
    for name in names:
        backend = get_backend(name)
        reason = backend.missing() or backend.cannot_win(device)
        if reason:
            why[name] = reason.split(";")[0]
        else:
            keep.append(name)
    return keep, why


def _timed(run: Callable[[np.ndarray], np.ndarray], x: np.ndarray, passes: int = 1):
    """(output, fastest seconds of `passes` runs)."""
    best, out = float("inf"), None
    for _ in range(passes):
        t0 = time.perf_counter()
        out = run(x)
        best = min(best, time.perf_counter() - t0)
    return out, best


def _unit(f: np.ndarray) -> np.ndarray:
    f = np.asarray(f, np.float64)
    return f / np.maximum(np.linalg.norm(f, axis=-1, keepdims=True), 1e-12)


def unit_diff(out: np.ndarray, ref: np.ndarray) -> float:
    """max |Δ| of the unit features (each row normalised): an encoder's bar."""
    return float(np.abs(_unit(out) - _unit(ref)).max())


def relative_diff(out: Any, ref: Any) -> float:
    """max |Δ| / max |PyTorch's|, the largest over the outputs (one array or a
    list): the bar of outputs that are not unit features (SAM's embeddings)."""
    outs, refs = (out, ref) if isinstance(ref, list) else ([out], [ref])
    return max(
        float(np.abs(np.asarray(o, np.float64) - r).max())
        / max(float(np.abs(r).max()), 1e-12)
        for o, r in zip(outs, refs, strict=True)
    )


_LABELS = {unit_diff: "max |Δ|", relative_diff: "max |Δ| / max |PyTorch|"}


def choose(
    x: np.ndarray,
    torch_run: Callable[[np.ndarray], np.ndarray],
    reference: Callable[[np.ndarray], np.ndarray],
    load: Callable[[str], Callable[[np.ndarray], np.ndarray]],
    candidates: list[str],
    skipped: dict[str, str],
    compare: Callable[[Any, Any], float] = unit_diff,
    unit: str = "crops",
) -> dict[str, Any]:
    """Decide among `candidates` on the input batch `x` (the sample, preprocessed).

    Args:
        torch_run: PyTorch as it would run (its precision), for the timing.
        reference: PyTorch in float32 (the features every runtime must give).
        load: a runtime's name → its encoding function (features of a batch).
        skipped: runtimes not tried and why (from `screen`), kept in the report.
        compare: (a runtime's output, PyTorch's) → the difference held to
            MAX_ABS_DIFF (reported as "max_abs_diff").
        unit: what one row of `x` is, in the reason ("crops", "images").

    Returns:
        {"runtime", "reason", "crops", "skipped", "seconds": {runtime: {trial,
        sample}}, "max_abs_diff": {runtime: float}, "bar": {...}}.
    """
    report: dict[str, Any] = {
        "crops": int(len(x)),
        "skipped": skipped,
        "bar": {"max_abs_diff": MAX_ABS_DIFF, "min_speedup": MIN_SPEEDUP},
        "seconds": {},
        "max_abs_diff": {},
    }
    if not len(x) or not candidates:
        why = _none_tried(skipped) if not candidates else f"no {unit} to measure on"
        return {"runtime": "torch", "reason": why, **report}
    trial = x[:TRIAL]
    runs = {"torch": torch_run}
    torch_run(trial)  # warm-up at the trial's shapes
    _, t_torch = _timed(torch_run, trial)
    report["seconds"]["torch"] = {"trial": t_torch}
    survivors = []
    for name in candidates:
        try:
            runs[name] = load(name)
            runs[name](trial)  # warm-up at the trial's shapes (and compilation)
        except Exception as exc:  # noqa: BLE001 - a runtime that fails is not used
            skipped[name] = f"failed to load: {type(exc).__name__}: {exc}"[:300]
            continue
        _, t = _timed(runs[name], trial)
        report["seconds"][name] = {"trial": t}
        if t < t_torch:
            survivors.append(name)
    if not survivors:
        return {"runtime": "torch", **report,
                "reason": "no runtime beat PyTorch on a trial of "
                          f"{_n(len(trial), unit)} "
                          f"({_rates(report, 'trial', len(trial), unit)})"}  # fmt: skip
    ref = reference(x)
    _, report["seconds"]["torch"]["sample"] = _timed(torch_run, x, passes=2)
    t_torch = report["seconds"]["torch"]["sample"]
    best, best_t = "torch", t_torch / MIN_SPEEDUP  # the time a runtime must beat
    for name in survivors:
        out, t = _timed(runs[name], x, passes=2)
        report["seconds"][name]["sample"] = t
        diff = compare(out, ref)
        report["max_abs_diff"][name] = diff
        if diff <= MAX_ABS_DIFF and t <= best_t:
            best, best_t = name, t
    rates = _rates(report, "sample", len(x), unit)
    label = _LABELS.get(compare, "difference")
    if best == "torch":
        why = (f"no runtime both agreed with PyTorch ({label} ≤ {MAX_ABS_DIFF:g}) and "
               f"beat it by {MIN_SPEEDUP:g}x on {_n(len(x), unit)} ({rates})")  # fmt: skip
    elif compare is unit_diff:
        why = (f"{best} fastest on {len(x)} of the scene's crops ({rates}), features "
               f"within {report['max_abs_diff'][best]:.1e} of PyTorch's")  # fmt: skip
    else:
        why = (f"{best} fastest on {_n(len(x), unit)} ({rates}), outputs within "
               f"{report['max_abs_diff'][best]:.1e} of PyTorch's ({label})")  # fmt: skip
    return {"runtime": best, "reason": why, **report}


def _n(n: int, unit: str) -> str:
    """`n` `unit`, singular for one: 1 image, 3 images."""
    return f"{n} {unit[:-1] if n == 1 and unit.endswith('s') else unit}"


def _rates(report: dict, stage: str, n: int, unit: str = "crops") -> str:
    rates = {name: n / max(s[stage], 1e-9)
             for name, s in report["seconds"].items() if stage in s}  # fmt: skip
    # below one a second (SAM's images), two significant digits, not "0.0"
    parts = [f"{name} {r:.1f}" if r >= 1 else f"{name} {r:.2g}"
             for name, r in rates.items()]  # fmt: skip
    return f"{unit}/s: " + ", ".join(parts)


def _none_tried(skipped: dict[str, str]) -> str:
    if not skipped:
        return "no other runtime"
    return "no other runtime can win here: " + "; ".join(
        f"{k}: {v}" for k, v in skipped.items()
    )


__all__ = [
    "MAX_ABS_DIFF",
    "MIN_SPEEDUP",
    "TRIAL",
    "choose",
    "relative_diff",
    "screen",
    "unit_diff",
]

"""The precision and the runtime an encoder runs in, decided once per artifact.

extract-features asks before its first view: `decide_precision` (OpenCLIP with
precision "auto": bf16 kept only where it agrees with fp32 on a sample of the
scene's own crops and is faster) and `decide_runtime` (runtime "auto": the
fastest runtime that agrees with PyTorch on that sample). Each decision is kept
in the partial artifact's notes before a view is written, so a resumed run makes
the same one and one artifact never mixes two precisions' or runtimes' rows. The
checks themselves are the encoder's (`OpenClipEncoder.check_precision`,
`check_runtime`); `check_precision_on` runs the encoder's on an image's crops.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

import numpy as np

from ptovs.crop import prepare_crop
from ptovs.encoders.memo import unique_segments

log = logging.getLogger(__name__)


def precision_sample(
    image: np.ndarray,
    levels: list,
    crop_size: int,
    n: int = 48,
    resample: str | None = None,
) -> np.ndarray:
    """Up to n crops of one image's distinct segments, evenly spread over them
    (the sample `precision = "auto"` checks the reduced-precision tower on)."""
    order, _ = unique_segments(levels)
    if not order:
        return np.zeros((0, crop_size, crop_size, 3), np.float32)
    pick = np.unique(np.linspace(0, len(order) - 1, min(n, len(order))).astype(int))
    return np.stack(
        [prepare_crop(image, levels[order[i][0]].mask(order[i][1]), crop_size,
                      resample=resample)
         for i in pick]
    )  # fmt: skip


def check_precision_on(encoder: Any, levels: list, image, crop_size: int):
    """Run the encoder's precision check on a sample of the crops of `image`
    (segmented as `levels`), when it asks for one (OpenCLIP with precision
    "auto"); None otherwise."""
    if getattr(encoder, "precision_wanted", None) != "auto":
        return None
    sample = precision_sample(
        image, levels, crop_size, resample=getattr(encoder, "resample", None)
    )
    if not len(sample):
        log.info("precision: no segments to check on; keeping fp32")
        return {"precision": "fp32", "checked": "bf16", "crops": 0}
    report = encoder.check_precision(sample)
    if "worst_centred_cosine" in report:
        log.info(
            "precision: %s (bf16 vs fp32 on %d crops: worst centred cosine %.4f, "
            "top-1 agreement %.3f; bar %.3f / %.2f)%s",
            report["precision"], report["crops"], report["worst_centred_cosine"],
            report["top1_agreement"], report["bar"]["worst_centred_cosine"],
            report["bar"]["top1_agreement"],
            "" if report["precision"] == "bf16" else ": bf16 disagrees, fp32 kept",
        )  # fmt: skip
    else:  # a check that did not compare (e.g. bf16 not faster here)
        log.info("precision: %s (%s)", report["precision"], report)
    return report


def _probe_words(probe: dict) -> str:
    """`bf16_is_fast`'s evidence in a few words, for the log."""
    if probe.get("device") == "cuda":
        return "no bf16 on this CUDA device"
    if probe.get("probe"):
        return (f"a bf16 matmul of width {probe['probe']['width']} ran "
                f"{probe['probe']['speedup']:.2f}x fp32's speed")  # fmt: skip
    found = probe.get("bf16_flags") or []
    if not found:
        return f"no bf16 instructions (CPU capability {probe.get('capability')})"
    return f"bf16 flags {', '.join(found)} on {probe.get('device')}"


def decide_precision(
    encoder: Any,
    notes: Any,
    sample: Callable[[], tuple[list, np.ndarray]],
    crop_size: int,
) -> dict | None:
    """The precision report of this artifact, and the encoder set to it.

    Made once per artifact: stored in `notes` before the first view is written
    and read back by a resumed run, which does not check again (another CPU's
    floats could choose otherwise and mix bf16 and fp32 rows in one artifact).
    `sample()` gives the (levels, image) the check crops; it is called only
    where bf16 may be faster (`precision_without_sample`, where the encoder has
    it: no bf16 instructions on this CPU is fp32 without segmenting anything).
    None when the encoder asks for no check (precision fp32 or bf16 given, or not
    OpenCLIP)."""
    if getattr(encoder, "precision_wanted", None) != "auto":
        return None
    report = None if notes is None else notes.get("precision")
    if report is not None:
        log.info(
            "precision: %s, as chosen when this artifact was begun (not checked again)",
            report["precision"],
        )
    else:
        quick = getattr(encoder, "precision_without_sample", None)
        report = quick() if quick is not None else None
        if report is not None:
            log.info("precision: %s (%s: %s; nothing sampled)", report["precision"],
                     report["reason"], _probe_words(report["bf16_probe"]))  # fmt: skip
        else:
            levels, image = sample()
            report = check_precision_on(encoder, levels, image, crop_size)
        if notes is not None:
            notes.put("precision", report)
    encoder.precision = report["precision"]
    return report


def decide_runtime(
    encoder: Any,
    notes: Any,
    sample: Callable[[], tuple[list, np.ndarray]],
    crop_size: int,
) -> dict | None:
    """The runtime report of this artifact, and the encoder set to it.

    Made once per artifact, as the precision is: kept in `notes` before the first
    view is written, so a resumed run uses the same runtime (one artifact never
    mixes two runtimes' rows; a runtime no longer installed is refused in one line).
    A named runtime is used as it is. "auto" encodes a sample only where a runtime
    besides PyTorch is installed and can win on this device
    (`runtime_without_sample`). None for an encoder with no runtime (the stand-in)."""
    wanted = getattr(encoder, "runtime_wanted", None)
    if wanted is None:
        return None
    report = None if notes is None else notes.get("runtime")
    if report is not None:
        encoder.tower.use(report["runtime"])
        if report["runtime"] != "torch":
            encoder.precision = "fp32"  # a runtime's rows are fp32
        log.info("runtime: %s, as chosen when this artifact was begun (not "
                 "measured again)", report["runtime"])  # fmt: skip
        return report
    if wanted != "auto":
        report = {"runtime": wanted, "reason": "asked for"}
        if wanted != "torch":
            encoder.precision = "fp32"
    else:
        report = encoder.runtime_without_sample()
        if report is None:
            levels, image = sample()
            crops = precision_sample(image, levels, crop_size,
                                     resample=getattr(encoder, "resample", None))  # fmt: skip
            report = encoder.check_runtime(crops)
    report["precision"] = encoder.precision  # what the rows are computed in
    log.info("extract-features: runtime = %s (%s: %s)", encoder.runtime,
             wanted, report["reason"])  # fmt: skip
    if notes is not None:
        notes.put("runtime", report)
    return report


__all__ = [
    "check_precision_on",
    "decide_precision",
    "decide_runtime",
    "precision_sample",
]

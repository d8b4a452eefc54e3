"""Multi-level language features of every original image and render (docs/method.md §4).

Reads render-appearances. For each train view and each image of it (the original
photo, the N−1 novel renders, the self render): segment at L levels (default 3:
subpart / part / whole), crop every segment as LangSplat does (mask, bbox crop,
square pad, resize, normalise) and encode it. One view at a time, resumable.

Per train view and appearance slot `app` ∈ {orig, nov1.., self}: `seg_<app>`
[L, H, W] int16 global table rows (-1 = no segment, see `ptovs.features`),
`feat_<app>` [n, D] float16 unit rows, `nseg_<app>` [L] rows per level. Root:
`levels_json` (level names, backends, slots).

A mask that recurs at several levels is encoded once (same crop, same row). With
OpenCLIP and `precision = "auto"`, a sample of the first view's crops decides
whether the bf16 image tower is kept (`levels_json`'s `precision` says what and why),
once per artifact: the choice is stored before the first view, and a resumed run
reuses it, so one artifact never mixes bf16 and fp32 rows.

A view whose segmented images hold no segment at any level (after `min_crop_px`) is
logged and counted (`levels_json`'s `empty_views` of `views`). When most views are
like that (`too_many_empty`) the segmenter is broken for these images (a random or
wrong checkpoint, thresholds too strict, images too small): the stage stops with an
error naming those causes and deletes its partial artifact.

Segments: by default (`segment = "once"`) each view is segmented once, from its
photo (`segment_from = "orig"`; "self": the self render), and every image of the
view is cropped with those segments, since the renders share the photo's camera;
`segment = "each"` (the paper's) segments every image. `min_crop_px` leaves out
segments whose crop is too small for the encoder to read (their pixels are
NO_SEGMENT at that level).

Backends: segmenter "hier" (nested levels from one merge hierarchy, the CPU
default), "graph" (one Felzenszwalb pass per level), "sam" (local checkpoint,
extra [sam]), "sam2" (SAM 2.1, local checkpoint, extra [sam2]) or "truth" (a
synthetic scene's part masks: the instrument's); encoder "synthetic" (the stand-in;
the default on synthetic scenes) or "openclip" (any open_clip model from a local
checkpoint, extra [clip]; the default elsewhere). Or
`import_dir`: a LangSplat feature folder (`<id>_f.npy`, `<id>_s.npy`, renders
`<id>_f_ma_<k>.npy`) used instead of segmenting and encoding.
"""

from __future__ import annotations

import functools
import hashlib
import logging
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from ptovs.artifacts import Artifact, Notes, json_dataset, read_json_dataset
from ptovs.encoders import Encoder, get_encoder, prepare_crop
from ptovs.encoders.memo import CropMemo
from ptovs.errors import UselessOutputError
from ptovs.features import SegmentFeatures, langsplat_suffix, read_langsplat
from ptovs.registry import scene_input, upstream
from ptovs.scene import check_size
from ptovs.segment import NO_SEGMENT, Level, Segmenter, check_levels, get_segmenter
from ptovs.stage import stage_command
from ptovs.visual import to_uint8

log = logging.getLogger(__name__)

NAME = "extract-features"
VERSION = 1


@dataclass(frozen=True)
class Config:
    levels: tuple[Literal["default", "s", "m", "l"], ...] = ("s", "m", "l")
    """Levels, from "default", "s", "m", "l" (LangSplat's four; the paper uses s/m/l)."""
    segmenter: Literal["graph", "hier", "sam", "sam2", "truth"] = "hier"
    """"graph": one Felzenszwalb pass per level; "hier": nested levels cut from
    one merge hierarchy over texture features (`ptovs.segment.hier`); "sam": a
    local SAM checkpoint; "sam2": a local SAM 2.1 checkpoint (cheaper on a CPU);
    "truth": a synthetic scene's part masks (the accuracy
    instrument's perfect segmenter; refused elsewhere)."""
    graph_k: tuple[float, ...] = ()
    """Felzenszwalb k per level (empty: 100/300/1000/3000 for default/s/m/l)."""
    graph_sigma: float = 0.8
    graph_min_size: int = 100
    """Smallest segment at 512×384, scaled with the image area."""
    hier_thresholds: tuple[float, ...] = ()
    """Merge cost at which each level is cut (empty: the segmenter's defaults)."""
    hier_texture: float = 1.0
    """Texture window (Gaussian sigma, px at 512×384) of the hier features."""
    hier_edge: float = 0.0
    """Weight of a boundary's feature gradient in the hier merge cost."""
    hier_min_size: int = 300
    """Smallest hier segment at 512×384, scaled with the image area."""
    sam_checkpoint: str = ""
    """The local checkpoint of segmenter "sam" or "sam2"."""
    sam_model: str = "vit_h"
    """segmenter "sam": vit_h, vit_l or vit_b."""
    sam2_model: str = "tiny"
    """segmenter "sam2": SAM 2.1 tiny, small, base_plus or large."""
    sam_points_per_side: int | Literal["auto"] = 32
    """SAM's prompt grid, points a side; "auto": one every 64 px of the working
    short side, 8 to 32 (ptovs.fit)."""
    sam_crop_n_layers: int = 1
    encoder: Literal["auto", "synthetic", "openclip"] = "auto"
    """"auto": the stand-in on synthetic scenes, OpenCLIP elsewhere."""
    clip_model: str = "ViT-B-16"
    """Any open_clip model name (docs/guide.md, "Real encoders and segmenters")."""
    clip_checkpoint: str = ""
    """The local state dict of clip_model (nothing is downloaded)."""
    clip_pretrained: str = ""
    """The checkpoint's open_clip tag (e.g. "dfndr2b"): it decides the
    preprocessing; needed only where a model's tags preprocess differently."""
    clip_tokenizer: str = ""
    """Local Hugging Face tokenizer folder (SigLIP models only)."""
    precision: Literal["auto", "fp32", "bf16"] = "auto"
    """OpenCLIP's image tower: "auto" encodes a sample of the scene's crops in
    fp32 and bf16 and keeps bf16 only if they agree (worst centred cosine ≥
    0.995, top-1 phrase agreement ≥ 0.98), else fp32; the choice and its figures
    go into the artifact. "fp32" / "bf16" force one."""
    runtime: Literal["auto", "torch", "onnxruntime", "openvino"] = "auto"
    """What runs the image encoders, OpenCLIP's tower and SAM's or SAM 2.1's:
    "auto" encodes a sample (the scene's crops; the segmenter's first photo) with
    PyTorch and each installed runtime (ONNX Runtime, OpenVINO; extra [clip]) and
    keeps the fastest whose outputs are within 1e-4 of PyTorch's (else PyTorch;
    on CUDA PyTorch without trying); each choice, why, and its figures go into the
    artifact. A named runtime is used as it is (refused in one line where not
    installed). Its export is made once per checkpoint, in the user's cache
    (docs/guide.md, "Runtimes")."""
    device: str = "cpu"
    batch_size: int = 0
    """Crops an encoder call; 0: the runtime's own (8 for PyTorch and ONNX
    Runtime, 16 for OpenVINO: the fastest measured on 2 cores)."""
    crop_size: int = 0
    """Crop side in pixels; 0: the encoder's own input size (224 for the
    stand-in and ViT-B, 256 for MobileCLIP)."""
    images: Literal["all", "orig+self", "orig", "auto"] = "all"
    """"all": the original and every render; "orig+self": the original and its
    self render (U_T without the novel appearances: 2 images a view instead of
    N + 1); "orig": originals only (then the stage does not depend on reconstruct:
    LangSplat's recipe on any geometry); "auto": "all" only where the encoder's
    features of a segment move with the novel appearances, measured on a few
    views first (`ptovs.fit.appearance_sensitivity`), else "orig+self"."""
    import_dir: str = ""
    """A LangSplat feature folder to read instead of segmenting and encoding."""
    segment: Literal["each", "once"] = "once"
    """"once": segment one image of the view (`segment_from`) and crop every image
    with its segments (the renders share the photo's camera): one segmenter call
    per view instead of 2 + N, and every slot describes the same regions; "each":
    segment every image of a view (the paper's), so a render that moves a little
    can move its segments a lot."""
    segment_from: Literal["self", "orig"] = "orig"
    """The image "once" segments: the original photo (no reconstruction, float
    path or seed moves it; also used when there are no renders) or the self
    render (the photo's camera and appearance without its transient occluders)."""
    min_crop_px: int = 0
    """Leave out segments whose crop (the longer side of the mask's bounding box,
    in pixels of the image) is shorter than this: no row is encoded and their
    pixels have no segment at that level. 0: keep every segment."""


@dataclass(frozen=True)
class Inputs:
    scene: Any = scene_input()
    renders: Artifact | None = upstream(
        "render-appearances", when=lambda c: c.images != "orig"
    )
    """Not for images = "orig": originals alone depend on the photos, not the field."""


def build_segmenter(config: Config, scene_root: Path | None = None) -> Segmenter:
    levels = check_levels(config.levels)
    if config.segmenter == "graph":
        if config.graph_k and len(config.graph_k) != len(levels):
            raise ValueError(f"graph_k needs one value per level {list(levels)}")
        k = dict(zip(levels, config.graph_k, strict=True)) if config.graph_k else None
        return get_segmenter(
            "graph",
            levels=levels,
            k=k,
            sigma=config.graph_sigma,
            min_size=config.graph_min_size,
        )
    if config.segmenter == "hier":
        if config.hier_thresholds and len(config.hier_thresholds) != len(levels):
            raise ValueError(
                f"hier_thresholds needs one value per level {list(levels)}"
            )
        th = config.hier_thresholds
        return get_segmenter(
            "hier",
            levels=levels,
            thresholds=dict(zip(levels, th, strict=True)) if th else None,
            texture=config.hier_texture,
            edge=config.hier_edge,
            min_size=config.hier_min_size,
        )
    if config.segmenter == "truth":
        if scene_root is None:
            raise ValueError("segmenter 'truth' needs the scene's folder")
        from ptovs.segment.truth import TruthSegmenter

        return TruthSegmenter(scene_root, levels)
    sam2 = config.segmenter == "sam2"
    return get_segmenter(
        config.segmenter,
        checkpoint=config.sam_checkpoint,
        model_type=config.sam2_model if sam2 else config.sam_model,
        levels=levels,
        points_per_side=config.sam_points_per_side,
        crop_n_layers=config.sam_crop_n_layers,
        device=config.device,
        runtime=config.runtime,
    )


def _vocabulary(scene_root: Path | None) -> Path | None:
    path = (
        None
        if scene_root is None
        else Path(scene_root) / "synthetic" / "vocabulary.json"
    )
    return path if path is not None and path.is_file() else None


def encoder_spec(config: Config, encoder: Encoder) -> dict:
    """What query needs to embed texts in the features' space: the encoder's
    name, and for OpenCLIP the model and checkpoint (recorded in levels_json)."""
    if encoder.name == "openclip":
        return {
            "name": "openclip",
            "model": config.clip_model,
            "checkpoint": str(config.clip_checkpoint),
            "pretrained": config.clip_pretrained,
            "tokenizer": str(config.clip_tokenizer),
        }
    return {"name": encoder.name}


def build_encoder(
    config: Config, synthetic: bool, scene_root: Path | None = None
) -> Encoder:
    name = config.encoder
    if name == "auto":
        name = "synthetic" if synthetic else "openclip"
    if name == "synthetic":
        # the image side needs no phrases, only the scene's stand-in version
        return get_encoder("synthetic", vocabulary=_vocabulary(scene_root))
    return get_encoder(
        "openclip",
        model=config.clip_model,
        checkpoint=config.clip_checkpoint,
        device=config.device,
        batch_size=config.batch_size,
        pretrained=config.clip_pretrained,
        tokenizer=config.clip_tokenizer,
        precision=config.precision,
        runtime=config.runtime,
    )


def crop_side(config: Config, encoder: Encoder) -> int:
    """The crop side: config.crop_size, or the encoder's own input size."""
    return int(config.crop_size or getattr(encoder, "size", 224))


def image_features(
    image: np.ndarray,  # [H, W, 3] uint8 RGB
    segmenter: Segmenter,
    encoder: Encoder,
    batch_size: int = 64,
    crop_size: int = 224,
) -> SegmentFeatures:
    """Segment one image at every level and encode each segment's crop."""
    return encode_levels(
        image, segmenter.segment(image), encoder, batch_size, crop_size
    )


def encode_levels(
    image: np.ndarray,  # [H, W, 3] uint8 RGB
    levels: list,
    encoder: Encoder,
    batch_size: int = 64,
    crop_size: int = 224,
) -> SegmentFeatures:
    """Encode each segment's crop of an image already segmented (`Level`s).

    A segment that recurs with the same mask (a region no finer level splits)
    gives the same crop, so it is encoded once and its row copied. Crops are
    resized as the encoder's pretrained tag resizes (`resample`, OpenCLIP's), or
    with cv2 for the stand-in."""
    resample = getattr(encoder, "resample", None)
    order, where = unique_segments(levels)
    feats = [np.zeros((lv.n, encoder.dim), np.float32) for lv in levels]
    step = int(batch_size) or 64
    for start in range(0, len(order), step):  # bounded memory per batch
        batch = order[start : start + step]
        crops = np.stack(
            [
                prepare_crop(image, levels[lv].mask(k), crop_size, resample=resample)
                for lv, k in batch
            ]  # fmt: skip
        )
        rows = encoder.encode_images(crops)
        for j, (lv, k) in enumerate(batch):
            for lv2, k2 in where[(lv, k)]:
                feats[lv2][k2] = rows[j]
    return SegmentFeatures.from_levels(levels, feats, encoder.dim)


def unique_segments(
    levels: list,
) -> tuple[list[tuple[int, int]], dict[tuple[int, int], list[tuple[int, int]]]]:
    """The (level, id) of each distinct segment mask, first occurrence first,
    and for each of them every (level, id) with the same mask."""
    first: dict[bytes, tuple[int, int]] = {}
    where: dict[tuple[int, int], list[tuple[int, int]]] = {}
    order: list[tuple[int, int]] = []
    for lv, level in enumerate(levels):
        for k in range(level.n):
            m = np.asarray(level.mask(k), bool)
            rows, cols = np.flatnonzero(m.any(1)), np.flatnonzero(m.any(0))
            box = np.array([rows[0], rows[-1], cols[0], cols[-1]], np.int64)
            inner = m[box[0] : box[1] + 1, box[2] : box[3] + 1]
            key = hashlib.blake2b(
                box.tobytes() + np.packbits(inner).tobytes(), digest_size=16
            ).digest()
            if key not in first:
                first[key] = (lv, k)
                order.append((lv, k))
                where[(lv, k)] = []
            where[first[key]].append((lv, k))
    return order, where


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


def check_precision(encoder: Encoder, levels: list, image, crop_size: int):
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
    encoder: Encoder,
    notes: Notes | None,
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
            report = check_precision(encoder, levels, image, crop_size)
        if notes is not None:
            notes.put("precision", report)
    encoder.precision = report["precision"]
    return report


def decide_runtime(
    encoder: Encoder,
    notes: Notes | None,
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


def restore_segmenter_runtime(segmenter: Segmenter, notes: Notes | None) -> bool:
    """A resumed run's SAM-class segmenter runs its image encoder in the runtime
    its artifact was begun with (kept in `notes`), not deciding again. True where
    a decision was kept (nothing more to note)."""
    report = None if notes is None else notes.get("segmenter_runtime")
    if report is not None and hasattr(segmenter, "use_runtime"):
        segmenter.use_runtime(report)
        log.info("segmenter runtime: %s, as chosen when this artifact was begun "
                 "(not measured again)", report["runtime"])  # fmt: skip
    return report is not None


def note_segmenter_runtime(segmenter: Segmenter, notes: Notes | None) -> bool:
    """Keep a SAM-class segmenter's runtime decision (made on its first image) in
    `notes` before a view of its is written. True once kept."""
    report = getattr(segmenter, "runtime_report", None)
    if report is None or notes is None:
        return False
    notes.put("segmenter_runtime", report)
    return True


EMPTY_FIRST = 3
"""Stop when each of the first this many views has no segment at all."""
EMPTY_AFTER = 5
"""From this many views on, stop when more than half have no segment."""
EMPTY_WARNINGS = 3
"""Warn for each of the first this many empty views, then for every tenth."""


def too_many_empty(empty: int, finished: int, total: int) -> bool:
    """Whether `empty` of `finished` views (of `total`) without any segment say
    the segmenter is broken for these images: all of the first EMPTY_FIRST, more
    than half from EMPTY_AFTER views on, or more than half of the whole scene."""
    if finished >= total:
        return 2 * empty > total
    if finished >= EMPTY_FIRST and empty == finished:
        return True
    return finished >= EMPTY_AFTER and 2 * empty > finished


def empty_causes(config: Config, shape: tuple[int, int]) -> str:
    """The likely causes of a segmenter finding nothing, with the config keys
    to look at (one line, for the error)."""
    seg = config.segmenter
    if seg in ("sam", "sam2"):
        model = config.sam2_model if seg == "sam2" else config.sam_model
        causes = [
            f"a wrong or randomly initialised checkpoint (sam_checkpoint = "
            f"{config.sam_checkpoint!r} for segmenter {seg!r}, model {model!r})",
            f"prompts too sparse (sam_points_per_side = {config.sam_points_per_side}"
            f", sam_crop_n_layers = {config.sam_crop_n_layers})",
        ]
    elif seg == "hier":
        causes = [
            "thresholds too strict (hier_thresholds, hier_min_size = "
            f"{config.hier_min_size})"
        ]
    elif seg == "graph":
        causes = [
            f"thresholds too strict (graph_k, graph_min_size = {config.graph_min_size})"
        ]
    else:
        causes = ["part masks missing from the scene's folder"]
    if config.min_crop_px > 0:
        causes.append(f"min_crop_px = {config.min_crop_px} leaving out every segment")
    causes.append(f"images too small ({shape[1]}x{shape[0]} px; see scene.downscale)")
    return "; ".join(causes)


def crop_sides(level: Level) -> np.ndarray:
    """[n] the longer side of each segment's crop box (of `level.mask(k)`, the
    pixels `prepare_crop` cuts out, its box inclusive), in pixels."""
    if level.masks is None:
        lab = level.labels
        n = level.n
        ys, xs = np.nonzero(lab >= 0)
        ids = lab[ys, xs]
        y0 = np.full(n, np.iinfo(np.int64).max)
        x0 = y0.copy()
        y1 = np.full(n, -1)
        x1 = y1.copy()
        np.minimum.at(y0, ids, ys)
        np.minimum.at(x0, ids, xs)
        np.maximum.at(y1, ids, ys)
        np.maximum.at(x1, ids, xs)
        return np.maximum(y1 - y0, x1 - x0) + 1
    sides = []
    for m in level.masks:
        rows = np.flatnonzero(m.any(axis=1))
        cols = np.flatnonzero(m.any(axis=0))
        sides.append(max(rows[-1] - rows[0], cols[-1] - cols[0]) + 1)
    return np.array(sides, np.int64)


def drop_small_segments(levels: list[Level], min_crop_px: int) -> list[Level]:
    """Each level without the segments whose crop's longer side is under
    `min_crop_px` (`crop_sides`): their pixels become NO_SEGMENT and the rest are
    renumbered 0..n'-1 in their order. 0 returns `levels` unchanged."""
    if min_crop_px <= 0:
        return levels
    out = []
    for level in levels:
        keep = crop_sides(level) >= min_crop_px
        if keep.all():
            out.append(level)
            continue
        new = np.where(keep, np.cumsum(keep) - 1, NO_SEGMENT).astype(np.int32)
        lab = level.labels
        labels = np.where(lab >= 0, new[np.maximum(lab, 0)], NO_SEGMENT)
        masks = None
        if level.masks is not None:
            masks = [m for m, k in zip(level.masks, keep, strict=True) if k]
        out.append(Level(labels.astype(np.int32), masks))
    return out


class _Cut:
    """A segmenter that hands back levels already cut (by `_cut_levels`), so that
    `image_features` crops and encodes an image with them."""

    name = "cut"

    def __init__(self, names: tuple[str, ...], levels: list[Level]):
        self.levels = names
        self._cut = levels

    def segment(self, image: np.ndarray) -> list[Level]:
        shape = self._cut[0].labels.shape if self._cut else image.shape[:2]
        if image.shape[:2] != shape:
            raise ValueError(f"image {image.shape[:2]} is not the segments' {shape}")
        return self._cut


def _cut_levels(
    segmenter: Segmenter, stem: str, app: str, image: np.ndarray, min_crop_px: int
) -> list[Level]:
    """Segment the image `app` of view `stem`, small segments left out."""
    if hasattr(segmenter, "select"):  # truth: this view, occluders or not
        segmenter.select(stem, app == "orig")
    return drop_small_segments(segmenter.segment(image), min_crop_px)


def run(
    inputs: Inputs, config: Config, skip=frozenset(), notes: Notes | None = None
) -> Iterator[tuple[str | None, dict]]:
    """Yield each train view's features for the original and every render.

    `notes` (the chain's partial artifact's): where the precision chosen and the
    views without segments are kept across an interrupted run."""
    scene = inputs.scene
    levels = check_levels(config.levels)
    slots = (
        read_json_dataset(inputs.renders.root()["slots_json"])["slots"]
        if inputs.renders is not None
        else []
    )
    novel = [s for s in slots if s != "self"]
    images = config.images
    importing = bool(config.import_dir)
    views = scene.train_views()
    encoder: Any = None  # importing: no encoder
    seg_noted = True  # importing: no segmenter runtime to note
    if importing:
        folder = Path(config.import_dir)
        if not folder.is_dir():
            raise FileNotFoundError(f"import_dir {folder} is not a folder")
    else:
        segmenter = build_segmenter(config, scene.root)
        seg_noted = restore_segmenter_runtime(segmenter, notes)
        encoder = build_encoder(config, scene.synthetic, scene.root)
        side = crop_side(config, encoder)

        @functools.cache
        def first_view() -> tuple[list, np.ndarray]:
            v0 = views[0]  # the same sample whatever was skipped
            img0 = to_uint8(scene.load_image(v0))
            cut0 = _cut_levels(segmenter, v0.stem, "orig", img0, config.min_crop_px)
            return cut0, img0

        precision = decide_precision(encoder, notes, first_view, side)
        runtime = decide_runtime(encoder, notes, first_view, side)
        if runtime is not None:  # a real encoder: each distinct crop encoded once
            encoder = CropMemo(encoder)
    probe = None
    if images == "auto" and importing:  # imported features: whatever the folder has
        images = "all"
    if images == "auto":
        probe = decide_images(
            notes, novel, lambda: _probe_views(
                scene, views, inputs.renders, slots, segmenter, encoder, config, side
            ),
        )  # fmt: skip
        images = probe["images"]
        if isinstance(encoder, CropMemo):
            encoder.pin()  # the probe views' crops: not encoded again below
    apps = ["orig"] + {"all": slots, "orig+self": ["self"], "orig": []}[images]
    # the image a view is segmented from when segment = "once"
    source = "self" if config.segment_from == "self" and "self" in apps else "orig"
    # views with no segment at any level: kept in the notes, so a resumed run
    # counts the whole artifact's (a view redone after a kill is counted once)
    empty = set(notes.get("empty_views", [])) if notes is not None else set()
    finished = len(skip & {v.name for v in views})
    for v in views:
        if v.name in skip:
            continue
        renders = inputs.renders[v.name]["rgb"] if len(apps) > 1 else None

        def image(app: str, v=v, renders=renders) -> np.ndarray:
            if app == "orig":
                return to_uint8(scene.load_image(v))  # clipped: no wrap
            return renders[slots.index(app)]

        shared = None  # the view's segments, cut once
        if not importing and config.segment == "once":
            shared = _cut_levels(
                segmenter, v.stem, source, image(source), config.min_crop_px
            )
        out: dict[str, np.ndarray] = {}
        found = False  # any segment in any image of the view
        for app in apps:
            if importing:
                f = read_langsplat(folder, v.stem, levels, langsplat_suffix(app, novel))
                check_size(f.seg[0], v, f"imported LangSplat features {app}")
            else:
                img = image(app)
                cut = shared
                if cut is None:
                    cut = _cut_levels(segmenter, v.stem, app, img, config.min_crop_px)
                found = found or any(lv.n > 0 for lv in cut)
                f = image_features(
                    img, _Cut(levels, cut), encoder, config.batch_size, side
                )
            f.validate(f"{v.name} {app}")
            out.update(f.datasets(app))
        finished += 1
        if isinstance(encoder, CropMemo):
            encoder.forget()
        if not importing and not seg_noted:  # the notes file read and written once
            seg_noted = note_segmenter_runtime(segmenter, notes)
        if not importing and not found:
            _note_empty(v.name, empty, notes)
        if not importing and too_many_empty(len(empty), finished, len(views)):
            causes = empty_causes(config, (v.height, v.width))
            raise UselessOutputError(
                f"extract-features: segmenter {config.segmenter!r} found no segment "
                f"at any level in {len(empty)} of {finished} views (e.g. "
                f"{', '.join(sorted(empty)[:3])}); likely causes: "
                f"{causes}. Nothing was kept; fix the config and rerun"
            )
        yield v.name, out
    if empty:
        log.warning(
            "extract-features: %d of %d views have no segment at any level (their "
            "pixels have no features): %s",
            len(empty), len(views), ", ".join(sorted(empty)[:10])
            + (", ..." if len(empty) > 10 else ""),
        )  # fmt: skip
    yield (
        None,
        {
            "levels_json": json_dataset(
                {
                    "levels": list(levels),
                    "apps": apps,
                    "images": images,
                    "images_probe": probe,
                    "segmenter": "import" if importing else config.segmenter,
                    "segment": None
                    if importing
                    else (
                        f"once from {source}" if config.segment == "once" else "each"
                    ),
                    "min_crop_px": None if importing else config.min_crop_px,
                    "encoder": "import" if importing else encoder.name,
                    "encoder_spec": None
                    if importing
                    else encoder_spec(config, encoder),
                    "precision": None if importing else precision,
                    "runtime": None if importing else runtime,
                    "segmenter_runtime": None
                    if importing
                    else getattr(segmenter, "runtime_report", None),
                    "crops": _crop_counts(encoder) if not importing else None,
                    "empty_views": None if importing else len(empty),
                    "empty_view_names": None if importing else sorted(empty),
                    "views": len(views),
                }
            )
        },
    )


def _crop_counts(encoder: Any) -> dict | None:
    """Crops the encoder ran and crops whose rows were reused (a `CropMemo`'s)."""
    if not isinstance(encoder, CropMemo):
        return None
    log.info("extract-features: %d crops encoded, %d reused (probe views and "
             "repeated pixels)", encoder.encoded, encoder.hits)  # fmt: skip
    return {"encoded": encoder.encoded, "reused": encoder.hits}


PROBE_VIEWS = 4
"""Views the images = "auto" probe encodes under every appearance (evenly spaced)."""


def _probe_views(
    scene, views, renders, slots, segmenter, encoder, config: Config, side: int
) -> list[tuple[np.ndarray, list[np.ndarray]]]:
    """Per probe view: the self render's segment features and each novel
    render's features of the same segments (one cut, every image cropped by it),
    as row-aligned [n, D] tables."""
    novel = [s for s in slots if s != "self"]
    step = max(1, len(views) // PROBE_VIEWS)
    out = []
    for v in views[::step][:PROBE_VIEWS]:
        rgb = renders[v.name]["rgb"]
        own = rgb[slots.index("self")]
        cut = _cut_levels(segmenter, v.stem, "self", own, config.min_crop_px)
        if not any(lv.n > 0 for lv in cut):
            continue
        shared = _Cut(check_levels(config.levels), cut)

        def table(img: np.ndarray, shared: _Cut = shared) -> np.ndarray:
            f = image_features(img, shared, encoder, config.batch_size, side)
            return np.asarray(f.table, np.float32)

        out.append((table(own), [table(rgb[slots.index(a)]) for a in novel]))
    return out


def decide_images(
    notes: Notes | None, novel: list[str], probe: Callable[[], list]
) -> dict[str, Any]:
    """images = "auto": "all" when the novel appearances move the encoder's
    features (`ptovs.fit.appearance_sensitivity` above `fit.SENSITIVITY`), else
    "orig+self"; with no novel appearance, "orig+self" without a probe. Made once
    per artifact (kept in `notes`, so a resumed run encodes the same images) and
    logged in one line with its evidence."""
    from ptovs import fit

    report = None if notes is None else notes.get("images")
    if report is not None:
        log.info("images: %s, as chosen when this artifact was begun", report["images"])
        return report
    if not novel:
        report = {"images": "orig+self", "why": "no novel appearance rendered"}
    else:
        report = fit.images_decision(probe())
    log.info(
        "extract-features: images = %s (auto: %s)", report["images"], report["why"]
    )
    if notes is not None:
        notes.put("images", report)
    return report


def _note_empty(name: str, empty: set[str], notes: Notes | None) -> None:
    """Count a view without segments; warn (the first few, then every tenth)."""
    if name in empty:  # redone after a kill: counted already
        return
    empty.add(name)
    if notes is not None:
        notes.put("empty_views", sorted(empty))
    n = len(empty)
    if n <= EMPTY_WARNINGS or n % 10 == 0:
        log.warning(
            "view %s: the segmenter found no segment at any level (%d such view%s "
            "so far)",
            name, n, "" if n == 1 else "s",
        )  # fmt: skip


def _count(inputs: Inputs, config: Config) -> int:
    return len(inputs.scene.train_views())


SAM_GENERATOR = "2"
"""The SAM/SAM 2.1 generator's version: 2 equals upstream's generators mask for mask
and orders SAM 2.1's outputs by area (its features differ from version 1's)."""


def extra_key(config: Config, scene_ref) -> dict[str, str]:
    """What besides the config keys the features: the SAM generator's version for
    segmenter sam/sam2 (so the other segmenters keep their keys), and the stand-in
    version of a scene written for version 5 (version 1 scenes keep the keys they
    always had)."""
    out = (
        {"sam_generator": SAM_GENERATOR}
        if config.segmenter in ("sam", "sam2") and not config.import_dir
        else {}
    )
    if config.encoder not in ("auto", "synthetic"):
        return out
    path = _vocabulary(scene_ref.load().root)
    if path is None:
        return out
    import json

    from ptovs.encoders import standin_version

    v = standin_version(json.loads(path.read_text()), path)
    return out if v == 1 else {**out, "standin": str(v)}


command = stage_command(
    NAME, VERSION, Config, Inputs, run, count=_count, extra_key=extra_key
)

__all__ = [
    "EMPTY_AFTER",
    "EMPTY_FIRST",
    "Config",
    "Inputs",
    "build_encoder",
    "encoder_spec",
    "build_segmenter",
    "command",
    "crop_sides",
    "decide_precision",
    "decide_runtime",
    "drop_small_segments",
    "encode_levels",
    "image_features",
    "run",
    "too_many_empty",
]

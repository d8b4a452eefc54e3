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
checkpoint, extra [clip]; the default elsewhere), each built and checked by its
backend (`ptovs.segment.backend`, `ptovs.encoders.backend`; the precision and
runtime decisions: `ptovs.encoders.decide`). Or
`import_dir`: a LangSplat feature folder (`<id>_f.npy`, `<id>_s.npy`, renders
`<id>_f_ma_<k>.npy`) used instead of segmenting and encoding.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from ptovs.artifacts import Artifact, Notes, json_dataset, read_json_dataset
from ptovs.encoders import Encoder, prepare_crop, vocabulary_file
from ptovs.encoders.backend import ENCODER_CHOICES, build_encoder, encoder_spec
from ptovs.encoders.decide import decide_precision, decide_runtime
from ptovs.encoders.memo import CropMemo, unique_segments
from ptovs.errors import UselessOutputError
from ptovs.features import SegmentFeatures, langsplat_suffix, read_langsplat
from ptovs.registry import scene_input, upstream
from ptovs.scene import check_size
from ptovs.segment import Segmenter, check_levels
from ptovs.segment.backend import (
    SEGMENTER_CHOICES,
    build_segmenter,
    get_segmenter_backend,
    note_segmenter_runtime,
    restore_segmenter_runtime,
)
from ptovs.segment.cut import Cut, cut_levels
from ptovs.stage import stage_command
from ptovs.visual import to_uint8

log = logging.getLogger(__name__)

NAME = "extract-features"
VERSION = 1


@dataclass(frozen=True)
class Config:
    levels: tuple[Literal["default", "s", "m", "l"], ...] = ("s", "m", "l")
    """Levels, from "default", "s", "m", "l" (LangSplat's four; the paper uses s/m/l)."""
    segmenter: Literal[SEGMENTER_CHOICES] = "hier"
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
    encoder: Literal[ENCODER_CHOICES] = "auto"
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
    to look at (one line, for the error): the segmenter's own, then these."""
    causes = get_segmenter_backend(config.segmenter).empty_causes(config)
    if config.min_crop_px > 0:
        causes.append(f"min_crop_px = {config.min_crop_px} leaving out every segment")
    causes.append(f"images too small ({shape[1]}x{shape[0]} px; see scene.downscale)")
    return "; ".join(causes)


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
            cut0 = cut_levels(segmenter, v0.stem, "orig", img0, config.min_crop_px)
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
            shared = cut_levels(
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
                    cut = cut_levels(segmenter, v.stem, app, img, config.min_crop_px)
                found = found or any(lv.n > 0 for lv in cut)
                f = image_features(
                    img, Cut(levels, cut), encoder, config.batch_size, side
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
        cut = cut_levels(segmenter, v.stem, "self", own, config.min_crop_px)
        if not any(lv.n > 0 for lv in cut):
            continue
        shared = Cut(check_levels(config.levels), cut)

        def table(img: np.ndarray, shared: Cut = shared) -> np.ndarray:
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


def extra_key(config: Config, scene_ref) -> dict[str, str]:
    """What besides the config keys the features: the SAM generator's version for
    segmenter sam/sam2 (so the other segmenters keep their keys), and the stand-in
    version of a scene written for version 5 (version 1 scenes keep the keys they
    always had)."""
    out = {}
    if not config.import_dir:
        out = get_segmenter_backend(config.segmenter).extra_key(config)
    if config.encoder not in ("auto", "synthetic"):
        return out
    path = vocabulary_file(scene_ref.load().root)
    if path is None:
        return out
    import json

    from ptovs.encoders import standin_version

    v = standin_version(json.loads(path.read_text()), path)
    return out if v == 1 else {**out, "standin": str(v)}


command = stage_command(
    NAME, VERSION, Config, Inputs, run, count=_count, extra_key=extra_key
)

# build_encoder/build_segmenter are the backends' (`ptovs.encoders.backend`,
# `ptovs.segment.backend`), named here as `run` calls them
__all__ = [
    "EMPTY_AFTER",
    "EMPTY_FIRST",
    "Config",
    "Inputs",
    "build_encoder",
    "build_segmenter",
    "command",
    "encode_levels",
    "extra_key",
    "image_features",
    "run",
    "too_many_empty",
]

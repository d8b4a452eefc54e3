"""Presets of synthetic scenes, the random streams of a seed, and the file
helpers every writer of a scene shares (docs/synthetic.md)."""

from __future__ import annotations

import dataclasses
import json
import shutil
import zipfile
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ptovs.synthetic.world import (
    Camera,
    World,
    build_world,
)

TRUTH_VERSION = 2  # 2: screened queries, every labelled part a query
STYLES = (
    "Neoclassical",
    "Gothic",
    "Baroque",
    "Romanesque",
    "Byzantine",
    "Renaissance",
    "Georgian",
    "Palladian",
    "Moorish",
    "Art Deco",
    "Victorian Gothic",
    "Edwardian Baroque",
)
"""Style names the generator gives landmarks (`scene_styles`)."""
N_STYLES = 5  # candidates per scene, as the paper's LLM proposes
# q95 without chroma subsampling: at ~96 px, 4:2:0 visibly smears part colours
_JPEG = [
    cv2.IMWRITE_JPEG_QUALITY,
    95,
    cv2.IMWRITE_JPEG_SAMPLING_FACTOR,
    cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444,
]


@dataclass(frozen=True)
class Preset:
    """Size of a generated scene.

    Every part labelled in some evaluation view is a query, unless the screen
    (`ptovs.synthetic.screen`) finds its phrase unanswerable.
    """

    n_train: int
    n_test: int
    n_eval: int
    n_cand: int  # frontal train cameras the evaluation views are chosen from
    long_side: tuple[int, int]  # range of the image's long side, pixels
    n_parts: tuple[int, int]  # range
    aa: int  # samples per pixel (1 or 5)
    points_per_image: int
    track_keep: float  # chance to keep a visible observation in a track
    swatch_px: int  # resolution the vocabulary swatches are rendered at
    max_cover: float = 0.4  # largest transient coverage of an image
    max_train: int = 0
    """The most train photos `--photos` may ask (0: n_train). Those past n_train are
    more photos of the same world: cameras drawn as the others' (never an
    evaluation candidate), after every photo of the preset's own plan."""
    scale: int = 1
    """Photograph the plan at `scale` times the side: the world, cameras, evaluation
    views and screen are those of the same preset at scale 1 (drawn at
    `long_side`), and only the photos have more pixels."""

    @property
    def train_limit(self) -> int:
        """The most train photos a scene of this preset may have."""
        return max(self.max_train, self.n_train)


PRESETS: dict[str, Preset] = {
    "tiny": Preset(
        n_train=12,
        n_test=1,
        n_eval=2,
        n_cand=8,
        long_side=(88, 104),
        n_parts=(3, 3),
        aa=5,
        points_per_image=60,
        track_keep=1.0,
        swatch_px=32,
    ),
    # the demo (make demo): big enough that a part's mask reads as the part (a
    # column is a column), small enough for the whole chain in about 5 minutes
    "demo": Preset(
        n_train=20,
        n_test=2,
        n_eval=3,
        n_cand=12,
        long_side=(160, 176),
        n_parts=(4, 4),
        aa=5,
        points_per_image=80,
        track_keep=1.0,
        swatch_px=48,
    ),
    # the accuracy instrument's scenes (bench/accuracy.py): bench's landmarks and
    # evaluation design at about half the image side and 60 % of the views
    "small": Preset(
        n_train=48,
        n_test=4,
        n_eval=20,
        n_cand=30,
        long_side=(176, 256),
        n_parts=(5, 7),
        aa=5,
        points_per_image=100,
        track_keep=1.0,
        swatch_px=64,
    ),
    "bench": Preset(
        n_train=80,
        n_test=8,
        n_eval=20,
        n_cand=42,
        long_side=(240, 400),
        n_parts=(6, 8),
        aa=5,
        points_per_image=120,
        track_keep=1.0,
        swatch_px=96,
    ),
    # a Brandenburg-sized collection (PT-OVS: 763 train photos at about 700 px on the
    # long side): bench's landmarks and evaluation design at a real photo size.
    # One sample a pixel (at this size aliasing is a pixel's, not a part's) and a
    # tenth of each point's observations keep generation and the model's tracks
    # within minutes and memory; `--photos N` takes the first N train photos.
    "landmark": Preset(
        n_train=763,
        n_test=8,
        n_eval=20,
        n_cand=42,
        long_side=(640, 760),
        n_parts=(6, 8),
        aa=1,
        points_per_image=60,
        track_keep=0.1,
        swatch_px=96,
        max_train=2934,  # Notre-Dame, PT-OVS's largest scene
    ),
    "scale": Preset(
        n_train=3000,
        n_test=60,
        n_eval=4,
        n_cand=14,
        long_side=(60, 68),
        n_parts=(6, 8),
        aa=1,
        points_per_image=8,
        track_keep=0.02,
        swatch_px=24,
    ),
}


# small's scenes photographed at three times the side (528-768 px, parts 60-250 px):
# the same worlds and cameras as small, at about PT-OVS's photo size (about 700 px)
PRESETS["small-3x"] = dataclasses.replace(PRESETS["small"], scale=3)


def _rng(seed: int, *stream: int) -> np.random.Generator:
    return np.random.default_rng([seed, *stream])


def _min_px(cam: Camera, frac: float, floor: int) -> int:
    return max(floor, int(frac * cam.width * cam.height))


def _world(cfg: Preset, seed: int) -> World:
    rng = _rng(seed, 0)
    return build_world(rng, int(rng.integers(cfg.n_parts[0], cfg.n_parts[1] + 1)))


def _prepare_out(out: Path, name: str) -> tuple[Path, Path]:
    scene = out / name
    label = out / "label" / name
    if scene.exists() and any(scene.iterdir()):
        if not (scene / "synthetic" / "truth").is_dir():
            raise FileExistsError(
                f"{scene} exists and is not a synthetic scene; refusing to overwrite"
            )
        shutil.rmtree(scene)
    if label.exists():
        shutil.rmtree(label)
    for p in (
        scene / "dense" / "images",
        scene / "dense" / "sparse",
        scene / "synthetic" / "truth",
        label,
    ):
        p.mkdir(parents=True, exist_ok=True)
    return scene, label


def _save_npz(path: Path, **arrays: np.ndarray) -> None:
    """np.savez_compressed with fixed zip timestamps: byte-identical reruns."""
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for key, arr in arrays.items():
            info = zipfile.ZipInfo(f"{key}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            with zf.open(info, "w", force_zip64=True) as f:
                np.lib.format.write_array(f, np.asanyarray(arr), allow_pickle=False)


def _write_json(path: Path, obj) -> None:
    path.write_text(json.dumps(obj, indent=1) + "\n")

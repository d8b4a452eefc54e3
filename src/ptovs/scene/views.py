"""A loaded scene and its views (cameras at working resolution)."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ptovs.scene.images import load_image

logger = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class View:
    """One registered image of a scene, with its camera at working resolution."""

    name: str
    """Image file name as in the COLMAP model, e.g. "15080601_1551250100.jpg"."""
    stem: str
    """`name` without its extension: the key of labels and per-view artifacts."""
    image_id: int
    """COLMAP image id."""
    image_path: Path
    split: str
    """"train" or "test"."""
    K: np.ndarray  # [3, 3] float64, at working size
    cam_from_world: np.ndarray  # [4, 4] float64
    width: int
    """Working width (after the downscale r)."""
    height: int
    full_width: int
    """Width of the COLMAP camera (the image file on disk)."""
    full_height: int
    has_label: bool = False
    """Whether `<labels_dir>/<stem>.json` exists."""

    @property
    def size(self) -> tuple[int, int]:
        """Working size as (H, W), numpy order."""
        return (self.height, self.width)


@dataclass
class Scene:
    """A loaded scene: views sorted by name, sparse points, where labels live."""

    root: Path
    name: str
    downscale: int
    views: list[View]
    points_xyz: np.ndarray  # [P, 3] float64
    points_rgb: np.ndarray  # [P, 3] uint8
    points_error: np.ndarray  # [P] float64
    points_track_len: np.ndarray  # [P] int64
    labels_dir: Path | None
    split_file: Path | None
    synthetic: bool
    points_id: np.ndarray = field(
        default_factory=lambda: np.zeros(0, np.int64)
    )  # [P] int64, COLMAP point3D ids
    layout: str = "colmap"
    """"phototourism" or "colmap"."""
    images_dir: Path | None = None
    model_dir: Path | None = None
    model_files: list[Path] = field(default_factory=list)
    _index: dict[str, View] = field(init=False, repr=False, default_factory=dict)

    def __post_init__(self) -> None:
        self._index = {}
        for v in self.views:
            self._index[v.name] = v
        for v in self.views:
            self._index.setdefault(v.stem, v)

    def train_views(self) -> list[View]:
        """Views of the train split, in name order."""
        return [v for v in self.views if v.split == "train"]

    def test_views(self) -> list[View]:
        """Views of the test split, in name order."""
        return [v for v in self.views if v.split == "test"]

    def labelled_views(self) -> list[View]:
        """Views with a label JSON, in name order."""
        return [v for v in self.views if v.has_label]

    def view(self, name_or_stem: str) -> View:
        """The view with this image name or stem.

        Raises:
            KeyError: no such view (the message lists a few names).
        """
        try:
            return self._index[name_or_stem]
        except KeyError:
            some = ", ".join(v.name for v in self.views[:5])
            raise KeyError(
                f"no view {name_or_stem!r} in scene {self.name} "
                f"({len(self.views)} views, e.g. {some})"
            ) from None

    def load_image(self, view: View | str) -> np.ndarray:
        """`load_image` for a view of this scene (or its name or stem)."""
        if isinstance(view, str):
            view = self.view(view)
        return load_image(view)

    def fingerprint_files(self) -> list[Path]:
        """The files whose content defines the scene. Labels are not among them:
        only the stages that read labels are keyed by them (`label_files`), so a
        label edit does not retrain the chain.

        Returns:
            Model files, the split file (if any) and the views' images, in that
            order.
        """
        files = list(self.model_files)
        if self.split_file is not None:
            files.append(self.split_file)
        files += [v.image_path for v in self.views]
        return files

    def label_files(self) -> list[Path]:
        """The labelled views' label JSONs, in view order."""
        if self.labels_dir is None:
            return []
        return [self.labels_dir / f"{v.stem}.json" for v in self.views if v.has_label]

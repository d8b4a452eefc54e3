"""In-stage checkpoints of a long stage: the one reader and writer of `.ckpt` files.

`Store.checkpoint(scene, stage, key)` gives the slot `<key[:12]>.ckpt/last.pt`
beside the artifact; the stage framework (`ptovs.chain`) hands it to a stage's
`run` as `ckpt`, shows its step in `ptovs status` and deletes the folder once the
artifact is complete. A stage reads its saved state only through `load()`.
"""

from __future__ import annotations

import logging
import os
import shutil
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from ptovs.atomic import atomic_file

log = logging.getLogger(__name__)


class Checkpoint:
    """In-stage checkpoints of a long stage: `<key[:12]>.ckpt/last.pt` beside the artifact.

    `save(state)` writes a dict of tensors and plain containers atomically (temporary
    name, fsync, rename), tagged with the artifact key; `load()` reads it back with
    `torch.load(weights_only=True)` and returns None when there is none, when it
    belongs to another key, or when it is damaged (logged, moved aside). The stage
    framework deletes the folder once the artifact is complete.
    """

    NAME = "last.pt"

    def __init__(self, folder: Path, key: str):
        self.folder = Path(folder)
        self.key = key

    @property
    def path(self) -> Path:
        return self.folder / self.NAME

    def exists(self) -> bool:
        return self.path.is_file()

    def save(self, state: Mapping[str, Any]) -> None:
        import torch

        self.folder.mkdir(parents=True, exist_ok=True)
        with atomic_file(self.path, keep_suffix=False, durable=True) as tmp:
            torch.save({"key": self.key, "state": dict(state)}, tmp)

    def load(self) -> dict[str, Any] | None:
        import pickle

        import torch

        if not self.path.is_file():
            return None
        try:
            blob = torch.load(self.path, map_location="cpu", weights_only=True)
        except (
            OSError,
            RuntimeError,
            EOFError,
            ValueError,
            pickle.UnpicklingError,
        ) as exc:
            bad = self.path.with_name(self.NAME + ".corrupt")
            log.warning(
                "checkpoint %s is unreadable (%s); moved to %s, starting over",
                self.path,
                exc,
                bad.name,
            )
            os.replace(self.path, bad)
            return None
        if not isinstance(blob, dict) or blob.get("key") != self.key:
            log.warning("checkpoint %s belongs to another run; ignored", self.path)
            return None
        return blob["state"]

    def step(self) -> int | None:
        """The iteration stored in the checkpoint (for `ptovs status`), if any."""
        state = self.load() if self.exists() else None
        return None if state is None else int(state.get("step", 0))

    def clear(self) -> None:
        shutil.rmtree(self.folder, ignore_errors=True)

"""Segmenter backends: what extract-features builds from its config, and what
preflight checks before a chain starts, behind one interface.

A backend is one subclass of `SegmenterBackend` in one module, named by one line
of SEGMENTER_BACKENDS ("module:class", imported only when asked for):

    backend = get_segmenter_backend("sam2")
    backend.check(config)                   # preflight: one line naming file and fix
    segmenter = backend.build(config, levels, scene_root)

Each backend says which extract-features fields it reads besides `levels`
(`config_keys`), which pip extra installs its package (`extra`), what it adds to
the features' artifact key (`extra_key`), and the likely causes of it finding no
segment (`empty_causes`). The config's `segmenter` choices are the registry's
names, in its order.

A SAM-class segmenter decides its image encoder's runtime on its first image;
`note_segmenter_runtime` keeps that decision in a partial artifact's notes and
`restore_segmenter_runtime` hands it to a resumed run's segmenter.
"""

from __future__ import annotations

import importlib
import logging
from pathlib import Path
from typing import Any

from ptovs.errors import InputError
from ptovs.segment.levels import Segmenter, check_levels

log = logging.getLogger(__name__)

SEGMENTER_BACKENDS: dict[str, str] = {
    "graph": "ptovs.segment:GraphBackend",
    "hier": "ptovs.segment:HierBackend",
    "sam": "ptovs.segment.sam:SamBackend",
    "sam2": "ptovs.segment.sam2:Sam2Backend",
    "truth": "ptovs.segment:TruthBackend",
}
"""Each segmenter: "module:class". A new segmenter is one module and one line here."""

SEGMENTER_CHOICES = tuple(SEGMENTER_BACKENDS)


class SegmenterBackend:
    """One segmenter as extract-features and preflight see it (defaults: no
    config of its own, no checks, nothing added to the key)."""

    name = ""
    extra = ""
    """The pip extra that installs its package ("": none needed)."""
    config_keys: tuple[str, ...] = ()
    """The extract-features config fields it reads besides `levels`."""

    def build(
        self, config: Any, levels: tuple[str, ...], scene_root: Path | None
    ) -> Segmenter:
        """The segmenter of `config` at `levels` (checked names)."""
        raise NotImplementedError

    def check(self, config: Any) -> None:
        """Preflight, before any scene is read: raise an InputError (or
        MissingInputError) of one line naming the file and the fix."""

    def extra_key(self, config: Any) -> dict[str, str]:
        """What besides the config keys its features (e.g. a generator's version)."""
        return {}

    def empty_causes(self, config: Any) -> list[str]:
        """The likely causes of it finding no segment, naming the config keys."""
        return []


def get_segmenter_backend(name: str) -> SegmenterBackend:
    """The backend named `name` (one of SEGMENTER_BACKENDS)."""
    if name not in SEGMENTER_BACKENDS:
        raise InputError(
            f"extract-features.segmenter = {name!r}: choose from "
            f"{list(SEGMENTER_CHOICES)}"
        )
    module, cls = SEGMENTER_BACKENDS[name].split(":")
    return getattr(importlib.import_module(module), cls)()


def build_segmenter(config: Any, scene_root: Path | None = None) -> Segmenter:
    """The segmenter extract-features' `config` names, built by its backend."""
    levels = check_levels(config.levels)
    return get_segmenter_backend(config.segmenter).build(config, levels, scene_root)


def restore_segmenter_runtime(segmenter: Segmenter, notes: Any) -> bool:
    """A resumed run's SAM-class segmenter runs its image encoder in the runtime
    its artifact was begun with (kept in `notes`), not deciding again. True where
    a decision was kept (nothing more to note)."""
    report = None if notes is None else notes.get("segmenter_runtime")
    if report is not None and hasattr(segmenter, "use_runtime"):
        segmenter.use_runtime(report)
        log.info("segmenter runtime: %s, as chosen when this artifact was begun "
                 "(not measured again)", report["runtime"])  # fmt: skip
    return report is not None


def note_segmenter_runtime(segmenter: Segmenter, notes: Any) -> bool:
    """Keep a SAM-class segmenter's runtime decision (made on its first image) in
    `notes` before a view of its is written. True once kept."""
    report = getattr(segmenter, "runtime_report", None)
    if report is None or notes is None:
        return False
    notes.put("segmenter_runtime", report)
    return True


__all__ = [
    "SEGMENTER_BACKENDS",
    "SEGMENTER_CHOICES",
    "SegmenterBackend",
    "build_segmenter",
    "get_segmenter_backend",
    "note_segmenter_runtime",
    "restore_segmenter_runtime",
]

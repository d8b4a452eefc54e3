"""Checks that run before the first stage of a chain: a mistake that
would fail hours in (a missing or mismatched checkpoint, a phrase the encoder does
not know, a view that does not exist, a label file that does not parse) fails in
seconds instead, as one line naming the file and the fix, and leaves nothing
behind: no stage has started, so no `.parts`, `.lock` or artifact exists.

Only the stages that will run are checked (a cached stage needs nothing). What a
backend (encoder, segmenter) needs, its backend checks (`ptovs.encoders.backend`,
`ptovs.segment.backend`); this module names none of them.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from ptovs.encoders.backend import encoder_name, get_encoder_backend
from ptovs.errors import MissingInputError
from ptovs.segment.backend import get_segmenter_backend

log = logging.getLogger(__name__)


def check_extract_config(config: Any, synthetic: bool = False) -> None:
    """What extract-features needs that no scene decides: its encoder's and its
    segmenter's backends check their checkpoints (a folder of unposed photos is
    never synthetic, so this runs before SfM poses it)."""
    if config.import_dir:
        if not Path(config.import_dir).is_dir():
            raise MissingInputError(
                f"extract-features.import_dir {config.import_dir} is not a folder"
            )
        return
    get_encoder_backend(encoder_name(config.encoder, synthetic)).check(config)
    get_segmenter_backend(config.segmenter).check(config)


def _extract(config: Any, scene: Any) -> None:
    check_extract_config(config, scene.synthetic)
    if config.import_dir:
        return
    name = encoder_name(config.encoder, scene.synthetic)
    get_encoder_backend(name).check_scene(config, scene)


def _query(config: Any, scene: Any) -> None:
    from ptovs.field.query import encoder_name as query_encoder
    from ptovs.field.query import resolve_queries, resolve_views

    queries = resolve_queries(config, scene)  # parses the labels when no texts
    resolve_views(config, scene)
    if query_encoder(config, scene) == "synthetic" and scene.synthetic:
        from ptovs.encoders import scene_encoder
        from ptovs.field.query import check_vocabulary

        check_vocabulary(scene_encoder(scene.root), queries)


def preflight(chain: Any, stages: list[str]) -> None:
    """Check what `stages` (those not yet done) will need, before any runs.
    Nothing is written unless every check passes (not even the photos'
    fingerprint cache)."""
    from ptovs.keys import flush_fingerprints, read_only

    ok = False
    try:
        with read_only():
            _preflight(chain, stages)
        ok = True
    finally:
        flush_fingerprints(write=ok)


def _preflight(chain: Any, stages: list[str]) -> None:
    todo = [s for s in stages if chain.state(s)[0] != "done"]
    if not todo:
        return
    scene = chain.scene.load()
    if "extract-features" in todo:
        _extract(chain.config("extract-features"), scene)
    if "query" in todo:
        _query(chain.config("query"), scene)
    log.debug("preflight: %s checked", ", ".join(todo))


__all__ = [
    "check_extract_config",
    "preflight",
]

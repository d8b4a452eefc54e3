"""The config a scene was run with, recorded in its work dir.

A command that runs stages with `--config FILE` records, once its checks pass,
the file's path, sha256 and text, and the group's `--set` items, in
`<work>/<scene>/config.json` (atomically). A later command on that scene without
--config uses the recorded config, and says so in one line; so `ptovs status`
keys the chain the stages were run with, and a forgotten --config never starts
another chain. The recorded text is used even when the file has changed or gone
since (the line says so). A command with a --config that differs from the
recorded one runs with it, says so in one line, and records it; `ptovs status`
(read-only) records nothing.
"""

from __future__ import annotations

import hashlib
import json
import logging
import sys
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ptovs.config import check_config, load_config, merge, parse_sets
from ptovs.errors import InputError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - python 3.10
    import tomli as tomllib

log = logging.getLogger(__name__)

RECORD = "config.json"  # <work>/<scene>/config.json
RECORD_VERSION = 1


@dataclass(frozen=True)
class GivenConfig:
    """What the `ptovs` group was given: the --config file (None: none) and its
    text as read, and the group's --set items."""

    file: Path | None = None
    text: str = ""
    sets: tuple[str, ...] = ()

    @classmethod
    def read(cls, file: Path | None, sets: Iterable[str]) -> GivenConfig:
        """The group's options, the file read once (`ptovs.config.load_config`
        says what is wrong with it)."""
        if file is not None:
            load_config(file)  # a missing or malformed file: one line
            return cls(Path(file), Path(file).read_bytes().decode(), tuple(sets))
        return cls(None, "", tuple(sets))

    @property
    def digest(self) -> str:
        return hashlib.sha256(self.text.encode()).hexdigest()

    def config(self) -> dict[str, Any]:
        """The group's config: the file's tables, then the --set items."""
        base = tomllib.loads(self.text) if self.file is not None else {}
        return merge(base, parse_sets(self.sets))


def record_path(work_dir: Path, scene: str) -> Path:
    return Path(work_dir) / scene / RECORD


def read_record(path: Path) -> dict[str, Any] | None:
    """The recorded config, or None when there is none; a damaged one is an
    InputError naming the fix."""
    if not path.is_file():
        return None
    try:
        rec = json.loads(path.read_text())
        if not isinstance(rec, dict) or not isinstance(rec.get("toml"), str):
            raise ValueError("not a recorded config")
        tomllib.loads(rec["toml"])
        return rec
    except (OSError, ValueError, tomllib.TOMLDecodeError) as exc:
        raise InputError(
            f"the config recorded for this scene, {path}, is damaged ({exc}); give "
            "--config FILE (it is then recorded again) or delete it"
        ) from None


def _record_text(given: GivenConfig) -> str:
    assert given.file is not None
    record = {
        "version": RECORD_VERSION,
        "file": str(given.file.resolve()),
        "given": str(given.file),
        "sha256": given.digest,
        "sets": list(given.sets),
        "toml": given.text,
    }
    return json.dumps(record, indent=1) + "\n"


def _origin(rec: dict[str, Any]) -> str:
    """Where a recorded config came from: its file, plus any --set items."""
    sets = "".join(f" --set {s}" for s in rec.get("sets", []))
    return f"{rec.get('given') or rec.get('file')}{sets}"


def _source_state(rec: dict[str, Any]) -> str:
    """'' when the recorded file still holds the recorded text, else what became
    of it."""
    file = Path(rec.get("file", ""))
    try:
        same = hashlib.sha256(file.read_bytes()).hexdigest() == rec.get("sha256")
    except OSError:
        return "which no longer exists"
    return "" if same else "which has changed since"


def scene_config(
    work_dir: Path,
    scene: str,
    given: GivenConfig,
    config: dict[str, Any],
    overrides: dict[str, Any],
) -> dict[str, Any]:
    """The config a command uses for one scene: adopted from, or recorded into,
    `<work>/<scene>/config.json` (`ptovs.chain.RunContext.for_scene`).

    Args:
        given: the group's --config file and --set items.
        config: the command's config as given (the file, --set items, overrides).
        overrides: the command's own options, kept on top of a recorded config.

    Returns:
        Without --config and with a record: the recorded text and --set items, then
        this command's --set items and `overrides`, said in one line. Otherwise
        `config`; with --config, one line if it differs from the record, which it
        replaces when the command's checks pass (never under
        `ptovs.keys.read_only`).
    """
    from ptovs.keys import READ_ONLY, write_when_checked

    path = record_path(work_dir, scene)
    rec = read_record(path)
    if given.file is not None:
        same = rec is not None and (rec.get("sha256"), rec.get("sets")) == (
            given.digest,
            list(given.sets),
        )
        if rec is not None and not same:
            then = (
                "status shows its keys and records nothing"
                if READ_ONLY.get()
                else f"running with it, and it becomes {scene}'s recorded config"
            )
            log.warning(
                "--config %s differs from the config recorded for %s (%s, in %s): %s",
                given.file, scene, _origin(rec), path, then,
            )  # fmt: skip
        elif rec is None and not READ_ONLY.get():
            log.info("recording the config for %s in %s: later commands on %s "
                     "without --config use it", scene, path, scene)  # fmt: skip
        if not READ_ONLY.get() and not (
            same and rec.get("file") == str(given.file.resolve())
        ):
            write_when_checked(path, _record_text(given))
        return config
    if rec is None:
        return config
    recorded = merge(tomllib.loads(rec["toml"]), parse_sets(rec.get("sets", [])))
    adopted = merge(merge(recorded, parse_sets(given.sets)), overrides)
    check_config(adopted, f"the config recorded for {scene} ({path})")
    state = _source_state(rec)
    how = (
        f"from {_origin(rec)}, {state}: its recorded text is used"
        if state
        else f"from {_origin(rec)}"
    )
    log.warning(
        "using the config recorded for %s: %s (%s); give --config to choose another",
        scene, path, how,
    )  # fmt: skip
    return adopted

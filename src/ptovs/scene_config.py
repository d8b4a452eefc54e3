"""The settings a scene was run with, recorded in its work dir.

A command that runs stages records, once its checks pass, every setting it ran
with in `<work>/<scene>/config.json` (atomically): each `--config` file (path,
sha256 and text, in the order given), the group's `--set` items and the command's
own `--set` items (as SECTION.KEY=VALUE). A run with no `--config` and no `--set`
records that it ran with the defaults.

A later command on that scene without `--config` uses the recorded settings (its
own `--set` items go on top, and are recorded with them), and says so in one line;
so `ptovs status` keys the chain the stages were run with, its advice repeats that
chain, and a forgotten `--config` never starts another chain. The recorded text is
used even when a file has changed or gone since (the line says so). A command with
`--config` runs with exactly what it was given; where that differs from the
recorded settings it says so in one line, naming the sections that differ, and its
settings are recorded as the latest. The record keeps the earlier settings too
(the last `HISTORY` that differ), so `ptovs status` can say that a scene was run
with different settings and name both. `ptovs status` (read-only) records nothing.
"""

from __future__ import annotations

import datetime
import hashlib
import json
import logging
import shlex
import sys
from collections.abc import Iterable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from ptovs.config import canonical_json, check_config, load_config, merge, parse_sets
from ptovs.errors import InputError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - python 3.10
    import tomli as tomllib

log = logging.getLogger(__name__)

RECORD = "config.json"  # <work>/<scene>/config.json
RECORD_VERSION = 2
HISTORY = 8
"""Distinct earlier settings a record keeps (the latest is the one used)."""


@dataclass(frozen=True)
class GivenConfig:
    """What a command was given: the --config files (in order, later ones winning
    key by key) and their texts as read, the group's --set items, and the
    command's own --set items as SECTION.KEY=VALUE (`with_command`)."""

    files: tuple[Path, ...] = ()
    texts: tuple[str, ...] = ()
    sets: tuple[str, ...] = ()
    command_sets: tuple[str, ...] = ()
    command: str = ""

    @classmethod
    def read(
        cls, files: Iterable[Path] | Path | None, sets: Iterable[str]
    ) -> GivenConfig:
        """The group's options, each file read once (`ptovs.config.load_config`
        says what is wrong with one)."""
        if files is None:
            files = ()
        elif isinstance(files, str | Path):
            files = (files,)
        paths = tuple(Path(f) for f in files)
        for path in paths:
            load_config(path)  # a missing or malformed file: one line
        texts = tuple(p.read_bytes().decode() for p in paths)
        return cls(paths, texts, tuple(sets))

    @property
    def file(self) -> Path | None:
        """The last --config file (None: none given)."""
        return self.files[-1] if self.files else None

    def with_command(self, name: str, items: Iterable[str]) -> GivenConfig:
        """These options plus a command's own --set items (SECTION.KEY=VALUE)."""
        return replace(self, command=name, command_sets=tuple(items))

    def config(self) -> dict[str, Any]:
        """The group's config: the files' tables in order, then the --set items."""
        base: dict[str, Any] = {}
        for text in self.texts:
            base = merge(base, tomllib.loads(text))
        return merge(base, parse_sets(self.sets))

    def entry(self) -> dict[str, Any]:
        """These settings as a record entry (`_settings` reads one back)."""
        configs = [
            {"file": str(p.resolve()), "given": str(p),
             "sha256": hashlib.sha256(t.encode()).hexdigest(), "toml": t}
            for p, t in zip(self.files, self.texts, strict=True)
        ]  # fmt: skip
        return _entry(configs, [*self.sets, *self.command_sets], self.command)

    def origin(self) -> str:
        """The group's options as typed: `--config A --config B --set X=1`."""
        group = replace(self, command_sets=(), command="")
        return _origin(group.entry(), with_command=False)


def _entry(configs: list[dict], sets: Iterable[str], command: str) -> dict[str, Any]:
    return {
        "configs": configs,
        "sets": _latest_sets(sets),
        "command": command,
        "when": datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
    }


def _latest_sets(items: Iterable[str]) -> list[str]:
    """SECTION.KEY=VALUE items with each key once, the later value winning, in
    the order the keys first came."""
    out: dict[str, str] = {}
    for item in items:
        key = item.partition("=")[0].strip()
        out[key] = item
    return list(out.values())


def _settings(entry: dict[str, Any]) -> dict[str, Any]:
    """The config an entry stands for: its files' tables, then its --set items."""
    base: dict[str, Any] = {}
    for c in entry.get("configs", []):
        base = merge(base, tomllib.loads(c["toml"]))
    return merge(base, parse_sets(entry.get("sets", [])))


def _same(a: dict[str, Any], b: dict[str, Any]) -> bool:
    return canonical_json(_settings(a)) == canonical_json(_settings(b))


def _sections_differing(a: dict[str, Any], b: dict[str, Any]) -> list[str]:
    sa, sb = _settings(a), _settings(b)
    return sorted(
        name for name in set(sa) | set(sb)
        if canonical_json(sa.get(name, {})) != canonical_json(sb.get(name, {}))
    )  # fmt: skip


def record_path(work_dir: Path, scene: str) -> Path:
    return Path(work_dir) / scene / RECORD


def read_record(path: Path) -> list[dict[str, Any]]:
    """The recorded settings, oldest first, the one in use last ([] when there
    is no record); a damaged record is an InputError naming the fix. A record of
    the first layout (one file, no history) reads as one entry."""
    if not path.is_file():
        return []
    try:
        rec = json.loads(path.read_text())
        if not isinstance(rec, dict):
            raise ValueError("not a recorded config")
        if rec.get("version") == 1 and isinstance(rec.get("toml"), str):
            conf = {k: rec.get(k, "") for k in ("file", "given", "sha256", "toml")}
            runs = [{"configs": [conf], "sets": list(rec.get("sets", [])),
                     "command": "", "when": ""}]  # fmt: skip
        else:
            runs = rec.get("runs")
        if not isinstance(runs, list) or not runs:
            raise ValueError("no recorded settings")
        for run in runs:
            if (
                not isinstance(run, dict)
                or not all(
                    isinstance(c, dict) and isinstance(c.get("toml"), str)
                    for c in run.get("configs", [])
                )
                or not all(isinstance(s, str) for s in run.get("sets", []))
            ):
                raise ValueError("a recorded entry is malformed")
            _settings(run)  # the texts and items parse
        return runs
    except (OSError, ValueError, TypeError, InputError, tomllib.TOMLDecodeError) as exc:
        raise InputError(
            f"the config recorded for this scene, {path}, is damaged ({exc}); give "
            "--config FILE (it is then recorded again) or delete it"
        ) from None


def _record_text(runs: list[dict[str, Any]]) -> str:
    return json.dumps({"version": RECORD_VERSION, "runs": runs}, indent=1) + "\n"


def _origin(entry: dict[str, Any], with_command: bool = True) -> str:
    """Where recorded settings came from, as options: `--config A --set X=1`
    (`the defaults` for none), then the command that ran with them."""
    words = []
    for c in entry.get("configs", []):
        words += ["--config", c.get("given") or c.get("file", "")]
    for s in entry.get("sets", []):
        words += ["--set", s]
    text = shlex.join(words) if words else "the defaults"
    if with_command and entry.get("command"):
        text += f" ({entry['command']}"
        text += f", {entry['when']})" if entry.get("when") else ")"
    return text


def _source_state(entry: dict[str, Any]) -> str:
    """'' when every recorded file still holds the recorded text, else what became
    of those that do not."""
    states = []
    for c in entry.get("configs", []):
        file = Path(c.get("file", ""))
        try:
            same = hashlib.sha256(file.read_bytes()).hexdigest() == c.get("sha256")
        except OSError:
            states.append(f"{c.get('given') or file} no longer exists")
            continue
        if not same:
            states.append(f"{c.get('given') or file} has changed since")
    return "; ".join(states)


def history_lines(work_dir: Path, scene: str) -> list[str]:
    """What `ptovs status` says of a scene's record: the settings in use and,
    where earlier commands ran it with other settings, those too."""
    path = record_path(work_dir, scene)
    runs = read_record(path)
    if not runs:
        return []
    lines = [f"settings: {_origin(runs[-1])}"]
    if len(runs) > 1:
        lines.append(
            f"this scene was also run with other settings ({path}); status shows "
            "the latest:"
        )
        lines += [f"  earlier: {_origin(r)}" for r in runs[-2::-1]]
    return lines


def scene_config(
    work_dir: Path,
    scene: str,
    given: GivenConfig,
    config: dict[str, Any],
    overrides: dict[str, Any],
) -> dict[str, Any]:
    """The config a command uses for one scene: adopted from, or recorded into,
    `<work>/<scene>/config.json` (`ptovs.settings.resolve_settings` calls it
    once per scene and command).

    Args:
        given: the group's --config files and --set items, and the command's own
            --set items.
        config: the command's config as given (the files, the group's --set items,
            overrides; the command's own --set items are applied by its chain).
        overrides: the command's own options, kept on top of a recorded config.

    Returns:
        Without --config and with a record: the latest recorded settings, then this
        command's --set items and `overrides`, said in one line. Otherwise
        `config`; with --config, one line if it differs from the record. The
        command's settings become the latest recorded ones when its checks pass
        (never under `ptovs.keys.read_only`).
    """
    from ptovs.keys import READ_ONLY, write_when_checked

    path = record_path(work_dir, scene)
    runs = read_record(path)
    last = runs[-1] if runs else None
    if given.files or last is None:
        entry = given.entry()
        result = config
        if last is not None and not _same(entry, last):
            then = (
                "status shows its keys and records nothing"
                if READ_ONLY.get()
                else f"running with it, and it becomes {scene}'s recorded config"
            )
            log.warning(
                "%s differs from the config recorded for %s (%s, in %s) in [%s]: %s",
                given.origin(), scene, _origin(last, with_command=False), path,
                "], [".join(_sections_differing(entry, last)), then,
            )  # fmt: skip
        elif last is None and not READ_ONLY.get():
            log.info("recording the settings of %s in %s: later commands on %s "
                     "without --config use them", scene, path, scene)  # fmt: skip
    else:
        new = [*given.sets, *given.command_sets]
        entry = _entry(last["configs"], [*last.get("sets", []), *new], given.command)
        recorded = _settings(last)
        result = merge(merge(recorded, parse_sets(given.sets)), overrides)
        check_config(result, f"the config recorded for {scene} ({path})")
        state = _source_state(last)
        how = f"from {_origin(last, with_command=False)}" + (
            f"; {state}: its recorded text is used" if state else ""
        )
        log.warning(
            "using the config recorded for %s: %s (%s); give --config to choose "
            "another", scene, path, how,
        )  # fmt: skip
    if not READ_ONLY.get() and (last is None or not _same(entry, last)
                                or entry["configs"] != last["configs"]):  # fmt: skip
        kept = [r for r in runs if not _same(r, entry)][-(HISTORY - 1) :]
        write_when_checked(path, _record_text([*kept, entry]))
    return result

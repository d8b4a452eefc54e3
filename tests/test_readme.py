"""Every `ptovs` command in the command blocks of the README and docs/guide.md is
one a user can run as written: the command and its options exist, its `--set` items name real
sections and keys with values of the right type, and on the synthetic scenes it
names (`data/bench_s1`, ...) its phrases, views and style candidates exist. The
scenes are planned, not rendered (`plan_scene`: the same world, cameras and
vocabulary `synth-scene` writes), so the check costs seconds. Lines with a
placeholder (`<stage>`, `NAME`) are templates and are skipped; `[...]` marks an
optional part, which is checked too unless it holds a placeholder (`[--image
IMAGE]`). The lines are read as `make check-readme` (tools/check_readme.py) reads them.
"""

from __future__ import annotations

import functools
import re
import shlex
import subprocess
import sys
import warnings
from pathlib import Path

import click
import pytest

from ptovs.cli import main
from ptovs.config import check_config, parse_sets

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
sys.path.insert(0, str(ROOT / "tools"))
from check_readme import BLOCKS, DOCS, as_written, readme_lines  # noqa: E402  (make check-readme's)


def readme_commands() -> list[list[str]]:
    """The argv of each `ptovs` line in the README's ```bash blocks, as
    `make check-readme` runs it (optional parts with a placeholder dropped;
    template lines, `<stage>`, skipped)."""
    return [argv[1:] for line in readme_lines() if (argv := as_written(line))]


COMMANDS = readme_commands()


def readme_make_lines() -> list[list[str]]:
    """The argv of each `make` in the README's ```bash blocks (`a && b`: both);
    lines naming a path the user supplies (/path/to, /cluster) are templates."""
    out = []
    for block in [b for page in DOCS for b in BLOCKS.findall(page.read_text())]:
        for line in block.replace("\\\n", " ").splitlines():
            if "/path/to" in line or "/cluster" in line:
                continue
            for part in line.split("#")[0].split("&&"):
                words = shlex.split(part)
                if words and words[0] == "make":
                    out.append(words[1:])
    return out


@pytest.mark.parametrize("argv", readme_make_lines())
def test_a_readme_make_line_names_a_target_that_exists(argv):
    """`make -n` (print, run nothing) of each README make line succeeds."""
    res = subprocess.run(["make", "-n", "-C", str(README.parent), *argv],
                         capture_output=True, text=True, timeout=120)  # fmt: skip
    assert res.returncode == 0, (argv, res.stderr[-2000:])


def test_the_readme_has_commands_to_check():
    assert len(COMMANDS) >= 25, COMMANDS


def _parse(argv: list[str]) -> tuple[str, click.Command, click.Context]:
    ctx = main.make_context("ptovs", list(argv), resilient_parsing=False)
    with warnings.catch_warnings():  # click 8.2-8.x: the subcommand's name is here
        warnings.simplefilter("ignore", DeprecationWarning)
        head = list(ctx.protected_args)
    name, cmd, rest = main.resolve_command(ctx, head + ctx.args)
    assert cmd is not None, argv
    sub = cmd.make_context(name, rest, parent=ctx)
    return name, cmd, sub


@pytest.mark.parametrize("argv", COMMANDS, ids=[" ".join(c)[:60] for c in COMMANDS])
def test_a_readme_command_parses_and_its_settings_exist(argv):
    name, cmd, sub = _parse(argv)
    ctx = sub.parent
    config = parse_sets(ctx.params.get("sets") or ())
    section = name if name in {s for s in _sections()} else None
    for item in sub.params.get("sets") or ():
        config = _merge(config, parse_sets([item], section))
    check_config(config, "the README's " + " ".join(argv))
    if ctx.params.get("config_file"):
        from ptovs.config import load_config

        check_config(load_config(ctx.params["config_file"]))
    data = sub.params.get("data")
    m = re.fullmatch(r"data/(tiny|demo|small|bench)_s(\d+)", str(data or ""))
    if m:
        _check_synthetic(name, sub.params, m.group(1), int(m.group(2)))


def _sections() -> list[str]:
    from ptovs.registry import REGISTRY, STAGE_MODULES

    return list(dict.fromkeys([*STAGE_MODULES, *REGISTRY]))


def _merge(a: dict, b: dict) -> dict:
    from ptovs.config import merge

    return merge(a, b)


@functools.lru_cache(maxsize=4)
def _plan(preset: str, seed: int):
    from ptovs.synthetic.generate import plan_scene

    return plan_scene(preset, seed)


def _check_synthetic(command: str, params: dict, preset: str, seed: int) -> None:
    """Phrases, views and style candidates against the scene the line names."""
    from ptovs.encoders import synthetic_encoder
    from ptovs.field.query import check_vocabulary
    from ptovs.synthetic.generate import PRESETS, scene_styles, scene_vocabulary

    plan = _plan(preset, seed)
    given = params.get("texts") or params.get("text") or ()
    phrases = [given] if isinstance(given, str) else [p for p in given if p]
    if phrases:
        enc = synthetic_encoder(
            scene_vocabulary(plan.world, PRESETS[preset], [plan.distractor])
        )
        check_vocabulary(enc, list(phrases))
    for view in params.get("view_names") or ():
        assert view in plan.stems, (view, f"{preset}_s{seed}", plan.stems[:5])
    if params.get("candidates"):
        _, styles = scene_styles(PRESETS[preset], seed, plan.world)
        given = [c.strip() for c in params["candidates"].split(",")]
        assert set(given) <= set(styles), (given, sorted(styles))

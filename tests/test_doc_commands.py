"""Every `ptovs` command the docs show (the README's and the guide's command blocks,
and the usage lines in the headers of configs/*.toml) runs, as written, up to the
point where its first stage would start: the options parse, the config files
compose, the scene is read, and the preflight checks pass (checkpoints load, the
encoder and segmenter fit the config, phrases and views exist). Then the stage is
stopped. A command whose inputs are not built yet (export-ply before reconstruct)
may stop earlier with the one line that names what to run.

The folders the docs name stand in as follows: `my_photos` (and any other folder a
user brings, `data/trevi_fountain`) is a posed folder of real-looking photos with
no synthetic ground truth, so a command that only works on the synthetic scenes
fails here; `data/bench_s1` is that synthetic scene with fewer photos (the same
world, vocabulary and labelled views). Each checkpoint a config or a `--set` names
is written where the command looks for it, with random weights of its model.
`make check-readme` runs the synthetic lines to the end.
"""

from __future__ import annotations

import re
import shlex
import shutil
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner

from ptovs.cli import main as cli

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))
from check_readme import as_written, readme_lines  # noqa: E402

HEADER = re.compile(r"^#\s{2,}(ptovs\s.*)$")  # an indented usage line


def header_lines() -> list[str]:
    """The `ptovs` usage lines in the comment headers of configs/*.toml."""
    out = []
    for path in sorted((ROOT / "configs").glob("*.toml")):
        for line in path.read_text().splitlines():
            if not line.startswith("#"):
                break  # the header ends at the first table or blank line
            m = HEADER.match(line)
            if m:
                out.append(shlex.join(shlex.split(m.group(1).split("  or  ")[0])))
    return out


def doc_commands() -> list[list[str]]:
    """The argv (after `ptovs`) of every command the docs show, templates left out
    (`<stage>`), and those that start no stage (synth-scene, view, --help)."""
    out: list[list[str]] = []
    for line in [*readme_lines(), *header_lines()]:
        argv = as_written(line)
        if argv is None:
            continue
        words = [w for w in argv[1:] if not w.startswith("-")]
        if not words or words[0] in ("synth-scene", "view") or "--help" in argv:
            continue
        if argv[1:] not in out:
            out.append(argv[1:])
    return out


COMMANDS = doc_commands()


class StageStarts(Exception):
    """Raised where the first stage would start: the command passed its checks."""


@pytest.fixture(scope="module")
def stage_root(tmp_path_factory, tiny_scene_dir: Path) -> Path:
    """A folder to run the docs' commands in: configs/, the scenes they name and
    the checkpoints the configs and --set items name."""
    root = tmp_path_factory.mktemp("docs")
    (root / "configs").symlink_to(ROOT / "configs")
    dense = tiny_scene_dir / "dense"
    for name in ("my_photos", "data/trevi_fountain", "data/brandenburg_gate"):
        folder = root / name  # posed photos as COLMAP leaves them, no ground truth
        shutil.copytree(dense / "images", folder / "images")
        shutil.copytree(dense / "sparse", folder / "sparse" / "0")
    res = CliRunner().invoke(
        cli,
        ["synth-scene", str(root / "data"), "--preset", "bench", "--seed", "1",
         "--photos", "20", "--name", "bench_s1"],
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    (root / "release" / "brandenburg").mkdir(parents=True)
    _write_checkpoints(root)
    return root


def _named_checkpoints() -> dict[str, str]:
    """{checkpoint path: OpenCLIP model, or "" for a SAM checkpoint} over the
    configs and the docs' --set items."""
    from ptovs.scene_config import tomllib  # tomli on Python 3.10
    from ptovs.stages.extract_features import Config

    found: dict[str, str] = {}
    for path in (ROOT / "configs").glob("*.toml"):
        section = tomllib.loads(path.read_text()).get("extract-features", {})
        if section.get("clip_checkpoint"):
            found[section["clip_checkpoint"]] = section.get(
                "clip_model", Config.clip_model
            )
        if section.get("sam_checkpoint"):
            found[section["sam_checkpoint"]] = ""
    for argv in COMMANDS:
        sets = dict(
            w.split("=", 1)[0].split(".")[-1:] + [w.split("=", 1)[1]]
            for w in argv if "=" in w and not w.startswith("-")
        )  # fmt: skip
        if sets.get("clip_checkpoint"):
            found[sets["clip_checkpoint"]] = sets.get("clip_model", Config.clip_model)
        if sets.get("sam_checkpoint"):
            found[sets["sam_checkpoint"]] = ""
    return found


def _write_checkpoints(root: Path) -> None:
    import torch

    from ptovs.encoders.openclip import build_net

    for rel, model in _named_checkpoints().items():
        path = root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        if not model:  # SAM 1: the file must exist (it is loaded by the stage)
            path.write_bytes(b"\0")
            continue
        torch.manual_seed(0)
        state = {k: v.to(torch.float16) if v.is_floating_point() else v
                 for k, v in build_net(model, None).state_dict().items()}  # fmt: skip
        if path.suffix == ".safetensors":
            from safetensors.torch import save_file

            save_file({k: v.contiguous() for k, v in state.items()}, str(path))
        else:
            torch.save(state, path)


def _cuda() -> bool:
    import torch

    return torch.cuda.is_available()


def test_the_docs_show_commands_on_photos_and_configs():
    joined = [" ".join(a) for a in COMMANDS]
    assert any("my_photos" in a for a in joined) and len(COMMANDS) >= 30, joined
    assert any("configs/auto.toml" in a and "photos-cpu" in a for a in joined), (
        "the scene-fitted recipe is shown with the CPU encoders on photos"
    )


@pytest.mark.parametrize("argv", COMMANDS, ids=[" ".join(a)[:80] for a in COMMANDS])
def test_a_command_the_docs_show_passes_its_checks(argv, stage_root, monkeypatch):
    """The command as written reaches its first stage, or names the stage to run
    first; a config that needs CUDA fails only for want of it."""
    import ptovs.chain
    import ptovs.stage

    def stop(chain, stage, **_):
        raise StageStarts(stage)

    monkeypatch.setattr(ptovs.chain, "execute", stop)
    monkeypatch.setattr(ptovs.stage, "execute", stop)
    monkeypatch.chdir(stage_root)
    work = stage_root / "work" / re.sub(r"\W+", "_", " ".join(argv))[:80]
    args = ["--work-dir", str(work), *argv]
    res = CliRunner().invoke(cli, args)
    out = res.output + repr(res.exception)
    gpu = any(
        "photos-gpu" in w for w in argv
    )  # its encoder runs on CUDA: refused in its checks on a machine without one
    if isinstance(res.exception, StageStarts):
        return
    if gpu and not _cuda():
        assert res.exit_code == 1 and "CUDA" in out, out
        return
    assert "Traceback" not in res.output, out
    if res.exit_code == 0:
        return
    assert re.search(r"no [\w-]+ artifact for \w+ .*; run: ptovs ", res.output), out

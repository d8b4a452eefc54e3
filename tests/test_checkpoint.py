"""In-stage checkpoints: the Checkpoint slot and the framework's resume of single stages."""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np
import torch
from click.testing import CliRunner

from ptovs.artifacts import Store
from ptovs.checkpoint import Checkpoint
from ptovs.registry import scene_input
from ptovs.stage import stage_command


def test_checkpoint_save_load_and_refusals(tmp_path):
    ck = Checkpoint(tmp_path / "x.ckpt", "k1")
    assert ck.load() is None and not ck.exists()
    state = {
        "step": 5,
        "w": torch.arange(4.0),
        "nested": {"a": [1, 2], "t": torch.ones(2)},
    }
    ck.save(state)
    back = ck.load()
    assert back["step"] == 5 and torch.equal(back["w"], state["w"])
    assert back["nested"]["a"] == [1, 2]
    assert ck.step() == 5
    # another key's checkpoint is ignored, not used
    assert Checkpoint(tmp_path / "x.ckpt", "k2").load() is None
    # a damaged file is moved aside and not trusted
    ck.path.write_bytes(b"garbage")
    assert ck.load() is None
    assert (ck.folder / "last.pt.corrupt").exists()
    ck.clear()
    assert not ck.folder.exists()


class Evil:
    """Any class: unpickling it would run arbitrary code paths."""

    def __init__(self):
        self.x = 1


def test_checkpoint_refuses_pickled_objects(tmp_path):
    """weights_only=True: a file needing arbitrary classes is not unpickled."""
    ck = Checkpoint(tmp_path / "y.ckpt", "k")
    ck.folder.mkdir()
    torch.save({"key": "k", "state": {"obj": Evil()}}, ck.path)
    assert ck.load() is None


# A single stage that "trains" for `steps` steps, checkpointing every 2; the
# environment variable TOY_DIE_AT makes it die at that step (as a kill would).


@dataclass(frozen=True)
class _Cfg:
    steps: int = 6


@dataclass(frozen=True)
class _In:
    scene: object = scene_input()


CALLS: list[int] = []


class _Killed(Exception):
    pass


def _run(inputs, config, ckpt=None):
    saved = ckpt.load() if ckpt else None
    step, acc = (saved["step"], saved["acc"]) if saved else (0, torch.zeros(3))
    die_at = int(os.environ.get("TOY_DIE_AT", "-1"))
    while step < config.steps:
        if step == die_at:
            raise _Killed()
        CALLS.append(step)
        acc = acc + step
        step += 1
        if step % 2 == 0:
            ckpt.save({"step": step, "acc": acc})
    return {"acc": acc.numpy()}


_cmd = stage_command(
    "toy-train", 1, _Cfg, _In, _run, kind="single", help="Toy training."
)


def test_single_stage_resumes_from_checkpoint(tmp_path, tiny_scene_dir, monkeypatch):
    from ptovs.artifacts import Artifact
    from ptovs.cli import main

    main.add_command(_cmd)
    runner = CliRunner()
    work = tmp_path / "work"
    args = ["--work-dir", str(work), "toy-train", "--data", str(tiny_scene_dir)]
    status = ["--work-dir", str(work), "status", "--data", str(tiny_scene_dir)]
    CALLS.clear()
    monkeypatch.setenv("TOY_DIE_AT", "5")
    res = runner.invoke(main, args)
    assert isinstance(res.exception, _Killed)
    assert CALLS == [0, 1, 2, 3, 4]
    res = runner.invoke(main, status)
    assert "checkpoint at iteration 4" in res.output
    monkeypatch.delenv("TOY_DIE_AT")
    CALLS.clear()
    res = runner.invoke(main, args)
    assert res.exit_code == 0, res.output
    assert CALLS == [4, 5]  # resumed from the last checkpoint, not from zero
    arts = list(work.rglob("toy-train/*.h5"))
    assert len(arts) == 1
    with Artifact(arts[0]) as art:
        np.testing.assert_array_equal(art.root()["acc"], np.full(3, 15.0, np.float32))
        key = art.key
    assert not Store(work).checkpoint(tiny_scene_dir.name, "toy-train", key).exists()
    # --force discards the checkpoint and recomputes from zero
    CALLS.clear()
    res = runner.invoke(main, [*args, "--force"])
    assert res.exit_code == 0 and CALLS == list(range(6))

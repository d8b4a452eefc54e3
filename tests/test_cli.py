"""The `ptovs` entry points: synth-scene, status, help and error reporting."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner

from ptovs.cli import main as cli


def test_synth_scene_then_status(tmp_path: Path):
    runner = CliRunner()
    r = runner.invoke(
        cli, ["synth-scene", str(tmp_path / "data"), "--preset", "tiny", "--seed", "5"]
    )
    assert r.exit_code == 0, r.output
    scene = tmp_path / "data" / "tiny_s5"
    assert (scene / "dense" / "sparse").is_dir() and (scene / "tiny.tsv").is_file()
    assert list((tmp_path / "data" / "label" / "tiny_s5").glob("*.json"))
    r = runner.invoke(
        cli, ["--work-dir", str(tmp_path / "work"), "status", "--data", str(scene)]
    )
    assert r.exit_code == 0, r.output
    assert "scene tiny_s5" in r.output and "downscale r=1" in r.output
    lines = [ln.split() for ln in r.output.splitlines()]
    scene_line = next(ln for ln in lines if ln and ln[-1] == "input")
    assert scene_line[0] == "scene" and len(scene_line[1]) == 12
    # the scene key is a content key: the same files elsewhere key the same
    shutil.copytree(tmp_path / "data", tmp_path / "elsewhere")
    r2 = runner.invoke(
        cli,
        [
            "--work-dir",
            str(tmp_path / "w2"),
            "status",
            "--data",
            str(tmp_path / "elsewhere" / "tiny_s5"),
        ],
    )
    assert r2.exit_code == 0 and scene_line[1] in r2.output


def test_bad_scene_is_a_message_not_a_traceback(tmp_path: Path):
    empty = tmp_path / "empty"
    empty.mkdir()
    r = CliRunner().invoke(
        cli, ["--work-dir", str(tmp_path / "w"), "status", "--data", str(empty)]
    )
    assert r.exit_code == 1
    assert "Error:" in r.output and str(empty) in r.output
    assert "Traceback" not in r.output
    r = CliRunner().invoke(cli, ["synth-scene", str(tmp_path), "--preset", "huge"])
    assert r.exit_code == 2 and "huge" in r.output


def test_module_entry_point_and_help():
    out = subprocess.run(
        [sys.executable, "-m", "ptovs", "--help"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    assert "synth-scene" in out and "status" in out and "--work-dir" in out
    out = subprocess.run(
        [sys.executable, "-m", "ptovs", "--version"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    assert "ptovs" in out


def test_default_toml_matches_every_stage_default():
    """configs/default.toml documents the defaults; it must not change any key."""
    from ptovs.config import build_config, load_config
    from ptovs.registry import all_stages

    root = Path(__file__).resolve().parents[1]
    cfg = load_config(root / "configs" / "default.toml")
    for spec in all_stages():
        built = build_config(spec.config_cls, cfg.get(spec.name, {}), spec.name)
        assert built == spec.config_cls(), spec.name


def test_every_shipped_config_is_valid():
    """Each file under configs/ passes the whole-config check (sections, keys,
    types) that `--config` runs before any stage."""
    from ptovs.config import check_config, load_config

    files = sorted((Path(__file__).resolve().parents[1] / "configs").glob("*.toml"))
    assert len(files) >= 5, files
    for f in files:
        check_config(load_config(f), str(f))


def test_openmp_threads_sleep_and_threads_option():
    """Idle OpenMP threads spin briefly, then sleep, unless the user chose a policy
    (long spins slowed reconstruct on a shared machine; sleeping at once slowed it
    alone); --threads sets torch's count."""
    code = (
        "import os, sys; import ptovs.cli as c, torch; "
        "print(os.environ.get('GOMP_SPINCOUNT'), os.environ.get('OMP_WAIT_POLICY'));"
        "c.main(['--threads', '1', 'status', '--help'], standalone_mode=False);"
        "print('threads', torch.get_num_threads())"
    )
    # the variables as importing ptovs.cli leaves them (what torch then reads)
    env_only = (
        "import os, ptovs.cli; "
        "print(os.environ.get('GOMP_SPINCOUNT'), os.environ.get('OMP_WAIT_POLICY'))"
    )
    own = ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT", "PTOVS_THREADS")
    env = {k: v for k, v in os.environ.items() if k not in own}

    def lines(env: dict[str, str], code: str = code) -> list[str]:
        run = [sys.executable, "-c", code]
        return subprocess.run(
            run, env=env, capture_output=True, text=True, check=True
        ).stdout.splitlines()

    out = lines(env)
    assert out[0] == "3000 None" and out[-1] == "threads 1"
    # the user's own setting wins, either variable (a fresh process each, without
    # torch: the variables are set, or left, when ptovs.cli is imported)
    assert lines(env | {"OMP_WAIT_POLICY": "ACTIVE"}, env_only) == ["None ACTIVE"]
    assert lines(env | {"GOMP_SPINCOUNT": "10"}, env_only) == ["10 None"]


def test_a_folder_inside_a_scene_names_the_scene_to_give(
    tiny_scene_dir: Path, tmp_path
):
    """--data <scene>/dense, .../dense/images, .../sparse/N or a photo collection's
    images/ would become a scene named "dense" or "images" that lost its split and
    labels: each is refused with the folder to give instead."""
    from ptovs.locate import scene_part

    dense = tiny_scene_dir / "dense"
    model = tmp_path / "colmap" / "sparse" / "0"
    model.mkdir(parents=True)
    (model / "cameras.bin").write_bytes(b"")
    (tmp_path / "colmap" / "images").mkdir()
    for folder, root in ((dense, tiny_scene_dir), (dense / "images", tiny_scene_dir),
                         (dense / "sparse", tiny_scene_dir), (model, tmp_path / "colmap"),
                         (tmp_path / "colmap" / "images", tmp_path / "colmap")):  # fmt: skip
        got = scene_part(folder)
        assert got is not None and got[0] == root.resolve(), folder
    assert (
        scene_part(tiny_scene_dir) is None and scene_part(tmp_path / "colmap") is None
    )
    r = CliRunner().invoke(
        cli, ["--work-dir", str(tmp_path / "w"), "status", "--data", str(dense)]
    )
    assert r.exit_code == 1 and f"pass --data {tiny_scene_dir.resolve()}" in r.output
    assert "Traceback" not in r.output and not (tmp_path / "w" / "dense").exists()


def test_several_models_use_the_one_with_most_images(tmp_path: Path, caplog):
    from ptovs.scene.colmap import find_model

    sparse = tmp_path / "sparse"
    for name, n in (("0", 3), ("1", 40), ("2", 12)):
        d = sparse / name
        d.mkdir(parents=True)
        for f in ("cameras", "points3D"):
            (d / f"{f}.txt").write_text("# empty\n")
        rows = "".join(f"{i} 1 0 0 0 0 0 0 1 im{i}.jpg\n\n" for i in range(n))
        (d / "images.txt").write_text("# header\n" + rows)
    with caplog.at_level("WARNING"):
        assert find_model(sparse) == (sparse / "1", "txt")
    assert "1: 40 images" in caplog.text and "using 1" in caplog.text
    (sparse / "1" / "images.txt").unlink()  # a broken model counts nothing
    (sparse / "1" / "cameras.txt").unlink()
    assert find_model(sparse) == (sparse / "2", "txt")


def test_a_misspelt_command_is_told_the_nearest_even_a_lazy_one():
    for typo, near in (("reconstuct", "reconstruct"), ("qurey", "query"),
                       ("synth-scen", "synth-scene"), ("sttus", "status")):  # fmt: skip
        r = CliRunner().invoke(cli, [typo])
        assert r.exit_code == 2 and f"did you mean {near!r}" in r.output, r.output
    r = CliRunner().invoke(cli, ["zzzzzz"])
    assert r.exit_code == 2 and "No such command" in r.output


def test_global_flags_work_after_the_subcommand(tiny_scene_dir: Path, tmp_path: Path):
    from ptovs.cli import hoist_global_flags

    assert hoist_global_flags(["query", "Wall", "-vv", "--threads", "2", "--", "-q"]) == [
        "-vv", "--threads", "2", "query", "Wall", "--", "-q"]  # fmt: skip
    assert hoist_global_flags(["--config", "c.toml", "status", "--data", "d"]) == [
        "--config", "c.toml", "status", "--data", "d"]  # fmt: skip
    work = str(tmp_path / "w")
    before = CliRunner().invoke(cli, ["--work-dir", work, "-q", "--threads", "1",
                                      "status", "--data", str(tiny_scene_dir)])  # fmt: skip
    after = CliRunner().invoke(cli, ["--work-dir", work, "status", "--data",
                                     str(tiny_scene_dir), "-q", "--threads", "1"])  # fmt: skip
    assert before.exit_code == after.exit_code == 0, after.output
    assert before.output == after.output


def test_a_key_without_its_section_is_told_the_section_and_the_advice_runs(
    tiny_scene_dir, tmp_path
):
    """`ptovs --set threshold=0.9` names `--set query.threshold=0.9` (the old hint
    named scene.), and that advice, applied as written, is accepted."""
    import re

    from click.testing import CliRunner

    from ptovs.cli import main

    runner = CliRunner()
    for bad in ("threshold=0.9", "tau_u=0.85", "treshold=0.9"):
        args = ["--work-dir", str(tmp_path / "w"), "--set", bad, "status",
                "--data", str(tiny_scene_dir)]  # fmt: skip
        res = runner.invoke(main, args)
        assert res.exit_code == 1 and "Traceback" not in res.output, res.output
        fixes = re.findall(r"(?:--set )?((?:query|train-ae|sfm)\.\w+)(?:=(\S+))?",
                           res.output)  # fmt: skip
        assert fixes, res.output
        key, value = fixes[0]
        item = f"{key}={value or bad.split('=')[1]}".rstrip("?,")
        args[args.index(bad)] = item
        res = runner.invoke(main, args)
        assert res.exit_code == 0, (item, res.output)
    assert not (tmp_path / "w").exists()  # status writes nothing


def test_a_number_no_stage_can_use_is_refused_and_the_range_named(tiny_scene_dir,
                                                                  tmp_path):  # fmt: skip
    """Negative counts, NaN, a threshold nothing passes: one line naming the key
    and its range before anything runs (they used to run, or fail late); a value
    at the named range's edge is accepted."""
    from click.testing import CliRunner

    from ptovs.cli import main

    runner = CliRunner()
    cases = {  # the value given, and the nearest one the message allows
        "reconstruct.iterations=-5": "reconstruct.iterations=1",
        "render-appearances.n_appearances=0": "render-appearances.n_appearances=1",
        "query.threshold=1.5": "query.threshold=0.99",
        "train-ae.tau_u=1.2": "train-ae.tau_u=1.0",
        "query.temperature=nan": "query.temperature=0",
        "reconstruct.import_iteration=-2": "reconstruct.import_iteration=-1",
    }
    for bad, good in cases.items():
        args = ["--work-dir", str(tmp_path / "w"), "--set", bad, "status",
                "--data", str(tiny_scene_dir)]  # fmt: skip
        res = runner.invoke(main, args)
        assert res.exit_code == 1 and "Traceback" not in res.output, res.output
        assert f"{bad.split('=')[0]} = " in res.output and "must be" in res.output
        args[args.index(bad)] = good
        assert runner.invoke(main, args).exit_code == 0, good
    res = runner.invoke(main, ["synth-scene", str(tmp_path / "d"), "--seed", "-1"])
    assert res.exit_code == 2 and "Traceback" not in res.output


def test_a_list_whose_quotes_the_shell_ate_is_read_and_its_items_checked():
    """`--set extract-features.levels=[s,m]` (bash drops the quotes of ["s","m"])
    is the list it means; an unknown level is named before anything runs."""
    from ptovs.config import check_config, parse_sets
    from ptovs.errors import InputError

    assert parse_sets(["extract-features.levels=[s, m]"]) == {
        "extract-features": {"levels": ["s", "m"]}
    }
    check_config(parse_sets(['extract-features.levels=["s","m"]']))
    with pytest.raises(InputError, match="'x': must be one of"):
        check_config(parse_sets(["extract-features.levels=[s,x]"]))
    with pytest.raises(InputError, match=r"expected a list, e.g. --set"):
        check_config(parse_sets(["extract-features.levels=s"]))

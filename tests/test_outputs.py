"""Outputs a user names: checked before any work, never sharing a path,
written through a verified temporary file, and every failure a one-line message
with nothing left behind."""

from __future__ import annotations

import errno
import os
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from conftest import RECON, copy_work
from ptovs.cli import main
from ptovs.outputs import OutputError, check_outputs, output_file

# ------------------------------------------------------------- the helpers --


def test_two_outputs_never_share_a_path(tmp_path):
    a = tmp_path / "sel.ply"
    with pytest.raises(OutputError, match="same file"):
        check_outputs({"--out": a, "--rest": tmp_path / "x" / ".." / "sel.ply"})
    with pytest.raises(OutputError, match="same file"):  # select --out X.json
        check_outputs({"--out": tmp_path / "r.json", "record": tmp_path / "r.json"})
    link = tmp_path / "link.ply"
    link.symlink_to(a)
    with pytest.raises(OutputError, match="same file"):
        check_outputs({"--out": a, "--rest": link})
    got = check_outputs({"--out": a, "--rest": None, "other": tmp_path / "b.ply"})
    assert set(got) == {"--out", "other"} and all(p.is_absolute() for p in got.values())


def test_bad_output_paths_are_refused_up_front(tmp_path):
    (tmp_path / "dir").mkdir()
    (tmp_path / "file").write_text("x")
    with pytest.raises(OutputError, match="is a folder.*e.g.*out.ply"):
        check_outputs({"--out": tmp_path / "dir"}, suffix=".ply")
    with pytest.raises(OutputError, match="is a file, not a folder"):
        check_outputs({"--out": tmp_path / "file" / "a.ply"})
    with pytest.raises(OutputError, match="cannot write in /proc"):
        check_outputs({"--out": Path("/proc/nope/a.ply")})
    with pytest.raises(OutputError, match="need about"):
        check_outputs({"--out": tmp_path / "a.mp4"}, need_bytes=2**62)
    check_outputs({"--out": tmp_path / "new" / "deeper" / "a.ply"})  # made on write
    assert not (tmp_path / "new").exists()  # the check itself creates nothing
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dir", "file"]


def test_output_file_renames_only_a_verified_file(tmp_path):
    path = tmp_path / "out.txt"
    path.write_text("old")

    def reject(tmp: Path) -> None:
        raise OutputError("reads back wrong")

    with pytest.raises(OutputError, match="reads back wrong"):
        with output_file(path, reject) as tmp:
            tmp.write_text("new")
    assert path.read_text() == "old"  # the earlier output stays
    with pytest.raises(RuntimeError), output_file(path) as tmp:
        tmp.write_text("half")
        raise RuntimeError("writer died")
    with pytest.raises(OutputError, match="nothing was written"), output_file(path):
        pass
    with output_file(path, lambda t: None) as tmp:
        tmp.write_text("new")
    assert path.read_text() == "new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.txt"]  # no .tmp


def test_a_full_disk_is_a_message_and_leaves_nothing(tmp_path):
    path = tmp_path / "out.bin"
    with pytest.raises(OutputError, match="no space left.*out.bin"):
        with output_file(path) as tmp:
            tmp.write_bytes(b"partial")
            raise OSError(errno.ENOSPC, "No space left on device", str(tmp))
    assert list(tmp_path.iterdir()) == []


def test_a_truncated_video_is_not_moved_into_place(tmp_path, monkeypatch):
    from ptovs.apps.roam import write_video

    frames = [np.full((32, 48, 3), i * 20, np.uint8) for i in range(6)]
    out = tmp_path / "tour.mp4"
    assert write_video(out, iter(frames), 10.0) == 6
    cap = cv2.VideoCapture(str(out))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 6
    cap.release()
    before = out.read_bytes()
    # a full disk as OpenCV meets it: writes fail without a word
    real = cv2.VideoWriter

    class Lossy:
        def __init__(self, *a):
            self.w, self.k = real(*a), 0

        def isOpened(self):  # noqa: N802 (OpenCV's name)
            return self.w.isOpened()

        def write(self, frame):
            self.k += 1
            if self.k <= 2:
                self.w.write(frame)

        def release(self):
            self.w.release()

    monkeypatch.setattr(cv2, "VideoWriter", Lossy)
    with pytest.raises(OutputError, match="2 of 6 frames"):
        write_video(out, iter(frames), 10.0)
    assert out.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["tour.mp4"]


# ------------------------------------------- temporary files (issue: links) --


def _victim(tmp_path: Path) -> Path:
    victim = tmp_path / "outside" / "victim.txt"  # e.g. /etc/something, for root
    victim.parent.mkdir()
    victim.write_text("precious")
    return victim


def test_a_link_planted_at_the_old_temporary_name_is_not_followed(tmp_path):
    from ptovs.artifacts import write_atomic

    victim = _victim(tmp_path)
    shared = tmp_path / "shared"
    shared.mkdir()
    out, small = shared / "out.ply", shared / "record.json"
    pid = os.getpid()
    for name in (f".out.{pid}.tmp.ply", f"record.json.{pid}.tmp"):  # <= 2026-12
        (shared / name).symlink_to(victim)
    with output_file(out) as tmp:
        tmp.write_bytes(b"ply data")
    write_atomic(small, '{"a": 1}')
    assert victim.read_text() == "precious"
    assert out.read_bytes() == b"ply data" and small.read_text() == '{"a": 1}'
    assert not out.is_symlink() and not small.is_symlink()
    assert sorted(p.name for p in shared.iterdir()) == sorted(
        [f".out.{pid}.tmp.ply", f"record.json.{pid}.tmp", "out.ply", "record.json"]
    )  # the planted links are left alone, nothing else is left over


def test_links_planted_at_every_name_tried_are_skipped(tmp_path, monkeypatch):
    """Even a name the attacker guessed is created exclusively (O_EXCL): a link
    there is never opened; the writer takes the next random name."""
    from ptovs import atomic
    from ptovs.artifacts import write_atomic

    victim = _victim(tmp_path)
    shared = tmp_path / "shared"
    shared.mkdir()
    guessed = ["0" * 12, "1" * 12]
    for token in guessed:  # every name the writers will try first, both patterns
        for name in (f".out.{token}.tmp.ply", f".record.json.{token}.tmp"):
            (shared / name).symlink_to(victim)
    tokens = iter([*guessed, "a" * 12, *guessed, "b" * 12])
    monkeypatch.setattr(atomic, "_token", lambda: next(tokens))
    with output_file(shared / "out.ply") as tmp:
        assert tmp.name == f".out.{'a' * 12}.tmp.ply"  # suffix kept (for OpenCV)
        tmp.write_bytes(b"ply data")
    write_atomic(shared / "record.json", "{}")
    assert victim.read_text() == "precious"
    assert (shared / "out.ply").read_bytes() == b"ply data"
    assert (shared / "record.json").read_text() == "{}"
    monkeypatch.setattr(atomic, "_token", lambda: guessed[0])  # all taken: an error
    with pytest.raises(OutputError, match="out.ply"), output_file(shared / "out.ply"):
        pass
    assert victim.read_text() == "precious"
    links = [p for p in shared.iterdir() if p.is_symlink()]
    assert len(links) == 4 and all(p.resolve() == victim for p in links)


def test_a_link_at_the_final_path_is_replaced_not_written_through(tmp_path):
    from ptovs.artifacts import write_atomic

    victim = _victim(tmp_path)
    for i, write in enumerate((
        lambda p: write_atomic(p, "new"),
        lambda p: _write_through_output_file(p, b"new"),
    )):  # fmt: skip
        out = tmp_path / f"out{i}.txt"
        out.symlink_to(victim)
        write(out)
        assert not out.is_symlink() and out.read_text() == "new"
        assert victim.read_text() == "precious"


def _write_through_output_file(path: Path, data: bytes) -> None:
    with output_file(path) as tmp:
        tmp.write_bytes(data)


def test_writers_in_threads_never_collide(tmp_path):
    from concurrent.futures import ThreadPoolExecutor

    from ptovs.artifacts import write_atomic

    def write(i: int) -> None:
        body = f"{i}\n" * 5000
        _write_through_output_file(tmp_path / "same.txt", body.encode())
        _write_through_output_file(tmp_path / f"own{i % 4}.txt", body.encode())
        write_atomic(tmp_path / "same.json", body)

    with ThreadPoolExecutor(8) as pool:
        list(pool.map(write, range(64)))  # re-raises any writer's error
    for name in ("same.txt", "same.json", "own0.txt", "own3.txt"):
        lines = (tmp_path / name).read_text().splitlines()
        assert len(lines) == 5000 and len(set(lines)) == 1  # one whole write
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        ["same.txt", "same.json", "own0.txt", "own1.txt", "own2.txt", "own3.txt"]
    )  # no temporary file left


def test_an_interrupted_write_leaves_no_temporary_file(tmp_path):
    from ptovs.artifacts import write_atomic
    from ptovs.atomic import atomic_dir

    with pytest.raises(KeyboardInterrupt), output_file(tmp_path / "a.ply") as tmp:
        tmp.write_bytes(b"half")
        raise KeyboardInterrupt  # Ctrl-C mid-write
    (tmp_path / "dir").mkdir()  # os.replace cannot put a file over a folder
    with pytest.raises(OSError):
        write_atomic(tmp_path / "dir", "x")
    with pytest.raises(RuntimeError), atomic_dir(tmp_path / "scene") as folder:
        (folder / "images").mkdir()
        raise RuntimeError("undistortion failed")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dir"]
    with atomic_dir(tmp_path / "dir") as folder:  # replaces the old folder whole
        (folder / "sparse").mkdir()
    assert [p.name for p in (tmp_path / "dir").iterdir()] == ["sparse"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dir"]


@pytest.mark.parametrize("umask", [0o022, 0o077, 0o002])
def test_outputs_get_the_usual_mode(tmp_path, umask):
    """Temporary files are created 0666 less the umask (not mkstemp's 0600), so a
    finished output is as readable as any file the user makes."""
    from ptovs.artifacts import write_atomic
    from ptovs.atomic import atomic_dir

    old = os.umask(umask)
    try:
        _write_through_output_file(tmp_path / "a.ply", b"x")
        write_atomic(tmp_path / "b.json", "{}")
        with atomic_dir(tmp_path / "c") as folder:
            (folder / "f").write_text("x")
    finally:
        os.umask(old)
    assert (tmp_path / "a.ply").stat().st_mode & 0o777 == 0o666 & ~umask
    assert (tmp_path / "b.json").stat().st_mode & 0o777 == 0o666 & ~umask
    assert (tmp_path / "c").stat().st_mode & 0o777 == 0o777 & ~umask


# --------------------------------------------------------------- the sweep --


@pytest.fixture(scope="module")
def sweep_work(tmp_path_factory, trained_work):
    return copy_work(trained_work[0], tmp_path_factory.mktemp("outputs") / "work")


def _commands(data: Path, out: Path) -> dict[str, list[str]]:
    """Every command that writes where the user says, with `out` as that place."""
    d = ["--data", str(data)]
    return {
        "select": ["select", "Brick Facade", *d, "--out", str(out)],
        "select --rest": [
            "select",
            "Brick Facade",
            *d,
            "--out",
            str(out.parent / "s.ply"),
            "--rest",
            str(out),
        ],  # fmt: skip
        "roam": [
            "roam",
            "Brick Facade",
            *d,
            "--out",
            str(out),
            "--frames",
            "2",
            "--size",
            "32x24",
        ],  # fmt: skip
        "export-ply": ["export-ply", *d, "--out", str(out)],
        "export-features": ["export-features", *d, "--out", str(out)],
        "query": ["query", *d, "--out", str(out)],
        "evaluate": ["evaluate", *d, "--out", str(out)],
        "style": ["style", *d, "--images", "2", "--out", str(out)],
        "table": ["table", "--data", str(data.parent), "--out", str(out)],
    }


FOLDER_OUTPUTS = {"export-features", "query", "evaluate", "style"}


def _assert_message(res, what: str) -> str:
    assert res.exit_code not in (0, None), what + res.output
    assert isinstance(res.exception, SystemExit), (what, res.exception)  # no traceback
    assert "Traceback" not in res.output, what + res.output
    errors = [ln for ln in res.output.splitlines() if ln.startswith("Error:")]
    assert len(errors) == 1, what + res.output
    return errors[0]


def test_every_command_refuses_a_bad_output_with_one_line(
    sweep_work, tiny_scene_dir, tmp_path
):
    base = tmp_path / "outs"
    base.mkdir()
    (base / "a_file").write_text("x")
    (base / "a_folder").mkdir()
    cases = {
        "output under a file": base / "a_file" / "o.ply",
        "output in /proc": Path("/proc/nope/o.ply"),
    }
    runner = CliRunner()
    for case, out in cases.items():
        for name, args in _commands(tiny_scene_dir, out).items():
            res = runner.invoke(main, ["--work-dir", str(sweep_work), *RECON, *args])
            line = _assert_message(res, f"{name} / {case}: ")
            assert str(out.parent) in line or str(out) in line, (name, line)
    for name, args in _commands(tiny_scene_dir, base / "a_folder").items():
        if name in FOLDER_OUTPUTS:
            continue  # a folder is what these take
        res = runner.invoke(main, ["--work-dir", str(sweep_work), *RECON, *args])
        assert "is a folder" in _assert_message(res, f"{name} / folder: ")
    for name, args in _commands(tiny_scene_dir, base / "a_file").items():
        if name not in FOLDER_OUTPUTS:
            continue
        res = runner.invoke(main, ["--work-dir", str(sweep_work), *RECON, *args])
        assert "is a file" in _assert_message(res, f"{name} / file: ")
    assert sorted(p.name for p in base.iterdir()) == ["a_file", "a_folder"]
    assert list((base / "a_folder").iterdir()) == []


def _advice(line: str) -> Path:
    """The path an error's "e.g. PATH" advice names."""
    assert "e.g. " in line, line
    return Path(line.rsplit("e.g. ", 1)[1].strip().rstrip(".)"))


def test_out_is_a_file_or_a_folder_by_one_rule_and_the_advice_works(
    sweep_work, tiny_scene_dir, tmp_path
):
    """`ptovs --help`'s rule: --out is the file of a one-file command, the folder
    of the others. The wrong kind is refused with an example, and the example,
    applied as given, runs."""
    runner = CliRunner()
    base = tmp_path / "outs"
    (base / "a_folder").mkdir(parents=True)
    for name, args in _commands(tiny_scene_dir, base / "masks.png").items():
        if name not in FOLDER_OUTPUTS:
            continue
        res = runner.invoke(main, ["--work-dir", str(sweep_work), *RECON, *args])
        line = _assert_message(res, f"{name} / file name: ")
        assert "names a file" in line and "give a folder" in line, line
        assert not (base / "masks.png").exists()
        fixed = _advice(line)
        assert fixed == base / "masks"
        args = _commands(tiny_scene_dir, fixed)[name]
        res = runner.invoke(main, ["--work-dir", str(sweep_work), *RECON, *args])
        assert res.exit_code == 0, (name, res.output)
        assert fixed.is_dir() and any(fixed.iterdir()), name
    for name, args in _commands(tiny_scene_dir, base / "a_folder").items():
        if name in FOLDER_OUTPUTS or name == "select --rest":
            continue
        res = runner.invoke(main, ["--work-dir", str(sweep_work), *RECON, *args])
        line = _assert_message(res, f"{name} / folder: ")
        fixed = _advice(line)
        assert fixed.parent == base / "a_folder", line
        args = _commands(tiny_scene_dir, fixed)[name]
        res = runner.invoke(main, ["--work-dir", str(sweep_work), *RECON, *args])
        assert res.exit_code == 0, (name, res.output)
        assert fixed.is_file(), name
    help_text = runner.invoke(main, ["--help"]).output
    assert "--out, in every command" in help_text


def test_roam_refuses_a_gif_first_and_its_example_runs(sweep_work, tiny_scene_dir,
                                                         tmp_path):  # fmt: skip
    """A .gif is named as the wrong kind of file (it once was blamed on the disk),
    before any work, and the example given runs."""
    runner = CliRunner()
    args = _commands(tiny_scene_dir, tmp_path / "tour.gif")["roam"]
    res = runner.invoke(main, ["--work-dir", str(sweep_work), *RECON, *args])
    line = _assert_message(res, "roam / gif: ")
    assert ".mp4 or .avi" in line and "disk" not in line, line
    assert not list(tmp_path.iterdir())
    fixed = _advice(line)
    args = _commands(tiny_scene_dir, fixed)["roam"]
    res = runner.invoke(main, ["--work-dir", str(sweep_work), *RECON, *args])
    assert res.exit_code == 0 and fixed.is_file(), res.output


def test_a_ply_output_named_as_another_file_is_refused_and_its_example_runs(
    sweep_work, tiny_scene_dir, tmp_path
):
    runner = CliRunner()
    for name in ("export-ply", "select"):
        args = _commands(tiny_scene_dir, tmp_path / "sel.txt")[name]
        res = runner.invoke(main, ["--work-dir", str(sweep_work), *RECON, *args])
        line = _assert_message(res, f"{name} / txt: ")
        assert ".ply file" in line, line
        fixed = _advice(line)
        assert fixed == tmp_path / "sel.ply"
        args = _commands(tiny_scene_dir, fixed)[name]
        res = runner.invoke(main, ["--work-dir", str(sweep_work), *RECON, *args])
        assert res.exit_code == 0 and fixed.is_file(), res.output
        fixed.unlink()


def test_style_lists_the_scenes_styles_for_an_unknown_one(sweep_work, tiny_scene_dir):
    """An unknown style on a synthetic scene is answered with its styles, and the
    candidates given back run."""
    import shlex

    runner = CliRunner()
    base = ["--work-dir", str(sweep_work), *RECON, "style", "--data",
            str(tiny_scene_dir), "--images", "2"]  # fmt: skip
    res = runner.invoke(main, [*base, "--candidates", "Gothic,Baroque"])
    line = _assert_message(res, "style / unknown: ")
    assert "styles" in line and "Brick" not in line, line
    given = shlex.split(line.split("--candidates ", 1)[1].split(" (", 1)[0])
    res = runner.invoke(main, [*base, "--candidates", *given])
    assert res.exit_code == 0, res.output


def test_view_takes_its_folder_as_out(tiny_scene_dir, tmp_path):
    res = CliRunner().invoke(
        main,
        ["--work-dir", str(tmp_path / "w"), "view", "--data", str(tiny_scene_dir),
         "--port", "1", "--out", str(tmp_path / "sel.ply")],
    )  # fmt: skip
    assert res.exit_code != 0
    assert "Traceback" not in res.output


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes read-only folders")
def test_a_read_only_folder_is_refused(sweep_work, tiny_scene_dir, tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        for name, args in _commands(tiny_scene_dir, ro / "o.ply").items():
            res = CliRunner().invoke(
                main, ["--work-dir", str(sweep_work), *RECON, *args]
            )
            _assert_message(res, f"{name} / read-only: ")
    finally:
        ro.chmod(0o755)


def test_a_full_disk_while_writing_is_a_message(
    sweep_work, tiny_scene_dir, tmp_path, monkeypatch
):
    from plyfile import PlyData

    def full(self, stream, *a, **k):
        raise OSError(errno.ENOSPC, "No space left on device", str(stream))

    monkeypatch.setattr(PlyData, "write", full)
    out = tmp_path / "sel.ply"
    for args in (
        ["select", "Brick Facade", "--out", str(out)],
        ["export-ply", "--out", str(out)],
    ):
        res = CliRunner().invoke(main, ["--work-dir", str(sweep_work), *RECON, *args,
                                        "--data", str(tiny_scene_dir)])  # fmt: skip
        assert "no space left" in _assert_message(res, f"{args[0]}: ")
    assert list(tmp_path.iterdir()) == []


def test_select_and_roam_name_an_unknown_image(sweep_work, tiny_scene_dir, tmp_path):
    for args in (
        ["select", "Brick Facade", "--out", str(tmp_path / "s.ply")],
        ["roam", "Brick Facade", "--out", str(tmp_path / "t.mp4"), "--frames", "2",
         "--size", "32x24"],
    ):  # fmt: skip
        res = CliRunner().invoke(main, ["--work-dir", str(sweep_work), *RECON, *args,
                                        "--data", str(tiny_scene_dir), "--image", "nope.jpg"])  # fmt: skip
        line = _assert_message(res, f"{args[0]}: ")
        assert "'nope.jpg'" in line and "--image" in line
    assert list(tmp_path.iterdir()) == []


def test_roam_sizes_are_bounded_before_any_work(tmp_path):
    for size, words in (
        ("100000x100000", "at most 8192"),
        ("8000x8000", "GB to render"),
    ):
        res = CliRunner().invoke(main, ["--work-dir", str(tmp_path / "w"), "roam", "x",
                                        "--data", str(tmp_path / "none"), "--out",
                                        str(tmp_path / "t.mp4"), "--size", size,
                                        "--highlight", "query"])  # fmt: skip
        assert res.exit_code == 2 and words in res.output and "--size" in res.output
    assert not (tmp_path / "w").exists()


def test_vv_shows_the_traceback_of_a_mapped_error(tmp_path):
    args = [
        "export-ply",
        "--data",
        str(tmp_path / "none"),
        "--out",
        str(tmp_path / "d"),
    ]
    (tmp_path / "d").mkdir()
    quiet = CliRunner().invoke(main, args)
    loud = CliRunner().invoke(main, ["-vv", *args])
    assert quiet.exit_code == loud.exit_code == 1
    assert "Traceback" not in quiet.output and "Traceback" in loud.output


# ------------------------------------------------------------- scene names --


def test_scene_given_a_path_is_resolved_or_refused(tiny_scene_dir, tmp_path):
    work = tmp_path / "work"
    res = CliRunner().invoke(main, ["--work-dir", str(work), "status", "--scene",
                                    str(tiny_scene_dir)])  # fmt: skip
    assert res.exit_code == 0, res.output
    assert "tiny_s0" in res.output
    assert not any(p.suffix == ".h5" for p in tiny_scene_dir.rglob("*"))
    res = CliRunner().invoke(main, ["--work-dir", str(work), "status", "--scene",
                                    "data/nope", "--data", str(tiny_scene_dir)])  # fmt: skip
    line = _assert_message(res, "scene path: ")
    assert "--scene takes a name" in line and "--data data/nope" in line
    for bad in ("..", "a/b", "/abs/nope"):  # with --data, or no such folder
        res = CliRunner().invoke(
            main, ["--work-dir", str(work), "status", "--scene", bad,
                   "--data", str(tiny_scene_dir)] if bad == ".." else
            ["--work-dir", str(work), "status", "--scene", bad]
        )  # fmt: skip
        assert "--scene takes a name" in _assert_message(res, bad)

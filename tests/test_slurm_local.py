"""workflow/slurm-local: which DIR start.sh and stop.sh refuse (before they write,
remove, start or kill anything), and one real start that must listen on loopback
only, with munged's checks on and the database password in no command line.

Like the Slurm test in test_workflow.py these fail, never skip, when not root or the
packages are missing; all are marked `slurm` (they need both)."""

from __future__ import annotations

import os
import pwd
import shutil
import signal
import socket
import stat
import subprocess
import tempfile
import time
from pathlib import Path

import pytest

from conftest import need_slurm_host

ROOT = Path(__file__).resolve().parents[1]
SLURM_LOCAL = ROOT / "workflow" / "slurm-local"
MARKER = ".ptovs-slurm-local"
NEEDS = ("munged", "mungekey", "mariadbd", "mariadb-install-db", "mariadb", "slurmdbd",
         "slurmctld", "slurmd", "sacctmgr", "sbatch", "sacct")  # fmt: skip
DAEMONS = ("munged", "mariadbd", "slurmdbd", "slurmctld", "slurmd")

pytestmark = pytest.mark.slurm


@pytest.fixture(scope="module", autouse=True)
def root_and_packages():
    need_slurm_host(NEEDS)


@pytest.fixture
def base():
    """A folder start.sh accepts as DIR's parent: under /tmp, root's, 0755 (pytest's
    tmp_path is under a 0700 folder, which munged, and so start.sh, refuses)."""
    folder = Path(tempfile.mkdtemp(prefix="ptovs-sl-", dir="/tmp"))
    folder.chmod(0o755)
    yield folder
    shutil.rmtree(folder, ignore_errors=True)


def script(name: str, folder: Path | str, env=None) -> subprocess.CompletedProcess:
    return subprocess.run(["bash", str(SLURM_LOCAL / name), str(folder)], env=env,
                          capture_output=True, text=True, timeout=300)  # fmt: skip


def check_dir(folder: Path | str, *how: str) -> subprocess.CompletedProcess:
    """stop.sh's check_dir alone (start.sh sources it): prints DIR_STATE."""
    cmd = 'source "$1"; check_dir "$2" ${3:-}; echo "$DIR_STATE"'
    return subprocess.run(["bash", "-c", cmd, "_", str(SLURM_LOCAL / "stop.sh"),
                           str(folder), *how], capture_output=True, text=True)  # fmt: skip


def snapshot(top: Path) -> dict:
    """Every path under top (links not followed): type, mode, owner, content."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(top):
        for name in ["", *dirnames, *filenames]:
            p = Path(dirpath, name)
            st = p.lstat()
            data = p.read_bytes() if stat.S_ISREG(st.st_mode) else None
            out[str(p)] = (st.st_mode, st.st_uid, data)
    return out


def ours_with_data(folder: Path) -> Path:
    """A DIR that start.sh made before (marker) holding data of an earlier run: on its
    own it is accepted (and its mysql/ is wiped on start); each case spoils one thing."""
    folder.mkdir(mode=0o700)
    (folder / MARKER).write_text("made by workflow/slurm-local/start.sh\n")
    (folder / "mysql").mkdir()
    (folder / "mysql" / "keep").write_text("not yours to delete")
    return folder


def assert_refused(proc: subprocess.CompletedProcess, why: str, before: dict,
                   top: Path) -> None:  # fmt: skip
    assert proc.returncode == 2, (proc.returncode, proc.stdout, proc.stderr)
    assert "refusing DIR" in proc.stderr and why in proc.stderr, proc.stderr
    assert snapshot(top) == before  # nothing written, removed or chmod-ed


def test_accepts_new_empty_and_marked_dirs(base):
    assert check_dir(base / "new", "start").stdout == "absent\n"
    (base / "empty").mkdir(mode=0o700)
    assert check_dir(base / "empty", "start").stdout == "empty\n"
    ours = ours_with_data(base / "ours")
    assert check_dir(ours, "start").stdout == "ours\n"
    assert check_dir(f"{ours}//", "start").stdout == "ours\n"
    os.chmod(ours, 0o755)  # readable by others is fine, writable is not
    assert check_dir(ours, "start").stdout == "ours\n"


def test_refuses_non_empty_dir_without_marker(base):
    folder = ours_with_data(base / "d")
    (folder / MARKER).unlink()
    before = snapshot(base)
    assert_refused(script("start.sh", folder), "not empty and has no", before, base)
    assert_refused(script("stop.sh", folder), "not empty and has no", before, base)
    assert (folder / "mysql" / "keep").read_text() == "not yours to delete"


def test_refuses_dir_owned_by_someone_else(base):
    folder = ours_with_data(base / "d")
    nobody = pwd.getpwnam("nobody")
    for p in (folder, folder / MARKER, folder / "mysql", folder / "mysql" / "keep"):
        os.chown(p, nobody.pw_uid, nobody.pw_gid)
    before = snapshot(base)
    assert_refused(script("start.sh", folder), "it is owned by uid", before, base)
    assert_refused(script("stop.sh", folder), "it is owned by uid", before, base)
    assert (folder / "mysql" / "keep").exists()
    # an empty one too: root would write and run wrappers in a folder nobody controls
    empty = base / "e"
    empty.mkdir(mode=0o700)
    os.chown(empty, nobody.pw_uid, nobody.pw_gid)
    before = snapshot(base)
    assert_refused(script("start.sh", empty), "it is owned by uid", before, base)


@pytest.mark.parametrize("mode", [0o777, 0o775, 0o1777, 0o720])
def test_refuses_dir_writable_by_others(base, mode):
    folder = ours_with_data(base / "d")
    os.chmod(folder, mode)
    before = snapshot(base)
    assert_refused(script("start.sh", folder), "writable by group or others", before,
                   base)  # fmt: skip
    assert_refused(script("stop.sh", folder), "writable by group or others", before,
                   base)  # fmt: skip


def test_refuses_symlink(base):
    target = ours_with_data(base / "real")
    link = base / "link"
    link.symlink_to(target)
    dangling = base / "dangling"
    dangling.symlink_to(base / "nothing-here")
    before = snapshot(base)
    for folder in (link, f"{link}/", dangling):
        assert_refused(script("start.sh", folder), "symbolic link", before, base)
        assert_refused(script("stop.sh", folder), "symbolic link", before, base)
    assert not (base / "nothing-here").exists()


def test_refuses_unsafe_parent(base):
    parent = base / "p"
    parent.mkdir()
    folder = ours_with_data(parent / "d")
    # world-writable without the sticky bit: anyone could swap DIR for their own
    os.chmod(parent, 0o777)
    before = snapshot(base)
    why = "writable by group or others without the sticky bit"
    assert_refused(script("start.sh", folder), why, before, base)
    assert_refused(script("start.sh", parent / "new"), why, before, base)
    assert_refused(script("stop.sh", folder), why, before, base)
    # sticky (like /tmp) and root's: fine
    os.chmod(parent, 0o1777)
    assert check_dir(folder, "start").stdout == "ours\n"
    # not writable, but owned by someone else (who could chmod it and rename DIR)
    os.chmod(parent, 0o755)
    os.chown(parent, pwd.getpwnam("nobody").pw_uid, -1)
    before = snapshot(base)
    why = "a directory above it, is owned by uid"
    assert_refused(script("start.sh", folder), why, before, base)
    assert_refused(script("stop.sh", folder), why, before, base)
    # not searchable by all: munged would refuse its socket, so start.sh does first
    os.chown(parent, 0, 0)
    os.chmod(parent, 0o700)
    before = snapshot(base)
    assert_refused(script("start.sh", folder), "not searchable by all", before, base)


def test_refuses_odd_paths(base):
    before = snapshot(base)
    for folder, why in [(base / "a b", "characters other than"),
                        (base / "no" / "such", "does not exist"),
                        (base / ("x" * 80), "longer than 80")]:  # fmt: skip
        assert_refused(script("start.sh", folder), why, before, base)
    assert_refused(script("start.sh", "/"), "it is /", before, base)


def test_refuses_to_start_off_loopback(base, tmp_path):
    """Slurm binds to the address the host name resolves to (NoInAddrAny): start.sh
    asks python3 for it; here a stand-in python3 answers with a network address."""
    (tmp_path / "python3").write_text("#!/bin/sh\necho 10.1.2.3\n")
    (tmp_path / "python3").chmod(0o755)
    env = {**os.environ, "PATH": f"{tmp_path}:{os.environ['PATH']}"}
    before = snapshot(base)
    proc = script("start.sh", base / "d", env=env)
    assert proc.returncode == 1, proc.stderr
    assert "resolves to '10.1.2.3', not to a loopback address" in proc.stderr
    assert snapshot(base) == before


def test_stop_kills_nothing_from_a_foreign_dir(base):
    """Pid files in a DIR that someone else controls could name any process."""
    folder = ours_with_data(base / "d")
    (folder / "run").mkdir()
    victim = subprocess.Popen(
        ["sleep", "60"], env={"SLURM_CONF": f"{folder}/slurm.conf"}
    )
    try:
        (folder / "run" / "slurmd.pid").write_text(f"{victim.pid}\n")
        os.chown(folder, pwd.getpwnam("nobody").pw_uid, -1)
        assert script("stop.sh", folder).returncode == 2
        time.sleep(0.2)
        assert victim.poll() is None
        os.chown(folder, 0, -1)  # the same folder, ours again: now it is stopped
        assert script("stop.sh", folder).returncode == 0
        assert victim.wait(timeout=15) == -signal.SIGTERM
    finally:
        victim.kill()
        victim.wait()


# --------------------------------------------------- one real start and stop --


def alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return False


def tcp_listeners(pid: int) -> list[tuple[str, int]]:
    """(address, port) of every TCP socket PID listens on, from /proc (no ss needed);
    IPv6 ones are returned with the address as /proc has it."""
    inodes = set()
    for fd in os.listdir(f"/proc/{pid}/fd"):
        try:
            link = os.readlink(f"/proc/{pid}/fd/{fd}")
        except OSError:
            continue
        if link.startswith("socket:["):
            inodes.add(link[8:-1])
    out = []
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        for line in Path(table).read_text().splitlines()[1:]:
            f = line.split()
            if f[3] != "0A" or f[9] not in inodes:  # 0A: LISTEN
                continue
            addr, port = f[1].split(":")
            if len(addr) == 8:  # IPv4, little-endian hex
                addr = socket.inet_ntoa(bytes.fromhex(addr)[::-1])
            out.append((addr, int(port, 16)))
    return out


def test_start_listens_on_loopback_only(tmp_path):
    """A fresh DIR: start.sh brings the cluster up with munged's checks on (no
    --force), every daemon listening on a 127.x address only, the database password
    in no process's command line; stop.sh stops them all."""
    folder = Path(tempfile.mkdtemp(prefix="ptovs-slurm-", dir="/tmp"))
    # every `mariadb` start.sh runs goes through this, which notes its arguments
    shim, argv_log = tmp_path / "shim", tmp_path / "mariadb-argv"
    shim.mkdir()
    (shim / "mariadb").write_text(f'#!/bin/sh\nprintf "%s\\n" "$*" >> {argv_log}\n'
                                  f'exec {shutil.which("mariadb")} "$@"\n')  # fmt: skip
    (shim / "mariadb").chmod(0o755)
    env = {**os.environ, "PATH": f"{shim}:{os.environ['PATH']}"}
    pids: dict[str, int] = {}
    try:
        start = script("start.sh", folder, env=env)
        assert start.returncode == 0, start.stderr[-4000:]
        assert stat.S_IMODE(folder.stat().st_mode) == 0o711
        assert (folder / MARKER).is_file()
        pids = {d: int((folder / "run" / f"{d}.pid").read_text()) for d in DAEMONS}
        assert all(alive(p) for p in pids.values()), pids
        cmdline = Path(f"/proc/{pids['munged']}/cmdline").read_bytes().split(b"\0")
        assert b"--force" not in cmdline

        for daemon in ("mariadbd", "slurmdbd", "slurmctld", "slurmd"):
            listening = tcp_listeners(pids[daemon])
            assert listening, daemon
            assert all(a.startswith("127.") for a, _ in listening), (daemon, listening)
        assert tcp_listeners(pids["munged"]) == []  # a unix socket only

        password = next(
            line.split("=", 1)[1]
            for line in (folder / "slurmdbd.conf").read_text().splitlines()
            if line.startswith("StoragePass=")
        )
        assert len(password) >= 16
        assert argv_log.read_text() and password not in argv_log.read_text()
        for proc in Path("/proc").glob("[0-9]*"):
            try:
                assert password.encode() not in (proc / "cmdline").read_bytes(), proc
            except OSError:
                pass
    finally:
        stop = script("stop.sh", folder)
        shutil.rmtree(folder, ignore_errors=True)
    assert stop.returncode == 0, stop.stderr
    assert not [d for d, p in pids.items() if alive(p)]

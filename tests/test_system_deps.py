"""tools/system-deps.sh (`make system-deps`, run first by `make test` and by .ci/run)
and the tests' side of it (tests/conftest.py): without root a contributor's suite
runs, one line saying which packages are missing and the command that installs
them, and the summary naming the tests skipped for them; as root the script
installs them; where they are required (CI=true, PTOVS_REQUIRE_SYSTEM_DEPS=1) a
missing one fails. apt-get is never run: a stub stands in for it."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "tools" / "system-deps.sh"
EVERY = ["g++", "chromium", "slurmctld", "slurmdbd", "munged", "mariadbd"]


def _bin(tmp_path: Path, present: list[str], uid: int, apt: bool = True) -> Path:
    """A PATH with the shell's tools, a fake `id`, a stub apt-get, and stubs of
    `present`."""
    d = tmp_path / "bin"
    d.mkdir()
    for tool in ("bash", "echo"):
        real = shutil.which(tool)
        if real:
            (d / tool).symlink_to(real)
    (d / "id").write_text(f"#!{shutil.which('bash')}\necho {uid}\n")
    if apt:
        (d / "apt-get").write_text(f'#!{shutil.which("bash")}\necho apt-get "$@"\n')
    for name in present:
        (d / name).write_text(f"#!{shutil.which('bash')}\nexit 0\n")
    for f in d.iterdir():
        if not f.is_symlink():
            f.chmod(0o755)
    return d


def _env(**extra: str) -> dict[str, str]:
    """This environment without the variables that require the packages (CI
    sets CI=true) and without an outer make's (the suite runs under `make
    test`, whose MAKELEVEL makes a nested make print "Entering directory"),
    plus `extra`."""
    drop = ("CI", "PTOVS_REQUIRE_SYSTEM_DEPS", "MAKEFLAGS", "MAKELEVEL", "MFLAGS",
            "MAKEOVERRIDES")  # fmt: skip
    env = {k: v for k, v in os.environ.items() if k not in drop}
    return env | extra


def _run(path: Path, **extra: str) -> subprocess.CompletedProcess:
    env = _env(PATH=str(path), **extra)
    return subprocess.run([shutil.which("bash"), str(SCRIPT)], env=env,
                          capture_output=True, text=True, timeout=30)  # fmt: skip


def test_without_root_one_line_names_the_packages_and_the_suite_goes_on(tmp_path):
    r = _run(_bin(tmp_path, ["g++", "munged"], uid=1000))
    assert r.returncode == 0, r.stderr
    assert r.stdout == ""  # nothing installed, apt-get never run
    assert r.stderr.splitlines() == [
        "system packages missing: chromium slurm-wlm slurmdbd mariadb-server; "
        "their tests are skipped; install them: sudo make system-deps"
    ]


@pytest.mark.parametrize("flag", [{"CI": "true"}, {"PTOVS_REQUIRE_SYSTEM_DEPS": "1"}])
def test_without_root_where_required_it_stops(tmp_path: Path, flag: dict):
    r = _run(_bin(tmp_path, ["g++", "munged"], uid=1000), **flag)
    assert r.returncode == 1 and r.stdout == ""
    assert "chromium slurm-wlm slurmdbd mariadb-server" in r.stderr
    assert "sudo make system-deps" in r.stderr and "required here" in r.stderr


def test_without_apt_it_names_the_debian_packages(tmp_path: Path):
    r = _run(_bin(tmp_path, EVERY[:-1], uid=0, apt=False))
    assert r.returncode == 0 and r.stdout == ""
    assert "mariadb-server" in r.stderr and "your package manager" in r.stderr


def test_missing_packages_as_root_are_installed(tmp_path: Path):
    r = _run(_bin(tmp_path, ["g++", "chromium", "slurmctld", "slurmdbd"], uid=0),
             CI="true")  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert "install -y -qq munge mariadb-server" not in r.stdout  # quiet install
    assert "installing munge mariadb-server" in r.stdout


def test_nothing_missing_does_nothing(tmp_path: Path):
    r = _run(_bin(tmp_path, EVERY, uid=1000), CI="true")
    assert r.returncode == 0 and r.stdout == "" and r.stderr == ""


def test_make_test_checks_the_packages_first():
    """`make test`'s first step is the script (its line is the run's first)."""
    out = subprocess.run(["make", "--no-print-directory", "-n", "test", "BIN=/nonexistent"], cwd=ROOT,
                         capture_output=True, text=True, timeout=60,
                         env=_env(PYTHON=sys.executable))  # fmt: skip
    assert out.returncode == 0, out.stderr
    assert out.stdout.splitlines()[0] == "bash tools/system-deps.sh"


SUITE = """
from conftest import need_system

def test_needs_a_package():
    need_system("fakepkg-a fakepkg-b", False)

def test_needs_nothing():
    need_system("g++", True)
"""


def _suite(tmp_path: Path, **extra: str) -> subprocess.CompletedProcess:
    """A two-test suite under a copy of tests/conftest.py, run by pytest."""
    shutil.copy(ROOT / "tests" / "conftest.py", tmp_path / "conftest.py")
    (tmp_path / "test_x.py").write_text(SUITE)
    return subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                           str(tmp_path)], cwd=tmp_path, capture_output=True,
                          text=True, timeout=120, env=_env(**extra))  # fmt: skip


def test_a_missing_package_skips_and_the_summary_says_how_to_install(tmp_path):
    r = _suite(tmp_path)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "1 passed, 1 skipped" in r.stdout
    assert (
        "1 skipped for missing system packages (fakepkg-a fakepkg-b); install "
        "them: sudo make system-deps" in r.stdout
    )


@pytest.mark.parametrize("flag", [{"CI": "true"}, {"PTOVS_REQUIRE_SYSTEM_DEPS": "1"}])
def test_a_missing_package_fails_where_required(tmp_path: Path, flag: dict):
    r = _suite(tmp_path, **flag)
    assert r.returncode == 1
    assert "1 failed, 1 passed" in r.stdout
    assert "[system: fakepkg-a fakepkg-b] not installed" in r.stdout
    assert "skipped for missing system packages" not in r.stdout

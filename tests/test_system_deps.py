"""tools/system-deps.sh (`make system-deps`, run by `make test` and .ci/run): on a
machine without the packages and without root, it stops before the suite with the
one command to run; with everything present it does nothing."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "tools" / "system-deps.sh"


def _bin(tmp_path: Path, present: list[str], uid: int) -> Path:
    """A PATH with the shell's tools, a fake `id`, and stubs of `present`."""
    d = tmp_path / "bin"
    d.mkdir()
    for tool in ("bash", "echo"):
        real = shutil.which(tool)
        if real:
            (d / tool).symlink_to(real)
    (d / "id").write_text(f"#!{shutil.which('bash')}\necho {uid}\n")
    (d / "apt-get").write_text(f'#!{shutil.which("bash")}\necho apt-get "$@"\n')
    for name in present:
        (d / name).write_text(f"#!{shutil.which('bash')}\nexit 0\n")
    for f in d.iterdir():
        if not f.is_symlink():
            f.chmod(0o755)
    return d


def _run(path: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, PATH=str(path))
    return subprocess.run([shutil.which("bash"), str(SCRIPT)], env=env,
                          capture_output=True, text=True, timeout=30)  # fmt: skip


def test_missing_packages_without_root_name_the_command(tmp_path: Path) -> None:
    r = _run(_bin(tmp_path, ["g++", "munged"], uid=1000))
    assert r.returncode == 1
    assert "sudo apt-get install -y chromium slurm-wlm slurmdbd mariadb-server" in (
        r.stderr
    )
    assert "installing" not in r.stdout


def test_missing_packages_as_root_are_installed(tmp_path: Path) -> None:
    r = _run(_bin(tmp_path, ["g++", "chromium", "slurmctld", "slurmdbd"], uid=0))
    assert r.returncode == 0, r.stderr
    assert "install -y -qq munge mariadb-server" not in r.stdout  # quiet install
    assert "installing munge mariadb-server" in r.stdout


def test_nothing_missing_does_nothing(tmp_path: Path) -> None:
    present = ["g++", "chromium", "slurmctld", "slurmdbd", "munged", "mariadbd"]
    r = _run(_bin(tmp_path, present, uid=1000))
    assert r.returncode == 0 and r.stdout == "" and r.stderr == ""

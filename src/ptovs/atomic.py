"""The one place ptovs makes temporary files and folders: beside their final path,
under a name nobody can guess, created exclusively, then renamed into place.

    with atomic_file(path) as tmp:      # an empty new file, hidden, same suffix
        write(tmp)                      # any writer that opens a name
    # here `path` is the complete file; on an error nothing is left behind

A temporary file is created with O_CREAT | O_EXCL under a random name, so a link
or file planted in a shared folder (at the old `<name>.<pid>.tmp`, or anywhere)
is never opened, followed or overwritten: the name is skipped. Its mode is
0666 less the umask (0777 for a folder), as any new file's, so outputs are as
readable as before. `os.replace` puts it in place: a link at the final path is
itself replaced, never written through.

Names: `.<stem>.<random>.tmp<suffix>` (`keep_suffix`, for writers that pick the
format by it, e.g. OpenCV), or `.<name>.<random>.tmp` (the store's shards,
checkpoints and small files: `*.tmp` finds what an interrupted run left).
Standard library only: every room may import it.
"""

from __future__ import annotations

import contextlib
import os
import secrets
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

_TRIES = 100  # names taken already (planted or another writer's) before giving up
_MAX_BASE = 120  # characters of the final name kept in the temporary one


def create_temp(
    path: Path | str, *, keep_suffix: bool = True, folder: bool = False
) -> Path:
    """Create a new, empty temporary file (or, with `folder`, folder) beside `path`.

    Exclusive (O_CREAT | O_EXCL, or mkdir): an existing name, a planted symbolic
    link included, is never opened or followed; another random name is tried.
    Mode 0666 (folders 0777) less the umask. The caller renames or removes it.
    Raises OSError (e.g. FileNotFoundError when the folder is missing).
    """
    path = Path(path)
    if keep_suffix and not folder:
        base, ext = path.stem, path.suffix
    else:
        base, ext = path.name, ""
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC
    for _ in range(_TRIES):
        tmp = path.with_name(f".{base[:_MAX_BASE]}.{_token()}.tmp{ext}")
        try:
            if folder:
                os.mkdir(tmp, 0o777)
            else:
                os.close(os.open(tmp, flags, 0o666))
        except FileExistsError:
            continue
        return tmp
    raise FileExistsError(f"no free temporary name beside {path} after {_TRIES} tries")


def _token() -> str:
    return secrets.token_hex(6)


def fsync_dir(path: Path) -> None:
    """Make a rename in `path` durable (best effort: some file systems refuse)."""
    with contextlib.suppress(OSError):
        fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def fsync_file(path: Path) -> None:
    """Flush a written file's data to disk."""
    fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


@contextmanager
def atomic_file(
    path: Path | str, *, keep_suffix: bool = True, durable: bool = False
) -> Iterator[Path]:
    """Yield a new empty temporary file beside `path` (`create_temp`); when the block
    ends without an error, rename it onto `path`; on any error remove it.

    `durable`: fsync the file before the rename and the folder after it (a crash
    leaves the old file or the complete new one)."""
    path = Path(path)
    tmp = create_temp(path, keep_suffix=keep_suffix)
    try:
        yield tmp
        if durable:
            fsync_file(tmp)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    if durable:
        fsync_dir(path.parent)


@contextmanager
def atomic_dir(path: Path | str) -> Iterator[Path]:
    """Yield a new empty temporary folder beside `path`; when the block ends without
    an error, it replaces `path` (a folder there is removed first, a file or link
    is unlinked, never followed); on any error it is removed."""
    path = Path(path)
    tmp = create_temp(path, folder=True)
    try:
        yield tmp
        if path.is_symlink() or (path.exists() and not path.is_dir()):
            path.unlink()
        else:
            shutil.rmtree(path, ignore_errors=True)
        os.replace(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


__all__ = ["atomic_dir", "atomic_file", "create_temp", "fsync_dir", "fsync_file"]

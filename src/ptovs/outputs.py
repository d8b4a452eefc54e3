"""One path for every file a command writes where the user said (PLY, video, PNG,
JSON, Markdown): checked before any work, written to a temporary sibling
(`ptovs.atomic`: an unguessable name, created exclusively), verified, and only
then renamed into place.

    paths = check_outputs({"--out": out, "--rest": rest, "record": out.with_suffix(".json")},
                          need_bytes=est)          # before the chain runs
    with output_file(out, verify=lambda tmp: ...) as tmp:
        write(tmp)                                  # any writer; tmp keeps the suffix

Failures are `OutputError`s (an `InputError`: the CLI prints the message, exit 1):
they name the path and the fix, and no temporary file is left behind.
"""

from __future__ import annotations

import errno
import os
import shutil
import tempfile
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path

from ptovs.atomic import atomic_file
from ptovs.errors import InputError


class OutputError(InputError):
    """An output path that cannot be written (the message names it and the fix)."""


def _existing_ancestor(path: Path) -> Path:
    p = path.parent
    while not p.exists() and p != p.parent:
        p = p.parent
    return p


def _mb(n: float) -> str:
    return f"{n / 2**20:,.0f} MB"


def check_outputs(
    outputs: Mapping[str, Path | None],
    need_bytes: int = 0,
    suffix: str = "",
) -> dict[str, Path]:
    """Check the outputs of one command before it does any work.

    `outputs` maps what names each path for the user (an option such as "--out",
    or a description such as "the record beside --out") to the path (None: not
    asked for). Raises OutputError when two outputs share a path, when a path is
    a folder, when its folder cannot be made or written, or when the disk holding
    the disk of the first output has less than `need_bytes` free (`suffix`: the file type, for the example
    name a message gives). Returns the given paths, absolute.
    """
    given = {k: Path(v) for k, v in outputs.items() if v is not None}
    seen: dict[Path, str] = {}
    for what, path in given.items():
        real = Path(os.path.realpath(path))
        if real in seen:
            raise OutputError(
                f"{seen[real]} and {what} are the same file ({path}); one would "
                f"overwrite the other. Give {what} another name"
            )
        seen[real] = what
    for what, path in given.items():
        if path.is_dir():
            example = f", e.g. {path / ('out' + suffix)}" if suffix else ""
            raise OutputError(
                f"{what} {path} is a folder; give a file name inside it{example}"
            )
        anc = _existing_ancestor(path)
        if not anc.is_dir():
            raise OutputError(
                f"{what} {path}: {anc} is a file, not a folder; choose another path"
            )
        _probe(what, path, anc)
    if need_bytes > 0 and given:  # the disk the first (the main) output goes to
        what, path = next(iter(given.items()))
        anc = _existing_ancestor(path)
        free = shutil.disk_usage(anc).free
        if free < need_bytes:
            raise OutputError(
                f"the disk holding {anc} has {_mb(free)} free; {what} will need about "
                f"{_mb(need_bytes)}. Free space or choose another folder"
            )
    return {k: Path(os.path.abspath(v)) for k, v in given.items()}


# names that say "a file": a new folder of such a name is a mistake, not a wish
FILE_SUFFIXES = frozenset(
    ".png .jpg .jpeg .gif .json .md .ply .mp4 .avi .npy .npz .h5 .txt .csv .toml".split()
)


def require_suffix(what: str, path: Path | None, suffixes: tuple[str, ...]) -> None:
    """A one-file output whose name says another kind of file (`sel.txt` for a
    PLY) is refused with the name it should have."""
    if path is not None and Path(path).suffix.lower() not in suffixes:
        raise OutputError(
            f"{what} {path}: this command writes a {' or '.join(suffixes)} file; "
            f"e.g. {Path(path).with_suffix(suffixes[0])}"
        )


def check_output_dir(what: str, path: Path) -> Path:
    """An output folder: may exist (as a folder) or be creatable, and writable.
    The one rule of `--out` (`ptovs --help`): a command that writes several files
    takes a folder, so a new path named like a file (`masks.png`) is refused."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise OutputError(
            f"{what} {path} is a file; this command writes several files into a "
            f"folder: give a folder, e.g. {path.with_suffix('')}"
        )
    if not path.exists() and path.suffix.lower() in FILE_SUFFIXES:
        raise OutputError(
            f"{what} {path} names a file; this command writes several files into a "
            f"folder: give a folder, e.g. {path.with_suffix('')}"
        )
    anc = path if path.is_dir() else _existing_ancestor(path)
    if not anc.is_dir():
        raise OutputError(f"{what} {path}: {anc} is a file, not a folder")
    _probe(what, path, anc)
    return path


def _probe(what: str, path: Path, folder: Path) -> None:
    """Create and remove a file in `folder` (permission bits do not tell: root
    passes os.access, a read-only mount or /proc does not)."""
    try:
        fd, name = tempfile.mkstemp(prefix=".ptovs-probe-", dir=folder)
        os.close(fd)
        os.unlink(name)
    except OSError as exc:
        raise OutputError(
            f"{what} {path}: cannot write in {folder} ({exc.strerror or exc}); "
            "choose a folder you can write to"
        ) from None


def describe_os_error(exc: OSError, path: Path | str | None = None) -> str:
    """One line for an OSError a user can cause, naming the file and the fix."""
    name = path or exc.filename or "a file"
    code = exc.errno
    if code == errno.ENOSPC or code == errno.EDQUOT:
        return (
            f"no space left on the disk holding {name}; free space or write elsewhere"
        )
    if code in (errno.EACCES, errno.EPERM):
        return f"permission denied: {name}; choose a path you can write to"
    if code == errno.EROFS:
        return f"{name} is on a read-only file system; write elsewhere"
    if code == errno.EISDIR:
        return f"{name} is a folder; give a file name"
    if code == errno.ENOTDIR:
        return f"a part of {name} is a file, not a folder; choose another path"
    if code == errno.ENOENT:
        return f"{name} does not exist"
    return f"{name}: {exc.strerror or exc}"


@contextmanager
def output_file(
    path: Path, verify: Callable[[Path], None] | None = None
) -> Iterator[Path]:
    """Yield a new, empty temporary file beside `path` (`ptovs.atomic.atomic_file`:
    unguessable hidden name, created exclusively, same suffix); when the block
    ends, check something was written (and `verify(tmp)`, which raises on a bad
    file), then rename it into place. On any failure the temporary file is removed
    and the error names `path`; OSErrors become OutputErrors."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_file(path) as tmp:
            yield tmp
            if not tmp.is_file() or tmp.stat().st_size == 0:
                raise OutputError(f"nothing was written to {path} (is the disk full?)")
            if verify is not None:
                verify(tmp)
    except OSError as exc:
        raise OutputError(
            f"cannot write {path}: {describe_os_error(exc, path)}"
        ) from exc


def write_text_output(path: Path, text: str) -> None:
    """A small text output (JSON, Markdown) through `output_file`."""
    with output_file(path) as tmp:
        tmp.write_text(text)


__all__ = [
    "OutputError",
    "check_output_dir",
    "check_outputs",
    "describe_os_error",
    "output_file",
    "write_text_output",
]

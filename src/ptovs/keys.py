"""Content keys: what an artifact's key is made of.

`artifact_key` hashes a stage's name, VERSION, canonical config
(`ptovs.config.canonical_json`) and upstream keys; a scene's key covers its
files through `fingerprint_files`, whose per-file digests are cached in the work
dir by (size, mtime). A model file a config names (a checkpoint, a tokenizer
folder: `MODEL_FILES`) enters its stage's key by content too (`model_file_deps`),
so a fine-tuned model at the path of the original gives new keys; its digest is
cached in `<work>/.model-digests.json` by (absolute path, size, mtime_ns). Under
`read_only()` (`ptovs status`, the preflight checks) nothing is written, those
caches included: what was hashed is kept in memory until `flush_fingerprints`,
as are the small files a command writes only once its checks pass
(`write_when_checked`: the scene's recorded config).
"""

from __future__ import annotations

import contextlib
import contextvars
import hashlib
import json
import os
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any

from ptovs.atomic import atomic_file
from ptovs.config import canonical_json


def artifact_key(
    stage: str, version: int, config: Any, inputs: Mapping[str, str]
) -> str:
    """sha256 of stage name, stage VERSION, canonical config and upstream keys.

    Args:
        stage: stage name (`"uncertainty"`).
        version: the stage's VERSION (plus the rasterizer's, for rendering stages,
            folded in by the caller through `config` or `inputs`).
        config: the stage's config dataclass or a plain mapping.
        inputs: {input name: upstream key}.

    Returns:
        64 hex characters.
    """
    payload = dict(stage=stage, version=version, config=config, inputs=dict(inputs))
    return hashlib.sha256(canonical_json(payload).encode()).hexdigest()


# set by read-only commands (`ptovs status`): nothing may be written, caches included
READ_ONLY: contextvars.ContextVar[bool] = contextvars.ContextVar(
    "ptovs_read_only", default=False
)


_PENDING: dict[Path, dict] = {}  # fingerprint caches computed while read-only
_DEFERRED: dict[Path, str] = {}  # small files written when the checks pass
_UNDO: dict[Path, str | None] = {}  # what those files held before (None: absent)


@contextlib.contextmanager
def read_only() -> Iterator[None]:
    """Within: nothing is written, the fingerprint cache included (it is kept in
    memory until `flush_fingerprints`)."""
    token = READ_ONLY.set(True)
    try:
        yield
    finally:
        READ_ONLY.reset(token)


def _write_fingerprints(cache: Path, memo: dict) -> None:
    cache.parent.mkdir(parents=True, exist_ok=True)
    with atomic_file(cache, keep_suffix=False) as tmp:
        tmp.write_text(json.dumps(memo))


def write_when_checked(path: Path, text: str) -> None:
    """Write `path` (atomically) when the command's checks pass and its stages
    are about to run (`flush_fingerprints`); dropped if they fail."""
    _DEFERRED[Path(path)] = text


def flush_fingerprints(write: bool = True) -> None:
    """Write (or, `write=False`, drop) the fingerprint caches computed while
    read-only and the files of `write_when_checked`: a preflight that passes keeps
    its hashing, one that fails leaves the work dir as it was."""
    pending, deferred = dict(_PENDING), dict(_DEFERRED)
    _PENDING.clear()
    _DEFERRED.clear()
    if write:
        for cache, memo in pending.items():
            _write_fingerprints(cache, memo)
        for path, text in deferred.items():
            if path not in _UNDO:
                try:
                    _UNDO[path] = path.read_text()
                except OSError:  # absent (or unreadable: nothing to restore)
                    _UNDO[path] = None
            _write_text(path, text)


def _write_text(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_file(path, keep_suffix=False) as tmp:
        tmp.write_text(text)


def forget_checked_writes() -> None:
    """Keep what `write_when_checked` wrote (a command ended, or a new one starts)."""
    _UNDO.clear()


def undo_checked_writes() -> None:
    """Put back what the files of `write_when_checked` held before this command
    wrote them: a command that failed (not one interrupted, which resumes with its
    settings) leaves the scene's recorded settings as they were, so a setting that
    made it fail is not adopted by the next command."""
    undo = dict(_UNDO)
    _UNDO.clear()
    _DEFERRED.clear()
    for path, text in undo.items():
        try:
            if text is None:
                path.unlink(missing_ok=True)
            else:
                _write_text(path, text)
        except OSError:  # best effort: the command's own error is the one to show
            pass


def file_sha256(path: Path) -> str:
    """sha256 of one file's bytes, read in 1 MiB blocks."""
    h = hashlib.sha256()
    with Path(path).open("rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def fingerprint_files(files: Iterable[Path], root: Path, cache: Path | None) -> str:
    """sha256 over (relative path, content sha256) of every file.

    File digests are cached by (size, mtime_ns), so a 3,000-image scene is hashed
    once; a file touched or replaced is hashed again.
    """
    # paths as given (made absolute, links kept): a folder of links to photos
    # elsewhere names its files by their place in the folder, not the targets'
    root = Path(os.path.abspath(root))
    memo: dict[str, list[Any]] = {}
    if cache is not None and cache.is_file():
        try:
            memo = json.loads(cache.read_text())
        except (OSError, ValueError):
            memo = {}
    if cache is not None and cache in _PENDING:  # hashed earlier in this process
        memo.update(_PENDING[cache])
    records, changed = [], False
    for path in sorted(Path(os.path.abspath(p)) for p in files):
        st = path.stat()
        try:
            rel = path.relative_to(root).as_posix()
        except ValueError:  # e.g. labels beside the scene folder
            try:
                rel = path.relative_to(root.parent).as_posix()
            except ValueError:
                rel = Path(os.path.relpath(path, root)).as_posix()
        hit = memo.get(str(path))
        if hit and hit[0] == st.st_size and hit[1] == st.st_mtime_ns:
            digest = hit[2]
        else:
            digest = file_sha256(path)
            memo[str(path)] = [st.st_size, st.st_mtime_ns, digest]
            changed = True
        records.append(f"{rel}:{digest}")
    if cache is not None and cache in _PENDING and not READ_ONLY.get():
        changed = True  # hashed while read-only: now it may be written
    if cache is not None and changed:
        if READ_ONLY.get():
            _PENDING[cache] = memo  # written by flush_fingerprints, if ever
        else:
            _write_fingerprints(cache, memo)
            _PENDING.pop(cache, None)
    return hashlib.sha256("\n".join(records).encode()).hexdigest()


# Config fields that name a local model file or folder, per config section: their
# content enters the stage's key (`model_file_deps`), not only their path. A new
# field naming a checkpoint, tokenizer or model folder belongs here
# (tests/test_checkpoint_key.py checks the names exist and finds undeclared ones).
MODEL_FILES: dict[str, tuple[str, ...]] = {
    "extract-features": (
        "sam_checkpoint",
        "clip_checkpoint",
        "clip_tokenizer",
        "import_dir",  # a LangSplat feature folder
    ),
    "query": ("clip_checkpoint",),
    "reconstruct": ("import_dir",),  # a released WE-GS model
    "sfm": ("vocab_tree",),
}

MODEL_DIGESTS = ".model-digests.json"  # under the work dir: one cache for every scene


def model_file_digest(path: str | Path, cache: Path | None) -> str:
    """sha256 of a model file's content (a folder: of its files' relative paths and
    contents), cached by (absolute path, size, mtime_ns) in `cache`; "missing" or
    "unreadable" instead of an error (the preflight checks say what is wrong).

    A file touched without a change is read once more (its mtime moved) and gives
    the same digest; size alone cannot tell a fine-tuned model from its original.
    """
    p = Path(path).expanduser()
    try:
        if p.is_dir():
            files = [f for f in p.rglob("*") if f.is_file()]
            return fingerprint_files(files, p, cache)
        if p.is_file():
            return fingerprint_files([p], p.parent, cache)
    except OSError:
        return "unreadable"
    return "missing"


def model_file_deps(section: str, config: Any, work_dir: Path) -> dict[str, str]:
    """{"file:<field>": digest} for the section's `MODEL_FILES` fields that are set.

    An empty field adds nothing, so the keys of configs without model files are
    what they were before digests entered keys.
    """
    out = {}
    for name in MODEL_FILES.get(section, ()):
        if isinstance(config, Mapping):
            value = config.get(name, "")
        else:
            value = getattr(config, name, "")
        if value:
            cache = Path(work_dir) / MODEL_DIGESTS
            out[f"file:{name}"] = model_file_digest(str(value), cache)
    return out

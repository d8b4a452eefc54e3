"""Content-keyed HDF5 artifacts: atomic resumable writes, verified reads.

The keys that name them are made in `ptovs.keys`.

Layout of `<work>/<scene>/<stage>/<key[:12]>.h5`:

    /views/<view name>/<dataset>   one group per view (stages that write views)
    /root/<dataset>                whole-scene datasets (models, tables, results)
    root attrs                     key, stage, version, config_json, inputs_json,
                                   git_sha, torch_version, ..., timings_json,
                                   data_sha256, complete

Every dataset carries a `sha256` attribute of its bytes (dtype and shape
included); the root `data_sha256` hashes the sorted list of those. Opening an
artifact recomputes them: a truncated or corrupted file is never used.

Writing is crash-safe and resumable. Each view goes to its own shard file in
`<key[:12]>.parts/` (written to a temporary name, fsynced, renamed), so a run
killed after 2,000 of 3,000 views keeps 2,000 finished shards and the next run
computes only the rest. `finish()` merges the shards into a temporary
`.<key[:12]>.h5.<random>.tmp`, fsyncs it and renames it into place: the final
name appears only when complete. Temporary names are unguessable and created
exclusively (`ptovs.atomic`), so a link planted in the store is never written
through.
Decisions a run makes once for the whole artifact (`Notes`: e.g. the precision
"auto" kept) live in `<key[:12]>.parts/notes.json`, written before the views they
govern, so a resumed run reuses them; `finish()` folds them into the root attrs
(`notes_json`).
A per-key lock file serialises concurrent runs of the same stage; a long stage's
in-stage checkpoint (`Store.checkpoint`) is a `ptovs.checkpoint.Checkpoint`.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import logging
import os
import shutil
import subprocess
import time
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from ptovs import __version__
from ptovs.atomic import atomic_file
from ptovs.checkpoint import Checkpoint
from ptovs.errors import InputError

log = logging.getLogger(__name__)

FORMAT = "ptovs-artifact/1"
SHORT = 12  # characters of the key in file names
ROOT = "/root"  # shard name of the whole-scene datasets (no view can be named so)


@dataclass(frozen=True)
class Dataset:
    """An array plus how to store it (compression for piecewise-constant maps)."""

    data: np.ndarray
    compression: str | None = None  # "gzip" | "lzf" | None


def json_dataset(obj: Any) -> np.ndarray:
    """A JSON document as a uint8 dataset (strings are not storable as arrays)."""
    text = json.dumps(obj, sort_keys=True, separators=(",", ":"))
    return np.frombuffer(text.encode(), dtype=np.uint8).copy()


def read_json_dataset(arr: np.ndarray) -> Any:
    """Inverse of `json_dataset`."""
    return json.loads(np.asarray(arr, np.uint8).tobytes().decode())


class CorruptArtifact(Exception):
    """The file exists but fails verification."""


def array_digest(arr: np.ndarray) -> str:
    """sha256 over dtype, shape and C-order bytes."""
    arr = np.ascontiguousarray(arr)
    h = hashlib.sha256(f"{arr.dtype.str}|{arr.shape}|".encode())
    h.update(arr.view(np.uint8).reshape(-1) if arr.size else b"")
    return h.hexdigest()


def _check_finite(name: str, arr: np.ndarray) -> None:
    # NaN must never reach an artifact; inf is allowed (e.g. sky depth).
    if arr.dtype.kind in "fc" and np.isnan(arr).any():
        raise ValueError(
            f"dataset {name!r} contains NaN ({int(np.isnan(arr).sum())} of "
            f"{arr.size} values); refusing to write it"
        )


def write_atomic(path: Path, data: bytes | str) -> None:
    """Write a small file so that a reader never sees it half written."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # a failed write (full disk, a folder in the way) leaves nothing behind
    with atomic_file(path, keep_suffix=False) as tmp:
        if isinstance(data, str):
            tmp.write_text(data)
        else:
            tmp.write_bytes(data)


def _safe_name(name: str) -> str:
    """View name → HDF5 link name / shard file name (no '/' and no leading '.')."""
    if not name:
        raise ValueError("empty view name")
    return name.replace("%", "%25").replace("/", "%2F").replace("\\", "%5C")


def _unsafe_name(name: str) -> str:
    return name.replace("%5C", "\\").replace("%2F", "/").replace("%25", "%")


def _write_group(group: h5py.Group, datasets: Mapping[str, Any]) -> None:
    for name, value in datasets.items():
        spec = value if isinstance(value, Dataset) else Dataset(np.asarray(value))
        arr = np.asarray(spec.data)
        if arr.dtype == object or arr.dtype.kind in "UO":
            raise TypeError(f"dataset {name!r}: dtype {arr.dtype} is not storable")
        _check_finite(name, arr)
        kwargs: dict[str, Any] = {}
        compression = spec.compression
        if compression is None and arr.dtype.kind in "biu" and arr.size >= 4096:
            compression = "gzip"  # label maps: tiny under gzip (docs/environment.md §7)
        if compression and arr.ndim > 0 and arr.size > 0:
            kwargs = dict(compression=compression, shuffle=True)
            if compression == "gzip":
                kwargs["compression_opts"] = 1
        ds = group.create_dataset(name, data=arr, **kwargs)
        ds.attrs["sha256"] = array_digest(arr)


def git_sha() -> str:
    """The package checkout's commit (or "unknown"), with "-dirty" if modified."""
    here = Path(__file__).resolve().parent
    try:
        sha = subprocess.run(
            ["git", "rev-parse", "HEAD"],
            cwd=here,
            capture_output=True,
            text=True,
            timeout=5,
            check=True,
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=here,
            capture_output=True,
            text=True,
            timeout=5,
            check=True,
        ).stdout.strip()
        return sha + ("-dirty" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def provenance() -> dict[str, str]:
    """Library versions, code identity and the threads (count and whether training
    ran torch on one of them, `ptovs --deterministic`) recorded in every artifact."""
    import torch  # imported here: only writers pay for it

    from ptovs.raster import deterministic as _deterministic

    return dict(
        format=FORMAT,
        ptovs_version=__version__,
        git_sha=git_sha(),
        torch_version=str(torch.__version__),
        numpy_version=np.__version__,
        h5py_version=h5py.__version__,
        threads=str(torch.get_num_threads()),
        deterministic=str(_deterministic()),
        created_utc=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    )


class Artifact:
    """A verified, read-only artifact.

    `names()` lists the views, `artifact[name]` gives a view's datasets as numpy
    arrays, `root()` the whole-scene datasets, `attrs` the provenance.
    """

    def __init__(self, path: Path, *, verify: bool = True):
        self.path = Path(path)
        try:
            self._h5 = h5py.File(self.path, "r")
        except (OSError, ValueError) as exc:
            raise CorruptArtifact(f"{self.path}: cannot open HDF5 ({exc})") from None
        try:
            self.attrs = {k: _attr(v) for k, v in self._h5.attrs.items()}
            if self.attrs.get("format") != FORMAT or not self.attrs.get("complete"):
                raise CorruptArtifact(f"{self.path}: not a complete ptovs artifact")
            if verify:
                self.verify()
        except BaseException:
            self._h5.close()
            raise

    key = property(lambda self: self.attrs["key"])
    stage = property(lambda self: self.attrs["stage"])

    @property
    def config(self) -> dict[str, Any]:
        return json.loads(self.attrs["config_json"])

    @property
    def inputs(self) -> dict[str, str]:
        return json.loads(self.attrs["inputs_json"])

    def verify(self) -> None:
        """Recompute every dataset digest; raise CorruptArtifact on any mismatch."""
        records = []
        try:
            for path, ds in _walk(self._h5):
                want = ds.attrs.get("sha256")
                got = array_digest(ds[()])
                if want is None or _attr(want) != got:
                    raise CorruptArtifact(
                        f"{self.path}: dataset {path} fails its checksum"
                    )
                records.append(f"{path}:{got}")
        except (OSError, RuntimeError, KeyError, ValueError) as exc:
            raise CorruptArtifact(f"{self.path}: unreadable data ({exc})") from None
        if _combined(records) != self.attrs.get("data_sha256"):
            raise CorruptArtifact(
                f"{self.path}: data_sha256 mismatch (datasets missing?)"
            )
        self.verify_identity()

    def verify_identity(self) -> None:
        """The identity attributes (stage, key, config, inputs, data digest) against
        `identity_sha256` (cheap: no data read). Artifacts written before it
        existed have none and pass."""
        want = self.attrs.get("identity_sha256")
        if want is not None and want != _identity(self.attrs):
            raise CorruptArtifact(
                f"{self.path}: its key, config or inputs were changed after writing "
                "(identity_sha256 mismatch)"
            )

    def names(self) -> list[str]:
        if "views" not in self._h5:
            return []
        return sorted(_unsafe_name(n) for n in self._h5["views"])

    def __contains__(self, name: str) -> bool:
        return "views" in self._h5 and _safe_name(name) in self._h5["views"]

    def __getitem__(self, name: str) -> dict[str, np.ndarray]:
        group = self._h5["views"][_safe_name(name)]
        return {k: group[k][()] for k in group}

    def read(self, name: str, keys: Iterable[str]) -> dict[str, np.ndarray]:
        """Only these datasets of a view (KeyError naming the view if one is absent)."""
        group = self._h5["views"][_safe_name(name)]
        out = {}
        for k in keys:
            if k not in group:
                raise KeyError(f"{self.path.name}: view {name} has no dataset {k!r}")
            out[k] = group[k][()]
        return out

    def root_item(self, key: str) -> np.ndarray | None:
        """One root dataset (None when the artifact has none of that name)."""
        if "root" not in self._h5 or key not in self._h5["root"]:
            return None
        return self._h5["root"][key][()]

    def root(self) -> dict[str, np.ndarray]:
        if "root" not in self._h5:
            return {}
        return {k: self._h5["root"][k][()] for k in self._h5["root"]}

    def close(self) -> None:
        self._h5.close()

    def __enter__(self) -> Artifact:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"Artifact({self.stage} {self.key[:SHORT]} at {self.path})"


def _attr(value: Any) -> Any:
    if isinstance(value, bytes):
        return value.decode()
    if isinstance(value, np.generic):
        return value.item()
    return value


def _walk(h5: h5py.Group) -> Iterator[tuple[str, h5py.Dataset]]:
    """Datasets under a group in sorted path order, opened one at a time.

    Only the paths are collected up front: an open h5py Dataset holds its own
    chunk cache, so keeping all of a 3,000-view artifact's datasets open at once
    cost 2.5 GB in `verify` (measured on the scale preset).
    """
    paths: list[str] = []
    h5.visititems(lambda p, o: paths.append(p) if isinstance(o, h5py.Dataset) else None)
    for path in sorted(paths):
        yield path, h5[path]


def _combined(records: list[str]) -> str:
    return hashlib.sha256("\n".join(sorted(records)).encode()).hexdigest()


IDENTITY_ATTRS = ("stage", "key", "config_json", "inputs_json", "data_sha256")
"""What an artifact is, besides its data: covered by `identity_sha256`. Provenance
and timings are not (a rerun of the same key may differ there)."""


def _identity(attrs: Mapping[str, Any]) -> str:
    parts = [f"{k}={attrs.get(k, '')}" for k in IDENTITY_ATTRS]
    return hashlib.sha256("\n".join(parts).encode()).hexdigest()


class Notes:
    """Decisions made once per artifact and kept across resumes (`ArtifactWriter.notes`).

    A view stage that decides something from the data before its first view (which
    precision to encode in, say) stores it here before yielding that view; a run
    resumed on another machine reads it back instead of deciding again, so every
    view of one artifact is made the same way. One JSON file in the artifact's
    `.parts/` folder, tagged with the key and replaced atomically and durably; it
    goes with the parts (`finish`, `discard`, `remove`).
    """

    NAME = "notes.json"  # not `*.h5`: never taken for a view's shard

    def __init__(self, folder: Path, key: str):
        self.path = Path(folder) / self.NAME
        self.key = key

    def all(self) -> dict[str, Any]:
        """Every note stored for this key ({} when none, or another key's)."""
        try:
            blob = json.loads(self.path.read_text())
        except FileNotFoundError:
            return {}
        except (OSError, ValueError) as exc:
            log.warning("notes %s are unreadable (%s); ignored", self.path, exc)
            return {}
        if not isinstance(blob, dict) or blob.get("key") != self.key:
            log.warning("notes %s belong to another key; ignored", self.path)
            return {}
        return dict(blob.get("notes", {}))

    def get(self, name: str, default: Any = None) -> Any:
        """The stored value of `name`, or `default`."""
        return self.all().get(name, default)

    def put(self, name: str, value: Any) -> None:
        """Store `value` (JSON-serialisable) under `name`, durably, before returning."""
        notes = dict(self.all(), **{name: value})
        text = json.dumps({"key": self.key, "notes": notes}, sort_keys=True)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_file(self.path, keep_suffix=False, durable=True) as tmp:
            tmp.write_text(text)


class ArtifactWriter:
    """Resumable writer for one artifact (use through `Store.writer`)."""

    def __init__(self, final: Path, attrs: Mapping[str, Any]):
        self.final = final
        self.parts = final.with_suffix(".parts")
        self.attrs = dict(attrs)
        self.parts.mkdir(parents=True, exist_ok=True)
        self.notes = Notes(self.parts, self.attrs["key"])
        self._done = self._scan()

    def _shard(self, name: str) -> Path:
        return self.parts / f"{_safe_name(name)}.h5"

    def _scan(self) -> set[str]:
        done = set()
        for shard in self.parts.glob("*.h5"):
            name = _unsafe_name(shard.name[: -len(".h5")])
            try:
                with h5py.File(shard, "r") as h5:
                    ok = h5.attrs.get("key") == self.attrs["key"] and h5.attrs.get(
                        "complete"
                    )
                    for _, ds in _walk(h5):
                        if _attr(ds.attrs.get("sha256")) != array_digest(ds[()]):
                            ok = False
            except (OSError, RuntimeError, ValueError):
                ok = False
            if ok:
                done.add(name)
            else:
                log.warning("discarding damaged shard %s", shard)
                shard.unlink(missing_ok=True)
        # writes that were interrupted: shards' `.<view>.h5.<random>.tmp` (`<view>.h5.tmp`
        # before), finish()'s `.<key12>.h5.<random>.tmp` (we hold the lock)
        for tmp in self.parts.glob("*.tmp"):
            tmp.unlink(missing_ok=True)
        for tmp in self.final.parent.glob(f".{self.final.name}.*.tmp"):
            tmp.unlink(missing_ok=True)
        return done

    def done_views(self) -> set[str]:
        """Views finished by this or an earlier, interrupted run."""
        return {n for n in self._done if n != ROOT}

    def write_view(self, name: str, datasets: Mapping[str, Any]) -> None:
        """Durably store one view's datasets (atomic per view)."""
        self._write_shard(name, datasets)

    def write_root(self, datasets: Mapping[str, Any]) -> None:
        """Durably store the whole-scene datasets."""
        self._write_shard(ROOT, datasets)

    def _write_shard(self, name: str, datasets: Mapping[str, Any]) -> None:
        with (
            atomic_file(self._shard(name), keep_suffix=False, durable=True) as tmp,
            h5py.File(tmp, "w") as h5,
        ):
            h5.attrs["key"] = self.attrs["key"]
            _write_group(h5, datasets)
            h5.attrs["complete"] = True
        self._done.add(name)

    def finish(self, extra_attrs: Mapping[str, Any] | None = None) -> Artifact:
        """Merge all shards into the final file, atomically; return it verified."""
        records = []
        with (
            atomic_file(self.final, keep_suffix=False, durable=True) as tmp,
            h5py.File(tmp, "w") as out,
        ):
            for name in sorted(self._done):
                src_path = self._shard(name)
                dst = (
                    out.require_group("root")
                    if name == ROOT
                    else (out.require_group("views").create_group(_safe_name(name)))
                )
                with h5py.File(src_path, "r") as src:
                    for ds_name in src:
                        src.copy(src[ds_name], dst, name=ds_name)
                for path, ds in _walk(dst):
                    records.append(
                        f"{dst.name.lstrip('/')}/{path}:{_attr(ds.attrs['sha256'])}"
                    )
            attrs = dict(self.attrs, **(extra_attrs or {}))
            notes = self.notes.all()
            if notes:  # the run's decisions, kept with what they made
                attrs["notes_json"] = json.dumps(notes, sort_keys=True)
            attrs["format"] = FORMAT
            attrs["n_views"] = len(self.done_views())
            attrs["data_sha256"] = _combined(records)
            attrs["identity_sha256"] = _identity(attrs)
            for k, v in attrs.items():
                # str subclasses (torch's TorchVersion) would become numpy '<U' arrays
                out.attrs[k] = str(v) if isinstance(v, str) else v
            out.attrs["complete"] = True
        shutil.rmtree(self.parts, ignore_errors=True)
        return Artifact(self.final)

    def discard(self) -> None:
        """Forget every finished view and note (used by --force)."""
        self.remove()
        self.parts.mkdir(parents=True, exist_ok=True)

    def remove(self) -> None:
        """Delete the partial artifact (views, notes, the folder): nothing of this
        key is left, so the next run starts clean."""
        shutil.rmtree(self.parts, ignore_errors=True)
        self._done = set()


class Store:
    """The work directory: where artifacts live, how they are found and locked."""

    def __init__(self, work_dir: str | Path):
        self.root = Path(work_dir)

    def path(self, scene: str, stage: str, key: str) -> Path:
        return self.root / scene / stage / f"{key[:SHORT]}.h5"

    def lookup(self, scene: str, stage: str, key: str) -> Artifact | None:
        """The verified artifact for `key`, or None. Corrupt files are moved aside."""
        path = self.path(scene, stage, key)
        if not path.exists():
            return None
        try:
            art = Artifact(path)
            if art.key != key:  # renamed or copied by hand (a 12-character prefix
                art.close()  # collision is astronomically rare)
                raise CorruptArtifact(
                    f"{path} holds key {art.key[:SHORT]}…, not {key[:SHORT]}…"
                )
        except CorruptArtifact as exc:
            bad = path.with_name(path.name + ".corrupt")
            log.warning(
                "%s; moved to %s: run the stage again to recompute it", exc, bad.name
            )
            os.replace(path, bad)
            return None
        return art

    def exists(self, scene: str, stage: str, key: str) -> bool:
        """Cheap check (no checksum pass): a complete artifact with this key exists."""
        path = self.path(scene, stage, key)
        if not path.exists():
            return False
        try:
            with Artifact(path, verify=False) as art:
                art.verify_identity()
                return art.key == key
        except CorruptArtifact:
            return False

    def partial_views(self, scene: str, stage: str, key: str) -> int:
        parts = self.path(scene, stage, key).with_suffix(".parts")
        return (
            len([p for p in parts.glob("*.h5") if p.name != f"{_safe_name(ROOT)}.h5"])
            if parts.is_dir()
            else 0
        )

    def others(self, scene: str, stage: str, key: str) -> list[Artifact]:
        """Complete artifacts of this stage under other keys, newest first (unverified)."""
        folder = self.root / scene / stage
        found = []
        for p in sorted(
            folder.glob("*.h5"), key=lambda q: q.stat().st_mtime, reverse=True
        ):
            if p.name == f"{key[:SHORT]}.h5":
                continue
            with contextlib.suppress(CorruptArtifact):
                found.append(Artifact(p, verify=False))
        return found

    @contextlib.contextmanager
    def lock(self, scene: str, stage: str, key: str) -> Iterator[None]:
        """Exclusive lock for one (scene, stage, key); waits for another holder."""
        path = self.path(scene, stage, key).with_suffix(".lock")
        path.parent.mkdir(parents=True, exist_ok=True)
        # O_NOFOLLOW: a link planted at the lock's name is refused, never followed
        flags = os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC
        try:
            fd = os.open(path, flags, 0o666)
        except OSError as exc:
            if path.is_symlink():
                raise InputError(
                    f"{path} is a symbolic link; ptovs never follows one in its work "
                    "folder. Remove it (and check who can write there)"
                ) from exc
            raise
        with os.fdopen(fd, "r+") as fh:
            try:
                fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                log.info("waiting for another ptovs process working on %s", path.stem)
                fcntl.flock(fh, fcntl.LOCK_EX)
            try:
                yield
            finally:
                fcntl.flock(fh, fcntl.LOCK_UN)

    def checkpoint(self, scene: str, stage: str, key: str) -> Checkpoint:
        """The in-stage checkpoint slot of one (scene, stage, key)."""
        return Checkpoint(self.path(scene, stage, key).with_suffix(".ckpt"), key)

    def writer(
        self, scene: str, stage: str, key: str, attrs: Mapping[str, Any]
    ) -> ArtifactWriter:
        """A resumable writer; hold `lock()` around its use."""
        return ArtifactWriter(
            self.path(scene, stage, key), dict(attrs, key=key, stage=stage)
        )

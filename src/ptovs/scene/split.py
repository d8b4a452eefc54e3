"""The train/test split: a NeRF-W style TSV beside the scene, or every view train."""

from __future__ import annotations

import logging
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from ptovs.errors import InputError, MissingInputError

logger = logging.getLogger(__name__)


def resolve_split_file(root: Path, layout: str, split_file: Any) -> Path | None:
    """The TSV to read, or None for all-train."""
    if split_file is None:
        split_file = "auto"
    if isinstance(split_file, str) and split_file == "all-train":
        return None
    if isinstance(split_file, str) and split_file == "auto":
        tsvs = sorted(p for p in root.glob("*.tsv") if p.is_file())
        if len(tsvs) > 1:
            raise InputError(
                f"several split files in {root}: {', '.join(p.name for p in tsvs)}; "
                "keep one, or pass split_file=<path> (--set scene.split_file=...)"
            )
        if tsvs:
            return tsvs[0]
        if layout == "phototourism":
            raise InputError(
                f"no split file (*.tsv) in {root}; add a NeRF-W style TSV "
                "(columns filename, id, split, dataset) or pass "
                'split_file="all-train" (--set scene.split_file=all-train)'
            )
        logger.info("no *.tsv in %s: every image is a train view", root)
        return None
    path = Path(split_file).expanduser()
    if not path.is_absolute() and not path.is_file() and (root / path).is_file():
        path = root / path
    if not path.is_file():
        raise MissingInputError(
            f"split file {path} does not exist; pass an existing TSV, 'auto' or "
            "'all-train'"
        )
    return path


def read_split_tsv(path: str | Path) -> dict[str, str]:
    """Read a NeRF-W style split file.

    Args:
        path: tab-separated file with a header holding at least `filename` and
            `split` (other columns are ignored).

    Returns:
        {filename: "train" | "test"}; any split other than "train" is "test".
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InputError(f"split file {path} is not UTF-8 text ({exc})") from exc
    lines = [(i, ln) for i, ln in enumerate(text.splitlines(), 1) if ln.strip()]
    if not lines:
        raise InputError(
            f"split file {path} is empty; it needs a tab-separated header "
            "'filename<TAB>id<TAB>split<TAB>dataset' and one row per image"
        )
    head = lines[0][1].split("\t")
    header = [h.strip().lower() for h in head]
    missing = [c for c in ("filename", "split") if c not in header]
    if missing:
        raise InputError(
            f"split file {path} lacks column(s) {missing} in its header {head}; "
            "it must be tab-separated with at least 'filename' and 'split'"
        )
    i_name, i_split = header.index("filename"), header.index("split")
    out: dict[str, str] = {}
    for lineno, line in lines[1:]:
        row = line.split("\t")
        if len(row) <= max(i_name, i_split):
            raise InputError(
                f"split file {path}, line {lineno}: {len(row)} field(s) {row}, "
                f"expected at least {max(i_name, i_split) + 1} tab-separated fields"
            )
        name, split = row[i_name].strip(), row[i_split].strip()
        if not name:
            raise InputError(f"split file {path}, line {lineno}: empty filename")
        split = "train" if split == "train" else "test"
        if out.get(name, split) != split:
            raise InputError(
                f"split file {path}, line {lineno}: {name!r} is listed as both "
                "train and test; keep one row per image"
            )
        out[name] = split
    return out


def preview(names: Iterable[str], n: int = 5) -> str:
    names = list(names)
    more = f", ... ({len(names)} in all)" if len(names) > n else ""
    return ", ".join(names[:n]) + more


def assign_splits(
    by_name: dict[str, int],
    splits: dict[str, str] | None,
    tsv: Path | None,
    model_dir: Path,
) -> dict[str, str]:
    """{registered image name: split}: the TSV's (names matched case-insensitively;
    unknown and unlisted names warned about) or every image train without a TSV."""
    if splits is not None:
        lower = {n.lower(): n for n in by_name}
        chosen: dict[str, str] = {}
        unknown = []
        for name, split in splits.items():
            key = name if name in by_name else lower.get(name.lower())
            if key is None:
                unknown.append(name)
            else:
                chosen[key] = split
        if unknown:
            logger.warning(
                "%s: %d name(s) in the split file are not registered in the model "
                "(skipped): %s",
                tsv,
                len(unknown),
                preview(unknown),
            )
        unlisted = sorted(set(by_name) - set(chosen))
        if unlisted:
            logger.warning(
                "%s: %d registered image(s) are not in the split file and are left "
                "out: %s",
                tsv,
                len(unlisted),
                preview(unlisted),
            )
        if not chosen:
            raise InputError(
                f"split file {tsv} lists none of the {len(by_name)} registered images "
                f"of {model_dir} (e.g. {preview(sorted(by_name), 3)}); fix the "
                "filename column or pass split_file='all-train'"
            )
    else:
        chosen = dict.fromkeys(by_name, "train")
    return chosen

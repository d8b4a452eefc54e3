"""The repository stands alone: no tracked file points at a document outside it.

Cheap (reads the ~200 tracked files once, no imports of ptovs): every reference to the
old out-of-tree notes must have moved to the in-repo docs (docs/method.md,
docs/rasterizer.md, docs/environment.md, docs/synthetic.md, docs/standin.md), and
every `docs/<name>.md` that a tracked file mentions must exist.
"""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# Names of documents that live outside the repository. Spelled in pieces so that this
# file does not match itself.
FORBIDDEN = (
    "PAPER" + "_SPEC",
    "RASTERIZER" + ".md",
    "ENVIRONMENT" + ".md",
    "SYNTHETIC" + ".md",
    "CLIP_" + "ROBUSTNESS",
    "STYLE" + ".md",
    "../" + "sha" + "red",
    "sha" + "red/data" + "/real",
)

# Files the forbidden-name check skips: none.
EXCLUDED_FILES: set[str] = set()
EXCLUDED_DIRS: tuple[str, ...] = ()

# `docs/<name>.md` as a repository path (not the tail of another path or a URL).
DOCS_PATH = re.compile(r"(?<![\w./-])docs/[\w-]+(?:/[\w-]+)*\.md")


def _tracked_texts() -> dict[str, str]:
    """{path: text} of every tracked text file present in the work tree."""
    try:
        out = subprocess.run(
            ["git", "ls-files", "-z"],
            cwd=ROOT,
            capture_output=True,
            timeout=30,
            check=True,
        ).stdout
    except (OSError, subprocess.SubprocessError):
        pytest.skip("not a git checkout (or git is missing)")
    texts = {}
    for name in out.decode().split("\0"):
        path = ROOT / name
        if not name or not path.is_file():
            continue  # deleted in the work tree, or a submodule
        data = path.read_bytes()
        if b"\0" in data[:8192]:
            continue  # binary
        try:
            texts[name] = data.decode("utf-8")
        except UnicodeDecodeError:
            continue  # not text
    if not texts:
        pytest.skip("git lists no files here")
    return texts


@pytest.fixture(scope="module")
def texts() -> dict[str, str]:
    return _tracked_texts()


def test_no_reference_to_outside_documents(texts):
    hits = []
    for name, text in texts.items():
        if name in EXCLUDED_FILES or name.startswith(EXCLUDED_DIRS):
            continue
        for lineno, line in enumerate(text.splitlines(), 1):
            hits += [f"{name}:{lineno}: {word}" for word in FORBIDDEN if word in line]
    assert not hits, "references to files outside the repository:\n" + "\n".join(hits)


def test_cited_docs_exist(texts):
    missing = sorted(
        {
            f"{name}: {m.group(0)}"
            for name, text in texts.items()
            for m in DOCS_PATH.finditer(text)
            if not (ROOT / m.group(0)).is_file()
        }
    )
    assert not missing, "cited documents that do not exist:\n" + "\n".join(missing)

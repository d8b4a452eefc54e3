"""Every figure a user reads carries its date, and the README's and the guide's
figures are docs/results.md's.

- A measured figure in README.md or docs/guide.md (a number with a unit of time,
  memory, speed or PSNR, a ratio in ×, or a score written 0.ddd), outside code
  blocks and inline code, occurs as written in docs/results.md, where its date,
  commit and command are. A number the code itself holds (a threshold, a default)
  is a setting, not a measurement, and may stand alone; so may a checkpoint's
  file size in the guide's download table.
- Every README table that shows a measured (bold) figure is dated: a date in
  each row, in its header, or in the sentence that introduces it.
- Every table of docs/results.md is followed by its record line (date · commit ·
  machine · command) before the next heading.

Reads files only: no ptovs import, milliseconds.
"""

from __future__ import annotations

import re
import tokenize
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
GUIDE = ROOT / "docs" / "guide.md"
RESULTS = ROOT / "docs" / "results.md"

NUM = r"\d[\d,]*(?:\.\d+)?"
UNIT = r"(?:s|min|h|MB|GB|dB|×|crops/s|ms)"
FIGURE = re.compile(rf"(?<![\w.])({NUM})(?:\s?[–-]\s?{NUM})?\s?{UNIT}(?!\w)")
SCORE = re.compile(r"(?<![\w.\-])(0\.\d{3})(?!\d)")
DATE = re.compile(r"\b20\d\d-\d\d-\d\d\b")
CODE_SPAN = re.compile(r"`[^`]*`")  # may run over a line break
DOWNLOAD_ROW = re.compile(r"^\|.*https?://")  # a download table's row: file sizes


def prose_lines(path: Path) -> list[tuple[int, str]]:
    """(line number, text) outside fenced code blocks, inline code removed."""
    text = CODE_SPAN.sub(lambda m: "\n" * m.group(0).count("\n"), path.read_text())
    out, fenced = [], False
    for i, line in enumerate(text.splitlines(), 1):
        if line.startswith("```"):
            fenced = not fenced
            continue
        if not fenced:
            out.append((i, line))
    return out


def source_literals() -> set[str]:
    """Every numeric literal of the package's code (not its docstrings or
    comments): settings and thresholds."""
    found: set[str] = set()
    for py in (ROOT / "src" / "ptovs").rglob("*.py"):
        with py.open("rb") as f:
            for tok in tokenize.tokenize(f.readline):
                if tok.type == tokenize.NUMBER:
                    found.add(tok.string.replace("_", ""))
    return found


def unheld_figures(path: Path) -> list[str]:
    results = RESULTS.read_text()
    literals = source_literals()
    missing = []
    for i, line in prose_lines(path):
        if DOWNLOAD_ROW.search(line):
            continue
        for m in [*FIGURE.finditer(line), *SCORE.finditer(line)]:
            number = m.group(1)
            if number in results or number.replace(",", "") in literals:
                continue
            missing.append(f"{m.group(0)!r} at {path.name}:{i}: {line.strip()[:90]!r}")
    return missing


@pytest.mark.parametrize("page", [README, GUIDE], ids=lambda p: p.name)
def test_a_figure_of_the_page_is_a_results_figure(page):
    missing = unheld_figures(page)
    assert not missing, (
        "figures that docs/results.md does not hold (give the figure there with its "
        "date and command and link to it, or drop it):\n" + "\n".join(missing)
    )


def test_the_figure_reader_finds_figures_and_skips_code(tmp_path, monkeypatch):
    page = tmp_path / "p.md"
    page.write_text(
        "took 12.5 s and 3.4× less, mIoU 0.731\n"
        "`ran 99.9 s` in code\n```\nlog 77.7 s\n```\n"
    )
    results = tmp_path / "r.md"
    results.write_text("12.5 s\n")
    monkeypatch.setattr(__import__(__name__), "RESULTS", results)
    missing = unheld_figures(page)
    said = [m.split(" at ")[0] for m in missing]
    assert said == ["'3.4×'", "'0.731'"], missing


def tables(path: Path) -> list[tuple[int, list[str]]]:
    """(first line number, the table's lines) for each Markdown table."""
    out: list[tuple[int, list[str]]] = []
    lines = path.read_text().splitlines()
    i = 0
    while i < len(lines):
        if (
            lines[i].startswith("|")
            and i + 1 < len(lines)
            and lines[i + 1].startswith("|---")
        ):
            j = i
            while j < len(lines) and lines[j].startswith("|"):
                j += 1
            out.append((i, lines[i:j]))
            i = j
        else:
            i += 1
    return out


def test_a_readme_table_of_figures_is_dated():
    lines = README.read_text().splitlines()
    undated = []
    for start, rows in tables(README):
        if not any("**" in r and re.search(r"\*\*[^*]*\d", r) for r in rows[2:]):
            continue  # no measured figure in it
        intro = "\n".join(lines[max(0, start - 4) : start])
        if DATE.search(rows[0]) or DATE.search(intro):
            continue
        if all(DATE.search(r) for r in rows[2:]):
            continue
        undated.append(f"README.md:{start + 1}: {rows[0][:70]}")
    assert not undated, "README tables of figures without a date:\n" + "\n".join(
        undated
    )


def test_a_results_table_carries_its_record_line():
    lines = RESULTS.read_text().splitlines()
    unrecorded = []
    for start, rows in tables(RESULTS):
        end = start + len(rows)
        after = []  # up to the next heading: tables of one question share a record
        for line in lines[end:]:
            if line.startswith("#"):
                break
            after.append(line)
        before = lines[max(0, start - 3) : start]
        if not any(DATE.search(x) for x in after + before):
            unrecorded.append(f"docs/results.md:{start + 1}: {rows[0][:70]}")
    assert not unrecorded, (
        "results tables without a date before the next table or heading:\n"
        + "\n".join(unrecorded)
    )

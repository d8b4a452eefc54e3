"""The docs hold each figure once: the README's figures are docs/results.md's.

The README and docs/results.md say what is true of today's code; docs/findings.md
and CHANGELOG.md say what was learned and what changed. So:

- every figure the README puts in bold occurs, as written, in docs/results.md;
- every link into docs/results.md names a heading that exists there;
- the demo's figures in docs/results.md are the ones `make pictures`
  (bench/pictures.py) wrote to docs/results/demo.json from a finished `make demo`;
- user docs carry no tracker numbers (an issue, amendment or stop is history for
  the project's notes, not for users), and the front pages stay short.

Reads files only: no ptovs import, milliseconds.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
RESULTS = ROOT / "docs" / "results.md"
DEMO_JSON = ROOT / "docs" / "results" / "demo.json"

BOLD = re.compile(r"\*\*([^*]+)\*\*")
LINK = re.compile(r"\]\((?:\./)?docs/results\.md#([^)\s]+)\)")
HISTORY = re.compile(r"\b(?:issue|amendment)s? \d+|\bstop \d+\b", re.I)


def slug(heading: str) -> str:
    """A Markdown heading's anchor as GitHub spells it."""
    text = re.sub(r"[`*_]", "", heading.strip().lower())
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    out = set()
    for line in path.read_text().splitlines():
        if m := re.match(r"#{1,6}\s+(.*)", line):
            out.add(slug(m.group(1)))
    return out


def readme_figures() -> list[str]:
    return [b.strip() for b in BOLD.findall(README.read_text()) if re.search(r"\d", b)]


def test_the_readme_has_figures_to_check():
    assert len(readme_figures()) >= 10, readme_figures()


@pytest.mark.parametrize("figure", readme_figures())
def test_a_readme_figure_is_a_results_figure(figure):
    assert figure in RESULTS.read_text(), (
        f"README.md says **{figure}**, docs/results.md does not: change the one that "
        "is out of date (docs/results.md holds the measured figure and its command)"
    )


def test_readme_links_into_results_name_existing_headings():
    have = anchors(RESULTS)
    links = LINK.findall(README.read_text())
    assert links, "the README links no section of docs/results.md"
    missing = sorted(set(links) - have)
    assert not missing, (
        f"README.md links docs/results.md#{missing}; headings: {sorted(have)}"
    )


def test_the_demo_figures_are_the_recorded_ones():
    """docs/results.md's demo table quotes docs/results/demo.json, value for value."""
    demo = json.loads(DEMO_JSON.read_text())
    text = RESULTS.read_text()
    section = text.split("## The demo", 1)[1].split("\n## ", 1)[0]
    for key in ("miou", "mpa", "mp"):
        assert f"{demo['evaluate'][key]:.3f}" in section, (key, demo["evaluate"])
    sel = demo["select"]
    assert f"{sel['selected']:,} of {sel['gaussians']:,}" in section, sel
    assert f"score {sel['score']:.3f}" in section, sel
    assert demo["style"]["winner"] in section, demo["style"]
    assert demo["commit"] in section, (
        "the demo table names the commit it was measured at"
    )


USER_DOCS = ["README.md", "CHANGELOG.md", *sorted(p.relative_to(ROOT).as_posix()
             for p in (ROOT / "docs").glob("*.md"))]  # fmt: skip


@pytest.mark.parametrize("name", USER_DOCS)
def test_user_docs_carry_no_tracker_history(name):
    hits = [
        f"{i}: {line.strip()[:80]}"
        for i, line in enumerate((ROOT / name).read_text().splitlines(), 1)
        if HISTORY.search(line)
    ]
    assert not hits, f"{name} names issues/amendments/stops:\n" + "\n".join(hits)


@pytest.mark.parametrize(
    "name, most",
    [("README.md", 250), ("docs/results.md", 400), ("docs/findings.md", 500)],
)
def test_front_pages_stay_short(name, most):
    n = len((ROOT / name).read_text().splitlines())
    assert n <= most, f"{name} has {n} lines; at most {most}"


def test_slug_matches_github_anchors():
    assert slug("The demo") == "the-demo"
    assert (
        slug("The paper's multi-appearance claim")
        == "the-papers-multi-appearance-claim"
    )
    assert slug("Speed: the `cpu` kernel") == "speed-the-cpu-kernel"

"""The docs hold each figure once: the README's figures are docs/results.md's.

The README and docs/results.md say what is true of today's code; docs/findings.md
and CHANGELOG.md say what was learned and what changed. So:

- every figure the README puts in bold occurs, as written, in docs/results.md;
- a figure findings.md, guide.md or design.md quotes from a results table (or
  another page's) is the table's: each such quote is a CLAIMS row, and any
  "point [low, high]" interval that results.md also gives carries its point;
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
import sys
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


# --- Figures quoted on more than one page -------------------------------------------
#
# findings.md, guide.md, design.md and the README may quote a figure that
# docs/results.md (or another page's table) holds. Two checks keep them equal:
#
# - every "point [low, high]" interval a page quotes that also occurs in results.md
#   must carry a point results.md gives with that interval (an interval is a
#   fingerprint: the same one with another point is a stale copy);
# - CLAIMS: (page, pattern, expected) for the other quoted figures. `pattern`'s
#   groups are the figures as the page writes them; `expected()` reads them from the
#   table that holds them. A page that no longer says it fails too: reword the
#   pattern with the sentence, or drop the claim with the figure.

N = r"(\d[\d,]*(?:\.\d+)?)"  # a figure in a claim
NUMBER = r"[−+-]?\d[\d,]*(?:\.\d+)?(?:e[−+-]?\d+)?"
INTERVAL = re.compile(rf"({NUMBER})\*{{0,2}}\s+\[({NUMBER}),\s+({NUMBER})\]")
QUOTING_PAGES = ["README.md", "docs/findings.md", "docs/guide.md", "docs/design.md"]


def norm(figure: str) -> str:
    """A figure as a comparable string: Unicode minus, thousands commas and
    markup dropped; a number in plain decimal form (6.3e-6 and 6.3e-06 agree)."""
    s = figure.replace("−", "-").replace(",", "").replace("*", "").replace("`", "")
    s = s.strip()
    try:
        return repr(float(s))
    except ValueError:
        return s


def first_number(cell: str) -> str:
    m = re.search(NUMBER, cell.replace("*", ""))
    assert m, f"no number in table cell {cell!r}"
    return m.group(0)


def table(page: str, header: str) -> list[dict[str, str]]:
    """The rows of the Markdown table of `page` whose header row contains `header`,
    each as {column name: cell}, plus "_key": the first cell without markup."""
    lines = (ROOT / page).read_text().splitlines()
    for i, line in enumerate(lines):
        if line.startswith("|") and header in line:
            names = [c.strip() for c in line.strip().strip("|").split("|")]
            rows = []
            for text in lines[i + 2 :]:
                if not text.startswith("|"):
                    break
                cells = [c.strip() for c in text.strip().strip("|").split("|")]
                rows.append(
                    {"_key": re.sub(r"[*`]", "", cells[0])}
                    | dict(zip(names, cells, strict=False))
                )
            return rows
    raise AssertionError(f"{page} has no table whose header holds {header!r}")


def row(page: str, header: str, starts: str) -> dict[str, str]:
    """The one row of that table whose first cell starts with `starts`."""
    rows = table(page, header)
    hits = [r for r in rows if r["_key"].startswith(starts.replace("`", ""))]
    assert len(hits) == 1, f"{page}, table {header!r}: rows {[r['_key'] for r in rows]}"
    return hits[0]


def gb(mb_cell: str) -> str:
    return f"{float(norm(first_number(mb_cell))) / 1000:.1f}"


def extremes(cells: list[str]) -> list[str]:
    vals = sorted(cells, key=lambda c: float(norm(c)))
    return [vals[0], vals[-1]]


def speedup(cell: str) -> str:
    m = re.search(rf"\({N}×\)", cell)
    assert m, cell
    return m.group(1)


R = "docs/results.md"
GROWTH, BIG = "400: s", "763: peak MB"
GPU, RASTER = "cuda64", "max rel. err"
SFM, THREADS = "rotation error median", "2 threads"
ENC, SEG = "crops/s fp32", "s a photo, 8² points"
PEERS = "| tool |"
SEGMENTERS = "2-D mIoU, best filter"


def _gpu():
    rows = table(R, GPU)
    return [
        *extremes([r["cuda"] for r in rows]),
        *extremes([r["cuda64"] for r in rows]),
    ]


def _peer(scene):
    rows = [r for r in table(R, PEERS) if r["scene"] == scene]
    assert len(rows) == 3, rows
    # OpenSplat's PSNR reads "a viewer's depth order / its own renderer"; pages
    # quote its own renderer's, the reading that favours it
    psnr = [r["held-out PSNR (dB)"].split(" / ")[-1] for r in rows]
    return [r["s a step"] for r in rows] + [first_number(c) for c in psnr]


def _chain_views() -> list[str]:
    """The real-class chain's seconds a view, before and now: full, then photo alone."""
    before = row(
        R, "stage, s", "the same, before (PyTorch, 64 crops a call; 2–4 views)"
    )
    now = row(R, "stage, s", "extract-features")
    cols = ("full method (`male`)", "photo alone (`langsplat-wild`)")
    return [
        re.search(pat, table[c]).group(1)
        for c in cols
        for table, pat in ((before, rf"^{N} s"), (now, rf"\*\*{N} s\*\*"))
    ]


CLAIMS = [
    ("docs/findings.md", rf"launch-bound: {N}–{N} ms at every size \(float64 {N}–{N}\)", _gpu),
    ("docs/findings.md", r"≤ (\S+) at the 99\.9th percentile",
     lambda: [max((r["p99.9"] for r in table(R, RASTER)), key=lambda c: float(norm(c)))]),
    ("docs/findings.md", rf"400 photos: {N} s end to end, mIoU\s+{N}",
     lambda: [first_number(row(R, GROWTH, "whole chain")["400: s"]),
              first_number(row(R, GROWTH, "query / evaluate")["quality"])]),
    ("docs/findings.md", rf"run end to end on 2 cores\*\*, peak {N} GB, mIoU {N}",
     lambda: [gb(row(R, BIG, "reconstruct")["763: peak MB"]),
              re.search(rf"mIoU {N}", row(R, BIG, "quality")["763: s (projected)"]).group(1)]),
    ("docs/findings.md", rf"reconstruct {N} / {N} / {N} GB at 400 / 763 / 2,934",
     lambda: [gb(row(R, GROWTH, "reconstruct")["400: MB"]),
              gb(row(R, BIG, "reconstruct")["763: peak MB"]),
              gb(row(R, BIG, "reconstruct")["2,934: peak MB"])]),
    ("docs/findings.md", rf"Now {N} GB at 763, and {N} GB in a probe",
     lambda: [gb(row(R, BIG, "train-male")["763: peak MB"]),
              gb(row(R, BIG, "train-male")["2,934: peak MB"])]),
    ("docs/findings.md", rf"every thread \(`--nondeterministic`\) made it {N}× faster",
     lambda: [first_number(row(R, THREADS, "reconstruct, `--nondeterministic`")["16 ÷ 2"])]),
    ("docs/findings.md", rf"query gained {N}×,\s+uncertainty\s+{N}×",
     lambda: [first_number(row(R, THREADS, "train-male / query")["16 ÷ 2"].split(" / ")[1]),
              first_number(row(R, THREADS, "render-appearances / uncertainty")["16 ÷ 2"].split(" / ")[1])]),
    ("docs/findings.md",
     rf"median rotation error {N}° and {N}°\s+\(rotations aligned; centres aligned {N}° and {N}°\)",
     lambda: [re.search(p, row(R, SFM, s)["rotation error median / p90 (°)"]).group(1)
              for p in (rf"^{N}", rf"centres aligned: {N}")
              for s in ("fountain_p11", "herzjesu_p8")]),
    ("docs/findings.md", rf"full method view went {N} → {N} s, photo alone {N} → {N} s",
     _chain_views),
    ("docs/findings.md", rf"halves the photo \({N} s against {N} s at",
     lambda: [row(R, SEG, "SAM 2.1")["s a photo, 8² points"], row(R, SEG, "SAM ViT-B")["s a photo, 8² points"]]),
    *[("docs/findings.md",
       rf"\| {scene} \| {N} / {N} / {N} \| {N} / {N} / {N} \|",
       lambda scene=scene: _peer(scene))
      for scene in ("herzjesu_p8", "fountain_p11", "bench seed 0")],
    ("docs/design.md", rf"2-D ceiling of\s+{N} against the graph segmenter's {N}",
     lambda: [row("docs/findings.md", SEGMENTERS, "truth part masks")[SEGMENTERS],
              first_number(row("docs/findings.md", SEGMENTERS, "graph (the old default)")[SEGMENTERS])]),
    ("docs/guide.md", r"take (\d+)² points\s+\(`sam_points_per_side = (\d+)`\)",
     lambda: 2 * [re.search(r"sam_points_per_side = (\d+)",
                            (ROOT / "configs" / "photos-cpu.toml").read_text()).group(1)]),
]  # fmt: skip


@pytest.mark.parametrize(
    "page, pattern, expected", CLAIMS, ids=[f"{c[0]}:{c[1][:24]}" for c in CLAIMS]
)
def test_a_quoted_figure_is_the_measured_one(page, pattern, expected):
    m = re.search(pattern, (ROOT / page).read_text())
    assert m, (
        f"{page} no longer says /{pattern}/: if the sentence was reworded, reword the "
        "pattern in tests/test_docs_figures.py CLAIMS; if the figure left, drop it"
    )
    said, want = list(m.groups()), [str(x) for x in expected()]
    assert [norm(s) for s in said] == [norm(w) for w in want], (
        f"{page} says {said} where the measured figures are {want}: rewrite the page "
        "that is out of date (docs/results.md holds the figure and its command)"
    )


def quoted_intervals(page: str) -> list[tuple[str, str, str]]:
    return INTERVAL.findall((ROOT / page).read_text())


def test_a_quoted_interval_carries_its_measured_point():
    measured: dict[tuple[str, str], set[str]] = {}
    for point, lo, hi in quoted_intervals(R):
        measured.setdefault((norm(lo), norm(hi)), set()).add(norm(point))
    shared, stale = 0, []
    for page in QUOTING_PAGES:
        for point, lo, hi in quoted_intervals(page):
            points = measured.get((norm(lo), norm(hi)))
            if points is None:
                continue  # a figure results.md does not hold (a finding's own)
            shared += 1
            if norm(point) not in points:
                stale.append(f"{page}: {point} [{lo}, {hi}] (results.md: {points})")
    assert shared >= 10, f"only {shared} shared intervals: is the pattern still right?"
    assert not stale, "stale copies of results.md's figures:\n" + "\n".join(stale)


def test_the_table_reader_reads_what_it_is_given(tmp_path, monkeypatch):
    page = tmp_path / "p.md"
    page.write_text(
        "x\n\n| a | b: s |\n|---|---|\n| **one** | 1,234 |\n| two | 5 |\n\ny\n"
    )
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    assert row("p.md", "b: s", "one")["b: s"] == "1,234"
    assert norm("−6.3e-6") == norm("-6.3e-06") and norm("2,494") == norm("2494")
    assert gb("5,112") == "5.1" and extremes(["9", "10.5", "2"]) == ["2", "10.5"]

"""bench/accuracy.py: a killed run resumes without redoing finished
seeds; the report's cluster statistics on hand-made results."""

from __future__ import annotations

import importlib.util
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "bench" / "accuracy.py"


def _bench():
    spec = importlib.util.spec_from_file_location("bench_accuracy", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_killed_run_resumes_without_redoing_finished_seeds(tmp_path: Path) -> None:
    data, work = tmp_path / "data", tmp_path / "work"
    cmd = [sys.executable, str(SCRIPT), "--preset", "tiny", "--seeds", "0-1",
           "--labels", "2d", "2d-best", "2d-nosmooth", "2d-truth", "--jobs", "1", "--config", str(ROOT / "configs/ci.toml"),
           "--data", str(data), "--work", str(work)]  # fmt: skip
    first = work / "results" / "tiny_s0.json"
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            start_new_session=True, text=True)  # fmt: skip
    try:
        t0 = time.time()
        while not first.is_file():
            assert proc.poll() is None, proc.communicate()[0]
            assert time.time() - t0 < 300, "seed 0 never finished"
            time.sleep(0.05)
    finally:  # kill the runner and its seed job, as a Ctrl-C or a lost shell would
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    assert not (work / "results" / "tiny_s1.json").is_file()
    before = first.stat().st_mtime_ns, first.read_bytes()
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "seed 1: done" in res.stdout
    assert (first.stat().st_mtime_ns, first.read_bytes()) == before  # not redone
    s1 = json.loads((work / "results" / "tiny_s1.json").read_text())
    pairs = s1["labels"]["2d"]["pairs"]
    assert pairs and all(0.0 <= p["iou"] <= 1.0 for p in pairs)
    for lab in ("2d-best", "2d-nosmooth", "2d-truth"):  # the same pairs, other ways
        other = s1["labels"][lab]["pairs"]
        assert [(p["view"], p["query"]) for p in other] == [
            (p["view"], p["query"]) for p in pairs
        ]
        assert all(0.0 <= p["iou"] <= 1.0 for p in other)
    keys = {lab: s1["labels"][lab]["key"] for lab in ("2d", "2d-nosmooth", "2d-truth")}
    assert len(set(keys.values())) == 2  # truth segments are other features
    assert keys["2d"] == keys["2d-nosmooth"]
    assert s1["screen"]["margin"] > 0 and set(s1["hard"]) >= {p["view"] for p in pairs}
    report = (work / "accuracy.md").read_text()
    assert "### dev seeds [0]" in report and "### test seeds [1]" in report
    # a third run has nothing to do
    both = first.read_bytes(), (work / "results" / "tiny_s1.json").read_bytes()
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stdout + res.stderr
    assert (
        first.read_bytes(),
        (work / "results" / "tiny_s1.json").read_bytes(),
    ) == both
    # a label stored under another artifact key (a changed default, say) is stale:
    # the next run drops and remeasures it, and drops labels it no longer knows
    s0 = json.loads(both[0])
    key = s0["labels"]["2d"]["key"]
    s0["labels"]["2d"]["key"] = "measured-under-old-code"
    s0["labels"]["2d"]["pairs"] = []
    s0["labels"]["retired-label"] = {"pairs": [], "stage_s": {}, "wall_s": 0}
    first.write_text(json.dumps(s0))
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stdout + res.stderr
    again = json.loads(first.read_text())
    assert set(again["labels"]) == {"2d", "2d-best", "2d-nosmooth", "2d-truth"}
    assert again["labels"]["2d"]["key"] == key
    assert (
        again["labels"]["2d"]["pairs"] == json.loads(both[0])["labels"]["2d"]["pairs"]
    )


def _fake(seed: int, scores: dict[str, dict[str, list[float]]]) -> dict:
    """A seed's results: {label: {query: [IoU per view]}}."""
    labels = {}
    for label, per_q in scores.items():
        pairs = [
            {"view": f"v{k}.jpg", "query": q, "iou": x, "pa": 0.9, "p": x}
            for q, xs in per_q.items()
            for k, x in enumerate(xs)
        ]
        labels[label] = {"pairs": pairs, "stage_s": {"train-male": 10.0}, "wall_s": 1}
    return {"seed": seed, "labels": labels, "hard": {"v1.jpg": True},
            "screen": {"parts": {}}}  # fmt: skip


def test_report_statistics_on_known_results() -> None:
    acc = _bench()
    results = {
        0: _fake(0, {"male": {"A": [0.5, 0.7], "B": [0.0, 0.0]},
                     "oracle": {"A": [0.9, 0.9], "B": [0.05, 0.0]},
                     "langsplat": {"A": [0.4, 0.4], "B": [0.0, 0.0]}}),
        1: _fake(1, {"male": {"A": [0.3, 0.5]},
                     "oracle": {"A": [0.6, 0.6]},
                     "langsplat": {"A": [0.2, 0.2]}}),
    }  # fmt: skip
    summ = acc.summarise(results, ["male", "oracle", "langsplat"])
    # clusters (0, A) 0.6, (0, B) 0.0, (1, A) 0.4: mIoU is their mean
    assert summ["male"]["miou"].mean == pytest.approx((0.6 + 0.0 + 0.4) / 3)
    assert summ["male"]["clusters"] == 3
    # paired differences langsplat − male per cluster: −0.2, 0, −0.2
    assert summ["langsplat"]["diff"].mean == pytest.approx(-0.4 / 3)
    assert summ["langsplat"]["diff"].hi <= 0.0
    # easy / hard: view v1 is hard
    assert summ["male"]["hard"] == pytest.approx((0.7 + 0.0 + 0.5) / 3)
    assert summ["male"]["easy"] == pytest.approx((0.5 + 0.0 + 0.3) / 3)
    bad, total, which = acc.unanswered(results, ["male", "oracle", "langsplat"])
    assert (bad, total, which) == (1, 3, [(0, "B")])
    assert "is at least every variant's mean" in "\n".join(acc._ceiling_lines(summ))


def test_differences_against_another_base() -> None:
    """Rows on truth segments pair against `male-truth`, not `male`;
    Table 4's truth labels are `male-truth` with one render-appearances change."""
    acc = _bench()
    results = {
        0: _fake(0, {"male-truth": {"A": [0.6, 0.6], "B": [0.2, 0.2]},
                     "same-appearance-truth": {"A": [0.5, 0.5], "B": [0.2, 0.2]}}),
    }  # fmt: skip
    summ = acc.summarise(results, ["male-truth", "same-appearance-truth"], "male-truth")
    assert "diff" not in summ["male-truth"]
    assert summ["same-appearance-truth"]["diff"].mean == pytest.approx(-0.05)
    assert "| Δ mIoU vs male-truth " in acc._main_table(summ, "male-truth")[0]
    alone = acc.summarise(results, ["same-appearance-truth"])  # no base: no pairing
    assert "diff" not in alone["same-appearance-truth"]
    for lab, change in (("same-appearance-truth", "targets=same"),
                        ("select-random-truth", "selection=random")):  # fmt: skip
        variant, sets = acc.CHAIN_LABELS[lab]
        assert variant == acc.CHAIN_LABELS["male-truth"][0] == "male"
        assert sets == {**acc.CHAIN_LABELS["male-truth"][1],
                        "render-appearances": [change]}  # fmt: skip
        assert lab in acc.ALL_LABELS and lab not in acc.LABELS
    assert acc._baseline("male-truth") == "langsplat-truth"
    assert acc._baseline("male") == "langsplat"


def test_best_union_is_the_best_subset() -> None:
    """2d-best's union against every subset of segments (small maps)."""
    import itertools

    import numpy as np

    best_union = _bench().best_union
    rng = np.random.default_rng(3)
    for _ in range(20):
        n = int(rng.integers(1, 7))
        labels = rng.integers(-1, n, (9, 11))
        gt = rng.random((9, 11)) < rng.random()
        iou, mask = best_union(labels, gt)
        ids = [k for k in range(n) if (labels == k).any()]
        brute = 0.0
        for r in range(1, len(ids) + 1):
            for sub in itertools.combinations(ids, r):
                m = np.isin(labels, sub)
                union = (m | gt).sum()
                brute = max(brute, (m & gt).sum() / union if union else 0.0)
        assert iou == pytest.approx(brute)
        assert (mask & gt).sum() / max((mask | gt).sum(), 1) == pytest.approx(iou)
        assert not mask[labels < 0].any()


def test_target_labels_and_the_renders_they_log(tmp_path: Path) -> None:
    """Table 4's labels are on request; the report says what the novel
    slots were rendered from; a scene of another stand-in's world is refused."""
    acc = _bench()
    for lab in ("same-appearance-truth", "select-random-truth"):
        assert lab in acc.ALL_LABELS and lab not in acc.LABELS

    def seed(s: int, targets: list[dict]) -> dict:
        renders = {"targets": targets, "psnr_train": 18.0, "psnr_test": 17.0 + s}
        return {"labels": {"male": {"pairs": [], "renders": renders}}}

    night = {"id": "a", "sky": "night", "filter": "none"}
    sepia = {"id": "b", "sky": "day", "filter": "sepia"}
    lines = acc._render_lines({0: seed(0, [night, sepia]), 1: seed(1, [night])},
                              ["male", "langsplat"])  # fmt: skip
    row = next(line for line in lines if line.startswith("| `male`"))
    assert "| 2 | 17.5 dB | night 2, day+sepia 1 |" in row
    assert not any("langsplat" in line for line in lines)
    from ptovs.synthetic import generate_scene

    generate_scene(tmp_path, "tiny", 0, progress=False)
    assert acc._scene(tmp_path, "tiny", 0, 1).name == "tiny_s0"
    with pytest.raises(SystemExit, match="generated for stand-in 1, not 2"):
        acc._scene(tmp_path, "tiny", 0, 2)

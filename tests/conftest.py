"""Shared fixtures: one tiny synthetic scene per test session, CLI helpers."""

from __future__ import annotations

import os
import re
import shutil
from pathlib import Path

import pytest

# System packages (tools/system-deps.sh installs them as root): without them a test
# that needs one is skipped, and the summary names them and the one command that
# installs them; where they are required (CI=true, PTOVS_REQUIRE_SYSTEM_DEPS=1) it
# fails instead, so CI never passes by skipping.
SYSTEM_FIX = "sudo make system-deps"
ROOT_FIX = "sudo make test-slurm"
SLURM_PACKAGES = "slurm-wlm munge slurmdbd mariadb-server"
# the command each package provides (the header's check, as the script's)
SYSTEM_COMMANDS = {"g++": "g++", "chromium": "chromium", "slurmctld": "slurm-wlm",
                   "slurmdbd": "slurmdbd", "munged": "munge",
                   "mariadbd": "mariadb-server"}  # fmt: skip
_TAG = re.compile(r"^\[(system|root): ([^\]]*)\]")


@pytest.fixture(autouse=True, scope="session")
def _runtime_cache(tmp_path_factory: pytest.TempPathFactory):
    """Exported encoders go to the session's own folder, never the user's cache
    (commands run in subprocesses inherit it)."""
    old = os.environ.get("PTOVS_RUNTIME_CACHE")
    os.environ["PTOVS_RUNTIME_CACHE"] = str(tmp_path_factory.mktemp("runtimes"))
    yield
    if old is None:
        os.environ.pop("PTOVS_RUNTIME_CACHE", None)
    else:
        os.environ["PTOVS_RUNTIME_CACHE"] = old


def system_deps_required() -> bool:
    """True in CI (CI=true) or with PTOVS_REQUIRE_SYSTEM_DEPS=1: a missing system
    package fails its tests instead of skipping them."""
    ci = os.environ.get("CI", "").strip().lower() in ("1", "true", "yes")
    return ci or os.environ.get("PTOVS_REQUIRE_SYSTEM_DEPS", "").strip() == "1"


def need_system(packages: str, present: bool, *, module: bool = False) -> None:
    """Skip the test (fail it where they are required) when the system `packages`
    (Debian names, space-separated) are missing; `module`: at module level."""
    if present:
        return
    why = f"[system: {packages}] not installed; install: {SYSTEM_FIX}"
    if system_deps_required():
        pytest.fail(f"{why} (required: CI or PTOVS_REQUIRE_SYSTEM_DEPS=1)",
                    pytrace=False)  # fmt: skip
    pytest.skip(why, allow_module_level=module)


def has_compiler() -> bool:
    """A C++ compiler for the compiled CPU rasterizer ($CXX, c++, g++ or clang++)."""
    names = (os.environ.get("CXX", "c++"), "g++", "clang++")
    return any(shutil.which(c) for c in names)


def missing_system_packages() -> list[str]:
    """The Debian packages of `SYSTEM_COMMANDS` whose command is not on PATH."""
    return list(dict.fromkeys(pkg for cmd, pkg in SYSTEM_COMMANDS.items()
                              if shutil.which(cmd) is None))  # fmt: skip


def pytest_report_header(config):
    missing = missing_system_packages()
    if not missing:
        return None
    then = "their tests fail" if system_deps_required() else "their tests are skipped"
    return (f"system packages missing: {' '.join(missing)}; {then} "
            f"(install: {SYSTEM_FIX})")  # fmt: skip


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    """One line per reason: how many tests were skipped for missing system
    packages (and which), and for not being root, with the command that fixes it."""
    counts: dict[str, int] = {}
    packages: dict[str, None] = {}
    for rep in terminalreporter.stats.get("skipped", []):
        longrepr = getattr(rep, "longrepr", None)
        seq = isinstance(longrepr, tuple | list)  # a list when xdist sent it
        reason = str(longrepr[2]) if seq else str(longrepr or "")
        m = _TAG.search(reason.removeprefix("Skipped: "))
        if m is None:
            continue
        counts[m[1]] = counts.get(m[1], 0) + 1
        if m[1] == "system":
            packages.update(dict.fromkeys(m[2].split()))
    if counts.get("system"):
        terminalreporter.write_line(
            f"{counts['system']} skipped for missing system packages "
            f"({' '.join(packages)}); install them: {SYSTEM_FIX}"
        )
    if counts.get("root"):
        terminalreporter.write_line(
            f"{counts['root']} skipped: they start a single-node Slurm as root; "
            f"run them as root: {ROOT_FIX}"
        )


def pytest_collection_modifyitems(config, items):
    """Under pytest-xdist (`make test` runs two workers), the tests that start the
    one-node Slurm share one worker: its daemons, ports and database are one per
    machine, so two such tests must never run at once."""
    for item in items:
        if item.get_closest_marker("slurm"):
            item.add_marker(pytest.mark.xdist_group("slurm"))


@pytest.fixture(scope="session")
def synth_root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A folder holding the `tiny` synthetic scene (seed 0) in PT-OVS layout."""
    from ptovs.synthetic import generate_scene

    root = tmp_path_factory.mktemp("synth")
    generate_scene(root, preset="tiny", seed=0, progress=False)
    return root


@pytest.fixture(scope="session")
def tiny_scene_dir(synth_root: Path) -> Path:
    """The tiny scene folder (read-only: copy it before changing anything)."""
    return synth_root / "tiny_s0"


@pytest.fixture
def scene_copy(tiny_scene_dir: Path, tmp_path: Path) -> Path:
    """A private, writable copy of the tiny scene (with its labels)."""
    dst = tmp_path / "data"
    shutil.copytree(tiny_scene_dir, dst / tiny_scene_dir.name)
    labels = tiny_scene_dir.parent / "label" / tiny_scene_dir.name
    if labels.is_dir():
        shutil.copytree(labels, dst / "label" / tiny_scene_dir.name)
    return dst / tiny_scene_dir.name


# The tiny chain up to uncertainty, built once per session and copied by the
# modules that need it (each gets its own work dir, so their extra artifacts
# never meet). Short reconstruct, everything else default.
RECON = ["--set=reconstruct.iterations=300", "--set=reconstruct.mask_warmup=100"]


def run_cli(work: Path, *args: str) -> str:
    """`ptovs --work-dir WORK <RECON sets> ARGS` in-process; asserts success."""
    from click.testing import CliRunner

    from ptovs.cli import main

    res = CliRunner().invoke(main, ["--work-dir", str(work), *RECON, *args])
    assert res.exit_code == 0, res.output + repr(res.exception)
    return res.output


@pytest.fixture(scope="session")
def extracted_work(tmp_path_factory: pytest.TempPathFactory, tiny_scene_dir: Path):
    """(work dir, `ptovs extract` output) with reconstruct and extract done on tiny."""
    work = tmp_path_factory.mktemp("extracted")
    run_cli(work, "reconstruct", "--data", str(tiny_scene_dir))
    out = run_cli(work, "extract", "--data", str(tiny_scene_dir))
    return work, out


@pytest.fixture(scope="session")
def trained_work(
    tmp_path_factory: pytest.TempPathFactory, tiny_scene_dir: Path, extracted_work
):
    """(work dir, `ptovs train` output): the extracted tiny chain, then train."""
    work = copy_work(extracted_work[0], tmp_path_factory.mktemp("trained") / "work")
    out = run_cli(work, "train", "--data", str(tiny_scene_dir))
    return work, out


def need_slurm_host(commands: tuple[str, ...]) -> None:
    """Skip unless the test Slurm can start here, root and Debian's packages
    (`need_system`); where they are required (CI), fail instead."""
    need_system(SLURM_PACKAGES, all(shutil.which(x) for x in commands))
    if os.geteuid() != 0:
        why = f"[root: slurm] the single-node Slurm starts its daemons as root: {ROOT_FIX}"
        if system_deps_required():
            pytest.fail(why, pytrace=False)
        pytest.skip(why)


def assert_points_match(ours, theirs, img) -> None:
    """Our point adapter (`ours`, a generator `PointPredictor`) answers three
    points in one batch as the upstream predictor `theirs` answers each alone
    (`theirs.predict`, logits and predicted IoUs); both share one encoder pass."""
    import numpy as np
    import torch

    points = np.array([[5.0, 7.0], [30.5, 12.0], [50.0, 35.0]])
    with torch.inference_mode():
        ours.set_image(img)
        logits, iou = ours.predict(points)
        assert logits.shape == (3, 3, *img.shape[:2]) and iou.shape == (3, 3)
        for i, p in enumerate(points):
            masks, ious, _ = theirs.predict(
                point_coords=p[None], point_labels=np.array([1]),
                multimask_output=True, return_logits=True,
            )  # fmt: skip
            np.testing.assert_allclose(logits[i].numpy(), masks, rtol=1e-4, atol=1e-3)
            np.testing.assert_allclose(iou[i].numpy(), ious, rtol=1e-4, atol=1e-5)


def reference_batched_nms(boxes, scores, idxs, iou_threshold: float):
    """torchvision's `batched_nms` written out (its compiled op does not load on
    our CPU torch), the oracle patched into upstream's generators: greedy by
    descending score, equal scores in input order (its CPU kernel's stable sort),
    a box kept unless a kept box of its category overlaps it by IoU > threshold."""
    import torch

    def iou(a, b) -> float:
        w = min(a[2], b[2]) - max(a[0], b[0])
        h = min(a[3], b[3]) - max(a[1], b[1])
        inter = max(w, 0.0) * max(h, 0.0)
        union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
        return inter / union if union > 0 else 0.0

    b, s, c = boxes.tolist(), scores.tolist(), idxs.tolist()
    keep: list[int] = []
    for i in sorted(range(len(s)), key=lambda i: -s[i]):  # sorted() is stable
        if all(c[i] != c[j] or iou(b[i], b[j]) <= iou_threshold for j in keep):
            keep.append(i)
    return torch.tensor(keep, dtype=torch.int64)


def add_disks(predict, radii: tuple[float, ...], to_pixels):
    """Upstream's batched predict (SAM's `predict_torch`, sam2's `_predict`) with a
    cone of radius `radii[k]` px around each prompt added to output k's logits
    (`to_pixels`: the prompts' model coordinates [N, 2] → pixels of the crop).
    Random weights answer every prompt alike; with this, masks depend on the
    prompt, differ in size by output, and keep the model's texture at their rims.
    Patched into ours and upstream's alike, it tests the generator, not SAM."""
    import torch

    def wrapped(points, labels, *args, **kwargs):
        masks, iou, low = predict(points, labels, *args, **kwargs)
        h, w = masks.shape[-2:]
        p = to_pixels(points[:, 0, :].float())
        yy, xx = torch.meshgrid(
            torch.arange(h) + 0.5, torch.arange(w) + 0.5, indexing="ij"
        )
        d = torch.hypot(xx - p[:, 0, None, None], yy - p[:, 1, None, None])
        cones = torch.stack([(r - d) * 0.25 for r in radii], 1)
        return masks + cones.to(masks.dtype), iou, low

    return wrapped


def one_output(predict, outputs: tuple[int, ...], by_area: bool, threshold: float):
    """Upstream's batched predict (SAM's `predict_torch`, sam2's `_predict`)
    answering with only `outputs` of its three multimask outputs; with `by_area`,
    each prompt's three sorted by mask area first (equal areas in output order)."""
    import torch

    a, b = outputs[0], outputs[-1] + 1

    def wrapped(*args, **kwargs):
        masks, iou, low = predict(*args, **kwargs)
        if by_area:
            for n in range(len(masks)):
                area = (masks[n] > threshold).flatten(1).sum(1).tolist()
                order = torch.tensor(sorted(range(3), key=lambda k: area[k]))
                masks[n], iou[n], low[n] = masks[n][order], iou[n][order], low[n][order]
        return masks[:, a:b], iou[:, a:b], low[:, a:b]

    return wrapped


def langsplat_paint(masks: list, iou: list, stability: list, shape):
    """LangSplat's `masks_update` and `mask2segmap` on one level's masks (its
    score is stability × predicted IoU in float64); the labels renumbered to the
    visible masks as ptovs does. Returns (labels [H, W] int32, visible masks)."""
    import numpy as np
    import torch

    from ptovs.segment.masks import mask_nms_reference

    if not masks:
        return np.full(shape, -1, np.int32), []
    scores = torch.from_numpy(np.asarray(stability) * np.asarray(iou))
    keep = mask_nms_reference(torch.from_numpy(np.stack(masks)), scores).tolist()
    kept = [m for i, m in enumerate(masks) if i in keep]  # LangSplat's `filter`
    raw = np.full(shape, -1, np.int64)
    for i, m in enumerate(kept):
        raw[m] = i
    visible = np.unique(raw[raw >= 0])
    lut = np.full(len(kept) + 1, -1, np.int32)
    lut[visible] = np.arange(len(visible))
    return lut[raw], [kept[i] for i in visible]


def langsplat_paint_anns(anns: list[dict], shape):
    """`langsplat_paint` of upstream's annotations (`generate()` records)."""
    return langsplat_paint(
        [a["segmentation"] for a in anns],
        [a["predicted_iou"] for a in anns],
        [a["stability_score"] for a in anns],
        shape,
    )


def assert_same_masks(ours: dict, anns: list[dict]) -> None:
    """Our candidates of one level (`MaskGenerator.candidates`) are upstream's
    annotations (`generate()` records), mask for mask, in the same order."""
    import numpy as np

    assert len(ours["masks"]) == len(anns)
    for k, ann in enumerate(anns):
        assert np.array_equal(ours["masks"][k].numpy(), ann["segmentation"]), k
    np.testing.assert_allclose(
        ours["iou"].numpy(), [a["predicted_iou"] for a in anns], rtol=1e-6
    )
    np.testing.assert_allclose(
        ours["stability"].numpy(), [a["stability_score"] for a in anns], rtol=1e-6
    )


def copy_work(src: Path, dst: Path) -> Path:
    """A private copy of a work dir (artifacts, no locks)."""
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("*.lock"))
    return dst


def bench_module(name: str):
    """Import bench/<name>.py (a script, not a package) with bench/ on sys.path, as
    its neighbours import each other; yields the module (a fixture's body)."""
    import importlib.util
    import sys

    bench = Path(__file__).resolve().parents[1] / "bench"
    sys.path.insert(0, str(bench))
    try:
        spec = importlib.util.spec_from_file_location(
            f"bench_{name}", bench / f"{name}.py"
        )
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
        yield mod
    finally:
        sys.path.remove(str(bench))


@pytest.fixture
def toy_commands():
    """The toy stages (tests/toy_stages.py) as `ptovs` subcommands."""
    import toy_stages
    from ptovs.cli import main as cli

    cli.add_command(toy_stages.views_command)
    cli.add_command(toy_stages.sum_command)
    yield

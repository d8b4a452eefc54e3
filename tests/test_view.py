"""`ptovs view` (issue 25): the session without a page, the viser page driven from
Python, and the page in a real browser (Debian's chromium through Playwright)."""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from conftest import RECON, copy_work
from ptovs.cli import main
from ptovs.errors import InputError
from ptovs.field.ply import read_ply

PHRASE = "Brick Facade"  # the tiny scene's wall: what the select tests use too


@pytest.fixture(scope="module")
def view_work(tmp_path_factory, trained_work):
    return copy_work(trained_work[0], tmp_path_factory.mktemp("view") / "work")


def _chain(work: Path, scene_dir: Path):
    from ptovs.config import parse_sets
    from ptovs.stage import Chain, RunContext, resolve_scene

    sets = parse_sets([r.split("=", 1)[1] for r in RECON])
    ctx = RunContext(work, sets, False)
    return Chain(ctx, resolve_scene(ctx, None, scene_dir))


@pytest.fixture(scope="module")
def session(view_work, tiny_scene_dir, tmp_path_factory):
    from ptovs.apps.view import ViewSession

    s = ViewSession(_chain(view_work, tiny_scene_dir), tmp_path_factory.mktemp("x"))
    yield s
    s.close()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# ------------------------------------------------------------------ session --


def test_session_selects_what_select_selects(session, view_work, tiny_scene_dir):
    from ptovs.apps import close_inputs
    from ptovs.apps.select import select_gaussians
    from ptovs.apps.view import HIGHLIGHT

    answer = session.query(PHRASE)
    sel, _, inputs = select_gaussians(_chain(view_work, tiny_scene_dir), PHRASE)
    close_inputs(inputs)
    assert np.array_equal(answer.mask, sel.mask) and answer.selected > 0
    assert answer.level == str(session.querier.levels[sel.level])
    assert answer.score == pytest.approx(sel.score)
    assert f"{answer.selected:,} of {answer.total:,}" in answer.line()
    rgb = session.colors()
    assert np.all(rgb[answer.mask] == HIGHLIGHT)
    base = session.baked(session.appearance)[0]
    assert np.array_equal(rgb[~answer.mask], base[~answer.mask])
    # the decoder table is reused: asking again adds no phrase
    n = len(session.querier.phrases)
    session.query(PHRASE)
    assert len(session.querier.phrases) == n


def test_session_appearances_bake_colours_and_sky(session):
    assert len(session.appearances) == 1 + len(session.photos) > 2
    rgb0, sky0 = session.baked(session.appearances[0])
    rgb1, sky1 = session.baked(session.appearances[1])
    for a in (rgb0, sky0, rgb1, sky1):
        assert a.dtype == np.float32 and np.isfinite(a).all()
        assert a.min() >= 0 and a.max() <= 1
    assert rgb0.shape == (len(session.centers), 3)
    assert not np.allclose(rgb0, rgb1)  # a photo's appearance is not the mean
    assert session.baked(session.appearances[1])[0] is rgb1  # baked once
    with pytest.raises(InputError, match="no appearance"):
        session.baked("nope.png")
    # covariances are symmetric and positive semi-definite
    cov = session.covariances.astype(np.float64)
    assert np.array_equal(cov, cov.transpose(0, 2, 1))
    assert np.linalg.eigvalsh(cov).min() > -1e-9


def test_session_heatmap_export_and_refusals(session, tmp_path):
    from ptovs.raster import Camera

    view = session.views[0]
    cam = Camera.from_view(view)
    session.query(PHRASE)
    heat = session.heatmap(cam)
    assert heat.shape == (view.height, view.width, 3) and heat.dtype == np.uint8
    assert heat.std() > 1  # not a constant image
    session.out_dir = tmp_path
    p1, p2 = session.export(), session.export()
    assert p1 != p2 and p1.exists() and p2.exists()  # never overwritten
    ply = read_ply(p1)
    assert len(ply["means"]) == session.answer.selected
    assert np.array_equal(ply["means"], session.centers[session.answer.mask])
    with pytest.raises(InputError, match="vocabulary"):
        session.query("Flying Spaghetti")
    with pytest.raises(InputError, match="empty"):
        session.query("  ")
    session.clear()
    with pytest.raises(InputError, match="nothing is selected"):
        session.export()
    plain = session.heatmap(cam)
    assert plain.shape == heat.shape
    near = session.nearest_view(
        np.asarray(torch.linalg.inv(cam.cam_from_world)[:3, 3], float)
    )
    assert near.name == view.name
    tour = session.tour(5)
    assert len(tour) == 5 and all(c.width == 320 for c in tour)


def test_phrase_decoder_grows_its_table_exactly():
    from ptovs.field.relevancy import PhraseDecoder

    g = torch.Generator().manual_seed(0)
    w = torch.randn(3, 8, generator=g)

    def decode(c):
        return torch.nn.functional.normalize(torch.tanh(c @ w), dim=-1)

    p = torch.nn.functional.normalize(torch.randn(5, 8, generator=g), dim=-1)
    grown = PhraseDecoder(decode, p[:3], size=9)
    _ = grown.table  # built before the new phrases come
    grown.add_phrases(p[3:])
    full = PhraseDecoder(decode, p, size=9)
    assert torch.allclose(grown.table, full.table, atol=1e-6)
    assert torch.equal(grown.phrases, full.phrases)


def test_covariances_against_float64_and_degenerate_quaternions():
    from ptovs.raster import Gaussians

    g = torch.Generator().manual_seed(1)
    q = torch.randn(6, 4, generator=g, dtype=torch.float64)
    q[0] = 0  # a zero quaternion is the identity
    s = torch.rand(6, 3, generator=g, dtype=torch.float64) + 0.01
    s[1] = 0  # a flat (degenerate) Gaussian
    gs = Gaussians(torch.zeros(6, 3, dtype=torch.float64), q, s, torch.ones(6))
    cov = gs.covariances()
    for i in range(6):
        if i == 0:
            rot = np.eye(3)
        else:
            w, x, y, z = (q[i] / q[i].norm()).tolist()
            rot = np.array([
                [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
            ])  # fmt: skip
        want = rot @ np.diag(s[i].numpy() ** 2) @ rot.T
        np.testing.assert_allclose(cov[i].numpy(), want, atol=1e-12)
    assert torch.all(cov[1] == 0)


# -------------------------------------------------------- refusals (no page) --


def test_port_in_use_is_a_clear_error():
    from ptovs.apps.view import check_port

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        with pytest.raises(InputError, match=f"port {port}.*--port"):
            check_port("127.0.0.1", port)


def test_view_cli_refusals_name_the_fix(tmp_path, tiny_scene_dir, view_work):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        res = CliRunner().invoke(
            main,
            ["--work-dir", str(view_work), *RECON, "view", "--data",
             str(tiny_scene_dir), "--port", str(port)],
        )  # fmt: skip
    assert (
        res.exit_code == 1 and f"port {port}" in res.output and "--port" in res.output
    )
    assert "Traceback" not in res.output
    # a work dir without the language field: the command to run, no training
    res = CliRunner().invoke(
        main,
        ["--work-dir", str(tmp_path / "empty"), *RECON, "view", "--data",
         str(tiny_scene_dir), "--port", str(_free_port())],
    )  # fmt: skip
    assert res.exit_code == 1, res.output
    assert "no trained language field" in res.output and "train-male" in res.output
    assert not (tmp_path / "empty" / tiny_scene_dir.name / "reconstruct").exists()


# ------------------------------------------------------------ page (viser) --


def _need_viser() -> None:
    """The page tests run wherever the suite runs (.ci/run installs viser): a
    missing viser fails them with the fix rather than skipping them."""
    try:
        import viser  # noqa: F401
    except ImportError:
        pytest.fail("viser is not installed: make setup (or .ci/run) installs it")


@pytest.fixture(scope="module")
def page(session):
    _need_viser()
    from ptovs.apps.view import Page

    p = Page(session, "127.0.0.1", _free_port(), heat_width=96)
    yield p
    p.stop()


def test_page_handles_drive_the_session(page, session, tmp_path):
    from ptovs.apps.view import HIGHLIGHT, NEUTRAL

    # set the text and press the button through viser's handles (their callbacks
    # run as a browser's would, without a client)
    page.text.value = PHRASE
    page.ask.value = True
    answer = session.answer
    assert answer is not None and answer.selected > 0 and answer.text == PHRASE
    assert f"{answer.selected:,} of" in page.status.content
    # the splats on the page carry the highlight exactly where the selection is
    rgba = np.ascontiguousarray(page.splats.buffer[:, 7]).view(np.uint8).reshape(-1, 4)
    magenta = (
        (rgba[:, 0] == round(255 * HIGHLIGHT[0]))
        & (rgba[:, 1] == 0)
        & (rgba[:, 2] == 255)
    )
    assert np.array_equal(magenta, answer.mask)
    session.out_dir = tmp_path
    page.export.value = True
    (path,) = tmp_path.glob("*.ply")
    assert str(path) in page.status.content
    assert len(read_ply(path)["means"]) == answer.selected
    page.text.value = "Flying Spaghetti"
    page.ask.value = True  # an unknown phrase: a message in the page, no crash
    assert "⚠" in page.status.content and "vocabulary" in page.status.content
    assert session.answer is answer  # the last good answer stays
    page.appearance.value = session.appearances[1]
    assert session.appearance == session.appearances[1]
    page.appearance.value = NEUTRAL
    page.nearest.value = True  # no browser connected: said in the page
    assert "No browser" in page.status.content
    page.clear.value = True
    assert session.answer is None


def test_page_serves_http(page):
    port = page.server.get_port()
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=10) as r:
        body = r.read().decode()
    assert r.status == 200 and "<html" in body.lower()


# ---------------------------------------------------------------- browser --

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


def test_page_in_a_real_browser(session, tmp_path):
    """Loads the page in Debian's chromium, types the phrase, presses Highlight,
    and checks the screenshot: not blank, and the highlight colour is there."""
    _need_viser()
    if CHROMIUM is None:
        pytest.fail("no chromium on PATH: apt-get install chromium (.ci/run does)")
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        pytest.fail(
            "playwright is not installed: pip install playwright (.ci/run does)"
        )
    import cv2

    from ptovs.apps.view import NEUTRAL, Page

    session.clear()
    session.appearance = NEUTRAL
    port = _free_port()
    page = Page(session, "127.0.0.1", port, heat_width=96)
    # PTOVS_VIEW_SCREENSHOT=docs/img/view.png keeps the picture (the README's)
    shot = Path(os.environ.get("PTOVS_VIEW_SCREENSHOT") or tmp_path / "view.png")
    try:
        with sync_playwright() as pw:
            try:
                browser = pw.chromium.launch(
                    executable_path=CHROMIUM,
                    args=["--no-sandbox", "--use-gl=angle", "--use-angle=swiftshader",
                          "--enable-unsafe-swiftshader"],
                )  # fmt: skip
            except Exception as exc:  # noqa: BLE001
                pytest.fail(f"chromium did not start: {exc}")
            tab = browser.new_page(viewport={"width": 1000, "height": 700})
            tab.goto(f"http://127.0.0.1:{port}/", wait_until="load")
            # viser's label and input ids differ: find the input in the label's row
            box = tab.locator(
                "xpath=//label[text()='Phrase']/ancestor::div"
                "[contains(@class, 'mantine-Flex-root')][1]//input"
            )
            box.wait_for(timeout=60_000)
            box.fill(PHRASE)
            tab.get_by_role("button", name="Highlight").click()
            deadline = time.time() + 60
            while session.answer is None and time.time() < deadline:
                time.sleep(0.2)
            assert session.answer is not None, "the click never reached the server"
            tab.get_by_text(f"{session.answer.selected:,} of").wait_for(timeout=30_000)
            time.sleep(3)  # the splats' sort and draw
            shot.parent.mkdir(exist_ok=True)
            tab.screenshot(path=str(shot))
            browser.close()
        # closing the browser leaves the server serving
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=10) as r:
            assert r.status == 200
    finally:
        page.stop()
    img = cv2.cvtColor(cv2.imread(str(shot)), cv2.COLOR_BGR2RGB).astype(int)
    assert img.std() > 10, "a blank page"
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    magenta = (r > 180) & (b > 180) & (g < 90)
    assert magenta.sum() > 200, f"no highlight in the screenshot ({magenta.sum()} px)"


def test_view_command_prints_the_url_and_stops_on_ctrl_c(view_work, tiny_scene_dir):
    _need_viser()
    import signal

    port = _free_port()
    cmd = [sys.executable, "-m", "ptovs", "--work-dir", str(view_work), *RECON,
           "view", "--data", str(tiny_scene_dir), "--port", str(port)]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)  # fmt: skip
    try:
        first = ""
        deadline = time.time() + 120
        while not first.startswith("view ") and time.time() < deadline:
            first = proc.stdout.readline()
            assert first or proc.poll() is None, "ptovs view ended early"
        assert f"http://127.0.0.1:{port}" in first and "Ctrl-C" in first, first
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=10) as r:
            assert r.status == 200
        # bound to the loopback only: the default host is not the network's
        assert "0.0.0.0" not in first
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            out, _ = proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()  # never leave a server behind
            out, _ = proc.communicate()
            pytest.fail(f"ptovs view did not stop on SIGINT within 30 s:\n{out}")
    assert proc.returncode == 0, out
    assert "view: stopped" in out and "Traceback" not in out


def test_view_help_lists_the_options():
    res = subprocess.run(
        [sys.executable, "-m", "ptovs", "view", "--help"],
        capture_output=True,
        text=True,
    )
    assert res.returncode == 0
    for opt in ("--host", "--port", "127.0.0.1", "8080", "--out-dir"):
        assert opt in res.stdout

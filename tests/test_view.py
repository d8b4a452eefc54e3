"""`ptovs view`: the session without a page, the viser page driven from
Python, and the page in a real browser (Debian's chromium through Playwright)."""

from __future__ import annotations

import os
import re
import shutil
import socket
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from conftest import RECON, copy_work, need_system
from ptovs.cli import main
from ptovs.errors import InputError
from ptovs.field.ply import read_ply

PHRASE = "Brick Facade"  # the tiny scene's wall: what the select tests use too


@pytest.fixture(scope="module")
def view_work(tmp_path_factory, trained_work):
    return copy_work(trained_work[0], tmp_path_factory.mktemp("view") / "work")


def _chain(work: Path, scene_dir: Path):
    from ptovs.chain import Chain, RunContext
    from ptovs.config import parse_sets
    from ptovs.locate import resolve_scene

    sets = parse_sets([r.split("=", 1)[1] for r in RECON])
    ctx = RunContext(work, sets, False)
    return Chain(ctx, resolve_scene(ctx, None, scene_dir))


@pytest.fixture(scope="module")
def session(view_work, tiny_scene_dir, tmp_path_factory):
    from ptovs.apps.view_session import ViewSession

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
    from ptovs.apps.view import HIGHLIGHT, NEUTRAL

    answer = session.query(PHRASE)
    sel, _, inputs = select_gaussians(_chain(view_work, tiny_scene_dir), PHRASE)
    close_inputs(inputs)
    assert np.array_equal(answer.mask, sel.mask) and answer.selected > 0
    assert answer.level == str(session.querier.levels[sel.level])
    assert answer.score == pytest.approx(sel.score)
    assert f"{answer.selected:,} of {answer.total:,}" in answer.line()
    rgb = session.colors(NEUTRAL, answer)
    assert np.all(rgb[answer.mask] == HIGHLIGHT)
    base = session.baked(NEUTRAL)[0]
    assert np.array_equal(rgb[~answer.mask], base[~answer.mask])
    # the decoder table is reused: asking again adds no phrase; another casing is
    # the same answer (the cache is keyed by the case-folded phrase)
    n = len(session.querier.phrases)
    assert session.query(PHRASE) is answer
    assert session.query(f"  {PHRASE.upper()} ") is answer
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
    from ptovs.apps.view_session import MAX_PHRASE, NEUTRAL
    from ptovs.raster import Camera

    view = session.views[0]
    cam = Camera.from_view(view)
    answer = session.query(PHRASE)
    heat = session.heatmap(cam, NEUTRAL, answer)
    assert heat.shape == (view.height, view.width, 3) and heat.dtype == np.uint8
    assert heat.std() > 1  # not a constant image
    session.out_dir = tmp_path
    p1, p2 = session.export(answer, NEUTRAL), session.export(answer, NEUTRAL)
    assert p1 != p2 and p1.exists() and p2.exists()  # never overwritten
    ply = read_ply(p1)
    assert len(ply["means"]) == answer.selected
    assert np.array_equal(ply["means"], session.centers[answer.mask])
    with pytest.raises(InputError, match="vocabulary"):
        session.query("Flying Spaghetti")
    for empty in ("  ", "\n\t", "\x00\x07"):
        with pytest.raises(InputError, match="empty"):
            session.query(empty)
    with pytest.raises(InputError, match=f"at most {MAX_PHRASE}"):
        session.query("x" * (MAX_PHRASE + 1))
    for not_text in (None, 3, ["Brick Facade"], {"a": 1}):
        with pytest.raises(InputError, match="must be text"):
            session.query(not_text)
    with pytest.raises(InputError, match="nothing is selected"):
        session.export(None, NEUTRAL)
    with pytest.raises(InputError, match="no appearance"):
        session.export(answer, "../../etc/passwd")
    plain = session.heatmap(cam, NEUTRAL, None)
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
    # a host beyond the loopback: refused without --allow-remote, before any work
    for host in ("0.0.0.0", "::", "192.0.2.7"):
        res = CliRunner().invoke(
            main,
            ["--work-dir", str(view_work), *RECON, "view", "--data",
             str(tiny_scene_dir), "--host", host, "--port", str(_free_port())],
        )  # fmt: skip
        assert res.exit_code == 1 and "--allow-remote" in res.output, res.output
        assert "Traceback" not in res.output
    # with it, a warning naming what is exposed (this address cannot be bound here,
    # so the command then stops at the port check)
    res = CliRunner().invoke(
        main,
        ["--work-dir", str(view_work), *RECON, "view", "--data", str(tiny_scene_dir),
         "--host", "192.0.2.7", "--allow-remote", "--port", str(_free_port())],
    )  # fmt: skip
    assert "WARNING" in res.output and "every machine" in res.output, res.output
    assert res.exit_code == 1 and "--port" in res.output


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


class PageClient:
    """A websocket client that speaks viser's protocol as the page does (or as an
    attacker would): it opens the page's socket, sends a camera, and keeps what
    the server sends in `messages` (read by a thread, so the server never waits)."""

    def __init__(self, url: str, origin: str | None = "same", path: str | None = None):
        import viser
        from websockets.sync.client import connect

        http_url = url.rstrip("/")
        ws_url = http_url.replace("http://", "ws://")
        if path is not None:
            ws_url = ws_url.rsplit("/", 1)[0] + path
        if origin == "same":
            origin = http_url.rsplit("/", 1)[0]
        self.ws = connect(ws_url, origin=origin, max_size=None, open_timeout=10,
                          subprotocols=[f"viser-v{viser.__version__}"])  # fmt: skip
        self.messages: list[dict] = []
        self.closed = threading.Event()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        import msgspec

        try:
            for raw in self.ws:
                self.messages.extend(msgspec.msgpack.decode(raw)["messages"])
        except Exception:  # noqa: BLE001 - closed, either side
            pass
        self.closed.set()

    def send(self, message) -> None:
        import msgspec

        self.ws.send(msgspec.msgpack.encode(message.as_serializable_dict()))

    def send_raw(self, data) -> None:
        self.ws.send(data)

    def camera(self, **kw) -> None:
        from viser import _messages

        base = dict(wxyz=(1.0, 0.0, 0.0, 0.0), position=(0.0, 0.0, -3.0), fov=1.0,
                    near=0.01, far=100.0, image_height=480, image_width=640,
                    look_at=(0.0, 0.0, 0.0), up_direction=(0.0, -1.0, 0.0))  # fmt: skip
        base.update(kw)
        self.send(_messages.ViewerCameraMessage(**base))

    def set(self, handle, value) -> None:
        """A control's new value, as the page sends it (a button: True)."""
        from viser import _messages

        self.send(_messages.GuiUpdateMessage(handle._impl.uuid, {"value": value}))

    def close(self) -> None:
        self.ws.close()


def _wait(cond, timeout: float = 60.0, what: str = "") -> None:
    deadline = time.time() + timeout
    while not cond():
        assert time.time() < deadline, f"timed out waiting for {what}"
        time.sleep(0.05)


@pytest.fixture
def client(page):
    c = PageClient(page.url)
    c.camera()
    panel = _wait_panel(page, c)
    yield c, panel
    c.close()
    _wait(lambda: c.closed.is_set(), what="the client to close")


def _wait_panel(page, c):
    before = set(page.panels)
    deadline = time.time() + 60
    while time.time() < deadline:
        new = set(page.panels) - before
        if new:
            return page.panels[new.pop()]
        if not before and page.panels:
            return next(iter(page.panels.values()))
        time.sleep(0.05)
    raise AssertionError("no panel for the client")


def test_page_handles_drive_the_session(page, session, client, tmp_path):
    from ptovs.apps.view import HIGHLIGHT, NEUTRAL

    c, panel = client
    # type the phrase and press the button as the page does (messages over the
    # websocket), then read the panel's state and what the server sent back
    c.set(panel.text, PHRASE)
    c.set(panel.ask, True)
    _wait(lambda: panel.state.answer is not None, what="the answer")
    answer = panel.state.answer
    assert answer.selected > 0 and answer.text == PHRASE
    _wait(lambda: f"{answer.selected:,} of" in panel.status.content, what="status")
    # the press's handler ends after the status (it redraws); a press before then
    # is refused as "still working" (a busy machine shows it)
    _wait(lambda: not panel.busy, what="the first request to end")
    # the splats on the page carry the highlight exactly where the selection is
    rgba = np.ascontiguousarray(panel.splats.buffer[:, 7]).view(np.uint8).reshape(-1, 4)
    magenta = (
        (rgba[:, 0] == round(255 * HIGHLIGHT[0]))
        & (rgba[:, 1] == 0)
        & (rgba[:, 2] == 255)
    )
    assert np.array_equal(magenta, answer.mask)
    session.out_dir = tmp_path
    panel.export_selection()
    (path,) = tmp_path.glob("*.ply")
    # the status names the file, never the server's folders
    assert path.name.replace("-", "&#45;").replace(".", "&#46;") in panel.status.content
    assert str(tmp_path) not in panel.status.content
    assert len(read_ply(path)["means"]) == answer.selected
    panel.ask_phrase("Flying Spaghetti")  # unknown: a message in the page, no crash
    assert "⚠" in panel.status.content and "vocabulary" in panel.status.content
    assert panel.state.answer is answer  # the last good answer stays
    panel.set_appearance(session.appearances[1])
    assert panel.state.appearance == session.appearances[1]
    panel.set_appearance(NEUTRAL)
    panel.go_nearest()
    assert "At photo" in panel.status.content
    panel.clear_phrase()
    assert panel.state.answer is None


def test_page_serves_http(page):
    with urllib.request.urlopen(page.url, timeout=10) as r:
        body = r.read().decode()
    assert r.status == 200 and "<html" in body.lower()
    # without the token: nothing
    root = page.url.rsplit("/", 2)[0] + "/"
    with pytest.raises(urllib.error.HTTPError) as err:
        urllib.request.urlopen(root, timeout=10)
    assert err.value.code == 404


def test_a_hostile_client_leaves_the_page_serving_others(page, session, client):
    """Wrong origin, no token, the share tunnel, uploads, oversized, malformed and
    foreign messages, markup in a phrase: each is refused or closes the attacker's
    own connection, and the good client's page goes on answering."""
    from viser import _messages

    from ptovs.apps.view import NEUTRAL

    good, panel = client
    from websockets.exceptions import InvalidStatus

    for kw in ({"origin": "http://attacker.example"}, {"origin": None},
               {"path": "/"}, {"path": "/nottoken"}):  # fmt: skip
        with pytest.raises(InvalidStatus):
            PageClient(page.url, **kw)
    refused = page.guard.refusals

    def attacker(*msgs, raw=None, closes=True):
        bad = PageClient(page.url)
        bad.camera()
        bad_panel = _wait_panel(page, bad)
        for m in msgs:
            bad.send(m)
        if raw is not None:
            bad.send_raw(raw)
        if closes:
            _wait(lambda: bad.closed.is_set(), 30, "the attacker to be closed")
        else:
            time.sleep(0.5)
            bad.close()
        _wait(lambda: bad_panel.client.client_id not in page.panels, 30, "clean-up")
        return bad_panel

    # dropped, the connection kept: the share tunnel and uploads
    attacker(_messages.ShareUrlRequest(),
             _messages.FileTransferStartUpload(panel.text._impl.uuid, "t", "f",
                                               "text/plain", 1, 10),
             _messages.FileTransferPart(panel.text._impl.uuid, "t", 0, b"x" * 1000),
             closes=False)  # fmt: skip
    assert getattr(page.server, "_share_tunnel", None) is None
    # closed: another client's control, a control's other properties, garbage
    attacker(_messages.GuiUpdateMessage(panel.export._impl.uuid, {"disabled": True}))
    attacker(raw=b"\x93\x01\x02")  # msgpack, not a message
    attacker(raw=b"\xc1")  # not msgpack
    attacker(raw="text frame")
    attacker(raw=b"\x00" * (200 * 1024))  # over the message limit
    assert page.guard.refusals >= refused + 6
    # a foreign control id changes nothing; a foreign dropdown value is refused in
    # the attacker's own page and its state stays
    bad_panel = attacker(
        _messages.GuiUpdateMessage(panel.appearance._impl.uuid, {"value": "x"}),
        closes=False,
    )
    assert panel.state.appearance == NEUTRAL and panel.export.disabled is False
    bad = PageClient(page.url)
    bad.camera()
    bad_panel = _wait_panel(page, bad)
    bad.set(bad_panel.appearance, "../../etc/passwd")
    _wait(lambda: "no appearance" in bad_panel.status.content, 30, "the refusal")
    assert bad_panel.state.appearance == NEUTRAL
    # markup and MDX in a phrase come back as plain characters, never as markup
    bad.set(bad_panel.text, "{window.pwned=1}<img src=x onerror=alert(1)>**b**")
    bad.set(bad_panel.ask, True)
    _wait(lambda: "vocabulary" in bad_panel.status.content, 30, "the refusal")
    for ch in "{}<>*":
        assert ch not in bad_panel.status.content.replace("**⚠", "").split("⚠", 1)[1]
    bad.set(bad_panel.text, "x" * 5000)
    bad.set(bad_panel.ask, True)
    _wait(lambda: "at most" in bad_panel.status.content, 30, "the length refusal")
    bad.close()
    # the heatmap's size is the server's, whatever aspect a page claims
    tall = PageClient(page.url)
    tall.camera(image_height=16384, image_width=1)
    tall_panel = _wait_panel(page, tall)
    _wait(lambda: tall_panel.client.camera.image_height == 16384, 30, "the camera")
    tall_panel.refresh_heatmap()
    h, w = tall_panel.heat.image.shape[:2]
    assert w == page.heat_width and h <= 4 * w
    tall.close()
    flat = PageClient(page.url)  # a zero-sized canvas: a page all the same
    flat.camera(image_height=0, image_width=0)
    flat_panel = _wait_panel(page, flat)
    assert flat_panel.heat.image.shape[1] == page.heat_width
    flat.close()
    # the good client still works, through its own page
    good.set(panel.text, PHRASE)
    good.set(panel.ask, True)
    _wait(lambda: panel.state.answer is not None, 60, "the good client's answer")
    assert panel.state.answer.selected > 0
    with urllib.request.urlopen(page.url, timeout=10) as r:
        assert r.status == 200
    assert not good.closed.is_set()


def test_exports_are_capped_per_page(page, session, client, tmp_path, monkeypatch):
    from ptovs.apps import view

    c, panel = client
    session.out_dir = tmp_path
    monkeypatch.setattr(view, "MAX_EXPORTS", 2)
    panel.ask_phrase(PHRASE)
    panel.export_selection()
    panel.export_selection()
    panel.export_selection()
    assert "limit" in panel.status.content
    assert len(list(tmp_path.glob("*.ply"))) == 2


def test_phrases_and_answers_stay_bounded(
    view_work, tiny_scene_dir, tmp_path, monkeypatch
):
    """Each new phrase costs decoder rows and tables: the session keeps at most
    EXTRA_PHRASES beyond its own and ANSWERS answers, and an answer whose phrase
    was forgotten still draws its heatmap."""
    from ptovs.apps import view_session
    from ptovs.apps.view_session import NEUTRAL, ViewSession
    from ptovs.raster import Camera

    s = ViewSession(_chain(view_work, tiny_scene_dir), tmp_path)
    try:
        q = s.querier
        # the stand-in refuses phrases outside its vocabulary; here it takes any
        # (as OpenCLIP does), so phrases can pile up
        monkeypatch.setattr(q.encoder, "knows", lambda p: True)
        # small bounds (each new phrase decodes a table, ~1.7 s here): six phrases
        # fill the querier twice over and evict answers three times
        monkeypatch.setattr(view_session, "EXTRA_PHRASES", 2)
        monkeypatch.setattr(view_session, "ANSWERS", 3)
        base, rows = q.base, q.decoder.phrases.shape[0]
        first = s.query("phrase 0")
        held = []
        for i in range(1, 6):
            s.query(f"phrase {i}")
            held.append(len(q.phrases) - base)
            assert 0 < held[-1] <= 2
            assert q.decoder.phrases.shape[0] == len(q.phrases)
            assert len(s._answers) <= 3
        assert max(held) == 2  # it did hold more than one beyond its own
        assert rows == base
        assert "phrase 0" not in q.index and "phrase 0" not in s._answers
        heat = s.heatmap(Camera.from_view(s.views[0]), NEUTRAL, first)
        assert heat.dtype == np.uint8 and heat.std() > 0
        q.truncate(0)  # never below the querier's own phrases
        assert len(q.phrases) == base == q.decoder.phrases.shape[0]
    finally:
        s.close()


# ---------------------------------------------------------------- browser --

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


def test_page_in_a_real_browser(session, tmp_path):
    """Loads the page in Debian's chromium, types the phrase, presses Highlight,
    and checks the screenshot: not blank, and the highlight colour is there."""
    _need_viser()
    need_system("chromium", CHROMIUM is not None)
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        pytest.fail(
            "playwright is not installed: pip install playwright (.ci/run does)"
        )
    import cv2

    from ptovs.apps.view import Page

    port = _free_port()
    page = Page(session, "127.0.0.1", port, heat_width=96)
    # PTOVS_VIEW_SCREENSHOT=PATH keeps the picture
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
            missing = []  # every file the page asked for and did not get
            tab.on("response", lambda r: r.status >= 400 and missing.append(r.url))
            tab.goto(page.url, wait_until="load")
            # viser's label and input ids differ: find the input in the label's row
            box = tab.locator(
                "xpath=//label[text()='Phrase']/ancestor::div"
                "[contains(@class, 'mantine-Flex-root')][1]//input"
            )
            box.wait_for(timeout=60_000)
            panel = page.panel()
            # markup and an MDX expression in a phrase: shown as typed, never run
            evil = "{window.pwned=1}<b>x</b>"
            box.fill(evil)
            tab.get_by_role("button", name="Highlight").click()
            tab.get_by_text("vocabulary", exact=False).wait_for(timeout=30_000)
            assert tab.evaluate("window.pwned") is None
            assert tab.get_by_text(evil, exact=False).count() >= 1
            box.fill(PHRASE)
            tab.get_by_role("button", name="Highlight").click()
            deadline = time.time() + 60
            while panel.state.answer is None and time.time() < deadline:
                time.sleep(0.2)
            answer = panel.state.answer
            assert answer is not None, "the click never reached the server"
            tab.get_by_text(f"{answer.selected:,} of").wait_for(timeout=30_000)
            time.sleep(3)  # the splats' sort and draw
            shot.parent.mkdir(exist_ok=True)
            tab.screenshot(path=str(shot))
            # no share button, and nothing the page needs is refused
            assert tab.get_by_role("button", name="Share").count() == 0
            assert not missing, missing
            browser.close()
        # closing the browser leaves the server serving
        with urllib.request.urlopen(page.url, timeout=10) as r:
            assert r.status == 200
    finally:
        page.stop()
    img = cv2.cvtColor(cv2.imread(str(shot)), cv2.COLOR_BGR2RGB).astype(int)
    assert img.std() > 10, "a blank page"
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    magenta = (r > 180) & (b > 180) & (g < 90)
    assert magenta.sum() > 200, f"no highlight in the screenshot ({magenta.sum()} px)"


@pytest.mark.parametrize("ask_first", [True, False], ids=["after-requests", "at-once"])
def test_view_command_prints_the_url_and_stops_on_ctrl_c(
    view_work, tiny_scene_dir, ask_first
):
    """Ctrl-C stops the server cleanly (exit 0, "view: stopped"), also when it
    comes the moment the URL shows (it once arrived before the handler's try
    and click aborted with exit 1)."""
    _need_viser()
    import signal

    port = _free_port()
    cmd = [sys.executable, "-m", "ptovs", "--work-dir", str(view_work), *RECON,
           "view", "--data", str(tiny_scene_dir), "--port", str(port)]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)  # fmt: skip
    seen = []  # every line up to ptovs's own
    try:
        first = ""
        deadline = time.time() + 120
        while not first.startswith("view ") and time.time() < deadline:
            first = proc.stdout.readline()
            seen.append(first)
            assert first or proc.poll() is None, "ptovs view ended early"
        assert f"http://127.0.0.1:{port}/" in first and "Ctrl-C" in first, first
        url = first.split()[2]
        assert len(url.rstrip("/").rsplit("/", 1)[1]) >= 20  # the token
        if ask_first:  # else the finally sends Ctrl-C at once
            with urllib.request.urlopen(url, timeout=10) as r:
                assert r.status == 200
            with pytest.raises(urllib.error.HTTPError):  # without the token: 404
                urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=10)
        # bound to the loopback only: the default host is not the network's
        assert "0.0.0.0" not in first
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            # generous: run at nice 19 beside a 2-thread job, stopping took over
            # 30 s once; a server that ignores SIGINT still fails here
            out, _ = proc.communicate(timeout=90)
        except subprocess.TimeoutExpired:
            proc.kill()  # never leave a server behind
            out, _ = proc.communicate()
            pytest.fail(f"ptovs view did not stop on SIGINT within 90 s:\n{out}")
    assert proc.returncode == 0, out
    assert "view: stopped" in out and "Traceback" not in out
    # the user sees one address, the one that opens the page: viser's own box
    # (its address without the token answers 404) is not printed
    printed = "".join(seen) + out
    addresses = re.findall(r"(?:https?|wss?)://\S+", printed)
    assert addresses == [url], printed


def test_view_help_lists_the_options():
    # in-process (`python -m ptovs --help` in a fresh process: tests/test_cli.py)
    res = CliRunner().invoke(main, ["view", "--help"])
    assert res.exit_code == 0, res.output
    for opt in ("--host", "--port", "127.0.0.1", "8080", "--out-dir", "--allow-remote"):
        assert opt in res.output

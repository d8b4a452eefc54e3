"""The viewer's front door, played by an attacker: raw HTTP requests that
climb out of the web root, websockets without the token or from another origin,
and the path cleaning and message checks on their own. The hostile websocket
client against a whole page is in test_view.py."""

from __future__ import annotations

import socket
from types import SimpleNamespace

import pytest

from ptovs.apps.view_guard import (
    Guard,
    check_message,
    clean_relpath,
    guarded_viser,
    is_loopback,
    list_files,
    viser_client_root,
)

SECRET = "ptovs-secret-file-content-7f3a"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def raw_get(
    port: int, target: str, host: str | None = None, extra: str = ""
) -> tuple[int, bytes]:
    """(status, body) of one HTTP/1.1 request sent byte for byte (no client
    normalises the path)."""
    host = host or f"127.0.0.1:{port}"
    req = f"GET {target} HTTP/1.1\r\nHost: {host}\r\n{extra}Connection: close\r\n\r\n"
    with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
        s.sendall(req.encode("latin-1"))
        data = b""
        while chunk := s.recv(65536):
            data += chunk
    if not data:
        return 0, b""
    head, _, body = data.partition(b"\r\n\r\n")
    return int(head.split()[1]), body


def test_clean_relpath_refuses_everything_but_plain_paths():
    ok = {"": "index.html", "index.html": "index.html",
          "assets/index-x.js": "assets/index-x.js", "a%20b.txt": "a b.txt"}  # fmt: skip
    for raw, want in ok.items():
        assert clean_relpath(raw) == want
    for raw in ["..", "../etc/passwd", "assets/../../x", "%2e%2e/x", "..%2fx",
                "%252e%252e/x", "a//b", "/etc/passwd", "a\\..\\b", "a%5c..%5cb",
                "./index.html", "a/./b", "index.html%00", "%c0%ae%c0%ae/x", "a\x00b", "a\nb", "a/"]:  # fmt: skip
        assert clean_relpath(raw) is None, raw


def test_file_list_has_no_links_out(tmp_path):
    (tmp_path / "web").mkdir()
    (tmp_path / "web" / "index.html").write_text("<html>")
    (tmp_path / "secret").write_text(SECRET)
    (tmp_path / "web" / "link").symlink_to(tmp_path / "secret")
    (tmp_path / "web" / "dir").symlink_to(tmp_path, target_is_directory=True)
    assert list(list_files(tmp_path / "web")) == ["index.html"]


def test_loopback_names():
    for h in ("127.0.0.1", "127.0.0.2", "::1", "localhost"):
        assert is_loopback(h)
    for h in ("0.0.0.0", "::", "192.168.1.1", "example.org"):
        assert not is_loopback(h)


def _cam(**kw):
    base = dict(wxyz=(1.0, 0.0, 0.0, 0.0), position=(0.0, 0.0, 0.0), fov=1.0,
                near=0.01, far=100.0, image_height=480, image_width=640,
                look_at=(0.0, 0.0, 1.0), up_direction=(0.0, -1.0, 0.0))  # fmt: skip
    base.update(kw)
    from viser import _messages

    return _messages.ViewerCameraMessage(**base)


def test_messages_are_checked():
    from viser import _messages

    assert check_message(_cam()) is None
    for bad in (dict(fov=float("nan")), dict(fov=0.0), dict(fov=4.0),
                dict(image_height=10**9), dict(image_width=-1),
                dict(position=(0.0, float("inf"), 0.0)), dict(wxyz=(0.0, 0.0, 0.0, 0.0)),
                dict(wxyz=(1.0, 0.0)), dict(position=("a", 0, 0))):  # fmt: skip
        assert check_message(_cam(**bad)) is not None, bad
    upd = _messages.GuiUpdateMessage
    assert check_message(upd("u", {"value": "Doric Column"})) is None
    assert check_message(upd("u", {"value": True})) is None
    assert check_message(upd("u", {"disabled": True})) is not None
    assert check_message(upd("u", {"value": "x", "visible": False})) is not None
    assert check_message(upd("u", {"value": {"a": 1}})) is not None
    assert check_message(upd("u", {"value": float("nan")})) is not None
    assert check_message(_messages.ShareUrlRequest()) is not None
    start = _messages.FileTransferStartUpload("u", "t", "f", "text/plain", 1, 10)
    assert check_message(start) is not None


@pytest.fixture(scope="module")
def bare_server():
    """viser's server behind the guard, with no scene (the front door alone)."""
    try:
        import viser
    except ImportError:
        pytest.fail("viser is not installed: make setup (or .ci/run) installs it")
    port = _free_port()
    guard = Guard(viser_client_root(), "127.0.0.1", port, max_clients=2)
    with guarded_viser(guard):
        server = viser.ViserServer(host="127.0.0.1", port=port, verbose=False)
    yield SimpleNamespace(server=server, guard=guard, port=port)
    server.stop()


TRAVERSALS = [
    "/../../../../../../../../../../../../../../../../../../../../{f}",
    "/{t}/../../../../../../../../../../../../../../../../../../../../{f}",
    "/{t}/%2e%2e/%2e%2e/%2e%2e/%2e%2e/%2e%2e/%2e%2e/%2e%2e/%2e%2e/%2e%2e/%2e%2e/%2e%2e/%2e%2e/%2e%2e/%2e%2e/{f}",
    "/{t}/" + "..%2f" * 20 + "{f2}",
    "/{t}/" + "%252e%252e/" * 20 + "{f}",
    "/{t}/" + "..\\" * 20 + "{fb}",
    "/{t}/assets/" + "..%5c" * 20 + "{f5}",
    "/{t}//{f}",
    "/{t}/" + "%c0%ae%c0%ae/" * 20 + "{f}",
    "/{t}/" + "%e0%80%ae%e0%80%ae/" * 20 + "{f}",
    "//{f}",
    "/{t}/./index.html",
    "/{t}/index.html%00.png",
    "/{t}/assets/../../viser/__init__.py",
    "/{t}/../_viser.py",
    "/{t}/" + "..;/" * 20 + "{f}",
    "/{t}/" + "%2e%2e%2f" * 20 + "{f}",
    "/index.html",
    "/",
    "/assets/",
    "/{t}x/index.html",
    "/{T}/index.html",
    "http://127.0.0.1:{p}/../../../../../../../../../../../../../../../../{f}",
]


def test_raw_traversal_requests_answer_404(bare_server, tmp_path):
    t, p = bare_server.guard.token, bare_server.port
    secret = tmp_path / "secret.txt"  # what a climb out of the web root would read
    secret.write_text(SECRET)
    f = str(secret.resolve()).lstrip("/")
    names = dict(t=t, T=t.upper() if t.upper() != t else t + "A", p=p, f=f,
                 f2=f.replace("/", "%2f"), f5=f.replace("/", "%5c"),
                 fb=f.replace("/", "\\"))  # fmt: skip
    for target in TRAVERSALS:
        target = target.format(**names)
        status, body = raw_get(p, target)
        assert status in (400, 404), (target, status)
        assert SECRET.encode() not in body, target
        assert b"import" not in body, target
    # the page itself is served, under its token only
    status, body = raw_get(p, f"/{t}/")
    assert status == 200 and b"<html" in body.lower()
    status, body = raw_get(p, f"/{t}/index.html")
    assert status == 200
    status, _ = raw_get(p, f"/{t}")  # to the folder, so the page's paths work
    assert status == 302


def test_host_and_origin_must_name_the_bound_address(bare_server):
    t, p = bare_server.guard.token, bare_server.port
    assert raw_get(p, f"/{t}/", host=f"localhost:{p}")[0] == 200
    for host in (f"attacker.example:{p}", "127.0.0.1", f"127.0.0.1:{p + 1}",
                 f"evil.127.0.0.1.nip.io:{p}"):  # fmt: skip
        assert raw_get(p, f"/{t}/", host=host)[0] == 403, host
    assert raw_get(p, f"/{t}/", extra=f"Host: 127.0.0.1:{p}\r\n")[0] == 403  # two
    evil = "Origin: http://attacker.example\r\n"
    assert raw_get(p, f"/{t}/", extra=evil)[0] == 403
    assert raw_get(p, f"/{t}/", extra=f"Origin: http://127.0.0.1:{p}\r\n")[0] == 200


def _ws(port, path, origin="same", **kw):
    from websockets.sync.client import connect

    origin = f"http://127.0.0.1:{port}" if origin == "same" else origin
    import viser

    return connect(f"ws://127.0.0.1:{port}{path}", origin=origin,
                   subprotocols=[f"viser-v{viser.__version__}"], open_timeout=10,
                   max_size=None, **kw)  # fmt: skip


def test_websocket_needs_the_token_the_origin_and_a_free_place(bare_server):
    from websockets.exceptions import InvalidStatus

    t, p = bare_server.guard.token, bare_server.port
    for path, origin in [("/", "same"), (f"/{t}x", "same"), (f"/{t}/", "same"),
                         (f"/{t}", None), (f"/{t}", "http://attacker.example"),
                         (f"/{t}", f"http://localhost:{p}"), (f"/{t}", "null")]:  # fmt: skip
        with pytest.raises(InvalidStatus):
            _ws(p, path, origin).close()
    with _ws(p, f"/{t}") as a, _ws(p, f"/{t}") as b:  # max_clients=2
        a.recv(timeout=10)  # viser's first messages: the connection is open
        b.recv(timeout=10)
        with pytest.raises(InvalidStatus) as err:  # the third: refused
            _ws(p, f"/{t}")
        assert err.value.response.status_code == 503
    # places are given back when clients leave
    with _ws(p, f"/{t}") as a:
        a.recv(timeout=10)

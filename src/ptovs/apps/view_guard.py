"""The viewer's front door: what may reach `ptovs view`'s server at all.

viser (1.0.0, and its newest release too) serves its web client with a handler that
joins the request path onto its build folder without normalising `..`, accepts any
Host and Origin, and hands every websocket message to its handlers unchecked. None
of that is changed in the installed package: `guarded_viser` starts viser with our
own `Guard` in front of its websocket server, so that

- HTTP answers only the files of viser's client build folder, listed once at start
  (an exact match of a cleaned path; anything else, `..`, encoded or doubled
  variants, backslashes, links, is 404), and only under the run's token;
- a websocket is opened only at `/<token>`, with a Host naming the bound address
  and an Origin that is the page's own; at most `max_clients` at once;
- a websocket message must decode, be one of the few kinds the page needs (camera,
  a control's value), carry finite numbers and sane sizes; a malformed one closes
  that connection alone (viser's own clean-up runs), an unneeded kind (the share
  tunnel, uploads, clicks, transforms) is dropped.

The token is a per-run secret in the printed URL (`http://HOST:PORT/<token>/`): the
page's own websocket address is its URL without the slash, so the page works with
it, and a client that was never shown the URL cannot connect.
"""

from __future__ import annotations

import contextlib
import gzip
import hmac
import http
import ipaddress
import math
import mimetypes
import secrets
import socket
import threading
import urllib.parse
from collections import deque
from collections.abc import Iterator
from pathlib import Path

# the websocket messages a page sends that the viewer needs; everything else a
# client may send (share tunnel, file uploads, clicks, transform drags, renders) is
# dropped before viser sees it
ALLOWED_MESSAGES = ("ViewerCameraMessage", "GuiUpdateMessage")
MAX_MESSAGE_BYTES = 64 * 1024  # a camera or a control's value is < 1 KiB
MAX_CLIENTS = 4
MAX_IMAGE_SIDE = 16384  # a client camera's reported canvas, pixels

SECURITY_HEADERS = {
    "Cache-Control": "no-store",
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",  # the token is in the URL
    "X-Frame-Options": "DENY",
    "Cross-Origin-Resource-Policy": "same-origin",
}
MIME = {
    ".css": "text/css; charset=utf-8",
    ".html": "text/html; charset=utf-8",
    ".js": "application/javascript",
    ".json": "application/json",
    ".wasm": "application/wasm",
    ".png": "image/png",
    ".svg": "image/svg+xml",
    ".ttf": "font/ttf",
    ".txt": "text/plain; charset=utf-8",
}


def is_loopback(host: str) -> bool:
    """Whether `host` (an address or a name) binds the loopback only."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def _host_names(host: str) -> set[str]:
    """The names a browser may use for the bound address (without the port)."""
    if is_loopback(host):
        names = {"localhost", "127.0.0.1", "[::1]"}
    else:
        names = set()
    if host in ("0.0.0.0", "::", ""):  # every interface: every address it has
        with contextlib.suppress(Exception):
            import psutil

            for addrs in psutil.net_if_addrs().values():
                for a in addrs:
                    if a.family == socket.AF_INET:
                        names.add(a.address)
                    elif a.family == socket.AF_INET6:
                        names.add(f"[{a.address.split('%')[0]}]")
        for name in (socket.gethostname(), socket.getfqdn()):
            names.add(name.lower())
        names |= {"localhost", "127.0.0.1", "[::1]"}
    else:
        names.add(f"[{host}]" if ":" in host else host.lower())
    return names


def list_files(root: Path) -> dict[str, Path]:
    """Every regular file under `root` (no links, nothing that resolves outside),
    by its path relative to root with '/' separators."""
    root = root.resolve()
    files: dict[str, Path] = {}
    for p in sorted(root.rglob("*")):
        if p.is_symlink() or not p.is_file():
            continue
        real = p.resolve()
        if real.is_relative_to(root) and not any(
            q.is_symlink() for q in p.relative_to(root).parents if str(q) != "."
        ):
            files[p.relative_to(root).as_posix()] = real
    return files


def clean_relpath(raw: str) -> str | None:
    """The request path's part to look up (after the token), or None when it is
    not a plain relative path: percent-decoded once, then no `%` left, no
    backslash, NUL or control character, no empty, `.` or `..` segment."""
    try:
        path = urllib.parse.unquote(raw, errors="strict")
    except UnicodeDecodeError:  # e.g. an overlong UTF-8 dot (%c0%ae)
        return None
    if any(c in path for c in "%\\") or any(ord(c) < 32 or ord(c) == 127 for c in path):
        return None
    if path == "":
        return "index.html"
    parts = path.split("/")
    if any(p in ("", ".", "..") for p in parts):
        return None
    return "/".join(parts)


def _number_ok(x, lo: float = -1e12, hi: float = 1e12) -> bool:
    return (
        isinstance(x, (int, float))
        and not isinstance(x, bool)
        and math.isfinite(x)
        and lo <= x <= hi
    )


def check_message(message) -> str | None:
    """Why a decoded client message is refused (None: it may pass). Camera fields
    must be finite and sized; a control update may set its value and nothing else."""
    kind = type(message).__name__
    if kind == "ViewerCameraMessage":
        m = message
        vecs = (m.wxyz, m.position, m.look_at, m.up_direction)
        if not all(
            isinstance(v, tuple) and all(_number_ok(x) for x in v) for v in vecs
        ):
            return "camera vectors must be finite numbers"
        if len(m.wxyz) != 4 or any(len(v) != 3 for v in vecs[1:]):
            return "camera vectors have the wrong length"
        if sum(x * x for x in m.wxyz) < 1e-12:
            return "camera rotation is zero"
        if not _number_ok(m.fov, 1e-4, math.pi - 1e-4):
            return "camera fov out of range"
        if not (_number_ok(m.near) and _number_ok(m.far)):
            return "camera near/far must be finite"
        for side in (m.image_width, m.image_height):
            if not (isinstance(side, int) and 0 <= side <= MAX_IMAGE_SIDE):
                return "camera image size out of range"
        return None
    if kind == "GuiUpdateMessage":
        if not isinstance(message.uuid, str) or len(message.uuid) > 64:
            return "bad control id"
        if not isinstance(message.updates, dict) or set(message.updates) != {"value"}:
            return "a page may only set a control's value"
        value = message.updates["value"]
        if not isinstance(value, (str, bool, int, float)) or (
            isinstance(value, float) and not math.isfinite(value)
        ):
            return "a control's value must be a string, a number or a flag"
        return None
    return f"{kind} is not accepted by this viewer"


class Guard:
    """Decides every request and message before viser's server sees it.

    Args:
        root: the folder of files the page may load (viser's client build).
        host, port: the bound address (Host and Origin must name it).
        token: the per-run secret (None: a fresh one).
        max_clients: websockets open at once; more are closed at once.
    """

    def __init__(
        self,
        root: Path,
        host: str,
        port: int,
        token: str | None = None,
        max_clients: int = MAX_CLIENTS,
    ) -> None:
        self.files = list_files(Path(root))
        if "index.html" not in self.files:
            raise RuntimeError(f"view: no index.html in viser's client build {root}")
        self.token = token or secrets.token_urlsafe(18)
        self.port = int(port)
        self.hosts = {f"{name}:{self.port}" for name in _host_names(host)}
        self.max_clients = max_clients
        self.open = 0
        self.refused: deque[str] = deque(maxlen=200)  # the latest refusals' reasons
        self.refusals = 0  # all of them
        self._lock = threading.Lock()
        self._cache: dict[tuple[str, bool], bytes] = {}
        self.installed = False  # set when viser's server was built through us

    def note(self, why: str) -> None:
        """Count a refusal and keep its reason (the latest 200)."""
        with self._lock:
            self.refused.append(why)
            self.refusals += 1

    # ------------------------------------------------------------------ HTTP --
    def _refuse(self, status: int, why: str):
        from websockets.datastructures import Headers
        from websockets.http11 import Response

        self.note(why)
        body = f"{status} {http.HTTPStatus(status).phrase}\n".encode()
        headers = Headers(
            {
                "Content-Type": "text/plain; charset=utf-8",
                "Content-Length": str(len(body)),
                "Connection": "close",
                **SECURITY_HEADERS,
            }
        )
        return Response(status, http.HTTPStatus(status).phrase, headers, body)

    @staticmethod
    def _header(request, name: str) -> str:
        """A header's values joined (one may be sent twice: never raise on it)."""
        return ", ".join(request.headers.get_all(name))

    def _host_ok(self, request) -> bool:
        hosts = request.headers.get_all("Host")
        return len(hosts) == 1 and hosts[0].lower() in self.hosts

    def _origin_ok(self, request, required: bool) -> bool:
        origins = request.headers.get_all("Origin")
        if not origins:
            return not required
        host = self._header(request, "Host").lower()
        return len(origins) == 1 and origins[0].lower() == f"http://{host}"

    def _token_of(self, path: str) -> tuple[bool, str | None]:
        """(the path starts with the token, the rest after `/<token>`)."""
        if not path.startswith("/"):
            return False, None
        head, sep, rest = path[1:].partition("/")
        ok = hmac.compare_digest(head.encode(), self.token.encode())
        return ok, (rest if sep else None)

    def process_request(self, connection, request):
        """websockets' hook: a Response ends the request; None lets a websocket
        handshake go on."""
        path = request.path.partition("?")[0].partition("#")[0]
        if not self._host_ok(request):
            return self._refuse(403, f"host {self._header(request, 'Host')!r}")
        upgrade = self._header(request, "Upgrade").lower() == "websocket"
        ok, rest = self._token_of(path)
        if upgrade:
            if not self._origin_ok(request, required=True):
                return self._refuse(403, f"origin {self._header(request, 'Origin')!r}")
            if not ok or rest is not None:
                return self._refuse(403, "websocket without the token")
            with self._lock:
                full = self.open >= self.max_clients
            if full:
                return self._refuse(503, "too many clients")
            return None
        if not self._origin_ok(request, required=False):
            return self._refuse(403, f"origin {self._header(request, 'Origin')!r}")
        if not ok:
            return self._refuse(404, f"no token: {path[:80]!r}")
        if rest is None:  # /<token> → /<token>/ (the page's files are relative)
            from websockets.datastructures import Headers
            from websockets.http11 import Response

            headers = Headers(
                {
                    "Location": f"/{self.token}/",
                    "Content-Length": "0",
                    **SECURITY_HEADERS,
                }
            )
            return Response(302, "Found", headers, b"")
        rel = clean_relpath(rest)
        if rel is None or rel not in self.files:
            return self._refuse(404, f"not served: {rest[:80]!r}")
        return self._file(rel, "gzip" in self._header(request, "Accept-Encoding"))

    def _file(self, rel: str, use_gzip: bool):
        from websockets.datastructures import Headers
        from websockets.http11 import Response

        key = (rel, use_gzip)
        if key not in self._cache:
            data = self.files[rel].read_bytes()
            self._cache[key] = gzip.compress(data) if use_gzip else data
        body = self._cache[key]
        suffix = Path(rel).suffix.lower()
        mime = MIME.get(suffix) or mimetypes.guess_type(rel)[0]
        headers = Headers(
            {
                "Content-Type": mime or "application/octet-stream",
                "Content-Length": str(len(body)),
                "Content-Encoding": "gzip" if use_gzip else "identity",
                **SECURITY_HEADERS,
            }
        )
        return Response(200, "OK", headers, body)

    # ------------------------------------------------------------ websocket --
    def wrap_handler(self, handler):
        """viser's connection handler behind a count and a message check."""
        guard = self

        async def guarded(connection):
            with guard._lock:
                if guard.open >= guard.max_clients:
                    full = True
                else:
                    guard.open += 1
                    full = False
            if full:
                await connection.close(1013, "too many viewers")
                return
            try:
                await handler(_CheckedConnection(connection, guard))
            finally:
                with guard._lock:
                    guard.open -= 1

        return guarded

    def serve(self, real_serve):
        """A stand-in for websockets' `serve` that puts this guard in front."""
        guard = self

        def serve(handler, host, port, **kwargs):
            kwargs["process_request"] = guard.process_request
            kwargs["max_size"] = MAX_MESSAGE_BYTES
            kwargs["max_queue"] = 16
            guard.installed = True
            return real_serve(guard.wrap_handler(handler), host, port, **kwargs)

        return serve


class _CheckedConnection:
    """A websocket connection whose `recv` hands on only checked messages; a bad
    one closes the connection as a closed connection would (so viser cleans up)."""

    def __init__(self, connection, guard: Guard) -> None:
        self._connection = connection
        self._guard = guard

    def __getattr__(self, name):
        return getattr(self._connection, name)

    async def _close(self, code: int, why: str):
        from websockets.exceptions import ConnectionClosedError
        from websockets.frames import Close

        self._guard.note(why)
        await self._connection.close(code, why[:120])
        raise ConnectionClosedError(Close(code, why[:120]), None)

    async def recv(self, *args, **kwargs):
        from viser import _messages

        while True:
            raw = await self._connection.recv(*args, **kwargs)
            if not isinstance(raw, bytes):
                await self._close(1003, "text frames are not accepted")
            try:
                message = _messages.Message.deserialize(raw)
            except Exception as exc:  # noqa: BLE001 - any decode failure closes
                await self._close(1007, f"malformed message ({type(exc).__name__})")
            why = check_message(message)
            if why is None:
                return raw
            if type(message).__name__ in ALLOWED_MESSAGES:
                await self._close(1008, why)
            self._guard.note(why)  # an unneeded kind: dropped, connection kept


_serve_lock = threading.Lock()


@contextlib.contextmanager
def guarded_viser(guard: Guard) -> Iterator[None]:
    """While viser builds its server, its websockets `serve` is `guard.serve`; the
    installed package is not changed and the swap ends with the block. Fails
    closed: if viser did not go through it, RuntimeError."""
    import websockets.asyncio.server as ws_server

    with _serve_lock:
        real = ws_server.serve
        ws_server.serve = guard.serve(real)
        try:
            yield
        finally:
            ws_server.serve = real
    if not guard.installed:
        raise RuntimeError(
            "view: viser did not start its server through ptovs's guard (a viser "
            "other than 1.0.0?); refusing to serve. Install viser==1.0.0"
        )


def viser_client_root() -> Path:
    """viser's client build folder (the only files the page may load)."""
    import viser

    return Path(viser.__file__).resolve().parent / "client" / "build"


__all__ = [
    "ALLOWED_MESSAGES",
    "Guard",
    "MAX_CLIENTS",
    "check_message",
    "clean_relpath",
    "guarded_viser",
    "is_loopback",
    "list_files",
    "viser_client_root",
]

"""`ptovs view`: roam the reconstructed Gaussians in a browser and ask them things.

    ptovs view --data data/demo [--host 127.0.0.1] [--port 8080]

Serves a local page (viser, the `[view]` extra) with the scene's Gaussians, and a
panel: an appearance chooser (any photo's embedding or the neutral mean, baked into
the colours and the sky dome once per choice), a text field whose phrase selects
Gaussians as `ptovs select` does (highlighted in 3-D, with the relevancy heatmap of
the current camera beside it, and the level, score and count), and buttons to jump
to the nearest photo's camera, to export the selection as a 3DGS PLY (as `select`
writes it) and to play the `roam` path.

`ptovs.apps.view_session.ViewSession` is everything but the page (load once,
answer queries, bake, export), shared by every browser; here, `Panel` is one browser's controls, scene and choices;
`Page` puts them behind viser, with `ptovs.apps.view_guard` in front (the token in
the printed URL, Host and Origin checks, only viser's own files, checked messages).
Every client input is data: validated, capped, never markup.
"""

from __future__ import annotations

import contextlib
import functools
import signal
import socket
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import click
import numpy as np
import torch

from ptovs.apps.view_guard import MAX_CLIENTS, is_loopback
from ptovs.apps.view_session import (
    HIGHLIGHT,
    NEUTRAL,
    QueryAnswer,
    ViewSession,
    camera_centre,
    plain,
    ready_chain,
)
from ptovs.errors import InputError
from ptovs.options import chain_options
from ptovs.raster import Camera
from ptovs.settings import RunContext

__all__ = ["HIGHLIGHT", "NEUTRAL", "Page", "Panel", "ViewSession", "check_port"]

MAX_EXPORTS = 20  # PLYs one browser may write
READY = "Type a phrase and press Highlight."


@dataclass
class ViewState:
    """One browser's choices."""

    appearance: str = NEUTRAL
    answer: QueryAnswer | None = None
    exports: int = 0


def check_port(host: str, port: int) -> None:
    """InputError if `port` on `host` cannot be bound (viser would silently take
    the next one)."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        try:
            s.bind((host, port))
        except OSError as exc:
            raise InputError(
                f"view: port {port} on {host} is in use or not allowed ({exc.strerror});"
                " choose another with --port"
            ) from None


def _camera_of(client_camera, width: int) -> Camera:
    """Our Camera from a viser client camera (OpenCV axes, vertical fov); the
    client's aspect and fov are clamped (a page sets them)."""
    from viser import transforms as tf

    try:  # a page that reports a zero-sized canvas has no aspect
        aspect = float(client_camera.aspect)
    except (ZeroDivisionError, ValueError, TypeError):
        aspect = 4 / 3
    aspect = min(max(aspect, 0.25), 4.0) if np.isfinite(aspect) else 4 / 3
    height = max(8, round(width / aspect))
    fov = float(client_camera.fov)
    fov = min(max(fov, 0.05), 3.0) if np.isfinite(fov) else 1.0
    f = 0.5 * height / np.tan(0.5 * fov)
    rot = tf.SO3(np.asarray(client_camera.wxyz, float)).as_matrix()
    t = np.eye(4)
    t[:3, :3] = rot.T
    t[:3, 3] = -rot.T @ np.asarray(client_camera.position, float)
    k = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]])
    return Camera(
        cam_from_world=torch.tensor(t, dtype=torch.float32),
        K=torch.tensor(k, dtype=torch.float32),
        width=width,
        height=height,
    )


def _pose_of(cam_from_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(wxyz, position) of a camera in the world (viser's client camera)."""
    from viser import transforms as tf

    t = np.asarray(cam_from_world, float)
    world_from_cam = t[:3, :3].T
    return tf.SO3.from_matrix(world_from_cam).wxyz, camera_centre(t)


def _safely(method):
    """A panel handler that answers its own errors in the page: an InputError's
    message, anything else as an internal error (logged on the server)."""

    @functools.wraps(method)
    def run(self, *args, **kwargs):
        try:
            return method(self, *args, **kwargs)
        except InputError as exc:
            self.say(f"⚠ {plain(exc)}")
        except Exception as exc:  # noqa: BLE001 - a handler never dies silently
            print(f"view: {method.__name__} failed: {exc!r}", file=sys.stderr)
            self.say(
                f"⚠ internal error ({plain(type(exc).__name__)}); see the server log"
            )
        return None

    return run


class Panel:
    """One browser's controls, splats, sky and choices (no other browser sees or
    changes them). Handlers are plain methods: tests call them, the page calls
    them; each answers its own errors in this browser's status line."""

    def __init__(self, page: Page, client) -> None:
        self.page = page
        self.client = client
        self.session = s = page.session
        self.state = ViewState()
        self.splats = None  # the splat node, added by the first draw
        self.sky = None
        self._busy = threading.Lock()
        gui = client.gui
        gui.configure_theme(show_share_button=False)
        gui.add_markdown(
            f"**ptovs view** · {plain(s.scene.name)} · {len(s.centers):,} Gaussians"
        )
        self.appearance = gui.add_dropdown(
            "Appearance", tuple(s.appearances), initial_value=NEUTRAL
        )
        self.text = gui.add_text("Phrase", initial_value="")
        self.ask = gui.add_button("Highlight")
        self.clear = gui.add_button("Clear")
        self.status = gui.add_markdown(READY)
        self.nearest = gui.add_button("Nearest photo")
        self.export = gui.add_button("Export selection (PLY)")
        self.play = gui.add_button("Play tour")
        w = page.heat_width
        self.heat = gui.add_image(
            np.zeros((w * 3 // 4, w, 3), np.uint8), label="Relevancy (current view)"
        )
        self.appearance.on_update(lambda _: self.set_appearance(self.appearance.value))
        self.ask.on_click(lambda _: self.ask_phrase(self.text.value))
        self.clear.on_click(lambda _: self.clear_phrase())
        self.nearest.on_click(lambda _: self.go_nearest())
        self.export.on_click(lambda _: self.export_selection())
        self.play.on_click(lambda _: self.play_tour())
        self.draw()
        self.draw_sky()
        view = s.views[0]
        wxyz, pos = _pose_of(view.cam_from_world)
        with client.atomic():
            client.camera.wxyz, client.camera.position = wxyz, pos
        self.refresh_heatmap()

    def say(self, markdown: str) -> None:
        """The status line (markdown: callers pass client text through `plain`)."""
        self.status.content = markdown

    def draw(self) -> None:
        """Send the splats' colours: the whole node once, then only its buffer with
        the colour words replaced (the page keeps its geometry)."""
        s, st = self.session, self.state
        rgb = s.colors(st.appearance, st.answer)
        if self.splats is None:
            self.splats = self.client.scene.add_gaussian_splats(
                "/gaussians", s.centers, s.covariances, rgb, s.opacities
            )
            return
        rgba = np.concatenate((rgb, s.opacities), 1)
        words = (np.clip(rgba * 255.0, 0, 255).astype(np.uint8)).view(np.uint32)
        buffer = self.splats.buffer.copy()
        buffer[:, 7] = words[:, 0]  # viser's layout: word 7 is RGBA
        self.splats.buffer = buffer

    def draw_sky(self) -> None:
        """The sky dome under the chosen appearance (only when that changes)."""
        pos, rgb, radius = self.session.sky_points(self.state.appearance)
        spacing = radius * np.sqrt(4 * np.pi / len(pos))  # between dome points
        self.sky = self.client.scene.add_point_cloud(
            "/sky", pos, rgb, point_size=float(1.5 * spacing)
        )

    @_safely
    def set_appearance(self, name) -> None:
        try:
            self.state.appearance = self.session.check_appearance(name)
        except InputError:
            self.appearance.value = self.state.appearance  # the page shows ours
            raise
        self.draw()
        self.draw_sky()
        self.refresh_heatmap()

    @property
    def busy(self) -> bool:
        """Whether a query or tour of this page is running (another is refused)."""
        return self._busy.locked()

    @contextlib.contextmanager
    def _alone(self) -> Iterator[None]:
        """One query or tour of this page at a time; another press is refused."""
        if not self._busy.acquire(blocking=False):
            raise InputError(
                "still working on the last request; press again when it ends"
            )
        try:
            yield
        finally:
            self._busy.release()

    @_safely
    def ask_phrase(self, text) -> QueryAnswer | None:
        with self._alone():
            t0 = time.perf_counter()
            answer = self.session.query(text)
            self.state.answer = answer
            self.draw()  # the highlighted colours go out first, then the status line
            self.say(answer.line(time.perf_counter() - t0))
            self.refresh_heatmap()
            return answer

    @_safely
    def clear_phrase(self) -> None:
        self.state.answer = None
        self.say(READY)
        self.draw()
        self.refresh_heatmap()

    def refresh_heatmap(self) -> None:
        cam = _camera_of(self.client.camera, self.page.heat_width)
        st = self.state
        self.heat.image = self.session.heatmap(cam, st.appearance, st.answer)

    @_safely
    def go_nearest(self) -> None:
        cam = self.client.camera
        view = self.session.nearest_view(np.asarray(cam.position, float))
        wxyz, pos = _pose_of(view.cam_from_world)
        with self.client.atomic():
            cam.wxyz, cam.position = wxyz, pos
        self.say(f"At photo {plain(view.name)}.")

    @_safely
    def export_selection(self) -> Path | None:
        if self.state.exports >= MAX_EXPORTS:
            raise InputError(
                f"view: this page has exported {self.state.exports} PLYs, its limit"
            )
        path = self.session.export(self.state.answer, self.state.appearance)
        self.state.exports += 1
        # the file's name only: no other client learns the server's folders
        self.say(f"Wrote {plain(path.name)} into the export folder.")
        return path

    @_safely
    def play_tour(self, frames: int = 90, fps: float = 30.0) -> None:
        with self._alone():
            for cam in self.session.tour(frames):
                wxyz, pos = _pose_of(cam.cam_from_world.numpy())
                with self.client.atomic():
                    self.client.camera.wxyz, self.client.camera.position = wxyz, pos
                time.sleep(1 / fps)


class Page:
    """The viser server behind the guard; one Panel per connected browser.

    Args:
        session: the shared ViewSession.
        host, port: where to listen (check `--allow-remote` before a non-loopback
            host: the command does).
        heat_width: the heatmap's width in pixels.
        token: the URL's secret (None: a fresh one each run).
        max_clients: browsers served at once.
    """

    def __init__(
        self,
        session: ViewSession,
        host: str,
        port: int,
        heat_width: int,
        token: str | None = None,
        max_clients: int = MAX_CLIENTS,
    ):
        import viser
        from rich import get_console
        from viser import _messages

        from ptovs.apps.view_guard import Guard, guarded_viser, viser_client_root

        self.session = session
        self.heat_width = heat_width
        self.guard = Guard(viser_client_root(), host, port, token, max_clients)
        self.panels: dict[int, Panel] = {}
        self._lock = threading.Lock()
        self.server = None
        try:
            # viser prints a box with its address, which lacks the token (the guard
            # answers it 404): captured and dropped, the command prints the URL
            with guarded_viser(self.guard), get_console().capture():
                self.server = viser.ViserServer(host=host, port=port, verbose=False)
        except BaseException:
            if self.server is not None:
                self.server.stop()
            raise
        if self.server.get_port() != port:  # lost the port after check_port
            self.server.stop()
            raise InputError(
                f"view: port {port} on {host} was taken while starting; choose "
                "another with --port"
            )
        # no share tunnel: its requests are unregistered (and dropped by the guard)
        ws = self.server._websock_server
        for kind in (_messages.ShareUrlRequest, _messages.ShareUrlDisconnect):
            if kind in ws._incoming_handlers:
                ws.unregister_handler(kind)
        self.server.gui.configure_theme(show_share_button=False)
        ups = [-np.asarray(v.cam_from_world)[1, :3] for v in session.views]
        up = np.mean(ups, 0)
        self.server.scene.set_up_direction(tuple(up / (np.linalg.norm(up) + 1e-12)))
        name = socket.gethostname() if host in ("0.0.0.0", "::", "") else host
        name = f"[{name}]" if ":" in name else name
        self.url = f"http://{name}:{port}/{self.guard.token}/"
        self.server.on_client_connect(self._connected)
        self.server.on_client_disconnect(self._disconnected)

    def _connected(self, client) -> None:
        try:
            panel = Panel(self, client)
        except Exception as exc:  # noqa: BLE001 - one page's failure, said and logged
            print(f"view: a page could not be set up: {exc!r}", file=sys.stderr)
            return
        with self._lock:
            self.panels[client.client_id] = panel

    def _disconnected(self, client) -> None:
        with self._lock:
            self.panels.pop(client.client_id, None)

    def panel(self, timeout: float = 30.0) -> Panel:
        """The first connected browser's panel (waits for one; tests use it)."""
        deadline = time.time() + timeout
        while time.time() < deadline:
            with self._lock:
                if self.panels:
                    return next(iter(self.panels.values()))
            time.sleep(0.05)
        raise TimeoutError("no browser connected")

    def stop(self) -> None:
        self.server.stop()


@click.command(name="view")
@chain_options(variant="one", force=None)
@click.option(
    "--host",
    default="127.0.0.1",
    show_default=True,
    help="Address to serve on. Anything but the loopback needs --allow-remote.",
)
@click.option(
    "--allow-remote",
    is_flag=True,
    help="Allow a --host other than the loopback (the page then reaches every "
    "machine that reaches this one; the printed URL's token is still needed).",
)
@click.option(
    "--port",
    type=click.IntRange(1, 65535),
    default=8080,
    show_default=True,
    help="Port to serve on (an error if in use).",
)
@click.option(
    "--out",
    "--out-dir",
    "out_dir",
    type=click.Path(path_type=Path),
    default=Path("view-exports"),
    show_default=True,
    help="Folder where 'Export selection' writes PLYs (--out-dir: the old name).",
)
@click.option(
    "--heat-width",
    type=click.IntRange(64, 1024),
    default=320,
    show_default=True,
    help="Width in pixels of the relevancy heatmap.",
)
@click.pass_obj
def command(
    obj: RunContext,
    scene_name: str | None,
    data: Path | None,
    host: str,
    allow_remote: bool,
    port: int,
    out_dir: Path,
    heat_width: int,
    variant: str,
    sets: tuple[str, ...],
) -> None:  # fmt: skip
    """Serve a page to roam the scene and highlight what a phrase describes.

    Needs the trained chain (`ptovs train-male`, or `make demo`) and viser
    (`make setup` installs it: the [view] extra, then viser==1.0.0 --no-deps).
    Prints the URL, which carries a per-run token: only a page opened from it
    can drive the viewer. Ctrl-C stops the server. Buttons: Highlight the
    phrase, Clear, Nearest photo, Export selection (PLY, into --out), Play
    tour. Each browser has its own controls; at most 4 at once.
    """
    t0 = time.perf_counter()
    if not is_loopback(host):
        if not allow_remote:
            raise InputError(
                f"view: --host {host} would serve the scene, its queries and "
                "exports into --out to every machine that can reach this one; "
                "add --allow-remote if that is meant (the printed URL's token is "
                "still required), or leave --host at 127.0.0.1"
            )
        click.echo(
            f"view: WARNING: serving on {host}: every machine that can reach this "
            "one can load the page; anyone given the URL (its token) can query the "
            f"scene and write PLYs into {out_dir}. Use a trusted network only.",
            err=True,
        )
    check_port(host, port)
    from ptovs.outputs import check_output_dir

    check_output_dir("--out", out_dir)
    chain, ref = ready_chain(obj, scene_name, data, variant, sets)
    try:
        import viser  # noqa: F401
    except ImportError:
        raise InputError(
            "view: the viewer needs viser; install it as `make setup` does: pip "
            "install -e '.[view]' && pip install --no-deps viser==1.0.0"
        ) from None
    # Ctrl-C (and a TERM) stop the server, even when started with SIGINT ignored
    # (a background job of a non-interactive shell inherits that). The handlers
    # and the try come before the URL is printed: a Ctrl-C sent as soon as the
    # URL shows (while the server's thread holds the interpreter) still stops
    # the server cleanly instead of aborting past it.
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    session = ViewSession(chain, out_dir)
    page = None
    try:
        page = Page(session, host, port, heat_width)
        click.echo(
            f"view {ref.name}: {page.url}  ({len(session.centers):,} Gaussians,"
            f" ready in {time.perf_counter() - t0:.1f} s; Ctrl-C stops)"
        )
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        click.echo("view: stopped")
    finally:
        if page is not None:
            page.stop()
        session.close()

"""`ptovs view`: roam the reconstructed Gaussians in a browser and ask them things.

    ptovs view --data data/demo [--host 127.0.0.1] [--port 8080]

Serves a local page (viser, the `[view]` extra) with the scene's Gaussians, and a
panel: an appearance chooser (any photo's embedding or the neutral mean, baked into
the colours and the sky dome once per choice), a text field whose phrase selects
Gaussians as `ptovs select` does (highlighted in 3-D, with the relevancy heatmap of
the current camera beside it, and the level, score and count), and buttons to jump
to the nearest photo's camera, to export the selection as a 3DGS PLY (as `select`
writes it) and to play the `roam` path.

`ViewSession` is everything but the page (load once, answer queries, bake, export),
so it can be used and tested without a browser; `serve` puts it behind viser.
"""

from __future__ import annotations

import re
import signal
import socket
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import click
import numpy as np
import torch

from ptovs.apps import close_inputs
from ptovs.errors import InputError
from ptovs.field.model import SH_C0
from ptovs.raster import Camera
from ptovs.stage import RunContext, chain_options

HIGHLIGHT = (1.0, 0.0, 1.0)  # selected Gaussians: magenta, found by the browser test
NEUTRAL = "neutral (mean of the photos)"
SKY_POINTS = 20000  # the sky dome: a Fibonacci sphere of points coloured by f_sky


@dataclass
class QueryAnswer:
    """What the panel shows for one phrase."""

    text: str
    level: str
    score: float
    selected: int
    total: int
    seconds: float
    mask: np.ndarray  # [P] bool

    def line(self, sent: float | None = None) -> str:
        """The panel's status line; `sent`: seconds from the press to the new
        colours handed to the page."""
        took = f"select {self.seconds * 1e3:.0f} ms"
        if sent is not None:
            took += f", highlight sent {sent * 1e3:.0f} ms"
        return (
            f"**{self.text}**: {self.selected:,} of {self.total:,} Gaussians, level "
            f"{self.level}, score {self.score:.3f} ({took})"
        )


def _fibonacci_sphere(n: int) -> np.ndarray:
    i = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * i / n)
    theta = np.pi * (1 + 5**0.5) * i
    return np.stack(
        [np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], 1
    )


def _image(appearance: str) -> str | None:
    """The photo an appearance names (None: the neutral mean)."""
    return None if appearance == NEUTRAL else appearance


def _centre(cam_from_world: np.ndarray) -> np.ndarray:
    t = np.asarray(cam_from_world, float)
    return -t[:3, :3].T @ t[:3, 3]


class ViewSession:
    """A trained chain loaded once for interactive use: baked colours per
    appearance, phrase queries on the Gaussians, heatmaps of any camera.

    Args:
        chain: a chain whose train-male stage is done (see `ready_chain`).
        out_dir: where exported selections go (never overwritten: a new name each).
    """

    def __init__(self, chain, out_dir: Path) -> None:
        from ptovs.field.query import Querier

        self.inputs = chain.inputs("query")
        self.scene = self.inputs.scene
        self.out_dir = Path(out_dir)
        self.querier = Querier(self.inputs, chain.config("query"), [])
        # the stand-in encoder knows a small vocabulary: decode it all once
        vocab = getattr(self.querier.encoder, "phrases", None)
        if vocab:
            self.querier.add_queries(list(vocab))
        if self.querier.decoder.mode == "table":  # built once, before any query
            _ = self.querier.decoder.table
        self.field = self.querier.field
        g = self.field.gaussians
        self.centers = g.means.numpy().astype(np.float32)
        self.covariances = g.covariances().numpy().astype(np.float32)
        self.opacities = g.opacities.reshape(-1, 1).numpy().astype(np.float32)
        self.views = self.scene.train_views() + self.scene.test_views()
        self.photos = [v.name for v in self.views if v.name in self.field.embeddings]
        self.appearances = [NEUTRAL, *self.photos] if self.field.wild else [NEUTRAL]
        self._baked: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        self.answer: QueryAnswer | None = None
        self.appearance = NEUTRAL
        self.lock = threading.Lock()  # viser calls back from its thread pool

    def close(self) -> None:
        close_inputs(self.inputs)

    # ------------------------------------------------------------ appearance --
    def baked(self, appearance: str) -> tuple[np.ndarray, np.ndarray]:
        """(RGB [P, 3] of every Gaussian, sky dome RGB [SKY_POINTS, 3]) under an
        appearance (a photo name or NEUTRAL), float32 in [0, 1]; baked once."""
        if appearance not in self.appearances:
            raise InputError(
                f"view: no appearance {appearance!r}; choose one of the scene's photos"
            )
        if appearance not in self._baked:
            from ptovs.field.export import baked_sh

            sh = baked_sh(self.field, _image(appearance))
            rgb = (SH_C0 * sh[:, 0] + 0.5).clamp(0, 1).numpy().astype(np.float32)
            sky = np.zeros((SKY_POINTS, 3), np.float32)
            emb = self._embedding(appearance)
            if emb is not None:
                dirs = torch.from_numpy(_fibonacci_sphere(SKY_POINTS)).float()
                with torch.no_grad():
                    self.field.nets.eval()
                    col = self.field.nets.background(dirs[None], emb[0])[0]
                    col = self.field.nets.map_colors(col, emb[0])
                sky = col.clamp(0, 1).numpy().astype(np.float32)
            self._baked[appearance] = (rgb, sky)
        return self._baked[appearance]

    def _embedding(self, appearance: str) -> torch.Tensor | None:
        """[1, D]: the appearance's embedding (None for a plain field)."""
        if self.field.nets is None or not self.field.embeddings:
            return None
        from ptovs.field.export import appearance_embedding

        return appearance_embedding(self.field, _image(appearance))[None]

    def colors(self) -> np.ndarray:
        """RGB [P, 3] to show: the chosen appearance, the selection in HIGHLIGHT."""
        rgb = self.baked(self.appearance)[0].copy()
        if self.answer is not None:
            rgb[self.answer.mask] = HIGHLIGHT
        return rgb

    def sky_points(self) -> tuple[np.ndarray, np.ndarray, float]:
        """(positions [S, 3], RGB [S, 3], radius) of the sky dome: a sphere three
        times as far from the scene's centre as its farthest camera."""
        cams = np.stack([_centre(v.cam_from_world) for v in self.views])
        centre = np.median(self.centers, 0)
        radius = 3.0 * float(np.max(np.linalg.norm(cams - centre, axis=1)) + 1e-6)
        pos = centre + radius * _fibonacci_sphere(SKY_POINTS)
        return pos.astype(np.float32), self.baked(self.appearance)[1], radius

    # ---------------------------------------------------------------- queries --
    def query(self, text: str) -> QueryAnswer:
        """Select the Gaussians `text` describes (as `ptovs select`); InputError
        for a phrase the encoder cannot embed."""
        from ptovs.field.query import SelectOptions

        t0 = time.perf_counter()
        (text,) = self.querier.add_queries([text])
        sel = self.querier.select(text, SelectOptions())
        self.answer = QueryAnswer(
            text=text,
            level=str(self.querier.levels[sel.level]),
            score=float(sel.score),
            selected=int(sel.mask.sum()),
            total=len(sel.mask),
            seconds=time.perf_counter() - t0,
            mask=np.asarray(sel.mask, bool),
        )
        return self.answer

    def clear(self) -> None:
        self.answer = None

    def heatmap(self, cam: Camera) -> np.ndarray:
        """[H, W, 3] uint8: the current phrase's relevancy in `cam` over the render
        (the plain render when no phrase is asked)."""
        from ptovs.visual import heatmap, to_uint8

        with torch.no_grad():
            rgb = self.field.render(cam, self._embedding(self.appearance))[0].numpy()
        if self.answer is None:
            return to_uint8(rgb)
        (res,) = self.querier.answer_view(cam, [self.answer.text])
        return heatmap(res.smoothed[res.level], rgb)

    # -------------------------------------------------------------- cameras --
    def nearest_view(self, position: np.ndarray):
        """The photo whose camera centre is nearest `position`."""
        d = [np.linalg.norm(_centre(v.cam_from_world) - position) for v in self.views]
        return self.views[int(np.argmin(d))]

    def tour(self, frames: int, width: int = 320, height: int = 240) -> list[Camera]:
        """The `roam` path's cameras."""
        from ptovs.apps.roam import camera_path, pick_keyframes

        train = self.scene.train_views()
        keys = pick_keyframes(train, 8, np.median(self.centers, 0))
        return camera_path(keys, frames, width, height)

    # --------------------------------------------------------------- export --
    def export(self) -> Path:
        """Write the selection as a 3DGS PLY under out_dir (a fresh name); its
        appearance is the chosen one."""
        from ptovs.field.export import export_field_ply

        if self.answer is None or self.answer.selected == 0:
            raise InputError("view: nothing is selected; ask for a phrase first")
        slug = re.sub(r"[^A-Za-z0-9]+", "-", self.answer.text).strip("-") or "sel"
        self.out_dir.mkdir(parents=True, exist_ok=True)
        n = 1
        while (path := self.out_dir / f"{slug}-{n}.ply").exists():
            n += 1
        export_field_ply(
            self.inputs.reconstruct,
            path,
            image=_image(self.appearance),
            index=self.answer.mask,
            field=self.field,
        )
        return path


def ready_chain(obj: RunContext, scene_name, data, variant, sets):
    """The chain, or an InputError naming the command that trains what is missing
    (the viewer never trains: that takes minutes)."""
    from ptovs.stage import variant_chain

    chain, ref = variant_chain(obj, scene_name, data, variant, sets)
    for stage in chain.closure("train-male"):
        state, _ = chain.state(stage)
        if state != "done":
            raise InputError(
                f"view: scene {ref.name} has no trained language field ({stage} is "
                f"{state}); run first: {chain.hint('train-male')}"
            )
    return chain, ref


def check_port(host: str, port: int) -> None:
    """InputError if `port` on `host` cannot be bound (viser would silently take
    the next one)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind((host, port))
        except OSError as exc:
            raise InputError(
                f"view: port {port} on {host} is in use or not allowed ({exc.strerror});"
                " choose another with --port"
            ) from None


def _camera_of(client_camera, width: int) -> Camera:
    """Our Camera from a viser client camera (OpenCV axes, vertical fov)."""
    from viser import transforms as tf

    aspect = float(client_camera.aspect) or 4 / 3
    height = max(8, round(width / aspect))
    f = 0.5 * height / np.tan(0.5 * float(client_camera.fov))
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
    return tf.SO3.from_matrix(world_from_cam).wxyz, _centre(t)


class Page:
    """The viser server and its panel over one ViewSession (handles kept for tests)."""

    def __init__(self, session: ViewSession, host: str, port: int, heat_width: int):
        import viser

        self.session = session
        self.heat_width = heat_width
        self.splats = None  # the splat node, added by the first draw
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        if self.server.get_port() != port:  # lost the port after check_port
            self.server.stop()
            raise InputError(
                f"view: port {port} on {host} was taken while starting; choose "
                "another with --port"
            )
        s = session
        ups = [-np.asarray(v.cam_from_world)[1, :3] for v in s.views]
        up = np.mean(ups, 0)
        self.server.scene.set_up_direction(tuple(up / (np.linalg.norm(up) + 1e-12)))
        gui = self.server.gui
        gui.add_markdown(
            f"**ptovs view** · {s.scene.name} · {len(s.centers):,} Gaussians"
        )
        self.appearance = gui.add_dropdown(
            "Appearance", tuple(s.appearances), initial_value=NEUTRAL
        )
        self.text = gui.add_text("Phrase", initial_value="")
        self.ask = gui.add_button("Highlight")
        self.clear = gui.add_button("Clear")
        self.status = gui.add_markdown("Type a phrase and press Highlight.")
        self.nearest = gui.add_button("Nearest photo")
        self.export = gui.add_button("Export selection (PLY)")
        self.play = gui.add_button("Play tour")
        self.heat = gui.add_image(
            np.zeros((heat_width * 3 // 4, heat_width, 3), np.uint8),
            label="Relevancy (current view)",
        )
        self.appearance.on_update(lambda _: self.set_appearance(self.appearance.value))
        self.ask.on_click(lambda e: self.ask_phrase(self.text.value, e.client))
        self.clear.on_click(lambda e: self.clear_phrase(e.client))
        self.nearest.on_click(lambda e: self.go_nearest(e.client))
        self.export.on_click(lambda _: self.export_selection())
        self.play.on_click(lambda e: self.play_tour(e.client))
        self.server.on_client_connect(self._connected)
        self.draw()
        self.draw_sky()

    # each handler is a plain method: tests call them, the page calls them
    def draw(self) -> None:
        """Send the splats' colours: the whole node once, then only its buffer with
        the colour words replaced (the page keeps its geometry)."""
        s = self.session
        with s.lock:
            rgb = s.colors()
        if self.splats is None:
            self.splats = self.server.scene.add_gaussian_splats(
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
        with self.session.lock:
            pos, rgb, radius = self.session.sky_points()
        spacing = radius * np.sqrt(4 * np.pi / len(pos))  # between dome points
        self.sky = self.server.scene.add_point_cloud(
            "/sky", pos, rgb, point_size=float(1.5 * spacing)
        )

    def set_appearance(self, name: str) -> None:
        self.session.appearance = name
        self.draw()
        self.draw_sky()

    def ask_phrase(self, text: str, client=None) -> QueryAnswer | None:
        t0 = time.perf_counter()
        s = self.session
        try:
            with s.lock:
                answer = s.query(text)
        except InputError as exc:
            self.status.content = f"⚠ {exc}"
            return None
        self.draw()  # the highlighted colours go out first, then the status line
        sent = time.perf_counter() - t0
        self.status.content = answer.line(sent)
        self.refresh_heatmap(client)
        return answer

    def clear_phrase(self, client=None) -> None:
        self.session.clear()
        self.status.content = "Type a phrase and press Highlight."
        self.draw()
        self.refresh_heatmap(client)

    def _client(self, client=None):
        """The client an event came from, else the first connected (or None)."""
        if client is None:
            clients = list(self.server.get_clients().values())
            client = clients[0] if clients else None
        return client

    def refresh_heatmap(self, client=None) -> None:
        client = self._client(client)
        if client is None:
            return
        cam = _camera_of(client.camera, self.heat_width)
        with self.session.lock:
            self.heat.image = self.session.heatmap(cam)

    def go_nearest(self, client=None) -> None:
        client = self._client(client)
        if client is None:
            self.status.content = "No browser is connected."
            return
        view = self.session.nearest_view(np.asarray(client.camera.position, float))
        wxyz, pos = _pose_of(view.cam_from_world)
        with client.atomic():
            client.camera.wxyz, client.camera.position = wxyz, pos
        self.status.content = f"At photo {view.name}."

    def export_selection(self) -> Path | None:
        try:
            with self.session.lock:
                path = self.session.export()
        except InputError as exc:
            self.status.content = f"⚠ {exc}"
            return None
        self.status.content = f"Wrote {path}"
        return path

    def play_tour(self, client=None, frames: int = 90, fps: float = 30.0) -> None:
        client = self._client(client)
        if client is None:
            self.status.content = "No browser is connected."
            return
        for cam in self.session.tour(frames):
            wxyz, pos = _pose_of(cam.cam_from_world.numpy())
            with client.atomic():
                client.camera.wxyz, client.camera.position = wxyz, pos
            time.sleep(1 / fps)

    def _connected(self, client) -> None:
        view = self.session.views[0]
        wxyz, pos = _pose_of(view.cam_from_world)
        with client.atomic():
            client.camera.wxyz, client.camera.position = wxyz, pos
        self.refresh_heatmap(client)

    def stop(self) -> None:
        self.server.stop()


@click.command(name="view")
@chain_options(variant="one", force=None)
@click.option(
    "--host",
    default="127.0.0.1",
    show_default=True,
    help="Address to serve on; 0.0.0.0 exposes the page to the network.",
)
@click.option(
    "--port",
    type=click.IntRange(1, 65535),
    default=8080,
    show_default=True,
    help="Port to serve on (an error if in use).",
)
@click.option(
    "--out-dir",
    type=click.Path(path_type=Path),
    default=Path("view-exports"),
    show_default=True,
    help="Where 'Export selection' writes PLYs.",
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
    port: int,
    out_dir: Path,
    heat_width: int,
    variant: str,
    sets: tuple[str, ...],
) -> None:  # fmt: skip
    """Serve a page to roam the scene and highlight what a phrase describes.

    Needs the trained chain (`ptovs train-male`, or `make demo`) and viser
    (`make setup` installs it: the [view] extra, then viser==1.0.0 --no-deps).
    Prints the URL; Ctrl-C stops the server. Buttons: Highlight the phrase,
    Clear, Nearest photo, Export selection (PLY, into --out-dir), Play tour.
    """
    t0 = time.perf_counter()
    check_port(host, port)
    chain, ref = ready_chain(obj, scene_name, data, variant, sets)
    try:
        import viser  # noqa: F401
    except ImportError:
        raise InputError(
            "view: the viewer needs viser; install it as `make setup` does: pip "
            "install -e '.[view]' && pip install --no-deps viser==1.0.0"
        ) from None
    session = ViewSession(chain, out_dir)
    page = Page(session, host, port, heat_width)
    click.echo(
        f"view {ref.name}: http://{host}:{port}  ({len(session.centers):,} Gaussians,"
        f" ready in {time.perf_counter() - t0:.1f} s; Ctrl-C stops)"
    )
    # Ctrl-C (and a TERM) stop the server, even when started with SIGINT ignored
    # (a background job of a non-interactive shell inherits that)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        click.echo("view: stopped")
    finally:
        page.stop()
        session.close()

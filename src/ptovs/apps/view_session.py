"""The viewer's session: a trained chain loaded once and shared by every browser.

`ViewSession` loads the chain, bakes each appearance's colours and sky dome once,
answers phrase queries on the Gaussians as `ptovs select` does (a bounded cache),
draws a camera's relevancy heatmap and exports selections as 3DGS PLYs. It knows
nothing of the page (`ptovs.apps.view`); every client input it takes is checked
here (`clean_phrase`, `check_appearance`), and `plain` turns client text into
characters that cannot form markup.
"""

from __future__ import annotations

import re
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ptovs.apps import close_inputs
from ptovs.errors import InputError
from ptovs.field.model import SH_C0
from ptovs.raster import Camera
from ptovs.settings import RunContext

HIGHLIGHT = (1.0, 0.0, 1.0)  # selected Gaussians: magenta, found by the browser test
NEUTRAL = "neutral (mean of the photos)"
SKY_POINTS = 20000  # the sky dome: a Fibonacci sphere of points coloured by f_sky
MAX_PHRASE = 200  # characters of a phrase
ANSWERS = 64  # phrase answers kept (least recently used dropped)
EXTRA_PHRASES = 16  # phrases the querier holds beyond its own before it forgets them
MAX_EXPORTS_TOTAL = 200  # PLYs one server may write


def plain(text: str) -> str:
    """`text` for the page's markdown as plain characters: everything but ASCII
    letters, digits and spaces becomes a character reference, so nothing a client
    typed can form markup or an MDX expression."""
    return "".join(
        c if (c.isascii() and c.isalnum()) or c == " " else f"&#{ord(c)};"
        for c in str(text)
    )


def clean_phrase(text) -> str:
    """A client's phrase: text, printable, whitespace folded, 1 to MAX_PHRASE
    characters; else InputError."""
    if not isinstance(text, str):
        raise InputError("view: the phrase must be text")
    text = " ".join("".join(c if c.isprintable() else " " for c in text).split())
    if not text:
        raise InputError("view: the phrase is empty; type what to look for")
    if len(text) > MAX_PHRASE:
        raise InputError(
            f"view: a phrase of {len(text):,} characters; at most {MAX_PHRASE}"
        )
    return text


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
        """The panel's status line (markdown; the phrase as plain characters);
        `sent`: seconds from the press to the new colours handed to the page."""
        took = f"select {self.seconds * 1e3:.0f} ms"
        if sent is not None:
            took += f", highlight sent {sent * 1e3:.0f} ms"
        return (
            f"**{plain(self.text)}**: {self.selected:,} of {self.total:,} Gaussians, "
            f"level {plain(self.level)}, score {self.score:.3f} ({took})"
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


def camera_centre(cam_from_world: np.ndarray) -> np.ndarray:
    t = np.asarray(cam_from_world, float)
    return -t[:3, :3].T @ t[:3, 3]


class ViewSession:
    """A trained chain loaded once for interactive use, shared by every browser:
    baked colours per appearance, phrase queries on the Gaussians (answers kept
    in a bounded cache, by case-folded phrase), heatmaps of any camera, exports.
    Thread-safe (viser calls back from a thread pool).

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
        self.querier.base = len(self.querier.phrases)  # never forgotten
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
        self._answers: OrderedDict[str, QueryAnswer] = OrderedDict()
        self.exports = 0
        self.lock = threading.RLock()

    def close(self) -> None:
        close_inputs(self.inputs)

    # ------------------------------------------------------------ appearance --
    def check_appearance(self, appearance) -> str:
        """`appearance` if it is one of the scene's (else InputError)."""
        if not isinstance(appearance, str) or appearance not in self.appearances:
            raise InputError(
                f"view: no appearance {str(appearance)[:80]!r}; choose one of the "
                "scene's photos"
            )
        return appearance

    def baked(self, appearance: str) -> tuple[np.ndarray, np.ndarray]:
        """(RGB [P, 3] of every Gaussian, sky dome RGB [SKY_POINTS, 3]) under an
        appearance (a photo name or NEUTRAL), float32 in [0, 1]; baked once."""
        appearance = self.check_appearance(appearance)
        with self.lock:
            if appearance not in self._baked:
                self._baked[appearance] = self._bake(appearance)
            return self._baked[appearance]

    def _bake(self, appearance: str) -> tuple[np.ndarray, np.ndarray]:
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
        return rgb, sky

    def _embedding(self, appearance: str) -> torch.Tensor | None:
        """[1, D]: the appearance's embedding (None for a plain field)."""
        if self.field.nets is None or not self.field.embeddings:
            return None
        from ptovs.field.export import appearance_embedding

        return appearance_embedding(self.field, _image(appearance))[None]

    def colors(self, appearance: str, answer: QueryAnswer | None) -> np.ndarray:
        """RGB [P, 3] to show: the appearance's, the selection in HIGHLIGHT."""
        rgb = self.baked(appearance)[0].copy()
        if answer is not None:
            rgb[answer.mask] = HIGHLIGHT
        return rgb

    def sky_points(self, appearance: str) -> tuple[np.ndarray, np.ndarray, float]:
        """(positions [S, 3], RGB [S, 3], radius) of the sky dome: a sphere three
        times as far from the scene's centre as its farthest camera."""
        cams = np.stack([camera_centre(v.cam_from_world) for v in self.views])
        centre = np.median(self.centers, 0)
        radius = 3.0 * float(np.max(np.linalg.norm(cams - centre, axis=1)) + 1e-6)
        pos = centre + radius * _fibonacci_sphere(SKY_POINTS)
        return pos.astype(np.float32), self.baked(appearance)[1], radius

    # ---------------------------------------------------------------- queries --
    def _phrase(self, text: str) -> str:
        """`text` made answerable by the querier, which forgets the phrases it
        was given after its own once more than EXTRA_PHRASES are held."""
        q = self.querier
        if text not in q.index and len(q.phrases) - q.base >= EXTRA_PHRASES:
            q.truncate(q.base)
        (text,) = q.add_queries([text])
        return text

    def query(self, text) -> QueryAnswer:
        """Select the Gaussians `text` describes (as `ptovs select`); InputError
        for a phrase that is not text, too long, or one the encoder cannot embed.
        Answers are kept (ANSWERS, least recently used dropped) by the phrase
        case-folded: the first casing asked answers for all."""
        from ptovs.field.query import SelectOptions

        text = clean_phrase(text)
        key = text.casefold()
        with self.lock:
            if key in self._answers:
                self._answers.move_to_end(key)
                return self._answers[key]
            t0 = time.perf_counter()
            text = self._phrase(text)
            sel = self.querier.select(text, SelectOptions())
            answer = QueryAnswer(
                text=text,
                level=str(self.querier.levels[sel.level]),
                score=float(sel.score),
                selected=int(sel.mask.sum()),
                total=len(sel.mask),
                seconds=time.perf_counter() - t0,
                mask=np.asarray(sel.mask, bool),
            )
            self._answers[key] = answer
            while len(self._answers) > ANSWERS:
                self._answers.popitem(last=False)
            return answer

    def heatmap(
        self, cam: Camera, appearance: str, answer: QueryAnswer | None
    ) -> np.ndarray:
        """[H, W, 3] uint8: the answer's relevancy in `cam` over the render under
        `appearance` (the plain render when no answer is given)."""
        from ptovs.visual import heatmap, to_uint8

        appearance = self.check_appearance(appearance)
        with self.lock, torch.no_grad():
            rgb = self.field.render(cam, self._embedding(appearance))[0].numpy()
            if answer is None:
                return to_uint8(rgb)
            (res,) = self.querier.answer_view(cam, [self._phrase(answer.text)])
        return heatmap(res.smoothed[res.level], rgb)

    # -------------------------------------------------------------- cameras --
    def nearest_view(self, position: np.ndarray):
        """The photo whose camera centre is nearest `position`."""
        d = [
            np.linalg.norm(camera_centre(v.cam_from_world) - position)
            for v in self.views
        ]
        return self.views[int(np.argmin(d))]

    def tour(self, frames: int, width: int = 320, height: int = 240) -> list[Camera]:
        """The `roam` path's cameras."""
        from ptovs.apps.roam import camera_path, pick_keyframes

        train = self.scene.train_views()
        keys = pick_keyframes(train, 8, np.median(self.centers, 0))
        return camera_path(keys, frames, width, height)

    # --------------------------------------------------------------- export --
    def export(self, answer: QueryAnswer | None, appearance: str) -> Path:
        """Write the selection as a 3DGS PLY under out_dir (a fresh name, never
        over a file); its appearance is the given one. At most
        MAX_EXPORTS_TOTAL per session."""
        from ptovs.field.export import export_field_ply

        if answer is None or answer.selected == 0:
            raise InputError("view: nothing is selected; ask for a phrase first")
        appearance = self.check_appearance(appearance)
        slug = re.sub(r"[^A-Za-z0-9]+", "-", answer.text).strip("-")[:60] or "sel"
        with self.lock:
            if self.exports >= MAX_EXPORTS_TOTAL:
                raise InputError(
                    f"view: this server has written {self.exports} PLYs, its limit; "
                    "restart it to export more"
                )
            self.out_dir.mkdir(parents=True, exist_ok=True)
            n = 1
            while (path := self.out_dir / f"{slug}-{n}.ply").exists():
                n += 1
            export_field_ply(
                self.inputs.reconstruct,
                path,
                image=_image(appearance),
                index=answer.mask,
                field=self.field,
            )
            self.exports += 1
        return path


def ready_chain(obj: RunContext, scene_name, data, variant, sets):
    """The chain, or an InputError naming the command that trains what is missing
    (the viewer never trains: that takes minutes)."""
    from ptovs.options import variant_chain

    chain, ref = variant_chain(obj, scene_name, data, variant, sets, until="train-male")
    for stage in chain.closure("train-male"):
        state, _ = chain.state(stage)
        if state != "done":
            raise InputError(
                f"view: scene {ref.name} has no trained language field ({stage} is "
                f"{state}); run first: {chain.hint('train-male')}"
            )
    return chain, ref

"""Every picture the README shows from `make demo`, and the figures its captions quote.

    python bench/pictures.py                            # data/demo_s0, work/demo_s0
    python bench/pictures.py --data D/demo_s0 --work W --figures /tmp/figures.json

From a finished demo work folder (`make demo`: the query, evaluate, select and style
outputs must be there), into --docs (docs/img):
  demo_overlay.png  one view's heatmap | overlay per query, enlarged 2x
  select.png        a labelled photo, the field rendered at its camera, and the
                    Gaussians --text selects rendered alone, enlarged 2x
  style_votes.png   the first voting view's style panel (`ptovs style`'s own)
  view_demo.png     `ptovs view` in Debian's chromium (Playwright) with --text
                    highlighted; --no-browser leaves it as it is
and --figures: the demo's mIoU / mPA / mP (evaluate), --text's selected Gaussians
of the total with level and score (select), the style vote (style), and the
viewer's status line for the screenshot.

It works on a private copy of <work>/<scene> (the demo's folder is only read) and
checks that its own selection is the one the demo's `select` recorded.
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import ROOT  # noqa: E402  (same folder)

VIEWPORT = {"width": 1000, "height": 700}
GAP = 2  # white pixels between the overlay picture's panels, before the enlargement


# the panel's phrase box (viser's mantine layout: the input beside the "Phrase" label)
PHRASE_INPUT = (
    "xpath=//label[text()='Phrase']/ancestor::div"
    "[contains(@class, 'mantine-Flex-root')][1]//input"
)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _write(path: Path, rgb: np.ndarray) -> None:
    from ptovs.visual import write_png

    path.parent.mkdir(parents=True, exist_ok=True)
    write_png(path, rgb)


def _pad(img: np.ndarray, width: int) -> np.ndarray:
    extra = width - img.shape[1]
    return np.pad(img, ((0, 0), (0, extra), (0, 0)), constant_values=255)


def compose(view_dir: Path, scale: int = 3) -> np.ndarray:
    """Rows [heatmap | overlay] for every query of one view, white between."""
    import cv2

    rows = []
    for heat in sorted(view_dir.glob("*_heatmap.png")):
        over = heat.with_name(heat.name.replace("_heatmap", "_overlay"))
        a, b = cv2.imread(str(heat)), cv2.imread(str(over))
        if a is None or b is None:
            raise SystemExit(f"cannot read {heat} or {over}: rerun `make demo`")
        h = max(a.shape[0], b.shape[0])
        a, b = (np.pad(x, ((0, h - x.shape[0]), (0, 0), (0, 0)), constant_values=255)
                for x in (a, b))  # fmt: skip
        rows.append(np.hstack([a, np.full((h, GAP, 3), 255, np.uint8), b]))
    if not rows:
        raise SystemExit(f"no *_heatmap.png in {view_dir}: run `make demo` first")
    width = max(r.shape[1] for r in rows)
    out = []
    for i, r in enumerate(rows):
        if i:
            out.append(np.full((GAP, width, 3), 255, np.uint8))
        out.append(_pad(r, width))
    pic = np.vstack(out)
    return cv2.resize(pic, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)


def overlay_picture(work: Path, scene: str, docs: Path) -> dict:
    """docs/demo_overlay.png from the first view of the demo's query output."""
    import cv2

    views = sorted(
        p for p in (work / scene / "query-out" / "male").iterdir() if p.is_dir()
    )
    if not views:
        raise SystemExit(f"no query output under {work / scene}: run `make demo` first")
    pic = compose(views[0], scale=2)  # BGR, as cv2 reads it
    _write(docs / "demo_overlay.png", cv2.cvtColor(pic, cv2.COLOR_BGR2RGB))
    return {"view": views[0].name, "size": [pic.shape[1], pic.shape[0]]}


def select_picture(
    work: Path, data: Path, config: Path, text: str, docs: Path, scale: int = 2
) -> dict:
    """docs/select.png: photo | field render | the selected Gaussians alone, at the
    first labelled view, enlarged `scale` times; the selection's figures."""
    import torch

    from ptovs.apps import close_inputs
    from ptovs.apps.select import select_gaussians
    from ptovs.config import load_config
    from ptovs.raster import Camera
    from ptovs.stage import Chain, RunContext, resolve_scene
    from ptovs.visual import to_uint8

    ctx = RunContext(work, load_config(config), False)
    ref = resolve_scene(ctx, None, data)
    sel, querier, inputs = select_gaussians(Chain(ctx, ref), text)
    try:
        field = querier.field
        scene = ref.load()
        view = scene.labelled_views()[0]
        cam = Camera.from_view(view)
        emb = field.embeddings_of([view.name])
        with torch.no_grad():
            full = field.render(cam, emb)[0].numpy()
            part = field.subset(torch.from_numpy(sel.mask)).render(cam, emb)[0].numpy()
        photo = scene.load_image(view)
        row = np.hstack([to_uint8(photo), to_uint8(full), to_uint8(part)])
        _write(docs / "select.png", np.repeat(np.repeat(row, scale, 0), scale, 1))
        return {
            "text": text,
            "view": view.name,
            "selected": int(sel.mask.sum()),
            "gaussians": int(len(sel.mask)),
            "share": round(float(sel.mask.mean()), 4),
            "level": str(querier.levels[sel.level]),
            "score": round(float(sel.score), 5),
        }
    finally:
        close_inputs(inputs)


def style_picture(work: Path, scene: str, data: Path, docs: Path) -> dict:
    """docs/style_votes.png: the first voting view's panel; the vote's figures."""
    out = work / scene / "style-out" / "male"
    panels = sorted(out.glob("*_styles.png"))
    if not panels or not (out / "style.json").is_file():
        raise SystemExit(f"no style output under {out}: run `make demo` first")
    docs.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(panels[0], docs / "style_votes.png")
    rec = json.loads((out / "style.json").read_text())
    truth = data / "synthetic" / "truth" / "parts.json"
    true = json.loads(truth.read_text()).get("style") if truth.is_file() else None
    return {
        "panel_view": panels[0].name.removesuffix("_styles.png"),
        "winner": rec["winner"],
        "votes": rec["votes"],
        "views": len(rec["views"]),
        "vote": rec["vote"],
        "true_style": true,
        "correct": None if true is None else rec["winner"] == true,
    }


def view_picture(work: Path, data: Path, config: Path, text: str, docs: Path) -> dict:
    """docs/view_demo.png: `ptovs view` in chromium with `text` highlighted (the
    command in a fresh process, opened at the URL it prints)."""
    from playwright.sync_api import sync_playwright

    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        raise SystemExit("no chromium: apt-get install chromium (or pass --no-browser)")
    port = free_port()
    cmd = [sys.executable, "-m", "ptovs", "--work-dir", str(work), "--config",
           str(config), "view", "--data", str(data), "--port", str(port)]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)  # fmt: skip
    try:
        line = ""
        while not line.startswith("view "):
            line = proc.stdout.readline()
            if not line and proc.poll() is not None:
                raise SystemExit(f"ptovs view ended: {proc.stdout.read()[-2000:]}")
        url = line.split()[2]
        with urllib.request.urlopen(url, timeout=60) as r:
            assert r.status == 200
        with sync_playwright() as pw:
            browser = pw.chromium.launch(
                executable_path=chromium,
                args=["--no-sandbox", "--use-gl=angle", "--use-angle=swiftshader",
                      "--enable-unsafe-swiftshader"],
            )  # fmt: skip
            tab = browser.new_page(viewport=VIEWPORT)
            tab.goto(url, wait_until="load")
            box = tab.locator(PHRASE_INPUT)
            box.wait_for(timeout=180_000)
            box.fill(text)
            time.sleep(1.5)  # the field's value reaches the server
            tab.get_by_role("button", name="Highlight").click()
            status = tab.get_by_text(re.compile(rf"^{re.escape(text)}: [\d,]+ of"))
            status.wait_for(timeout=180_000)
            time.sleep(3)  # software WebGL draws the highlighted splats
            docs.mkdir(parents=True, exist_ok=True)
            tab.screenshot(path=str(docs / "view_demo.png"))
            said = status.inner_text()
            browser.close()
    finally:
        proc.send_signal(signal.SIGINT)  # what Ctrl-C sends
        try:
            proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()
    m = re.search(
        r": ([\d,]+) of ([\d,]+) Gaussians, level (\S+), score ([\d.]+)", said
    )
    rec = {"status": said}
    if m:
        rec.update(selected=int(m[1].replace(",", "")),
                   gaussians=int(m[2].replace(",", "")), level=m[3],
                   score=float(m[4]))  # fmt: skip
    return rec


def _commit() -> str:
    """The checkout's commit (what the pictures and figures describe)."""
    res = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"],
                         capture_output=True, text=True, check=False)  # fmt: skip
    return res.stdout.strip() or "unknown"


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--data", type=Path, default=ROOT / "data" / "demo_s0",
                    help="the demo's scene folder")  # fmt: skip
    ap.add_argument("--work", type=Path, default=ROOT / "work",
                    help="the work folder `make demo` wrote (read only)")  # fmt: skip
    ap.add_argument("--config", type=Path, default=ROOT / "configs" / "demo.toml")
    ap.add_argument("--text", default="Minaret", help="the demo's DEMO_TEXT")
    ap.add_argument("--docs", type=Path, default=ROOT / "docs" / "img")
    ap.add_argument("--figures", type=Path, default=None,
                    help="default: <work>/<scene>/figures.json "
                         "(docs/results/demo.json is what the docs quote)")  # fmt: skip
    ap.add_argument("--no-browser", action="store_true",
                    help="leave view_demo.png (no chromium screenshot)")  # fmt: skip
    args = ap.parse_args()
    scene = args.data.resolve().name
    demo = args.work / scene
    for need in ("evaluate.json", "select.json"):
        if not (demo / need).is_file():
            raise SystemExit(f"no {demo / need}: run `make demo` first")
    ev = json.loads((demo / "evaluate.json").read_text())["results"]["male"][scene]
    recorded = json.loads((demo / "select.json").read_text())
    figures: dict = {
        "scene": scene,
        "measured": time.strftime("%Y-%m-%d"),
        "commit": _commit(),
        "evaluate": {k: round(ev[k], 4) for k in ("miou", "mpa", "mp")}
        | {"pairs": ev["pairs"]},
    }
    with tempfile.TemporaryDirectory(prefix="ptovs-pictures-") as tmp:
        work = Path(tmp) / "work"
        shutil.copytree(demo, work / scene, ignore=shutil.ignore_patterns("*.lock"))
        figures["overlay"] = overlay_picture(work, scene, args.docs)
        figures["select"] = select_picture(work, args.data, args.config, args.text,
                                           args.docs)  # fmt: skip
        if recorded.get("text") == args.text:
            got = figures["select"]["selected"], figures["select"]["gaussians"]
            if got != (recorded["selected"], recorded["gaussians"]):
                raise SystemExit(f"select now takes {got}, the demo recorded "
                                 f"{recorded['selected']} of {recorded['gaussians']}")  # fmt: skip
        figures["style"] = style_picture(work, scene, args.data, args.docs)
        if not args.no_browser:
            figures["view"] = view_picture(work, args.data, args.config, args.text,
                                           args.docs)  # fmt: skip
    out = args.figures or demo / "figures.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(figures, indent=1) + "\n")
    print(json.dumps(figures, indent=1))
    print(f"pictures: {args.docs}; figures: {out}")


if __name__ == "__main__":
    main()

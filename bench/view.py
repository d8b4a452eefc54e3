"""`ptovs view` on a trained chain (issue 25 targets): time to the first page, query →
highlight, and the frame rate the browser gets.

    python bench/view.py --data data/bench_s0 --work work            # a trained chain
    python bench/view.py --data data/tiny_s0 --work work --shot docs/img/view.png

Starts `ptovs view` in a fresh process and drives Debian's chromium through
Playwright (as tests/test_view.py does):
  start → first page   from launching the command to the page answering HTTP 200
                       (the process printed its URL), and to the panel drawn in the
                       browser (its "Phrase" field on screen)
  query → highlight    per phrase: on the server, select's decode, and the press
                       to the highlighted colours handed to the page (both printed
                       in the status line); in the page, a DOM click on Highlight to
                       the status line in the DOM (a MutationObserver's timestamp)
  frame rate           requestAnimationFrame callbacks per second in the page over
                       --fps-seconds, with the splats on screen (software WebGL:
                       chromium's SwiftShader on our CPU machines)

The chain must be trained (`ptovs evaluate --data D` first); results go to
<work>/bench_view.json and are printed as markdown rows.
"""

from __future__ import annotations

import argparse
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import ROOT, Results  # noqa: E402

PHRASE_INPUT = (
    "xpath=//label[text()='Phrase']/ancestor::div"
    "[contains(@class, 'mantine-Flex-root')][1]//input"
)
# in the page: press Highlight (a DOM click, no automation waits) and resolve with the
# milliseconds until a paragraph starts with "<phrase>: " (the status line arrived)
CLICK_JS = """(text) => new Promise((done) => {
  const seen = () => [...document.querySelectorAll('p')]
    .some((p) => p.textContent.startsWith(text + ': '));
  const t0 = performance.now();
  const obs = new MutationObserver(() => {
    if (seen()) { obs.disconnect(); done(performance.now() - t0); } });
  obs.observe(document.body, {subtree: true, childList: true, characterData: true});
  [...document.querySelectorAll('button')]
    .find((b) => b.textContent.trim() === 'Highlight').click();
})"""
FPS_JS = """(seconds) => new Promise((done) => {
  let n = 0; const t0 = performance.now();
  function tick(t) { n++; if (t - t0 < seconds * 1000) requestAnimationFrame(tick);
                     else done(n / ((t - t0) / 1000)); }
  requestAnimationFrame(tick);
})"""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--data", type=Path, required=True, help="the scene folder")
    ap.add_argument("--work", type=Path, default=ROOT / "work")
    ap.add_argument("--phrases", nargs="+", default=None,
                    help="default: the scene's first four vocabulary phrases")  # fmt: skip
    ap.add_argument("--fps-seconds", type=float, default=5.0)
    ap.add_argument("--shot", type=Path, help="save a screenshot with the first phrase")
    ap.add_argument("--set", dest="sets", action="append", default=[])
    args = ap.parse_args()
    from playwright.sync_api import sync_playwright

    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        sys.exit("no chromium: apt-get install chromium")
    phrases = args.phrases
    if phrases is None:
        from ptovs.encoders import scene_encoder

        phrases = list(scene_encoder(args.data).phrases)[:4]
    port = free_port()
    cmd = [sys.executable, "-m", "ptovs", "--work-dir", str(args.work)]
    cmd += [f"--set={s}" for s in args.sets]
    cmd += ["view", "--data", str(args.data), "--port", str(port)]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)  # fmt: skip
    row: dict = {"scene": args.data.name}
    try:
        # the URL carries the run's token: read it from the command's first line
        line = ""
        while not line.startswith("view "):
            line = proc.stdout.readline()
            if not line and proc.poll() is not None:
                sys.exit(f"ptovs view ended: {proc.stdout.read()[-2000:]}")
        url = line.split()[2]
        while True:
            if proc.poll() is not None:
                sys.exit(f"ptovs view ended: {proc.stdout.read()[-2000:]}")
            try:
                with urllib.request.urlopen(url, timeout=1) as r:
                    if r.status == 200:
                        break
            except OSError:
                time.sleep(0.05)
        row["first_http_s"] = time.perf_counter() - t0
        with sync_playwright() as pw:
            browser = pw.chromium.launch(
                executable_path=chromium,
                args=["--no-sandbox", "--use-gl=angle", "--use-angle=swiftshader",
                      "--enable-unsafe-swiftshader"],
            )  # fmt: skip
            tab = browser.new_page(viewport={"width": 1000, "height": 700})
            tab.goto(url, wait_until="load")
            box = tab.locator(PHRASE_INPUT)
            box.wait_for(timeout=120_000)
            row["first_panel_s"] = time.perf_counter() - t0
            time.sleep(2)
            row["fps_idle"] = tab.evaluate(FPS_JS, args.fps_seconds)
            row["queries"] = []
            for i, text in enumerate(phrases):
                box.fill(text)
                time.sleep(1.5)  # the field's value reaches the server
                t1 = time.perf_counter()
                page_ms = tab.evaluate(CLICK_JS, text)
                seconds = time.perf_counter() - t1
                status = tab.get_by_text(re.compile(rf"^{re.escape(text)}: [\d,]+ of"))
                line = status.inner_text()
                select_ms = float(re.search(r"select (\d+) ms", line).group(1))
                sent_ms = float(re.search(r"highlight sent (\d+) ms", line).group(1))
                row["queries"].append(
                    {"text": text, "highlight_s": seconds, "page_ms": page_ms,
                     "server_select_ms": select_ms, "server_sent_ms": sent_ms,
                     "status": line}
                )  # fmt: skip
                if i == 0:
                    time.sleep(2)
                    row["fps_highlighted"] = tab.evaluate(FPS_JS, args.fps_seconds)
                    if args.shot:
                        args.shot.parent.mkdir(parents=True, exist_ok=True)
                        tab.screenshot(path=str(args.shot))
            browser.close()
    finally:
        proc.send_signal(signal.SIGINT)  # what Ctrl-C sends
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
    out = proc.stdout.read()
    row["stopped_cleanly"] = proc.returncode == 0 and "view: stopped" in out
    res = Results(args.work / "bench_view.json")
    res[args.data.name] = row
    res.save()
    print("| scene | first HTTP (s) | panel drawn (s) | fps idle | fps highlighted |")
    print("|---|---|---|---|---|")
    print(
        f"| {row['scene']} | {row['first_http_s']:.1f} | {row['first_panel_s']:.1f} | "
        f"{row['fps_idle']:.1f} | {row['fps_highlighted']:.1f} |"
    )
    print("| phrase | server: select (ms) | server: press → colours sent (ms) "
          "| page: click → status in the DOM (ms) | status |")  # fmt: skip
    print("|---|---|---|---|---|")
    for q in row["queries"]:
        print(
            f"| {q['text']} | {q['server_select_ms']:.0f} | {q['server_sent_ms']:.0f} "
            f"| {q['page_ms']:.0f} | {q['status']} |"
        )


if __name__ == "__main__":
    main()

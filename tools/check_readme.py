"""Run the commands of the README and the guide as written: `make check-readme`.

    python tools/check_readme.py [--root work/readme] [--keep-going]

Every `ptovs` line of the ```bash blocks of README.md and docs/guide.md that names a synthetic scene
(`data/bench_s1`, `data/tiny_s0`, ...) runs as written, one after the other, in
a folder of its own (`--root`): the README's own `ptovs synth-scene data ...` lines
make the scenes there, `configs/` is the repository's. `[...]` marks an optional
part of a line, which runs too unless it holds a placeholder. Lines that name what only a user has (a folder of
photos, a PT-OVS scene, a cluster, a checkpoint) and templates (`<stage>`, `NAME`)
are listed and not run; tests/test_readme.py checks each of those parses, with
valid settings. `ptovs view` serves until stopped, so it is started, checked to
print its URL, and stopped. Prints a table (line, exit code, seconds) and exits 1
when a line failed. The whole run takes about an hour on 2 cores (the `bench`
scene through every variant the README names).
"""

from __future__ import annotations

import argparse
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
GUIDE = ROOT / "docs" / "guide.md"
DOCS = (README, GUIDE)  # the pages whose commands a user copies
SYNTHETIC = re.compile(r"\bdata/(tiny|small|bench)_s\d+\b|\bsynth-scene data\b")
TEMPLATE = re.compile(r"<[a-z]+>|\bNAME\b|\bDIR\b|\bIMAGE\b|key=value")
BLOCKS = re.compile(r"```bash\n(.*?)```", re.S)  # a page's command blocks


def readme_lines() -> list[str]:
    """Each `ptovs` command line of the docs' bash blocks, comments removed."""
    out = []
    blocks = [b for page in DOCS for b in BLOCKS.findall(page.read_text())]
    for block in blocks:
        for line in block.replace("\\\n", " ").splitlines():
            words = shlex.split(line, comments=True)
            if words and words[0] == "ptovs":
                out.append(shlex.join(words))
    return out


def as_written(line: str) -> list[str] | None:
    """The argv of a line, its optional `[...]` parts included, except those that
    hold a placeholder (`[--image IMAGE]`); None for a template line."""
    out, group = [], None
    for w in shlex.split(line):
        if group is None and w.startswith("["):
            group = []
        if group is None:
            out.append(w)
            continue
        group.append(w.strip("[]"))
        if w.endswith("]"):
            if not TEMPLATE.search(" ".join(group)):
                out += [g for g in group if g]
            group = None
    return None if TEMPLATE.search(" ".join(out)) else out


def run_view(argv: list[str], cwd: Path, env: dict) -> tuple[int, str]:
    """Start the viewer, wait for its URL, stop it: 0 when the URL was printed."""
    proc = subprocess.Popen(argv, cwd=cwd, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True,
                            start_new_session=True)  # fmt: skip
    seen = ""
    t0 = time.monotonic()
    try:
        while time.monotonic() - t0 < 1800:
            line = proc.stdout.readline()
            if not line:
                break
            seen += line
            if re.search(r"http://127\.0\.0\.1:\d+/\S+/", line):
                return 0, seen
    finally:
        os.killpg(proc.pid, signal.SIGINT)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
    return proc.poll() or 1, seen


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--root", type=Path, default=ROOT / "work" / "readme")
    ap.add_argument("--keep-going", action="store_true",
                    help="run the remaining lines after a failure")  # fmt: skip
    args = ap.parse_args()
    root = args.root.resolve()
    root.mkdir(parents=True, exist_ok=True)
    if not (root / "configs").exists():
        shutil.copytree(ROOT / "configs", root / "configs")
    env = dict(os.environ)
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    rows, failed = [], False
    for line in readme_lines():
        argv = as_written(line)
        if argv is None or not SYNTHETIC.search(line):
            rows.append((line, "not run (the user's data or a template)", ""))
            continue
        t0 = time.perf_counter()
        if argv[1:2] == ["view"]:
            rc, out = run_view(argv, root, env)
        else:
            proc = subprocess.run(argv, cwd=root, env=env, capture_output=True,
                                  text=True)  # fmt: skip
            rc, out = proc.returncode, proc.stdout + proc.stderr
        secs = time.perf_counter() - t0
        ran = shlex.join(argv)
        rows.append((ran, str(rc), f"{secs:.0f}"))
        print(f"{'ok ' if rc == 0 else 'FAIL'} {secs:7.0f} s  {ran}", flush=True)
        if rc != 0:
            failed = True
            print(out[-3000:], flush=True)
            if not args.keep_going:
                break
    print("\n| README line | exit | s |\n|---|---|---|")
    for line, rc, secs in rows:
        print(f"| `{line}` | {rc} | {secs} |")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())

"""Benchmark the batch drivers (issue 26 targets): `make -j2 all` against the
Snakemake workflow, on one machine and through a single-node Slurm.

python bench/cluster.py --parts make local slurm --work work/cluster
python bench/cluster.py --parts stages --work work/cluster     # per-stage figures

Parts (each from an empty work folder, default config, one after the other):
  make    7 tiny synthetic scenes (seeds 0-6) through `make -j2 all`: wall time,
          the per-scene table
  local   the same through `snakemake --profile workflow/profiles/local --cores 2`
  slurm   the same through the slurm profile on a single-node Slurm started here
          (workflow/slurm-local/start.sh; root; 2 CPUs, one thread a job): wall
          time, the table, and per job from sacct: rule, scene, state, elapsed,
          requested memory, MaxRSS of the job's step
  stages  the `bench` preset's seed 0 through the local profile with 2 cores:
          each stage's wall time and peak RSS (the workflow's benchmark files),
          the figures src/ptovs/pipeline.py's RESOURCES come from
  paper   no run: the seven PT-OVS scenes on a 16-node cluster from `stages` and
          bench/extract_gpu.py's per-photo backend cost (the model is in paper_part)
  growth  no run: the same from each stage's measured growth at a real photo size
          (bench/growth.py's results, copied to <work>/growth.json; growth_part),
          each CPU stage sped up by its measured gain at RESOURCES' threads over 2
          (bench/threads.py's results on a many-core machine, copied to
          <work>/threads.json, when there)
Results: <work>/cluster.json (a part's entry is replaced when it is rerun).
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import ROOT, bench_scene, run_ptovs  # noqa: E402  (same folder)
from growth import fit_power  # noqa: E402  (same folder)

from ptovs.pipeline import PIPELINE as PIPELINE_STAGES  # noqa: E402

SNAKEFILE = ROOT / "workflow" / "Snakefile"
PROFILES = ROOT / "workflow" / "profiles"


def tiny_data(root: Path, n: int = 7) -> Path:
    data = root / "tiny_data"
    for seed in range(n):
        if not (data / f"tiny_s{seed}" / "dense").is_dir():
            run_ptovs(
                root, "synth-scene", str(data), "--preset", "tiny", "--seed", str(seed)
            )
    return data


def timed(cmd: list[str], cwd: Path, work: Path, env: dict | None = None) -> dict:
    """Run a batch driver: its wall time, exit code, the table it left in `work` and,
    when it failed, the tail of its output."""
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    table = work / "table.md"
    return {"wall_s": round(wall, 1), "exit": proc.returncode,
            "table": table.read_text() if table.exists() else "",
            "tail": proc.stdout[-4000:] + proc.stderr[-4000:] if proc.returncode else ""}  # fmt: skip


def fresh(path: Path) -> Path:
    shutil.rmtree(path, ignore_errors=True)
    path.mkdir(parents=True)
    return path


def make_part(root: Path) -> dict:
    data, work = tiny_data(root), fresh(root / "make_work")
    cmd = ["make", "-s", "-j2", "all", f"DATA={data}", f"WORK={work}", "SETUP=",
           f"PTOVS_BIN={sys.executable} -m ptovs"]  # fmt: skip
    return timed(cmd, ROOT, work)


def snakemake(profile: str, data: Path, work: Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", "snakemake", "-s", str(SNAKEFILE),
            "--profile", str(PROFILES / profile), *extra,
            "--config", f"data={data}", f"work={work}"]  # fmt: skip


def local_part(root: Path) -> dict:
    data, work = tiny_data(root), fresh(root / "local_work")
    return timed(
        snakemake("local", data, work, "--cores", "2"), fresh(root / "local_run"), work
    )


def sacct(env: dict) -> list[dict]:
    fields = "JobID,Comment%80,Partition,State,Elapsed,ReqMem,AllocCPUS,MaxRSS"
    out = subprocess.run(["sacct", "-a", "-P", "--units=M", "-o", fields], env=env,
                         capture_output=True, text=True, check=True).stdout  # fmt: skip
    names = fields.replace("%80", "").split(",")
    rows = [
        dict(zip(names, line.split("|"), strict=True)) for line in out.splitlines()[1:]
    ]
    steps = {r["JobID"].split(".")[0]: r for r in rows if r["JobID"].endswith(".0")}
    jobs = []
    for r in rows:
        if "." in r["JobID"]:
            continue
        rule, _, scene = r["Comment"].removeprefix("rule_").partition("_wildcards_")
        step = steps.get(r["JobID"], {})
        jobs.append({"job": r["JobID"], "rule": rule, "scene": scene, "state": r["State"],
                     "elapsed": r["Elapsed"], "req_mem": r["ReqMem"], "cpus": r["AllocCPUS"],
                     "max_rss": step.get("MaxRSS", "")})  # fmt: skip
    return jobs


def slurm_part(root: Path) -> dict:
    data, work = tiny_data(root), fresh(root / "slurm_work")
    # a new private folder each run: start.sh refuses one it did not make (or that
    # others can write), and a fixed /tmp name could be anyone's. In /tmp, not $TMPDIR:
    # munged wants the folders above its socket searchable by all, the path short.
    cluster = Path(tempfile.mkdtemp(prefix="ptovs-bench-slurm-", dir="/tmp"))
    start = subprocess.run(["bash", str(ROOT / "workflow/slurm-local/start.sh"), str(cluster)],
                           capture_output=True, text=True)  # fmt: skip
    if start.returncode:
        shutil.rmtree(cluster, ignore_errors=True)
        return {"error": start.stderr[-4000:]}
    env = {**os.environ, "SLURM_CONF": str(cluster / "slurm.conf"),
           "PATH": f"{cluster / 'bin'}:{os.environ['PATH']}"}  # fmt: skip
    try:
        cmd = snakemake("slurm", data, work, "--default-resources", "slurm_partition=cpu",
                        "slurm_account=ptovs", "--max-threads", "1",
                        "--slurm-init-seconds-before-status-checks", "5")  # fmt: skip
        res = timed(cmd, fresh(root / "slurm_run"), work, env)
        res["jobs"] = sacct(env)
    finally:
        subprocess.run(["bash", str(ROOT / "workflow/slurm-local/stop.sh"), str(cluster)],
                       capture_output=True)  # fmt: skip
        shutil.rmtree(cluster, ignore_errors=True)
    return res


def stages_part(root: Path) -> dict:
    """bench seed 0, one scene, 2 cores: per-stage wall and peak RSS."""
    scene = bench_scene(root / "bench_data", 0)
    work = fresh(root / "stages_work")
    res = timed(
        snakemake("local", scene.parent, work, "--cores", "2")
        + [f"scenes={scene.name}"],
        fresh(root / "stages_run"),
        work,
    )
    stages = {}
    for tsv in sorted((work / scene.name / "bench").glob("*.tsv")):
        with tsv.open() as f:
            row = next(csv.DictReader(f, delimiter="\t"))
        stages[tsv.stem] = {
            "wall_s": float(row["s"]),
            "max_rss_mb": float(row["max_rss"]),
        }
    return {**res, "scene": scene.name, "stages": stages}


# The seven PT-OVS scenes: train photos (docs/method.md §1.1)
PT_OVS = {"brandenburg": 763, "trevi": 1689, "buckingham": 1379, "notre": 2934,
          "pantheon": 1308, "taj": 1238, "temple": 859}  # fmt: skip
BENCH_VIEWS, BENCH_MP = 80, 320 * 240 / 1e6  # the `bench` preset's train photos
PT_MP = 700 * 470 / 1e6  # a PhotoTourism photo at the authors' r = 2
STEP_EXPONENT = 0.87  # reconstruct s/step ~ MP^0.87 (bench 0.12 s at 0.077 MP, real 0.59 s at 0.48 MP)
# one photo through SAM ViT-H (32x32 points, one crop layer) + OpenCLIP ViT-B-16 on 256
# crops, random weights (bench/extract_gpu.py): H200 2.63 + 0.06 s; 16 CPU cores 182 s
SAM_CLIP_GPU_S, SAM_CPU_S, IMAGES_PER_VIEW = 2.69, 182.0, 5


def paper_part(root: Path) -> dict:
    """The seven PT-OVS scenes on a 16-node cluster, on paper, from the `stages`
    part's per-stage wall times on bench (2 threads) and the backends' per-photo
    cost on a GPU (bench/extract_gpu.py). Each scene's chain is sequential; with
    7 scenes on 16 nodes every chain has its own node, so the wall time is the
    longest chain (the critical path) plus the queue's turn-around per job."""
    stages = json.loads((root / "cluster.json").read_text())["stages"]["stages"]
    rho = PT_MP / BENCH_MP
    w = {s: stages[s]["wall_s"] for s in stages}

    def chain(n: int) -> dict[str, float]:
        per_view = n / BENCH_VIEWS
        return {
            # steps fixed, each ~MP^0.87; then one render a photo (the residual masks)
            "reconstruct": w["reconstruct"] * rho**STEP_EXPONENT
            + per_view * w["render-appearances"] * rho / 4,
            "render-appearances": w["render-appearances"] * per_view * rho,
            "extract-features (GPU)": n * IMAGES_PER_VIEW * SAM_CLIP_GPU_S,
            "uncertainty": w["uncertainty"] * per_view * rho,
            "train-ae": w["train-ae"] * per_view,  # segments, not pixels
            "train-male": w["train-male"] * per_view * rho,
            "query": w["query"] * rho * 3,  # 8-27 labelled photos against bench's few
            "evaluate": w["evaluate"] * 3,
        }

    per_scene = {name: chain(n) for name, n in PT_OVS.items()}
    totals = {name: sum(c.values()) for name, c in per_scene.items()}
    worst = max(totals, key=totals.get)
    cpu_extract = {name: n * IMAGES_PER_VIEW * SAM_CPU_S for name, n in PT_OVS.items()}
    queue_s = 60 * len(w)  # a minute of queue and status polling per job
    return {"rho": round(rho, 2), "per_scene_s": per_scene, "totals_s": totals,
            "critical_path": worst, "wall_s": totals[worst] + queue_s,
            "extract_on_cpu_s": cpu_extract, "node_hours": sum(totals.values()) / 3600}  # fmt: skip


def growth_part(root: Path) -> dict:
    """The seven PT-OVS scenes on a 16-node cluster, on paper, from the measured
    growth of each stage at a real photo size (bench/growth.py's <root>/growth.json,
    the `landmark` preset: 640-760 px, 0.37 MP a photo against PT-OVS's 0.33 MP, so
    the figures lean long): a stage's time at n photos is a·n^b fitted to its
    measured sizes (2 threads, our machine), extract-features' taken instead from
    the real backends on a GPU as in `paper` (the stand-in's time says nothing of
    SAM's). Peak memory: the largest measured, and a·n^b at n when b > 0.05.
    Threads: a CPU stage's time is divided by its speed-up at RESOURCES' threads
    over 2 threads, measured on one machine (<root>/threads.json from
    bench/threads.py; 1 where the stage asks for 2 threads or was not measured)."""
    from ptovs.pipeline import RESOURCES

    growth = json.loads((root / "growth.json").read_text())
    thr_path = root / "threads.json"
    thr = json.loads(thr_path.read_text())["runs"] if thr_path.exists() else {}

    def speedup(stage: str) -> float:
        base = thr.get("2", {}).get(stage, {})
        want = thr.get(str(RESOURCES[stage].threads), {}).get(stage, {})
        if base.get("exit") == 0 and want.get("exit") == 0 and want["wall_s"] > 0:
            return base["wall_s"] / want["wall_s"]
        return 1.0

    runs = [r for r in growth["runs"].values()
            if r.get("preset") == "landmark" and r.get("photos")]  # fmt: skip

    def fit(points: list[tuple[float, float]]) -> tuple[float, float]:
        # one size: linear in photos
        return fit_power(points) or (points[0][1] / points[0][0], 1.0)

    model: dict[str, dict] = {}
    for stage in PIPELINE_STAGES:
        recs = [(r["photos"], r["stages"][stage]) for r in runs
                if r.get("stages", {}).get(stage, {}).get("exit") == 0]  # fmt: skip
        if not recs:
            continue
        a, b = fit([(n, rec["wall_s"]) for n, rec in recs])
        am, bm = fit([(n, rec["peak_rss_mb"]) for n, rec in recs])
        model[stage] = {"a": a, "b": round(b, 3), "mem_a": am, "mem_b": round(bm, 3),
                        "sizes": [n for n, _ in recs],
                        "threads": RESOURCES[stage].threads,
                        "speedup": round(speedup(stage), 3),
                        "peak_mb": max(rec["peak_rss_mb"] for _, rec in recs)}  # fmt: skip

    def chain(n: int) -> dict[str, float]:
        out = {}
        for stage, m in model.items():
            if stage == "extract-features":
                out["extract-features (GPU)"] = n * IMAGES_PER_VIEW * SAM_CLIP_GPU_S
            else:
                out[stage] = m["a"] * n ** m["b"] / m["speedup"]
        return out

    def memory(n: int) -> dict[str, float]:
        return {stage: max(m["peak_mb"], m["mem_a"] * n ** m["mem_b"])
                if m["mem_b"] > 0.05 else m["peak_mb"] for stage, m in model.items()}  # fmt: skip

    per_scene = {name: chain(n) for name, n in PT_OVS.items()}
    totals = {name: sum(c.values()) for name, c in per_scene.items()}
    worst = max(totals, key=totals.get)
    queue_s = 60 * len(model)
    return {"model": model, "per_scene_s": per_scene, "totals_s": totals,
            "memory_mb": {name: memory(n) for name, n in PT_OVS.items()},
            "critical_path": worst, "wall_s": totals[worst] + queue_s,
            "node_hours": sum(totals.values()) / 3600}  # fmt: skip


PARTS = {
    "make": make_part,
    "local": local_part,
    "slurm": slurm_part,
    "stages": stages_part,
    "paper": paper_part,
    "growth": growth_part,
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--parts", nargs="+", choices=list(PARTS), default=["make", "local"]
    )
    ap.add_argument("--work", type=Path, default=ROOT / "work" / "cluster")
    args = ap.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    out = args.work / "cluster.json"
    results = json.loads(out.read_text()) if out.exists() else {}
    for part in args.parts:
        res = PARTS[part](args.work.resolve())
        res["when"] = time.strftime("%Y-%m-%d %H:%M")
        results[part] = res
        out.write_text(json.dumps(results, indent=1))
        print(
            part,
            json.dumps({k: v for k, v in res.items() if k != "jobs"}, indent=1),
            flush=True,
        )


if __name__ == "__main__":
    main()

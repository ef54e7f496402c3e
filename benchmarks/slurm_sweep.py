"""The paper's ablation sweep (`--config sweep=paper_ablations`) on small demo scenes, run twice side by
side from empty work folders: with the local profile (2 cores) and through the local SLURM cluster
(`scripts/local_slurm.sh start`, profile `slurm-local`). Writes wall time and job counts per run, and
for the SLURM run each job's allocation and completion time from the controller's log (how many ran at
once) -> results/benchmarks/slurm_sweep.{csv,png}.

    sudo scripts/local_slurm.sh start
    .venv/bin/python benchmarks/slurm_sweep.py
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
import tempfile
import time
from datetime import datetime
from pathlib import Path

import pandas as pd
import yaml

from common import OUT, ROOT

# the demo's config, made small: one pair, a few clusters, short solves, small renders
SMALL = {
    "scenes": {"ant": {"n_gaussians": 3000}, "pebbles": {"n_gaussians": 6000}},
    "pairs": [["ant", "pebbles"]],
    "partitions": {"default": {"cluster": {"target_cluster_size": 500}},
                   "half": {"cluster": {"target_cluster_size": 1000}}},
    "experiments": {"default": {"stylize": {"iterations": 5}}},
    "evaluation": {"render": {"frames": 4, "size": 64, "key_views": 2},
                   "crops": {"count": 4, "size": 16},
                   "metrics": {"patches": 16, "candidates": 32, "patch_size": 8}},
}
CTLD_LOG = Path("/var/log/slurm/slurmctld.log")


def run(profile: str, workdir: Path, sweep: str) -> dict:
    overlay = workdir / "small.yaml"
    overlay.write_text(yaml.safe_dump(SMALL))
    # the target goes first: --configfile and --config take several values
    cmd = [sys.executable, "-m", "snakemake", f"results/tables/{sweep}.csv", "-s", str(ROOT / "Snakefile"),
           "-d", str(workdir), "--profile", str(ROOT / "workflow/profiles" / profile),
           "--configfile", str(ROOT / "config/config.yaml"), str(overlay), "--config", f"sweep={sweep}"]
    t0 = time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    out = r.stdout + r.stderr
    if r.returncode:
        raise SystemExit(f"{profile}: snakemake failed\n{out[-3000:]}")
    m = re.search(r"(\d+) of (\d+) steps \(100%\) done", out)
    return {"profile": profile, "wall_s": round(wall, 1), "jobs": int(m.group(2)) if m else -1,
            "slurm_ids": [int(i) for i in re.findall(r"submitted with SLURM jobid (\d+)", out)]}


def slurm_intervals(ids: list[int]) -> pd.DataFrame:
    """Allocation and completion time of each job, from slurmctld's log."""
    log = CTLD_LOG.read_text()
    stamp = r"\[([\d\-T:.]+)\]"
    rows = []
    for i in ids:
        # the main scheduler logs "sched: Allocate JobId=N NodeList=... #CPUs=C", the backfill scheduler
        # "sched/backfill: _start_job: Started JobId=N in PARTITION on NODE" (no CPU count)
        a = re.search(rf"{stamp} sched: Allocate JobId={i} NodeList=\S+ #CPUs=(\d+)", log) or \
            re.search(rf"{stamp} sched/backfill: _start_job: Started JobId={i} ()", log)
        d = re.search(rf"{stamp} _job_complete: JobId={i} done", log)
        if a and d:
            rows.append({"job": i, "cpus": int(a.group(2)) if a.group(2) else None,
                         "start": datetime.fromisoformat(a.group(1)), "end": datetime.fromisoformat(d.group(1))})
    return pd.DataFrame(rows)


def max_concurrent(iv: pd.DataFrame) -> int:
    ev = sorted([(t, 1) for t in iv.start] + [(t, -1) for t in iv.end], key=lambda e: (e[0], e[1]))
    n = best = 0
    for _, d in ev:
        n += d
        best = max(best, n)
    return best


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sweep", default="paper_ablations")
    args = ap.parse_args()
    if subprocess.run([ROOT / "scripts/local_slurm.sh", "status"], capture_output=True).returncode:
        raise SystemExit("the local SLURM cluster is not running: sudo scripts/local_slurm.sh start")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for profile in ("local", "slurm-local"):
            wd = Path(tmp) / profile
            wd.mkdir()
            res = run(profile, wd, args.sweep)
            ids = res.pop("slurm_ids")
            row = {**res, "sweep": args.sweep}
            if ids:
                iv = slurm_intervals(ids)
                row.update(slurm_jobs=len(ids), jobs_in_log=len(iv), max_running_at_once=max_concurrent(iv),
                           job_s_mean=round((iv.end - iv.start).dt.total_seconds().mean(), 2))
                t0 = iv.start.min()
                iv["start_s"] = (iv.start - t0).dt.total_seconds()
                iv["end_s"] = (iv.end - t0).dt.total_seconds()
            print(row, flush=True)
            rows.append(row)
    df = pd.DataFrame(rows)
    df["wall_vs_local"] = (df.wall_s / df.wall_s.iloc[0]).round(2)
    OUT.mkdir(parents=True, exist_ok=True)
    df.to_csv(OUT / "slurm_sweep.csv", index=False)
    print(df.to_string(index=False))

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 0.18 * len(iv) + 1.5))
    for k, r in enumerate(iv.sort_values("start_s").itertuples()):
        ax.barh(k, r.end_s - r.start_s, left=r.start_s, height=0.8, color="C1" if r.cpus > 1 else "C0")
    ax.set_xlabel("seconds since the first job started")
    ax.set_ylabel("SLURM job")
    ax.set_title(f"sweep={args.sweep} through the local SLURM cluster: {len(iv)} jobs, "
                 f"at most {max_concurrent(iv)} at once (orange: 2 CPUs)", fontsize=9)
    fig.tight_layout()
    fig.savefig(OUT / "slurm_sweep.png", dpi=110)


if __name__ == "__main__":
    main()

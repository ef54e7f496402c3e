"""Where a workflow run's minutes went: per rule, the jobs' summed seconds and peak memory (their
``benchmark:`` files), and when each target a user waits for was done.

    python benchmarks/workflow_minutes.py [.snakemake/log/<run>.snakemake.log] [--targets comparison_sheet table1]

Reads the Snakemake log of one run (default: the newest under ``.snakemake/log/``): each job's rule and
benchmark file, and the time each job finished. Writes ``results/benchmarks/workflow_minutes.csv`` (one row
per rule: jobs, summed seconds, largest peak resident memory, first and last finish in minutes from the
run's start) and prints it. Seconds are the jobs' own (Snakemake's benchmark ``s``); two light jobs run at
once on the local profile, so they add up to more than the wall time.
"""

from __future__ import annotations

import argparse
import re
import sys
from datetime import datetime
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import OUT, ROOT, write_rows  # noqa: E402

STAMP = re.compile(r"^\[(\w{3} \w{3} +\d+ \d\d:\d\d:\d\d \d{4})\]$")


def parse_log(path: Path) -> tuple[datetime, list[dict]]:
    """(start, jobs): each job's rule, benchmark file and finish time, from a Snakemake log."""
    start, now, jobs, by_id = None, None, [], {}
    job = None
    for line in path.read_text().splitlines():
        m = STAMP.match(line.strip())
        if m:
            now = datetime.strptime(m.group(1), "%a %b %d %H:%M:%S %Y")
            start = start or now
            continue
        s = line.strip()
        rm = re.match(r"^(?:local)?rule (\w+):$", s)
        if rm:
            job = {"rule": rm.group(1), "benchmark": None, "started": now}
            jobs.append(job)
        elif job is not None and s.startswith("benchmark:"):
            job["benchmark"] = s.split(":", 1)[1].strip()
        elif job is not None and s.startswith("jobid:"):
            by_id[s.split(":", 1)[1].strip()] = job
        fm = re.match(r"^Finished jobid: (\d+)", s)
        if fm and fm.group(1) in by_id:
            by_id[fm.group(1)]["finished"] = now
    if start is None:
        raise ValueError(f"{path}: no time stamps: not a Snakemake log")
    return start, jobs


def rule_rows(start: datetime, jobs: list[dict], root: Path) -> list[dict]:
    import pandas as pd

    rows = {}
    for j in jobs:
        r = rows.setdefault(j["rule"], {"rule": j["rule"], "jobs": 0, "seconds": 0.0, "peak_mb": 0.0,
                                        "first_done_min": None, "last_done_min": None})
        r["jobs"] += 1
        tsv = root / j["benchmark"] if j["benchmark"] else None
        if tsv is not None and tsv.exists():
            b = pd.read_csv(tsv, sep="\t").iloc[-1]
            r["seconds"] += float(b["s"])
            r["peak_mb"] = max(r["peak_mb"], float(b["max_rss"]) if b["max_rss"] != "-" else 0.0)
        if j.get("finished"):
            m = (j["finished"] - start).total_seconds() / 60
            r["first_done_min"] = m if r["first_done_min"] is None else min(r["first_done_min"], m)
            r["last_done_min"] = m if r["last_done_min"] is None else max(r["last_done_min"], m)
    return sorted(rows.values(), key=lambda r: -r["seconds"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("log", nargs="?", type=Path, help="a Snakemake log (default: the newest)")
    ap.add_argument("--root", type=Path, default=ROOT, help="the workflow's folder (its results/ and .snakemake/)")
    ap.add_argument("--out", type=Path, default=OUT / "workflow_minutes.csv")
    a = ap.parse_args()
    log = a.log or max((a.root / ".snakemake" / "log").glob("*.snakemake.log"), key=lambda p: p.stat().st_mtime)
    start, jobs = parse_log(log)
    rows = rule_rows(start, jobs, a.root)
    done = [j["finished"] for j in jobs if j.get("finished")]
    wall = (max(done) - start).total_seconds() / 60 if done else float("nan")
    df = write_rows(rows, a.out)
    print(df.to_string(index=False, float_format=lambda x: f"{x:.2f}"))
    print(f"{log}: {len(jobs)} jobs, {wall:.1f} min from the first job to the last; jobs' own time "
          f"{sum(r['seconds'] for r in rows) / 60:.1f} min; wrote {a.out}")


if __name__ == "__main__":
    main()

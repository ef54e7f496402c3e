"""The paper's scale, stage by stage: lego (pretrained) against a procedural pebbles style of 1e6
Gaussians (and smaller), 400 clusters, 30 steps (config/paper_scale.yaml), through the workflow.

    python benchmarks/paper_scale.py [--sizes 250000 1000000] [--previous REV]

For each style size the workflow runs ``config/paper_scale.yaml`` with the style scene resized (one
extra config file per size, under ``results/benchmarks/paper_scale/``) up to the stylized scene
(``final.ply``), with the local profile; the lego scene's pretraining and surface sampling are shared
(cached) and reported as they were measured. Every rule's time and peak memory come from its own
Snakemake ``benchmark:`` file; the table adds how each stage's time grows with the number of style
Gaussians (the exponent of a power law through the sizes run), and the issue's figure: the
stylization given the pretrained lego (every stage after pretraining, summed; each ran alone, so the
sum is what one run costs). The Sinkhorn stage runs at ``tol: 0.1`` there (config/paper_scale.yaml: more
accurate than the paper's geomloss solve; the demo's 1e-3 costs about 2.6x at this size). Needs
``../shared/data`` (the lego).

``--previous REV`` compares two implementations side by side in one run: this checkout's HEAD and
revision REV each run every stage after pretraining (surface, clusters, the style scene, registration,
selection, eq. 9, rescale) from nothing, in a git worktree of its own, on the same pretrained lego
(a copy of this checkout's ``results/scenes/lego``; the workflow runs with ``--rerun-triggers mtime``
so neither re-trains it), one after the other; the table gains a ``version`` column and each
stage's time ratio REV / HEAD. Commit first: HEAD is what runs.

Writes ``results/benchmarks/paper_scale.{csv,png}``.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import OUT, ROOT, worktree  # noqa: E402


def style_name(n: int) -> str:
    return "pebbles_1m" if n == 1_000_000 else f"pebbles_{n // 1000}k"


def run_size(n: int, log_dir: Path, root: Path = ROOT, env: dict | None = None, extra_args=()) -> float:
    """Run ``config/paper_scale.yaml`` in ``root`` up to the stylized scene at style size ``n``; seconds."""
    import yaml

    name = style_name(n)
    extra = log_dir / f"config_{name}.yaml"
    extra.write_text(yaml.safe_dump({
        "scenes": {name: {"source": "procedural", "kind": "style", "name": "pebbles", "n_gaussians": n}},
        "pairs": [["lego", name]], "table1": {"pairs": [["lego", name]]}}))
    target = f"results/stylize/lego__{name}/paper/final.ply"
    cmd = [str(ROOT / ".venv" / "bin" / "snakemake"), "--profile", "workflow/profiles/local", "--configfile",
           "config/paper_scale.yaml", str(extra.resolve()), *extra_args, "--", target]
    t0 = time.perf_counter()
    with open(log_dir / f"snakemake_{name}.log", "w") as fh:
        subprocess.run(cmd, cwd=root, check=True, stdout=fh, stderr=subprocess.STDOUT, env=env)
    return time.perf_counter() - t0


def read_tsv(path: Path) -> dict:
    import pandas as pd

    row = pd.read_csv(path, sep="\t").iloc[-1]
    return {"seconds": float(row["s"]), "peak_mb": float(row["max_rss"])}


def version_rows(root: Path, sizes: list[int], log_dir: Path, run: bool, env: dict | None = None,
                 extra_args=()) -> list[dict]:
    """Every stage's time and peak memory (its rule's benchmark file) for the workflow in ``root``."""
    rules = root / "results" / "benchmarks" / "rules"
    walls = {n: run_size(n, log_dir, root, env, extra_args) if run else None for n in sorted(sizes)}
    rows = []  # read after the runs: the lego's surface and clusters may be among what they made
    for stage, tsv in (("pretrain (lego, given)", "pretrain_lego.tsv"), ("surface (lego)", "surface_lego.tsv"),
                       ("cluster (k-means, 400)", "cluster_lego_paper.tsv")):
        if (rules / tsv).exists():
            rows.append({"style_gaussians": None, "stage": stage, **read_tsv(rules / tsv)})
    for n in sorted(sizes):
        name = style_name(n)
        wall = walls[n]
        for stage, tsv in (("style scene (procedural)", f"scene_{name}.tsv"), ("register", f"register_lego__{name}_paper.tsv"),
                           ("select", f"select_lego__{name}_paper.tsv"), ("stylize (eq. 9)", f"sinkhorn_lego__{name}_paper.tsv"),
                           ("rescale", f"rescale_lego__{name}_paper.tsv")):
            rows.append({"style_gaussians": n, "stage": stage, **read_tsv(rules / tsv)})
        info = json.loads((root / f"results/stylize/lego__{name}/paper/losses.json").read_text())
        sel = json.loads((root / f"results/register/lego__{name}/paper/selection.json").read_text())
        stages = [r for r in rows if r["style_gaussians"] in (None, n) and not r["stage"].startswith("pretrain")]
        rows.append({"style_gaussians": n, "stage": "stylization, given the pretrained lego (sum of the stages above)",
                     "seconds": sum(r["seconds"] for r in stages), "peak_mb": max(r["peak_mb"] for r in stages),
                     "clusters": info["clusters"], "stylized_gaussians": info["gaussians"],
                     "selected_median_per_cluster": sel["size_median"], "selected_max_per_cluster": sel["size_max"],
                     "ms_per_cluster_step": 1000 * info["seconds_per_cluster_step"]})
        rows.append({"style_gaussians": n, "stage": "workflow wall (this invocation; cached stages not re-run)",
                     "seconds": wall, "peak_mb": None})
    return rows


def worktree_rows(rev: str, sizes: list[int], log_dir: Path) -> list[dict]:
    """:func:`version_rows` of revision ``rev``, run from nothing after pretraining in a temporary worktree
    given a copy of this checkout's pretrained lego."""
    import os
    import shutil

    lego = ROOT / "results" / "scenes" / "lego"
    given = ["scene.ply", "pretrain_log.csv", "pretrain_eval.json", "pretrain.ckpt"]
    if not all((lego / f).exists() for f in given[:3]):
        sys.exit(f"--previous needs the pretrained lego in {lego} (run config/paper_scale.yaml once)")
    with worktree(rev, prefix="wast3d-paper-") as wt:
        dst = wt / "results" / "scenes" / "lego"
        dst.mkdir(parents=True)
        for f in given:
            if (lego / f).exists():
                shutil.copy(lego / f, dst / f)
        (wt / "results" / "benchmarks" / "rules").mkdir(parents=True)
        shutil.copy2(ROOT / "results" / "benchmarks" / "rules" / "pretrain_lego.tsv", wt / "results" / "benchmarks" / "rules")
        sub = log_dir / rev.replace("/", "_")
        sub.mkdir(parents=True, exist_ok=True)
        env = {**os.environ, "PYTHONPATH": str(wt)}
        rows = version_rows(wt, sizes, sub, True, env, ("--rerun-triggers", "mtime"))
    # the workflow there still resumes pretraining from the copied checkpoint (nothing left to train;
    # Snakemake finds the lego's images newer), so its row is that resume, not the training
    resumed = "pretrain (lego, resumed from the given checkpoint)"
    return [{"version": rev, **r, **({"stage": resumed} if r["stage"].startswith("pretrain") else {})} for r in rows]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[250_000, 1_000_000])
    ap.add_argument("--skip-run", action="store_true", help="only collect the benchmark files of earlier runs")
    ap.add_argument("--previous", help="also run this git revision, and HEAD, each in a worktree (side by side)")
    ap.add_argument("--out", type=Path, default=OUT / "paper_scale.csv")
    a = ap.parse_args()
    import pandas as pd

    log_dir = a.out.parent / "paper_scale"
    log_dir.mkdir(parents=True, exist_ok=True)
    if a.previous:
        rows = worktree_rows(a.previous, a.sizes, log_dir) + worktree_rows("HEAD", a.sizes, log_dir)
    else:
        rows = [{"version": "current", **r} for r in version_rows(ROOT, a.sizes, log_dir, not a.skip_run)]
    df = pd.DataFrame(rows)
    sizes = sorted(a.sizes)
    if len(sizes) > 1:
        lo, hi = sizes[0], sizes[-1]
        for (version, stage), g in df.groupby(["version", "stage"]):
            t = g.set_index("style_gaussians").seconds
            if not stage.startswith("workflow wall") and lo in t.index and hi in t.index and t[lo] and t[hi]:
                df.loc[g.index, "growth_exponent"] = math.log(t[hi] / t[lo]) / math.log(hi / lo)
    if a.previous:  # each stage's time of REV over HEAD's, on HEAD's rows
        key = df.stage + "@" + df.style_gaussians.fillna(0).astype(int).astype(str)
        prev = df.seconds[df.version == a.previous].groupby(key).last()
        cur = df.version == "HEAD"
        df.loc[cur, f"time_{a.previous}_over_HEAD"] = key[cur].map(prev) / df.seconds[cur]
    df.to_csv(a.out, index=False)
    print(df.to_string(index=False))
    picture(df[df.version == df.version.iloc[-1]], a.out.with_suffix(".png"))


def picture(df, out: Path) -> None:
    """One row per stage, a bar per style size (the lego's own stages once), seconds on a log axis."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    d = df[~df.stage.str.startswith("workflow wall")].copy()
    d["short"] = d.stage.str.replace(r" \(sum of the stages above\)", "", regex=True)
    stages = list(dict.fromkeys(d.short))
    sizes = sorted(int(n) for n in d.style_gaussians.dropna().unique())
    fig, ax = plt.subplots(figsize=(9, 0.3 * len(stages) * max(1, len(sizes)) + 1.5))
    h = 0.8 / max(1, len(sizes))
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for y, st in enumerate(stages):
        g = d[d.short == st]
        for _, r in g.iterrows():
            i = sizes.index(int(r.style_gaussians)) if r.style_gaussians == r.style_gaussians else None
            off = 0 if i is None else (i - (len(sizes) - 1) / 2) * h
            c = "grey" if i is None else colours[i]
            ax.barh(y + off, r.seconds, h, color=c)
            ax.annotate(f"{r.seconds:.0f} s, {r.peak_mb:.0f} MB", (r.seconds, y + off), va="center", fontsize=7)
    from matplotlib.patches import Patch

    handles = [Patch(color=colours[i], label=f"{n // 1000}k style Gaussians") for i, n in enumerate(sizes)]
    handles.append(Patch(color="grey", label="the lego's own stages (shared)"))
    ax.set_yticks(range(len(stages)), stages, fontsize=8)
    ax.set_xscale("log")
    ax.set_xlabel("seconds (log), 2 CPU threads")
    ax.set_title("paper scale (config/paper_scale.yaml): lego x pebbles, 400 clusters, per stage", fontsize=9)
    ax.invert_yaxis()
    ax.legend(handles=handles, fontsize=7, loc="upper right", bbox_to_anchor=(1.0, -0.08), ncol=3)
    fig.tight_layout()
    fig.savefig(out, dpi=120)


if __name__ == "__main__":
    main()

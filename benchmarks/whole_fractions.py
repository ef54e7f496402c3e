"""element_thickness_w1's neighbourhood (a fraction of the style's element size n_e) on the volume pairs:
per fraction, ours (default, and the ``--seed-experiment`` draw), the collage, the unstylized content and
the chips (every copy of ours flattened to a fifth of its height, as benchmarks/element_validation.py
makes them), and the two margins the metric is read for: the content's gap over the seed spread
(content - the farther of ours, over |ours - other draw|) and the chips' over the metric's own spread
(chips - collage, over the standard deviation of ours over 3 metric seeds).

    .venv/bin/python benchmarks/whole_fractions.py ant__bouquet ant__bouquet_trained lego__bouquet_trained \\
        guitar__bouquet_trained ant__pinecone [--seed-experiment seeds-seed1]

reads the workflow's results (run them first: docs/measurements.md#styles-that-are-objects) and writes
results/benchmarks/whole_fractions.csv.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from dataclasses import replace
from pathlib import Path

import pandas as pd
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import write_rows  # noqa: E402

FRACTIONS = (1 / 16, 1 / 8, 1 / 4, 1 / 2)


def main(argv=None) -> None:
    from element_validation import flattened

    from wast3d.elements import copy_ids
    from wast3d.io_utils import load_npz
    from wast3d.metrics import MetricsConfig, element_metrics
    from wast3d.ply import read_ply
    from wast3d.stages import artifact

    ap = argparse.ArgumentParser()
    ap.add_argument("pairs", nargs="+")
    ap.add_argument("--seed-experiment", default="seeds-seed1")
    ap.add_argument("--results", type=Path, default=ROOT / "results")
    a = ap.parse_args(argv)
    rows = []
    for pair in a.pairs:
        names = dict(zip(("content", "style"), pair.split("__")))
        ev = {m: json.loads(Path(artifact("eval", a.results, **names, method=m)).read_text())
              for m in ("default", a.seed_experiment, "selected", "input")}
        style, n_e = read_ply(ev["default"]["style"]), ev["default"]["element_size_gaussians"]
        cfg = MetricsConfig(**ev["default"]["config"]["metrics"])
        scenes = {m: read_ply(ev[m]["result"]) for m in ev}
        ours = scenes["default"]
        npz = load_npz(Path(artifact("stylize_npz", a.results, **names, experiment="default")))
        scenes["chips"] = replace(ours, means=flattened(ours.means, copy_ids(ours.element, torch.from_numpy(npz["labels"]))))
        for f in FRACTIONS:
            v = {m: element_metrics(sc, style, n_e, cfg, f)["element_thickness_w1"] for m, sc in scenes.items()}
            spread = statistics.stdev(element_metrics(ours, style, n_e, replace(cfg, seed=k), f)["element_thickness_w1"]
                                      for k in range(3))
            seeds = abs(v["default"] - v[a.seed_experiment])
            row = {"pair": pair, "fraction": f, **{f"thickness_{m}": x for m, x in v.items()},
                   "content_gap_x_seed_spread": (v["input"] - max(v["default"], v[a.seed_experiment])) / max(seeds, 1e-12),
                   "chips_margin_x_metric_spread": (v["chips"] - v["selected"]) / max(spread, 1e-12)}
            rows.append(row)
            print(pd.DataFrame([row]).to_string(index=False, header=len(rows) == 1), flush=True)
    out = a.results / "benchmarks" / "whole_fractions.csv"
    write_rows(rows, out)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()

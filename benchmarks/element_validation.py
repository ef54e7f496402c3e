"""The element metrics against controls, on the workflow's own results for each pair given:

- the collage (registration + selection, no optimization): element_intact 1 by construction;
- the result (default experiment), and with other k-means and registration seeds (``--seed-experiment``,
  config/seeds.yaml) for the spread between seeds;
- confetti (negative): the result's Gaussians shuffled within each cluster, so that every position is
  still on the result but the element copies are torn apart; intact must fall to ~0;
- the unstylized content and the colour transfer (negatives): element_share 0.

    .venv/bin/python benchmarks/element_validation.py ant__pebbles ant__pebbles_trained [--seed-experiment seed1]

reads results/eval/PAIR/METHOD.json (element_share_ratio, element_intact; run them through the workflow
first) and computes the confetti control with wast3d.elements; writes results/benchmarks/element_validation.csv.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import pandas as pd
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main(argv=None) -> None:
    from wast3d.elements import ElementConfig, copy_ids, element_intact
    from wast3d.io_utils import load_npz
    from wast3d.ply import read_ply

    ap = argparse.ArgumentParser()
    ap.add_argument("pairs", nargs="+")
    ap.add_argument("--seed-experiment", default="seed1")
    ap.add_argument("--results", type=Path, default=ROOT / "results")
    a = ap.parse_args(argv)
    rows = []
    for pair in a.pairs:
        ev = a.results / "eval" / pair
        for method, role in (("selected", "collage (positive)"), ("default", "ours"),
                             (a.seed_experiment, "ours, other seeds"), ("input", "content (negative)"),
                             ("colour_ot", "colour transfer (negative)")):
            f = ev / f"{method}.json"
            if not f.exists():
                continue
            m = json.loads(f.read_text())
            rows.append({"pair": pair, "control": role, "method": method, "element_share_ratio": m.get("element_share_ratio"),
                         "element_intact": m.get("element_intact"), "coverage": m.get("coverage")})
        d = a.results / "stylize" / pair / "default"
        res = read_ply(d / "final.ply")
        npz = load_npz(d / "stylize.npz")
        clusters = torch.from_numpy(npz["labels"])
        before = torch.from_numpy(npz["before_means"])
        g = torch.Generator().manual_seed(0)
        shuffled = res.means.clone()
        for c in clusters.unique():
            idx = (clusters == c).nonzero().squeeze(1)
            shuffled[idx] = res.means[idx[torch.randperm(len(idx), generator=g)]]
        conf = element_intact(before, shuffled, copy_ids(res.element, clusters), ElementConfig())
        rows.append({"pair": pair, "control": "confetti (negative)", "method": "default, shuffled in each cluster",
                     "element_share_ratio": None, "element_intact": conf["intact"], "coverage": None})
    df = pd.DataFrame(rows)
    out = a.results / "benchmarks" / "element_validation.csv"
    out.parent.mkdir(parents=True, exist_ok=True)
    df.to_csv(out, index=False)
    print(df.to_string(index=False))


if __name__ == "__main__":
    main()

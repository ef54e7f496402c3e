"""Sampling error of the weights-free metrics against their run time.

    python benchmarks/metrics_error_vs_time.py [--result PLY --style PLY] [--seeds 5]

The style metrics sample patches and colours; their error is the spread over ``--seeds`` seeds (the
standard deviation, relative to the mean) at each sample size, against the time of one evaluation.
Patches P (with 4P style candidates; the patch matching costs O(P x 4P)) and colour points C are
varied together from a quarter to twice the defaults (128 patches, 4,096 colours). Default inputs:
the demo's stylized ant and pebbles (``results/stylize/ant__pebbles/default/final.ply``), else a
procedural grass scene against pebbles. Writes ``results/benchmarks/metrics_error_vs_time.csv``.

    python benchmarks/metrics_error_vs_time.py --whole ant__bouquet [--seeds 5]

does the same for the whole-element metrics (``element_colour_w1``, ``element_thickness_w1``) of the
pair's default result, by the evaluate stage's own function, over ``element_centres`` from 2,048 to
131,072 (the default 32,768); their error is the standard deviation over seeds in the metric's own unit
(W1 over the style's interquartile range). Writes ``results/benchmarks/whole_metrics_error_vs_time.csv``.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import pandas as pd
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import OUT, ROOT, write_rows  # noqa: E402

KEYS = ("style_patch_chamfer", "style_patch_sinkhorn", "colour_sinkhorn")


def main() -> None:
    from wast3d.metrics import MetricsConfig, style_metrics
    from wast3d.ply import read_ply
    from wast3d.procedural import make_scene

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--result", type=Path, default=ROOT / "results/stylize/ant__pebbles/default/final.ply")
    ap.add_argument("--style", type=Path, default=ROOT / "results/scenes/pebbles/scene.ply")
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--scales", type=float, nargs="+", default=[0.25, 0.5, 1.0, 2.0])
    ap.add_argument("--whole", metavar="PAIR", help="the whole-element metrics of results/eval/PAIR/default.json")
    a = ap.parse_args()
    if a.whole:
        return whole_error_vs_time(a.whole, a.seeds)
    torch.set_flush_denormal(True)
    if a.result.exists() and a.style.exists():
        result, style, what = read_ply(a.result), read_ply(a.style), f"{a.result} vs {a.style}"
    else:
        result, style, what = make_scene("style", "grass", 20000), make_scene("style", "pebbles", 30000), "grass vs pebbles"
    print(f"inputs: {what} ({len(result)} / {len(style)} Gaussians)")
    base = MetricsConfig()
    rows = []
    for sc in a.scales:
        cfg = replace(base, patches=max(8, round(base.patches * sc)), candidates=max(32, round(base.candidates * sc)),
                      colour_points=max(256, round(base.colour_points * sc)))
        vals, secs = [], []
        for seed in range(a.seeds):
            t = time.perf_counter()
            vals.append(style_metrics(result, style, replace(cfg, seed=seed)))
            secs.append(time.perf_counter() - t)
        df = pd.DataFrame(vals)
        row = {"patches": cfg.patches, "candidates": cfg.candidates, "colour_points": cfg.colour_points,
               "seconds_median": float(pd.Series(secs).median())}
        for k in KEYS:
            row[f"{k}_mean"] = float(df[k].mean())
            row[f"{k}_rel_std_pct"] = float(100 * df[k].std() / abs(df[k].mean()))
        rows.append(row)
        print(pd.DataFrame([row]).to_string(index=False), flush=True)
    out = pd.DataFrame(rows)
    for k in KEYS:  # error relative to the largest sample's mean (its own spread is the floor)
        ref = out[f"{k}_mean"].iloc[-1]
        out[f"{k}_dev_from_largest_pct"] = 100 * (out[f"{k}_mean"] - ref).abs() / abs(ref)
    write_rows(out.to_dict("records"), OUT / "metrics_error_vs_time.csv")
    print(out.to_string(index=False))


def whole_error_vs_time(pair: str, seeds: int) -> None:
    """The module docstring's ``--whole`` table."""
    import json

    from wast3d.metrics import MetricsConfig
    from wast3d.pipeline import evaluate_whole_elements
    from wast3d.ply import read_ply
    from wast3d.stages import artifact

    content, style_name = pair.split("__")
    ev = json.loads(Path(artifact("eval", ROOT / "results", content=content, style=style_name, method="default")).read_text())
    result, style = read_ply(ev["result"]), read_ply(ev["style"])
    ref = Path(artifact("texture_reference", ROOT / "results", content=content, style=style_name))
    base = MetricsConfig(**ev["config"]["metrics"])
    print(f"inputs: {ev['result']} vs {ev['style']} ({len(result)} / {len(style)} Gaussians)")
    rows = []
    for centres in (2048, 8192, 32768, 131072):
        vals, secs = [], []
        for seed in range(seeds):
            t = time.perf_counter()
            vals.append(evaluate_whole_elements(result, style, ref, replace(base, element_centres=centres, seed=seed)))
            secs.append(time.perf_counter() - t)
        df = pd.DataFrame(vals)
        row = {"element_centres": centres, "seconds_median": float(pd.Series(secs).median())}
        for k in ("element_colour_w1", "element_thickness_w1"):
            row.update({f"{k}_mean": float(df[k].mean()), f"{k}_std": float(df[k].std())})
        rows.append(row)
        print(pd.DataFrame([row]).to_string(index=False), flush=True)
    print(write_rows(rows, OUT / "whole_metrics_error_vs_time.csv").to_string(index=False))


if __name__ == "__main__":
    main()

"""Sweep stylization settings on one pair through the workflow's own stage functions (stylize, rescale,
render, evaluate of wast3d.pipeline), reading the pair's partition artifacts (clusters, registration,
selection) from a results folder the workflow made, and write every metric of evaluate per setting.

    .venv/bin/python benchmarks/element_sweep.py ant__pebbles --set smoothing.passes=0,4,8 [--results results]

Each setting is one override of the experiment's stylize block (``--experiment``, default ``default``, as
the config file defines it); the rows also hold the run time of the Sinkhorn stage. Output:
``results/benchmarks/element_sweep_<pair>.csv`` and a sheet of the close-ups (RGB and normals) per
setting, ``element_sweep_<pair>.png``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def parse_value(v: str):
    return yaml.safe_load(v)


def main(argv=None) -> None:
    from wast3d import pipeline
    from wast3d.figures import comparison_sheet
    from wast3d.stages import artifact

    ap = argparse.ArgumentParser()
    ap.add_argument("pair", help="CONTENT__STYLE, as under results/stylize")
    ap.add_argument("--set", required=True,
                    help="KEY=V1,V2,... (a stylize key, dotted into its group, e.g. smoothing.passes=0,4, or rescale.KEY, e.g. "
                         "rescale.bound=1,2)")
    ap.add_argument("--experiment", default="default")
    ap.add_argument("--results", type=Path, default=ROOT / "results")
    ap.add_argument("--config", type=Path, default=ROOT / "config" / "config.yaml")
    a = ap.parse_args(argv)
    cfg = yaml.safe_load(a.config.read_text())
    exp = cfg["experiments"][a.experiment]
    part = exp.get("partition", "default")
    key, values = a.set.split("=", 1)
    content, style = a.pair.split("__")
    R = a.results
    content_ply = Path(artifact("surface", R, scene=content))
    if not content_ply.exists():
        content_ply = Path(artifact("scene", R, scene=content))
    style_ply = Path(artifact("style", R, scene=style))
    if not style_ply.exists():
        style_ply = Path(artifact("scene", R, scene=style))
    clusters = artifact("clusters", R, content=content, partition=part)
    reg = artifact("registration", R, content=content, style=style, partition=part)
    sel = artifact("selection", R, content=content, style=style, partition=part)
    ev = cfg.get("evaluation", {})
    render_cfg = ev.get("render", {})
    eval_cfg = {k: ev[k] for k in ("metrics", "texture", "crops", "clip", "elements") if k in ev}
    out = R / "benchmarks" / "element_sweep" / a.pair
    rows, cols = [], []
    for v in values.split(","):
        val = parse_value(v)
        name = f"{key}={val}"
        d = out / name.replace("=", "_")
        d.mkdir(parents=True, exist_ok=True)
        import copy

        params, rescale = copy.deepcopy(exp.get("stylize", {})), dict(exp.get("rescale", {}))
        if key.startswith("rescale."):
            rescale[key.split(".", 1)[1]] = val
        else:  # a stylize key, or GROUP.KEY of one of its option groups
            *path, leaf = key.removeprefix("stylize.").split(".")
            node = params
            for p in path:
                node = node.setdefault(p, {})
            node[leaf] = val
        t = time.perf_counter()
        pipeline.run_stylize(content=content_ply, clusters=clusters, style=style_ply, registration=reg, selection=sel,
                             out_ply=d / "stylized.ply", out_npz=d / "stylize.npz", out_csv=d / "losses.csv",
                             params=params, progress=False)
        secs = time.perf_counter() - t
        pipeline.run_rescale(stylized=d / "stylized.ply", stylize_npz=d / "stylize.npz", out_ply=d / "final.ply",
                             params=rescale)
        pipeline.run_render(scene=d / "final.ply", reference=content_ply, out_folder=d / "render", params=render_cfg,
                            progress=False)
        pipeline.run_evaluate(result=d / "final.ply", content=content_ply, style=style_ply, result_render=d / "render",
                              style_render=artifact("render_scene", R, scene=style),
                              texture_reference=artifact("texture_reference", R, content=content, style=style),
                              content_render=artifact("render_pair", R, content=content, style=style, method="input"),
                              out_json=d / "eval.json",
                              params=eval_cfg, stylize_npz=d / "stylize.npz")
        m = json.loads((d / "eval.json").read_text())
        rows.append({"setting": name, "sinkhorn_seconds": secs,
                     **{k: v for k, v in m.items() if isinstance(v, (int, float)) or v is None}})
        cols.append((name, d / "render"))
        print(pd.DataFrame(rows[-1:]).to_string(index=False), flush=True)
    bench = R / "benchmarks"
    df = pd.DataFrame(rows)
    df.to_csv(bench / f"element_sweep_{a.pair}.csv", index=False)
    comparison_sheet(cols, bench / f"element_sweep_{a.pair}.png", tiles=(("closeup_rgb", "close-up"), ("closeup_normal", "close-up normals")))
    print(df[["setting", "element_intact", "element_share_ratio", "coverage", "content_chamfer", "relief_w1",
              "texture_swd", "sinkhorn_seconds"]].to_string(index=False))


if __name__ == "__main__":
    np.set_printoptions(precision=4)
    main()

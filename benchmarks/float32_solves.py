"""The evaluation's two colour solves in float32 against float64: value, difference and time.

    python benchmarks/float32_solves.py [--result PLY] [--content PLY] [--style PLY] [--seeds 3]

``colour_sinkhorn`` (:func:`wast3d.metrics.colour_sinkhorn`, 4,096 colours a side) of the demo's result
against its style, and the colour-transfer baseline's map (:func:`wast3d.baselines.colour_map`) of the
demo's content onto 4,096 style colours, each solved in float64 and in float32 (the default), one
thread. Beside the difference, the metric's spread over ``--seeds`` seeds (its sampling error): a solve
error far under it changes nothing that Table 1 can tell. Default inputs: the demo's files under
``results/`` (run the demo first). Writes ``results/benchmarks/float32_solves.csv``.
"""

from __future__ import annotations

import argparse
import statistics
import sys
from dataclasses import replace
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import OUT, ROOT, Peak, write_rows  # noqa: E402


def timed(fn):
    """fn() and its seconds (:class:`common.Peak`)."""
    with Peak() as p:
        out = fn()
    return out, p.seconds


def main() -> None:
    from wast3d.baselines import ColourTransferConfig, colour_map
    from wast3d.metrics import MetricsConfig, colour_sinkhorn
    from wast3d.ply import read_ply

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--result", type=Path, default=ROOT / "results/stylize/ant__pebbles/default/final.ply")
    ap.add_argument("--content", type=Path, default=ROOT / "results/scenes/ant/scene.ply")
    ap.add_argument("--style", type=Path, default=ROOT / "results/scenes/pebbles/scene.ply")
    ap.add_argument("--seeds", type=int, default=3)
    a = ap.parse_args()
    for p in (a.result, a.content, a.style):
        if not p.exists():
            sys.exit(f"{p}: not found (run the demo first: .venv/bin/snakemake --profile workflow/profiles/local)")
    torch.set_num_threads(1)
    torch.set_flush_denormal(True)
    result, content, style = read_ply(a.result), read_ply(a.content), read_ply(a.style)
    rows = []

    mcfg = MetricsConfig()
    vals = {dt: timed(lambda dt=dt: colour_sinkhorn(result.rgb, style.rgb, mcfg, dt)) for dt in (torch.float64, torch.float32)}
    seeds = [colour_sinkhorn(result.rgb, style.rgb, replace(mcfg, seed=s)) for s in range(a.seeds)]
    (v64, t64), (v32, t32) = vals[torch.float64], vals[torch.float32]
    rows.append({"solve": "colour_sinkhorn", "float64_s": t64, "float32_s": t32, "speedup": t64 / t32,
                 "difference": abs(v32 - v64) / abs(v64), "difference_is": "relative, of the value",
                 "seed_spread": statistics.stdev(seeds) / abs(statistics.mean(seeds)) if a.seeds > 1 else None})

    ccfg = ColourTransferConfig()
    g = torch.Generator().manual_seed(ccfg.seed)
    dst = style.rgb[torch.randperm(len(style), generator=g)[:ccfg.max_style_points]]
    maps = {dt: timed(lambda dt=dt: colour_map(content.rgb, dst, ccfg, dt).double()) for dt in (torch.float64, torch.float32)}
    (m64, t64), (m32, t32) = maps[torch.float64], maps[torch.float32]
    rows.append({"solve": "colour_transfer", "float64_s": t64, "float32_s": t32, "speedup": t64 / t32,
                 "difference": float((m64 - m32).abs().max()), "difference_is": "largest, of a colour in [0, 1]",
                 "seed_spread": None})
    df = write_rows(rows, OUT / "float32_solves.csv")
    print(df.to_string(index=False))


if __name__ == "__main__":
    main()

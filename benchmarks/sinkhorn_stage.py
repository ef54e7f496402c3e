"""The Sinkhorn stage, side by side: the paper's per-pair geomloss loop against wast3d's solver.

    python benchmarks/sinkhorn_stage.py [--pairs 8] [--points 2500] [--steps 20]

Both optimize the same P cluster pairs (N content vs N style points, 4-D features) for S Adam steps
with the same learning rate, in one process:

- ``geomloss loop``: one ``SamplesLoss("sinkhorn", p=2, blur=0.05, scaling=0.5, debias=True)`` call
  per pair and step, autograd gradient (the paper's way; tensorized backend);
- ``wast3d``: :func:`wast3d.stylize.stylize_cluster` defaults (native kernel, scaling 0.5, first step
  a full eps schedule + 0 extra iterations, later steps warm-started with 3 iterations).

Accuracy: the final style points of both are scored by one converged float64 divergence
(scaling 0.9 + 300 iterations); ``final_S`` should agree. Reported: seconds per step per pair, peak
memory, the speed-up, and the extrapolation to the paper's stage (400 pairs x 2,500 points, 100 steps).
Writes ``results/benchmarks/sinkhorn_stage.csv``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import OUT, Peak, cluster_pair  # noqa: E402


def geomloss_loop(pairs, steps, lr, blur, scaling):
    from geomloss import SamplesLoss

    L = SamplesLoss("sinkhorn", p=2, blur=blur, scaling=scaling, debias=True, backend="tensorized")
    outs = []
    for x, y in pairs:
        Y = y.clone().requires_grad_(True)
        opt = torch.optim.Adam([Y], lr=lr)
        for _ in range(steps):
            opt.zero_grad()
            L(x, Y).backward()
            opt.step()
        outs.append(Y.detach())
    return outs


def wast3d_loop(pairs, steps, lr, blur, scaling):
    from wast3d.sinkhorn import SinkhornConfig, sinkhorn

    cfg = SinkhornConfig(blur=blur, scaling=scaling)
    outs = []
    for x, y in pairs:
        Y = y.clone().requires_grad_(True)
        opt = torch.optim.Adam([Y], lr=lr)
        pot = None
        for _ in range(steps):
            opt.zero_grad()
            r = sinkhorn(x, Y.detach(), cfg, init=pot)
            pot = r.potentials
            Y.grad = r.grad_y
            opt.step()
        outs.append(Y.detach())
    return outs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", type=int, default=8)
    ap.add_argument("--points", type=int, default=2500)
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--lr", type=float, default=0.01)
    ap.add_argument("--blur", type=float, default=0.05)
    ap.add_argument("--scaling", type=float, default=0.5)
    ap.add_argument("--out", type=Path, default=OUT / "sinkhorn_stage.csv")
    a = ap.parse_args()
    torch.set_flush_denormal(True)
    import pandas as pd

    from wast3d.sinkhorn import SinkhornConfig, sinkhorn

    pairs = [cluster_pair(a.points, seed=i) for i in range(a.pairs)]
    score_cfg = SinkhornConfig(blur=a.blur, scaling=0.9, extra_iters=300)
    s0 = sum(float(sinkhorn(x.double(), y.double(), score_cfg, grad_y=False).value) for x, y in pairs) / a.pairs
    rows = []
    for name, fn in (("geomloss loop", geomloss_loop), ("wast3d", wast3d_loop)):
        with Peak() as p:
            outs = fn(pairs, a.steps, a.lr, a.blur, a.scaling)
        final = sum(float(sinkhorn(x.double(), Y.double(), score_cfg, grad_y=False).value)
                    for (x, _), Y in zip(pairs, outs)) / a.pairs
        per = p.seconds / (a.pairs * a.steps)
        rows.append({"method": name, "pairs": a.pairs, "points": a.points, "steps": a.steps,
                     "threads": torch.get_num_threads(), "seconds": p.seconds, "s_per_step_per_pair": per,
                     "peak_mb": p.mb, "initial_S": s0, "final_S": final,
                     "paper_stage_hours_400x100": per * 400 * 100 / 3600})
        print(rows[-1], flush=True)
    df = pd.DataFrame(rows)
    ref = df.set_index("method").loc["geomloss loop", "seconds"]
    df["speedup_vs_geomloss"] = ref / df.seconds
    a.out.parent.mkdir(parents=True, exist_ok=True)
    df.to_csv(a.out, index=False)
    print(df.to_string(index=False))


if __name__ == "__main__":
    main()

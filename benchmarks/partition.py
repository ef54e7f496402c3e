"""Partitioning benchmark: time and peak memory of each step against content size.

    python benchmarks/partition.py [--sizes 10000 100000 1000000] [--style-size 1000000]

Content: N surface Gaussians on a procedural mesh (``--content``), plus 5 % floaters and interior
Gaussians so that surface sampling has work to do; style: a procedural ``--style`` scene of
``--style-size`` Gaussians. Steps: surface sampling (opacity, kNN outliers, visibility over 24
rendered views), k-means (N clusters as the paper, 400; MiniBatchKMeans where N x clusters is large),
registration (eq. 7, default settings), selection (eq. 8, k = 3). Each step's wall time and peak
resident memory above the process level before it. The last columns give the growth per 10x of N
(``time_ratio_vs_prev``): close to 10 means linear. Writes ``results/benchmarks/partition.csv``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import OUT, Peak  # noqa: E402


def content_with_junk(name: str, n: int, seed: int = 0):
    from wast3d.gaussians import GaussianScene
    from wast3d.procedural import make_scene

    surf = make_scene("content", name, n, seed=seed)
    g = torch.Generator().manual_seed(seed)
    k = max(n // 20, 1)
    junk = torch.cat([torch.randn(k // 2, 3, generator=g) * 0.2, (torch.rand(k - k // 2, 3, generator=g) - 0.5) * 4])
    extra = GaussianScene.from_activated(junk, torch.full((k, 3), float(surf.scales.median())), opacities=0.5)
    return GaussianScene.concat([surf, extra])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[10_000, 100_000, 1_000_000])
    ap.add_argument("--style-size", type=int, default=1_000_000)
    ap.add_argument("--content", default="airplane")
    ap.add_argument("--style", default="pebbles")
    ap.add_argument("--clusters", type=int, default=400)
    ap.add_argument("--out", type=Path, default=OUT / "partition.csv")
    a = ap.parse_args()
    torch.set_flush_denormal(True)
    import pandas as pd

    from wast3d.clustering import ClusterConfig, cluster_content
    from wast3d.procedural import make_scene
    from wast3d.registration import RegistrationConfig, register
    from wast3d.selection import SelectConfig, select_style
    from wast3d.surface import SurfaceConfig, surface_points

    style = make_scene("style", a.style, a.style_size, seed=0)
    rows = []
    for n in a.sizes:
        content = content_with_junk(a.content, n)
        with Peak() as p:
            c, _ = surface_points(content, SurfaceConfig(views=24, resolution=200))
        rows.append({"n": n, "step": "surface", "seconds": p.seconds, "peak_mb": p.mb, "out": len(c)})
        with Peak() as p:
            cl = cluster_content(c, ClusterConfig(n_clusters=a.clusters))
        rows.append({"n": n, "step": f"kmeans ({cl.info['algorithm']})", "seconds": p.seconds, "peak_mb": p.mb,
                     "out": cl.info["clusters"]})
        with Peak() as p:
            reg = register(c.means, cl.labels, style.means, RegistrationConfig(), normals=cl.normals)
        rows.append({"n": n, "step": "register", "seconds": p.seconds, "peak_mb": p.mb,
                     "out": float(reg.residual.mean()), "residual_init": float(reg.residual_init.mean())})
        with Peak() as p:
            sel = select_style(SelectConfig(mode="knn", k=3), c, cl.labels, style, reg)
        rows.append({"n": n, "step": "select", "seconds": p.seconds, "peak_mb": p.mb, "out": len(sel.indices)})
        for r in rows[-4:]:
            print(r, flush=True)
    df = pd.DataFrame(rows)
    df["step_kind"] = df.step.str.split(" ").str[0]
    df["time_ratio_vs_prev"] = df.groupby("step_kind").seconds.transform(lambda s: s / s.shift(1))
    a.out.parent.mkdir(parents=True, exist_ok=True)
    df.to_csv(a.out, index=False)
    print(df.to_string(index=False))


if __name__ == "__main__":
    main()

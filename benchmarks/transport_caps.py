"""Stage 5's error against its run time over the transport caps (``stylize.content_points``, ``style_points``).

    python benchmarks/transport_caps.py [--size 1000000] [--clusters 48] [--caps 0:0 4096:4096 2048:2048 ...]

A content of ``--size`` Gaussians and the 1e6-Gaussian procedural pebbles, through stages 2-4 as
``benchmarks/content_size.py`` runs them (the paper experiment's settings), then :func:`wast3d.stylize.stylize`
on ``--clusters`` of its clusters (a seeded draw; the others' selections emptied) once per pair of caps
``CONTENT:STYLE`` (0: no cap). The error of a run is the RMS distance of its Gaussians' final positions
from the uncapped run's, over the RMS of the uncapped run's displacements (0: the same flow; 1: as far off
as not moving at all), and in content spacings. Controls: the uncapped run again (must score 0) and the
collage (30 steps -> 0, must score 1); the uncapped run with the solver converged to 1e-3 eps instead of
the paper experiment's 0.1 gives the error the experiment already accepts. Writes ``results/benchmarks/transport_caps.{csv,png}``.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from dataclasses import replace
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import OUT, write_rows  # noqa: E402
from content_size import apply_sets, content_with_junk, paper_blocks  # noqa: E402


def prepare(n: int, style, blocks: dict, content_name: str):
    """Stages 2-4 as the workflow's functions run them: (content points, clusters, registration, selection)."""
    from wast3d.clustering import ClusterConfig, cluster_content
    from wast3d.options import make_config
    from wast3d.registration import RegistrationConfig, register
    from wast3d.selection import SelectConfig, select_style
    from wast3d.surface import SurfaceConfig, surface_points

    content = surface_points(content_with_junk(content_name, n), make_config(SurfaceConfig, {}, "surface"))[0]
    cl = cluster_content(content, make_config(ClusterConfig, blocks.get("cluster"), "cluster"))
    reg = register(content.means, cl.labels, style.means, make_config(RegistrationConfig, blocks.get("register"),
                                                                        "register"), normals=cl.normals)
    sel = select_style(make_config(SelectConfig, blocks.get("select"), "select"), content, cl.labels, style, reg)
    return content, cl, reg, sel


def only(sel, keep: torch.Tensor):
    """The selection with every cluster but those in ``keep`` emptied."""
    sizes = sel.sizes.clone()
    mask = torch.zeros(len(sizes), dtype=torch.bool)
    mask[keep] = True
    sizes[~mask] = 0
    parts = [sel.indices[sel.offsets[i]:sel.offsets[i + 1]] for i in keep.tolist()]
    return replace(sel, offsets=torch.cat([sizes.new_zeros(1), sizes.cumsum(0)]), indices=torch.cat(parts))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=1_000_000)
    ap.add_argument("--style-size", type=int, default=1_000_000)
    ap.add_argument("--content", default="airplane")
    ap.add_argument("--style", default="pebbles")
    ap.add_argument("--clusters", type=int, default=48)
    ap.add_argument("--caps", nargs="+", default=["4096:4096", "2048:2048", "1024:2048", "1024:1024", "512:1024",
                                                  "512:512", "256:256"])
    ap.add_argument("--set", nargs="*", default=[], help="BLOCK.KEY=VALUE overrides of the paper experiment's blocks")
    ap.add_argument("--out", type=Path, default=OUT / "transport_caps.csv")
    a = ap.parse_args()
    torch.set_num_threads(2)
    torch.set_flush_denormal(True)
    logging.getLogger("wast3d.stylize").setLevel(logging.ERROR)  # one "empty cluster" line per emptied cluster
    from wast3d.geometry import mean_spacing
    from wast3d.options import make_config
    from wast3d.procedural import make_scene
    from wast3d.stylize import StylizeConfig, stylize

    blocks = apply_sets(paper_blocks(), a.set)
    style = make_scene("style", a.style, a.style_size)
    t = time.perf_counter()
    content, cl, reg, sel = prepare(a.size, style, blocks, a.content)
    K = int(cl.labels.max()) + 1
    keep = torch.randperm(K, generator=torch.Generator().manual_seed(0))[:a.clusters].sort().values
    keep = keep[sel.sizes[keep] > 0]
    sub = only(sel, keep)
    n_k = torch.bincount(cl.labels.long(), minlength=K)[keep]
    spacing = mean_spacing(content.means)
    print(f"content {len(content)} points, {K} clusters in {time.perf_counter() - t:.0f} s; {len(keep)} clusters "
          f"kept: content points per cluster median {int(n_k.median())}, style {int(sub.sizes[keep].median())} "
          f"(max {int(sub.sizes.max())})", flush=True)

    def run(content_points: int, style_points: int, **over):
        cfg = make_config(StylizeConfig, blocks.get("stylize"), "stylize")
        cfg = replace(cfg, content_points=content_points, style_points=style_points, **over)
        t0 = time.perf_counter()
        res = stylize(content, cl.labels, style, reg, sub, cfg, progress=False)
        return res, time.perf_counter() - t0

    ref, t_ref = run(0, 0)
    moved = (ref.scene.means - ref.before_means).square().sum(1).mean().sqrt()
    rows = []

    def row(name, res, seconds, c, s):
        d = (res.scene.means - ref.scene.means).square().sum(1).mean().sqrt()
        rows.append({"caps": name, "content_points": c, "style_points": s, "seconds": seconds,
                     "speedup": t_ref / seconds, "error": float(d / moved), "error_spacings": float(d / spacing)})
        print(f"{name:22s} {seconds:7.1f} s  x{t_ref / seconds:5.2f}  error {float(d / moved):.4f} "
              f"({float(d / spacing):.3f} spacings)", flush=True)

    row("uncapped", ref, t_ref, 0, 0)
    again, t_again = run(0, 0)
    row("uncapped again (0)", again, t_again, 0, 0)
    collage, t_col = run(0, 0, iterations=0)
    row("collage (1)", collage, t_col, 0, 0)
    tight, t_tight = run(0, 0, sinkhorn=replace(make_config(StylizeConfig, blocks.get("stylize"), "stylize").sinkhorn,
                                                 tol=1e-3))
    row("uncapped, tol 1e-3", tight, t_tight, 0, 0)
    for spec in a.caps:
        c, s = (int(v) for v in spec.split(":"))
        res, secs = run(c, s)
        row(f"{c}:{s}", res, secs, c, s)
    df = write_rows(rows, a.out)
    plot(df, a.out.with_suffix(".png"), a.size)
    print(f"wrote {a.out} and {a.out.with_suffix('.png')}")


def plot(df, path: Path, size: int) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 4))
    d = df[~df.caps.str.contains(r"\(")]
    ax.plot(d.seconds, d.error, "o-")
    for _, r in d.iterrows():
        ax.annotate(r.caps, (r.seconds, r.error), fontsize=7, xytext=(3, 3), textcoords="offset points")
    ax.set_xscale("log")
    ax.set_xlabel("stage 5 seconds (2 threads)")
    ax.set_ylabel("error: RMS position difference / RMS displacement")
    ax.set_title(f"transport caps, content {size:.0e} Gaussians (CONTENT:STYLE)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()

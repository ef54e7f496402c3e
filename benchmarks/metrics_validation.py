"""Are the metrics able to see the style? Controls for every metric.

    python benchmarks/metrics_validation.py [--pairs ant:pebbles ant:grass ...] [--seeds 5] [--full]

For each (content, style) pair, every style metric is computed for
  floor     the style against an independent copy of itself (the procedural generator's seed 1),
  negative  the unstylized content against the style,
  positive  a collage: registration + footprint selection without Sinkhorn (every style Gaussian over
            and under each registered cluster, mapped back unoptimized; wast3d.selection
            ``mode: footprint``): the style's own elements, whole, on the content's shape,
and the content metric (content_chamfer, in content spacings) for
  floor     the content against a copy jittered by 0.5 content spacings,
  negative  another shape (the airplane; both normalized to the unit ball),
  positive  the same positive control,
each at ``--seeds`` metric seeds (patches, crops and directions; the jitter for the content floor).
spread = the largest standard deviation over seeds among the three cases. Verdict: **valid** when
negative - floor >= 10 x spread and the positive control is closer to the floor than to the negative.
The content_chamfer rows also give ``style_relief``: the Chamfer distance, in style spacings, between
the style patch and its own flat base (a plane through it, sampled at the style's spacing, at the
offset that minimizes it): what a result scores that carries the style's relief exactly on a flat
content at the style's density, i.e. the part of content_chamfer that is the style's relief, not a
departure from the content's shape.
Writes results/benchmarks/metrics_validation.{csv,png}. ``--full`` adds the patch-matching metrics and
colour Sinkhorn (slow: seconds per call).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import OUT, Pairs, demo_scene, render_frames, style_scores, texture_reference_frames  # noqa: E402


def verdict(floor: float, neg: float, pos: float, spread: float) -> str:
    if neg - floor < 10 * spread:
        return "invalid: negative - floor < 10 x spread"
    if abs(pos - floor) >= abs(neg - pos):
        return "invalid: positive not closer to the floor than to the negative"
    return "valid"


def style_relief_chamfer(points: torch.Tensor, margin: float = 0.1, offsets: int = 21) -> float:
    """Chamfer between a planar style patch [N, 3] and its flat base, in the patch's mean spacing: the
    base is the least-squares plane of the points, sampled on a grid at that spacing over the patch's
    extent shrunk by ``margin`` on each side (edges left out on both sides; grid points more than a
    spacing from the patch's in-plane footprint dropped, since the plane's axes need not follow the
    patch's edges), at the best of ``offsets``
    heights (the 0-100 % quantiles of the points' heights)."""
    from wast3d.geometry import knn_mean_dist
    from wast3d.metrics import chamfer

    p = points.double()
    h = float(knn_mean_dist(p, 1).mean())
    c = p - p.mean(0)
    frame = torch.linalg.svd(c, full_matrices=False).Vh  # rows: in-plane u, v, then the normal
    q = c @ frame.T
    lo, hi = q.min(0).values, q.max(0).values
    m = margin * (hi - lo)
    inner = q[((q[:, :2] > lo[:2] + m[:2]) & (q[:, :2] < hi[:2] - m[:2])).all(1)]
    u = torch.arange(float(lo[0] + m[0]), float(hi[0] - m[0]), h, dtype=torch.float64)
    v = torch.arange(float(lo[1] + m[1]), float(hi[1] - m[1]), h, dtype=torch.float64)
    gu, gv = (g.flatten() for g in torch.meshgrid(u, v, indexing="ij"))
    from wast3d.geometry import knn

    on = knn(torch.stack([gu, gv], 1), inner[:, :2].contiguous(), 1)[0][:, 0] <= h  # the base under the patch only
    gu, gv = gu[on], gv[on]
    heights = torch.quantile(inner[:, 2], torch.linspace(0.0, 1.0, offsets, dtype=torch.float64))
    return min(chamfer(inner, torch.stack([gu, gv, torch.full_like(gu, float(z))], 1)) for z in heights) / h


def main() -> None:
    from wast3d.metrics import content_chamfer
    from wast3d.geometry import mean_spacing
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", nargs="+", default=["ant:pebbles", "ant:grass", "ant:wicker", "ant:stones"],
                    help="content:style; lego:STYLE once results/scenes/lego/surface.ply exists")
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--radius", type=float, default=1.0, help="footprint radius of the positive control (style spacings)")
    ap.add_argument("--full", action="store_true")
    ap.add_argument("--out", default=str(OUT / "metrics_validation.csv"), help="CSV (the PNG beside it)")
    a = ap.parse_args()
    torch.set_num_threads(2)
    rows = []
    tmp = Path(tempfile.mkdtemp(prefix="wast3d_validation_"))
    for spec in a.pairs:
        cname, sname = spec.split(":")
        content, style, style_b = demo_scene(cname), demo_scene(sname), demo_scene(sname, seed=1)
        other = demo_scene("airplane" if cname != "airplane" else "ant").means.double()
        cc0, oc0 = content.means.double().mean(0), other.mean(0)  # the other shape at the content's place and size
        other = (other - oc0) * ((content.means.double() - cc0).norm(dim=1).max() / (other - oc0).norm(dim=1).max()) + cc0
        positive, _, _ = Pairs(content, style).run({"select": {"mode": "footprint", "radius": a.radius},
                                                     "stylize": {"iterations": 0}})
        # texture: the style and its copy at the pixel scale of renders fitted to the content (the
        # texture reference), the content and the collage in those renders
        fr = {"style": texture_reference_frames(style, content, tmp / f"{spec}_style"),
              "floor": texture_reference_frames(style_b, content, tmp / f"{spec}_floor"),
              "negative": render_frames(content, content, tmp / f"{spec}_negative"),
              "positive": render_frames(positive, content, tmp / f"{spec}_positive")}
        cases = {"floor": style_b, "negative": content, "positive": positive}
        vals: dict[str, dict[str, list]] = {}
        for seed in range(a.seeds):
            for case, sc in cases.items():
                for k, v in style_scores(sc, fr[case], style, fr["style"], seed, fast=not a.full).items():
                    vals.setdefault(k, {}).setdefault(case, []).append(v)
            h = mean_spacing(content.means)
            g = torch.Generator().manual_seed(seed)
            jit = content.means + 0.5 * h * torch.randn(content.means.shape, generator=g) / 3**0.5
            cc = vals.setdefault("content_chamfer", {})
            cc.setdefault("floor", []).append(content_chamfer(jit, content.means))
            cc.setdefault("negative", []).append(content_chamfer(other.float(), content.means))
            cc.setdefault("positive", []).append(content_chamfer(positive.means, content.means))
            print(f"{spec}: seed {seed} done", flush=True)
        for metric, v in vals.items():
            if not all(c in v for c in ("floor", "negative", "positive")):
                continue
            m = {c: float(np.mean(v[c])) for c in v}
            spread = max(float(np.std(v[c], ddof=1)) if len(v[c]) > 1 else 0.0 for c in v)
            extra = {"style_relief": style_relief_chamfer(style.means)} if metric == "content_chamfer" else {}
            rows.append({"pair": spec, "metric": metric, **m, "spread": spread, **extra,
                         "separation": (m["negative"] - m["floor"]) / spread if spread > 0 else float("inf"),
                         "verdict": verdict(m["floor"], m["negative"], m["positive"], spread)})
            print(f"{spec} {metric:22s} floor {m['floor']:.4g} negative {m['negative']:.4g} positive "
                  f"{m['positive']:.4g} spread {spread:.2g} -> {rows[-1]['verdict']}", flush=True)
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    df = pd.DataFrame(rows)
    df.to_csv(out, index=False)
    plot(df, out.with_suffix(".png"))
    print(f"wrote {out} and {out.with_suffix('.png')}")


def plot(df: pd.DataFrame, path: Path) -> None:
    """One panel per metric: floor, positive and negative of each pair on a scale where floor = 0 and
    negative = 1, with the 10 x spread band."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    metrics = list(dict.fromkeys(df["metric"]))
    fig, axes = plt.subplots(1, len(metrics), figsize=(3.2 * len(metrics), 3.2), squeeze=False)
    for ax, met in zip(axes[0], metrics):
        d = df[df.metric == met].reset_index(drop=True)
        span = (d.negative - d.floor).where(lambda s: s.abs() > 0, 1e-12)
        x = np.arange(len(d))
        ax.bar(x, 10 * d.spread / span.abs(), color="0.85", label="10 x spread")
        ax.scatter(x, np.zeros(len(d)), marker="_", s=200, c="k", label="floor")
        ax.scatter(x, np.ones(len(d)), marker="x", c="tab:red", label="negative (content)")
        ax.scatter(x, (d.positive - d.floor) / span, marker="o", c="tab:green", label="positive control")
        ax.set_xticks(x, [p.split(":")[1] for p in d.pair], rotation=45)
        ax.set_title(met, fontsize=9)
        ax.set_ylim(-0.5, 2.0)
    axes[0][0].legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    main()

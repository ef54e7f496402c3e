"""Every stage's time and peak memory against the content's size, up to the paper's (1e6-4e6 Gaussians).

    python benchmarks/content_size.py [--sizes 100000 300000 1000000 3000000] [--style-size 1000000]

Content: N Gaussians on a procedural mesh (``--content``) plus 5 % floaters and interior Gaussians, as a
trained capture holds, so that surface sampling has work to do; style: procedural ``--style`` of
``--style-size`` Gaussians. The stages run through the functions the workflow's rules call, at the
settings of ``config/paper_scale.yaml``'s ``paper`` experiment (400 clusters, 30 steps, Sinkhorn to 0.1
eps), each in one process, one size after another: surface sampling (stage 2), k-means (3),
registration and selection (4), Sinkhorn (5), scale readjustment (6) and a turntable of the result (7).
Per stage: wall time, peak resident memory above the process's level before it (Linux: VmHWM reset
through /proc/self/clear_refs) and the process's own peak, and the growth exponent of its time between
successive sizes (1: linear). Writes ``results/benchmarks/content_size.{csv,png}`` and each size's turntable,
key views and close-up under ``results/benchmarks/content_size/N/``.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import torch
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import OUT, ROOT, Peak, rss_mb, write_rows  # noqa: E402


def paper_blocks() -> dict:
    """The paper experiment's blocks of config/paper_scale.yaml (its partition's and its own)."""
    cfg = yaml.safe_load((ROOT / "config" / "paper_scale.yaml").read_text())
    exp = cfg["experiments"]["paper"]
    part = cfg["partitions"][exp["partition"]]
    return {**part, **{k: v for k, v in exp.items() if k != "partition"}}


def content_with_junk(name: str, n: int, seed: int = 0):
    """N Gaussians on the procedural mesh ``name`` plus 5 % junk: half inside it, half floating around it."""
    from wast3d.gaussians import GaussianScene
    from wast3d.procedural import make_scene

    surf = make_scene("content", name, n, seed=seed)
    g = torch.Generator().manual_seed(seed)
    k = max(n // 20, 1)
    junk = torch.cat([torch.randn(k // 2, 3, generator=g) * 0.2, (torch.rand(k - k // 2, 3, generator=g) - 0.5) * 4])
    extra = GaussianScene.from_activated(junk, torch.full((k, 3), float(surf.scales.median())), opacities=0.5)
    return GaussianScene.concat([surf, extra])


def apply_sets(blocks: dict, sets: list[str]) -> dict:
    """BLOCK.KEY=VALUE overrides (YAML values) applied to the experiment's blocks, in place."""
    for kv in sets:
        path, value = kv.split("=", 1)
        *keys, leaf = path.split(".")
        node = blocks
        for k in keys:
            node = node.setdefault(k, {})
        node[leaf] = yaml.safe_load(value)
    return blocks


def run_size(n: int, style, blocks: dict, content_name: str, render_size: int) -> list[dict]:
    from wast3d.clustering import ClusterConfig, cluster_content
    from wast3d.options import make_config
    from wast3d.registration import RegistrationConfig, register
    from wast3d.render import RenderConfig, render_turntable
    from wast3d.rescale import RescaleConfig, rescale
    from wast3d.selection import SelectConfig, select_style
    from wast3d.stylize import StylizeConfig, stylize
    from wast3d.surface import SurfaceConfig, surface_points

    rows = []

    def step(name, fn, out=lambda r: None):
        with Peak() as p:
            r = fn()
        rows.append({"n": n, "stage": name, "seconds": p.seconds, "peak_mb": p.mb, "process_peak_mb": rss_mb("VmHWM"),
                     "out": out(r)})
        print(f"{n:>9} {name:10s} {p.seconds:8.1f} s  +{p.mb:7.0f} MB  (process {rss_mb('VmHWM'):7.0f} MB)  {out(r)}",
              flush=True)
        return r

    raw = step("content", lambda: content_with_junk(content_name, n), len)
    content = step("surface", lambda: surface_points(raw, make_config(SurfaceConfig, {}, "surface"))[0], len)
    del raw
    cl = step("cluster", lambda: cluster_content(content, make_config(ClusterConfig, blocks.get("cluster"), "cluster")),
              lambda c: int(c.labels.max()) + 1)
    reg = step("register", lambda: register(content.means, cl.labels, style.means,
                                            make_config(RegistrationConfig, blocks.get("register"), "register"),
                                            normals=cl.normals), lambda r: round(float(r.residual.mean()), 3))
    sel = step("select", lambda: select_style(make_config(SelectConfig, blocks.get("select"), "select"), content,
                                              cl.labels, style, reg), lambda s: len(s.indices))
    res = step("sinkhorn", lambda: stylize(content, cl.labels, style, reg, sel,
                                           make_config(StylizeConfig, blocks.get("stylize"), "stylize"), progress=False),
               lambda r: len(r.scene))
    final, _ = step("rescale", lambda: rescale(res.scene, res.before_means, res.labels,
                                               make_config(RescaleConfig, blocks.get("rescale"), "rescale")),
                    lambda r: len(r[0]))
    pictures = OUT / "content_size" / str(n)  # the turntable kept: look at the result, not only its times
    step("render", lambda: render_turntable(final, content, pictures, RenderConfig(frames=24, size=render_size,
                                                                                   closeup_size=512)),
         lambda i: i["frames"])
    return rows


def plot(df, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4.2))
    for stage, d in df[df.stage != "content"].groupby("stage", sort=False):
        a.loglog(d.n, d.seconds, "o-", label=stage)
        b.semilogx(d.n, d.process_peak_mb / 1024, "o-", label=stage)
    n = sorted(df.n.unique())
    ref = df[(df.stage == "sinkhorn")].seconds
    if len(ref):
        a.loglog(n, [float(ref.iloc[0]) * x / n[0] for x in n], "k:", lw=1, label="linear")
    a.set_xlabel("content Gaussians")
    a.set_ylabel("seconds (2 threads)")
    a.legend(fontsize=7)
    a.set_title("time per stage")
    b.axhline(8, color="r", lw=0.8, ls="--")
    b.set_xlabel("content Gaussians")
    b.set_ylabel("process peak, GB")
    b.set_title("peak resident memory after each stage")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[100_000, 300_000, 1_000_000, 3_000_000])
    ap.add_argument("--style-size", type=int, default=1_000_000)
    ap.add_argument("--content", default="airplane")
    ap.add_argument("--style", default="pebbles")
    ap.add_argument("--render-size", type=int, default=256)
    ap.add_argument("--set", nargs="*", default=[], help="BLOCK.KEY=VALUE overrides of the paper experiment's blocks")
    ap.add_argument("--out", type=Path, default=OUT / "content_size.csv")
    a = ap.parse_args()
    torch.set_num_threads(2)
    torch.set_flush_denormal(True)
    from wast3d.procedural import make_scene

    blocks = paper_blocks()
    apply_sets(blocks, a.set)
    t = time.perf_counter()
    style = make_scene("style", a.style, a.style_size)
    print(f"style: {len(style)} Gaussians in {time.perf_counter() - t:.1f} s; blocks {blocks}", flush=True)
    rows = []
    for n in a.sizes:
        rows += run_size(n, style, blocks, a.content, a.render_size)
        df = write_rows(rows, a.out)
    df["growth"] = float("nan")
    for stage, d in df.groupby("stage"):
        d = d.sort_values("n")
        df.loc[d.index[1:], "growth"] = [math.log(t1 / t0) / math.log(n1 / n0) if t0 > 0 and t1 > 0 else float("nan")
                                         for (n0, t0), (n1, t1) in zip(zip(d.n[:-1], d.seconds[:-1]),
                                                                       zip(d.n[1:], d.seconds[1:]))]
    total = df[~df.stage.isin(["content", "render"])].groupby("n").seconds.sum()
    for n, s in total.items():
        df.loc[len(df)] = {"n": n, "stage": "stylization (stages 2-6)", "seconds": s,
                           "process_peak_mb": df[df.n == n].process_peak_mb.max()}
    write_rows(df.to_dict("records"), a.out)
    plot(df[~df.stage.str.startswith("stylization")], a.out.with_suffix(".png"))
    print(df.to_string(index=False))
    print(f"wrote {a.out} and {a.out.with_suffix('.png')}")


if __name__ == "__main__":
    main()

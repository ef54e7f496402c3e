"""Content fidelity against style fidelity against run time: the pipeline's own "error
against run time".

    python benchmarks/style_tradeoff.py [--pairs ant:pebbles ...] [--variants NAME ...] [--seeds 1]

For each (content, style) pair, stages 3-6 run with the library's functions (k-means and registration
each partition made once: benchmarks/common.Pairs over wast3d.pair, the rules' stage functions) for every variant below, one setting
changed at a time from ``base`` (and a few from ``footprint``); every result is rendered (24 turntable frames, 256 px, cameras fitted
to the content) and scored:

  content_chamfer  result vs content surface, in content spacings (lower: the content's shape)
  relief_w1        local shape at the style's element scale vs the style scene (lower: more style)
  tilt_w1_deg      Gaussian orientation vs local surface, W1 in degrees, vs the style
  texture_swd      Laplacian-pyramid patch SWD of the result's frames vs the style's texture reference
  coverage         share of the content render's foreground the result covers (holes: < 1)
  seconds          selection + stylization + scale readjustment (2 threads)

and two references: ``input`` (the unstylized content) and ``collage`` (registration + footprint
selection, no optimization: the style's elements whole on the content's shape). Which metrics are
valid is benchmarks/metrics_validation.py's verdict. Rows are appended to
results/benchmarks/style_tradeoff.csv as they finish (a run can be stopped and resumed; finished
(pair, variant) rows are skipped); the plot results/benchmarks/style_tradeoff.png is redrawn at the end.
Renders are kept under results/benchmarks/renders/style_tradeoff/ (``--renders``); ``--rescore``
recomputes the image metric of every finished row from them (after a change of the image metric),
without re-running any stylization.
"""

from __future__ import annotations

import argparse
import copy
import shutil
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import OUT, Pairs, demo_scene, render_frames, texture_reference_frames, texture_score  # noqa: E402

# base: the paper's recipe as we read it (eq. 8 kNN selection with k = 3, Adam at lr 0.01, gamma 0.3)
BASE = {"reg": 1.0, "select": {"mode": "knn", "k": 3},
        "stylize": {"iterations": 60, "optimizer": "adam", "lr": 0.01, "sinkhorn": {"blur": 0.3, "tol": 1e-3}},
        "bound": 2.0}


def _with(**kw) -> dict:
    v = copy.deepcopy(BASE)
    for key, val in kw.items():
        if isinstance(val, dict):
            for k2, v2 in val.items():
                if isinstance(v2, dict):
                    v[key].setdefault(k2, {}).update(v2)
                else:
                    v[key][k2] = v2
        else:
            v[key] = val
    return v


VARIANTS = {
    "base": _with(),
    # below 0.3 the converged solve (tol 1e-3) costs minutes per pair (> 440 s at 0.05): these run the
    # fixed eps-scaling schedule with 3 warm iterations (the old default; its error: 19 % at 0.05)
    **{f"gamma_{g:g}": _with(stylize={"sinkhorn": {"blur": g, "tol": 0.0}}) for g in (0.02, 0.05, 0.1)},
    **{f"gamma_{g:g}": _with(stylize={"sinkhorn": {"blur": g}}) for g in (0.6, 1.0)},
    "reg_2x": _with(reg=2.0),
    "reg_0.5x": _with(reg=0.5),
    "k_16": _with(select={"k": 16}),
    "footprint": _with(select={"mode": "footprint", "radius": 1.0}),
    "footprint_gamma_1": _with(select={"mode": "footprint", "radius": 1.0}, stylize={"sinkhorn": {"blur": 1.0}}),
    "steps_20": _with(stylize={"iterations": 20}),
    "steps_120": _with(stylize={"iterations": 120}),
    "bound_1.2": _with(bound=1.2),
    "bound_4": _with(bound=4.0),
    "footprint_steps_20": _with(select={"mode": "footprint", "radius": 1.0}, stylize={"iterations": 20}),
    "footprint_lr_0.003": _with(select={"mode": "footprint", "radius": 1.0}, stylize={"lr": 0.003}),
    "lr_0.003": _with(stylize={"lr": 0.003}),
    "flow": _with(stylize={"optimizer": "flow", "lr": 0.1}),
    "footprint_flow": _with(select={"mode": "footprint", "radius": 1.0}, stylize={"optimizer": "flow", "lr": 0.1}),
    **{f"footprint_flow_gamma_{g:g}": _with(select={"mode": "footprint", "radius": 1.0},
                                            stylize={"optimizer": "flow", "lr": 0.1, "sinkhorn": {"blur": g}})
       for g in (0.6, 1.0)},
    "footprint_flow_gamma_0.45": _with(select={"mode": "footprint", "radius": 1.0},
                                       stylize={"optimizer": "flow", "lr": 0.1, "sinkhorn": {"blur": 0.45}}),
    **{f"footprint_r1.5_flow_gamma_{g:g}": _with(select={"mode": "footprint", "radius": 1.5},
                                                 stylize={"optimizer": "flow", "lr": 0.1, "sinkhorn": {"blur": g}})
       for g in (0.3, 0.45, 0.6)},
    "footprint_r1.5_flow_gamma_0.3_steps_30_lr_0.2": _with(
        select={"mode": "footprint", "radius": 1.5},
        stylize={"optimizer": "flow", "lr": 0.2, "iterations": 30, "sinkhorn": {"blur": 0.3}}),
    "footprint_r2_flow_gamma_0.3": _with(select={"mode": "footprint", "radius": 2.0},
                                         stylize={"optimizer": "flow", "lr": 0.1, "sinkhorn": {"blur": 0.3}}),
    "footprint_flow_gamma_0.6_bound_4": _with(select={"mode": "footprint", "radius": 1.0}, bound=4.0,
                                              stylize={"optimizer": "flow", "lr": 0.1, "sinkhorn": {"blur": 0.6}}),
    "footprint_flow_gamma_0.1": _with(select={"mode": "footprint", "radius": 1.0},
                                      stylize={"optimizer": "flow", "lr": 0.1, "sinkhorn": {"blur": 0.1, "tol": 0.0}}),
    "collage": _with(select={"mode": "footprint", "radius": 1.0}, stylize={"iterations": 0}),
    "input": None,
}


def main() -> None:
    from wast3d.image_metrics import coverage
    from wast3d.metrics import content_chamfer
    from wast3d.ply import write_ply
    from wast3d.geometry import mean_spacing
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", nargs="+", default=["ant:pebbles", "ant:grass", "ant:wicker", "ant:stones"],
                    help="content:style; lego:STYLE once results/scenes/lego/surface.ply exists")
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    ap.add_argument("--seeds", type=int, default=1, help="metric seeds per result (mean; with 2 or more also *_std columns)")
    ap.add_argument("--out", default=str(OUT / "style_tradeoff.csv"))
    ap.add_argument("--renders", default=str(OUT / "renders" / "style_tradeoff"), help="folder of the kept renders")
    ap.add_argument("--rescore", action="store_true", help="recompute texture_swd of the finished rows from the kept renders")
    a = ap.parse_args()
    torch.set_num_threads(2)
    out = Path(a.out)
    tmp = Path(a.renders)
    if a.rescore:
        rescore(out, tmp, a.seeds)
        return
    out.parent.mkdir(parents=True, exist_ok=True)
    done = set()
    if out.exists():
        old = pd.read_csv(out)
        done = set(zip(old.pair, old.variant))
    for spec in a.pairs:
        cname, sname = spec.split(":")
        todo = [v for v in a.variants if (spec, v) not in done]
        if not todo:
            print(f"{spec}: all variants done, skipped")
            continue
        content, style = demo_scene(cname), demo_scene(sname)
        h = mean_spacing(content.means)
        style_frames = render_frames(style, style, tmp / f"{spec}_style")
        reference = texture_reference_frames(style, content, tmp / f"{spec}_texture_reference")
        content_frames = render_frames(content, content, tmp / f"{spec}_content")
        pairs = Pairs(content, style)
        s0 = mean_spacing(style.means) / h
        sheet = {"style": style_frames[SHEET_FRAME, ..., :3].clone()}
        for name in todo:
            v = VARIANTS[name]
            t0 = time.perf_counter()
            if v is None:
                result, secs, curves = content, 0.0, []
            else:
                result, secs, curves = pairs.run({
                    "register": {"scale": 0.0 if v["reg"] == 1.0 else v["reg"] * s0}, "select": v["select"],
                    "stylize": v["stylize"], "rescale": {"bound": v["bound"]}})
            shutil.rmtree(tmp / f"{spec}_{name}", ignore_errors=True)  # a re-run variant: never an old render
            frames = render_frames(result, content, tmp / f"{spec}_{name}")
            sheet[name] = frames[SHEET_FRAME, ..., :3].clone()
            row = {"pair": spec, "variant": name, "seconds": secs, "gaussians": len(result),
                   "content_chamfer": content_chamfer(result.means, content.means),
                   "coverage": coverage(frames[..., 3], content_frames[..., 3])}
            write_ply(tmp / f"{spec}_{name}" / "result.ply", result)  # kept: --rescore recomputes from it
            row.update(seed_scores(result, frames, style, reference, a.seeds))
            row["negative_losses"] = int(sum(1 for c in curves if c and min(c) < -1e-6 * abs(c[0])))
            row["wall_seconds"] = time.perf_counter() - t0
            done_rows = [pd.read_csv(out)] if out.exists() else []  # columns may differ (*_std): align by name
            pd.concat(done_rows + [pd.DataFrame([row])], ignore_index=True).to_csv(out, index=False)
            print(f"{spec} {name:18s} " + " ".join(f"{k} {row[k]:.4g}" for k in
                  ("content_chamfer", "relief_w1", "tilt_w1_deg", "texture_swd", "coverage", "seconds")), flush=True)
        contact_sheet(sheet, out.parent / f"style_tradeoff_{cname}_{sname}.png")
    plot(pd.read_csv(out), out.with_suffix(".png"))
    print(f"wrote {out} and {out.with_suffix('.png')}")


SHEET_FRAME = 2


def contact_sheet(frames: dict, path: Path) -> None:
    """Each result's turntable frame SHEET_FRAME [H, W, 3] over a 2x close-up of its centre."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, len(frames), figsize=(2.2 * len(frames), 4.6), squeeze=False)
    for j, (name, img) in enumerate(frames.items()):
        h, w = img.shape[:2]
        axes[0][j].imshow(img.clamp(0, 1).numpy())
        axes[1][j].imshow(img[h // 4:3 * h // 4, w // 4:3 * w // 4].clamp(0, 1).numpy(), interpolation="nearest")
        axes[0][j].set_title(name, fontsize=7)
        for ax in axes[:, j]:
            ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def seed_scores(result, frames, style, reference, seeds: int) -> dict:
    """relief_w1, tilt_w1_deg and texture_swd of a result: the mean over ``seeds`` metric seeds and,
    with 2 or more, the standard deviation (``*_std``: the noise a difference is measured against)."""
    from wast3d.metrics import MetricsConfig, relief_w1, tilt_degrees, wasserstein_1d

    vals: dict[str, list] = {}
    for seed in range(seeds):
        m = MetricsConfig(seed=seed)
        for k, v in (("relief_w1", relief_w1(result.means, style.means, m)),
                     ("tilt_w1_deg", wasserstein_1d(tilt_degrees(result, m.normal_k), tilt_degrees(style, m.normal_k))),
                     ("texture_swd", texture_score(frames, reference, seed))):
            vals.setdefault(k, []).append(v)
    out = {k: float(np.mean(v)) for k, v in vals.items()}
    if seeds > 1:
        out.update({f"{k}_std": float(np.std(v, ddof=1)) for k, v in vals.items()})
    return out


def rescore(out: Path, renders: Path, seeds: int) -> None:
    """Recompute the seeded metrics of every row of ``out`` from the renders (and result.ply) kept
    under ``renders``: all of them where the result was kept, texture_swd alone where only the frames were."""
    from wast3d.ply import read_ply
    from wast3d.render import read_frames

    df = pd.read_csv(out)
    refs, styles = {}, {}
    for i, r in df.iterrows():
        folder = renders / f"{r.pair}_{r.variant}"
        if not (folder / "frames").is_dir():
            print(f"{r.pair} {r.variant}: no kept render under {folder}, left as it was")
            continue
        if r.pair not in refs:
            cname, sname = r.pair.split(":")
            styles[r.pair] = demo_scene(sname)
            refs[r.pair] = texture_reference_frames(styles[r.pair], demo_scene(cname),
                                                    renders / f"{r.pair}_texture_reference")
        frames = read_frames(folder)
        if (folder / "result.ply").exists() or r.variant == "input":
            result = demo_scene(r.pair.split(":")[0]) if r.variant == "input" else read_ply(folder / "result.ply")
            for k, v in seed_scores(result, frames, styles[r.pair], refs[r.pair], seeds).items():
                df.loc[i, k] = v
        else:
            df.loc[i, "texture_swd"] = float(np.mean([texture_score(frames, refs[r.pair], sd) for sd in range(seeds)]))
        print(f"{r.pair} {r.variant:18s} relief_w1 {df.loc[i, 'relief_w1']:.4g} texture_swd {df.loc[i, 'texture_swd']:.4g}",
              flush=True)
    df.to_csv(out, index=False)
    plot(df, out.with_suffix(".png"))
    print(f"rescored {out}")


def plot(df: pd.DataFrame, path: Path) -> None:
    """Per pair: style fidelity (relief_w1, texture_swd) against content fidelity, and against time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pairs = list(dict.fromkeys(df.pair))
    cols = [("content_chamfer", "relief_w1"), ("content_chamfer", "texture_swd"), ("seconds", "relief_w1"),
            ("seconds", "texture_swd")]
    fig, axes = plt.subplots(len(pairs), len(cols), figsize=(4.2 * len(cols), 3.4 * len(pairs)), squeeze=False)
    for r, pair in enumerate(pairs):
        d = df[df.pair == pair]
        for c, (x, y) in enumerate(cols):
            ax = axes[r][c]
            for _, row in d.iterrows():
                ref = row.variant in ("input", "collage")
                ax.scatter(row[x], row[y], marker="s" if ref else "o", c="tab:red" if ref else "tab:blue", s=18)
                ax.annotate(row.variant, (row[x], row[y]), fontsize=6)
            ax.set_xlabel(x + (" (content spacings)" if x == "content_chamfer" else ""))
            ax.set_ylabel(y)
            ax.set_title(pair, fontsize=9)
            if x == "seconds":
                ax.set_xscale("symlog", linthresh=1.0)
    fig.tight_layout()
    fig.savefig(path, dpi=100)


if __name__ == "__main__":
    main()

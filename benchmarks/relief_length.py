"""The style's relief length (registration.relief) over seeds and trained copies, read now and as before.

    python benchmarks/relief_length.py [--seeds 4] [--out results/benchmarks/relief_length.csv]

Every rule measured in relief lengths (registration's element scale s0, the flow's parts and its
smoothing reach, the relief basins) inherits L, so L should be the style's, not the patch's: four
patches of each procedural style (seeds 0..3, 30k Gaussians, and seed 0 at 10k), the demo's trained
copies (``results/scenes/<style>_trained/style.ply``, cleaned, where the workflow made them) and the
shared fruit capture (``../shared/data/real_3dgs``, cleaned by ``surface.clean_style``, where present).
Each is read by the rule now (the autocorrelation's 0.05 crossing over 0.92, at least twice the
interquartile range of the top heights) and by the plain zero crossing, in the same
run. Writes the CSV, and prints per style the spread over seeds (max / min) and each trained copy's
L over its source's (seed 0).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path


sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import OUT, ROOT, write_rows  # noqa: E402

STYLES = ("pebbles", "stones", "grass", "wicker")


# the plain rule: the first zero crossing, no height bound
RULES = {"now": {}, "zero_crossing": {"level": 0.0, "level_ratio": 1.0, "height_factor": 0.0}}


def patches(seeds: int):
    """(style, source, seed, Gaussians, positions [M, 3]) of every patch measured."""
    from wast3d.formats import read_scene
    from wast3d.procedural import style_scene
    from wast3d.surface import StyleCleanConfig, clean_style

    for name in STYLES:
        for seed in range(seeds):
            yield name, "procedural", seed, 30000, style_scene(name, 30000, seed=seed).means
        yield name, "procedural", 0, 10000, style_scene(name, 10000, seed=0).means
        trained = ROOT / f"results/scenes/{name}_trained/style.ply"
        if trained.exists():
            m = read_scene(trained).means
            yield name, "trained (demo, cleaned)", 0, len(m), m
    fruit = ROOT.parent / "shared/data/real_3dgs/fruit_drops_sh3.ply"
    if fruit.exists():
        scene = read_scene(fruit)
        keep, _ = clean_style(scene, StyleCleanConfig())
        yield "fruit", "capture (cleaned)", 0, int(len(keep)), scene.means[keep]


def main() -> None:
    from wast3d.registration import relief

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--out", type=Path, default=OUT / "relief_length.csv")
    a = ap.parse_args()
    rows = []
    for name, source, seed, n, means in patches(a.seeds):
        row = {"style": name, "source": source, "seed": seed, "gaussians": n}
        for rule, kw in RULES.items():
            t = time.perf_counter()
            r = relief(means, **kw)
            row |= {f"L_{rule}": r.length, f"aspect_{rule}": r.aspect, f"s_{rule}": time.perf_counter() - t}
        rows.append(row)
        print({k: (round(v, 4) if isinstance(v, float) else v) for k, v in row.items()}, flush=True)
    df = write_rows(rows, a.out)
    seeds = df[(df.source == "procedural") & (df.gaussians == 30000)]
    print("\nspread over seeds (max / min of L), and trained copy / source (seed 0):")
    for name in STYLES:
        s = seeds[seeds["style"] == name]
        line = [f"{name:8s}"]
        for rule in reversed(RULES):
            line.append(f"{rule}: seeds {s[f'L_{rule}'].max() / s[f'L_{rule}'].min():.2f}")
            t = df[(df["style"] == name) & (df.source != "procedural")]
            if len(t):
                line.append(f"trained {float(t[f'L_{rule}'].iloc[0]) / float(s[s.seed == 0][f'L_{rule}'].iloc[0]):.2f}")
        print("  ".join(line))
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()

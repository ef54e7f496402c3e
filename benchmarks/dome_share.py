"""How much the k-means parts cut the style's domes (stylize.dome_share), over seeds, sizes and cleanings.

    python benchmarks/dome_share.py [--seeds 4] [--out results/benchmarks/dome_share.csv]

``stylize.parts.shape: auto`` takes the relief's basins instead of the k-means parts where the median
basin keeps less than ``parts.dome_cut`` of its Gaussians in one k-means part of ``parts.dome_probe``
relief lengths (whatever ``parts`` is). This reads that share,
with the stage's own functions and defaults (``stylize.flow_parts``' relief, k-means parts and basins),
on four patches of the procedural pebbles and stones (seeds 0..N-1, 30k and 8k Gaussians) and on the
cleaned trained copies the workflow made (``results/scenes/{pebbles,stones}{_trained,_seen05}/style.ply``,
where present: config/trained_styles.yaml, studies/style_cleaning), with what the labels say of each cut: the median
element's share of its Gaussians in one part (``whole``) and the lowest quarter's, for the k-means
parts (of ``parts.size`` and of the probe's size), the basins and the one auto chose. Prints the range per
style family and the gap the threshold must sit in.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import OUT, ROOT, write_rows  # noqa: E402

FAMILIES = ("pebbles", "stones")
TRAINED = ("_trained", "_seen05")


def scenes(seeds: int):
    """(family, source, seed, scene) of every patch measured."""
    from wast3d.formats import read_scene
    from wast3d.procedural import style_scene

    for name in FAMILIES:
        for seed in range(seeds):
            for n in (30000, 8000):
                yield name, f"procedural {n}", seed, style_scene(name, n, seed=seed)
        for tail in TRAINED:
            p = ROOT / f"results/scenes/{name}{tail}/style.ply"
            if p.exists():
                yield name, f"trained{tail} (cleaned)", 0, read_scene(p)


def whole(part: np.ndarray, el: np.ndarray, q: float) -> float:
    """The q-quantile over elements of the share of an element's Gaussians in its largest part."""
    return float(np.quantile([np.bincount(part[el == e]).max() / (el == e).sum() for e in np.unique(el[el > 0])], q))


def main() -> None:
    from wast3d.registration import relief, relief_basins, style_up
    from wast3d.stylize import StylizeConfig, dome_share, flow_parts, probe_parts, style_parts

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--out", type=Path, default=OUT / "dome_share.csv")
    a = ap.parse_args()
    cfg = StylizeConfig()
    rows = []
    for family, source, seed, s in scenes(a.seeds):
        up = style_up(s.means, "z").tolist()
        rel = relief(s.means, up=up)
        kmeans = style_parts(s.means, s.rgb, up, cfg.parts.size * rel.length, cfg.parts.colour)
        probe = probe_parts(s, up, rel.length, cfg)
        basins = relief_basins(s.means, up, rel.length)
        auto = flow_parts(s, up, cfg)
        row = {"family": family, "source": source, "seed": seed, "gaussians": len(s), "aspect": rel.aspect,
               "dome_share": dome_share(basins, probe), "chose": "relief" if torch_equal(auto, basins) else "kmeans"}
        if s.element is not None:
            el = s.element.numpy()
            for name, part in (("kmeans", kmeans), ("probe", probe), ("basins", basins), ("auto", auto)):
                row[f"whole_{name}"] = whole(part.numpy(), el, 0.5)
                row[f"q25_{name}"] = whole(part.numpy(), el, 0.25)
        rows.append(row)
        print({k: (round(v, 3) if isinstance(v, float) else v) for k, v in row.items()}, flush=True)
    df = write_rows(rows, a.out)
    print(f"\nparts.dome_cut {cfg.parts.dome_cut} at parts.dome_probe {cfg.parts.dome_probe} (parts.size {cfg.parts.size}):")
    for family in FAMILIES:
        d = df[df.family == family]
        print(f"  {family:8s} dome_share {d.dome_share.min():.3f}-{d.dome_share.max():.3f} over {len(d)} scenes; "
              f"chose {({k: int(v) for k, v in d.chose.value_counts().items()})}; median element whole: k-means "
              f"{d.whole_kmeans.min():.3f}-{d.whole_kmeans.max():.3f} (at the probe {d.whole_probe.min():.3f}-"
              f"{d.whole_probe.max():.3f}), basins {d.whole_basins.min():.3f}-"
              f"{d.whole_basins.max():.3f}, auto {d.whole_auto.min():.3f}-{d.whole_auto.max():.3f}")
    print(f"wrote {a.out}")


def torch_equal(a, b) -> bool:
    import torch

    return a is not None and bool(torch.equal(a, b))


if __name__ == "__main__":
    main()

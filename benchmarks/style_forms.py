"""Patch or volume: every style's thickness as the style stage tests it, and the label-free pieces against labels.

    python benchmarks/style_forms.py [--out results/benchmarks/style_forms.csv]

Rows of two kinds. ``form``: the thickness e_3 / e_2 (wast3d.volume) of every style the project knows,
read by the style stage's own function (``surface.clean_style`` at the defaults, visibility test off: the
form is decided before it): the procedural patches and volumes (seeds 0-1), the trained styles the
workflow made (``results/scenes/*_trained/scene.ply``, where present) and the real captures in
``../shared/data/real_3dgs`` (where present). ``pieces``: ``volume.volume_pieces`` on the procedural
volumes at 3-6 pieces across, against their labels: the median piece's purity (share of its labelled
Gaussians in its main element) and the median element's share of its Gaussians in its main piece.
Prints the gap between the patches' largest thickness and the volumes' smallest, which FLAT sits in.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import OUT, ROOT, write_rows  # noqa: E402

PATCHES = ("pebbles", "grass", "wicker", "stones")
VOLUMES = ("bouquet", "pinecone")


def styles():
    """(name, source, scene) of every style measured."""
    from wast3d.formats import read_scene
    from wast3d.procedural import style_scene

    for name in PATCHES + VOLUMES:
        for seed in (0, 1):
            yield name, f"procedural seed {seed}", style_scene(name, 30000, seed=seed)
    for p in sorted((ROOT / "results" / "scenes").glob("*_trained/scene.ply")):
        yield p.parent.name, "trained (results/scenes)", read_scene(p)
    for p in sorted((ROOT.parent / "shared" / "data" / "real_3dgs").glob("*.ply")):
        yield p.name, "capture (../shared/data)", read_scene(p)


def piece_scores(scene, across: int) -> dict:
    import wast3d.volume as volume

    old, volume.PIECES_ACROSS = volume.PIECES_ACROSS, across
    try:
        piece = volume.volume_pieces(scene.means.numpy(), scene.rgb.numpy())
    finally:
        volume.PIECES_ACROSS = old
    lab = scene.element.numpy()
    on = lab > 0
    joint = np.zeros((piece.max() + 1, lab.max() + 1))
    np.add.at(joint, (piece[on], lab[on]), 1)
    big = joint.sum(1) >= 20
    return {"pieces": int(piece.max()), "elements": int(lab.max()),
            "purity": float(np.median(joint.max(1)[big] / joint.sum(1)[big])),
            "held": float(np.median(joint.max(0)[1:] / np.maximum(joint.sum(0)[1:], 1)))}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, default=OUT / "style_forms.csv")
    a = ap.parse_args()
    import torch

    from wast3d.procedural import style_scene
    from wast3d.surface import StyleCleanConfig, clean_style
    from wast3d.volume import FLAT

    torch.set_num_threads(1)
    rows = []
    for name, source, scene in styles():
        _, rep = clean_style(scene, StyleCleanConfig(visibility=False))
        rows.append({"kind": "form", "style": name, "source": source, "gaussians": len(scene),
                     "thickness": rep["thickness"], "form": rep["form"]})
        print(f"{name:32s} {source:28s} thickness {rep['thickness']:.3f} -> {rep['form']}", flush=True)
    for name in VOLUMES:
        scene = style_scene(name, 30000, seed=0)
        for across in (3, 4, 5, 6):
            r = piece_scores(scene, across)
            rows.append({"kind": "pieces", "style": name, "source": "procedural seed 0", "across": across, **r})
            print(f"{name} pieces {across} across: {r}", flush=True)
    write_rows(rows, a.out)
    forms = [r for r in rows if r["kind"] == "form" and r["source"] != "capture (../shared/data)"]
    patch = max(r["thickness"] for r in forms if r["style"].split("_")[0] in PATCHES)
    vol = min(r["thickness"] for r in forms if r["style"].split("_")[0] in VOLUMES)
    print(f"patches up to {patch:.3f}, volumes from {vol:.3f}; FLAT = {FLAT}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

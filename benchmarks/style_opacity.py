"""Are a style's elements solid or see-through? Their alpha, by view elevation and zoom.

    python benchmarks/style_opacity.py SCENE|PLY:SOURCE ... [--out results/benchmarks/style_opacity.csv]

A style patch on a content is seen from every direction of its upper hemisphere, face-on wherever the
content is flat. Per scene (``results/scenes/SCENE/style.ply`` where style cleaning wrote one, else
``scene.ply``; labels from the PLY, or from the nearest Gaussian of ``results/scenes/SOURCE/scene.ply``,
SOURCE the name before the first ``_``; or a PLY file as it is, e.g. a trained style before cleaning:
``results/external/stones_trained.ply:stones``), three orbit views per elevation (90, 55, 30 degrees) at the
distance and size the demo's ``export_views`` renders it from (``cameras.fit_orbit``, 200 px: the
training scale of a trained style) and 3x closer (``render.closeup_zoom``'s default): the share of
element pixels (label channel > 0.5, alpha > 0.1) whose alpha is under 0.95, i.e. where whatever lies
behind the element shows through it. A procedural style's elements are solid discs (about 0.03).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import OUT, ROOT, write_rows  # noqa: E402

ELEVATIONS = (90.0, 55.0, 30.0)
ZOOMS = (1.0, 3.0)


def labelled(name: str):
    from wast3d.elements import transfer_elements
    from wast3d.formats import read_scene
    from wast3d.stages import artifact

    results = ROOT / "results"
    path, _, source = name.partition(":")
    if path.endswith(".ply"):
        s = read_scene(ROOT / path)
    else:
        cleaned = Path(artifact("style", results, scene=name))
        s = read_scene(cleaned if cleaned.exists() else artifact("scene", results, scene=name))
        source = name.split("_")[0]
    if s.element is None:
        src = read_scene(artifact("scene", results, scene=source))
        if src.element is None:
            raise ValueError(f"{name}: no element labels, and its source {source} has none")
        s.element = transfer_elements(s.means, src.means, src.element)
    return s


def see_through(scene, elevation: float, zoom: float) -> float:
    from dataclasses import replace

    from wast3d.cameras import fit_orbit
    from wast3d.elements import element_pixels, label_colours
    from wast3d.rasterizer import rasterize

    shares = []
    for cam in fit_orbit(scene, 3, 200, elevations_deg=(elevation,)):
        cam = replace(cam, fx=cam.fx * zoom, fy=cam.fy * zoom)
        m = rasterize(scene, cam, background=(0.0, 0.0, 0.0), colors=label_colours(scene.element, scene.dtype))
        px = (element_pixels(m.rgb, m.alpha) > 0.5) & (m.alpha > 0.1)
        shares.append(float((m.alpha[px] < 0.95).float().mean()) if bool(px.any()) else math.nan)
    return sum(shares) / len(shares)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", nargs="+")
    ap.add_argument("--out", type=Path, default=OUT / "style_opacity.csv")
    a = ap.parse_args()
    rows = []
    for name in a.scenes:
        s = labelled(name)
        row = {"scene": name, "gaussians": len(s)}
        for z in ZOOMS:
            for el in ELEVATIONS:
                row[f"see_through_{el:g}deg_x{z:g}"] = see_through(s, el, z)
        rows.append(row)
        print(" ".join(f"{k} {v:.3f}" if isinstance(v, float) else f"{k} {v}" for k, v in row.items()), flush=True)
    write_rows(rows, a.out)


if __name__ == "__main__":
    main()

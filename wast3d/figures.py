"""Pictures of intermediate artifacts (pyvista off-screen for 3D point sets, matplotlib for curves)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .io_utils import atomic_path


def _plotter(size=(900, 700)):
    import pyvista as pv

    pv.OFF_SCREEN = True
    os.environ.setdefault("PYVISTA_OFF_SCREEN", "true")
    p = pv.Plotter(off_screen=True, window_size=size)
    p.set_background("white")
    return p


def _palette(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    hues = rng.permutation(n) / max(n, 1)
    import colorsys

    return np.array([colorsys.hsv_to_rgb(h, 0.75, 0.9) for h in hues])


def clusters_picture(points: np.ndarray, labels: np.ndarray, path: str | Path, title: str = "") -> None:
    """Points coloured by cluster label."""
    import pyvista as pv

    pal = _palette(int(labels.max()) + 1)
    p = _plotter()
    cloud = pv.PolyData(points.astype(np.float32))
    cloud["rgb"] = (pal[labels] * 255).astype(np.uint8)
    p.add_points(cloud, scalars="rgb", rgb=True, point_size=4, render_points_as_spheres=True)
    if title:
        p.add_text(title, font_size=10, color="black")
    p.view_isometric()
    with atomic_path(path) as tmp:
        p.screenshot(str(tmp))
    p.close()


def registration_picture(panels: list[tuple[np.ndarray, np.ndarray, np.ndarray]], path: str | Path) -> None:
    """Each panel: (mapped content points [N,3], nearby style points [M,3], style colours [M,3]);
    content in red over the style patch, one sub-view per panel."""
    import pyvista as pv

    n = len(panels)
    cols = min(n, 3)
    rows = (n + cols - 1) // cols
    p = pv.Plotter(off_screen=True, shape=(rows, cols), window_size=(340 * cols, 320 * rows))
    for i, (c, s, sc) in enumerate(panels):
        p.subplot(i // cols, i % cols)
        p.set_background("white")
        sp = pv.PolyData(s.astype(np.float32))
        sp["rgb"] = (np.clip(sc, 0, 1) * 255).astype(np.uint8)
        p.add_points(sp, scalars="rgb", rgb=True, point_size=3)
        p.add_points(pv.PolyData(c.astype(np.float32)), color="red", point_size=5, render_points_as_spheres=True)
        p.add_text(f"cluster {i}", font_size=8, color="black")
        p.view_isometric()
    with atomic_path(path) as tmp:
        p.screenshot(str(tmp))
    p.close()


def loss_curves_picture(curves: list[list[float]], path: str | Path, title: str = "") -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for c in curves:
        ax.plot(c, color="tab:blue", alpha=0.25, lw=0.8)
    curves = [c for c in curves if len(c)]  # iterations: 0 (the positive control) has no curve
    if curves:
        L = min(len(c) for c in curves)
        ax.plot(np.mean([c[:L] for c in curves], 0), color="black", lw=2, label="mean over clusters")
        ax.legend()
    ax.set_xlabel("iteration")
    ax.set_ylabel("cluster loss (normalized units)")
    if curves and min(min(c) for c in curves) > 0:
        ax.set_yscale("log")
    ax.set_title(title)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp)
    plt.close(fig)

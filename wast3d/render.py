"""Stage 7, rendering: camera rigs fitted to a scene, preview grids, turntables and posed-image export.

Pure helpers take and return tensors; the ``save_*``/``export_*`` functions are the I/O edge.
"""

from __future__ import annotations

import math
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import torch

from .cameras import Camera, orbit_cameras
from .datasets import write_blender
from .gaussians import GaussianScene
from .io_utils import atomic_path
from .rendering import rasterize


def scene_bounds(scene: GaussianScene, q: float = 0.005) -> tuple[torch.Tensor, float]:
    """Robust centre [3] and radius of a scene (quantiles ``q``..``1-q`` ignore stray floaters)."""
    m = scene.means.detach().float()
    if len(m) == 0:
        return torch.zeros(3), 1.0
    lo = torch.quantile(m, q, dim=0) if len(m) > 1 else m[0]
    hi = torch.quantile(m, 1 - q, dim=0) if len(m) > 1 else m[0]
    centre = 0.5 * (lo + hi)
    radius = max(float(0.5 * (hi - lo).norm()), 1e-3)
    return centre, radius


def fit_orbit(scene: GaussianScene, n: int, width: int, height: int | None = None, fov_deg: float = 40.0,
              elevations_deg=(25.0, 45.0), margin: float = 0.95, phase_deg: float = 30.0) -> list[Camera]:
    """``n`` orbit cameras around the scene's centre at a distance that frames it (z up)."""
    centre, radius = scene_bounds(scene)
    dist = margin * radius / math.sin(math.radians(fov_deg) / 2)
    return orbit_cameras(n, dist, width, height or width, fov_deg, tuple(elevations_deg),
                         tuple(centre.tolist()), phase_deg=phase_deg)


@torch.no_grad()
def render_views(scene: GaussianScene, cams: list[Camera], background=(1.0, 1.0, 1.0), **kw) -> list[dict]:
    return [rasterize(scene, c, background=background, **kw) for c in cams]


def to_uint8(img: torch.Tensor) -> np.ndarray:
    """[H, W, C] float in [0, 1] -> uint8."""
    return (img.detach().clamp(0, 1).cpu().numpy() * 255 + 0.5).astype(np.uint8)


def grid(images: list[np.ndarray], cols: int) -> np.ndarray:
    """Tile equally sized [H, W, C] images into a grid, row-major."""
    rows = math.ceil(len(images) / cols)
    h, w, c = images[0].shape
    out = np.full((rows * h, cols * w, c), 255, np.uint8)
    for i, im in enumerate(images):
        r, k = divmod(i, cols)
        out[r * h:(r + 1) * h, k * w:(k + 1) * w] = im
    return out


def save_png(path: str | Path, img: np.ndarray) -> None:
    with atomic_path(path) as tmp:
        iio.imwrite(tmp, img, extension=".png")


def save_preview(scene: GaussianScene, path: str | Path, n_views: int = 4, size: int = 256,
                 background=(1.0, 1.0, 1.0)) -> None:
    """A 1 x n_views grid of orbit renders, for a quick look at a scene."""
    cams = fit_orbit(scene, n_views, size)
    imgs = [to_uint8(r["rgb"]) for r in render_views(scene, cams, background)]
    save_png(path, grid(imgs, n_views))


@torch.no_grad()
def export_blender(scene: GaussianScene, root: str | Path, n_views: int = 48, size: int = 200,
                   holdout_views: int = 0) -> None:
    """Render ``scene`` from orbit cameras into a Blender-format posed image set (train split).

    The renders are on a transparent background (RGBA with straight alpha), as NeRF-Synthetic.
    """
    cams = fit_orbit(scene, n_views, size, elevations_deg=(15.0, 35.0, 55.0), phase_deg=7.0)
    outs = render_views(scene, cams, background=(0.0, 0.0, 0.0))
    write_blender(root, cams, [o["rgb"] for o in outs], [o["alpha"] for o in outs])

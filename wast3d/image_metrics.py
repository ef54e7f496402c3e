"""Stage 8, weights-free image metrics on renders: texture statistics and coverage.

``texture_swd`` (Karras et al. 2018, "Progressive growing of GANs": sliced Wasserstein distance of
Laplacian-pyramid patch descriptors), between the turntable frames of a result and a *texture
reference* render of the style (:func:`wast3d.render.texture_reference_cameras`: the style's elements
at the pixel size they have in the result's render, since the registration maps one content spacing
onto one style spacing):

- each frame (composited on the background) is decomposed into a Laplacian pyramid
  ``L_l = G_l - up(G_{l+1})`` with ``G_0`` the frame and ``G_{l+1}`` its 2x2 average-pooled copy; only
  the band-pass levels ``l = 0 .. levels-1`` are used, never the low-pass residual, so the metric sees
  texture (edges, relief shading, the size of elements) and not the mean colour;
- descriptors: ``windows`` ``patch x patch`` windows of each level ([3 patch^2]), drawn uniformly among
  the windows lying *inside the foreground*: the alpha of level l (``alpha`` 2^l-average-pooled) is
  ``>= min_alpha`` over the window and a 2-pixel margin (the band-pass reads that far through the
  upsampling). Silhouette edges against the background are thereby left out: they are the content's
  outline, not texture, and would otherwise dominate a thin shape's descriptors;
- both sets of a level are divided by the per-channel standard deviation of the *style* set's
  descriptors (one fixed unit, so that a flat, low-contrast result is far from a rough style);
- SWD of a level: the mean over ``directions`` random unit directions of the exact 1-D W1 between
  the projections of the two sets (equal sizes: the mean absolute difference of the sorted
  projections); ``texture_swd`` is the mean over the levels where both sides hold at least
  ``min_windows`` distinct interior windows. A level with fewer is left out (and said): its
  ``windows`` descriptors would be a handful of windows drawn again and again. A trained style's
  reference, small and with soft edges at the result's pixel scale, has 0-1 such windows at level 1
  (the demo's pebbles_px07: 2,986 at level 0), where its one window drawn 2,048 times scored a result
  of its own pebbles farther from the style (1.30) than the plain content (0.88).

Deterministic given ``seed``; identical frame sets give exactly 0. Raises ``ValueError`` (naming the
level) when a side has no window inside its foreground at some level (a scattered or collapsed result).

``coverage``: the share of the reference render's foreground pixels (alpha > 0.5) where the result's
alpha is also > 0.5, over the same views: 1 = no holes where the content is.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from .options import checked, option


@dataclass
@checked("texture")
class TextureConfig:
    """levels: band-pass levels; patch: window side (px of its level); windows: descriptors per level and
    side; directions: random projections; min_alpha: foreground threshold of a window (and its margin);
    min_windows: distinct interior windows each side needs at a level for the level to count."""

    levels: int = option(2, "band-pass pyramid levels", minimum=1)
    patch: int = option(5, "window side in pixels of its level", minimum=1)
    windows: int = option(2048, "windows per level and side", minimum=1)
    directions: int = option(128, "random projections of the sliced distance", minimum=1)
    min_alpha: float = option(0.99, "a window (and a 2-pixel margin) must have at least this alpha: silhouettes are "
                                    "left out", exclusiveMinimum=0, maximum=1)
    min_windows: int = option(128, "distinct interior windows a level needs in both the result and the style reference "
                                   "to count (fewer: the level is left out, and the status says so)", minimum=1)
    seed: int = option(0, "seed of windows and directions")



MARGIN = 2  # pixels of a level around a window that must be foreground too (the upsampling's reach)


def laplacian_pyramid(img: torch.Tensor, levels: int) -> list[torch.Tensor]:
    """img: [n, c, H, W] -> ``levels`` band-pass images [n, c, H / 2^l, W / 2^l] (l = 0 .. levels-1)."""
    out, g = [], img
    for _ in range(levels):
        if min(g.shape[-2:]) < 2:
            break
        low = F.avg_pool2d(g, 2, ceil_mode=True)
        up = F.interpolate(low, size=g.shape[-2:], mode="bilinear", align_corners=False)
        out.append(g - up)
        g = low
    return out


def interior_windows(alpha: torch.Tensor, patch: int, min_alpha: float) -> torch.Tensor:
    """alpha: [V, h, w] -> [n, 3] (view, y0, x0) of every ``patch x patch`` window whose alpha, and that
    of a ``MARGIN``-pixel border around it, is >= ``min_alpha`` (outside the image counts as 0)."""
    a = F.pad(alpha[:, None], (MARGIN,) * 4, value=0.0)
    low = -F.max_pool2d(-a, patch + 2 * MARGIN, stride=1)  # [V, 1, h - patch + 1, w - patch + 1]
    return (low[:, 0] >= min_alpha).nonzero()


def window_descriptors(frames: torch.Tensor, cfg: TextureConfig, background=(1.0, 1.0, 1.0)) -> list[tuple]:
    """frames: [V, H, W, 4] straight alpha in [0, 1] -> per band-pass level, (descriptors
    [cfg.windows, 3 patch^2] of interior windows drawn with ``cfg.seed``, or None where the level has
    none; the number of distinct interior windows they were drawn from)."""
    bg = torch.as_tensor(background, dtype=torch.float64)
    f = frames.double()
    rgb = f[..., :3] * f[..., 3:] + (1 - f[..., 3:]) * bg
    pyramid = laplacian_pyramid(rgb.permute(0, 3, 1, 2), cfg.levels)
    alpha = f[..., 3][:, None]
    g = torch.Generator().manual_seed(cfg.seed)
    out: list[tuple] = []
    for lvl, band in enumerate(pyramid):
        a = alpha if lvl == 0 else F.avg_pool2d(alpha, 2 ** lvl, ceil_mode=True)
        p = cfg.patch
        ok = interior_windows(a[:, 0], p, cfg.min_alpha) if min(band.shape[-2:]) >= p else torch.zeros(0, 3)
        if len(ok) == 0:
            out.append((None, 0))
            continue
        pick = ok[torch.randint(0, len(ok), (cfg.windows,), generator=g)]
        win = band.unfold(2, p, 1).unfold(3, p, 1).permute(0, 2, 3, 1, 4, 5)  # [V, h-p+1, w-p+1, 3, p, p]
        out.append((win[pick[:, 0], pick[:, 1], pick[:, 2]].reshape(cfg.windows, -1), len(ok)))
    return out


def sliced_w1(a: torch.Tensor, b: torch.Tensor, directions: int, g: torch.Generator) -> float:
    """Sliced 1-Wasserstein distance between point sets a: [n, D] and b: [m, D] (the larger one is
    subsampled to the smaller size): mean over random unit directions of W1 of the projections."""
    n = min(len(a), len(b))
    a = a[torch.randperm(len(a), generator=g)[:n]]
    b = b[torch.randperm(len(b), generator=g)[:n]]
    d = torch.randn(a.shape[1], directions, generator=g, dtype=a.dtype)
    d = d / d.norm(dim=0, keepdim=True)
    pa, _ = (a @ d).sort(0)
    pb, _ = (b @ d).sort(0)
    return float((pa - pb).abs().mean())


def texture_levels(result_frames: torch.Tensor, style_frames: torch.Tensor, cfg: TextureConfig,
                   background=(1.0, 1.0, 1.0)) -> dict:
    """Frames [V, H, W, 4] (straight alpha in [0, 1]) of the result and of the style's texture reference
    -> ``{"texture_swd": mean over the used levels, "levels": [{"level", "swd" (None: left out),
    "result_windows", "style_windows"}]}`` (module docstring). ValueError when no level is usable."""
    da = window_descriptors(result_frames, cfg, background)
    db = window_descriptors(style_frames, cfg, background)
    if len(da) != cfg.levels or len(db) != cfg.levels:
        raise ValueError(f"texture: frames too small for {cfg.levels} pyramid levels")
    levels = []
    for lvl, ((a, na), (b, nb)) in enumerate(zip(da, db)):
        row = {"level": lvl, "swd": None, "result_windows": na, "style_windows": nb}
        if min(na, nb) >= cfg.min_windows:
            std = b.reshape(len(b), 3, -1).transpose(0, 1).reshape(3, -1).std(1).clamp_min(1e-6)
            unit = std.repeat_interleave(b.shape[1] // 3)
            g = torch.Generator().manual_seed(cfg.seed + 1)
            row["swd"] = sliced_w1(a / unit, b / unit, cfg.directions, g)
        levels.append(row)
    used = [r["swd"] for r in levels if r["swd"] is not None]
    if not used:
        counts = "; ".join(f"level {r['level']}: result {r['result_windows']}, style reference {r['style_windows']}"
                           for r in levels)
        raise ValueError(f"texture: no pyramid level has {cfg.min_windows} distinct {cfg.patch}x{cfg.patch} windows "
                         f"inside the foreground (alpha >= {cfg.min_alpha}) on both sides ({counts})")
    return {"texture_swd": float(sum(used) / len(used)), "levels": levels}


def texture_swd(result_frames: torch.Tensor, style_frames: torch.Tensor, cfg: TextureConfig,
                background=(1.0, 1.0, 1.0)) -> float:
    """The texture SWD of the module docstring (:func:`texture_levels`' mean)."""
    return texture_levels(result_frames, style_frames, cfg, background)["texture_swd"]


def coverage(result_alpha: torch.Tensor, reference_alpha: torch.Tensor, threshold: float = 0.5) -> float:
    """Share of the reference's foreground pixels (alpha > threshold) where the result's alpha > threshold.

    result_alpha, reference_alpha: [V, H, W] (same views). 1.0 when the reference has no foreground."""
    if result_alpha.shape != reference_alpha.shape:
        raise ValueError(f"coverage: renders differ in shape {list(result_alpha.shape)} vs {list(reference_alpha.shape)}")
    fg = reference_alpha > threshold
    n = int(fg.sum())
    return 1.0 if n == 0 else float((result_alpha[fg] > threshold).double().mean())


def close_mask(mask: torch.Tensor, radius: float) -> torch.Tensor:
    """Morphological closing (dilation, then erosion) of a [H, W] bool mask by a disc of ``radius``
    pixels (the pixel offsets with dx^2 + dy^2 <= radius^2): every gap narrower than the disc's diameter
    is filled, nothing outside the mask's convex parts is added. Pixels beyond the frame count as
    background; the dilation extends ``r`` = floor(radius) pixels past the frame before the erosion.
    Both steps by exact squared Euclidean distance transforms, O(H W) whatever the radius."""
    r = int(math.floor(radius))
    if r < 1 or not bool(mask.any()):
        return mask.clone()
    H, W = mask.shape
    grown = np.zeros((H + 2 * r, W + 2 * r), dtype=bool)
    grown[r:r + H, r:r + W] = mask.cpu().numpy()
    dilated = _squared_distance_to(grown) <= radius * radius
    if dilated.all():
        return torch.ones_like(mask)
    kept = _squared_distance_to(~dilated) > radius * radius
    return torch.from_numpy(kept[r:r + H, r:r + W].copy())


def _squared_distance_to(target: np.ndarray) -> np.ndarray:
    """Exact squared Euclidean distance (integer pixels) of each pixel to the nearest True of ``target``
    [H, W] (at least one True)."""
    from scipy.ndimage import distance_transform_edt

    idx = distance_transform_edt(~target, return_distances=False, return_indices=True)
    yy, xx = np.indices(target.shape)
    return (idx[0] - yy) ** 2 + (idx[1] - xx) ** 2


def projected_radii(cameras: list[dict], centre, length: float) -> list[float]:
    """Half of ``length`` (world units) in pixels at ``centre`` [3], per camera (``world_to_cam`` [4, 4]
    and ``fx``, as the renders' ``render.json`` lists them): ``0.5 fx length / z``."""
    c = torch.as_tensor(centre, dtype=torch.float64)
    out = []
    for cam in cameras:
        w2c = torch.as_tensor(cam["world_to_cam"], dtype=torch.float64)
        z = float(w2c[2, :3] @ c + w2c[2, 3])
        if not z > 0:
            raise ValueError(f"coverage: the content's centre is behind a camera (z = {z:g})")
        out.append(0.5 * float(cam["fx"]) * length / z)
    return out


def coverage_at_scale(result_alpha: torch.Tensor, reference_alpha: torch.Tensor, radii, threshold: float = 0.5) -> float:
    """:func:`coverage` with the result's gaps narrower than ``2 radii[v]`` pixels closed first
    (:func:`close_mask`, per view v). With the radius half a style element (``coverage_element``), a
    result whose elements leave the style's own gaps between them (the trained pebbles' sand between
    the stones, a weave's holes) scores as one without gaps, while a hole larger than an element (a
    part of the content lost) still counts. result_alpha, reference_alpha: [V, H, W]; radii: [V]."""
    if len(radii) != len(result_alpha):
        raise ValueError(f"coverage: {len(radii)} radii for {len(result_alpha)} views")
    closed = [close_mask(a > threshold, float(r)) for a, r in zip(result_alpha, radii)]
    return coverage(torch.stack(closed).to(result_alpha.dtype) if closed else result_alpha, reference_alpha, threshold)

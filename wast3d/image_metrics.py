"""Stage 8, weights-free image metrics on renders: texture statistics of crops and coverage.

``texture_swd`` (Karras et al. 2018, "Progressive growing of GANs", sliced Wasserstein distance of
Laplacian-pyramid patch descriptors), on the same crops as CLIP (:func:`wast3d.clip_eval.random_crops`):

- each crop [s, s, 3] is decomposed into a Laplacian pyramid: ``L_l = G_l - up(G_{l+1})`` with
  ``G_0`` the crop and ``G_{l+1}`` its 2x2 average-pooled copy; only the band-pass levels
  ``l = 0 .. levels-1`` are used, never the low-pass residual, so the metric sees texture (edges,
  relief shading, the scale of elements) and not the mean colour (that is ``colour_sinkhorn``'s job);
- descriptors: ``per_crop`` random ``patch x patch`` windows of every level, flattened ([3 patch^2]);
- both sets of a level are divided by the per-channel standard deviation of the *style* set's
  descriptors (one fixed unit, so that a flat, low-contrast result is far from a rough style);
- SWD of a level: the mean over ``directions`` random unit directions of the exact 1-D W1 between
  the projections of the two sets (equal sizes, so W1 is the mean absolute difference of the sorted
  projections); ``texture_swd`` is the mean over levels.

Deterministic given ``seed``; identical crop sets give exactly 0.

``coverage``: the share of the reference render's foreground pixels (alpha > 0.5) where the result's
alpha is also > 0.5, over the same views: 1 = no holes where the content is.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F


@dataclass
class TextureConfig:
    levels: int = 3
    patch: int = 7
    per_crop: int = 64
    directions: int = 128
    seed: int = 0

    def __post_init__(self):
        if self.levels < 1 or self.patch < 1 or self.per_crop < 1 or self.directions < 1:
            raise ValueError("texture: need levels, patch, per_crop, directions >= 1")


def laplacian_pyramid(img: torch.Tensor, levels: int) -> list[torch.Tensor]:
    """img: [n, 3, H, W] -> ``levels`` band-pass images [n, 3, H / 2^l, W / 2^l] (l = 0 .. levels-1)."""
    out, g = [], img
    for _ in range(levels):
        if min(g.shape[-2:]) < 2:
            break
        low = F.avg_pool2d(g, 2, ceil_mode=True)
        up = F.interpolate(low, size=g.shape[-2:], mode="bilinear", align_corners=False)
        out.append(g - up)
        g = low
    return out


def patch_descriptors(level: torch.Tensor, patch: int, per_crop: int, g: torch.Generator) -> torch.Tensor:
    """``per_crop`` random ``patch x patch`` windows of each image of level [n, 3, h, w] -> [n * per_crop, 3 patch^2]."""
    n, c, h, w = level.shape
    p = min(patch, h, w)
    win = level.unfold(2, p, 1).unfold(3, p, 1)  # [n, c, h-p+1, w-p+1, p, p]
    H, W = win.shape[2], win.shape[3]
    iy = torch.randint(0, H, (n, per_crop), generator=g)
    ix = torch.randint(0, W, (n, per_crop), generator=g)
    b = torch.arange(n)[:, None].expand(-1, per_crop)
    return win.permute(0, 2, 3, 1, 4, 5)[b, iy, ix].reshape(n * per_crop, -1)


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


def texture_swd(result_crops: torch.Tensor, style_crops: torch.Tensor, cfg: TextureConfig) -> float:
    """Crops [n, s, s, 3] (values in [0, 1]) of result and style -> the texture SWD of the module docstring."""
    if len(result_crops) == 0 or len(style_crops) == 0:
        raise ValueError(f"texture: need crops on both sides (result {len(result_crops)}, style {len(style_crops)})")
    ra = laplacian_pyramid(result_crops.double().permute(0, 3, 1, 2), cfg.levels)
    sa = laplacian_pyramid(style_crops.double().permute(0, 3, 1, 2), cfg.levels)
    scores = []
    for lr, ls in zip(ra, sa):
        g = torch.Generator().manual_seed(cfg.seed)  # same draws for both sides: identical sets -> 0
        da = patch_descriptors(lr, cfg.patch, cfg.per_crop, g)
        g = torch.Generator().manual_seed(cfg.seed)
        db = patch_descriptors(ls, cfg.patch, cfg.per_crop, g)
        std = db.reshape(len(db), 3, -1).transpose(0, 1).reshape(3, -1).std(1).clamp_min(1e-6)
        unit = std.repeat_interleave(db.shape[1] // 3)
        g = torch.Generator().manual_seed(cfg.seed + 1)
        scores.append(sliced_w1(da / unit, db / unit, cfg.directions, g))
    return float(sum(scores) / len(scores))


def coverage(result_alpha: torch.Tensor, reference_alpha: torch.Tensor, threshold: float = 0.5) -> float:
    """Share of the reference's foreground pixels (alpha > threshold) where the result's alpha > threshold.

    result_alpha, reference_alpha: [V, H, W] (same views). 1.0 when the reference has no foreground."""
    if result_alpha.shape != reference_alpha.shape:
        raise ValueError(f"coverage: renders differ in shape {list(result_alpha.shape)} vs {list(reference_alpha.shape)}")
    fg = reference_alpha > threshold
    n = int(fg.sum())
    return 1.0 if n == 0 else float((result_alpha[fg] > threshold).double().mean())

"""Stage 6, scale readjustment.

Optimization moves style Gaussians apart or together; their sizes should follow, or the result shows
holes (spread out) or blobs (bunched up). Each Gaussian's scales are multiplied by

    r_j = clamp( mean_{k NN} |x_j' - x_n'| / mean_{k NN} |x_j - x_n| , 1 / bound, bound )

where x are the positions before optimization (mapped back into the content frame, same cluster)
and x' after; neighbours are taken within the Gaussian's own cluster (where the optimization acted).
The bound (default 2) keeps a stray Gaussian from exploding or vanishing.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch

from .gaussians import GaussianScene
from .geometry import knn_mean_dist
from .options import checked, option


@dataclass
@checked("rescale")
class RescaleConfig:
    enabled: bool = option(True, "false: keep the style Gaussians' mapped scales")
    k: int = option(8, "neighbours (same cluster) whose mean distance sets the scale factor", minimum=1)
    bound: float = option(2.0, "the factor is clamped to [1/bound, bound]", minimum=1)


def readjust_scales(after: GaussianScene, before_means: torch.Tensor, labels: torch.Tensor, k: int = 8,
                    bound: float = 2.0) -> tuple[GaussianScene, torch.Tensor]:
    """after: the stylized scene [N]; before_means: [N, 3] positions before optimization; labels: [N]
    cluster of each Gaussian. Returns the rescaled scene and the ratios r [N]."""
    if bound < 1:
        raise ValueError(f"rescale.bound must be >= 1, got {bound}")
    ratio = torch.ones(len(after), dtype=torch.float64)
    for i in torch.unique(labels).tolist():
        m = (labels == i).nonzero().squeeze(1)
        if len(m) < 2:
            continue
        kk = min(k, len(m) - 1)
        d0 = knn_mean_dist(before_means[m].double(), kk)
        d1 = knn_mean_dist(after.means[m].detach().double(), kk)
        r = torch.where(d0 > 0, d1 / d0.clamp_min(1e-30), torch.ones_like(d0))
        ratio[m] = r.clamp(1.0 / bound, bound)
    out = replace(after, log_scales=after.log_scales + ratio.log().to(after.log_scales)[:, None])
    return out, ratio


def rescale(after: GaussianScene, before_means: torch.Tensor, labels: torch.Tensor,
            cfg: RescaleConfig) -> tuple[GaussianScene, torch.Tensor | None]:
    """Stage 6 as ``cfg`` asks: :func:`readjust_scales`, or the scene unchanged (ratios None) when disabled."""
    if not cfg.enabled:
        return after, None
    return readjust_scales(after, before_means, labels, cfg.k, cfg.bound)

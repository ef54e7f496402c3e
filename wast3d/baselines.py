"""Stage 9, baselines in the same framework.

ARF, StyleRF and SNeRF need an image style, VGG weights and NeRF code that cannot run here; what the
paper says they achieve, a change of colour on unchanged geometry, is reproduced by:

``colour_transfer``: the content's Gaussians keep their geometry (means, scales, rotations, opacity);
their view-independent colours c_i are moved by the entropic optimal-transport map to the style's
colour distribution {d_j} (RGB, cost |c-d|^2/2, uniform weights, eps = blur^2):

    T(c_i) = sum_j pi_ij d_j / a_i = c_i - grad_{c_i} OT_eps(alpha, beta) / a_i

(the barycentric projection of the optimal plan; eq. 4 of the paper without debiasing, so that the
gradient is exactly the displacement). Only the DC term changes (``f_dc += (T(c) - c) / SH_C0``), so
view-dependent effects of the content are kept.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch

from .gaussians import GaussianScene, rgb_to_sh_dc
from .options import checked, option


@dataclass
@checked("colour_transfer")
class ColourTransferConfig:
    blur: float = option(0.02, "blur in RGB units", exclusiveMinimum=0)
    scaling: float = option(0.5, "eps-scaling ratio", exclusiveMinimum=0, exclusiveMaximum=1)
    extra_iters: int = option(10, "extra iterations at the final eps", minimum=0)
    max_style_points: int = option(4096, "random style colours the content is transported to", minimum=1)
    seed: int = option(0, "seed of that subsample")


def colour_map(src: torch.Tensor, dst: torch.Tensor, cfg: ColourTransferConfig, dtype=torch.float32) -> torch.Tensor:
    """Entropic OT barycentric map of colours src [N, 3] onto the distribution dst [M, 3] -> [N, 3]. Solved
    in float32 by default: within 2e-6 of float64 on the demo (1/2000 of an 8-bit step), 7-9x faster
    (``benchmarks/float32_solves.py``)."""
    from .sinkhorn import SinkhornConfig, sinkhorn

    scfg = SinkhornConfig(blur=cfg.blur, scaling=cfg.scaling, debias=False, extra_iters=cfg.extra_iters)
    x = src.to(dtype)
    r = sinkhorn(x, dst.to(dtype), scfg, grad_x=True, grad_y=False)
    return (x - r.grad_x * len(x)).to(src.dtype)


def colour_transfer(content: GaussianScene, style: GaussianScene, cfg: ColourTransferConfig) -> GaussianScene:
    """The content scene with its colours mapped to the style's colour distribution."""
    if len(content) == 0 or len(style) == 0:
        raise ValueError(f"colour transfer: empty scene (content {len(content)}, style {len(style)} Gaussians)")
    dst = style.rgb
    if len(dst) > cfg.max_style_points:
        g = torch.Generator().manual_seed(cfg.seed)
        dst = dst[torch.randperm(len(dst), generator=g)[:cfg.max_style_points]]
    src = content.rgb
    mapped = colour_map(src, dst, cfg)
    out = content.detach()
    return replace(out, sh_dc=out.sh_dc + (rgb_to_sh_dc(mapped) - rgb_to_sh_dc(src)).to(out.sh_dc))

"""Stage 4b, selection of the style Gaussians for each cluster (paper eq. 8).

    D_i = union over g in C_i of kNN_k( S_i R_i (g_x - t_i) )        (eq. 8)

The k nearest style Gaussians of every registered content point, deduplicated per cluster. One
KD-tree query serves all clusters. Stored as CSR: ``offsets`` [K+1] and ``indices`` (into the style
scene), cluster i owning ``indices[offsets[i]:offsets[i+1]]``, sorted.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from .geometry import knn


@dataclass
class SelectConfig:
    k: int = 3


@torch.no_grad()
def select(mapped: torch.Tensor, labels: torch.Tensor, style: torch.Tensor, k: int) -> tuple[torch.Tensor, torch.Tensor]:
    """mapped: [N,3] content points in the style frame (eq. 7), labels: [N], style: [M,3] ->
    (offsets [K+1], indices [sum |D_i|])."""
    if k < 1:
        raise ValueError(f"selection: k must be >= 1, got {k}")
    K = int(labels.max()) + 1
    _, idx = knn(mapped, style, k)
    key = labels.long()[:, None] * len(style) + idx
    key = torch.unique(key.reshape(-1))  # sorted: by cluster, then style index
    cl = key // len(style)
    indices = key % len(style)
    offsets = torch.zeros(K + 1, dtype=torch.int64)
    offsets[1:] = torch.cumsum(torch.bincount(cl, minlength=K), 0)
    return offsets, indices

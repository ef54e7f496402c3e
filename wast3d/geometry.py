"""Nearest-neighbour helpers shared by initialization, surface sampling, registration, selection
and scale readjustment.

On CPU a KD-tree (``scipy.spatial.cKDTree``, multi-threaded queries) is used; on CUDA a chunked
``torch.cdist`` that never materializes more than ``chunk x M`` distances.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree


def knn(query: torch.Tensor, ref: torch.Tensor, k: int, exclude_self: bool = False,
        chunk: int = 4096) -> tuple[torch.Tensor, torch.Tensor]:
    """k nearest neighbours of each query point among ``ref``.

    query: [Q, 3], ref: [M, 3] -> (distances [Q, k], indices [Q, k] into ref), sorted by distance.
    ``exclude_self`` drops the first neighbour (use when query is ref). k is capped at the number of
    available neighbours.
    """
    if ref.shape[0] == 0:
        raise ValueError("knn: reference set is empty")
    extra = 1 if exclude_self else 0
    kk = min(k + extra, ref.shape[0])
    if query.is_cuda:
        ds, ids = [], []
        for q in query.split(chunk):
            d = torch.cdist(q, ref)
            dv, iv = d.topk(kk, dim=1, largest=False)
            ds.append(dv)
            ids.append(iv)
        d, i = torch.cat(ds), torch.cat(ids)
    else:
        tree = cKDTree(ref.detach().double().cpu().numpy())
        dn, inn = tree.query(query.detach().double().cpu().numpy(), k=kk, workers=-1)
        dn = np.asarray(dn).reshape(len(query), kk)
        inn = np.asarray(inn).reshape(len(query), kk)
        d = torch.from_numpy(dn).to(query.dtype)
        i = torch.from_numpy(inn.astype(np.int64))
    return d[:, extra:], i[:, extra:]


def knn_mean_sq_dist(points: torch.Tensor, k: int = 3) -> torch.Tensor:
    """Mean squared distance of each point to its k nearest other points; points: [N, 3] -> [N].

    A lone point gets 0 (the caller clamps).
    """
    if points.shape[0] < 2:
        return torch.zeros(points.shape[0], dtype=points.dtype)
    d, _ = knn(points, points, k, exclude_self=True)
    return (d**2).mean(dim=1)


def knn_mean_dist(points: torch.Tensor, k: int) -> torch.Tensor:
    """Mean distance of each point to its k nearest other points; points: [N, 3] -> [N]."""
    if points.shape[0] < 2:
        return torch.zeros(points.shape[0], dtype=points.dtype)
    d, _ = knn(points, points, k, exclude_self=True)
    return d.mean(dim=1)

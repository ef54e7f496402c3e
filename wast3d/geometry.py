"""Geometry helpers shared by the stages: nearest neighbours (initialization, surface sampling,
registration, selection, scale readjustment), Kabsch rotations and frames from normals.

On CPU a KD-tree (``scipy.spatial.cKDTree``, queries on ``torch.get_num_threads()`` threads, so that a
job keeps to the threads it was given) is used; on CUDA a chunked
``torch.cdist`` that never materializes more than ``chunk x M`` distances.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree


def _flushing_denormals() -> bool:
    """Whether this thread flushes denormals to zero (``torch.set_flush_denormal``; the CLI sets it)."""
    return float(torch.tensor([1e-310], dtype=torch.float64) * 1.0) == 0.0


def kdtree(points: np.ndarray) -> cKDTree:
    """``scipy.spatial.cKDTree(points)``, built with denormals honoured. Under flush-to-zero, which the CLI
    sets for the CPU kernels' speed, scipy's (1.17) balanced build crashes the process on many tied
    coordinates (1e5 points on a 20-step grid; a 0.0125 grid of ground and dome); queries are unaffected."""
    if not _flushing_denormals():
        return cKDTree(points)
    torch.set_flush_denormal(False)
    try:
        return cKDTree(points)
    finally:
        torch.set_flush_denormal(True)


class KnnIndex:
    """A reference set [M, 3] indexed once for many :meth:`query` calls (a KD-tree on CPU; on CUDA the
    points themselves, for chunked ``torch.cdist``). Building the tree of a 1e6-Gaussian style takes
    about a second: registration's ICP queries the same style 120 times."""

    def __init__(self, ref: torch.Tensor):
        if ref.shape[0] == 0:
            raise ValueError("knn: reference set is empty")
        self.ref = ref
        self.tree = None if ref.is_cuda else kdtree(ref.detach().double().cpu().numpy())

    def query(self, query: torch.Tensor, k: int, exclude_self: bool = False,
              chunk: int = 4096) -> tuple[torch.Tensor, torch.Tensor]:
        """query: [Q, 3] -> (distances [Q, k], indices [Q, k] into ref), as :func:`knn`."""
        extra = 1 if exclude_self else 0
        kk = min(k + extra, self.ref.shape[0])
        if self.tree is None:
            ds, ids = [], []
            for q in query.split(chunk):
                dv, iv = torch.cdist(q, self.ref).topk(kk, dim=1, largest=False)
                ds.append(dv)
                ids.append(iv)
            d, i = torch.cat(ds), torch.cat(ids)
        else:
            dn, inn = self.tree.query(query.detach().double().cpu().numpy(), k=kk, workers=torch.get_num_threads())
            d = torch.from_numpy(np.asarray(dn).reshape(len(query), kk)).to(query.dtype)
            i = torch.from_numpy(np.asarray(inn).reshape(len(query), kk).astype(np.int64))
        return d[:, extra:], i[:, extra:]


def knn(query: torch.Tensor, ref: torch.Tensor, k: int, exclude_self: bool = False,
        chunk: int = 4096) -> tuple[torch.Tensor, torch.Tensor]:
    """k nearest neighbours of each query point among ``ref``.

    query: [Q, 3], ref: [M, 3] -> (distances [Q, k], indices [Q, k] into ref), sorted by distance.
    ``exclude_self`` drops the first neighbour (use when query is ref). k is capped at the number of
    available neighbours. Many queries of one ``ref``: :class:`KnnIndex`.
    """
    return KnnIndex(ref).query(query, k, exclude_self, chunk)


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


def gaussian_smooth(points: torch.Tensor, support: torch.Tensor, sigma: float, chunk: int = 2048) -> torch.Tensor:
    """Each point replaced by the Gaussian-weighted mean of the support points around it:

        p~_i = sum_j w_ij y_j / sum_j w_ij,   w_ij = exp(-|p_i - y_j|^2 / (2 sigma^2)),  |p_i - y_j| <= 2 sigma

    points: [N, 3], support: [M, 3] -> [N, 3] (float64). A point with no support within 2 sigma is kept.
    Relief narrower than about sigma is averaged away; a part thinner than sigma collapses to its axis
    (on both sides of a comparison alike). KD-tree pairs in chunks of ``chunk`` points (bounded memory)."""
    if sigma <= 0:
        raise ValueError(f"gaussian_smooth: sigma must be > 0, got {sigma}")
    if len(support) == 0:
        raise ValueError("gaussian_smooth: the support set is empty")
    p = points.detach().double().cpu().numpy()
    y = support.detach().double().cpu().numpy()
    tree = kdtree(y)
    out = p.copy()
    for s in range(0, len(p), chunk):
        q = kdtree(p[s:s + chunk])
        pairs = q.sparse_distance_matrix(tree, 2 * sigma, output_type="ndarray")
        w = np.exp(-pairs["v"] ** 2 / (2 * sigma**2))
        i = pairs["i"]
        den = np.bincount(i, w, minlength=len(q.data))
        num = np.stack([np.bincount(i, w * y[pairs["j"], a], minlength=len(q.data)) for a in range(3)], 1)
        has = den > 0
        out[s:s + chunk][has] = num[has] / den[has, None]
    return torch.from_numpy(out)


def local_normals(points: torch.Tensor, at: torch.Tensor, k: int) -> torch.Tensor:
    """Least-variance direction (unit, sign arbitrary) of the ``k`` nearest ``points`` [M, 3] of each
    query in ``at`` [B, 3]: the local surface normal by PCA. -> [B, 3]."""
    _, idx = knn(at, points, k)
    nb = points[idx]  # [B, k, 3]
    c = nb - nb.mean(1, keepdim=True)
    _, vecs = torch.linalg.eigh(c.transpose(1, 2) @ c)
    return vecs[:, :, 0]


def kabsch(H: torch.Tensor) -> torch.Tensor:
    """H: [B,3,3] = sum g u^T -> the proper rotation R maximizing tr(R H), i.e. minimizing |R g - u|^2.

    The determinant is fixed to +1; a rank-deficient H (1-2 points, collinear) still gives a rotation.
    """
    U, _, Vh = torch.linalg.svd(H)
    V = Vh.transpose(-1, -2)
    d = torch.sign(torch.linalg.det(V @ U.transpose(-1, -2)))
    d = torch.where(d == 0, torch.ones_like(d), d)
    D = torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), d], -1))
    return V @ D @ U.transpose(-1, -2)


def frame_from_normal(n: torch.Tensor) -> torch.Tensor:
    """n: [N,3] unit normals -> [N,3,3] rotations whose third column is n."""
    helper = torch.where(n[:, 2:3].abs() < 0.9, n.new_tensor([0.0, 0.0, 1.0]), n.new_tensor([1.0, 0.0, 0.0]))
    t1 = torch.linalg.cross(helper.expand_as(n), n)
    t1 = t1 / t1.norm(dim=1, keepdim=True).clamp_min(1e-12)
    t2 = torch.linalg.cross(n, t1)
    return torch.stack([t1, t2, n], dim=2)


def robust_bounds(points: torch.Tensor, q: float = 0.005) -> tuple[torch.Tensor, float]:
    """Robust centre [3] and radius of points [N, 3]: the box of the per-axis quantiles ``q``..``1-q``
    (stray floaters ignored), its centre and half its diagonal (at least 1e-3)."""
    m = points.detach().float()
    if len(m) == 0:
        return torch.zeros(3), 1.0
    lo = torch.quantile(m, q, dim=0) if len(m) > 1 else m[0]
    hi = torch.quantile(m, 1 - q, dim=0) if len(m) > 1 else m[0]
    return 0.5 * (lo + hi), max(float(0.5 * (hi - lo).norm()), 1e-3)


def group_diameters(labels: np.ndarray, points: np.ndarray) -> np.ndarray:
    """[K] each group's diameter (labels [N] in 0..K-1, points [N, 3]): twice the 90th percentile of its
    points' distances to its centroid, so that a stray point does not set it (0 for an empty group)."""
    K = int(labels.max()) + 1
    cent = np.zeros((K, 3))
    np.add.at(cent, labels, points)
    cent /= np.maximum(np.bincount(labels, minlength=K), 1)[:, None]
    d = np.linalg.norm(points - cent[labels], axis=1)
    order = np.argsort(labels, kind="stable")
    bounds = np.searchsorted(labels[order], np.arange(K + 1))
    return np.array([2 * np.quantile(d[order[a:b]], 0.9) if b > a else 0.0 for a, b in zip(bounds[:-1], bounds[1:])])


def local_thickness(points: np.ndarray, at: np.ndarray, k: int = 16, reach: float = 0.4) -> np.ndarray:
    """The thickness of a surface sample at query points: points [M, 3] (dense, about uniform), at [Q, 3]
    -> [Q]. Along each query's local PCA normal (:func:`local_normals`, ``k`` neighbours), either way,
    the distance to the nearest sample within 3 h of that line and farther than 3 h (h: the samples'
    median nearest-neighbour distance): through a leg, its diameter. inf where no sample lies on the
    line within ``reach`` of the sample's diameter (an open sheet). Measured, not used by a stage: where
    the content is thinner than a style element, a whole element widens it (benchmarks/element_copies.py --thickness)."""
    tree = kdtree(points)
    h = float(np.median(tree.query(points, 2)[0][:, 1]))
    normals = local_normals(torch.from_numpy(points), torch.from_numpy(at), k).numpy()
    diameter = float(np.linalg.norm(np.percentile(points, 99, 0) - np.percentile(points, 1, 0)))
    out = np.full(len(at), np.inf)
    for i, near in enumerate(tree.query_ball_point(at, reach * diameter)):
        v = points[near] - at[i]
        t = v @ normals[i]
        hit = (np.abs(t) > 3 * h) & (np.linalg.norm(v - t[:, None] * normals[i], axis=1) < 3 * h)
        if hit.any():
            out[i] = np.abs(t[hit]).min()
    return out


def mean_spacing(points: torch.Tensor, max_points: int = 200_000, seed: int = 0) -> float:
    """Mean distance to the nearest other point (on a random subsample of ``max_points``)."""
    if len(points) < 2:
        return 1.0
    if len(points) > max_points:
        g = torch.Generator().manual_seed(seed)
        points = points[torch.randperm(len(points), generator=g)[:max_points]]
    d, _ = knn(points, points, 1, exclude_self=True)
    return max(float(d.mean()), 1e-12)


def cap_per_label(labels: torch.Tensor, cap: int, g: torch.Generator) -> torch.Tensor:
    """labels [N] (ids 0..K-1) -> the indices of at most ``cap`` points per label, drawn uniformly by the
    generator ``g`` (every point where a label has at most ``cap``), in the order of their label then of
    the draw. ``cap`` 0: every point, in label order."""
    labels = labels.long()
    if len(labels) == 0:
        return labels
    order = torch.argsort(labels * 1.0 + torch.rand(len(labels), generator=g, dtype=torch.float64))
    if cap <= 0:
        return order
    lab_sorted = labels[order]
    first = torch.searchsorted(lab_sorted, torch.arange(int(labels.max()) + 1))
    rank = torch.arange(len(labels)) - first[lab_sorted]
    return order[rank < cap]


def kmeans_from_groups(feats: np.ndarray, group: np.ndarray, max_iter: int) -> np.ndarray:
    """K-means of ``feats`` [M, D] started from the centroids of ``group`` [M] (ids 0..P-1, each used):
    one cluster per group, its borders then moved by the features -> [M] cluster ids 0..K-1 (K <= P).
    A single group, or as many groups as points, is returned as it is."""
    from sklearn.cluster import KMeans

    P = int(group.max()) + 1
    if P == 1 or P >= len(feats):
        return group.astype(np.int64)
    init = np.zeros((P, feats.shape[1]))
    np.add.at(init, group, feats)
    init /= np.bincount(group, minlength=P)[:, None]
    km = KMeans(P, init=init, n_init=1, max_iter=max_iter).fit(feats)
    return np.unique(km.labels_, return_inverse=True)[1].reshape(-1).astype(np.int64)

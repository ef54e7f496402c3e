"""Stage 4b, selection of the style Gaussians for each cluster (paper eq. 8).

    D_i = union over g in C_i of kNN_k( S_i R_i (g_x - t_i) )        (eq. 8)

The k nearest style Gaussians of every registered content point, deduplicated per cluster. One
KD-tree query serves all clusters. Stored as CSR: ``offsets`` [K+1] and ``indices`` (into the style
scene), cluster i owning ``indices[offsets[i]:offsets[i+1]]``, sorted.

``mode: footprint`` (our variant, not the paper's): the style Gaussians *under and over* the mapped
cluster instead of the ones nearest to it,

    D_i = { h in style :  min_{g in C_i} | P_i (h - S_i R_i (g_x - t_i)) | / rho_g <= radius,
                          | n_i . (h - c_i) | <= r_i },
    rho_g = min(max(spacing, d_g), 4 spacing)

with n_i the least-variance axis of the mapped cluster (its normal), P_i the projection onto the plane
orthogonal to n_i, c_i its centroid, r_i its radius, and d_g the in-plane distance from the mapped
point g to its nearest neighbour in the cluster: each content point's footprint is the area it stands
for, at least the style's spacing. A trained scene covers flat regions with few large Gaussians (the
lego's base plate) and details with many small ones, so its surface samples are far sparser in some
places than the mean spacing that sets the registration's scale says; with a fixed radius those
places came out as holes (lego x pebbles: coverage 0.92). The cap keeps an isolated point (lego: up
to 15 style spacings from its neighbour) from claiming a large patch of the style. A kNN ball of small k around points that lie
on the style's mean surface takes a slab of it and leaves the tops of the elements (pebble domes,
blade tips) out; the footprint keeps every element the cluster covers whole. It assumes the style is
a height field over the plane of each cluster at the cluster's scale (a ground with objects on it).

``extent`` (a content Gaussian's own area): the rule above reads a point's area from its spacing, but a
trained content's Gaussians clump (the lego at paper scale: a centre's nearest neighbour 1.1 style
spacings away in the cluster's plane, its 4th 3.9) while one large Gaussian stands for a flat area. The
discs then covered a median 40 % of a cluster's convex hull in its plane at paper scale (61 % on the
lego x trained pebbles, 87 % on the procedural ant) and the style was copied through a stencil:
pebble slices and crescents. So each content Gaussian also claims the disc of ``extent`` standard
deviations of its covariance projected on the plane, ``extent * det(E Sigma_g E^T)^(1/4)`` (E: the plane's axes; an
edge-on Gaussian claims little), clipped to the cluster's convex hull in its plane (a k-means cluster
is convex in space; past its hull a large Gaussian's disc overlaps the neighbouring clusters' copies).
A procedural content's Gaussians are as large as their spacing, so there it changes little.

``max_per_point`` (:func:`thin`): a cluster's selection is capped at ``max_per_point * |C_i|``. Eq. 8
selects at most ``k |C_i|`` Gaussians, so its size follows the content; the footprint's follows the
style's density instead: a 1e6-Gaussian style on the lego (400 clusters of 71 points) selected 85 per
content point (2.5e6 in all), and the Sinkhorn self-term grows as the square of it. Past the cap the
cluster keeps a uniform random subset (every element keeps its share of Gaussians, so it stays whole)
and the kept Gaussians are enlarged by the growth of their spacing, as stage 6 does after the flow.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from .geometry import frame_from_normal, kdtree, knn
from .options import checked, option


MODES = ("knn", "footprint")
MAX_FOOTPRINT = 4.0  # a content point's footprint is at most this many style spacings (isolated points)
THIN_K = 8  # neighbours of the spacing that sets a thinned cluster's scale gain (as stage 6's k)


@dataclass
@checked("select")
class SelectConfig:
    k: int = option(3, "knn: nearest style Gaussians per registered content point (eq. 8)", minimum=1)
    mode: str = option("footprint", "knn (eq. 8) or footprint (every style Gaussian over and under the mapped cluster)",
                                    enum=MODES)
    radius: float = option(1.5, "footprint: in-plane distance to a mapped content point, in style spacings",
                                exclusiveMinimum=0)
    extent: float = option(2.0, "footprint: a content Gaussian also claims the disc of this many standard deviations "
                                "of its extent in the cluster's plane (trained content: one large Gaussian stands "
                                "for a flat area, many small ones for a detail); 0: the spacing rule alone",
                                minimum=0)
    max_per_point: float = option(16.0, "cap on a cluster's selection, in style Gaussians per content point of the "
                                        "cluster: past it a uniform subset is kept and enlarged by the growth of its "
                                        "spacing (a style far denser than the content, e.g. 1e6 Gaussians on the lego's"
                                        " 71 points a cluster, selects 85 per point; the demo's pairs select at most "
                                        "22); 0: no cap", minimum=0)



@dataclass(frozen=True)
class Selection:
    """The style Gaussians of each of K clusters, as CSR: cluster i owns ``indices[offsets[i]:offsets[i+1]]``
    (sorted indices into the style scene). ``log_gain`` [K]: added to those Gaussians' log-scales (0 where
    the cluster was not thinned)."""

    offsets: torch.Tensor  # [K+1] int64
    indices: torch.Tensor  # [S] int64
    log_gain: torch.Tensor  # [K] float64

    @property
    def sizes(self) -> torch.Tensor:
        return self.offsets[1:] - self.offsets[:-1]


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
    return _csr(key // len(style), key % len(style), K)


def _csr(cluster: torch.Tensor, indices: torch.Tensor, K: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(cluster id, style index) pairs, sorted by cluster then index -> (offsets [K+1], indices)."""
    offsets = torch.zeros(K + 1, dtype=torch.int64)
    offsets[1:] = torch.cumsum(torch.bincount(cluster, minlength=K), 0)
    return offsets, indices


@torch.no_grad()
def select_footprint(mapped: torch.Tensor, labels: torch.Tensor, style: torch.Tensor, radius: float,
                     spacing: float, covariances: torch.Tensor | None = None,
                     extent: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """The footprint selection of the module docstring. mapped: [N,3], labels: [N], style: [M,3],
    radius in units of ``spacing`` (the style's mean spacing) -> (offsets [K+1], indices), as :func:`select`.
    ``covariances`` [N,3,3]: the content Gaussians' covariances mapped into the style frame; with
    ``extent`` > 0 each point also claims the disc of ``extent`` in-plane standard deviations, clipped to
    the cluster's convex hull in its plane.
    """
    K = int(labels.max()) + 1
    sty = style.double().numpy()
    tree3 = kdtree(sty)
    lab = labels.long().numpy()
    mp = mapped.double().numpy()
    clusters, chosen = [], []
    for i in range(K):
        y = mp[lab == i]
        if len(y) == 0:
            continue
        c = y.mean(0)
        r = float(np.linalg.norm(y - c, axis=1).max()) if len(y) > 1 else spacing
        n = np.linalg.eigh(np.cov((y - c).T) if len(y) > 2 else np.eye(3))[1][:, 0]
        flat_y = (y - c) - np.outer((y - c) @ n, n)
        rho = np.full(len(y), spacing)
        if len(y) > 1:
            rho = np.clip(kdtree(flat_y).query(flat_y, k=2)[0][:, 1], spacing, MAX_FOOTPRINT * spacing)
        rho = radius * rho
        ext, big = rho, np.zeros(len(y), dtype=bool)
        if covariances is not None and extent > 0 and len(y) > 2:
            E = frame_from_normal(torch.from_numpy(n[None])).numpy()[0][:, :2].T  # [2, 3] the plane's axes
            ext = np.maximum(rho, extent * _plane_sigma(covariances[lab == i].double().numpy(), E))
            big = ext > rho
        cand = np.asarray(tree3.query_ball_point(c, np.sqrt(2) * r + float(ext.max())), dtype=np.int64)
        if len(cand) == 0:
            continue
        d = sty[cand] - c
        near = np.abs(d @ n) <= r
        cand, d = cand[near], d[near]
        flat_s = d - np.outer(d @ n, n)
        # the style Gaussians in each mapped point's own footprint (one query, a radius per point)
        tree2 = kdtree(flat_s)
        inside = np.fromiter((j for h in tree2.query_ball_point(flat_y, rho) for j in h), dtype=np.int64)
        if big.any():  # the discs past the spacing rule's, clipped to the hull
            hits = tree2.query_ball_point(flat_y[big], ext[big])
            claimed = np.unique(np.fromiter((j for h in hits for j in h), dtype=np.int64))
            inside = np.concatenate([inside, claimed[_in_hull(flat_y @ E.T, flat_s[claimed] @ E.T)]])
        keep = np.sort(cand[np.unique(inside)])
        clusters.append(np.full(len(keep), i, dtype=np.int64))
        chosen.append(keep)
    cl = torch.from_numpy(np.concatenate(clusters)) if clusters else torch.zeros(0, dtype=torch.int64)
    ix = torch.from_numpy(np.concatenate(chosen)) if chosen else torch.zeros(0, dtype=torch.int64)
    return _csr(cl, ix, K)


def _plane_sigma(cov: np.ndarray, E: np.ndarray) -> np.ndarray:
    """In-plane standard deviation of Gaussians ``cov`` [N,3,3] in the plane of the axes ``E`` [2, 3]: the
    geometric mean of the two axes of the projected covariance, ``det(E cov E^T)^(1/4)`` -> [N]."""
    c2 = np.einsum("ij,njk,lk->nil", E, cov, E)
    return np.clip(np.linalg.det(c2), 0.0, None) ** 0.25


def _in_hull(hull: np.ndarray, points: np.ndarray) -> np.ndarray:
    """[S] bool: which of ``points`` [S, 2] lie inside the convex hull of ``hull`` [N, 2]; none where the
    hull is degenerate (points on a line)."""
    from scipy.spatial import Delaunay, QhullError

    try:
        tri = Delaunay(hull)
    except QhullError:
        return np.zeros(len(points), dtype=bool)
    return tri.find_simplex(points) >= 0


@torch.no_grad()
def thin(offsets: torch.Tensor, indices: torch.Tensor, counts: torch.Tensor, style: torch.Tensor,
         max_per_point: float, seed: int = 0) -> Selection:
    """Cap cluster i's selection at ``n_i = ceil(max_per_point * counts[i])`` Gaussians (``counts``: [K]
    content points per cluster; style: [M, 3] positions).

    A cluster over the cap keeps ``n_i`` of its Gaussians drawn uniformly without replacement (seeded),
    and its scale gain is the median over the kept Gaussians of

        g_j = dbar_kept(j) / dbar_all(j)   (>= 1),

    dbar the mean distance to the ``THIN_K`` nearest others of the same cluster: thinning a surface by a
    fraction f spreads it by about f^(-1/2), a volume by f^(-1/3); the ratio measures which. One gain per
    cluster, as the thinning is uniform. ``max_per_point`` 0: nothing is thinned."""
    from .geometry import KnnIndex, knn_mean_dist

    K = len(offsets) - 1
    gain = torch.zeros(K, dtype=torch.float64)
    sizes = offsets[1:] - offsets[:-1]
    cap = torch.ceil(max_per_point * counts.double()).long().clamp_min(1)
    if max_per_point <= 0 or not bool((sizes > cap).any()):
        return Selection(offsets, indices, gain)
    rng = np.random.default_rng(seed)
    kept = []
    for i in range(K):
        sel = indices[offsets[i]:offsets[i + 1]]
        n = int(cap[i])
        if len(sel) <= n:
            kept.append(sel)
            continue
        pick = torch.from_numpy(np.sort(rng.choice(len(sel), n, replace=False)))
        if n > THIN_K:
            pts = style[sel].double()
            d_all = KnnIndex(pts).query(pts[pick], THIN_K, exclude_self=True)[0].mean(1)  # the kept ones only
            d_kept = knn_mean_dist(pts[pick], THIN_K)
            ok = d_all > 0
            if bool(ok.any()):
                gain[i] = float(torch.log((d_kept[ok] / d_all[ok]).median()).clamp_min(0.0))
        kept.append(sel[pick])
    cluster = torch.repeat_interleave(torch.arange(K), torch.tensor([len(k) for k in kept], dtype=torch.int64))
    off, idx = _csr(cluster, torch.cat(kept) if kept else indices[:0], K)
    return Selection(off, idx, gain)


def select_with(cfg: SelectConfig, mapped: torch.Tensor, labels: torch.Tensor, style: torch.Tensor,
                spacing: float, covariances: torch.Tensor | None = None) -> Selection:
    """The selection ``cfg`` names: :func:`select` (``knn``, k) or :func:`select_footprint` (radius in
    units of ``spacing``, the style's mean spacing), then capped by :func:`thin`."""
    if cfg.mode == "footprint":
        offsets, indices = select_footprint(mapped, labels, style, cfg.radius, spacing, covariances, cfg.extent)
    else:
        offsets, indices = select(mapped, labels, style, cfg.k)
    counts = torch.bincount(labels.long(), minlength=len(offsets) - 1)
    return thin(offsets, indices, counts, style, cfg.max_per_point)


def select_style(cfg: SelectConfig, content, labels: torch.Tensor, style, reg) -> Selection:
    """Stage 4b on scenes: the content's points mapped by the registration ``reg`` (eq. 7) and their
    covariances, then :func:`select_with` over the style's means."""
    cm = content.means.double()
    return select_with(cfg, reg.apply(cm, labels), labels, style.means.double(), reg.style_spacing,
                       reg.apply_covariances(content.covariances.double(), labels))

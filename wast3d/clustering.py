"""Stage 3, k-means of the content into clusters on position and colour.

Features: ``[xyz / radius, colour_weight * rgb]`` (positions divided by the scene radius so that the
colour weight means the same at every scene scale). Number of clusters: ``n_clusters`` when given
(paper: 400), else ``round(points / target_cluster_size)`` clamped to [1, max_clusters]: a small scene
gets few clusters of a useful size instead of 400 tiny ones. ``span`` > 0 corrects that count by
``(d / (span D))^(1/p)`` with d the median diameter of the clusters it gave, D the content's diameter and
p the exponent of d ~ k^-p (1/2 on a patch, then measured from the last two fits), refitting until d
is within ``SPAN_TOLERANCE`` of ``span D`` (at most ``SPAN_FITS`` fits; the closest kept), so
that clusters are about as wide in the content's units (and so in the style's element lengths, which
registration maps onto a fixed share of D) whatever the capture's density. scikit-learn's ``KMeans``
(deterministic by seed) up to ``minibatch_above`` x clusters feature rows, ``MiniBatchKMeans`` beyond.
**Wrapped clusters split** (``flatness`` > 0, needs each point's outward normal,
:func:`wast3d.surface.outward_normals`): on positions alone 15 of the ant's 25 clusters wrap all the way
around a leg or a body segment (their mean unit normal under 0.1 long) and 31 % of its points face
more than 90 degrees away from their cluster's mean normal, so the flat style patch registered onto
such a cluster is seen from under its ground on the far side (registration assumes the style is a
height field over each cluster's plane). A cluster whose mean normal is shorter than ``flatness`` is
split in two by 2-means on its normals (halves of a tube, each connected), again until every cluster
is flat enough or would fall below ``min_split`` points. Normals as a k-means feature instead joined
the same sides of different legs into one cluster, and the flow then filled the gaps between them.
Empty clusters are impossible with Lloyd's algorithm in scikit-learn; clusters below ``min_size``
points are merged into the nearest remaining centroid and the merge is logged.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import torch

from .options import checked, option

log = logging.getLogger(__name__)


@dataclass
@checked("cluster")
class ClusterConfig:
    n_clusters: int = option(0, "number of clusters (0: points / target_cluster_size)", minimum=0,
                              maximum=1_000_000)
    target_cluster_size: int = option(800, "points per cluster when n_clusters is 0 (then corrected by span)",
                                     minimum=1)
    max_clusters: int = option(400, "cap on the derived number of clusters (the paper: 400)", minimum=1,
                                maximum=1_000_000)
    colour_weight: float = option(0.2, "weight of RGB against positions normalized to the unit ball", minimum=0)
    flatness: float = option(0.5, "split clusters whose mean outward unit normal is shorter than this, in two by their "
                                  "normals, until flat (0: off, the paper)", minimum=0, maximum=1)
    coherence: int = option(3, "passes of a majority vote among each point's 16 nearest neighbours after k-means and "
                               "the splits, where the clusters interleave (coherence_below): they become contiguous "
                               "patches (k-means on position and colour interleaves them on a textured capture, and a "
                               "split by noisy normals into halves that interleave); 0: off", minimum=0)
    coherence_below: float = option(0.75, "the vote runs only when fewer than this share of the points' 8 nearest "
                                         "neighbours are in their own cluster (own_share; the guitar's capture 0.56-"
                                         "0.62, the ant, the lego and the floaters at span 0.13: 0.81-0.91)",
                                    minimum=0, maximum=1)
    span: float = option(0.092, "clusters about this wide, as a fraction of the content's diameter (robust_bounds, "
                              "as register.element_scale's): the count from target_cluster_size is corrected by "
                              "the median k-means cluster's diameter over this (to the power 2, then the one the "
                              "fits measure), refitted until within 5 %, before the splits (800 points span 0.084 "
                              "of the guitar's dense capture, 0.128 of the ant, 0.36 of the floaters'); 0: the "
                              "count alone", minimum=0)
    min_split: int = option(100, "a split never makes a cluster smaller than this many points", minimum=1)
    min_size: int = option(4, "smaller clusters are merged into their nearest neighbour", minimum=1)
    seed: int = option(0, "k-means seed")
    minibatch_above: int = option(20_000_000, "mini-batch k-means above this many points", minimum=1)


@dataclass
class Clusters:
    """Stage 3's result: ``labels`` [N] (0..K-1), ``centroids`` [K, 3], each point's outward ``normals``
    [N, 3] (None when ``flatness`` is 0: no split needed them) and what was done (``info``)."""

    labels: torch.Tensor
    centroids: np.ndarray
    normals: torch.Tensor | None
    info: dict


def cluster_content(content, cfg: ClusterConfig) -> Clusters:
    """Stage 3 on a content scene (:class:`~wast3d.gaussians.GaussianScene`): :func:`kmeans` on its means
    and colours, with its outward normals (:func:`wast3d.surface.outward_normals`) where ``flatness`` splits
    wrapped clusters."""
    normals, decided = None, None
    if cfg.flatness > 0:
        from .surface import outward_normals

        normals, decided = outward_normals(content)
        normals = normals.float()
    labels, cent, info = kmeans(content.means, content.rgb, cfg, normals)
    if decided is not None:
        info["normals_decided_by_a_view"] = float(decided.double().mean())
    return Clusters(torch.from_numpy(labels).long(), cent, normals, info)


def n_clusters_for(n_points: int, cfg: ClusterConfig, count: float | None = None) -> int:
    """``n_clusters`` when given, else ``count`` (default: points / target_cluster_size) rounded and clamped
    to [1, min(max_clusters, n_points)]."""
    if cfg.n_clusters:
        return max(1, min(cfg.n_clusters, n_points))
    if count is None:
        count = n_points / max(cfg.target_cluster_size, 1)
    return int(max(1, min(cfg.max_clusters, round(count), n_points)))


def kmeans(means: torch.Tensor, rgb: torch.Tensor, cfg: ClusterConfig,
           normals: torch.Tensor | None = None) -> tuple[np.ndarray, np.ndarray, dict]:
    """means: [N, 3], rgb: [N, 3], normals: [N, 3] outward unit normals (needed when ``cfg.flatness``
    > 0) -> labels [N] (0..K-1, every label used), centroids [K, 3] (xyz), info."""
    from sklearn.cluster import KMeans, MiniBatchKMeans

    x = means.detach().double().cpu().numpy()
    n = len(x)
    if n == 0:
        raise ValueError("k-means: no points to cluster")
    centre = np.median(x, axis=0)
    radius = max(float(np.quantile(np.linalg.norm(x - centre, axis=1), 0.99)), 1e-12)
    feats = np.concatenate([(x - centre) / radius, cfg.colour_weight * rgb.detach().double().cpu().numpy()], 1)
    k = n_clusters_for(n, cfg)

    def fit(k: int) -> tuple[np.ndarray, str]:
        if n * k > cfg.minibatch_above:
            km = MiniBatchKMeans(k, random_state=cfg.seed, batch_size=4096, n_init=3)
            return km.fit_predict(feats), "MiniBatchKMeans"
        return KMeans(k, random_state=cfg.seed, n_init=1).fit_predict(feats), "KMeans"

    labels, algo = fit(k)
    span = None
    if cfg.span > 0 and not cfg.n_clusters:
        from .geometry import group_diameters, robust_bounds

        D = 2 * robust_bounds(means)[1]
        span = {"clusters_by_count": k, "fits": []}
        power, best = 0.5, None  # the width falls as k^-power: 1/2 on a patch, up to 1 along a strip (a neck)
        for i in range(SPAN_FITS):
            got = float(np.median(group_diameters(labels, x))) / D
            span["fits"].append({"clusters": k, "diameter": got})
            if best is None or abs(np.log(got / cfg.span)) < abs(np.log(best[2] / cfg.span)):
                best = (labels, algo, got, k)
            if got <= 0 or abs(got / cfg.span - 1) <= SPAN_TOLERANCE or i == SPAN_FITS - 1:
                break  # (clusters of one point or of coincident points have no width to correct by)
            if i:  # the secant in log-log: the exponent the last two fits measured
                (k0, d0), (k1, d1) = ((f["clusters"], f["diameter"]) for f in span["fits"][-2:])
                if k0 != k1 and d0 != d1:  # both > 0: a fit without a width stopped the loop
                    power = float(np.clip(-np.log(d1 / d0) / np.log(k1 / k0), 0.25, 1.5))
            k_next = n_clusters_for(n, cfg, k * (got / cfg.span) ** (1 / power))
            if k_next == k:
                break
            k = k_next
            labels, algo = fit(k)
        labels, algo, _, k = best
        span["clusters"] = k
        log.info("k-means: span %.3g of the content's diameter: %s clusters (median widths %s); %d kept", cfg.span,
                 " -> ".join(str(f["clusters"]) for f in span["fits"]),
                 ", ".join(f"{f['diameter']:.3g}" for f in span["fits"]), k)
    labels, merged = _merge_small(labels, feats, cfg.min_size)
    split = 0
    if cfg.flatness > 0:
        if normals is None or tuple(normals.shape) != tuple(means.shape):
            raise ValueError("k-means: flatness > 0 needs an outward normal [N, 3] per point")
        labels, split = split_wrapped(labels, normals.detach().double().cpu().numpy(), cfg)
    changed, own = 0.0, None
    if cfg.coherence:
        own = own_share(labels, x)
        if own < cfg.coherence_below:
            labels, changed = contiguous(labels, x, cfg.coherence)
        else:
            log.info("k-means: no majority vote: %.2f of the points' %d nearest share their cluster (coherence_below "
                     "%.2f)", own, OWN_K, cfg.coherence_below)
    K = labels.max() + 1
    cent = np.stack([x[labels == i].mean(0) for i in range(K)])
    sizes = np.bincount(labels, minlength=K)
    info = {"algorithm": algo, "requested_clusters": k, "clusters": int(K), "merged_small_clusters": merged,
            "split_wrapped_clusters": split, "own_share": own, "coherence_relabelled": changed,
            "span": span,
            "size_min": int(sizes.min()), "size_median": float(np.median(sizes)), "size_max": int(sizes.max()),
            "points": n}
    log.info("k-means (%s): %d clusters of %d..%d points (median %.0f)", algo, K, sizes.min(), sizes.max(),
             np.median(sizes))
    return labels.astype(np.int64), cent, info


COHERENCE_K = 16  # neighbours of the majority vote (clustering.contiguous)
OWN_K = 8  # neighbours of own_share
SPAN_FITS = 5  # k-means fits at most when span corrects the count ...
SPAN_TOLERANCE = 0.05  # ... until the median width is within this share of span


def own_share(labels: np.ndarray, points: np.ndarray, k: int = OWN_K, max_points: int = 200_000) -> float:
    """Share of the pairs (point of points [N, 3], one of its ``k`` nearest neighbours) whose labels [N]
    agree: near 1 for compact patches (only their borders disagree), lower where clusters interleave.
    Beyond ``max_points`` points it is estimated on a seeded uniform draw of that many (standard error
    below 0.001; it is compared with ``coherence_below``)."""
    from .geometry import kdtree

    k = min(k, len(points) - 1)
    if k < 1:
        return 1.0
    q = np.arange(len(points))
    if len(points) > max_points:
        q = np.sort(np.random.default_rng(0).choice(len(points), max_points, replace=False))
    nb = kdtree(points).query(points[q], k=k + 1)[1][:, 1:]
    return float((labels[nb] == labels[q, None]).mean())


def contiguous(labels: np.ndarray, points: np.ndarray, passes: int, k: int = COHERENCE_K) -> tuple[np.ndarray, float]:
    """``passes`` rounds of: every point [N, 3] takes the most common label among itself and its ``k``
    nearest neighbours (a tie with its own label keeps it) -> labels renumbered 0..K'-1 (a cluster voted away
    disappears), and the share of points relabelled."""
    from .geometry import kdtree

    k = min(k, len(points) - 1)
    if k < 1 or passes < 1:
        return labels, 0.0
    nb = kdtree(points).query(points, k=k + 1)[1]  # itself first
    lab = labels.copy()
    for _ in range(passes):
        new = np.empty_like(lab)
        for a in range(0, len(lab), 100_000):  # [chunk, k+1, k+1] agreements at once
            votes = lab[nb[a:a + 100_000]]
            agree = (votes[:, :, None] == votes[:, None, :]).sum(-1)
            new[a:a + 100_000] = votes[np.arange(len(votes)), agree.argmax(1)]  # a tie keeps the first: itself
        if np.array_equal(new, lab):
            break
        lab = new
    changed = float((lab != labels).mean())
    return np.unique(lab, return_inverse=True)[1].astype(labels.dtype), changed


def _merge_small(labels: np.ndarray, feats: np.ndarray, min_size: int) -> tuple[np.ndarray, int]:
    """Merge clusters smaller than ``min_size`` into the nearest large cluster; relabel 0..K-1."""
    ids, counts = np.unique(labels, return_counts=True)
    small = ids[counts < min_size]
    big = ids[counts >= min_size]
    if len(small) and len(big):
        cents = np.stack([feats[labels == i].mean(0) for i in big])
        for s in small:
            m = labels == s
            d = ((feats[m][:, None, :] - cents[None]) ** 2).sum(-1)
            labels[m] = big[d.argmin(1)]
        log.info("k-means: merged %d clusters below %d points into their nearest neighbours", len(small), min_size)
    _, labels = np.unique(labels, return_inverse=True)
    return labels, int(len(small)) if len(big) else 0


def flatness_of(labels: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """[K] length of each cluster's mean unit normal (1: all normals agree, 0: a closed tube or blob)."""
    K = labels.max() + 1
    m = np.zeros((K, 3))
    np.add.at(m, labels, normals)
    return np.linalg.norm(m, axis=1) / np.maximum(np.bincount(labels, minlength=K), 1)


def split_wrapped(labels: np.ndarray, normals: np.ndarray, cfg: ClusterConfig) -> tuple[np.ndarray, int]:
    """Split every cluster whose :func:`flatness_of` is below ``cfg.flatness`` in two by 2-means on its
    normals [N, 3], repeatedly, while both halves keep ``cfg.min_split`` points -> labels (0..K-1), splits."""
    from sklearn.cluster import KMeans

    labels = labels.copy()
    splits, todo = 0, list(range(labels.max() + 1))
    while todo:
        k = todo.pop()
        idx = np.nonzero(labels == k)[0]
        if len(idx) < 2 * cfg.min_split or flatness_of(np.zeros(len(idx), np.int64), normals[idx])[0] >= cfg.flatness:
            continue
        half = KMeans(2, random_state=cfg.seed, n_init=1).fit_predict(normals[idx])
        if min(half.sum(), len(half) - half.sum()) < cfg.min_split:
            continue
        new = labels.max() + 1
        labels[idx[half == 1]] = new
        splits += 1
        todo += [k, new]
    return labels, splits

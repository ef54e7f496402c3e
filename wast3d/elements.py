"""Stage 8, element metrics: does the result show the style's elements, whole?

A labelled style (``GaussianScene.element``: 0 = the ground, 1.. = one pebble, blade, strand or
stone each; :mod:`wast3d.procedural`, or taken from the nearest source Gaussian for a style trained
from a procedural one's renders) carries its labels through selection, stylization and rescale, so
every Gaussian of a result knows which element of the style it came from.

``element_share``
    The share of a render's foreground pixels (alpha > 0.5) that element Gaussians draw: the
    label channel ``e = render(colours = [element > 0]) / alpha`` (the same rasterizer, the same
    cameras as the RGB frames), a pixel counting when ``e > 0.5``. Reported for the result (its
    turntable) and for the style (its texture reference: the style at the result's pixel scale), and
    as their ratio (1 = the style's own mix of elements and ground; a result of sand alone scores 0).
    An unlabelled result (the content, a colour transfer) draws no element pixel: 0.

``element_intact``
    How whole the elements stay. Each *copy* of an element in the result (the Gaussians of one element
    selected by one cluster) is compared with itself before the optimization (the collage: the same
    Gaussians registered onto the content, rigid within the cluster). The copy's best similarity
    x' ~ s R x + t (orthogonal Procrustes with scale, R proper) is fitted, and each of its Gaussians
    scores its residual after that fit over the copy's RMS radius after it,

        d_j = | x'_j - (s R x_j + t) | / ( s * rms_k |x_k - mean x| )

    A Gaussian is intact when d_j <= ``tol`` (default 0.25: a pebble may bend by a quarter of its own
    size); the score is the share of intact element Gaussians. Moved, turned or uniformly resized
    elements score 1 (scale readjustment resizes them on purpose), the collage 1 by construction; an
    element torn into confetti or squashed flat scores near 0. Copies of fewer than ``min_size``
    Gaussians are left out (an element cut at the edge of a cluster's footprint to a sliver has no
    shape to keep).

``element_whole``
    How large the element pieces a viewer sees are: the pixel-weighted mean area of the visible
    *pieces* (connected pixels drawn by one element copy), on the same views as ``element_share``, and
    its ratio to the style's own (its texture reference, at the result's pixel scale). Each copy gets
    a random code c in [0, 1]^D (D = ``PIECE_DIM``, the ground 0) and the renders of the codes give
    per pixel v = render(codes) / render(element channel): a pixel drawn by one copy reads that copy's
    code, a blend of copies (copies piled on each other, or an element seen through another) reads
    none. An element pixel (``element_pixels`` > 0.5, alpha > ``min_alpha``) belongs to the copy whose
    code c is nearest, if within ``piece_tol`` times the distance from c to the nearest other code (a
    blend in which other copies weigh ``piece_tol`` or more is in no piece, however close two random codes
    fall); 4-neighbours of the same copy join one piece, and

        element_whole = sum_p area(piece(p)) / #pixels p in pieces.

    Its elements cut into fragments by the clusters' edges, or overlapping so that no one shows whole,
    lower it (the guitar x trained stones' gravel with specks); a copy that stays whole and unhidden
    scores its element's full area. Whether the element reads as a dome (its shading) it does not see.
    Where clusters make their elements smaller on purpose (``register.follow_thickness``: cluster k's
    elements come out f_k = s0 / base_k <= 1 times the size), a piece's area counts times (f_ref / f_k)^2,
    f_ref the size the texture reference shows the style at (the clusters' median), so that a whole small
    element scores as a whole large one.

``segment_whole``, ``segment_intact``
    The same two measures with no label: the style's *segments* stand in for its elements, written by
    the texture reference: a patch's relief basins (one per dome of its top surface,
    :func:`wast3d.registration.relief_basins`), a volume's sheet's laid-out elements (the style stage
    made them from labels or from label-free pieces). Every result Gaussian is a copy of one style
    Gaussian (stylize's ``source``) and takes its segment; a copy is one segment selected by one
    cluster. A basin holds its dome and the ground around it, so every Gaussian is in one; the flow
    may bend that ground, so ``segment_intact`` reads below ``element_intact`` (0.69 against 0.85 on
    the demo), and unlike ``element_whole`` and ``relief_w1`` it sees elements flattened into chips.
    A user's own style, unlabelled, gets both (benchmarks/element_validation.py checks them against
    the labelled pair and the controls).

``element_diameter``
    The median over elements of twice the 90th-percentile distance of an element's Gaussians to its
    centroid (robust to a stray Gaussian). Registration does not use it (its scale rule needs no
    labels: :func:`wast3d.registration.relief_length`); it is the labelled size that rule is checked
    against.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from .options import checked, option


@dataclass
@checked("elements")
class ElementConfig:
    tol: float = option(0.25, "element_intact: a Gaussian's residual after its element copy's best similarity fit (in "
                              "copy radii) that still counts as intact", exclusiveMinimum=0)
    min_size: int = option(4, "element_intact: element copies with fewer Gaussians are left out", minimum=2)
    min_alpha: float = option(0.5, "element_share: pixels above this alpha are foreground",
                                   exclusiveMinimum=0, exclusiveMaximum=1)
    piece_tol: float = option(0.25, "element_whole: a pixel is a copy's where the other copies weigh less than this "
                                    "share of it (its code within this share of the distance from the copy's code "
                                    "to the nearest other)", exclusiveMinimum=0, exclusiveMaximum=0.5)


PIECE_DIM = 6  # element_whole's code length: two 3-channel renders



def label_colours(element: torch.Tensor, dtype=torch.float32) -> torch.Tensor:
    """[N] labels -> [N, 3] colours for the label channel: 1 for element Gaussians, 0 for the ground."""
    return (element > 0).to(dtype)[:, None].expand(-1, 3).contiguous()


def element_pixels(label_rgb: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """Label-channel render (background 0) [H, W, 3] and alpha [H, W] -> the element share per pixel
    [H, W] in [0, 1] (``rgb / alpha``; 0 where nothing is drawn)."""
    return (label_rgb[..., 0] / alpha.clamp_min(1e-6)).clamp(0, 1) * (alpha > 1e-6)


def element_share(element_frames: torch.Tensor, alpha: torch.Tensor, min_alpha: float = 0.5) -> float:
    """element_frames: [V, H, W] per-pixel element share (:func:`element_pixels`), alpha [V, H, W] ->
    the share of foreground pixels (alpha > min_alpha) that element Gaussians draw (e > 0.5)."""
    fg = alpha > min_alpha
    if not bool(fg.any()):
        raise ValueError(f"element share: no foreground pixel (alpha > {min_alpha})")
    return float(((element_frames > 0.5) & fg).sum() / fg.sum())


def share_blind(element: torch.Tensor) -> str | None:
    """Why ``element_share_ratio`` cannot tell results of this style apart ([N] labels), or None. Where
    every Gaussian of the style is an element (a volume's sheet: what held the elements was left off),
    every result made of it draws element pixels only and scores 1, flowers whole or cut."""
    if len(element) and bool((element > 0).all()):
        return "every Gaussian of the style is an element (a volume's sheet): any result of it scores 1"
    return None


def copy_codes(copies: torch.Tensor, seed: int = 0, dtype=torch.float32) -> tuple[torch.Tensor, torch.Tensor]:
    """[N] copy id of each Gaussian (-1: the ground) -> (per-Gaussian colours [N, PIECE_DIM], the ground
    0; the distinct copies' codes [C, PIECE_DIM], uniform in [0, 1], row c for the c-th smallest id)."""
    ids, inv = torch.unique(copies, return_inverse=True)
    codes = torch.rand(len(ids), PIECE_DIM, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    cols = codes[inv].to(dtype)
    cols[copies < 0] = 0
    return cols, codes[ids >= 0]


def piece_areas(code_rgb: torch.Tensor, element: torch.Tensor, alpha: torch.Tensor, codes: torch.Tensor,
                tol: float, min_alpha: float = 0.5, weight: np.ndarray | None = None) -> np.ndarray:
    """One view of ``element_whole``: code_rgb [H, W, PIECE_DIM] (the render of :func:`copy_codes`'s colours
    on black), element [H, W] (:func:`element_pixels`), alpha [H, W], codes [C, PIECE_DIM] -> the area of
    its piece for every pixel in a piece ([P], pixels; empty where none), times its copy's ``weight`` [C]
    where given (the module docstring's size factor)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    el = ((element > 0.5) & (alpha > min_alpha)).numpy()
    if len(codes) == 0 or not el.any():
        return np.zeros(0, dtype=np.int64)
    w = (element * alpha).clamp_min(1e-6)[..., None]  # the element Gaussians' blending weight
    v = (code_rgb / w).double().numpy()[el]
    tree = cKDTree(codes.double().numpy())
    # each code's distance to its nearest other code: a blend with another copy moves a pixel off the
    # code by its weight times their distance, so the tolerance is a share of that distance
    gap = tree.query(codes.double().numpy(), k=2)[0][:, 1] if len(codes) > 1 else np.full(1, np.inf)
    d, j = tree.query(v)
    owner = np.full(el.shape, -1, dtype=np.int64)
    owner[el] = np.where(d <= tol * gap[j], j, -1)
    # pieces: the connected components of the graph joining 4-neighbours of one owner
    H, W = owner.shape
    idx = np.arange(H * W).reshape(H, W)
    a, b = [], []
    for oa, ob, ia, ib in ((owner[:, :-1], owner[:, 1:], idx[:, :-1], idx[:, 1:]),
                           (owner[:-1], owner[1:], idx[:-1], idx[1:])):
        joined = (oa == ob) & (oa >= 0)
        a.append(ia[joined])
        b.append(ib[joined])
    a, b = np.concatenate(a), np.concatenate(b)
    graph = coo_matrix((np.ones(len(a), dtype=np.int8), (a, b)), shape=(H * W, H * W))
    piece = connected_components(graph, directed=False)[1][(owner >= 0).ravel()]
    area = np.bincount(piece)[piece]
    return area if weight is None else area * np.asarray(weight, dtype=np.float64)[owner.ravel()[owner.ravel() >= 0]]


def element_whole(areas: list[np.ndarray]) -> float | None:
    """Per-view :func:`piece_areas` -> the pixel-weighted mean piece area (None: no pixel in a piece)."""
    a = np.concatenate([np.asarray(x, dtype=np.float64) for x in areas]) if areas else np.zeros(0)
    return float(a.mean()) if len(a) else None


def similarity_residuals(before: torch.Tensor, after: torch.Tensor) -> torch.Tensor:
    """d_j of the module docstring for one copy: before, after [n, 3] -> [n] (float64)."""
    b = before.double() - before.double().mean(0)
    a = after.double() - after.double().mean(0)
    U, S, Vt = torch.linalg.svd(b.T @ a)
    D = torch.ones(3, dtype=b.dtype)
    D[2] = torch.sign(torch.det(U @ Vt))  # a proper rotation (no reflection)
    R = (U * D) @ Vt  # a ~ s b R
    s = float((S * D).sum() / b.square().sum().clamp_min(1e-300))
    rms = float(b.square().sum(1).mean().sqrt())
    return (a - s * b @ R).norm(dim=1) / max(abs(s) * rms, 1e-300)


def element_intact(before: torch.Tensor, after: torch.Tensor, copies: torch.Tensor, cfg: ElementConfig) -> dict:
    """before, after: [N, 3] positions of the same Gaussians (the collage and the result, one frame);
    copies: [N] int64 id of each Gaussian's element copy (-1: the ground, left out) -> ``{"intact": share,
    "copies": number measured, "gaussians": element Gaussians measured, "median_distortion": median d_j}``."""
    ok = copies >= 0
    ids, inv, counts = torch.unique(copies[ok], return_inverse=True, return_counts=True)
    idx_all = ok.nonzero().squeeze(1)
    order = torch.argsort(inv, stable=True)
    starts = torch.cat([counts.new_zeros(1), counts.cumsum(0)])
    dist = []
    for c in range(len(ids)):
        if int(counts[c]) < cfg.min_size:
            continue
        members = idx_all[order[starts[c]:starts[c + 1]]]
        if float((before[members] - before[members].mean(0)).abs().max()) <= 0:
            continue  # coincident Gaussians: no shape to keep
        dist.append(similarity_residuals(before[members], after[members]))
    if not dist:
        return {"intact": None, "copies": 0, "gaussians": 0, "median_distortion": None}
    d = torch.cat(dist)
    return {"intact": float((d <= cfg.tol).double().mean()), "copies": len(dist), "gaussians": len(d),
            "median_distortion": float(d.median())}


def segment_copies(segments: torch.Tensor, source: torch.Tensor, clusters: torch.Tensor) -> torch.Tensor:
    """The segment copies of a result: [M] segment of each style Gaussian (0..), [N] the style Gaussian
    each result Gaussian is a copy of, [N] its cluster -> [N] copy ids (cluster, segment), all >= 0."""
    if len(source) and (int(source.min()) < 0 or int(source.max()) >= len(segments)):
        raise ValueError(f"segment copies: source indices outside the style's {len(segments)} Gaussians")
    return copy_ids(segments.long()[source.long()] + 1, clusters)


def copy_ids(element: torch.Tensor, clusters: torch.Tensor) -> torch.Tensor:
    """[N] element labels and [N] cluster of each result Gaussian -> [N] id of its element copy
    (cluster, element), -1 for the ground."""
    key = clusters.long() * (int(element.max()) + 1) + element.long()
    return torch.where(element > 0, key, torch.full_like(key, -1))


def element_diameter(means: torch.Tensor, element: torch.Tensor, min_size: int = 4) -> float:
    """Median element diameter of a labelled scene (see the module docstring); means [N, 3]."""
    from .geometry import group_diameters

    e = element.numpy()
    on = e > 0
    _, groups, counts = np.unique(e[on], return_inverse=True, return_counts=True)
    diam = group_diameters(groups, means.detach().double().numpy()[on])[counts >= min_size] if on.any() else []
    if not len(diam):
        raise ValueError("element diameter: no element with at least %d Gaussians" % min_size)
    return float(np.median(diam))


def transfer_elements(target: torch.Tensor, source: torch.Tensor, source_element: torch.Tensor) -> torch.Tensor:
    """Labels for a scene trained from renders of a labelled one: each target Gaussian [N, 3] takes the
    label of its nearest source Gaussian (source [M, 3], source_element [M]) -> [N] int64."""
    from .geometry import knn

    _, idx = knn(target.detach().float(), source.detach().float(), 1)
    return source_element[idx[:, 0]].long()

"""Stage 5, stylization: minimize the Sinkhorn divergence between each content cluster and its style
Gaussians (paper eq. 9), then map the result back into the content frame.

    L_opt = sum_i SD_gamma( C_i , D_i(C_i) )                                         (eq. 9)

For cluster i, in the registered (style) frame:

- the content cluster is mapped by eq. 7, ``X = S_i R_i (g - t_i)``; its selected style Gaussians
  ``D_i`` (eq. 8) keep their positions ``Y``;
- both are normalized by :func:`normalize_pair`: centred at the mapped content's mean and divided by
  its radius (largest distance to that mean), so gamma (= geomloss' blur) is a fraction of the
  cluster's radius at any scene scale: gamma = 0.3 is 30 % of it (the other reading of the paper,
  gamma as a length in the whole content scene, changed no result beyond the seed spread:
  studies/options);
- features (the paper's ablation): ``xyz`` (positions only), ``xyz+lum`` (default: positions and
  ``colour_weight * Y`` with Rec. 601 luma Y = 0.299 R + 0.587 G + 0.114 B), ``xyz+rgb``;
- the optimized variables are the style Gaussians' normalized positions and colour offsets (one
  luminance offset per Gaussian, or three RGB offsets), with Adam (``optimizer: adam``) or by the
  Sinkhorn gradient flow (``optimizer: flow``: plain steps along ``-M grad``, i.e. towards each
  point's transport target); the content is fixed;
- piecewise-rigid flow (``parts.size``, default on for a style whose relief is gentle, :func:`flow_parts`):
  the style is cut into parts about an element across, each moving by its Gaussians' best rigid
  motion towards their targets, so an element made of many trained Gaussians moves whole;
- displacement smoothing (``smoothing.passes``, default on where the parts are left out: blades, strands,
  :func:`smooth_displacements`): each step averaged over the neighbours within ``smoothing.radius`` relief
  lengths (on a sparse style, as far as its ``smoothing.neighbours``-th nearest, at most ``smoothing.radius_max``:
  :func:`smoothing_reach`),
  16 times, so a blade's Gaussians move together and it still bends with the content.
  Clusters are independent terms of eq. 9 and both optimizers act per coordinate, so optimizing them
  together (one packed Sinkhorn solve per step over ``batch`` clusters, :func:`stylize_clusters`) is
  the same as optimizing the sum, and the same as one cluster after another;
- colour update: a luminance offset dY is added to all three channels, ``rgb' = rgb + dY``: the
  luma changes by exactly dY (the weights sum to 1) and the chroma (differences between channels), so
  the hue, is kept. In SH terms only the DC coefficients change, ``f_dc' = f_dc + dY / SH_C0``;
  view-dependent coefficients are untouched. RGB offsets update the DC the same way per channel;
- the optimized style Gaussians go back to the content frame by the inverse of eq. 7,
  ``x = R_i^T S_i^{-1} y + t_i``, covariances ``A Sigma A^T`` with ``A = R_i^T S_i^{-1}``;
  opacities and the Gaussians' own rotations are carried over (rotated with A), and the
  view-dependent SH bands are rotated by ``R_i^T`` (the rotation of A's polar decomposition), so a
  style Gaussian shows its highlights towards the same side of itself as in the style scene.

Ablation switches: ``sinkhorn.debias=False`` (entropic OT, eq. 5), and ``loss="arap"``: instead of
Sinkhorn, a Chamfer data term plus an as-rigid-as-possible energy over each style Gaussian's k
nearest neighbours (per-Gaussian best rotations by Kabsch, held fixed within a step), our reading of
the paper's surface-energy baseline (eq. 10).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, fields, replace
from typing import NamedTuple

import numpy as np
import torch

from .device import resolve_device
from .gaussians import SH_C0, GaussianScene, footprint, luminance
from .geometry import kabsch, knn
from .options import checked, group, option
from .sinkhorn import SinkhornConfig, sinkhorn

log = logging.getLogger(__name__)

FEATURES = ("xyz", "xyz+lum", "xyz+rgb")


MASSES = ("uniform", "area", "style-area")
SMOOTH_AXES = ("all", "up")
PART_MOTIONS = ("translation", "rigid")
PART_SHAPES = ("auto", "kmeans", "relief")
PART_STARTS = ("cells", "basins")


@dataclass
class StylizeSinkhornConfig(SinkhornConfig):
    """Eq. 9's solver settings: gamma 30 % of the cluster radius (why not the paper's 0.05:
    docs/method.md, stage 5), potentials converged to 1e-3 eps at every step."""

    blur: float = option(0.3, "gamma, a fraction of each cluster's radius (the pair normalized by it)",
                              exclusiveMinimum=0)
    tol: float = option(1e-3, "iterate at the final eps until the potentials change by <= tol * eps (0: fixed iteration"
                              " counts)", minimum=0)


@dataclass
@checked("stylize.parts")
class PartsConfig:
    """The piecewise-rigid flow (:func:`flow_parts`): the style cut into parts about an element across,
    each moving as one rigid body, on a style whose relief is gentle."""

    size: float = option(1.2, "piecewise-rigid flow: the style cut into parts (k-means on [position / (size relief "
                              "lengths), colour]: parts about this many relief lengths across), each moving as one, "
                              "so that elements made of many Gaussians move whole (0: off)", minimum=0)
    shape: str = option("auto", "how the style is cut into parts: kmeans (parts relief lengths across, on "
                                "position and colour, started as start says), relief (the watershed basins of its top "
                                "surface: one part per dome, whatever its size, bordered by the crevices) or "
                                "auto (kmeans, or relief where parts of one size, dome_probe relief "
                                "lengths from cells, cut the domes: the median basin keeps less than "
                                "dome_cut of its Gaussians in one part); size > 0 "
                                "turns them on", enum=PART_SHAPES)
    dome_cut: float = option(0.65, "shape auto: the basins replace the k-means parts where the median "
                                   "basin (of 8 Gaussians or more) keeps less than this share of its Gaussians "
                                   "in one k-means part (procedural and trained stones 0.48-0.60, pebbles "
                                   "0.69-0.80)", minimum=0, maximum=1)
    dome_probe: float = option(0.8, "shape auto: the k-means parts that test the domes are this many "
                                    "relief lengths across, whatever size is (dome_cut was measured "
                                    "there; at 1.2 the stones' domes read 0.709 and would get k-means parts)",
                               exclusiveMinimum=0)
    start: str = option("basins", "where the k-means parts start: cells (one per occupied cell of size relief "
                                  "lengths on the patch's plane) or basins (one per basin of the relief, so one "
                                  "per dome, refined by position and colour: by the labels the procedural "
                                  "pebbles keep 0.916 of their Gaussians in their largest part against 0.884 from "
                                  "cells, the 1M pebbles 0.895 against 0.829, the trained pebbles 0.956 against "
                                  "0.952)", enum=PART_STARTS)
    colour: float = option(3.0, "the colour's weight in the parts' k-means (features [xyz / part size, "
                                "colour * rgb]): part borders follow colour edges such as a pebble's rim",
                                minimum=0)
    motion: str = option("rigid", "each part's step: the mass-weighted mean of its Gaussians' steps (translation)"
                                  " or their best rigid motion (rigid: a part also turns to follow a curved "
                                  "content)", enum=PART_MOTIONS)
    max_aspect: float = option(0.16, "parts only on a style whose relief aspect (RMS height of its top surface "
                                     "over its relief length) is at most this: elements about a relief length in "
                                     "every direction (pebbles, boulders: 0.08-0.13), not blades or a weave (0.26-"
                                     "0.34), which rigid parts would tear; a large value: parts on "
                                     "every style", minimum=0)


@dataclass
@checked("stylize.smoothing")
class SmoothingConfig:
    """Displacement smoothing (:func:`smooth_displacements`, :func:`smoothing_reach`): each flow step
    averaged over the style's own neighbours, where the parts are left out (blades, strands)."""

    passes: int = option(16, "passes of the average per step (0: off); elements move as"
                             " wholes", minimum=0)
    k: int = option(32, "neighbours (in the style's own positions, same cluster) each "
                        "step's displacement is averaged over", minimum=1)
    radius: float = option(0.25, "a pass averages only over the neighbours within this "
                                 "many style relief lengths (a reach in length, whatever the style's density); "
                                 "0: over all k neighbours", minimum=0)
    neighbours: int = option(16, "where the style is so sparse that radius holds "
                                 "fewer neighbours, the radius widens to the median distance of a Gaussian's "
                                 "this-many-th nearest, up to radius_max (the trained weave: 0.25 -> 0.5 "
                                 "relief lengths; every grass keeps 0.25); 0: radius alone", minimum=0)
    radius_max: float = option(0.5, "neighbours widens the radius to at most this "
                                    "many relief lengths (half an element: farther, a pass ties neighbouring "
                                    "elements into plates)", minimum=0)
    axis: str = option("all", "the smoothing acts on the whole step (all) or only on its component "
                              "along the style's up (up: elements keep their relief, move freely across the "
                              "surface)", enum=SMOOTH_AXES)
    with_parts: bool = option(False, "smoothing also where parts move the style; false: only where "
                                     "the parts are left out (a steep relief, or parts 0), whose Gaussians would"
                                     " otherwise each move on their own")


@dataclass
@checked("stylize.copies")
class CopiesConfig:
    """What happens to the part copies the selection cut at a cluster's edge (:func:`completed_selection`,
    :func:`own_copies`). Null: by the style's form (:data:`SHEET_COPIES` on a volume's element sheet, whose
    parts are its elements: each flower copy whole, once; off on a patch)."""

    trim: float | None = option(None, "a part copy (one flow part's Gaussians selected by one cluster; one Gaussian "
                                      "where the parts are left out) is dropped where less than this share of it lies "
                                      "over the cluster's own content (its nearest content point, registered back, in "
                                      "the cluster): the neighbours' footprints overlap, and their copies piled on each"
                                      " other show no element whole; 0: every selected Gaussian flows; null: 0.5 on a "
                                      "volume's element sheet, 0 on a patch", minimum=0, maximum=1)
    complete: float | None = option(None, "a part copy (one flow part's Gaussians selected by one cluster) holding at "
                                          "least this share of its part is completed to the whole part (the footprint "
                                          "cuts elements at a cluster's edge: a trained boulder copy held a median "
                                          "third of its boulder); only where parts are on, on clusters the selection "
                                          "did not thin, before trim; 0: off; null: 0.3 on a volume's element sheet, 0 "
                                          "on a patch", minimum=0, maximum=1)
    complete_height: float = option(0.0, "complete only the parts whose mean height (along the style's up) ranks above "
                                         "this quantile of the parts' mean heights: the ones standing out of the "
                                         "ground, mostly elements; 0: every part", minimum=0, maximum=1)
    drop: float | None = option(None, "a part copy holding less than this share of its part is dropped (with complete: "
                                      "the fragments left beside the completed copies); 0: off; null: 0.3 on a "
                                      "volume's element sheet, 0 on a patch", minimum=0, maximum=1)


SHEET_COPIES = {"trim": 0.5, "complete": 0.3, "drop": 0.3}  # a sheet's copies where the config leaves them null


def resolved_copies(cfg: "StylizeConfig", sheet: bool) -> "StylizeConfig":
    """``cfg`` with its null ``copies`` set by the style's form (``sheet``: a volume's element sheet), logged."""
    null = [k for k in SHEET_COPIES if getattr(cfg.copies, k) is None]
    if not null:
        return cfg
    values = {k: SHEET_COPIES[k] if sheet else 0.0 for k in null}
    if sheet:
        log.info("stylize: part copies by the style's form (a volume's element sheet: each element copy whole, once): "
                 "%s", ", ".join(f"{k} {v:g}" for k, v in values.items()))
    return replace(cfg, copies=replace(cfg.copies, **values))


@dataclass
@checked("stylize")
class StylizeConfig:
    features: str = option("xyz+lum", "what the divergence compares: positions, positions + luminance (the paper), "
                                      "positions + RGB", enum=FEATURES)
    colour_weight: float = option(0.5, "weight of the colour coordinates against normalized positions", minimum=0)
    iterations: int = option(30, "optimization steps (0: registration + selection mapped back unoptimized, a collage)",
                                 minimum=0)
    lr: float = option(0.2, "step size: the flow's fraction of the way to the transport target per step, or Adam's "
                            "learning rate", exclusiveMinimum=0)
    lr_colour: float = option(0.02, "Adam's learning rate of the luminance offsets", minimum=0)
    optimizer: str = option("flow", "adam, or the Sinkhorn gradient flow (steps of lr towards the transport target)",
                                    enum=["adam", "flow"])
    loss: str = option("sinkhorn", "sinkhorn (eq. 9) or arap (Chamfer + as-rigid-as-possible energy: the paper's "
                                   "ablation, our reading of eq. 10)", enum=["sinkhorn", "arap"])
    warm_start: bool = option(True, "start each step's solve from the previous step's potentials")
    arap_weight: float = option(1.0, "arap: weight of the rigidity energy", minimum=0)
    arap_k: int = option(8, "arap: neighbours of the rigidity graph", minimum=1)
    dtype: str = option("float32", "precision of the optimization", enum=["float32", "float64"])
    device: str = option("auto", "auto: CUDA when available", enum=["auto", "cpu", "cuda"])
    batch: int = option(0, "clusters per packed Sinkhorn solve (0: all in one; 1: one at a time, the per-pair "
                           "reference); same result, fewer kernel launches", minimum=0)
    content_points: int = option(4096, "each cluster's content points in the transport, at most (a uniform draw "
                                       "beyond, transport_points: the cost grows as content points times style "
                                       "Gaussians; every project scene has fewer per cluster); 0: every point",
                                 minimum=0)
    style_points: int = option(4096, "each cluster's style Gaussians in the transport, at most (a uniform draw "
                                     "beyond, transport_leaders, carrying the others' masses; every Gaussian then "
                                     "moves by the solved potentials' gradient at its own position: the "
                                     "self-term costs style Gaussians squared; every project scene has fewer per "
                                     "cluster); 0: every one",
                               minimum=0)
    masses: str = option("style-area", "each Gaussian's mass in the transport: area (opacity times its two largest "
                                       "scales: both sides are distributions of surface, whatever the Gaussians' "
                                       "sizes), uniform (one per Gaussian: where a trained scene uses many small "
                                       "Gaussians, mass piles up and the flow tears elements to even it out) or "
                                       "style-area (the style's by area, the content's one per point: a trained "
                                       "capture's large Gaussians behind its visible surface then do not pull the style"
                                       " in)", enum=MASSES)
    parts: PartsConfig = group(PartsConfig, "the piecewise-rigid flow: parts about an element across move as one")
    smoothing: SmoothingConfig = group(SmoothingConfig, "displacement smoothing where the parts are left out")
    copies: CopiesConfig = group(CopiesConfig, "part copies cut at a cluster's edge: trimmed, completed or dropped (by "
                                                           "default on a volume's element sheet, off on a patch)")
    sinkhorn: SinkhornConfig = group(StylizeSinkhornConfig, "the debiased Sinkhorn solver (geomloss conventions: cost |x-y|^2/2, eps = blur^2)")


def normalize_pair(content: torch.Tensor, style: torch.Tensor | None = None) -> tuple[torch.Tensor, float]:
    """Centre [3] and radius of a mapped content cluster [N, 3]. A cluster of one point (or of
    coincident points) has no radius: then the style's [M, 3] distance to the centre is used, and
    failing that 1e-9 (dividing by ~0 made a one-point cluster's divergence ~1e17 and froze it)."""
    c = content.mean(0)
    r = float((content - c).norm(dim=1).max()) if len(content) > 1 else 0.0
    if r <= 1e-9 and style is not None and len(style):
        r = float((style.to(c) - c).norm(dim=1).max())
    return c, max(r, 1e-9)


def colour_features(rgb: torch.Tensor, features: str) -> torch.Tensor:
    """[N, 3] -> [N, 0 | 1 | 3]."""
    if features == "xyz":
        return rgb[:, :0]
    if features == "xyz+lum":
        return luminance(rgb)[:, None]
    return rgb


@dataclass
class ClusterResult:
    positions: torch.Tensor  # [M, 3] optimized, style frame
    colour_offset: torch.Tensor  # [M, 0|1|3]
    losses: list[float]
    seconds: float  # this cluster's share of its batch's time (by its work, N M + M^2)


@dataclass
class ClusterPair:
    """One term of eq. 9: content cluster x_* [N, 3] in the style frame, its style Gaussians y_* [M, 3],
    its gamma in normalized units (a fraction of the cluster's radius) and the two sides' masses x_w [N], y_w [M]
    (any positive scale, normalized per side; None: uniform)."""

    x_pos: torch.Tensor
    x_rgb: torch.Tensor
    y_pos: torch.Tensor
    y_rgb: torch.Tensor
    blur: float
    x_w: torch.Tensor | None = None
    y_w: torch.Tensor | None = None
    y_part: torch.Tensor | None = None  # [M] each style Gaussian's part (style_parts); None: every one free
    y_reach: float | None = None  # displacement smoothing's neighbourhood radius, style units; None: k nearest only


def footprint_masses(scene: GaussianScene) -> torch.Tensor:
    """[N] each Gaussian's mass for ``masses: area``: ``o s_1 s_2``, its opacity times the product of
    its two largest scales (the integral of its footprint seen face-on, over 2 pi).

    Why: the transport moves one distribution of mass onto the other. With uniform masses a region
    holds as much mass as it has Gaussians, so where a trained scene puts many small Gaussians (a
    pebble's rim, a leg's edge) and where it puts a few large ones (a pebble's top, the flat ground)
    weigh differently, and the flow moves Gaussians from the first kind of region to the second to
    even out the count: elements tear (the procedural styles, uniform discs at one spacing, never
    showed it). With masses by area both sides are distributions of visible surface, whatever the
    Gaussians' sizes.

    Where it fails: a trained *capture* as content keeps large Gaussians behind or under its visible
    surface (the guitar's body), and by area they hold much of a cluster's mass, so the flow pulls the
    style into the body (``masses: style-area`` weighs the content's points one each and the style's by
    footprint)."""
    return footprint(scene.scales, scene.opacities).clamp_min(1e-30)


def transport_masses(content: GaussianScene, style: GaussianScene, masses: str) -> tuple[torch.Tensor | None, torch.Tensor | None]:
    """The content's [N] and the style's [M] masses for ``stylize.masses`` (None: one per Gaussian)."""
    if masses not in MASSES:
        raise ValueError(f"stylize.masses must be one of {MASSES}, got '{masses}'")
    c_mass = footprint_masses(content) if masses == "area" else None
    s_mass = footprint_masses(style) if masses in ("area", "style-area") else None
    return c_mass, s_mass


def neighbour_graph(ys: list[torch.Tensor], k: int, radii: list[float | None] | None = None) -> torch.Tensor:
    """[sum M, k] indices into the packed style rows: each row's k nearest neighbours (itself included)
    among its own cluster's style Gaussians, in their positions before optimization. ``radii`` (one per
    cluster, in the units of ``ys``; None: no limit): a neighbour farther than that is replaced by the
    row itself, so one pass of :func:`smooth_displacements` moves a step by at most that distance."""
    out, off = [], 0
    for j, y in enumerate(ys):
        kk = min(k, len(y))
        d, idx = knn(y.double().cpu(), y.double().cpu(), kk)
        if kk < k:  # a cluster smaller than k: repeat its own row
            idx = torch.cat([idx, idx[:, :1].expand(-1, k - kk)], 1)
            d = torch.cat([d, d[:, :1].expand(-1, k - kk)], 1)
        if radii is not None and radii[j] is not None:
            idx = torch.where(d <= radii[j], idx, idx[:, :1])
        out.append(idx + off)
        off += len(y)
    return torch.cat(out) if out else torch.zeros(0, k, dtype=torch.long)


def smooth_displacements(g: torch.Tensor, nb: torch.Tensor, passes: int, up: torch.Tensor | None = None) -> torch.Tensor:
    """g: [M, D] per-Gaussian step directions, nb: [M, k] neighbours -> g averaged over the neighbours
    ``passes`` times (a discrete diffusion of the displacement field over the style's own surface, of
    radius about sqrt(passes) neighbourhoods). Gaussians of one element then take one displacement and
    move together, as the Sinkhorn flow alone does only at scales above gamma.

    ``up`` [3] (unit, D = 3): only the component along it, ``h = g . up``, is averaged and the rest
    kept, ``g' = g - h up + smooth(h) up``: an element's Gaussians keep their heights relative to each
    other (its relief) while each still moves freely across the surface."""
    if up is not None:
        u = up.to(g)
        h = (g @ u)[:, None]
        return g + (smooth_displacements(h, nb, passes) - h) * u
    for _ in range(passes):
        g = g[nb].mean(1)
    return g


def style_parts(style: torch.Tensor, rgb: torch.Tensor, up, size: float, colour: float = 1.0,
                max_iter: int = 10, start: torch.Tensor | None = None) -> torch.Tensor:
    """style [M, 3] positions, rgb [M, 3] colours, its up (:func:`~wast3d.registration.patch_frame`), a
    part diameter ``size`` in its units -> [M] int64 part ids: k-means on ``[xyz / size, colour * rgb]``,
    started from the centroids of the occupied ``size`` x ``size`` cells of the patch's plane (so about
    one part per cell, deterministic), or of the groups of ``start`` [M] (ids, e.g. the relief's basins:
    one part per basin, its borders then moved to the colour edges). The colour term puts part borders
    where the colour changes (a pebble's rim): on the demo's trained pebbles at one relief length the
    median pebble has 71 % of its Gaussians in one part on positions alone, 99 % with ``colour`` 1.

    Why: each step of the flow moves every style Gaussian towards its own transport target, so the
    Gaussians of one trained pebble (many small ones, of different colours) go different ways and the
    pebble tears (``element_intact``). With parts, each part moves by the mass-weighted mean of its
    Gaussians' steps, ``v_P = sum_j b_j v_j / sum_j b_j``: the exact gradient flow of eq. 9 restricted
    to one translation per part. At about an element's size (one relief length,
    :func:`~wast3d.registration.relief_length`) the elements move whole and still independently of each
    other, unlike a diffusion of the steps (``smoothing.passes``), whose reach spans several elements."""
    from .geometry import kmeans_from_groups
    from .registration import patch_frame

    if not size > 0:
        raise ValueError(f"style parts: need a part size > 0, got {size}")
    x = style.detach().double().cpu().numpy()
    if start is None:
        c, axes = patch_frame(style, up)
        cells = np.floor(((x - c) @ axes[:2].T) / size).astype(np.int64)
        _, cell = np.unique(cells, axis=0, return_inverse=True)
    else:
        if len(start) != len(x):
            raise ValueError(f"style parts: start has {len(start)} ids for {len(x)} Gaussians")
        _, cell = np.unique(start.detach().cpu().numpy(), return_inverse=True)
    feats = np.concatenate([x / size, colour * rgb.detach().double().cpu().numpy()], 1)
    return torch.from_numpy(kmeans_from_groups(feats, cell.reshape(-1), max_iter))


def dome_share(basins: torch.Tensor, part: torch.Tensor, min_size: int = 8) -> float:
    """basins [M] ids of the relief's basins (:func:`~wast3d.registration.relief_basins`), part [M] ids of
    another cut -> the median over basins of ``min_size`` Gaussians or more of the share of a basin's
    Gaussians in its largest part (1: no dome is cut; 1 where no basin is that large).

    Why (``parts.shape`` auto): k-means parts of one size cut elements larger than a part, or
    elements that colour does not tell apart; they then tear in the flow (``element_intact``: the
    trained stones 0.70 with k-means parts, 0.94 with the basins), while on the pebbles the k-means
    parts do better (trained pebbles on the lego: 0.84 against 0.74). The basins stand in for the
    elements where no labels exist: 24 style scenes of both (benchmarks/dome_share.py) read 0.48-0.60
    on the stones and 0.69-0.80 on the pebbles."""
    b, p = basins.long(), part.long()
    B, P = int(b.max()) + 1, int(p.max()) + 1
    counts = torch.bincount(b * P + p, minlength=B * P).view(B, P)  # Gaussians per (basin, part)
    size, big = counts.sum(1), counts.max(1).values
    keep = size >= min_size
    if not bool(keep.any()):
        return 1.0
    return float(np.median((big[keep].double() / size[keep].double()).numpy()))


def probe_parts(style: GaussianScene, up, length: float, cfg: StylizeConfig) -> torch.Tensor:
    """The parts that ``parts.shape: auto`` tests the domes with ([M] ids): k-means parts of
    ``parts.dome_probe`` relief lengths ``length``, started from cells, whatever ``parts.size`` and
    ``parts.start`` are (``parts.dome_cut`` was measured on them)."""
    return style_parts(style.means, style.rgb, up, cfg.parts.dome_probe * length, cfg.parts.colour)


def flow_parts(style: GaussianScene, up, cfg: StylizeConfig, sheet: bool = False) -> torch.Tensor | None:
    """The style's parts for the flow ([M] ids, :func:`style_parts`), or None where every Gaussian moves
    freely: ``parts.size`` 0, a style without relief, or a steep one (relief aspect above ``parts.max_aspect``:
    blades or strands longer than a part, which turning parts as one would tear: docs/measurements.md).
    ``sheet``: the style is a volume's element sheet (:mod:`wast3d.volume`), whose elements were laid out
    one by one: each is a part, whatever its relief. Says which, and why, in the log."""
    from .registration import relief, relief_basins

    if cfg.parts.size <= 0:
        return None
    if sheet:
        if style.element is None:
            raise ValueError("stylize: the style is an element sheet without element labels")
        part = torch.unique(style.element.long(), return_inverse=True)[1]
        log.info("stylize: the style is a volume's element sheet: its %d elements are the parts, each moving as "
                 "one (%s)", int(part.max()) + 1, cfg.parts.motion)
        return part
    try:
        rel = relief(style.means, up=up)
    except ValueError as e:
        log.warning("stylize: parts left out, every Gaussian moves freely (no relief: %s)", e)
        return None
    if rel.aspect > cfg.parts.max_aspect:
        log.info("stylize: parts left out, every Gaussian moves freely: the style's relief aspect %.3g is above "
                 "parts.max_aspect %.3g (elements longer than a relief length: blades, strands)", rel.aspect,
                 cfg.parts.max_aspect)
        return None
    size = cfg.parts.size * rel.length
    basins = relief_basins(style.means, up, rel.length) if cfg.parts.shape != "kmeans" or cfg.parts.start == "basins" else None
    use_basins, why = cfg.parts.shape == "relief", ""
    if cfg.parts.shape == "auto":  # decided before any k-means parts of the flow's size are made
        probe = cfg.parts.dome_probe * rel.length
        cut = dome_share(basins, probe_parts(style, up, rel.length, cfg))
        use_basins = cut < cfg.parts.dome_cut
        why = (f"parts of {probe:.4g} across {'would cut its domes' if use_basins else 'keep its domes'} (the median "
               f"keeps {cut:.3g} of its Gaussians in one, parts.dome_cut {cfg.parts.dome_cut:.3g})")
    if use_basins:
        part = basins
        how = f"the relief's basins (relief length {rel.length:.4g})" + (f": {why}" if why else "")
    else:
        part = style_parts(style.means, style.rgb, up, size, cfg.parts.colour,
                           start=basins if cfg.parts.start == "basins" else None)
        how = (f"k-means parts (position over {size:.4g}, colour x {cfg.parts.colour:.3g}) started from the "
               f"{cfg.parts.start}" + (f"; {why}" if why else ""))
    counts = torch.bincount(part)
    log.info("stylize: relief aspect %.3g <= %.3g: %d parts (median %d Gaussians) moving as one (%s): %s",
             rel.aspect, cfg.parts.max_aspect, len(counts), int(counts.median()), cfg.parts.motion, how)
    return part


def neighbour_distance(points: torch.Tensor, k: int, sample: int = 20000) -> float:
    """points [M, 3] -> the median over (at most ``sample``, evenly strided) points of the distance to
    their k-th nearest other point (inf where there are at most k points)."""
    x = points.detach().double().cpu()
    if len(x) <= k:
        return float("inf")
    d, _ = knn(x[::max(1, len(x) // sample)], x, k, exclude_self=True)
    return float(np.median(d[:, -1].numpy()))  # the mean of the middle two, as numpy (torch takes the lower)


def smoothing_reach(style: GaussianScene, up, cfg: StylizeConfig) -> float | None:
    """The displacement smoothing's neighbourhood radius in the style's units, ``smoothing.radius`` relief
    lengths L (:func:`~wast3d.registration.relief`), widened to :func:`neighbour_distance` d_k of the
    ``smoothing.neighbours``-th nearest where that is farther, up to ``smoothing.radius_max`` L:
    ``r = max(radius L, min(d_k, radius_max L))``. None (no limit: ``smoothing.k`` nearest,
    whatever their distance) when smoothing is off, ``smoothing.radius`` is 0 or the style has no relief.

    Why a length: the k nearest neighbours span a distance set by the style's density, so 16 passes
    over 16 neighbours reach about half a relief length on the demo's trained grass (1,000 Gaussians a
    cluster) and two on its trained wicker (50 a cluster), where they make each cluster one rigid plate.
    Why the floor in neighbours: a quarter L holds a median 27 of the trained grass's Gaussians but 5
    of the trained weave's, whose strands then tear (intact 0.58); its 16th nearest lies at 0.51 L,
    and at half an L they stay whole (0.89), while half an L on the grass moves it in plates that leave
    the guitar capture's shape (coarse 1.18 -> 1.67). Why the cap: on the fruit capture's sparse label
    the 16th nearest lies at 1.21 L, and there the clusters move as plates (coarse 4.69; 1.69 at the
    cap)."""
    from .registration import relief

    if not (cfg.smoothing.passes and cfg.smoothing.radius > 0):
        return None
    try:
        rel = relief(style.means, up=up)
    except ValueError as e:
        log.warning("stylize: displacement smoothing over the %d nearest, at any distance (no relief: %s)", cfg.smoothing.k, e)
        return None
    L, k = rel.length, cfg.smoothing.neighbours
    d = neighbour_distance(style.means, k) if k else 0.0
    w = max(cfg.smoothing.radius * L, min(d, cfg.smoothing.radius_max * L))
    why = "" if not k else (f"; the {k}-th nearest at {d / L:.3g} L" if w <= cfg.smoothing.radius * L else
                            f": this sparse style's {k}-th nearest lies at {d / L:.3g} L, farther than smoothing.radius "
                            f"{cfg.smoothing.radius:g}; smoothing.radius_max {cfg.smoothing.radius_max:g}")
    log.info("stylize: displacement smoothing within %.4g (%.3g relief lengths of %.4g%s), %d passes", w, w / L, L, why,
             cfg.smoothing.passes)
    return w


def part_centroids(v: torch.Tensor, part: torch.Tensor, w: torch.Tensor | None = None) -> torch.Tensor:
    """v [M, D] per-Gaussian values, part [M] ids (0..P-1), w [M] masses (None: equal) -> [P, D] each
    part's w-weighted mean."""
    P = int(part.max()) + 1 if len(part) else 0
    w = torch.ones(len(v), dtype=v.dtype, device=v.device) if w is None else w.to(v)
    num = torch.zeros(P, v.shape[1], dtype=v.dtype, device=v.device).index_add_(0, part, v * w[:, None])
    den = torch.zeros(P, dtype=v.dtype, device=v.device).index_add_(0, part, w)
    return num / den.clamp_min(torch.finfo(v.dtype).tiny)[:, None]


def part_means(g: torch.Tensor, part: torch.Tensor, w: torch.Tensor | None = None) -> torch.Tensor:
    """g [M, D] per-Gaussian steps, part [M] ids, w [M] masses -> [M, D] each Gaussian's part's
    w-weighted mean step (:func:`style_parts`)."""
    return part_centroids(g, part, w)[part]


def part_rigid_steps(y: torch.Tensor, step: torch.Tensor, part: torch.Tensor, w: torch.Tensor | None = None) -> torch.Tensor:
    """y [M, 3] positions, step [M, 3] each Gaussian's displacement, part [M] ids, w [M] masses -> [M, 3]
    the displacement of each part's best rigid motion from y to y + step (w-weighted Kabsch:
    ``y' = R (y - c_y) + c_t``, c the parts' weighted centroids): a part turns to follow a curved content
    as well as moving, and stays whole."""
    from .geometry import kabsch

    t = y + step
    cy, ct = part_centroids(y, part, w), part_centroids(t, part, w)
    g, u = y - cy[part], t - ct[part]
    w = torch.ones(len(y), dtype=y.dtype, device=y.device) if w is None else w.to(y)
    H = torch.zeros(len(cy), 3, 3, dtype=torch.float64, device=y.device).index_add_(
        0, part, (w[:, None, None] * g[:, :, None] * u[:, None, :]).double())
    R = kabsch(H).to(y)
    return torch.einsum("mij,mj->mi", R[part], g) + ct[part] - y


def stylize_cluster(x_pos: torch.Tensor, x_rgb: torch.Tensor, y_pos: torch.Tensor, y_rgb: torch.Tensor,
                    cfg: StylizeConfig) -> ClusterResult:
    """One term of eq. 9 alone (the per-pair path). x_*: content cluster in the style frame [N,3]; y_*:
    its style Gaussians [M,3]."""
    return stylize_clusters([ClusterPair(x_pos, x_rgb, y_pos, y_rgb, cfg.sinkhorn.blur)], cfg)[0]


class _Descent:
    """Plain gradient descent, ``p <- p - lr * p.grad`` per parameter group: torch.optim.SGD's step at its
    defaults (no momentum, no weight decay), without its first use importing torch._dynamo (about 2 s
    of every stylize process)."""

    def __init__(self, groups: list[dict]):
        self.param_groups = groups

    def zero_grad(self, set_to_none: bool = True):
        for g in self.param_groups:
            for p in g["params"]:
                p.grad = None

    @torch.no_grad()
    def step(self):
        for g in self.param_groups:
            for p in g["params"]:
                if p.grad is not None:
                    p.add_(p.grad, alpha=-g["lr"])


class Leaders(NamedTuple):
    """The packed style rows a capped transport sees (:func:`transport_leaders`): ``rows`` [C'] the drawn
    rows, ``offsets`` [K+1] their CSR offsets, ``mass`` [C'] each one's mass (its Voronoi cell's)."""

    rows: torch.Tensor
    offsets: torch.Tensor
    mass: torch.Tensor


def transport_leaders(ys: list[torch.Tensor], masses: torch.Tensor | None, cap: int) -> Leaders | None:
    """Each cluster's style Gaussians cut to at most ``cap`` in the transport (None where no cluster has
    more). ys: the clusters' normalized positions [M_k, 3]; masses: packed [sum M_k], each cluster's
    summing to 1 (None: uniform).

    Beyond the cap a seeded uniform draw of ``cap`` rows is transported, each with the mass of the rows
    nearest it at the start (:func:`cell_masses`): a quantization of the whole cluster's distribution
    (eq. 9 on the same measure, fewer atoms). Every row then moves by the gradient of the solved
    potentials at its own position (:func:`wast3d.sinkhorn.grad_y_at`), so the flow stays smooth at the
    blur's scale (30 % of the cluster's radius) and no cell moves as a block (error against run time:
    benchmarks/transport_caps.py)."""
    sizes = [len(y) for y in ys]
    if cap <= 0 or max(sizes, default=0) <= cap:
        return None
    g = torch.Generator().manual_seed(0)
    rows, mass, start = [], [], 0
    for y in ys:
        m = len(y)
        w = None if masses is None else masses[start:start + m]
        if m <= cap:
            rows.append(torch.arange(start, start + m))
            mass.append(torch.full((m,), 1.0 / m, dtype=torch.float64) if w is None else w.detach().double().cpu())
        else:
            pick = torch.randperm(m, generator=g)[:cap].sort().values
            rows.append(pick + start)
            mass.append(cell_masses(y[pick].double(), y, w))
        start += m
    counts = torch.tensor([len(r) for r in rows])
    log.info("stylize: each cluster's transport sees at most %d of its style Gaussians (%d of %d in all)", cap,
             int(counts.sum()), start)
    return Leaders(torch.cat(rows), torch.cat([counts.new_zeros(1), counts.cumsum(0)]), torch.cat(mass))


def stylize_clusters(pairs: list[ClusterPair], cfg: StylizeConfig, progress: bool = False,
                     up: torch.Tensor | None = None) -> list[ClusterResult]:
    """Terms of eq. 9 optimized together: one packed (ragged) Sinkhorn solve per step over all of them
    (:func:`wast3d.sinkhorn.sinkhorn_batched`), each cluster normalized by :func:`normalize_pair`.

    The terms are independent and both optimizers act per coordinate, so this is the same computation
    as one :func:`stylize_cluster` per pair, with 4 kernel calls per Sinkhorn iteration instead of 4 per
    cluster (what makes 400 clusters cheap on a GPU, and keeps both cores busy on small clusters)."""
    from tqdm import tqdm

    from .sinkhorn import grad_y_at, segment_ids, sinkhorn_batched

    t0 = time.perf_counter()
    dt = torch.float64 if cfg.dtype == "float64" else torch.float32
    dev = resolve_device(cfg.device)
    w = cfg.colour_weight
    xs, ys, y0cs, norms = [], [], [], []
    for pr in pairs:
        c, r = normalize_pair(pr.x_pos.double(), pr.y_pos.double())
        norms.append((c, r))
        xn = ((pr.x_pos.double() - c) / r).to(dev, dt)
        xs.append(torch.cat([xn, w * colour_features(pr.x_rgb, cfg.features).to(dev, dt)], 1))
        ys.append(((pr.y_pos.double() - c) / r).to(dev, dt))
        y0cs.append(colour_features(pr.y_rgb, cfg.features).to(dev, dt))
    n = torch.tensor([len(t) for t in xs])
    m = torch.tensor([len(t) for t in ys])
    x_off, y_off = torch.cat([n.new_zeros(1), n.cumsum(0)]), torch.cat([m.new_zeros(1), m.cumsum(0)])
    xf, y0c = torch.cat(xs), torch.cat(y0cs)
    yid = segment_ids(y_off).to(dev)
    a, b = packed_masses([pr.x_w for pr in pairs], n, dev, dt), packed_masses([pr.y_w for pr in pairs], m, dev, dt)
    blur = torch.tensor([pr.blur for pr in pairs], dtype=torch.float64)
    lead = transport_leaders(ys, b, cfg.style_points) if cfg.loss == "sinkhorn" else None
    if lead is not None:  # the transport on the drawn rows; every row's gradient from its potentials
        rows, y_off_t, b_t = lead.rows.to(dev), lead.offsets, lead.mass.to(dev, dt)
        b_all = (1.0 / m.to(dev, dt))[yid] if b is None else b
    Y = torch.cat(ys).clone().requires_grad_(True)
    dC = torch.zeros_like(y0c).requires_grad_(True)
    groups = [{"params": [Y], "lr": cfg.lr}]
    if dC.shape[1]:
        groups.append({"params": [dC], "lr": cfg.lr_colour})
    # "adam": per-coordinate normalized steps of ~lr whatever the gradient's size, so points the
    # transport barely pulls still move by ~lr per step (noise on the style's surfaces). "flow": the
    # Sinkhorn gradient flow, y_j <- y_j - lr * M * dS/dy_j = y_j - lr * (y_j - T(y_j)) with T the
    # (debiased, blurred) transport target: a displacement field smooth at the scale gamma, so that
    # the style's elements move as wholes
    opt = torch.optim.Adam(groups) if cfg.optimizer == "adam" else _Descent(groups)
    # the flow's step is the gradient over each row's mass: 1 / b_j (M of its cluster when uniform)
    flow = (m.to(dev, dt)[yid] if b is None else 1.0 / b)[:, None] if cfg.optimizer == "flow" else None
    losses: list[list[float]] = [[] for _ in pairs]
    pot = None
    araps = [_ArapState(yn, cfg.arap_k) for yn in ys] if cfg.loss == "arap" else None
    radii = [None if pr.y_reach is None else pr.y_reach / r for pr, (_, r) in zip(pairs, norms)]
    nb = neighbour_graph(ys, cfg.smoothing.k, radii).to(dev) if cfg.smoothing.passes else None
    part = packed_parts([pr.y_part for pr in pairs], m)
    part = None if part is None else part.to(dev)
    if nb is not None and cfg.smoothing.axis == "up":
        if up is None:
            raise ValueError("stylize: smoothing.axis up needs the style's up direction")
        up = torch.as_tensor(up, dtype=torch.float64)
        up = (up / up.norm()).to(dev, dt)
    else:
        up = None
    steps = tqdm(range(cfg.iterations), desc=f"stylize steps ({len(pairs)} clusters)", mininterval=2.0,
                 disable=not progress)
    for it in steps:
        opt.zero_grad(set_to_none=True)
        yf = torch.cat([Y, w * (y0c + dC)], 1)
        if araps is None:
            yt, bt, ot = (yf.detach()[rows], b_t, y_off_t) if lead is not None else (yf.detach(), b, y_off)
            res = sinkhorn_batched(xf, yt, x_off, ot, cfg.sinkhorn, a=a, b=bt, blur=blur,
                                   init=pot if cfg.warm_start else None, x_fixed=True)
            pot = res.potentials
            gy = res.grad_y if lead is None else \
                grad_y_at(yf.detach(), y_off, xf, yt, res, cfg.sinkhorn, a=a, b=b_t) * b_all[:, None]
            Y.grad = gy[:, :3].contiguous()
            if dC.shape[1]:
                dC.grad = (w * gy[:, 3:]).contiguous()
            vals = res.value.tolist()
        else:
            terms = [arap.loss(xf[x_off[k]:x_off[k + 1]], yf[y_off[k]:y_off[k + 1]], Y[y_off[k]:y_off[k + 1]],
                               cfg.arap_weight) for k, arap in enumerate(araps)]
            torch.stack(terms).sum().backward()
            vals = [float(t.detach()) for t in terms]
        for k, v in enumerate(vals):
            losses[k].append(v)
        if flow is not None:
            Y.grad.mul_(flow)
            if dC.grad is not None:
                dC.grad.mul_(flow)
        if nb is not None:
            Y.grad = smooth_displacements(Y.grad, nb, cfg.smoothing.passes, up)
        if part is not None and cfg.parts.motion == "rigid":  # the optimizer's step is -lr * grad
            Y.grad = -part_rigid_steps(Y.detach(), -cfg.lr * Y.grad, part, b) / cfg.lr
        elif part is not None:
            Y.grad = part_means(Y.grad, part, b)
        bad = ~torch.isfinite(Y.grad).all(1)
        if dC.grad is not None:
            bad |= ~torch.isfinite(dC.grad).all(1)
        if bad.any():
            k = int(yid[bad.nonzero()[0, 0]])
            raise FloatingPointError(f"stylize: non-finite gradient at iteration {it} (cluster {k} of the batch)")
        opt.step()
    seconds = time.perf_counter() - t0
    work = (n * m + m * m).double()
    out = []
    for k, (pr, (c, r)) in enumerate(zip(pairs, norms)):
        sl = slice(int(y_off[k]), int(y_off[k + 1]))
        pos = Y.detach()[sl].cpu().double() * r + c
        out.append(ClusterResult(pos.to(pr.y_pos.dtype), dC.detach()[sl].cpu().to(pr.y_rgb.dtype), losses[k],
                                 seconds * float(work[k] / work.sum())))
    return out


def packed_masses(ws: list[torch.Tensor | None], sizes: torch.Tensor, dev, dt) -> torch.Tensor | None:
    """Per-problem masses [sum sizes], each problem's normalized to 1; None when every one is uniform."""
    if all(w is None for w in ws):
        return None
    parts = [torch.full((int(k),), 1.0 / int(k), dtype=torch.float64) if w is None else w.double() / w.double().sum()
             for w, k in zip(ws, sizes)]
    return torch.cat(parts).to(dev, dt)


def packed_parts(parts: list[torch.Tensor | None], sizes: torch.Tensor) -> torch.Tensor | None:
    """Per-problem part ids -> [sum sizes] ids unique across problems (a problem without parts: one part
    per row); None when no problem has parts."""
    if all(p is None for p in parts):
        return None
    out, off = [], 0
    for p, k in zip(parts, sizes.tolist()):
        ids = torch.arange(k) if p is None else torch.unique(p, return_inverse=True)[1].reshape(-1)
        out.append(ids + off)
        off += int(ids.max()) + 1 if k else 0
    return torch.cat(out)


def stylize_in_batches(pairs: list[ClusterPair], cfg: StylizeConfig, progress: bool = False,
                       up: torch.Tensor | None = None) -> list[ClusterResult]:
    """:func:`stylize_clusters` over groups of ``cfg.batch`` pairs (0: all in one group)."""
    from tqdm import tqdm

    size = cfg.batch or len(pairs)
    batches = range(0, len(pairs), size)
    results: list[ClusterResult] = []
    for b0 in tqdm(batches, desc="stylize cluster batches", disable=not progress or len(batches) == 1):
        results += stylize_clusters(pairs[b0:b0 + size], cfg, progress=progress and len(batches) == 1, up=up)
    return results


class _ArapState:
    """Chamfer + as-rigid-as-possible energy over a fixed kNN graph of the initial style positions."""

    def __init__(self, y0: torch.Tensor, k: int):
        self.y0 = y0.detach()
        kk = min(k, max(len(y0) - 1, 1))
        _, self.nb = knn(y0, y0, kk, exclude_self=len(y0) > 1)
        self.e0 = self.y0[self.nb] - self.y0[:, None, :]  # [M, k, 3]

    def loss(self, xf, yf, Y, weight):
        d = torch.cdist(yf, xf)
        chamfer = d.min(1).values.square().mean() + d.min(0).values.square().mean()
        e = Y[self.nb] - Y[:, None, :]
        with torch.no_grad():
            Rj = kabsch((self.e0[:, :, :, None] * e.detach()[:, :, None, :]).sum(1))
        rigid = (e - torch.einsum("mij,mkj->mki", Rj, self.e0)).square().sum(-1).mean()
        return chamfer + weight * rigid


def apply_colour_offset(scene: GaussianScene, offset: torch.Tensor) -> GaussianScene:
    """Add a luminance [M,1] or RGB [M,3] offset to the DC colour (see module docstring)."""
    if offset.shape[1] == 0:
        return scene
    delta = offset.expand(-1, 3) if offset.shape[1] == 1 else offset
    return replace(scene, sh_dc=scene.sh_dc + delta.to(scene.sh_dc) / SH_C0)


@dataclass
class Stylized:
    """What :func:`stylize` returns. ``scene``: the stylized Gaussians in the content frame [M];
    ``labels`` [M]: each one's cluster; ``curves``: per cluster solved, its loss per step; ``seconds``:
    per cluster solved, its time; ``before_means`` [M, 3]: each Gaussian's position before the
    optimization, mapped back to the content frame (the scale readjustment's reference); ``source`` [M]:
    the style Gaussian each one is a copy of (its index in the style scene)."""

    scene: GaussianScene
    labels: torch.Tensor
    curves: list[list[float]]
    seconds: list[float]
    before_means: torch.Tensor
    source: torch.Tensor


def own_copies(nearest: torch.Tensor, cluster: int, part: torch.Tensor | None, share: float) -> torch.Tensor:
    """``stylize.trim`` for one cluster: nearest [S] the cluster of each selected Gaussian's nearest content
    point (registered back into the content's frame), part [S] its flow part (None: each Gaussian its own)
    -> [S] bool, the Gaussians of the part copies with at least ``share`` of their Gaussians over the
    cluster's own content."""
    own = (nearest == cluster).double()
    if part is None:
        return own >= share
    ids, inv = torch.unique(part, return_inverse=True)
    frac = torch.zeros(len(ids), dtype=own.dtype).index_add_(0, inv, own) / torch.bincount(inv).to(own.dtype)
    return frac[inv] >= share


@dataclass(frozen=True)
class PartCopies:
    """One cluster's selection split by ``stylize.complete`` / ``drop`` (sorted style indices): ``whole``
    the parts it holds at least ``complete`` of, each whole; ``kept`` the copies left as selected;
    ``cut`` the copies holding less than ``drop``."""

    whole: torch.Tensor
    kept: torch.Tensor
    cut: torch.Tensor


def part_copies(sel: torch.Tensor, part: torch.Tensor, part_size: torch.Tensor, complete: float,
                drop: float, eligible: torch.Tensor | None = None) -> PartCopies:
    """sel [S] one cluster's selected style indices, part [M] each style Gaussian's flow part, part_size [P]
    Gaussians per part -> :class:`PartCopies` (``complete`` 0: nothing completed; ``drop`` 0: nothing cut;
    eligible [P] bool: the parts that may be completed, default all)."""
    ids, held = torch.unique(part[sel], return_counts=True)
    share = held.double() / part_size[ids].double()
    whole = ids[(share >= complete) & (True if eligible is None else eligible[ids])] if complete > 0 else ids[:0]
    cut = ids[share < drop]
    return PartCopies(torch.nonzero(torch.isin(part, whole)).squeeze(1),
                      sel[~torch.isin(part[sel], torch.cat([whole, cut]))], sel[torch.isin(part[sel], cut)])


def completed_selection(selection, part: torch.Tensor, cfg: "StylizeConfig", height: torch.Tensor) -> list:
    """``stylize.complete`` / ``drop`` over all clusters -> per cluster its style indices (sorted), or None
    where left as selected: a thinned cluster (a random subset of its footprint), or one none of whose
    copies is whole or kept. height [M]: each style Gaussian's height along its up (complete_height)."""
    size = torch.bincount(part)
    eligible = None
    if cfg.copies.complete_height > 0:
        mean_h = torch.zeros(len(size), dtype=torch.float64).index_add_(0, part, height.double()) / size.double()
        eligible = mean_h > torch.quantile(mean_h, cfg.copies.complete_height)
    out, added, cut, thinned = [None] * (len(selection.offsets) - 1), 0, 0, 0
    for i in range(len(out)):
        sel = selection.indices[selection.offsets[i]:selection.offsets[i + 1]]
        if len(sel) == 0 or float(selection.log_gain[i]) != 0.0:
            thinned += len(sel) > 0
            continue
        c = part_copies(sel, part, size, cfg.copies.complete, cfg.copies.drop, eligible)
        new = torch.sort(torch.cat([c.whole, c.kept]))[0]
        if len(new):
            added += len(c.whole) - (len(sel) - len(c.kept) - len(c.cut))  # the whole parts' Gaussians not selected
            cut += len(c.cut)
            out[i] = new
    log.info("stylize: complete %.2f added %d Gaussians to part copies holding that share of their part, drop %.2f "
             "left out %d of copies holding less%s", cfg.copies.complete, added, cfg.copies.drop, cut,
             f"; {thinned} thinned clusters left as selected" if thinned else "")
    return out


def cell_masses(drawn: torch.Tensor, points: torch.Tensor, w: torch.Tensor | None = None) -> torch.Tensor:
    """drawn [N', 3] of points [N, 3] (masses w [N], None: uniform) -> [N'] each drawn point's mass: the
    masses of the points nearest it (its Voronoi cell), normalized to sum 1: the draw as a quantization
    of the whole cloud rather than a sample of it."""
    from .geometry import kdtree

    near = torch.from_numpy(kdtree(drawn.double().cpu().numpy()).query(points.double().cpu().numpy())[1]).long()
    w = torch.ones(len(points), dtype=torch.float64) if w is None else w.detach().double().cpu()
    mass = torch.zeros(len(drawn), dtype=torch.float64).index_add_(0, near, w)
    return (mass / mass.sum()).to(drawn.dtype)


def transport_points(labels: torch.Tensor, cap: int) -> torch.Tensor:
    """[N] bool: the content points each cluster's transport sees, at most ``cap`` per cluster (a seeded
    uniform draw, :func:`~wast3d.geometry.cap_per_label`; every point where ``cap`` is 0 or no cluster is
    larger). The divergence's target is the cluster's surface, and the flow moves the style at the scale
    of gamma (30 % of the cluster's radius): a few thousand samples of a patch stand for it as well as
    more, while the cost grows as content points times style Gaussians."""
    keep = torch.ones(len(labels), dtype=torch.bool)
    if cap <= 0 or len(labels) == 0 or int(torch.bincount(labels.long()).max()) <= cap:
        return keep
    from .geometry import cap_per_label

    keep[:] = False
    keep[cap_per_label(labels, cap, torch.Generator().manual_seed(0))] = True
    log.info("stylize: each cluster's transport sees at most %d of its content points (%d of %d in all)", cap,
             int(keep.sum()), len(labels))
    return keep


def stylize(content: GaussianScene, labels: torch.Tensor, style: GaussianScene, reg, selection,
            cfg: StylizeConfig, progress: bool = True, sheet: bool = False) -> Stylized:
    """Run eq. 9 over all clusters (:class:`Stylized`); ``selection``: a :class:`~wast3d.selection.Selection`
    (each cluster's style Gaussians and their scale gain); ``sheet``: the style is a volume's element sheet
    (:func:`flow_parts`)."""
    offsets, indices = selection.offsets, selection.indices
    K = len(offsets) - 1
    cfg = resolved_copies(cfg, sheet)
    cm = content.means.double()
    mapped = reg.apply(cm, labels).float()
    c_rgb = content.rgb.float()
    c_mass, s_mass = transport_masses(content, style, cfg.masses)
    part = flow_parts(style, reg.style_up.tolist(), cfg, sheet)
    if part is not None and cfg.smoothing.passes and not cfg.smoothing.with_parts:
        log.info("stylize: displacement smoothing left out: the parts keep the elements whole (smoothing.with_parts false)")
        cfg = replace(cfg, smoothing=replace(cfg.smoothing, passes=0))
    reach = smoothing_reach(style, reg.style_up.tolist(), cfg)
    asked = cfg.copies.complete > 0 or cfg.copies.drop > 0
    completing = asked and part is not None
    if asked and part is None:
        log.info("stylize: complete %.2f and drop %.2f left out: no parts, so no part copies", cfg.copies.complete, cfg.copies.drop)
    completed = [None] * K
    if completing:
        completed = completed_selection(selection, part, cfg, style.means.double() @ reg.style_up.double())
    tree = None
    if cfg.copies.trim > 0:
        from .geometry import kdtree

        tree, trimmed, total = kdtree(cm.numpy()), 0, 0
    in_transport = transport_points(labels, cfg.content_points)
    todo, pairs = [], []
    for i in range(K):
        sel = indices[offsets[i]:offsets[i + 1]]
        m = (labels == i) & in_transport
        if len(sel) == 0 or not bool(m.any()):
            log.warning("stylize: cluster %d is empty (content %d, style %d); skipped", i, int(m.sum()), len(sel))
            continue
        if completed[i] is not None:
            sel = completed[i]
        if tree is not None:
            back = reg.inverse(style.means[sel].double(), torch.full((len(sel),), i, dtype=torch.long))
            nearest = labels.long()[torch.from_numpy(tree.query(back.numpy())[1])]
            keep = own_copies(nearest, i, None if part is None else part[sel], cfg.copies.trim)
            total += len(sel)
            if bool(keep.any()):  # a cluster none of whose copies is its own keeps them all
                trimmed += int((~keep).sum())
                sel = sel[keep]
        sub = style.subset(sel)
        if float(selection.log_gain[i]) != 0.0:  # a thinned cluster: its Gaussians enlarged (selection.thin)
            sub = replace(sub, log_scales=sub.log_scales + float(selection.log_gain[i]))
        todo.append((i, sel, sub))
        x_w = None if c_mass is None else c_mass[m]
        if not bool(in_transport[labels == i].all()):  # a capped cluster: the drawn points carry the others' mass
            x_w = cell_masses(mapped[m], mapped[labels == i], None if c_mass is None else c_mass[labels == i])
        pairs.append(ClusterPair(mapped[m], c_rgb[m], sub.means.float(), sub.rgb.float(),
                                 cfg.sinkhorn.blur,
                                 x_w=x_w, y_w=None if s_mass is None else s_mass[sel],
                                 y_part=None if part is None else part[sel], y_reach=reach))
    if not pairs:
        raise ValueError("stylize: no non-empty cluster")
    if tree is not None:
        log.info("stylize: trim %.2f dropped %d of %d selected Gaussians (%.1f %%): part copies mostly over the "
                 "neighbouring clusters' content", cfg.copies.trim, trimmed, total, 100.0 * trimmed / max(total, 1))
    else:
        log.info("stylize: trim 0: every selected Gaussian flows, the neighbours' overlapping copies included")
    results = stylize_in_batches(pairs, cfg, progress, up=reg.style_up)
    parts, before_parts, labs, curves, secs = [], [], [], [], []
    for (i, sel, sub), res in zip(todo, results):
        if res.losses and cfg.loss == "sinkhorn" and min(res.losses) < -1e-6 * abs(res.losses[0]):
            log.warning("stylize: cluster %d: divergence went negative (%.3g; first %.3g): the solve is not "
                        "converged (raise sinkhorn.max_iters or lower sinkhorn.tol)", i, min(res.losses), res.losses[0])
        curves.append(res.losses)
        secs.append(res.seconds)
        lab = torch.full((len(sel),), i, dtype=torch.long)
        before_parts.append(reg.inverse(sub.means.double(), lab))
        out = apply_colour_offset(replace(sub, means=res.positions.to(sub.dtype)), res.colour_offset)
        parts.append(out.transform(rotation=reg.R[i].T.to(out.dtype), translation=reg.t[i].to(out.dtype),
                                   scale=(1.0 / reg.s[i]).to(out.dtype)))
        labs.append(lab)
    return Stylized(GaussianScene.concat(parts), torch.cat(labs), curves, secs, torch.cat(before_parts).float(),
                    torch.cat([sel.long() for _, sel, _ in todo]))

"""Styles that are objects, not patches: the form test and the element sheet (stage 2 for a style).

Every later stage reads a style as a **patch**: a ground with elements on it, seen from above, its relief
a height field over one plane (registration's relief length and basins, selection's footprint, the
parts' domes). A bouquet, a pine cone or a captured object is a **volume**: seen from every side, no
ground, no top surface. It is read as its elements laid side by side on a plane, each turned so that
the side it shows outwards faces up (:func:`element_sheet`); the sheet is a patch, and the stages after
this one take it as they take any patch: a content cluster is filled with whole flowers, not with a
slice through the bouquet.

**Form** (:func:`style_form`). A patch is flat: its relief is a small part of its width. With e_1 >= e_2
>= e_3 the extents of the style's Gaussian centres along their principal axes (2-98 % quantile ranges),

    thickness = e_3 / e_2,        patch if thickness < FLAT (0.35), else volume.

e_2, not e_1: a long strip of grass is still a patch, a pine cone (e_2 = e_3) is not. Measured where the
style stage tests it (after floaters, haze and outliers; docs/measurements.md#styles-that-are-objects):
the patches 0.04-0.21 (procedural and trained pebbles, grass, weave, stones; the fruit capture 0.19),
the bouquet 0.98, the pine cone 1.00, the captured guitar 0.59.

**Sheet** (:func:`element_sheet`). Each element j (its Gaussians share a label > 0) has a centroid c_j
and an axis a_j: its least-variance axis (a flower's face, a cone scale's plate), signed to point away
from the style's centre o (a_j . (c_j - o) > 0). R_j is the shortest rotation taking a_j to +z. The
element is turned by R_j, its base (the 5 % quantile of its heights) set on z = 0 and its centre on the
next node of a hexagonal grid of pitch ``PITCH`` x the median element diameter (< sqrt(3)/2, so that
neighbouring elements overlap and no gap shows the content through the sheet). Gaussians of label 0 (a
bouquet's stems and leaves, a cone's core: what holds the elements, hidden or thin from outside) are
not on the sheet; the report says how many.

**Without labels** (a captured object, :func:`volume_pieces`) the elements are pieces of the volume:
k-means on position over ``size`` = e_2 / PIECES_ACROSS (4) and colour, started from the occupied cells
of a grid of that size; every Gaussian is in one. Against the procedural volumes' labels (30k Gaussians,
benchmarks/style_forms.py), the median piece is all of one element (purity 1.0) and the median element
keeps 85 % (bouquet) and 99.6 % (cone) of its Gaussians in one piece; 3 across merges elements (purity
0.66 and 0.72), 6 cuts them (0.54 and 0.38 kept in one piece).
A piece of a smooth object is a patch of its surface, so a capture's sheet is its surface cut into
tiles, each laid flat.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

log = logging.getLogger(__name__)

FORMS = ("auto", "patch", "volume")
FLAT = 0.35  # thickness below which a style is a patch
PITCH = 0.8  # grid pitch of the sheet, in median element diameters
BASE_Q = 0.05  # an element's base: this quantile of its heights once turned
PIECES_ACROSS = 4  # label-free elements: a volume's middle extent over this (tests/test_volume.py)
PIECE_COLOUR = 1.0  # label-free elements: the colour's weight beside position / size
PROCEDURAL_VOLUMES = ("bouquet", "pinecone")  # the generator's styles that are volumes (wast3d.procedural)


@dataclass(frozen=True)
class Form:
    """How a style is read: ``form`` (patch or volume), its ``thickness`` (module docstring) and why."""

    form: str
    thickness: float
    reason: str


def extents(points) -> np.ndarray:
    """points [M, 3] -> e_1 >= e_2 >= e_3 [3]: the 2-98 % quantile ranges along the principal axes."""
    x = np.asarray(points, dtype=np.float64)
    x = x - x.mean(0)
    y = x @ np.linalg.svd(x, full_matrices=False)[2].T
    return np.quantile(y, 0.98, axis=0) - np.quantile(y, 0.02, axis=0)


def thickness(points) -> float:
    """points [M, 3] -> e_3 / e_2 of the module docstring (:func:`extents`)."""
    if len(points) < 4:
        raise ValueError(f"style form: {len(points)} Gaussians are too few to tell a patch from a volume")
    ext = extents(points)
    return float(ext[2] / max(ext[1], 1e-12))


def style_form(points, asked: str = "auto") -> Form:
    """The form a style is read as: ``asked`` unless it is ``auto``, then by :func:`thickness`."""
    if asked not in FORMS:
        raise ValueError(f"style form must be one of {', '.join(FORMS)}, got '{asked}'")
    t = thickness(points)
    if asked != "auto":
        return Form(asked, t, f"asked in the config (thickness {t:.2f})")
    if t < FLAT:
        return Form("patch", t, f"flat: thickness {t:.2f} < {FLAT} (its relief is a small part of its width)")
    return Form("volume", t, f"thickness {t:.2f} >= {FLAT}: an object seen from every side, no ground")


def _turn_to_z(a: np.ndarray) -> np.ndarray:
    """The shortest rotation [3, 3] taking the unit vector a [3] to +z (a half turn about x for -z)."""
    z = np.array([0.0, 0.0, 1.0])
    v, c = np.cross(a, z), float(a @ z)
    if c < -1 + 1e-9:
        return np.diag([1.0, -1.0, -1.0])
    V = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + V + V @ V / (1.0 + c)


@dataclass(frozen=True)
class Elements:
    """The elements of a labelled style: ``ids`` [E] (labels > 0), ``centroids`` [E, 3], ``axes`` [E, 3]
    (unit, outward) and the ``members`` of each (indices into the scene)."""

    ids: np.ndarray
    centroids: np.ndarray
    axes: np.ndarray
    members: list


def element_axes(means, element) -> Elements:
    """means [M, 3], element [M] (0: no element) -> :class:`Elements` (module docstring); elements of
    fewer than 3 Gaussians have no axis and are left out."""
    x = np.asarray(means, dtype=np.float64)
    lab = np.asarray(element).astype(np.int64)
    o = x.mean(0)
    ids, cents, axes, members = [], [], [], []
    order = np.argsort(lab, kind="stable")
    uniq, start = np.unique(lab[order], return_index=True)
    for u, lo, hi in zip(uniq, start, np.append(start[1:], len(order))):
        if u <= 0 or hi - lo < 3:
            continue
        idx = order[lo:hi]
        c = x[idx].mean(0)
        a = np.linalg.svd(x[idx] - c, full_matrices=False)[2][2]
        if a @ (c - o) < 0:
            a = -a
        ids.append(u), cents.append(c), axes.append(a), members.append(idx)
    return Elements(np.asarray(ids, np.int64), np.asarray(cents).reshape(-1, 3), np.asarray(axes).reshape(-1, 3),
                    members)


def volume_pieces(means, rgb) -> np.ndarray:
    """Label-free elements of a volume: means [M, 3], rgb [M, 3] -> [M] piece ids from 1 (module docstring):
    k-means on ``[x / size, PIECE_COLOUR rgb]`` started from the occupied cells of a grid of ``size`` =
    e_2 / PIECES_ACROSS."""
    from .geometry import kmeans_from_groups

    x = np.asarray(means, dtype=np.float64)
    size = piece_size(x)
    _, cell = np.unique(np.floor((x - x.min(0)) / size).astype(np.int64), axis=0, return_inverse=True)
    feats = np.concatenate([x / size, PIECE_COLOUR * np.asarray(rgb, dtype=np.float64)], 1)
    return kmeans_from_groups(feats, cell.reshape(-1), max_iter=20) + 1


def piece_size(points) -> float:
    """The label-free element size of a volume: its middle extent e_2 (:func:`extents`) over PIECES_ACROSS."""
    return float(extents(points)[1] / PIECES_ACROSS)


def element_sheet(scene, seed: int = 0):
    """A labelled volume style (:class:`~wast3d.gaussians.GaussianScene` with ``element``) -> (the sheet,
    a GaussianScene of its elements laid out as the module docstring says, labels kept; report dict)."""
    import torch

    from .gaussians import GaussianScene

    if scene.element is None:
        raise ValueError("element sheet: the style has no element labels")
    el = element_axes(scene.means.detach().double().numpy(), scene.element.numpy())
    if len(el.ids) == 0:
        raise ValueError("element sheet: the style has no element of 3 Gaussians or more")
    turned, diam = [], []
    for a, idx in zip(el.axes, el.members):
        R = torch.from_numpy(_turn_to_z(a))
        sub = scene.subset(torch.from_numpy(idx)).transform(rotation=R)
        xyz = sub.means.detach().double().numpy()
        centre = np.array([*np.median(xyz[:, :2], 0), np.quantile(xyz[:, 2], BASE_Q)])
        r = np.linalg.norm(xyz[:, :2] - centre[:2], axis=1)
        diam.append(2.0 * float(np.quantile(r, 0.9)))
        turned.append((sub, centre))
    pitch = PITCH * float(np.median(diam))
    cols = math.ceil(math.sqrt(len(turned)))
    slots = np.random.default_rng(seed).permutation(len(turned))
    parts = []
    for (sub, centre), k in zip(turned, slots):
        row, col = divmod(int(k), cols)
        node = np.array([(col + 0.5 * (row % 2)) * pitch, row * pitch * math.sqrt(3) / 2, 0.0])
        parts.append(sub.transform(translation=torch.from_numpy(node - centre)))
    sheet = GaussianScene.concat(parts)
    dropped = int((scene.element <= 0).sum())
    report = {"elements": len(parts), "element_diameter_median": float(np.median(diam)), "pitch": pitch,
              "grid_columns": cols, "gaussians": len(sheet), "left_off_unlabelled": dropped,
              "left_off_small_elements": len(scene) - len(sheet) - dropped}
    log.info("style form volume: %d elements (median diameter %.4g) laid side by side, outer side up, on a "
             "hexagonal grid of pitch %.4g, %d columns; %d Gaussians of no element (what holds the elements: "
             "stems, a core) left off", len(parts), report["element_diameter_median"], pitch, cols, dropped)
    return sheet, report

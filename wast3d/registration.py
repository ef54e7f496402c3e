"""Stage 4a, per-cluster registration to the style scene (paper eq. 7).

For every content cluster C_i find a translation t_i, a rotation R_i in SO(3) and an anisotropic scale
S_i = diag(s_i) > 0 minimizing

    sum_{g in C_i} min_{h in style} | S_i R_i (g_x - t_i) - h_x |          (eq. 7)

Method: multi-start anisotropic ICP, batched over all clusters x starts at once.

- Internally the map is ``y = S R (g - mu_i) + p`` (mu_i the cluster mean, p the landing point in the
  style scene); eq. 7's translation is ``t_i = mu_i - R^T S^{-1} p``.
- Scale bound: eq. 7 alone is minimized by S -> 0 (the whole cluster collapses onto one style
  Gaussian). S is therefore kept in ``[s0 / scale_range, s0 * scale_range]`` per axis.
- s0 sets how large the style's elements come out on the content (:func:`base_scale`). By default
  (``element_scale`` > 0) it is chosen so that one *relief length* L of the style (:func:`relief_length`:
  the correlation length of its height field, about a pebble's or a boulder's width, a weave's
  period) covers ``element_scale`` of the content's diameter D_c (robust box diagonal):
  ``s0 = L / (element_scale * D_c)``. This depends on the two scenes' shapes only, not on how many
  Gaussians either has: the older rule, ``s0 = mean NN distance of the style / mean NN distance of the
  content`` (``element_scale: 0``), made the elements of the demo's trained pebbles (19k Gaussians,
  floaters) half as large as the procedural pebbles' (30k) on the same ant, and those of its cleaned
  copy (9k) 1.7x larger. ``scale`` sets s0 explicitly. Eq. 7's per-axis scale still moves within
  ``scale_range`` of s0, so the elements come out at :func:`element_size_factors` times the asked size
  (a median 1.03-1.2x on the project's pairs, the trained weave 1.19x; 1.36x on it when it was pretrained
  to 1,500 steps, its strands sparse clumps that pulled the map to the bound, and on the fruit capture);
  ``registration.json`` reports it and the log warns beyond 1.2x.
- Element scale that follows the content (``follow_thickness`` > 0; by default on for a volume's
  element sheet, off for a patch): a cluster thinner than an element is wide gets its own base scale,
  s0 times :func:`thickness_factors`, so that its elements come out smaller and the content keeps its
  width there. On patches it is a study (the ant's legs: coarse Chamfer -20-26 % against boulders 4-9x
  wider than a leg, at 3-8x the Sinkhorn stage's time; studies/follow_thickness); on a sheet, whose
  copies are whole elements (:mod:`wast3d.stylize`'s ``copies``), it keeps whole flowers from
  thickening the legs (docs/measurements.md#styles-that-are-objects).
- ICP converges slowly and then snaps: from 29 degrees off, 30 rounds left 1.7 spacings of residual
  and 100 rounds reached 1e-11 on a test patch, hence the round counts.
- Starts, ``landings x yaws`` per cluster: landing points (:func:`landing_points`: by default drawn
  evenly by area over the central 80 % of the style's footprint, on its top surface); at each, the
  cluster's PCA normal (least-variance axis) is aligned with the style's local normal (PCA of 32
  style neighbours), at ``yaws`` evenly spaced
  rotations about the normal (random offset per cluster). With ``orient`` (default) the content
  normal is turned *outward* (:func:`outward_normals`) and the style's *up* (the side its elements
  stand on: :func:`style_up`), so that every cluster shows the elements' tops; without it both signs
  are started (``x 2``) and the residual picks one, which it cannot tell apart on a patch that is flat
  at the cluster's scale: on the demo's ant 11 of 25 clusters (pebbles) and 15 of 25 (trained pebbles)
  came out upside down, the sand's underside outward and the pebbles inside the content.
- ICP on at most ``subsample`` points per cluster for ``iterations`` rounds: nearest style
  neighbours (KD-tree, one query for all clusters and starts), then p by the mean residual, R by
  orthogonal Procrustes with the determinant fixed to +1 (Kabsch), S per axis by the ratio of the
  spreads of matched style points and rotated content points, clamped. The best start per cluster is refined on all its points for ``refine_iterations`` rounds.
- Degenerate clusters (1-3 points, collinear, planar, duplicates) give rank-deficient Procrustes
  problems: the SVD still yields a proper rotation, an axis without extent keeps its scale, and any
  non-finite value falls back to the start's transform (logged). Never NaN.

Residuals are reported as mean nearest-neighbour distance in units of the style's mean spacing.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np
import torch

from .cameras import UP_AXES
from .gaussians import quat_to_rotmat
from .geometry import KnnIndex, cap_per_label, frame_from_normal, kabsch, knn, local_normals, mean_spacing
from .options import checked, option

log = logging.getLogger(__name__)


LANDINGS = ("area", "centre")
# the options the config leaves null, by the style's form: (a patch, a volume's element sheet)
# A sheet's elements (a flower, a cone scale) stand as tall as they are wide, on both sides of a thin part:
# smaller, and at most half as wide as the content is thick, they keep the lego's and the guitar's coarse
# shape (docs/measurements.md#styles-that-are-objects)
FORM_DEFAULTS = {"follow_thickness": (0.0, 0.5), "element_scale": (0.062, 0.045)}
MAX_SHRINK = 4.0  # follow_thickness shrinks elements at most this much: 16x the style area per cluster
THICKNESS_POINTS = 64  # points per cluster whose local thickness follow_thickness takes the median of


@dataclass
@checked("register")
class RegistrationConfig:
    landings: int = option(2, "start points per cluster in the style (see landing)", minimum=1)
    landing: str = option("area", "where the starts land: area (drawn evenly by area over the central 80 % of "
                                  "the style's footprint, each on its top surface, spread over the clusters) or centre "
                                  "(the style's centre, then random style Gaussians: half the ant's clusters "
                                  "copied the trained stones' middle)", enum=LANDINGS)
    yaws: int = option(6, "rotations about the normal tried per start", minimum=1)
    orient: bool = option(True, "each cluster's outward normal onto the style's up (the elements' tops outside); false:"
                                " both signs started, the residual picks")
    iterations: int = option(40, "ICP iterations per start", minimum=0)
    refine_iterations: int = option(80, "ICP iterations of the best start on all points", minimum=0)
    refine_points: int = option(4096, "the refinement's points per cluster at most (a uniform draw beyond: a "
                                      "similarity is fitted as well from 4,096 as from 7,500; every project scene has "
                                      "fewer per cluster); 0: every point", minimum=0)
    subsample: int = option(128, "points per cluster during the multi-start phase", minimum=1)
    scale: float = option(0.0, "content-to-style scale s0 explicitly (0: from element_scale)", minimum=0)
    element_scale: float | None = option(None, "how large the style's elements come out: one relief length of the "
                                                "style (about an element's width) covers this fraction of the content's"
                                                " diameter; 0: s0 = style spacing / content spacing (density-matched, "
                                                "depends on the Gaussian counts); null: by the style's form, 0.062 on a "
                                                "patch, 0.045 on a volume's element sheet (its elements stand as tall "
                                                "as they are wide)", minimum=0)
    scale_range: float = option(1.5, "the scale is bounded to [s0 / range, s0 * range]", minimum=1)
    follow_thickness: float | None = option(None, "element scale that follows the content: where a cluster is thinner "
                                                  "(its median local thickness) than an element's width on the content "
                                                  "over this, its base scale is raised so that its elements come out that "
                                                  "much smaller (at most 4x); 0: one element size everywhere; null: by "
                                                  "the style's form, 0.5 on a volume's element sheet (whole flowers the "
                                                  "legs can carry), 0 on a patch (studies/follow_thickness)",
                                            minimum=0)
    style_up: str = option("z", "the side the style's elements stand on (outward content normals are mapped onto it): a"
                                " world axis, as the views of the style were taken (export_views, style_clean and the "
                                "texture reference look from +z), or auto (the skew of the heights; fooled by a trained"
                                " patch's unseen underside)", enum=[*UP_AXES, "auto"])
    seed: int = option(0, "seed of the starts and subsamples")



@dataclass
class Registration:
    """Per cluster (K): R [K,3,3], s [K,3], t [K,3] (eq. 7), p [K,3], mu [K,3], residual_init [K],
    residual [K] (in style spacings), s0 (scalar), style_spacing (scalar), style_up [3] (the style's up
    that the outward content normals were mapped onto, :func:`style_up`), base [K] (each cluster's base
    scale, the centre of its scale bounds: s0, or more where ``follow_thickness`` shrinks its elements;
    s0 everywhere when not given)."""

    R: torch.Tensor
    s: torch.Tensor
    t: torch.Tensor
    p: torch.Tensor
    mu: torch.Tensor
    residual_init: torch.Tensor
    residual: torch.Tensor
    s0: float
    style_spacing: float
    style_up: torch.Tensor
    base: torch.Tensor | None = None

    def __post_init__(self):
        if self.base is None:
            self.base = torch.full((len(self.s),), float(self.s0), dtype=torch.float64)

    def apply(self, points: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
        """Eq. 7's map of content points into the style scene: S R (g - t); points [N,3], labels [N]."""
        R, s, t = self.R[labels], self.s[labels], self.t[labels]
        return s * torch.einsum("nij,nj->ni", R, points - t)

    def apply_covariances(self, cov: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
        """The same map on covariances [N,3,3]: A cov A^T with A = S R."""
        A = self.s[labels].to(cov)[:, :, None] * self.R[labels].to(cov)
        return A @ cov @ A.transpose(-1, -2)

    def inverse(self, points: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
        """Style-scene points back to the content frame: R^T S^{-1} y + t."""
        R, s, t = self.R[labels], self.s[labels], self.t[labels]
        return torch.einsum("nji,nj->ni", R, points / s) + t

    def to_npz(self) -> dict:
        return {k: (v.numpy() if torch.is_tensor(v) else np.asarray(v)) for k, v in self.__dict__.items()}

    @classmethod
    def from_npz(cls, d: dict) -> "Registration":
        missing = sorted(set(cls.__dataclass_fields__) - set(d) - {"base"})  # base: s0 where not written
        if missing:
            raise ValueError(f"registration file lacks {', '.join(missing)} (written by an older wast3d?): run register again")
        return cls(**{k: (torch.from_numpy(np.asarray(d[k])) if np.asarray(d[k]).ndim else float(d[k]))
                      for k in cls.__dataclass_fields__ if k in d})


def thickness_factors(content: torch.Tensor, labels: torch.Tensor, K: int, width: float, cfg: "RegistrationConfig",
                      g: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """How much smaller each cluster's elements must be to fit the content there (``follow_thickness``):
    content [N, 3], labels [N], K clusters, ``width`` an element's width on the content -> (factors [K]
    >= 1, the clusters' thickness [K]). A cluster's thickness T_k is the median local thickness
    (:func:`~wast3d.geometry.local_thickness`, the distance through the content along its normal; inf on
    an open sheet) of at most ``THICKNESS_POINTS`` of its points, and

        f_k = clamp(width / (follow_thickness * T_k), 1, MAX_SHRINK)

    so an element is at most ``follow_thickness`` times as wide as the content is thick (an ant's leg
    gets pebbles it can carry, its body the full size)."""
    from .geometry import local_thickness, robust_bounds

    pick = cap_per_label(labels, THICKNESS_POINTS, g)
    # only thicknesses below width / follow_thickness change a factor: the search along the normal stops there
    reach = width / cfg.follow_thickness / (2 * robust_bounds(content, 0.01)[1])
    t = torch.from_numpy(local_thickness(content.double().numpy(), content[pick].double().numpy(), reach=reach))
    T = torch.stack([t[labels[pick] == k].median() if bool((labels[pick] == k).any()) else t.new_tensor(float("inf"))
                     for k in range(K)])
    f = (width / (cfg.follow_thickness * T)).clamp(1.0, MAX_SHRINK)
    return torch.where(torch.isfinite(T), f, torch.ones_like(f)), T


def element_size_factors(reg: Registration) -> torch.Tensor:
    """[K] how large the style's elements come out on each cluster, over the size s0 asks for
    (:func:`base_scale`; 1: as asked). Eq. 7's scale S = diag(s) varies per axis within
    ``scale_range``, so a patch of the style's plane (unit normal u, the style's up) of area a maps back
    onto the content with area ``a |S u| / (s_1 s_2 s_3)`` (the area a linear map M = S^-1 gives a plane
    with normal u: ``|det M| |M^-T u|``), and a length in it by the square root of that:

        f_k = s0 sqrt(|s_k * u| / prod(s_k))

    (u = z: ``s0 / sqrt(s_x s_y)``, the in-plane scales; the normal's scale, which squashes the
    content's curvature into the style's layer, does not change the elements' width)."""
    u = reg.style_up.double() / reg.style_up.double().norm()
    s = reg.s.double()
    return reg.s0 * torch.sqrt((s * u).norm(dim=1) / s.prod(dim=1))


def element_size_report(reg: Registration, scale_range: float) -> dict:
    """:func:`element_size_factors`' median and 10 / 90 % quantiles over the clusters, and the share of
    clusters with an in-plane scale axis (the two least aligned with the style's up) at ``scale_range``'s
    bound (its base scale over or times the range: ``s0 / range`` or ``s0 * range`` but where
    ``follow_thickness`` raised it)."""
    f = element_size_factors(reg)
    s = reg.s.double()[:, torch.argsort(reg.style_up.double().abs())[:2]]
    base = reg.base.double()[:, None].expand_as(s)
    at = torch.zeros_like(s, dtype=torch.bool)
    for b in (base / scale_range, base * scale_range):
        at |= torch.isclose(s, b, rtol=1e-6)
    return {"median": float(f.median()), "p10": float(torch.quantile(f, 0.1)), "p90": float(torch.quantile(f, 0.9)),
            "clusters_at_scale_bound": float(at.any(dim=1).double().mean()),
            "units": "the elements' size on the content over the size s0 asks (1: as asked)"}




def patch_frame(style: torch.Tensor, up="auto") -> tuple[np.ndarray, np.ndarray]:
    """(centre [3], axes [3, 3]) of a style patch [M, 3]: rows by decreasing variance (the patch plane,
    then its normal), the normal signed to point to the patch's *up*, the side its elements stand on.

    ``up``: a world axis (``"z"``, ``"-y"``, ... of ``UP_AXES``) or a direction [3] (the normal's sign
    agrees with it), or
    ``"auto"``: the sign that gives the heights along the normal a positive skew (elements stand up from
    the ground, their tops are the rare high points). The skew is right on every procedural style and
    wrong on the demo's trained pebbles, whose unseen underside holds large opaque Gaussians down to 0.15
    below the ground (a tail the other way); the side the training cameras saw is the reliable up."""
    x = style.detach().double().cpu().numpy()
    c = x.mean(0)
    axes = np.linalg.svd(x - c, full_matrices=False)[2]
    if up == "auto":
        h = (x - c) @ axes[2]
        flip = ((h - h.mean()) ** 3).mean() < 0
    elif not isinstance(up, str) or up in UP_AXES:
        flip = float(axes[2] @ np.asarray(UP_AXES[up] if isinstance(up, str) else up, dtype=np.float64)) < 0
    else:
        raise ValueError(f"style up must be 'auto' or one of {', '.join(UP_AXES)}, got '{up}'")
    if flip:
        axes[2] = -axes[2]
    return c, axes


def style_up(style: torch.Tensor, up="auto") -> torch.Tensor:
    """[3] the style patch's up (:func:`patch_frame`)."""
    return torch.from_numpy(patch_frame(style, up)[1][2].copy()).to(torch.float64)


def outward_normals(content: torch.Tensor, labels: torch.Tensor, normals: torch.Tensor, grid: int = 64,
                    rays: int = 9) -> torch.Tensor:
    """Each cluster's normal [K, 3] turned to the outside of the content (content [N, 3], labels [N],
    normals [K, 3] of either sign). From the cluster's centroid, ``rays`` rays in a 30-degree cone
    around +n and around -n are marched through an occupancy grid of the content (``grid`` cells along
    its largest side, one cell dilated), from one cluster radius out, until they leave its box; the
    outside is the side whose rays escape without meeting the content (hits before the first free cell
    are the cluster's own surface and do not count).
    Ties (both or neither escape: an open sheet, an enclosed pocket) keep the side facing away from
    the content's centroid."""
    x = content.double()
    lo, hi = x.min(0).values, x.max(0).values
    cell = float((hi - lo).max()) / grid + 1e-12
    dims = ((hi - lo) / cell).long() + 3
    occ = torch.zeros(*dims.tolist(), dtype=torch.bool)
    ijk = ((x - lo) / cell).long() + 1
    for d in ((0, 0, 0), (1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1)):
        q = (ijk + torch.tensor(d)).clamp(torch.zeros(3, dtype=torch.long), dims - 1)
        occ[q[:, 0], q[:, 1], q[:, 2]] = True
    K = len(normals)
    mu = _segment_mean(x, labels.long(), K)
    # cone directions around +z, rotated onto each normal
    a = torch.linspace(0, 2 * torch.pi, rays, dtype=torch.float64)[:-1] if rays > 1 else torch.zeros(0, dtype=torch.float64)
    tilt = torch.tensor(torch.pi / 6, dtype=torch.float64)
    cone = torch.cat([torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64),
                      torch.stack([tilt.sin() * a.cos(), tilt.sin() * a.sin(), tilt.cos().expand_as(a)], 1)])
    F = frame_from_normal(normals.double())  # columns: tangent, tangent, normal
    # rays start one cluster radius out (past the cluster's own surface, wherever the centroid of a
    # curved cluster lies) and step by half a cell
    rad = (x - mu[labels.long()]).norm(dim=1)
    r0 = torch.zeros(K, dtype=torch.float64).scatter_reduce(0, labels.long(), rad, "amax").clamp_min(1.5 * cell)
    steps = torch.arange(0, int(dims.max()) * 2, dtype=torch.float64) * 0.5 * cell
    escaped = []
    for sign in (1.0, -1.0):
        dirs = torch.einsum("kij,rj->kri", F, cone * torch.tensor([1.0, 1.0, sign], dtype=torch.float64))
        p = mu[:, None, None, :] + dirs[:, :, None, :] * (r0[:, None, None, None] + steps[None, None, :, None])
        q = ((p - lo) / cell).floor().long() + 1
        inside = ((q >= 0) & (q < dims)).all(-1)
        qc = torch.minimum(q.clamp_min(0), dims - 1)
        hit = occ[qc[..., 0], qc[..., 1], qc[..., 2]] & inside
        # leave the cluster's own surface first: hits before the first free cell do not count
        free = (~hit).cumsum(-1) > 0
        again = (hit & free).any(-1)
        escaped.append((~again).double().mean(-1))
    up, down = escaped
    away = ((mu - x.mean(0)) * normals.double()).sum(-1) >= 0
    outward = torch.where(up > down, True, torch.where(down > up, False, away))
    return torch.where(outward[:, None], normals.double(), -normals.double())


@dataclass(frozen=True)
class Relief:
    """A style patch's relief (:func:`relief`): ``length`` L, about an element's width, and ``height``,
    the RMS of its top surface about the patch's shape; ``aspect`` = height / length."""

    length: float
    height: float

    @property
    def aspect(self) -> float:
        return self.height / self.length


# The level the autocorrelation profile crosses for the relief length, and the ratio of that crossing to
# the zero crossing on packed elements (benchmarks/relief_length.py): a profile that hovers at
# +-0.01-0.04 (a field of independent blades, one patch of pebbles) crosses zero where its noise does.
RELIEF_LEVEL = 0.05
RELIEF_LEVEL_RATIO = 0.92
# A steep element (a blade) is longer up than across: its length is at least this many interquartile
# ranges of the top heights (2.0: the demo's grass keeps the length 0.33 it was tuned at).
RELIEF_HEIGHT_FACTOR = 2.0


def relief_length(style: torch.Tensor, grid: int = 128, q: float = 0.02, up="z") -> float:
    """The style's relief length (:func:`relief`). style: [M, 3] -> L, in its units."""
    return relief(style, grid, q, up).length


def top_surface(uvw: np.ndarray, lo, cell: float, shape: tuple[int, int]):
    """A patch's top surface on a raster of its plane. uvw [M, 3]: positions in the patch frame (plane
    coordinates, height); ``lo`` [2] the raster's corner, ``cell`` its pitch, ``shape`` its size.

    Returns H [shape] (each cell's largest height minus the least-squares quadratic in the plane
    through those tops: the patch's bend is its shape, not its relief; 0 in empty cells), ``filled``
    [shape] bool, and each point's cell [M, 2] (outside the raster where a point lies beyond it)."""
    ij = np.floor((uvw[:, :2] - lo) / cell).astype(np.int64)
    ok = (ij >= 0).all(1) & (ij < np.asarray(shape)).all(1)
    H = np.full(shape, -np.inf)
    np.maximum.at(H, (ij[ok, 0], ij[ok, 1]), uvw[ok, 2])
    filled = np.isfinite(H)
    ci, cj = np.nonzero(filled)
    x, y = ci / shape[0] - 0.5, cj / shape[1] - 0.5
    A = np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], 1)  # the patch's shape to second order
    top = H[filled]
    H = np.zeros(shape)
    H[ci, cj] = top - A @ np.linalg.lstsq(A, top, rcond=None)[0]
    return H, filled, ij


def relief_basins(style: torch.Tensor, up, length: float, cells: int = 8, smooth: float = 0.1) -> torch.Tensor:
    """style [M, 3] (a patch), its up, its relief length L -> [M] int64 ids of the relief's basins: one
    per dome of the top surface, bordered by the crevices between them (a watershed).

    The top surface (:func:`top_surface`) on a raster of ``cells`` cells per L, empty cells given
    their nearest filled cell's height, smoothed by a Gaussian of ``smooth`` L; every cell climbs to
    its highest neighbour (of 8) until none is higher, and the cells that reach one top make one
    basin; each point takes its cell's basin. Unlike parts of one size
    (:func:`wast3d.stylize.style_parts`), a basin follows its element whatever its size: on the
    demo's trained stones (elements 0.83-0.88 L across) 19 basins for 14 stones, the median stone with
    99.2 % of its Gaussians in one (k-means parts of 0.8 L: 73 %); on the trained pebbles 58 basins
    for 60 pebbles, 97.6 % (94 %) (benchmarks/dome_share.py). Its scale is L's: where L is
    off, basins merge elements."""
    from scipy import ndimage

    if not length > 0:
        raise ValueError(f"relief basins: need a relief length > 0, got {length}")
    c, axes = patch_frame(style, up)
    uvw = (style.detach().double().cpu().numpy() - c) @ axes.T
    lo = uvw[:, :2].min(0)
    cell = length / cells
    shape = tuple(int(n) for n in np.floor((uvw[:, :2].max(0) - lo) / cell) + 1)
    H, filled, ij = top_surface(uvw, lo, cell, shape)
    near = ndimage.distance_transform_edt(~filled, return_distances=False, return_indices=True)
    H = ndimage.gaussian_filter(H[near[0], near[1]], smooth * cells, mode="nearest")
    # each cell's highest neighbour (itself where none is higher), then followed to its top
    pad = np.pad(H, 1, constant_values=-np.inf)
    rows, cols = np.indices(shape)
    best, best_h = rows * shape[1] + cols, H.copy()
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            h = pad[1 + di:1 + di + shape[0], 1 + dj:1 + dj + shape[1]]
            up_ = h > best_h
            best = np.where(up_, (rows + di) * shape[1] + cols + dj, best)
            best_h = np.where(up_, h, best_h)
    top = best.ravel()
    while True:  # pointer jumping: log2(longest climb) rounds
        nxt = top[top]
        if np.array_equal(nxt, top):
            break
        top = nxt
    ij = np.clip(ij, 0, np.asarray(shape) - 1)
    ids = np.unique(top.reshape(shape)[ij[:, 0], ij[:, 1]], return_inverse=True)[1]  # numbered over the points
    return torch.from_numpy(ids.reshape(-1).astype(np.int64))


def relief(style: torch.Tensor, grid: int = 128, q: float = 0.02, up="z", level: float = RELIEF_LEVEL,
           level_ratio: float = RELIEF_LEVEL_RATIO, height_factor: float = RELIEF_HEIGHT_FACTOR) -> Relief:
    """The style's relief (:class:`Relief`). style: [M, 3] (a patch: ground with elements on it) -> its
    relief length L, read from the radial autocorrelation of its top-surface height field (below), and
    the RMS height h of that field, both in its units. ``level`` 0, ``level_ratio`` 1 and
    ``height_factor`` 0 give the plain zero crossing, which noise moves (benchmarks/relief_length.py).

    The patch's plane is its two largest principal axes, its normal the third, oriented to the patch's
    up (``up``, :func:`patch_frame`); on a ``grid`` x ``grid`` raster of the
    plane's ``q``..``1-q`` box, h(cell) = the largest height there (the visible top), empty cells
    left out of the autocorrelation A(r) = sum h(x) h(x + r) / sum 1 (counts from the cells' own
    autocorrelation, both by FFT), averaged over |r|. Before it, the least-squares quadratic in the
    plane's coordinates is removed from h: a patch's bend or bowl is its shape, not its relief, and
    a few percent of it keep A(r) above 0 far beyond the elements (the demo's trained grass: 1.34
    with the mean removed only, against 0.39 for the grass it was trained from; 0.32 detrended).
    The profile A(r) / A(0) is read where it first falls below ``level`` (0.05), r_0.05, and
    L = 2 r_0.05 / ``level_ratio`` (0.92, the ratio of the two crossings on packed elements,
    where the profile has a negative lobe: the procedural pebbles, stones and weave, 0.90-0.94 over
    four seeds each), so that L keeps the zero crossing's values there. The zero crossing itself
    is noise where the profile hovers near 0 beyond the elements: independent blades (no negative
    lobe) crossed at 0.18-0.33 over four seeds and at 0.55 on the trained grass (their width at
    0.05: 0.09-0.12; their L, from the height bound below: 0.32-0.33 and 0.41); one
    patch of pebbles (seed 1, +0.01-0.04 from 11 to 23 cells) at 0.78 against 0.30-0.35, now 0.34.
    A field of bumps of width w decorrelates at about w / 2: L = 2 r_0 is about an element's width
    (procedural pebbles 0.31 and stones 0.53 in units where their labelled diameters are 0.21 and
    0.45; a weave's 0.087 at a period of 0.17). The demo's trained pebbles: 1.65 raw (floaters), 0.37
    cleaned (surface.clean_style): clean first.

    A steep element is longer up than across: L is at least ``height_factor`` (2.0) times the
    interquartile range of the top heights (not h: a trained patch's stray tops weigh in an RMS; the
    trained grass's h is 1.43x its source's, its range 1.22x). On the blades this bound is L; on the
    weave it and the width are about equal; on pebbles and stones it is far below the width.

    The aspect h / L says whether the elements are about L in every direction: a gentle relief (domes,
    boulders: 0.08-0.13 on the demo's pebbles and stones, procedural and trained) has elements about
    L wide; a steep one (blades, a weave: 0.26-0.34) has elements far longer than L across along some
    direction (up for a blade, along the strand for a weave)."""
    if len(style) < 16:
        raise ValueError(f"relief length: {len(style)} style points (need at least 16)")
    c, axes = patch_frame(style, up)
    uvw = (style.detach().double().cpu().numpy() - c) @ axes.T
    lo, hi = np.quantile(uvw[:, :2], q, axis=0), np.quantile(uvw[:, :2], 1 - q, axis=0)
    cell = max(float((hi - lo).max()) / grid, 1e-12)
    H, filled, _ = top_surface(uvw, lo, cell, (grid, grid))
    size = (2 * grid, 2 * grid)
    acf = np.fft.irfft2(np.abs(np.fft.rfft2(H, s=size)) ** 2, s=size)
    cnt = np.fft.irfft2(np.abs(np.fft.rfft2(filled.astype(float), s=size)) ** 2, s=size)
    acf = acf / np.maximum(cnt, 1.0)
    if acf[0, 0] <= (1e-9 * cell) ** 2:  # what is left after the quadratic is rounding
        raise ValueError("relief length: the style is flat (no height variation)")
    f = np.fft.fftfreq(2 * grid) * 2 * grid
    r = np.hypot(f[:, None], f[None, :]).round().astype(np.int64).ravel()
    prof = np.bincount(r, acf.ravel() / acf[0, 0])[:grid] / np.maximum(np.bincount(r)[:grid], 1)
    height = float(np.sqrt(acf[0, 0]))
    below = prof < level
    if not below.any():
        return Relief(2.0 * grid * cell, height)
    k = int(np.argmax(below))  # the first crossing, linearly between the radii k - 1 and k
    r0 = k - 1 + (prof[k - 1] - level) / (prof[k - 1] - prof[k])
    iqr = float(np.subtract(*np.quantile(H[filled], [0.75, 0.25])))  # robust to a trained patch's stray tops
    return Relief(max(2.0 * r0 * cell / level_ratio, height_factor * iqr), height)


def base_scale(content: torch.Tensor, style: torch.Tensor, cfg: RegistrationConfig,
               diameter: float | None = None) -> tuple[float, dict]:
    """s0 of the module docstring and how it was chosen. content: [N, 3], style: [M, 3]; ``diameter``: the
    content diameter the element scale refers to (default: the content's own; a region of a content gives
    the whole content's, so that its elements come out as large as the style alone makes them)."""
    from .geometry import robust_bounds

    if cfg.scale > 0:
        return cfg.scale, {"rule": "scale (explicit)"}
    why = None
    cfg = by_form(cfg, sheet=False)  # as register() resolves it where it is left null
    if cfg.element_scale > 0:
        try:
            L = relief_length(style, up=cfg.style_up)
        except ValueError as e:  # a flat style (a printed label) has no relief to size its elements by
            why = f"element_scale not applicable ({e}); density rule used"
            log.warning("registration: %s", why)
        else:
            Dc = diameter if diameter else 2 * robust_bounds(content)[1]
            return L / (cfg.element_scale * Dc), {"rule": "element_scale", "relief_length": L, "content_diameter": Dc,
                                                  "element_scale": cfg.element_scale}
    h_s, h_c = mean_spacing(style, seed=cfg.seed), mean_spacing(content, seed=cfg.seed)
    return h_s / h_c, {"rule": "density (style spacing / content spacing)", "style_spacing": h_s, "content_spacing": h_c,
                       **({"note": why} if why else {})}


def landing_points(style: torch.Tensor, up: torch.Tensor, K: int, L: int, g: torch.Generator,
                   how: str = "area", cells: int = 32, inner: float = 0.8) -> torch.Tensor:
    """style [M, 3], up [3] -> [K, L, 3] the multi-start phase's landing points, L per cluster, kept
    off the style's border, where a cluster's footprint would have no style around it.

    - ``area``: the style's footprint on the plane normal to ``up`` (its box between the 0.5 % and
      99.5 % quantiles per axis) is cut into ``cells x cells`` cells, and the cells of its central
      ``inner`` per axis that hold Gaussians are dealt out as concatenated random permutations (every
      cell once before any twice); a landing is its cell's top Gaussian (highest along ``up``). So the
      K L landings cover the footprint evenly by area, on its top surface, whatever the style's
      density: a trained style's gravel holds many small Gaussians, its boulders few large ones, and
      drawing Gaussians (or measuring "inner" from their median) draws the gravel.
    - ``centre``: the rule before: the style's median for every cluster's first landing, Gaussians
      drawn at random within the inner 80 % (by distance from the median) for the others; on the ant x
      trained stones half the clusters kept the first, all copying the same middle of the style."""
    if how == "centre":
        sc = style.median(0).values
        rad = (style - sc).norm(dim=1)
        pool = (rad <= torch.quantile(rad, 0.8)).nonzero().squeeze(1)
        lp = style[pool[torch.randint(len(pool), (K, L), generator=g)]]
        lp[:, 0] = sc
        return lp
    if how != "area":
        raise ValueError(f"registration: landing must be one of {', '.join(LANDINGS)}, got '{how}'")
    uvh = style @ frame_from_normal(up.to(style)[None])[0]  # columns: tangent, tangent, up
    uv = uvh[:, :2]
    q = torch.tensor([0.005, 0.995], dtype=uv.dtype)
    lo, hi = torch.quantile(uv, q[0], dim=0), torch.quantile(uv, q[1], dim=0)
    mid, half = (lo + hi) / 2, (hi - lo).clamp_min(1e-12) / 2
    pool = ((uv - mid).abs() <= inner * half).all(1).nonzero().squeeze(1)
    if len(pool) == 0:  # a degenerate footprint (a line, a point): any Gaussian
        pool = torch.arange(len(style))
    ij = ((uv[pool] - lo) / (2 * half) * cells).long().clamp(0, cells - 1)
    cell = ij[:, 0] * cells + ij[:, 1]
    # the top Gaussian of each occupied cell: sort by height, then stably by cell, take each cell's last
    order = torch.argsort(uvh[pool, 2])
    order = order[torch.argsort(cell[order], stable=True)]
    last = torch.ones(len(order), dtype=torch.bool)
    last[:-1] = cell[order[1:]] != cell[order[:-1]]
    tops = pool[order[last]]
    n = K * L
    deal = torch.cat([torch.randperm(len(tops), generator=g) for _ in range(-(-n // len(tops)))])[:n]
    return style[tops[deal]].reshape(K, L, 3)


def _segment_mean(v: torch.Tensor, seg: torch.Tensor, n: int) -> torch.Tensor:
    s = v.new_zeros(n, *v.shape[1:]).index_add_(0, seg, v)
    c = v.new_zeros(n).index_add_(0, seg, torch.ones_like(seg, dtype=v.dtype)).clamp_min(1)
    return s / c.view(-1, *([1] * (v.ndim - 1)))


def _icp(g: torch.Tensor, seg: torch.Tensor, B: int, style: torch.Tensor, R, s, p, s_lo, s_hi, iters: int,
         index: KnnIndex):
    """Anisotropic ICP on centred points g [P,3] belonging to transforms seg [P] (B of them); ``index``:
    the style [M,3] indexed for nearest-neighbour queries.

    Returns the best R, s, p and residual [B] of each transform, and the residual at its start [B]."""
    best = (R.clone(), s.clone(), p.clone())
    best_res = torch.full((B,), float("inf"), dtype=g.dtype)
    for it in range(iters + 1):
        y = s[seg] * torch.einsum("pij,pj->pi", R[seg], g) + p[seg]
        d, idx = index.query(y, 1)
        res = _segment_mean(d[:, 0], seg, B)
        if it == 0:
            res_start = res
        better = res < best_res
        best_res = torch.where(better, res, best_res)
        best = tuple(torch.where(better.view(-1, *([1] * (b.ndim - 1))), cur, b) for cur, b in zip((R, s, p), best))
        if it == iters:
            break
        q = style[idx[:, 0]]
        Rg = torch.einsum("pij,pj->pi", R[seg], g)
        p = _segment_mean(q - s[seg] * Rg, seg, B)
        u = q - p[seg]
        H = g.new_zeros(B, 3, 3).index_add_(0, seg, g[:, :, None] * (u / s[seg])[:, None, :])
        R_new = kabsch(H)
        Rg = torch.einsum("pij,pj->pi", R_new[seg], g)
        # per-axis ratio of spreads: the least-squares slope sum(Rg u) / sum(Rg^2) is biased towards 0
        # when nearest-neighbour correspondences are noisy (regression dilution) and drove S to its bound
        num = g.new_zeros(B, 3).index_add_(0, seg, u * u)
        den = g.new_zeros(B, 3).index_add_(0, seg, Rg * Rg)
        s_new = torch.where(den > 1e-12, (num / den.clamp_min(1e-30)).sqrt(), s).clamp(s_lo, s_hi)
        ok = torch.isfinite(R_new).all(-1).all(-1) & torch.isfinite(s_new).all(-1) & torch.isfinite(p).all(-1)
        if not bool(ok.all()):
            log.warning("registration: %d non-finite updates fell back to the previous transform", int((~ok).sum()))
        R = torch.where(ok[:, None, None], R_new, R)
        s = torch.where(ok[:, None], s_new, s)
        p = torch.where(ok[:, None], p, best[2])
    return best[0], best[1], best[2], best_res, res_start


def by_form(cfg: RegistrationConfig, sheet: bool) -> RegistrationConfig:
    """``cfg`` with the options it leaves null (:data:`FORM_DEFAULTS`: ``follow_thickness``,
    ``element_scale``) set by the style's form; ``sheet``: a volume's element sheet, else a patch."""
    return replace(cfg, **{k: float(v[sheet]) for k, v in FORM_DEFAULTS.items() if getattr(cfg, k) is None})


@torch.no_grad()
def register(content: torch.Tensor, labels: torch.Tensor, style: torch.Tensor,
             cfg: RegistrationConfig = RegistrationConfig(), normals: torch.Tensor | None = None,
             diameter: float | None = None, sheet: bool = False) -> Registration:
    """content: [N,3] points, labels: [N] in 0..K-1, style: [M,3], normals: [N,3] the points' outward
    normals if known (stage 3 makes them) -> :class:`Registration`. With normals, a cluster's normal is
    their mean (already outward); without, its least-variance axis turned outward by
    :func:`outward_normals`. ``diameter``: see :func:`base_scale`; ``sheet``: the style is a volume's
    element sheet (:func:`by_form`)."""
    resolved = by_form(cfg, sheet)
    chosen = {k: getattr(resolved, k) for k in FORM_DEFAULTS if getattr(cfg, k) is None}
    if chosen:
        log.info("registration: %s by the style's form (%s)", ", ".join(f"{k} {v:.3g}" for k, v in chosen.items()),
                 "a volume's element sheet" if sheet else "a patch")
    cfg = resolved
    content, style = content.double(), style.double()
    labels = labels.long()
    K = int(labels.max()) + 1 if len(labels) else 0
    if K == 0 or len(style) == 0:
        raise ValueError(f"registration: need content clusters and style points (K={K}, style={len(style)})")
    sizes = torch.bincount(labels, minlength=K)
    if (sizes == 0).any():
        raise ValueError(f"registration: empty clusters {(sizes == 0).nonzero().squeeze(1).tolist()[:10]} "
                         "(labels must use every id 0..K-1)")
    g = torch.Generator().manual_seed(cfg.seed)
    mu = _segment_mean(content, labels, K)
    cent = content - mu[labels]
    sp_style = mean_spacing(style, seed=cfg.seed)
    s0, how = base_scale(content, style, cfg, diameter)
    log.info("registration: s0 = %.4g by %s", s0, ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                                                               for k, v in how.items()))
    sub = cap_per_label(labels, cfg.subsample, g)  # <= cfg.subsample points per cluster for the multi-start phase
    signs = 1 if cfg.orient else 2
    M = cfg.landings * cfg.yaws * signs
    B = K * M
    s0k = torch.full((K,), s0, dtype=torch.float64)  # each cluster's base scale
    if cfg.follow_thickness > 0:
        if "relief_length" not in how:
            log.warning("registration: follow_thickness left out: s0 is not from the style's relief (%s)", how["rule"])
        else:
            f, T = thickness_factors(content, labels, K, how["relief_length"] / s0, cfg,
                                     torch.Generator().manual_seed(cfg.seed))
            s0k = s0 * f
            log.info("registration: follow_thickness %.3g: %d of %d clusters thinner than an element (width %.4g); their "
                     "elements shrunk a median %.2fx (max %.2fx)", cfg.follow_thickness, int((f > 1).sum()), K,
                     how["relief_length"] / s0, float(f[f > 1].median()) if bool((f > 1).any()) else 1.0, float(f.max()))
    s_lo, s_hi = (s0k / cfg.scale_range)[:, None], (s0k * cfg.scale_range)[:, None]
    # start j of a cluster: landing j // (signs yaws), normal sign j % signs, yaw (j // signs) % yaws
    j = torch.arange(M)
    land, sign, yaw_i = j // (signs * cfg.yaws), j % signs, (j // signs) % cfg.yaws
    up = style_up(style, cfg.style_up)
    p0 = landing_points(style, up, K, cfg.landings, g, cfg.landing)[:, land].reshape(B, 3)
    n_style = local_normals(style, p0, 32)
    # cluster normals (least-variance axis of each cluster)
    cov = content.new_zeros(K, 3, 3).index_add_(0, labels, cent[:, :, None] * cent[:, None, :])
    _, vecs = torch.linalg.eigh(cov + 1e-12 * torch.eye(3, dtype=cov.dtype))
    n_content = vecs[:, :, 0]
    ok = torch.zeros(K, dtype=torch.bool)
    if normals is not None:
        if normals.shape != content.shape:
            raise ValueError(f"registration: normals {tuple(normals.shape)} do not match the content {tuple(content.shape)}")
        mean_n = _segment_mean(normals.double(), labels, K)
        ok = mean_n.norm(dim=1) > 1e-3  # a cluster whose normals cancel keeps the ray test's normal
    if cfg.orient and not ok.all():  # outward content normals onto the style's up (see the module docstring)
        n_content = outward_normals(content, labels, n_content)
    if normals is not None:
        n_content = torch.where(ok[:, None], mean_n / mean_n.norm(dim=1, keepdim=True).clamp_min(1e-12), n_content)
    if cfg.orient:
        n_style = torch.where(((n_style * up).sum(-1) >= 0)[:, None], n_style, -n_style)
    Fc = frame_from_normal(n_content)  # columns: cluster tangent, tangent, normal
    flip = torch.where(sign == 0, 1.0, -1.0).to(style).repeat(K)
    Fs = frame_from_normal(n_style * flip[:, None])
    yaw = yaw_i.double().repeat(K) * (2 * torch.pi / cfg.yaws) + \
        torch.rand(K, generator=g, dtype=torch.float64).repeat_interleave(M) * 2 * torch.pi
    Rz = quat_to_rotmat(torch.stack([torch.cos(yaw / 2), torch.zeros_like(yaw), torch.zeros_like(yaw),
                                     torch.sin(yaw / 2)], -1))
    R0 = Fs @ Rz @ Fc.repeat_interleave(M, 0).transpose(1, 2)
    s_init = s0k.repeat_interleave(M)[:, None].expand(B, 3).clone()
    # point instances: every subsampled point once per start
    inst_pt = sub.repeat(M)
    inst_tf = labels[sub].repeat(M) * M + torch.arange(M).repeat_interleave(len(sub))
    index = KnnIndex(style)  # one KD-tree for every ICP round of both phases
    R, s, p, res, res0 = _icp(cent[inst_pt], inst_tf, B, style, R0, s_init, p0, s_lo.repeat_interleave(M, 0),
                              s_hi.repeat_interleave(M, 0), cfg.iterations, index)
    best = (res.view(K, M)).argmin(1)
    pick = torch.arange(K) * M + best
    R, s, p = R[pick], s[pick], p[pick]
    # refine the best start on every point of its cluster (at most refine_points, drawn after the starts' draw)
    if cfg.refine_points and int(sizes.max()) > cfg.refine_points:
        fine = cap_per_label(labels, cfg.refine_points, g)
        log.info("registration: refined on %d of each cluster's points at most (%d of %d points)", cfg.refine_points,
                 len(fine), len(labels))
        R, s, p, res_final, _ = _icp(cent[fine], labels[fine], K, style, R, s, p, s_lo, s_hi, cfg.refine_iterations,
                                     index)
    else:
        R, s, p, res_final, _ = _icp(cent, labels, K, style, R, s, p, s_lo, s_hi, cfg.refine_iterations, index)
    t = mu - torch.einsum("kji,kj->ki", R, p / s)
    reg = Registration(R, s, t, p, mu, res0.view(K, M).mean(1) / sp_style, res_final / sp_style, s0, sp_style, up,
                       s0k)
    log.info("registration: %d clusters x %d starts; residual %.3f -> %.3f style spacings (mean); s0 = %.4g",
             K, M, float(reg.residual_init.mean()), float(reg.residual.mean()), s0)
    return reg


def random_rotation(g: torch.Generator, dtype=torch.float64) -> torch.Tensor:
    q = torch.randn(1, 4, generator=g, dtype=dtype)
    return quat_to_rotmat(q)[0]

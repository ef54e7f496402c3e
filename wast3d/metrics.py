"""Stage 8, weights-free metrics: what a stylized scene keeps of the content and takes from the style,
measured on the Gaussians themselves (no network, no weights). Each is 0 for identical inputs (the
same cloud, the same seed) and grows as one input is perturbed.

Content fidelity
    ``content_chamfer``: symmetric Chamfer distance between the result's means X and the content's
    surface samples C, in units of the content's mean nearest-neighbour spacing h_C:
    ``(mean_x min_c |x-c| + mean_c min_x |x-c|) / (2 h_C)``.  1.0 = one content point spacing.

    ``coarse_chamfer``: the same, after result and content are each smoothed at the style's element
    length L on the content (:func:`~wast3d.geometry.gaussian_smooth`, sigma = L / 2, over at most
    ``coarse_support`` points of each cloud): the content's shape without the relief that the style is
    meant to add (a style with relief cannot meet a plain Chamfer of a few content spacings). Same unit
    (the unsmoothed content's spacing). L: ``coarse_scale`` x the content's diameter if set, else the
    style's relief length over the registration's base scale (the texture reference records it).

Style fidelity (result vs style scene; neither needs the two to share a coordinate frame)
    ``style_patch_chamfer``: ``patches`` local patches of the result (every ``patch_stride``-th of
    the ``patch_size * patch_stride`` nearest means of random centres) and ``candidates`` patches of the style, each normalized to be invariant
    to position, scale, rotation and reflection: centred on its centroid, rotated into its principal
    frame (axes by decreasing variance, each axis' sign fixed by a positive third moment), divided by
    its RMS radius, and compared to the other side's patch under ``rotations`` in-plane rotations about
    the smallest axis (the principal frame is ambiguous in-plane when the patch is round). Score: mean
    over result patches of the smallest symmetric Chamfer distance (mean NN distance, both ways, /2) to
    any style patch; the unit is the patch RMS radius.
    ``style_patch_sinkhorn``: the debiased Sinkhorn divergence S_eps (p=2, blur 0.05, cost |x-y|^2/2)
    between each result patch and its best (Chamfer) style patch, averaged.
    ``tilt_w1_deg``: 1-D Wasserstein-1 distance (degrees) between the distributions of *tilt* in the
    result and in the style: the angle between a Gaussian's shortest axis and the local surface normal
    (smallest principal axis of its ``normal_k`` nearest means). Relief, pebbles standing up, blades of
    grass: all show as tilt.
    ``aniso_w1``: W1 between the distributions of log10(max scale / min scale).
    ``relief_w1``: local shape below the scale of the style's elements. Around ``relief_centres`` random
    means, the k nearest means for each k in ``relief_scales`` (8, 16, 32 Gaussians: the surface of
    an element, its rims and creases, its micro-relief; counted in Gaussians so that no shared length
    unit is needed. 64-512 were dropped by benchmarks/metrics_validation.py: at the demo's density an
    ant's leg is as large as a pebble, so at those scales the content's own shape dominates and a
    collage of the style's elements scored as far from the style as the plain content), their
    covariance eigenvalues l1 >= l2 >= l3 and two descriptors: the relative height above the fitted
    plane ``sqrt(l3 / (l1 + l2))`` (relief: domes, blades, strands, boulders) and the in-plane
    isotropy ``sqrt(l2 / l1)`` (round patches vs strands and blades). Score: the mean over scales and
    descriptors of the 1-D W1 between result and style distributions.
    ``colour_sinkhorn``: S_eps (blur 0.05) between RGB colours of the result and the style
    (``colour_points`` random Gaussians of each).

Whole elements, label-free (:func:`element_metrics`; result vs style, at the style's element size in
Gaussians, n_e: the median Gaussians per segment of the style, its relief basins or a volume's laid-out
elements, so that no shared length unit is needed: a copy holds as many Gaussians as its element)
    ``element_colour_w1``: colour coherence inside an element. Around ``element_centres`` random means,
    the summed RGB variance of the k nearest Gaussians, for k = n_e / 32, n_e / 16, n_e / 8 (at least 8):
    inside a whole element a small neighbourhood is of few colours (a petal, a flower's centre); an
    element torn apart and its Gaussians scattered (confetti) mixes every colour of its surroundings.
    Score: the mean over the three k of the 1-D W1 between result and style distributions, each over the
    interquartile range of the style's (unit-free).
    ``element_thickness_w1``: an element's own relief. Around the same centres, the n_e / 4 nearest
    Gaussians whose colour lies within tau (inclusive) of the centre's (tau: the style's median RGB distance from a
    Gaussian to its 8 nearest; mostly the centre's own element, whatever the content's curvature under
    it) and their ``sqrt(l3 / (l1 + l2))`` (at least 8 kept, else the centre is not counted): an element
    flattened into a chip falls towards 0, a confetti of colours keeps few and scattered Gaussians.
    Score: W1 over the style's interquartile range, as above.

Patches and colour samples are drawn by a ``torch.Generator`` seeded with ``seed``; identical clouds
therefore give identical samples and the scores are exactly 0 (S_eps to ~1e-6: its colour solve is float32).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from .gaussians import GaussianScene, anisotropy, shortest_axis
from .geometry import knn, knn_mean_dist, local_normals
from .options import checked, option


@dataclass
@checked("metrics")
class MetricsConfig:
    patches: int = option(0, "result patches of the patch metrics (style_patch_chamfer, style_patch_sinkhorn); 0: not "
                             "computed (they have not passed the metric validation's controls, and cost half an "
                             "evaluation: 20 of its 40 s on the demo); 128 was their setting", minimum=0)
    candidates: int = option(512, "style patches each result patch is matched against", minimum=1)
    patch_size: int = option(32, "points per patch", minimum=4)
    patch_stride: int = option(4, "a patch takes every stride-th of its patch_size * stride nearest means", minimum=1)
    rotations: int = option(8, "in-plane rotations tried per patch match", minimum=1)
    normal_k: int = option(16, "neighbours of the local normal (tilt_w1_deg)", minimum=3)
    colour_points: int = option(4096, "Gaussians per side of colour_sinkhorn", minimum=1)
    blur: float = option(0.05, "blur of the patch and colour Sinkhorn divergences", exclusiveMinimum=0)
    relief_scales: tuple = option((8, 16, 32), "neighbourhood sizes (Gaussians) of relief_w1",
                                               items={"type": "integer", "minimum": 4}, minItems=1)
    relief_centres: int = option(8192, "random centres of relief_w1 (its seed-to-seed spread falls as 1/sqrt)",
                                       minimum=1)
    element_centres: int = option(32768, "random centres of element_colour_w1 and element_thickness_w1 (their standard "
                                         "deviation over metric seeds on the ant x bouquet: 0.005 at 32768 in 1.9 s, "
                                         "0.011-0.021 at 8192 in 0.5 s)", minimum=1)
    coarse_scale: float = option(0.0, "coarse_chamfer's smoothing length as a fraction of the content's diameter (0: "
                                      "the style's element length on the content)", minimum=0)
    coarse_support: int = option(20000, "points of each cloud the coarse Chamfer smooths over", minimum=16)
    seed: int = option(0, "seed of every sampled metric")

    def __post_init__(self):
        self.relief_scales = tuple(int(k) for k in self.relief_scales)
        if not self.relief_scales or min(self.relief_scales) < 4:
            raise ValueError(f"metrics.relief_scales: need at least one, each >= 4, got {list(self.relief_scales)}")


def chamfer(x: torch.Tensor, y: torch.Tensor) -> float:
    """Symmetric Chamfer distance ``(mean_x min_y |x-y| + mean_y min_x |x-y|) / 2``; x: [N, D], y: [M, D]."""
    dxy = knn(x.double(), y.double(), 1)[0][:, 0].mean()
    dyx = knn(y.double(), x.double(), 1)[0][:, 0].mean()
    return float(0.5 * (dxy + dyx))


def content_chamfer(result: torch.Tensor, content: torch.Tensor) -> float:
    """Chamfer(result, content) in units of the content's mean nearest-neighbour spacing."""
    h = float(knn_mean_dist(content.double(), 1).mean()) if len(content) > 1 else 1.0
    return chamfer(result, content) / max(h, 1e-12)


def surface_distance(x: torch.Tensor, y: torch.Tensor, k: int = 8) -> torch.Tensor:
    """Distance of each point of x [N, 3] to the surface sampled by y [M, 3] -> [N]: to the plane of its
    k nearest y (centroid c, normal n the smallest principal axis), |(x - c) . n|, where x lies over
    that neighbourhood (tangential offset within its largest radius); else to the nearest y. Unlike
    the nearest-point distance it does not grow with y's sampling spacing."""
    d, i = knn(x.double(), y.double(), k)
    nb = y.double()[i]  # [N, k, 3]
    c = nb.mean(1)
    q = nb - c[:, None]
    n = torch.linalg.eigh(q.transpose(1, 2) @ q)[1][..., 0]  # smallest axis
    v = x.double() - c
    along = (v * n).sum(-1)
    tangential = (v - along[:, None] * n).norm(dim=-1)
    over = tangential <= q.norm(dim=-1).max(1).values
    return torch.where(over, along.abs(), d[:, 0])


def coarse_chamfer(result: torch.Tensor, content: torch.Tensor, length: float, support: int = 20000,
                   seed: int = 0) -> float:
    """Symmetric surface distance (:func:`surface_distance`, mean both ways, /2) of result [N, 3] and
    content [M, 3], each smoothed at ``length`` (sigma = length / 2, over at most ``support`` of its own
    points), in units of the unsmoothed content's mean spacing."""
    from .geometry import gaussian_smooth

    if length <= 0:
        raise ValueError(f"coarse Chamfer: the smoothing length must be > 0, got {length}")
    g = torch.Generator().manual_seed(seed)
    rs = gaussian_smooth(result, result[_subsample(len(result), support, g)], length / 2)
    cs = gaussian_smooth(content, content[_subsample(len(content), support, g)], length / 2)
    h = float(knn_mean_dist(content.double(), 1).mean()) if len(content) > 1 else 1.0
    d = 0.5 * (surface_distance(rs, cs).mean() + surface_distance(cs, rs).mean())
    return float(d) / max(h, 1e-12)


def principal_frames(p: torch.Tensor) -> torch.Tensor:
    """Normalize patches p: [P, k, 3] -> [P, k, 3] centred, in their principal frame (decreasing
    variance, each axis' sign making the third moment positive) and scaled to unit RMS radius."""
    c = p - p.mean(1, keepdim=True)
    cov = c.transpose(1, 2) @ c / p.shape[1]
    _, vec = torch.linalg.eigh(cov)  # ascending
    q = c @ vec.flip(-1)
    s = torch.sign((q**3).sum(1, keepdim=True))
    q = q * torch.where(s == 0, torch.ones_like(s), s)
    return q / q.pow(2).sum(-1).mean(-1).sqrt().clamp_min(1e-12)[:, None, None]


def sample_patches(points: torch.Tensor, n: int, k: int, g: torch.Generator, stride: int = 1) -> torch.Tensor:
    """``n`` random centres (with replacement when n > N) and every ``stride``-th of their ``k * stride``
    nearest points (by rank): [n, k, 3]. A stride > 1 widens a patch at the same cost."""
    N = len(points)
    kk = min(k * stride, N)
    idx = torch.randint(0, N, (n,), generator=g) if n > N else torch.randperm(N, generator=g)[:n]
    nb = knn(points[idx], points, kk)[1][:, ::stride]
    return points[nb]


def _pairwise_chamfer(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """a: [P, k, 3], b: [Q, k, 3] -> [P, Q] symmetric Chamfer distances."""
    d = torch.cdist(a[:, None].expand(-1, len(b), -1, -1).reshape(-1, a.shape[1], 3),
                    b[None].expand(len(a), -1, -1, -1).reshape(-1, b.shape[1], 3))
    return (0.5 * (d.min(2).values.mean(1) + d.min(1).values.mean(1))).reshape(len(a), len(b))


def patch_match(a: torch.Tensor, b: torch.Tensor, rotations: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """For each normalized patch of ``a`` [P, k, 3], the smallest Chamfer distance to a patch of ``b``
    [Q, k', 3] over ``rotations`` in-plane rotations of ``a``: (distance [P], index into b [P], the
    rotated a patches [P, k, 3])."""
    best = torch.full((len(a),), math.inf, dtype=a.dtype)
    arg = torch.zeros(len(a), dtype=torch.long)
    rot = a.clone()
    for r in range(rotations):
        t = 2 * math.pi * r / rotations
        R = a.new_tensor([[math.cos(t), -math.sin(t), 0], [math.sin(t), math.cos(t), 0], [0, 0, 1]])
        ar = a @ R.T
        for i in range(0, len(a), 16):  # [16, Q, k, k] distance blocks
            d = _pairwise_chamfer(ar[i:i + 16], b)
            v, j = d.min(1)
            better = v < best[i:i + 16]
            best[i:i + 16] = torch.where(better, v, best[i:i + 16])
            arg[i:i + 16] = torch.where(better, j, arg[i:i + 16])
            rot[i:i + 16][better] = ar[i:i + 16][better]
    return best, arg, rot


def tilt_degrees(scene: GaussianScene, k: int) -> torch.Tensor:
    """Angle in degrees [0, 90] between each Gaussian's shortest axis and the local surface normal."""
    m = scene.means.double()
    n = local_normals(m, m, k)
    a = shortest_axis(scene.quats.double(), scene.scales.double())
    return torch.rad2deg(torch.arccos((n * a).sum(-1).abs().clamp(0, 1)))


def shape_descriptors(points: torch.Tensor, centres: torch.Tensor, ks: tuple) -> torch.Tensor:
    """Local shape around points[centres]: points [N, 3], centres [C] -> [C, len(ks), 2] holding, per
    neighbourhood of the k nearest points, ``sqrt(l3 / (l1 + l2))`` and ``sqrt(l2 / l1)`` of its
    covariance eigenvalues l1 >= l2 >= l3 (k capped at N)."""
    p = points.double()
    kmax = min(max(ks), len(p))
    _, nb = knn(p[centres], p, kmax)
    out = []
    for k in ks:
        q = p[nb[:, :min(k, kmax)]]
        c = q - q.mean(1, keepdim=True)
        lam = torch.linalg.eigvalsh(c.transpose(1, 2) @ c / q.shape[1]).clamp_min(0)  # ascending
        l3, l2, l1 = lam[:, 0], lam[:, 1], lam[:, 2]
        height = (l3 / (l1 + l2).clamp_min(1e-30)).sqrt()
        iso = (l2 / l1.clamp_min(1e-30)).sqrt()
        out.append(torch.stack([height, iso], -1))
    return torch.stack(out, 1)


def relief_w1(result: torch.Tensor, style: torch.Tensor, cfg: "MetricsConfig") -> float:
    """``relief_w1`` of the module docstring; result [N, 3], style [M, 3] means."""
    rng = lambda: torch.Generator().manual_seed(cfg.seed)  # noqa: E731
    da = shape_descriptors(result, _subsample(len(result), cfg.relief_centres, rng()), cfg.relief_scales)
    db = shape_descriptors(style, _subsample(len(style), cfg.relief_centres, rng()), cfg.relief_scales)
    return float(np.mean([wasserstein_1d(da[:, i, j], db[:, i, j]) for i in range(da.shape[1]) for j in range(2)]))


COHERENCE_FRACTIONS = (1 / 32, 1 / 16, 1 / 8)  # element_colour_w1's neighbourhoods, in elements (n_e)
THICKNESS_FRACTION = 1 / 4  # element_thickness_w1's neighbourhood, in elements (benchmarks/whole_fractions.py)
MIN_NEIGHBOURS = 8


def element_descriptors(means: torch.Tensor, rgb: torch.Tensor, n_e: int, tau: float, centres: torch.Tensor,
                        thickness_fraction: float = THICKNESS_FRACTION):
    """Per centre (means [N, 3], rgb [N, 3], centres [C] indices) the descriptors of :func:`element_metrics`:
    (colour variance [C, len(COHERENCE_FRACTIONS)], thickness [C], NaN where fewer than MIN_NEIGHBOURS
    Gaussians within colour distance ``tau`` of the centre's are among its n_e * ``thickness_fraction`` nearest)."""
    x, c = means.double(), rgb.double()
    ks = [max(MIN_NEIGHBOURS, round(n_e * f)) for f in (*COHERENCE_FRACTIONS, thickness_fraction)]
    kmax = min(max(ks), len(x))
    *ks, kt = [min(k, kmax) for k in ks]
    cols, thicks = [], []
    # centres in chunks of about 2^22 neighbour entries: memory bounded whatever the element size
    for part in centres.split(max(1, 2**22 // kmax)):
        _, nb = knn(x[part], x, kmax)
        cols.append(torch.stack([c[nb[:, :k]].var(1, unbiased=False).sum(-1) for k in ks], 1))
        q, w = x[nb[:, :kt]], (c[nb[:, :kt]] - c[part, None]).norm(dim=-1) <= tau
        n = w.sum(1, keepdim=True).clamp_min(1)
        d = (q - (q * w[..., None]).sum(1, keepdim=True) / n[..., None]) * w[..., None]
        lam = torch.linalg.eigvalsh(d.transpose(1, 2) @ d / n[..., None]).clamp_min(0)  # ascending
        thick = (lam[:, 0] / (lam[:, 1] + lam[:, 2]).clamp_min(1e-30)).sqrt()
        thicks.append(torch.where(w.sum(1) >= MIN_NEIGHBOURS, thick, torch.nan))
    return torch.cat(cols), torch.cat(thicks)


def colour_tolerance(means: torch.Tensor, rgb: torch.Tensor, g: torch.Generator, centres: int = 8192) -> float:
    """tau of :func:`element_metrics`: the median RGB distance from a Gaussian to its 8 nearest (means [N, 3],
    rgb [N, 3]; over ``centres`` seeded random Gaussians)."""
    idx = _subsample(len(means), centres, g)
    _, nb = knn(means.double()[idx], means.double(), MIN_NEIGHBOURS + 1, exclude_self=True)
    return float((rgb.double()[nb] - rgb.double()[idx, None]).norm(dim=-1).median())


def element_metrics(result: GaussianScene, style: GaussianScene, n_e: int, cfg: "MetricsConfig",
                    thickness_fraction: float = THICKNESS_FRACTION) -> dict:
    """``element_colour_w1`` and ``element_thickness_w1`` of the module docstring; n_e: the style's median
    Gaussians per element (segment). Each side's centres are drawn by a fresh generator seeded with
    ``cfg.seed``: the same cloud scores 0. ``thickness_fraction``: benchmarks/whole_fractions.py's sweep."""
    if n_e < 1:
        raise ValueError(f"element metrics: the style's element size must be >= 1 Gaussian, got {n_e}")
    rng = lambda: torch.Generator().manual_seed(cfg.seed)  # noqa: E731
    tau = colour_tolerance(style.means, style.rgb, rng())
    ca, ta = element_descriptors(result.means, result.rgb, n_e, tau, _subsample(len(result), cfg.element_centres, rng()),
                                 thickness_fraction)
    cb, tb = element_descriptors(style.means, style.rgb, n_e, tau, _subsample(len(style), cfg.element_centres, rng()),
                                 thickness_fraction)

    def unit_free(u: torch.Tensor, v: torch.Tensor) -> float | None:
        u, v = u[~u.isnan()], v[~v.isnan()]
        if len(u) == 0 or len(v) == 0:
            return None
        iqr = float(v.quantile(0.75) - v.quantile(0.25))
        return wasserstein_1d(u, v) / max(iqr, 1e-12)

    colour = [unit_free(ca[:, i], cb[:, i]) for i in range(ca.shape[1])]
    return {"element_colour_w1": None if None in colour else float(np.mean(colour)),
            "element_thickness_w1": unit_free(ta, tb), "element_size_gaussians": int(n_e),
            "element_colour_tolerance": tau, "element_thickness_counted": float((~ta.isnan()).float().mean())}


def wasserstein_1d(u: torch.Tensor, v: torch.Tensor) -> float:
    """Exact W1 between two 1-D empirical distributions."""
    from scipy.stats import wasserstein_distance

    return float(wasserstein_distance(u.double().numpy(), v.double().numpy()))


def _subsample(n: int, m: int, g: torch.Generator) -> torch.Tensor:
    return torch.randperm(n, generator=g)[:m] if n > m else torch.arange(n)


def colour_sinkhorn(a: torch.Tensor, b: torch.Tensor, cfg: MetricsConfig, dtype=torch.float32) -> float:
    """``colour_sinkhorn`` of the module docstring: S_eps (blur ``cfg.blur``) between ``cfg.colour_points``
    seeded random rows of the colours a [N, 3] and b [M, 3]. Solved in float32 by default: within 3e-6
    of float64 on the demo's methods, 7x faster (``benchmarks/float32_solves.py``)."""
    from .sinkhorn import sinkhorn

    rng = lambda: torch.Generator().manual_seed(cfg.seed)  # noqa: E731
    ia, ib = _subsample(len(a), cfg.colour_points, rng()), _subsample(len(b), cfg.colour_points, rng())
    return float(sinkhorn(a[ia].to(dtype), b[ib].to(dtype), _solver(cfg), grad_y=False).value)


def _solver(cfg: MetricsConfig):
    """The Sinkhorn settings of the metrics' divergences (patch and colour)."""
    from .sinkhorn import SinkhornConfig

    return SinkhornConfig(blur=cfg.blur, scaling=0.7, extra_iters=20)


def style_metrics(result: GaussianScene, style: GaussianScene, cfg: MetricsConfig) -> dict:
    """The style-fidelity metrics of the module docstring."""
    from .sinkhorn import sinkhorn

    if len(result) < 2 or len(style) < 2:
        raise ValueError(f"metrics: need at least 2 Gaussians on each side (result {len(result)}, style {len(style)})")
    scfg = _solver(cfg)
    # each side draws from a fresh generator with the same seed: identical clouds -> identical samples
    rng = lambda: torch.Generator().manual_seed(cfg.seed)  # noqa: E731
    patch_chamfer = patch_sinkhorn = None
    if cfg.patches:
        pa = principal_frames(sample_patches(result.means.double(), cfg.patches, cfg.patch_size, rng(), cfg.patch_stride))
        pb = principal_frames(sample_patches(style.means.double(), cfg.candidates, cfg.patch_size, rng(), cfg.patch_stride))
        best, arg, rot = patch_match(pa, pb, cfg.rotations)
        patch_chamfer = float(best.mean())
        patch_sinkhorn = float(np.mean([float(sinkhorn(rot[i], pb[arg[i]], scfg, grad_y=False).value)
                                        for i in range(len(pa))]))
    colour = colour_sinkhorn(result.rgb, style.rgb, cfg)
    tr, ts = tilt_degrees(result, cfg.normal_k), tilt_degrees(style, cfg.normal_k)
    ar, as_ = anisotropy(result.scales.double()).log10(), anisotropy(style.scales.double()).log10()
    return {
        "style_patch_chamfer": patch_chamfer,
        "style_patch_sinkhorn": patch_sinkhorn,
        "tilt_w1_deg": wasserstein_1d(tr, ts),
        "aniso_w1": wasserstein_1d(ar, as_),
        "relief_w1": relief_w1(result.means, style.means, cfg),
        "colour_sinkhorn": colour,
        "tilt_median_deg": float(tr.median()), "style_tilt_median_deg": float(ts.median()),
        "aniso_median_log10": float(ar.median()), "style_aniso_median_log10": float(as_.median()),
    }


def weights_free_metrics(result: GaussianScene, content_points: torch.Tensor, style: GaussianScene,
                         cfg: MetricsConfig) -> dict:
    """All weights-free metrics of ``result`` against the content surface samples [M, 3] and the style."""
    return {"content_chamfer": content_chamfer(result.means, content_points), **style_metrics(result, style, cfg),
            "gaussians": len(result)}

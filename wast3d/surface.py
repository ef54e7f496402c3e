"""Stage 2, surface sampling of the content scene.

3DGS scenes carry floaters around objects and Gaussians hidden inside them; clusters should follow
the visible surface. The sampler chains four steps, each switchable, and reports what each removed:

1. ``min_opacity``: drop nearly transparent Gaussians (opacity below the threshold);
2. outliers (the official WaSt-3D notebooks' rule): drop Gaussians whose distance to their
   ``outlier_k``-th nearest neighbour is above the ``outlier_quantile`` quantile (default 30th, 0.95);
3. visibility: render the Gaussians kept so far (expected depth and alpha) from ``views`` orbit
   cameras fitted to them and keep those whose centre lies within ``depth_tolerance`` (a fraction of
   the scene radius) of the rendered surface, where alpha > 0.5, in at least one view. Interior and
   occluded Gaussians go;
4. density-uniform resampling: keep at most ``max_points`` Gaussians, drawn without replacement with
   probability proportional to the cube of the distance to the ``density_k``-th neighbour (inverse
   local density), so dense patches do not dominate the clusters.

``mode: backproject`` (the paper's "we sample points on the surface of the content scene"): after
steps 1-2, the Gaussians kept are rendered from the ``views`` orbit cameras (expected depth, colour,
the normals of their shortest axes), every pixel with alpha > 0.9 whose surface faces the camera
within 60 degrees is back-projected to a 3D point,
and the points of all views are fused on a voxel grid of ``spacing`` (a fraction of the scene's robust
radius; 0: about as many points as Gaussians kept, never finer than their median spacing; the median
spacing alone gave a capture with large Gaussians 10x as many points as Gaussians): one point per voxel, the mean of its position, its
straight colour and its normal. The result is spread by area over the visible surface whatever the
sizes of the Gaussians that drew it (a trained capture's Gaussians span 0.004-0.068 in largest axis):
a cluster then covers a fixed area and every content point, with uniform mass, stands for the same
area in the transport. Each point becomes a flat Gaussian (scales spacing/2, spacing/2, spacing/10)
facing its normal. ``mode: footprints``: after steps 1-3, ``oversample`` points per Gaussian kept are
drawn over the Gaussians' footprints, each Gaussian with probability by its footprint (opacity times
its two largest scales), each point spread along its two largest axes (:func:`footprint_samples`),
with its Gaussian's colour and outward normal (:func:`outward_normals`), and fused on the same voxel
grid: uniform by area like the back-projection, but on the Gaussians themselves (no depth of a pixel
mixing a thin part with what lies behind it). ``mode: filter`` (default) keeps the Gaussians
themselves.

Procedural and other already-clean scenes set ``enabled: false``: every Gaussian is kept and the
report says the stage was skipped and why.

Style cleaning (:func:`clean_style`, :class:`StyleCleanConfig`) applies the same steps to a *trained
style* with the style's own rules: a style is a patch seen from above (its training views orbit it at
positive elevations), so visibility is judged from above only; and a trained patch carries floaters
far outside it (the demo's trained pebbles span 3.8 x 3.7 x 3.3 units for a 2 x 2 x 0.16 patch), so
Gaussians outside the patch's *core box* (per-axis ``core_quantile`` .. 1 - ``core_quantile`` of the
opaque Gaussians, widened by ``core_margin`` of its size on each side) go first. Nearly transparent
Gaussians (haze that no training view resolves) and hidden ones are what put tints into a result
that the style's renders never show. *Hidden* is judged by what each Gaussian draws
(:func:`seen_fraction`: the share of it that its best view from above shows), not by its centre's
distance to the rendered depth: a trained surface is made of overlapping Gaussians whose centres lie
off it, and the depth test at 0.02 scene radii removed visible ones (dark spots in the pebbles) while
at 0.05 it kept opaque interior ones. *Below the ground*: Gaussians whose
centre lies more than ``below_ground`` relief heights under the ground a view from above meets
(:func:`ground_and_relief`). A view from above sees them only through gaps (their seen fractions,
0.06-0.44, pass the hidden test), but every cut the selection makes through the patch exposes them,
and on the content they are seen from the side: on the demo's trained pebbles, 225 Gaussians more
than 0.05 under the ground (3 % of the collage's) drew 38 % of its close-up's pixels, large opaque
blobs in tints the style's renders do not show. A two-layer weave would lose its lower strands to
this rule (the procedural wicker, which is never cleaned, loses 6,535 of 30,000). *Colour
outliers* (``colour_outliers`` > 0, off by default): Gaussians whose colour lies farther than that (RGB
distance) from the median colour of their ``colour_k`` nearest kept neighbours; a trained patch holds
a few percent of magenta, blue or green Gaussians inside brown and grey pebbles, mostly seen through
gaps, which the stylization exposes as specks. Dropping them moves the relief (positions go);
``recolour`` (0.3) gives a kept Gaussian farther than that from its neighbours' median colour that
median instead, every position and label staying, where its colour also lies farther than
``shown_limit`` (0.3) from what the style's own renders show at it (:func:`shown_colours`). The first
test alone cleans the trained demo styles but smears a real capture whose small features are colour
(the shared fruit label's dark letters on white turn grey: its white Gaussians' neighbours are the
letters'); the second spares what the renders show, and a trained speck is what they do not
(docs/method.md, stage 2).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace

import numpy as np
import torch

from .gaussians import GaussianScene, footprint, rgb_to_sh_dc
from .geometry import knn
from .options import checked, option
from .volume import FORMS, style_form

log = logging.getLogger(__name__)


SURFACE_MODES = ("filter", "footprints", "backproject")


@dataclass
@checked("surface")
class SurfaceConfig:
    enabled: bool = option(True, "false: pass the scene through unchanged")
    min_opacity: float = option(0.05, "drop Gaussians below this opacity", minimum=0, maximum=1)
    outlier_k: int = option(30, "outlier rule: distance to the k-th neighbour (0: off)", minimum=0)
    outlier_quantile: float = option(0.95, "outlier rule: drop Gaussians whose k-th-neighbour distance is above this "
                                           "quantile", exclusiveMinimum=0, maximum=1)
    visibility: bool = option(True, "keep only centres within depth_tolerance of the rendered depth in at least one "
                                    "view (removes interior Gaussians)")
    views: int = option(24, "orbit views of the visibility test", minimum=1)
    resolution: int = option(200, "pixels (side) of the visibility renders", minimum=16, maximum=16384)
    depth_tolerance: float = option(0.02, "visibility: distance to the rendered depth, as a fraction of the scene "
                                          "radius", exclusiveMinimum=0)
    max_points: int = option(0, "density-uniform resampling down to this many points (0: off)", minimum=0)
    density_k: int = option(8, "resampling: probability proportional to the cubed distance to this neighbour",
                               minimum=1)
    mode: str = option("filter", "filter: the Gaussians kept; footprints: points drawn over the kept Gaussians' "
                                 "footprints by area and fused on a voxel grid; backproject: the kept Gaussians' orbit "
                                 "renders back-projected and fused on a voxel grid (points uniform by area)",
                                 enum=SURFACE_MODES)
    spacing: float = option(0.0, "footprints, backproject: voxel size as a fraction of the scene's radius (0: about as "
                                 "many points as Gaussians kept, never finer than their median spacing)", minimum=0)
    oversample: int = option(8, "footprints: points drawn per Gaussian kept, before the fusion", minimum=1)
    seed: int = option(0, "seed of the resampling")


@dataclass
@checked("style_clean")
class StyleCleanConfig:
    enabled: bool = option(True, "false: use the style scene as it is")
    form: str = option("auto", "patch (a ground with elements on it, seen from above), volume (an object seen from every "
                               "side: its elements, or label-free pieces, laid side by side on a sheet, outer side up) "
                               "or auto: volume where the style is thicker than 0.35 of its width (wast3d.volume)",
                       enum=list(FORMS))
    min_opacity: float = option(0.05, "drop Gaussians below this opacity (translucent haze)", minimum=0, maximum=1)
    core_quantile: float = option(0.01, "patch box: these quantiles (and 1 minus them) of the opaque Gaussians' "
                                        "positions, per axis", minimum=0, exclusiveMaximum=0.5)
    core_opacity: float = option(0.5, "patch box: opacity from which a Gaussian counts as opaque", minimum=0, maximum=1)
    core_margin: float = option(0.05, "patch box: widened by this fraction of its size on each side; outside it, "
                                      "floaters", minimum=0)
    max_scale: float = option(0.0, "drop Gaussians whose largest axis is above this many times the median largest axis "
                                   "(0: off)", minimum=0)
    outlier_k: int = option(30, "outlier rule: distance to the k-th neighbour (0: off)", minimum=0)
    outlier_quantile: float = option(0.99, "outlier rule: drop Gaussians whose k-th-neighbour distance is above this "
                                           "quantile", exclusiveMinimum=0, maximum=1)
    visibility: bool = option(True, "drop hidden Gaussians: those of which less than min_seen is seen in every view "
                                    "from above")
    views: int = option(24, "views (elevations 15-80 degrees) of the visibility test", minimum=1)
    resolution: int = option(200, "pixels (side) of the visibility renders", minimum=16, maximum=16384)
    min_seen: float = option(0.2, "visibility: the share of a Gaussian (its blending weight over its weight alone and "
                                  "face-on) its best view must show. A trained patch keeps a dense ground under its "
                                  "elements that its own views barely show and the content's curved surface lays "
                                  "bare (the demo's trained grass: 37 % of its Gaussians at 0.05, 25 % at 0.2, its "
                                  "source 20 %); 0.2 leaves the style's renders within 30-35 dB of 0.05's, 0.4 "
                                  "opens holes in them", minimum=0)
    below_ground: float = option(0.5, "drop Gaussians whose centre lies more than this many relief heights under the "
                                      "ground a view from above meets (a trained patch's unseen underside; 0: off)",
                                      minimum=0)
    colour_outliers: float = option(0.0, "drop Gaussians whose RGB lies farther than this from the median of their "
                                         "colour_k nearest neighbours (0: off): specks of odd colour inside the "
                                         "elements", minimum=0)
    recolour: float = option(0.3, "the colour-outlier test (this limit) on the kept Gaussians, which take their "
                                  "neighbours' median colour instead of going: positions, relief and labels stay (0: "
                                  "off). With shown_limit, only specks the style's renders do not show", minimum=0)
    colour_k: int = option(16, "neighbours of the colour-outlier test", minimum=1)
    shown_limit: float = option(0.3, "recolour only Gaussians whose RGB also lies farther than this from the colour the "
                                     "style's own renders show at them (surface.shown_colours, the visibility test's "
                                     "views): a trained speck its neighbours' blending hid, not a real capture's "
                                     "colour feature (0: off)", minimum=0)
    refit: int = option(0, "steps of the appearance refit (:func:`refit_appearance`): the kept Gaussians' scales, "
                           "opacities and colours fitted to the renders of the whole patch (before cleaning, floaters "
                           "excepted) on the visibility test's views, so that the layers and translucent fill cleaning "
                           "removed from under them leave no gaps (0: off)", minimum=0)
    dilate: float = option(0.0, "each kept Gaussian's variance grows by (dilate x the kept Gaussians' median "
                                "nearest-neighbour distance)^2 on every axis, opacity kept: a trained surface of "
                                "small Gaussians closes where its gaps let what lies behind show through (0: off)",
                           minimum=0)
    seed: int = option(0, "seed")

    def __post_init__(self):
        if not self.min_opacity < 1:
            raise ValueError(f"style_clean.min_opacity must be < 1 (1 would drop every Gaussian), got {self.min_opacity}")


CONTENT_ELEVATIONS = (-30.0, 10.0, 40.0, 75.0)
STYLE_ELEVATIONS = (15.0, 35.0, 55.0, 80.0)  # a style patch is seen from above (cf. render.export_blender)
REFIT_GROWTH = 1.5  # refit_appearance: the most each scale may grow


def median_spacing(points: torch.Tensor) -> float:
    """The median distance of points [N >= 2, 3] to their nearest other point."""
    p = points.detach()
    return float(knn(p, p, 1, exclude_self=True)[0].median())


def _pixels_of(points: torch.Tensor, cam) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The points [N, 3] in front of ``cam`` that land inside its image: their indices [n], pixel columns
    u [n], rows v [n] and camera depths z [n]."""
    V = cam.world_to_cam.to(points)
    pc = points @ V[:3, :3].T + V[:3, 3]
    z = pc[:, 2]
    u = (cam.fx * pc[:, 0] / z.clamp_min(1e-9) + cam.cx).floor().long()
    v = (cam.fy * pc[:, 1] / z.clamp_min(1e-9) + cam.cy).floor().long()
    inside = (z > cam.near) & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
    idx = inside.nonzero().squeeze(1)
    return idx, u[idx], v[idx], z[idx]


def _visible_in(scene: GaussianScene, cam, tol: float, radius: float) -> torch.Tensor:
    """[N] bool: the centre lies on the surface ``cam`` renders (|z - depth| < tol * radius, alpha > 0.5)."""
    from .rasterizer import rasterize

    r = rasterize(scene, cam)
    idx, u, v, z = _pixels_of(scene.means, cam)
    ok = (r.alpha[v, u] > 0.5) & ((z - r.depth[v, u]).abs() < tol * radius)
    seen = torch.zeros(len(scene), dtype=torch.bool)
    seen[idx[ok]] = True
    return seen


@torch.no_grad()
def visible_mask(scene: GaussianScene, views: int, resolution: int, tol: float,
                 elevations_deg: tuple = CONTENT_ELEVATIONS) -> torch.Tensor:
    """[N] bool: the centre lies on the rendered surface (|z - depth| < tol * radius, alpha > 0.5)
    in at least one of ``views`` orbit views (at ``elevations_deg``, cycled)."""
    from .cameras import fit_orbit, scene_bounds

    _, radius = scene_bounds(scene)
    seen = torch.zeros(len(scene), dtype=torch.bool)
    for cam in fit_orbit(scene, views, resolution, elevations_deg=elevations_deg):
        seen |= _visible_in(scene, cam, tol, radius)
    return seen


@torch.no_grad()
def outward_normals(scene: GaussianScene, views: int = 24, resolution: int = 128, tol: float = 0.02,
                    elevations_deg: tuple = CONTENT_ELEVATIONS) -> tuple[torch.Tensor, torch.Tensor]:
    """Each Gaussian's outward normal [N, 3] (float64) and whether a view decided its sign [N] bool.

    The normal is the Gaussian's shortest axis n_i; its sign is that of
    ``sum_v seen_iv sign(n_i . (c_v - x_i))`` over the ``views`` orbit cameras c_v whose render shows
    the centre x_i on its surface (:func:`visible_mask`'s test): the outside of a surface is the side it
    is seen from. Gaussians no view decides (hidden, or a tie) keep the side facing away from the
    scene's centre. A ray test through an occupancy grid got 27 % of the ant's signs wrong on its thin
    legs; this one is right wherever a camera sees the surface."""
    from .gaussians import shortest_axis
    from .cameras import fit_orbit, scene_bounds

    centre, radius = scene_bounds(scene)
    x = scene.means.detach()
    n = shortest_axis(scene.quats.detach(), scene.scales.detach()).double()
    vote = torch.zeros(len(scene), dtype=torch.float64)
    for cam in fit_orbit(scene, views, resolution, elevations_deg=elevations_deg):
        seen = _visible_in(scene, cam, tol, radius)
        c = cam.center.double()
        vote += seen.double() * torch.sign(((c - x.double()) * n).sum(1))
    decided = vote != 0
    away = torch.sign(((x.double() - torch.as_tensor(centre).double()) * n).sum(1))
    sign = torch.where(decided, torch.sign(vote), torch.where(away == 0, torch.ones_like(away), away))
    return n * sign[:, None], decided


def _blend_weights(s: GaussianScene, cam, image: torch.Tensor | None = None):
    """(w [N], wi [N, 3] or None): each Gaussian's blending weights in ``cam``'s render summed over the
    pixels, sum_p alpha_i(p) T_i(p) (the gradient of the render's sum with respect to per-Gaussian colours
    of 1), and with ``image`` [H, W, 3] the same sum weighting each pixel by its value there."""
    from .rasterizer import rasterize

    ones = torch.ones(len(s), 3, dtype=s.dtype, requires_grad=True)
    out = rasterize(s, cam, colors=ones)
    (w,) = torch.autograd.grad(out.rgb[..., 0].sum(), ones, retain_graph=image is not None)
    wi = None if image is None else torch.autograd.grad((out.rgb * image).sum(), ones)[0]
    return w[:, 0], wi


def seen_fraction(scene: GaussianScene, views: int, resolution: int, elevations_deg: tuple) -> torch.Tensor:
    """[N] how much of each Gaussian the renders show, in its best of ``views`` orbit views:

        f_i = max_v  (sum_pixels alpha_i T_i) * (z_i / f)^2 / (o_i * 2 pi s_1 s_2)

    the total blending weight it gets (pixels; exactly the gradient of the rendered image's sum with
    respect to per-Gaussian colours of 1) over the weight it would have alone and face-on (its opacity
    times the integral of its footprint, s_1 s_2 its two largest scales, z_i / f the pixel size at its
    depth). About 1 for an unoccluded Gaussian seen face-on, 0 for one hidden in every view; independent
    of the resolution and of the Gaussians' sizes."""
    from .cameras import fit_orbit

    best = torch.zeros(len(scene), dtype=torch.float64)
    s = scene.detach()
    alone = 2 * torch.pi * footprint(s.scales, s.opacities)
    for cam in fit_orbit(s, views, resolution, elevations_deg=elevations_deg):
        w, _ = _blend_weights(s, cam)
        V = cam.world_to_cam.to(s.means)
        z = (s.means @ V[2, :3] + V[2, 3]).double()
        f = w.double().cpu() * (z / cam.fx) ** 2 / alone.clamp_min(1e-30)
        best = torch.maximum(best, torch.where(z > cam.near, f, torch.zeros_like(f)))
    return best


def shown_colours(scene: GaussianScene, views: int, resolution: int,
                  elevations_deg: tuple = STYLE_ELEVATIONS) -> torch.Tensor:
    """[N, 3] the colour the scene's own renders show where each Gaussian is drawn:

        shown_i = sum_v sum_p w_iv(p) R_v(p) / sum_v sum_p w_iv(p)

    over ``views`` orbit views, w_iv(p) Gaussian i's blending weight at pixel p (the gradient of the
    render with respect to its colour, as in :func:`seen_fraction`), R_v(p) the render's colour
    un-premultiplied by its alpha (the background does not enter). A Gaussian whose colour the blending
    with its neighbours hid gets theirs. One that its neighbours overlap shows about its own colour; an
    isolated one, about half of it blended with what surrounds it (for a Gaussian profile
    sum_p alpha^2 / sum_p alpha = o / 2), so the test errs towards keeping a colour. Gaussians no view
    draws get their own colour. (The colour at each one's centre pixel in its best view was tried too:
    it recoloured 2.5x more of the fruit capture's Gaussians, with grey smudges on its letters.)"""
    from .cameras import fit_orbit
    from .rasterizer import rasterize

    s = scene.detach()
    num = torch.zeros(len(s), 3, dtype=torch.float64)
    den = torch.zeros(len(s), dtype=torch.float64)
    for cam in fit_orbit(s, views, resolution, elevations_deg=elevations_deg):
        with torch.no_grad():
            r = rasterize(s, cam)
            shown = r.rgb / r.alpha.clamp_min(1e-6)[..., None]
        w, g = _blend_weights(s, cam, shown)
        num += g.double().cpu()
        den += w.double().cpu()
    own = s.rgb.clamp(0, 1).double().cpu()
    drawn = den > 1e-9
    return torch.where(drawn[:, None], num / den.clamp_min(1e-30)[:, None], own).to(s.means)


def _drop(keep: torch.Tensor, out: torch.Tensor, report: dict, key: str) -> None:
    """Clear ``out`` [N] bool from ``keep`` and count the newly removed under ``report[key]``."""
    report[key] = int((keep & out).sum())
    keep &= ~out


def _outliers(scene: GaussianScene, keep: torch.Tensor, k: int, quantile: float, report: dict) -> None:
    """Drop kept Gaussians whose k-th neighbour distance (among the kept) is above the quantile."""
    idx = keep.nonzero().squeeze(1)
    if k > 0 and len(idx) > k + 1:
        d, _ = knn(scene.means[idx], scene.means[idx], k, exclude_self=True)
        dk = d[:, -1]
        thr = torch.quantile(dk.double(), quantile).to(dk)
        out = torch.zeros_like(keep)
        out[idx[dk > thr]] = True
        _drop(keep, out, report, "removed_outliers")
        report["outlier_threshold"] = float(thr)


def _hidden(scene: GaussianScene, keep: torch.Tensor, views: int, resolution: int, tol: float, elevations,
            report: dict) -> None:
    # render only what survived the steps before: a removed floater would still occlude the surface
    # (the 0.3 px^2 dilation gives even a tiny Gaussian a pixel-sized footprint) and widen the
    # camera rig; with 25k floaters in a 1e6-Gaussian scene this cut the kept surface to 30 %
    idx = keep.nonzero().squeeze(1)
    vis = torch.zeros_like(keep)
    if len(idx):
        vis[idx[visible_mask(scene.subset(idx), views, resolution, tol, elevations)]] = True
    _drop(keep, ~vis, report, "removed_not_on_visible_surface")


def _begin(scene: GaussianScene, enabled: bool, what: str, role: str):
    """(keep [N] all True, report) to start a filter, or the skipped result ``(indices, report)`` when
    it is disabled; an empty scene is an error naming ``what`` and the scene's ``role``."""
    n = len(scene)
    if n == 0:
        raise ValueError(f"{what}: the {role} scene has no Gaussians")
    if not enabled:
        reason = f"{what} disabled for this scene (already a clean surface)"
        log.info("%s skipped: %s", what, reason)
        return None, (torch.arange(n), {"input": n, "skipped": True, "reason": reason, "kept": n})
    return (torch.ones(n, dtype=torch.bool), {"input": n}), None


def sample_surface(scene: GaussianScene, cfg: SurfaceConfig) -> tuple[torch.Tensor, dict]:
    """Indices [K] of the content Gaussians kept, and a report of counts removed and why."""
    start, skipped = _begin(scene, cfg.enabled, "surface sampling", "content")
    if skipped:
        return skipped
    (keep, report), n = start, len(scene)
    _drop(keep, scene.opacities.detach() < cfg.min_opacity, report, "removed_low_opacity")
    _outliers(scene, keep, cfg.outlier_k, cfg.outlier_quantile, report)
    if cfg.visibility:
        _hidden(scene, keep, cfg.views, cfg.resolution, cfg.depth_tolerance, CONTENT_ELEVATIONS, report)
    idx = keep.nonzero().squeeze(1)
    if len(idx) == 0:
        raise ValueError("surface sampling removed every Gaussian; relax min_opacity / depth_tolerance")
    if cfg.max_points and len(idx) > cfg.max_points:
        d, _ = knn(scene.means[idx], scene.means[idx], cfg.density_k, exclude_self=True)
        w = d[:, -1].double().clamp_min(1e-12) ** 3
        g = torch.Generator().manual_seed(cfg.seed)
        pick = torch.multinomial(w / w.sum(), cfg.max_points, replacement=False, generator=g)
        report["removed_by_resampling"] = len(idx) - cfg.max_points
        idx = idx[pick.sort().values]
    return idx, _kept(report, idx, n, "surface sampling")


@torch.no_grad()
def backprojected_pixels(scene: GaussianScene, views: int, resolution: int,
                         elevations_deg: tuple = CONTENT_ELEVATIONS, tol: float = 0.02,
                         max_violations: int = 1) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """World points [P, 3], straight colours [P, 3] and normals [P, 3] of the pixels of ``views`` orbit
    renders of ``scene`` at ``resolution`` px that are solid (alpha > 0.9) and face the camera within 60
    degrees (float64), less the points that lie in front of the surface another view shows (depth
    below that view's solid rendered depth by more than ``tol`` x the scene's radius) in more than
    ``max_violations`` views: free space seen from elsewhere, where the expected depth of a pixel mixed a
    thin part with what lies behind it."""
    from .cameras import fit_orbit, scene_bounds
    from .render import RenderConfig, pixel_rays, render_maps

    cfg = RenderConfig(normals="axis", background=(0.0, 0.0, 0.0))
    _, radius = scene_bounds(scene)
    pts, cols, nrms, maps = [], [], [], []
    cams = fit_orbit(scene, views, resolution, elevations_deg=elevations_deg)
    for cam in cams:
        m = render_maps(scene, cam, cfg)
        ray = pixel_rays(cam)
        facing = -(m.normal.double() * ray).sum(-1) / ray.norm(dim=-1)
        # solid pixels of surfaces within 60 degrees of facing the camera: at a silhouette and at grazing
        # views the expected depth mixes surfaces (each Gaussian draws all its pixels at its centre's depth)
        fg = (m.alpha > 0.9) & (facing > 0.5)
        P = (ray * m.depth.double()[..., None])[fg]
        V = cam.world_to_cam.double()
        R, t = V[:3, :3], V[:3, 3]
        pts.append((P - t) @ R)  # camera -> world: R^T (p - t)
        cols.append(m.rgb.double()[fg] / m.alpha.double()[fg][:, None])  # straight colour (black background)
        nrms.append(m.normal.double()[fg] @ R)
        maps.append((m.depth.double(), m.alpha > 0.9))
    if not pts or sum(len(p) for p in pts) == 0:
        raise ValueError("back-projection: no view shows any of the scene")
    P, C, N = torch.cat(pts), torch.cat(cols).clamp(0, 1), torch.cat(nrms)
    violations = torch.zeros(len(P), dtype=torch.long)
    for cam, (depth, solid) in zip(cams, maps):
        i, u, v, z = _pixels_of(P, cam)
        bad = solid[v, u] & (z < depth[v, u] - tol * radius)
        violations[i[bad]] += 1
    keep = violations <= max_violations
    log.info("back-projection: %d of %d pixel points lie in free space seen from %d+ other views (dropped)",
             int((~keep).sum()), len(P), max_violations + 1)
    return P[keep], C[keep], N[keep]


def _voxel_index(points: torch.Tensor, spacing: float) -> tuple[torch.Tensor, int]:
    """Each point's voxel [P] among the V voxels of side ``spacing`` the points [P, 3] occupy, and V."""
    key = torch.floor((points - points.min(0).values) / spacing).long()
    _, inv = torch.unique(key, dim=0, return_inverse=True)
    return inv, int(inv.max()) + 1


def voxel_count(points: torch.Tensor, spacing: float) -> int:
    """How many voxels of side ``spacing`` the points [P, 3] occupy."""
    return _voxel_index(points, spacing)[1]


def voxel_means(P: torch.Tensor, spacing: float, *values: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """The mean of the points P [P, 3] in each voxel of side ``spacing`` they occupy [V, 3], and the
    mean of each of ``values`` ([P, D] each) over the same voxels (float64)."""
    inv, n = _voxel_index(P, spacing)
    count = torch.bincount(inv, minlength=n).double()[:, None]
    return tuple(torch.zeros(n, x.shape[1], dtype=torch.float64).index_add_(0, inv, x.double()) / count
                 for x in (P, *values))


def fuse_points(P: torch.Tensor, C: torch.Tensor, N: torch.Tensor, spacing: float, dtype=torch.float32) -> GaussianScene:
    """One flat Gaussian per voxel of side ``spacing`` that points P [P, 3] occupy: the mean of their
    positions, colours C and normals N (scales spacing/2, spacing/2, spacing/10, facing the normal)."""
    from .gaussians import rotmat_to_quat
    from .geometry import frame_from_normal

    if spacing <= 0:
        raise ValueError(f"back-projection: spacing must be > 0, got {spacing}")
    # normals of either sign fused as given: the renderer turns them towards each camera, and cameras on
    # one side of a surface agree; a thin part seen from both sides averages towards 0 and is re-normalized
    P, C, N = voxel_means(P, spacing, C, N)
    n = len(P)
    N = N / N.norm(dim=1, keepdim=True).clamp_min(1e-12)
    quats = rotmat_to_quat(frame_from_normal(N)).to(dtype)
    scales = torch.tensor([spacing / 2, spacing / 2, spacing / 10], dtype=dtype).expand(n, 3)
    return GaussianScene.from_activated(P.to(dtype), scales, quats, opacities=0.99, rgb=C.to(dtype))


def backproject_surface(scene: GaussianScene, views: int, resolution: int, spacing: float,
                        elevations_deg: tuple = CONTENT_ELEVATIONS) -> GaussianScene:
    """Surface points of ``scene`` (module docstring, ``mode: backproject``) fused at ``spacing``."""
    return fuse_points(*backprojected_pixels(scene, views, resolution, elevations_deg), spacing, scene.dtype)


@torch.no_grad()
def footprint_samples(scene: GaussianScene, count: int, normals: torch.Tensor, seed: int = 0
                      ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``count`` points [P, 3] drawn over the Gaussians' footprints by area, with their Gaussians' DC
    colours [P, 3] and the given normals [N, 3] of their Gaussians [P, 3] (float64).

    Gaussian i is drawn with probability ``o_i s_1 s_2`` (:func:`~wast3d.gaussians.footprint`), and a
    point of it at ``mu_i + R_i (s_1 z_1, s_2 z_2, 0)``, z standard normal clipped to [-2, 2]: its two
    largest axes span the surface it draws, its shortest one is across it. A large Gaussian of a trained
    capture (the guitar's largest 1 % hold 22 % of the footprint) becomes many points spread over its
    disc instead of one heavy point at its centre, onto which the transport would pile the style."""
    from .gaussians import footprint

    w = footprint(scene.scales, scene.opacities).clamp_min(0)
    if not torch.isfinite(w).all() or float(w.sum()) <= 0:
        raise ValueError("footprint sampling: the Gaussians' footprints are not finite and positive")
    g = torch.Generator().manual_seed(seed)
    parent = torch.multinomial(w / w.sum(), count, replacement=True, generator=g)
    sc, order = scene.scales.detach().double()[parent].sort(dim=1, descending=True)
    R = scene.rotations.detach().double()[parent]
    axes = R.gather(2, order[:, None, :2].expand(-1, 3, 2))  # [P, 3, 2]: the two largest axes
    z = torch.randn(count, 2, generator=g, dtype=torch.float64).clamp(-2, 2)
    P = scene.means.detach().double()[parent] + (axes * (sc[:, None, :2] * z[:, None, :])).sum(-1)
    return P, scene.rgb.detach().double()[parent].clamp(0, 1), normals.double()[parent]


def fused_count_spacing(P: torch.Tensor, n: int, h: float) -> float:
    """The voxel side, from ``h`` up, at which points P [P, 3] occupy about ``n`` voxels (within 10 %):
    h grown by ``sqrt(n_h / n)`` (the count falls slower than 1 / h^2 where the points have depth noise)."""
    for _ in range(4):
        grow = (voxel_count(P, h) / n) ** 0.5
        if grow <= 1.05:
            break
        h *= grow
    return h


def surface_points(scene: GaussianScene, cfg: SurfaceConfig) -> tuple[GaussianScene, dict]:
    """Stage 2's output scene and its report: the Gaussians :func:`sample_surface` keeps
    (``mode: filter``); points drawn over their footprints (``mode: footprints``,
    :func:`footprint_samples`, ``oversample`` per Gaussian kept, normals by :func:`outward_normals`); or
    points back-projected from the Gaussians kept by steps 1-2 (``mode: backproject``). The last two are
    fused at ``spacing`` (0: about as many points as Gaussians kept, never finer than their median
    spacing: :func:`fused_count_spacing`)."""
    if cfg.mode == "filter" or not cfg.enabled:
        idx, report = sample_surface(scene, cfg)
        return scene.subset(idx), report
    if cfg.mode == "footprints":
        idx, report = sample_surface(scene, replace(cfg, max_points=0))
        kept = scene.subset(idx)
        normals, _ = outward_normals(kept, cfg.views, min(cfg.resolution, 128), cfg.depth_tolerance)
        P, C, N = footprint_samples(kept, cfg.oversample * len(kept), normals, cfg.seed)
    else:
        idx, report = sample_surface(scene, replace(cfg, visibility=False, max_points=0))  # floaters and haze out
        kept = scene.subset(idx)
        P, C, N = backprojected_pixels(kept, cfg.views, cfg.resolution, tol=cfg.depth_tolerance)
    if cfg.spacing > 0:
        from .cameras import scene_bounds

        h = cfg.spacing * scene_bounds(kept)[1]
    else:
        h = median_spacing(kept.means) if len(kept) > 1 else 1.0
        h = fused_count_spacing(P, len(kept), h)
    out = fuse_points(P, C, N, h, scene.dtype)
    report.update({"mode": cfg.mode, "spacing": h, "points": len(out), "kept": len(out)})
    log.info("surface sampling (%s): %d points from %d Gaussians at spacing %.4g", cfg.mode, len(out), len(kept), h)
    return out, report


def _kept(report: dict, idx: torch.Tensor, n: int, what: str) -> dict:
    report["kept"] = len(idx)
    log.info("%s: kept %d of %d (%s)", what, len(idx), n,
             ", ".join(f"{k}={v}" for k, v in report.items() if k.startswith("removed")))
    return report


def core_box(scene: GaussianScene, cfg: StyleCleanConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """(lo [3], hi [3]) of the style's core box (module docstring); the opaque Gaussians, or all when
    fewer than 16 are opaque."""
    m = scene.means.detach().double()
    opaque = scene.opacities.detach() >= cfg.core_opacity
    core = m[opaque] if int(opaque.sum()) >= 16 else m
    lo = torch.quantile(core, cfg.core_quantile, dim=0)
    hi = torch.quantile(core, 1 - cfg.core_quantile, dim=0)
    pad = cfg.core_margin * (hi - lo)
    return lo - pad, hi + pad


def in_patch(scene: GaussianScene, cfg: StyleCleanConfig) -> torch.Tensor:
    """[N] bool: the Gaussian's centre lies inside the style's core box (:func:`core_box`)."""
    lo, hi = core_box(scene, cfg)
    m = scene.means.detach().double()
    return ~((m < lo) | (m > hi)).any(1)


def surface_heights(points: torch.Tensor, opacity: torch.Tensor, grid: int = 64, q: float = 0.02) -> torch.Tensor:
    """The surface a view straight down (-z) meets: points [M, 3], opacities [M] -> heights [grid, grid]
    (NaN where a cell is empty), on a raster of the x-y box between the ``q`` and ``1 - q`` quantiles.
    Each cell's points are taken from the top down, and its height is that of the point at which their
    accumulated opacity ``1 - prod (1 - o)`` first reaches 1/2 (the lowest point if it never does)."""
    x = points.detach().double().cpu().numpy()
    o = np.clip(opacity.detach().double().cpu().numpy().reshape(len(x)), 0.0, 0.999)
    lo, hi = np.quantile(x[:, :2], q, axis=0), np.quantile(x[:, :2], 1 - q, axis=0)
    cell = np.maximum((hi - lo) / grid, 1e-12)
    ij = np.floor((x[:, :2] - lo) / cell).astype(np.int64)
    ok = (ij >= 0).all(1) & (ij < grid).all(1)
    key, z, lt = ij[ok, 0] * grid + ij[ok, 1], x[ok, 2], np.log1p(-o[ok])
    order = np.lexsort((-z, key))
    key, z, lt = key[order], z[order], lt[order]
    cells, start = np.unique(key, return_index=True)
    counts = np.diff(np.append(start, len(key)))
    cum = np.cumsum(lt) - np.repeat(np.cumsum(lt)[start] - lt[start], counts)  # within each cell
    first = np.full(len(cells), -1)
    reached = np.flatnonzero(cum <= np.log(0.5))
    first[np.searchsorted(cells, key[reached])[::-1]] = reached[::-1]  # the first per cell
    pick = np.where(first >= 0, first, start + counts - 1)
    H = np.full(grid * grid, np.nan)
    H[cells] = z[pick]
    return torch.from_numpy(H.reshape(grid, grid))


def ground_and_relief(points: torch.Tensor, opacity: torch.Tensor, grid: int = 64) -> tuple[float, float]:
    """The patch's ground and relief height as a view from above sees them (:func:`surface_heights`):
    the 10 % quantile of the surface's heights (the ground between the elements) and the 90 % minus
    the 10 % quantile (how far the elements rise above it)."""
    H = surface_heights(points, opacity, grid)
    H = H[torch.isfinite(H)]
    if len(H) == 0:
        raise ValueError("ground height: no point inside the patch")
    q10, q90 = torch.quantile(H, 0.1), torch.quantile(H, 0.9)
    return float(q10), float(q90 - q10)


def clean_style(scene: GaussianScene, cfg: StyleCleanConfig) -> tuple[torch.Tensor, dict]:
    """Indices [K] of the style Gaussians kept, and a report of counts removed and why (module docstring)."""
    start, skipped = _begin(scene, cfg.enabled, "style cleaning", "style")
    if skipped:
        return skipped
    (keep, report), n = start, len(scene)
    lo, hi = core_box(scene, cfg)
    m = scene.means.detach().double()
    _drop(keep, ~in_patch(scene, cfg), report, "removed_outside_patch")
    report["patch_box"] = [lo.tolist(), hi.tolist()]
    _drop(keep, scene.opacities.detach() < cfg.min_opacity, report, "removed_low_opacity")
    if cfg.max_scale > 0 and bool(keep.any()):
        big = scene.scales.detach().max(1).values
        _drop(keep, big > cfg.max_scale * big[keep].median(), report, "removed_oversized")
    _outliers(scene, keep, cfg.outlier_k, cfg.outlier_quantile, report)
    form = style_form(m[keep].numpy(), cfg.form)
    report["form"], report["thickness"], report["form_reason"] = form.form, form.thickness, form.reason
    log.info("style form: %s (%s)", form.form, form.reason)
    if form.form == "volume":
        log.info("style cleaning: the ground and visibility tests left out: a volume has no ground and is seen "
                 "from every side")
    elif cfg.below_ground > 0 and bool(keep.any()):
        idx = keep.nonzero().squeeze(1)
        ground, relief = ground_and_relief(m[idx], scene.opacities.detach()[idx])
        report["ground_height"], report["relief_height"] = ground, relief
        _drop(keep, m[:, 2] < ground - cfg.below_ground * relief, report, "removed_below_ground")
    if cfg.visibility and form.form == "patch":
        idx = keep.nonzero().squeeze(1)
        w = torch.zeros(n, dtype=torch.float64)
        if len(idx):
            w[idx] = seen_fraction(scene.subset(idx), cfg.views, cfg.resolution, STYLE_ELEVATIONS)
        _drop(keep, w < cfg.min_seen, report, "removed_hidden")
    if cfg.colour_outliers > 0:
        _colour_outliers(scene, keep, cfg.colour_k, cfg.colour_outliers, report)
    idx = keep.nonzero().squeeze(1)
    if len(idx) == 0:
        raise ValueError("style cleaning removed every Gaussian; relax min_opacity / min_seen")
    return idx, _kept(report, idx, n, "style cleaning")


def _colour_deviation(scene: GaussianScene, idx: torch.Tensor, k: int) -> tuple[torch.Tensor, torch.Tensor]:
    """For the Gaussians ``idx`` [M]: the median RGB [M, 3] of each one's k nearest others among them
    (positions), and the RGB distance [M] of its own colour from it."""
    _, nb = knn(scene.means[idx], scene.means[idx], k, exclude_self=True)
    rgb = scene.rgb.detach().clamp(0, 1)[idx]
    med = rgb[nb].median(dim=1).values
    return med, (rgb - med).norm(dim=1)


def _colour_outliers(scene: GaussianScene, keep: torch.Tensor, k: int, limit: float, report: dict) -> None:
    """Drop kept Gaussians whose RGB lies more than ``limit`` from the median RGB of their k nearest
    kept neighbours (positions)."""
    idx = keep.nonzero().squeeze(1)
    if len(idx) <= k:
        return
    _, dev = _colour_deviation(scene, idx, k)
    out = torch.zeros_like(keep)
    out[idx[dev > limit]] = True
    _drop(keep, out, report, "removed_colour_outliers")


def dilate_gaussians(scene: GaussianScene, amount: float) -> tuple[GaussianScene, float]:
    """``scene`` with every covariance R S^2 R^T grown to R (S^2 + c^2 I) R^T, c = ``amount`` x the median
    nearest-neighbour distance of its means (each axis s_i -> sqrt(s_i^2 + c^2), rotation and opacity
    kept), and c. A trained scene's Gaussians were fitted with the rasterizer's screen-space dilation at
    its training views' pixel size; seen closer, that dilation shrinks with the pixels and the gaps
    between small Gaussians open (Yu et al., Mip-Splatting, CVPR 2024); growing each Gaussian in 3D
    keeps them closed at any zoom."""
    if len(scene) < 2 or amount <= 0:
        return scene, 0.0
    c = amount * median_spacing(scene.means)
    out = scene.clone()
    with torch.no_grad():
        out.log_scales.copy_(0.5 * torch.log(torch.exp(2 * scene.log_scales.detach()) + c * c))
    return out, c


def recolour_outliers(scene: GaussianScene, k: int, limit: float, shown: torch.Tensor | None = None,
                      shown_limit: float = 0.0) -> tuple[GaussianScene, int]:
    """``scene`` with each Gaussian whose RGB lies more than ``limit`` from the median RGB of its k
    nearest neighbours recoloured to that median (DC term; its view-dependent terms zeroed), and how
    many were. With ``shown`` [N, 3] (:func:`shown_colours`) and ``shown_limit`` > 0, only those whose RGB
    also lies more than ``shown_limit`` from what the renders show at them. Unlike dropping them
    (``colour_outliers``) every position stays, so the patch's relief, its element labels and what
    registration measures on it do not change: a trained patch's magenta, blue and green Gaussians
    inside brown and grey pebbles are ones its views barely constrain, and the colour their neighbours
    show is the best guess of what the surface there looks like. The second test keeps a real
    capture's colour features (a label's dark letters on white differ from their neighbours too, but
    the renders show them)."""
    if len(scene) <= k:
        return scene, 0
    med, dev = _colour_deviation(scene, torch.arange(len(scene)), k)
    odd = dev > limit
    if shown is not None and shown_limit > 0:
        odd &= (scene.rgb.detach().clamp(0, 1) - shown.to(scene.rgb)).norm(dim=1) > shown_limit
    out = scene.clone()
    out.sh_dc[odd] = rgb_to_sh_dc(med[odd]).to(out.sh_dc)
    out.sh_rest[odd] = 0
    return out, int(odd.sum())


def refit_appearance(kept: GaussianScene, reference: GaussianScene, steps: int, views: int = 24,
                     resolution: int = 200, seed: int = 0, progress: bool = False) -> tuple[GaussianScene, dict]:
    """``kept`` [K] with its scales, opacities and colours refitted so that, alone, it renders as
    ``reference`` [R] does (positions, rotations and labels stay); and a report.

    Cleaning drops the Gaussians a style's views barely show, among them the second layer that fills
    the gaps of the first: what is kept is see-through where the reference was solid. The refit
    minimises, over ``steps`` Adam steps on ``views`` orbit views from above (``STYLE_ELEVATIONS``,
    ``resolution`` px, one view per step),

        | C_kept + (1 - A_kept) b  -  (C_ref + (1 - A_ref) b) |_1

    (C premultiplied colour, A alpha, b a random background per step, so both colour and alpha are
    fitted) over log-scales, opacity logits and the DC colour; each scale grows at most ``REFIT_GROWTH``
    fold (uncapped, a trained speck of odd colour swells into a blob on the result)."""
    from .cameras import fit_orbit
    from .rasterizer import rasterize

    if steps <= 0 or len(kept) == 0:
        return kept, {"steps": 0}
    cams = fit_orbit(reference, views, resolution, elevations_deg=STYLE_ELEVATIONS)
    with torch.no_grad():
        targets = [(r.rgb, r.alpha) for r in (rasterize(reference.detach(), c) for c in cams)]

        def error(s):  # mean |C - C_ref| + |A - A_ref| over the views
            total = 0.0
            for c, (rgb, alpha) in zip(cams, targets):
                r = rasterize(s, c)
                total += float((r.rgb - rgb).abs().mean() + (r.alpha - alpha).abs().mean())
            return total / len(cams)
        before = error(kept.detach())
    out = kept.clone()
    fitted = ((out.log_scales, 5e-3), (out.opacity_logits, 5e-2), (out.sh_dc, 2.5e-3))  # pretraining's rates
    for p, _ in fitted:
        p.requires_grad_(True)
    opt = torch.optim.Adam([{"params": [p], "lr": lr} for p, lr in fitted], eps=1e-15)
    g = torch.Generator().manual_seed(seed)
    cap = kept.log_scales.detach() + math.log(REFIT_GROWTH)
    from tqdm import tqdm

    for _ in tqdm(range(steps), desc="style refit", disable=not progress, mininterval=2.0):
        i = int(torch.randint(len(cams), (1,), generator=g))
        b = torch.rand(3, generator=g).to(out.means)
        r = rasterize(out, cams[i], background=b)
        loss = ((r.rgb - (targets[i][0] + (1 - targets[i][1])[..., None] * b)).abs().mean()
                + (r.alpha - targets[i][1]).abs().mean())
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        with torch.no_grad():  # each axis grows at most REFIT_GROWTH-fold: a speck must not become a blob
            out.log_scales.copy_(torch.minimum(out.log_scales, cap))
    out = out.detach()
    with torch.no_grad():
        after = error(out)
    return out, {"steps": steps, "views": views, "error_before": before, "error_after": after}

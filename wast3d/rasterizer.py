"""Differentiable rasterization of 3D Gaussians (EWA splatting, Kerbl et al. 2023).

One interface, :func:`rasterize`, three backends:

- ``"torch"``: pure PyTorch, tile by tile (16x16), each tile checkpointed so memory stays bounded by
  one tile's ``pixels x Gaussians``; the reference the others are tested against;
- ``"native"``: the same compositing as a C/OpenMP kernel with the analytic backward of the reference
  CUDA code (``csrc/raster_cpu.c``), the default on CPU;
- ``"gsplat"``: ``gsplat.rasterization`` on CUDA (optional dependency), the default on GPU.

The torch and native backends share the projection (:func:`project`), spherical-harmonic colours
(:func:`wast3d.sh.eval_sh`) and tile binning (:func:`bin_tiles`), all differentiable PyTorch.

Conventions: OpenCV camera (see :mod:`wast3d.cameras`); pixel centres at (i + 0.5, j + 0.5); the 2D
covariance is dilated by 0.3 px^2 (the reference low-pass filter); a Gaussian contributes to a pixel
when ``alpha = min(0.99, o exp(-sigma)) >= 1/255``; compositing stops before transmittance falls
below 1e-4. The result is a :class:`Rendering`, with the same meaning on every backend.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import torch
from torch.utils.checkpoint import checkpoint

from .cameras import Camera
from .gaussians import GaussianScene, quat_to_rotmat
from .sh import eval_sh

log = logging.getLogger(__name__)

TILE = 16
EPS2D = 0.3
ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
T_MIN = 1e-4


@dataclass
class Projected:
    """Per-Gaussian screen-space quantities; tensors of the visible Gaussians only.

    ids: [V] indices into the scene; means2d: [V, 2]; conics: [V, 3] (a, b, c) of the inverse 2D
    covariance; depths: [V] camera z; radii: [V, 2] half-widths (x, y) in pixels of the box of the
    alpha >= 1/255 ellipse;
    opacities: [V].
    """

    ids: torch.Tensor
    means2d: torch.Tensor
    conics: torch.Tensor
    depths: torch.Tensor
    radii: torch.Tensor
    opacities: torch.Tensor


def project(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
            cam: Camera) -> Projected:
    """EWA projection: ``Sigma2d = J W Sigma W^T J^T + 0.3 I`` with the perspective Jacobian J.

    means: [N, 3], quats: [N, 4], scales: [N, 3], opacities: [N]. The Jacobian uses the mean clamped
    to 1.3x the field of view (as the reference) so that Gaussians far outside do not blow up.
    Culled: behind ``near``, beyond ``far``, degenerate 2D covariance, opacity < 1/255, or a box that
    misses the image.
    """
    dt = means.dtype
    V = cam.world_to_cam.to(device=means.device, dtype=dt)
    R, t = V[:3, :3], V[:3, 3]
    pc = means @ R.T + t
    z = pc[:, 2]
    keep = (z > cam.near) & (z < cam.far) & (opacities >= ALPHA_MIN)
    ids = keep.nonzero().squeeze(1)
    pc, z = pc[ids], z[ids]
    x, y = pc[:, 0], pc[:, 1]
    fx, fy, cx, cy = cam.fx, cam.fy, cam.cx, cam.cy
    tanx, tany = 0.5 * cam.width / fx, 0.5 * cam.height / fy
    limx_pos, limx_neg = (cam.width - cx) / fx + 0.3 * tanx, cx / fx + 0.3 * tanx
    limy_pos, limy_neg = (cam.height - cy) / fy + 0.3 * tany, cy / fy + 0.3 * tany
    tx = z * (x / z).clamp(-limx_neg, limx_pos)
    ty = z * (y / z).clamp(-limy_neg, limy_pos)
    zero = torch.zeros_like(z)
    J = torch.stack([fx / z, zero, -fx * tx / z**2, zero, fy / z, -fy * ty / z**2], -1).reshape(-1, 2, 3)
    Rg = quat_to_rotmat(quats[ids])
    M = R @ Rg * scales[ids][:, None, :]  # camera-frame R_g S
    JM = J @ M
    cov2 = JM @ JM.transpose(1, 2)
    a = cov2[:, 0, 0] + EPS2D
    b = cov2[:, 0, 1]
    c = cov2[:, 1, 1] + EPS2D
    det = a * c - b * b
    op = opacities[ids]
    mx = fx * x / z + cx
    my = fy * y / z + cy
    with torch.no_grad():
        # the box of the ellipse where o exp(-d^T Sigma2d^-1 d / 2) >= 1/255, i.e. d^T Sigma2d^-1 d <= k^2:
        # its half-widths are k sqrt(Sigma_xx) and k sqrt(Sigma_yy) (gsplat >= 1.5's per-axis radii)
        k = (2 * torch.log((op * 255.0).clamp_min(1.0))).sqrt()
        radii = torch.stack([torch.ceil(k * a.clamp_min(0).sqrt()), torch.ceil(k * c.clamp_min(0).sqrt())], -1)
        rx, ry = radii.unbind(-1)
        ok = (det > 0) & (rx > 0) & (ry > 0) & (mx + rx > 0) & (mx - rx < cam.width) & \
             (my + ry > 0) & (my - ry < cam.height)
    sel = ok.nonzero().squeeze(1)
    det = det[sel]
    conics = torch.stack([c[sel] / det, -b[sel] / det, a[sel] / det], -1)
    return Projected(ids[sel], torch.stack([mx[sel], my[sel]], -1), conics, z[sel], radii[sel], op[sel])


@torch.no_grad()
def bin_tiles(p: Projected, width: int, height: int, tile: int = TILE) -> tuple[torch.Tensor, torch.Tensor]:
    """Sort (tile, Gaussian) intersections by tile, then depth.

    Returns isect_gid [M] int32 (positions into ``p``'s arrays) and tile_off [n_tiles + 1] int64.
    """
    tx_n, ty_n = (width + tile - 1) // tile, (height + tile - 1) // tile
    n_tiles = tx_n * ty_n
    dev = p.means2d.device
    if p.ids.numel() == 0:
        return torch.zeros(0, dtype=torch.int32, device=dev), torch.zeros(n_tiles + 1, dtype=torch.int64, device=dev)
    m, rx, ry = p.means2d.detach(), p.radii[:, 0], p.radii[:, 1]
    # pixels whose centre (i + .5) lies in the box [m - r, m + r]
    px0 = torch.ceil(m[:, 0] - rx - 0.5).clamp(0, width - 1).long()
    px1 = torch.floor(m[:, 0] + rx - 0.5).clamp(0, width - 1).long()
    py0 = torch.ceil(m[:, 1] - ry - 0.5).clamp(0, height - 1).long()
    py1 = torch.floor(m[:, 1] + ry - 0.5).clamp(0, height - 1).long()
    tx0, tx1, ty0, ty1 = px0 // tile, px1 // tile, py0 // tile, py1 // tile
    w = (tx1 - tx0 + 1).clamp_min(0)
    counts = w * (ty1 - ty0 + 1).clamp_min(0)
    total = int(counts.sum())
    g = torch.repeat_interleave(torch.arange(len(counts), device=dev), counts)
    start = torch.cumsum(counts, 0) - counts
    off = torch.arange(total, device=dev) - start[g]
    tid = (ty0[g] + off // w[g]) * tx_n + tx0[g] + off % w[g]
    depth_rank = torch.empty_like(g[: len(counts)])
    # stable: Gaussians at the same depth (clones) keep their order whatever else is culled
    depth_rank[torch.argsort(p.depths.detach(), stable=True)] = torch.arange(len(counts), device=dev)
    key = tid * len(counts) + depth_rank[g]
    order = torch.argsort(key)
    gid = g[order].to(torch.int32)
    tile_off = torch.zeros(n_tiles + 1, dtype=torch.int64, device=dev)
    tile_off[1:] = torch.cumsum(torch.bincount(tid, minlength=n_tiles), 0)
    return gid, tile_off


# ----------------------------------------------------------------------------------------------
# compositing backends: (means2d [V,2], conics [V,3], colors [V,C], opac [V], bins) -> (out [H,W,C], T [H,W])
# ----------------------------------------------------------------------------------------------


def _composite_tile(means2d, conics, colors, opac, pix):
    """One tile in PyTorch. pix: [P, 2] pixel centres; the others are the tile's Gaussians, front first."""
    d = means2d[None, :, :] - pix[:, None, :]  # [P, n, 2]
    dx, dy = d[..., 0], d[..., 1]
    sigma = 0.5 * (conics[:, 0] * dx * dx + conics[:, 2] * dy * dy) + conics[:, 1] * dx * dy
    # clamp the exponent: exp of large arguments is slow (denormals) and the result is skipped anyway
    alpha = (opac * torch.exp(-sigma.clamp(0.0, 12.0))).clamp_max(ALPHA_MAX)
    alpha = torch.where((sigma >= 0) & (alpha >= ALPHA_MIN), alpha, torch.zeros_like(alpha))
    log1m = torch.log1p(-alpha)
    logT_incl = torch.cumsum(log1m, dim=1)
    # the forward stops before the first Gaussian that brings T below T_MIN; T is non-increasing,
    # so "included" is exactly "inclusive transmittance >= T_MIN"
    inc = logT_incl >= math.log(T_MIN)
    logT_excl = (logT_incl - log1m).clamp_min(-30.0)
    w = alpha * torch.exp(logT_excl) * inc
    out = w @ colors
    T = torch.exp((log1m * inc).sum(1).clamp_min(-30.0))
    return out, T


def composite_torch(means2d, conics, colors, opac, gid, tile_off, width, height, tile=TILE, radii=None):
    C = colors.shape[1]
    out = means2d.new_zeros(height, width, C)
    T = means2d.new_ones(height, width)
    tx_n = (width + tile - 1) // tile
    offs = tile_off.tolist()
    need_grad = torch.is_grad_enabled() and any(t.requires_grad for t in (means2d, conics, colors, opac))
    for t in range(len(offs) - 1):
        s, e = offs[t], offs[t + 1]
        if s == e:
            continue
        x0, y0 = (t % tx_n) * tile, (t // tx_n) * tile
        x1, y1 = min(x0 + tile, width), min(y0 + tile, height)
        ys, xs = torch.meshgrid(torch.arange(y0, y1, device=means2d.device, dtype=means2d.dtype) + 0.5,
                                torch.arange(x0, x1, device=means2d.device, dtype=means2d.dtype) + 0.5, indexing="ij")
        pix = torch.stack([xs.reshape(-1), ys.reshape(-1)], -1)
        ids = gid[s:e].long()
        args = (means2d[ids], conics[ids], colors[ids], opac[ids], pix)
        o, tt = checkpoint(_composite_tile, *args, use_reentrant=False) if need_grad else _composite_tile(*args)
        out[y0:y1, x0:x1] = o.reshape(y1 - y0, x1 - x0, C)
        T[y0:y1, x0:x1] = tt.reshape(y1 - y0, x1 - x0)
    return out, T


class _NativeComposite(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, colors, opac, gid, tile_off, width, height, tile, radii):
        from . import _native

        lib = _native.load("raster_cpu")
        sfx = "_f64" if means2d.dtype == torch.float64 else "_f32"
        tensors = [x.detach().contiguous() for x in (means2d, conics, colors, opac)]
        gid, tile_off = gid.contiguous(), tile_off.contiguous()
        # radii [V, 2] (Projected.radii): the kernel skips a Gaussian's tile rows beyond its box's y half-width
        radii = radii[:, 1].to(means2d.dtype).contiguous()
        C = colors.shape[1]
        out = means2d.new_empty(height, width, C)
        T = means2d.new_empty(height, width)
        last = torch.empty(height, width, dtype=torch.int32)
        P = _native.ptr
        getattr(lib, "raster_fwd" + sfx)(*[P(x) for x in tensors], P(radii), P(gid), P(tile_off), width, height,
                                         tile, C, torch.get_num_threads(), P(out), P(T), P(last))
        ctx.save_for_backward(*tensors, radii, gid, tile_off, T, last)
        ctx.dims = (width, height, tile, C, sfx)
        return out, T

    @staticmethod
    def backward(ctx, g_out, g_T):
        from . import _native

        lib = _native.load("raster_cpu")
        means2d, conics, colors, opac, radii, gid, tile_off, T, last = ctx.saved_tensors
        width, height, tile, C, sfx = ctx.dims
        M = gid.numel()
        gm = means2d.new_zeros(M, 2)
        gc = means2d.new_zeros(M, 3)
        gcol = means2d.new_zeros(M, C)
        go = means2d.new_zeros(M)
        g_out = (g_out if g_out is not None else torch.zeros_like(T)[..., None].expand(-1, -1, C)).contiguous()
        g_T = (g_T if g_T is not None else torch.zeros_like(T)).contiguous()
        P = _native.ptr
        getattr(lib, "raster_bwd" + sfx)(P(means2d), P(conics), P(colors), P(opac), P(radii), P(gid), P(tile_off), width,
                                         height, tile, C, torch.get_num_threads(), P(T), P(last), P(g_out), P(g_T),
                                         P(gm), P(gc), P(gcol), P(go))
        idx = gid.long()
        V = means2d.shape[0]
        red = lambda g, *shape: means2d.new_zeros(V, *shape).index_add_(0, idx, g)  # noqa: E731
        return red(gm, 2), red(gc, 3), red(gcol, C), red(go), None, None, None, None, None, None


def composite_native(means2d, conics, colors, opac, gid, tile_off, width, height, tile=TILE, radii=None):
    if colors.shape[1] > 16:
        raise ValueError("native compositor supports at most 16 channels")
    if tile > 32:
        raise ValueError("native compositor supports tiles up to 32 pixels")
    return _NativeComposite.apply(means2d, conics, colors, opac, gid, tile_off, width, height, tile, radii)


# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Rendering:
    """One view rendered by :func:`rasterize`; the same fields and meanings on every backend.

    - ``rgb`` [H, W, 3]: colour composited on the background ([H, W, C] for C-channel ``colors``);
    - ``alpha`` [H, W]: accumulated opacity;
    - ``depth`` [H, W]: expected camera-space z of the visible Gaussians (``sum w_i z_i / alpha``, 0
      where alpha = 0);
    - ``visible_ids`` [V]: indices (into the scene) of the Gaussians that reach the image;
    - ``means2d`` [V, 2]: their pixel centres (differentiable; retains its gradient when it has one);
    - ``radii`` [V]: the larger half-width of each one's screen box, in pixels;
    - ``densify``: with ``full_means2d=True``, gsplat's densification-strategy ``info`` (``means2d``
      [1, N, 2] and ``radii`` [1, N, 2] for all N Gaussians, 0 where not drawn; ``width``, ``height``,
      ``n_cameras``); otherwise None;
    - ``normal`` [H, W, 3]: camera-frame normals, filled by :func:`wast3d.render.render_maps` only.
    """

    rgb: torch.Tensor
    alpha: torch.Tensor
    depth: torch.Tensor
    visible_ids: torch.Tensor
    means2d: torch.Tensor
    radii: torch.Tensor
    densify: dict | None = None
    normal: torch.Tensor | None = None


def default_backend(device: torch.device) -> str:
    if device.type == "cuda":
        try:
            import gsplat  # noqa: F401

            return "gsplat"
        except ImportError:
            log.warning("gsplat not installed: rendering on CUDA with the PyTorch backend (slow)")
            return "torch"
    from . import _native

    return "native" if _native.load("raster_cpu") is not None else "torch"


def rasterize(scene: GaussianScene, cam: Camera, background=(0.0, 0.0, 0.0), sh_degree: int | None = None,
              backend: str | None = None, colors: torch.Tensor | None = None,
              full_means2d: bool = False) -> Rendering:
    """Render ``scene`` from ``cam`` (see :class:`Rendering` for what comes back).

    ``colors`` [N, C] overrides the SH colours (labels, codes: C channels in one pass, at most 15 on the
    CPU; ``rgb`` is then [H, W, C] and ``background`` one value or C). ``sh_degree`` defaults to the
    scene's degree. ``full_means2d=True`` also returns gsplat's densification layout (``densify``).
    """
    backend = backend or default_backend(scene.device)
    deg = scene.sh_degree if sh_degree is None else min(sh_degree, scene.sh_degree)
    bg = torch.as_tensor(background, dtype=scene.dtype, device=scene.device).reshape(-1)
    channels = 3 if colors is None else colors.shape[1]
    if len(bg) != channels:
        if not bool((bg == bg[0]).all()):
            raise ValueError(f"rasterize: a background of {len(bg)} values for {channels} channels")
        bg = bg[:1].expand(channels)
    if backend == "gsplat":
        return _rasterize_gsplat(scene, cam, bg, deg, colors, full_means2d)
    p = project(scene.means, scene.quats, scene.scales, scene.opacities, cam)
    if colors is None:
        dirs = scene.means[p.ids] - cam.center.to(scene.means)
        dirs = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        rgb = (eval_sh(scene.sh[p.ids], dirs, deg) + 0.5).clamp_min(0.0)
    else:
        rgb = colors[p.ids]
    feats = torch.cat([rgb, p.depths[:, None]], dim=1)
    gid, tile_off = bin_tiles(p, cam.width, cam.height)
    means2d = p.means2d
    densify = None
    if full_means2d:
        # [1, N, 2] for densification strategies (gsplat's layout): the visible means are read back out
        # of it, so its .grad holds every Gaussian's screen-space gradient (zero when not visible)
        full = means2d.new_zeros(1, len(scene), 2).index_put((torch.zeros_like(p.ids), p.ids), means2d)
        means2d = full[0, p.ids]
        radii = p.radii.new_zeros(1, len(scene), 2)
        radii[0, p.ids] = p.radii
        densify = {"means2d": full, "radii": radii, "width": cam.width, "height": cam.height, "n_cameras": 1,
                   "gaussian_ids": p.ids}
    elif means2d.requires_grad:
        means2d.retain_grad()
    fn = {"torch": composite_torch, "native": composite_native}[backend]
    out, T = fn(means2d, p.conics, feats, p.opacities, gid, tile_off, cam.width, cam.height, radii=p.radii)
    alpha = 1 - T
    image = out[..., :channels] + T[..., None] * bg
    depth = torch.where(alpha > 1e-6, out[..., channels] / alpha.clamp_min(1e-6), torch.zeros_like(alpha))
    return Rendering(rgb=image, alpha=alpha, depth=depth, visible_ids=p.ids, means2d=means2d,
                     radii=p.radii.amax(-1), densify=densify)


def _rasterize_gsplat(scene, cam, bg, deg, colors, full_means2d):  # pragma: no cover - needs CUDA
    from gsplat import rasterization

    viewmat = cam.world_to_cam.to(scene.means)[None]
    K = cam.K.to(scene.means)[None]
    if colors is None:
        cols, kw = scene.sh, {"sh_degree": deg}
    else:
        cols, kw = colors, {}
    rc, ra, meta = rasterization(scene.means, scene.quats, scene.scales, scene.opacities, cols, viewmat, K,
                                 cam.width, cam.height, near_plane=cam.near, far_plane=cam.far,
                                 render_mode="RGB+ED", backgrounds=torch.cat([bg, bg.new_zeros(1)])[None],
                                 eps2d=EPS2D, packed=False, **kw)
    alpha = ra[0, ..., 0]
    radii = meta["radii"][0]
    if radii.dim() == 2:  # gsplat >= 1.5: a radius per image axis
        radii = radii.max(-1).values
    ids = (radii > 0).nonzero().squeeze(1)  # as the CPU backends: the Gaussians that reach the image
    densify = None
    if full_means2d:
        densify = {"means2d": meta["means2d"], "radii": meta["radii"], "width": cam.width, "height": cam.height,
                   "n_cameras": 1}
    c = len(bg)
    return Rendering(rgb=rc[0, ..., :c], alpha=alpha, depth=rc[0, ..., c], visible_ids=ids,
                     means2d=meta["means2d"][0][ids], radii=radii[ids], densify=densify)

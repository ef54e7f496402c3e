"""Procedural scenes: the project's embedded default data (no downloads).

Style scenes have real local geometry, in the spirit of the paper's style scenes. Patches (x, y in
[-1, 1], z up: a ground with elements on it):

- ``pebbles``: flattened ellipsoidal pebbles of a river-bed palette lying on sand;
- ``grass``: curved blades (chains of small Gaussians) standing on soil;
- ``wicker``: a basket weave, warp and weft tubes passing over and under each other;
- ``stones``: rough boulders (spheres displaced by random bumps) half sunk in gravel.

Volumes (objects seen from every side, no ground):

- ``bouquet``: flower heads of several colours with petals on a dome, stems converging below, leaves;
- ``pinecone``: woody scales on a spiral round an ovoid core.

Content scenes are meshes that pyvista ships (``ant``, ``airplane``, ``nut``, ``globe``, and the
parametric ``torus``/``sphere``), normalized to the unit ball, with Gaussians sampled on the surface
(area-weighted), thin and facing the normal, with the log-normal in-plane elongation and size of a
trained scene's Gaussians (so that metrics on Gaussian shape can tell the style's from the content's).

Every style Gaussian carries the id of its element (``GaussianScene.element``: 0 the ground or gravel,
1.. each pebble, blade, strand or stone), written to the PLY as the property ``element``.

Every generator is deterministic given its seed. Style Gaussians are surface discs: tangential scale
0.6 x the sample spacing, normal scale ``flatness`` x that, so no needles appear (the paper
regularizes its style scenes for the same reason).
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np
import torch

from .gaussians import GaussianScene, rotmat_to_quat
from .geometry import frame_from_normal

STYLES: dict[str, Callable] = {}
CONTENTS = ("ant", "airplane", "nut", "globe", "torus", "sphere")
CONTENT_COLORS = {"ant": (0.75, 0.35, 0.2), "airplane": (0.45, 0.6, 0.85), "nut": (0.85, 0.7, 0.35),
                  "globe": (0.35, 0.6, 0.75), "torus": (0.8, 0.45, 0.6), "sphere": (0.6, 0.75, 0.5)}


def _register(fn):
    STYLES[fn.__name__.removeprefix("style_")] = fn
    return fn


def surface_gaussians(points: np.ndarray, normals: np.ndarray, colors: np.ndarray, spacing: float | np.ndarray,
                      flatness: float = 0.3, opacity: float = 0.95, tangent: np.ndarray | None = None,
                      elongation: float = 1.0) -> GaussianScene:
    """Disc-shaped Gaussians on a surface.

    points/normals/colors: [N, 3]; spacing: scalar or [N]. With ``tangent`` [N, 3] given, the first
    axis follows it and is ``elongation`` (scalar or [N]) times longer (blades, strands).
    """
    n = normals / np.linalg.norm(normals, axis=1, keepdims=True).clip(1e-12)
    if tangent is not None:
        t1 = tangent - (tangent * n).sum(1, keepdims=True) * n
        t1 /= np.linalg.norm(t1, axis=1, keepdims=True).clip(1e-12)
        R = np.stack([t1, np.cross(n, t1), n], axis=2)
    else:
        R = frame_from_normal(torch.from_numpy(n)).numpy()
    sp = np.broadcast_to(np.asarray(spacing, dtype=np.float64), (len(points),))[:, None] * 0.6
    el = np.broadcast_to(np.asarray(elongation, dtype=np.float64), (len(points),))[:, None]
    scales = np.concatenate([sp * el, sp, sp * flatness], axis=1)
    q = rotmat_to_quat(torch.from_numpy(R))
    return GaussianScene.from_activated(
        torch.from_numpy(points).float(), torch.from_numpy(scales).float(), q.float(), opacities=opacity,
        rgb=torch.from_numpy(np.clip(colors, 0.0, 1.0)).float(),
    )


def _fibonacci_sphere(n: int) -> np.ndarray:
    i = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * i / n)
    theta = math.pi * (1 + 5**0.5) * i
    return np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], 1)


def _ground(rng: np.random.Generator, n: int, base: np.ndarray, noise: float, height=0.0, roughness=0.01):
    xy = rng.uniform(-1, 1, size=(n, 2))
    z = height + roughness * rng.standard_normal(n)
    pts = np.concatenate([xy, z[:, None]], 1)
    nrm = np.tile([0.0, 0.0, 1.0], (n, 1)) + 0.15 * rng.standard_normal((n, 3))
    col = base[None] * (1 + noise * rng.standard_normal((n, 1))) + 0.03 * rng.standard_normal((n, 3))
    return pts, nrm, col


def _place_disks(rng, count, rmin, rmax, max_tries=20000):
    """Non-overlapping discs in [-1, 1]^2 by dart throwing: centres [K, 2], radii [K]."""
    cs, rs = [], []
    for _ in range(max_tries):
        if len(cs) >= count:
            break
        r = rng.uniform(rmin, rmax)
        c = rng.uniform(-1 + r * 0.5, 1 - r * 0.5, size=2)
        if all(np.hypot(*(c - c2)) > 0.9 * (r + r2) for c2, r2 in zip(cs, rs)):
            cs.append(c)
            rs.append(r)
    return np.array(cs), np.array(rs)


@_register
def style_pebbles(n_gaussians: int = 30000, seed: int = 0) -> GaussianScene:
    rng = np.random.default_rng(seed)
    palette = np.array([[0.55, 0.53, 0.50], [0.35, 0.33, 0.32], [0.62, 0.48, 0.36], [0.80, 0.77, 0.70],
                        [0.42, 0.36, 0.30], [0.25, 0.25, 0.27]])
    centres, radii = _place_disks(rng, 60, 0.08, 0.18)
    n_ground = n_gaussians // 6
    per = (n_gaussians - n_ground) * radii**2 / (radii**2).sum()
    P, N, C = [], [], []
    for c, r, m in zip(centres, radii, per.astype(int)):
        d = _fibonacci_sphere(max(int(m / 0.65), 8))
        d = d[d[:, 2] > -0.3]  # the buried underside is not sampled (65 % of the sphere is kept)
        ax = np.array([r, r * rng.uniform(0.6, 0.95), r * rng.uniform(0.3, 0.5)])
        yaw = rng.uniform(0, 2 * math.pi)
        Rz = np.array([[math.cos(yaw), -math.sin(yaw), 0], [math.sin(yaw), math.cos(yaw), 0], [0, 0, 1]])
        p = (d * ax) @ Rz.T + np.array([c[0], c[1], ax[2] * 0.55])
        nrm = (d / ax**2) @ Rz.T
        base = palette[rng.integers(len(palette))]
        shade = 0.75 + 0.25 * d[:, 2:3]  # darker underneath
        col = base * shade * (1 + 0.06 * rng.standard_normal((len(p), 1))) + 0.02 * rng.standard_normal((len(p), 3))
        P.append(p), N.append(nrm), C.append(col)
    g = _ground(rng, n_ground, np.array([0.76, 0.68, 0.52]), 0.12)
    P.append(g[0]), N.append(g[1]), C.append(g[2])
    E = _element_ids([len(p) for p in P[:-1]], ground=len(g[0]))
    P, N, C = map(np.concatenate, (P, N, C))
    return _labelled(surface_gaussians(P, N, C, _spacing(P, 4.0 + 2 * math.pi * (radii**2).sum() * 0.8)), E)


@_register
def style_grass(n_gaussians: int = 30000, seed: int = 0) -> GaussianScene:
    rng = np.random.default_rng(seed)
    n_ground = n_gaussians // 5
    per_blade = 24
    n_blades = (n_gaussians - n_ground) // per_blade
    base = rng.uniform(-1, 1, size=(n_blades, 2))
    height = rng.uniform(0.12, 0.32, n_blades)
    yaw = rng.uniform(0, 2 * math.pi, n_blades)
    lean = rng.uniform(0.1, 0.6, n_blades)
    s = np.linspace(0, 1, per_blade)
    # blade centreline: rises and bends towards its lean direction (quadratic)
    dirx, diry = np.cos(yaw), np.sin(yaw)
    off = (lean[:, None] * height[:, None] * s[None] ** 2)
    x = base[:, :1] + dirx[:, None] * off
    y = base[:, 1:] + diry[:, None] * off
    z = height[:, None] * (s[None] - 0.35 * lean[:, None] * s[None] ** 3)
    P = np.stack([x, y, z], -1).reshape(-1, 3)
    tang = np.gradient(np.stack([x, y, z], -1), axis=1).reshape(-1, 3)
    side = np.stack([-diry, dirx, np.zeros_like(dirx)], -1)[:, None].repeat(per_blade, 1).reshape(-1, 3)
    nrm = np.cross(tang, side)
    green = np.array([[0.20, 0.45, 0.12], [0.35, 0.60, 0.18], [0.50, 0.62, 0.22], [0.28, 0.40, 0.10]])
    bc = green[rng.integers(len(green), size=n_blades)]
    tipfac = (0.55 + 0.6 * s)[None, :, None]
    C = (bc[:, None, :] * tipfac).reshape(-1, 3) + 0.02 * rng.standard_normal((len(P), 3))
    spacing = (height[:, None] / per_blade * np.ones((1, per_blade))).reshape(-1)
    blades = surface_gaussians(P, nrm, C, spacing, flatness=0.35, tangent=tang, elongation=1.6)
    g = _ground(rng, n_ground, np.array([0.36, 0.27, 0.18]), 0.15)
    ground = surface_gaussians(*g, _spacing(g[0], 4.0))
    return _labelled(GaussianScene.concat([ground, blades]), _element_ids([], ground=len(g[0]))
                     + [np.repeat(np.arange(1, n_blades + 1), per_blade)])


@_register
def style_wicker(n_gaussians: int = 30000, seed: int = 0) -> GaussianScene:
    rng = np.random.default_rng(seed)
    n_strands = 12
    d = 2.0 / n_strands
    amp = 0.035
    tube_r = 0.022
    per_strand = n_gaussians // (2 * n_strands)
    ring = 8
    along = per_strand // ring
    u = np.linspace(-1, 1, along)
    th = np.linspace(0, 2 * math.pi, ring, endpoint=False)
    P, N, C, T = [], [], [], []
    pal = np.array([[0.72, 0.55, 0.33], [0.62, 0.45, 0.25], [0.80, 0.64, 0.40]])
    for direction in (0, 1):
        for j in range(n_strands):
            off = -1 + d * (j + 0.5) + rng.uniform(-0.08, 0.08) * d  # hand-woven: irregular spacing
            phase = math.pi * (j + direction)
            a_j = amp * rng.uniform(0.8, 1.2)
            zc = a_j * np.sin(math.pi * u / d + phase)
            dz = a_j * math.pi / d * np.cos(math.pi * u / d + phase)
            t = np.stack([np.ones_like(u), np.zeros_like(u), dz], -1)
            t /= np.linalg.norm(t, axis=1, keepdims=True)
            side = np.array([0.0, 1.0, 0.0])
            up = np.cross(t, side)
            circ = (np.cos(th)[None, :, None] * side[None, None] + np.sin(th)[None, :, None] * up[:, None, :])
            centre = np.stack([u, np.full_like(u, off), zc], -1)
            p = centre[:, None, :] + tube_r * rng.uniform(0.85, 1.15) * circ
            if direction == 1:  # warp runs along y: swap x and y
                p = p[..., [1, 0, 2]]
                circ = circ[..., [1, 0, 2]]
                t = t[:, [1, 0, 2]]
            base = pal[rng.integers(len(pal))]
            stripe = 0.85 + 0.15 * np.cos(3 * th)[None, :, None]  # lengthwise fibres
            col = base * stripe * (1 + 0.05 * rng.standard_normal((along, ring, 1)))
            P.append(p.reshape(-1, 3)), N.append(circ.reshape(-1, 3)), C.append(col.reshape(-1, 3))
            T.append(np.repeat(t, ring, axis=0))
    E = _element_ids([len(p) for p in P])  # one element per strand; a weave has no ground
    P, N, C, T = map(np.concatenate, (P, N, C, T))
    spacing = max(2.0 / along, 2 * math.pi * tube_r / ring)
    return _labelled(surface_gaussians(P, N, C, spacing, flatness=0.4, tangent=T, elongation=1.3), E)


@_register
def style_stones(n_gaussians: int = 30000, seed: int = 0) -> GaussianScene:
    rng = np.random.default_rng(seed)
    centres, radii = _place_disks(rng, 14, 0.16, 0.34)
    n_ground = n_gaussians // 5
    per = (n_gaussians - n_ground) * radii**2 / (radii**2).sum()
    P, N, C = [], [], []
    for c, r, m in zip(centres, radii, per.astype(int)):
        d = _fibonacci_sphere(max(m * 2, 16))
        bumps = rng.standard_normal((6, 3))
        bumps /= np.linalg.norm(bumps, axis=1, keepdims=True)
        amp = rng.uniform(-0.18, 0.18, 6)
        rad = 1 + (amp[None] * np.exp(-((d @ bumps.T) - 1) ** 2 / 0.08)).sum(1)
        rad *= 1 + 0.03 * rng.standard_normal(len(d))  # rough surface
        p = d * rad[:, None] * r
        p[:, 2] *= 0.8
        p += np.array([c[0], c[1], -0.25 * r])  # half sunk
        keep = p[:, 2] > -0.02
        # normals by finite differences of the radial function are noisy; the radial direction with
        # the squash is close enough for disc orientation
        nrm = d * np.array([1.0, 1.0, 1.25])
        grey = rng.uniform(0.35, 0.6)
        col = np.array([grey, grey * 0.98, grey * 0.95]) * (1 + 0.12 * rng.standard_normal((len(p), 1)))
        speck = rng.random(len(p)) < 0.05
        col[speck] *= 0.4
        P.append(p[keep]), N.append(nrm[keep]), C.append(col[keep])
    g = _ground(rng, n_ground, np.array([0.45, 0.42, 0.38]), 0.25, roughness=0.015)
    P.append(g[0]), N.append(g[1]), C.append(g[2])
    E = _element_ids([len(p) for p in P[:-1]], ground=len(g[0]))
    P, N, C = map(np.concatenate, (P, N, C))
    return _labelled(surface_gaussians(P, N, C, _spacing(P, 4.0 + 4 * math.pi * (radii**2).sum() * 0.7)), E)


def _tube(a: np.ndarray, b: np.ndarray, radius: float, n_along: int, ring: int, rng, bend: float = 0.0):
    """Surface samples of a (slightly bent) tube from ``a`` to ``b``: points, normals, tangents [n, 3]."""
    t = np.linspace(0, 1, n_along)[:, None]
    axis = b - a
    side = np.cross(axis, [0.3, 0.5, 0.8])
    side /= np.linalg.norm(side)
    centre = a + t * axis + bend * np.sin(math.pi * t) * side
    tang = np.gradient(centre, axis=0)
    tang /= np.linalg.norm(tang, axis=1, keepdims=True).clip(1e-12)
    u = np.cross(tang, side)
    u /= np.linalg.norm(u, axis=1, keepdims=True).clip(1e-12)
    v = np.cross(tang, u)
    th = np.linspace(0, 2 * math.pi, ring, endpoint=False) + rng.uniform(0, 2 * math.pi)
    circ = np.cos(th)[None, :, None] * u[:, None] + np.sin(th)[None, :, None] * v[:, None]
    p = centre[:, None] + radius * circ
    return p.reshape(-1, 3), circ.reshape(-1, 3), np.repeat(tang, ring, axis=0)


def _ellipse(centre, e1, e2, a: float, b: float, m: int, rng, cup: float = 0.0):
    """m samples of an elliptic plate (semi-axes a along e1, b along e2) bent into a cup of depth ``cup``
    along e1 x e2: points, normals [m, 3], and its area."""
    r, th = np.sqrt(rng.random(m)), rng.uniform(0, 2 * math.pi, m)
    x, y = r * np.cos(th), r * np.sin(th)
    n0 = np.cross(e1, e2)
    n0 /= np.linalg.norm(n0)
    p = centre + (a * x)[:, None] * e1 + (b * y)[:, None] * e2 + (cup * (x**2 + y**2))[:, None] * n0
    nrm = n0[None] - (2 * cup * (x / a**2 * a))[:, None] * e1 - (2 * cup * (y / b**2 * b))[:, None] * e2
    return p, nrm, math.pi * a * b


@_register
def style_bouquet(n_gaussians: int = 30000, seed: int = 0) -> GaussianScene:
    """A bouquet: flower heads of several colours on a dome, each a ring of cupped petals around a dark
    centre, their stems converging below, leaves on some stems; no ground. One flower (petals and centre)
    is one element; stems and leaves are label 0. Seen from every side: a volume, not a patch."""
    rng = np.random.default_rng(seed)
    palette = np.array([[0.86, 0.14, 0.20], [0.96, 0.58, 0.70], [0.97, 0.95, 0.90], [0.98, 0.80, 0.20],
                        [0.58, 0.30, 0.76], [0.96, 0.50, 0.14]])
    dirs = _fibonacci_sphere(120)
    dirs = dirs[dirs[:, 2] > math.cos(math.radians(70))]
    dirs = dirs + 0.05 * rng.standard_normal(dirs.shape)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    n_fl = len(dirs)
    base = np.array([0.0, 0.0, -1.1])
    centres = 0.7 * dirs + np.array([0.0, 0.0, 0.15])
    radii = rng.uniform(0.11, 0.16, n_fl)
    heads = int(n_gaussians * 0.78)
    per_head = heads // n_fl
    green = np.array([0.22, 0.45, 0.16])
    P, N, C, T, S, E, STEM_EL = [], [], [], [], [], [], []
    for i, (c, d, r) in enumerate(zip(centres, dirs, radii)):
        e1 = np.cross(d, [0.0, 0.0, 1.0]) if abs(d[2]) < 0.99 else np.array([1.0, 0.0, 0.0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(d, e1)
        col = palette[rng.integers(len(palette))]
        k = int(rng.integers(6, 11))
        m_pet = int(per_head * 0.85 / k)
        for j in range(k):
            phi = 2 * math.pi * j / k + rng.uniform(-0.15, 0.15)
            out = math.cos(phi) * e1 + math.sin(phi) * e2
            tilt = math.radians(rng.uniform(20, 40))
            along = math.cos(tilt) * out + math.sin(tilt) * d
            p, nrm, area = _ellipse(c + 0.55 * r * along, along, np.cross(d, out), 0.5 * r, 0.28 * r, m_pet, rng,
                                    cup=0.08 * r)
            rim = np.linalg.norm(p - c, axis=1) / r
            P.append(p), N.append(nrm), C.append(col * (0.7 + 0.35 * rim[:, None])), T.append(None)
            S.append(np.full(m_pet, math.sqrt(area / m_pet))), E.append(np.full(m_pet, i + 1))
        m_c = max(per_head - k * m_pet, 8)
        dd = _fibonacci_sphere(m_c)
        R = np.stack([e1, e2, d], 1)
        p = c + (dd * np.array([0.22, 0.22, 0.12]) * r) @ R.T
        P.append(p), N.append(dd @ R.T), C.append(np.tile([0.35, 0.25, 0.08], (len(p), 1))), T.append(None)
        S.append(np.full(len(p), 0.05 * r)), E.append(np.full(len(p), i + 1))
    stems = int(n_gaussians * 0.15) // n_fl
    ring, stem_r = 4, 0.012
    for i, c in enumerate(centres):  # thin tubes of Gaussians long along the stem
        along = max(stems // ring, 4)
        p, nrm, t = _tube(c - 0.05 * dirs[i], base + 0.05 * rng.standard_normal(3), stem_r, along, ring,
                          rng, bend=rng.uniform(-0.08, 0.08))
        P.append(p), N.append(nrm), C.append(np.tile(green * rng.uniform(0.8, 1.1), (len(p), 1))), T.append(t)
        step = np.linalg.norm(c - base) / along
        width = max(2 * math.pi * stem_r / ring, step / 2.0)  # at most twice as long as wide: no needles
        S.append(np.full(len(p), width)), E.append(np.zeros(len(p), np.int64))
        STEM_EL.append(step / width)
    leaves = n_gaussians - sum(len(p) for p in P)
    n_leaf = max(n_fl // 3, 1)
    for i in rng.choice(n_fl, n_leaf, replace=False):
        at = base + 0.45 * (centres[i] - base)
        out = at - np.array([0.0, 0.0, at[2]])
        out = out / max(np.linalg.norm(out), 1e-9) if np.linalg.norm(out) > 1e-6 else np.array([1.0, 0.0, 0.0])
        up = np.array([0.0, 0.0, 1.0])
        along = (out + up) / np.linalg.norm(out + up)
        m = max(leaves // n_leaf, 8)
        p, nrm, area = _ellipse(at + 0.14 * along, along, np.cross(up, out) if np.linalg.norm(np.cross(up, out)) > 1e-6
                                else np.array([0.0, 1.0, 0.0]), 0.16, 0.05, m, rng, cup=0.01)
        P.append(p), N.append(nrm), C.append(np.tile(green * 1.15, (len(p), 1))), T.append(None)
        S.append(np.full(m, math.sqrt(area / m))), E.append(np.zeros(m, np.int64))
    parts, stem = [], iter(STEM_EL)
    for p, nrm, c, t, s in zip(P, N, C, T, S):
        c = c * (1 + 0.05 * rng.standard_normal((len(p), 1))) + 0.015 * rng.standard_normal((len(p), 3))
        parts.append(surface_gaussians(p, nrm, c, s, flatness=0.35, tangent=t,
                                       elongation=1.0 if t is None else next(stem)))
    return _labelled(GaussianScene.concat(parts), E)


@_register
def style_pinecone(n_gaussians: int = 30000, seed: int = 0) -> GaussianScene:
    """A pine cone: woody scales on a Fibonacci spiral round an ovoid core, each tilted outward and up,
    darker at its tip; no ground. One scale is one element; the core is label 0."""
    rng = np.random.default_rng(seed)
    n_sc = 110
    golden = math.pi * (3 - math.sqrt(5))
    z = np.linspace(-0.92, 0.92, n_sc)
    prof = lambda zz: 0.30 * np.clip(1 - zz**2, 0, None) ** 0.55 + 0.03  # noqa: E731 - the core's radius at height z
    browns = np.array([[0.52, 0.33, 0.18], [0.44, 0.27, 0.14], [0.60, 0.40, 0.22]])
    core = n_gaussians // 6
    per = (n_gaussians - core) // n_sc
    P, N, C, S, E = [], [], [], [], []
    for i in range(n_sc):
        phi = i * golden
        out = np.array([math.cos(phi), math.sin(phi), 0.0])
        rho = prof(z[i])
        foot = np.array([rho * out[0], rho * out[1], z[i]])
        size = 0.16 + 0.18 * np.clip(1 - abs(z[i]), 0, 1)  # larger scales round the middle
        tilt = math.radians(25)
        along = math.cos(tilt) * out + math.sin(tilt) * np.array([0.0, 0.0, 1.0])
        side = np.array([-out[1], out[0], 0.0])
        p, nrm, area = _ellipse(foot + 0.5 * size * along, along, side, 0.5 * size, 0.32 * size, per, rng,
                                cup=-0.06 * size)
        tip = np.clip(((p - foot) @ along) / size, 0, 1)
        col = browns[rng.integers(len(browns))] * (1.05 - 0.45 * tip[:, None])
        P.append(p), N.append(nrm), C.append(col), S.append(np.full(per, math.sqrt(area / per))),
        E.append(np.full(per, i + 1))
    zz = rng.uniform(-0.95, 0.95, core)
    th = rng.uniform(0, 2 * math.pi, core)
    r = prof(zz) * 0.9
    p = np.stack([r * np.cos(th), r * np.sin(th), zz], 1)
    P.append(p), N.append(np.stack([np.cos(th), np.sin(th), np.zeros(core)], 1))
    C.append(np.tile([0.30, 0.20, 0.11], (core, 1))), S.append(np.full(core, math.sqrt(4.0 / core)))
    E.append(np.zeros(core, np.int64))
    parts = [surface_gaussians(p, nrm, c * (1 + 0.05 * rng.standard_normal((len(p), 1))), s, flatness=0.35)
             for p, nrm, c, s in zip(P, N, C, S)]
    return _labelled(GaussianScene.concat(parts), E)


def _element_ids(sizes: list[int], ground: int = 0) -> list[np.ndarray]:
    """Labels in generation order: element j (1-based) for each of ``sizes``, then ``ground`` zeros."""
    return [np.full(m, j + 1, np.int64) for j, m in enumerate(sizes)] + [np.zeros(ground, np.int64)]


def _labelled(scene: GaussianScene, parts: list[np.ndarray]) -> GaussianScene:
    el = np.concatenate(parts)
    if len(el) != len(scene):
        raise AssertionError(f"element labels: {len(el)} for {len(scene)} Gaussians")
    scene.element = torch.from_numpy(el)
    return scene


def _spacing(points: np.ndarray, area: float) -> float:
    return math.sqrt(area / max(len(points), 1))


def style_scene(name: str, n_gaussians: int = 30000, seed: int = 0) -> GaussianScene:
    if name not in STYLES:
        raise ValueError(f"unknown procedural style '{name}' (choose from {', '.join(sorted(STYLES))})")
    return STYLES[name](n_gaussians=n_gaussians, seed=seed)


# ---------------------------------------------------------------------------------------------
# content from meshes shipped by pyvista
# ---------------------------------------------------------------------------------------------


def load_mesh(name: str):
    """A triangle mesh (pyvista PolyData) that pyvista ships, or a parametric shape; no downloads."""
    import pyvista as pv
    from pyvista import examples

    loaders = {
        "ant": examples.load_ant, "airplane": examples.load_airplane, "nut": examples.load_nut,
        "globe": lambda: examples.load_globe(), "torus": lambda: pv.ParametricTorus(ringradius=1.0, crosssectionradius=0.35),
        "sphere": lambda: pv.Sphere(radius=1.0, theta_resolution=64, phi_resolution=64),
    }
    if name not in loaders:
        raise ValueError(f"unknown content mesh '{name}' (choose from {', '.join(CONTENTS)})")
    mesh = loaders[name]()
    return mesh.extract_surface(algorithm=None).triangulate().clean()


def sample_mesh_surface(mesh, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, float]:
    """Area-weighted uniform samples on a triangle mesh -> points [n, 3], normals [n, 3], total area."""
    faces = mesh.faces.reshape(-1, 4)[:, 1:]
    v = np.asarray(mesh.points, dtype=np.float64)
    a, b, c = v[faces[:, 0]], v[faces[:, 1]], v[faces[:, 2]]
    cr = np.cross(b - a, c - a)
    area = 0.5 * np.linalg.norm(cr, axis=1)
    ok = area > 0
    a, b, c, cr, area = a[ok], b[ok], c[ok], cr[ok], area[ok]
    f = rng.choice(len(area), size=n, p=area / area.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    pts = (1 - s)[:, None] * a[f] + (s * (1 - r2))[:, None] * b[f] + (s * r2)[:, None] * c[f]
    nrm = cr[f] / np.linalg.norm(cr[f], axis=1, keepdims=True)
    return pts, nrm, float(area.sum())


def content_scene(name: str, n_gaussians: int = 20000, seed: int = 0) -> GaussianScene:
    """Surface Gaussians on a pyvista mesh, normalized to the unit ball centred at the origin, z up."""
    rng = np.random.default_rng(seed)
    mesh = load_mesh(name)
    pts, nrm, area = sample_mesh_surface(mesh, n_gaussians, rng)
    lo, hi = pts.min(0), pts.max(0)
    centre = 0.5 * (lo + hi)
    scale = 1.0 / np.linalg.norm(pts - centre, axis=1).max()
    pts = (pts - centre) * scale
    spacing = math.sqrt(area * scale**2 / n_gaussians)
    # colour: a light base with a gentle gradient along the longest axis and normal shading, so that
    # k-means on position + colour has something to see
    ax = np.argmax(hi - lo)
    g = (pts[:, ax] - pts[:, ax].min()) / max(np.ptp(pts[:, ax]), 1e-9)
    hue = CONTENT_COLORS.get(name, (0.7, 0.6, 0.5))
    base = np.asarray(hue)[None] * (0.55 + 0.45 * g[:, None])
    col = base * (0.8 + 0.2 * np.abs(nrm[:, 2:3]))
    # Gaussians shaped as a trained scene's are, not as the styles' round discs: thin (flatness 0.1),
    # elongated in the surface by a log-normal aspect (median 1.5) along a random tangent, log-normal
    # sizes (sigma 0.25) at the same area per Gaussian; so that the style's own Gaussian shapes
    # (aniso_w1) and orientations tell a stylized result from the content
    t = rng.standard_normal((n_gaussians, 3))
    el = np.exp(rng.normal(np.log(1.5), 0.35, n_gaussians))
    sp = spacing * np.exp(rng.normal(0.0, 0.25, n_gaussians)) / np.sqrt(el)
    return surface_gaussians(pts, nrm, col, sp, flatness=0.1, tangent=t, elongation=el)


def make_scene(kind: str, name: str, n_gaussians: int, seed: int = 0) -> GaussianScene:
    """``kind`` is ``style`` or ``content``."""
    if kind == "style":
        return style_scene(name, n_gaussians, seed)
    if kind == "content":
        return content_scene(name, n_gaussians, seed)
    raise ValueError(f"procedural scene kind must be 'style' or 'content', got '{kind}'")

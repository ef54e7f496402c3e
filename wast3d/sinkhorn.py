"""Debiased Sinkhorn divergence between point clouds (paper eq. 5, 6), with analytic gradients.

Conventions (those of geomloss' ``SamplesLoss("sinkhorn", p=2, blur, scaling, debias)``):

- cost ``C(x, y) = |x - y|^2 / 2`` (p = 2), entropic regularization ``eps = blur^p = blur^2``;
- ``OT_eps(a, b) = min_pi <pi, C> + eps KL(pi | a x b)`` (eq. 5);
- ``S_eps(a, b) = OT_eps(a, b) - 1/2 OT_eps(a, a) - 1/2 OT_eps(b, b)`` (eq. 6), computed from the dual
  potentials as ``<a, f_ba - f_aa> + <b, g_ab - g_bb>``;
- eps-scaling: eps runs from ``diameter^2`` down to ``blur^2`` by factors ``scaling^2``, one symmetric
  (averaged) Sinkhorn update per level, then a last full "extrapolation" update (geomloss' schedule).

The paper's gamma is geomloss' ``blur`` (a length), applied after each cluster pair is normalized to a
fixed extent (see :func:`wast3d.stylize.normalize_pair`), so gamma = 0.05 means 5 % of the cluster's
radius at any scene scale.

What this module adds to geomloss (and why):

- a fused C soft-min kernel (``csrc/sinkhorn_cpu.c``: online log-sum-exp, exponents clamped at -80, no
  N x M buffer, barycentric projection in the same pass). On CPU, geomloss' tensorized backend spends
  most of its time in exp of very negative arguments and page faults on N x M temporaries;
- ``extra_iters``: symmetric iterations at the final eps beyond geomloss' one-per-level schedule
  (geomloss has a ~2 % error floor at scaling 0.5 that only scaling >= 0.9 removes);
- warm starts: :class:`Potentials` from the previous optimization step seed the next solve, which then
  needs a few iterations at the final eps instead of a whole schedule;
- gradients from the potentials directly, by the envelope theorem:
  ``grad_y S = b_j (T_bb(y_j) - T_ba(y_j))`` and ``grad_x S = a_i (T_aa(x_i) - T_ab(x_i))``, with
  ``T_ba(y_j) = sum_i pi_ij x_i / b_j`` the barycentric projection (for OT without debiasing,
  ``grad_y OT = b_j (y_j - T_ba(y_j))``). Checked against geomloss' autograd and finite differences.

Degenerate inputs are handled, not NaN: the diameter is floored at ``blur`` (a single point, or
identical clouds, made geomloss' schedule take log(0)), and empty clouds raise a ValueError.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import torch

log = logging.getLogger(__name__)


@dataclass
class SinkhornConfig:
    """Solver settings. ``blur`` is gamma (a length in normalized units); eps = blur^2."""

    blur: float = 0.05
    scaling: float = 0.5
    debias: bool = True
    extra_iters: int = 0
    warm_iters: int = 3
    tol: float = 0.0  # > 0: iterate at the final eps until max |change of a potential| <= tol * eps
    max_iters: int = 200  # cap on those convergence iterations (per solve)
    backend: str = "auto"  # "native" | "torch" | "geomloss" (reference) | "auto"

    def __post_init__(self):
        if not (self.tol >= 0 and math.isfinite(self.tol)) or self.max_iters < 0 or self.warm_iters < 0 \
                or self.extra_iters < 0:
            raise ValueError("sinkhorn: need tol >= 0 (finite), max_iters, warm_iters, extra_iters >= 0")
        if not (self.blur > 0 and math.isfinite(self.blur)):
            raise ValueError(f"sinkhorn.blur must be a positive finite number, got {self.blur}")
        if not 0 < self.scaling < 1:
            raise ValueError(f"sinkhorn.scaling must be in (0, 1), got {self.scaling}")
        if self.backend not in ("auto", "native", "torch", "geomloss"):
            raise ValueError(f"sinkhorn.backend must be auto/native/torch/geomloss, got '{self.backend}'")


@dataclass
class Potentials:
    """Dual potentials of one pair at ``eps``: f_ba [N], g_ab [M], f_aa [N], g_bb [M]."""

    f_ba: torch.Tensor
    g_ab: torch.Tensor
    f_aa: torch.Tensor
    g_bb: torch.Tensor
    eps: float
    iterations: int = 0
    converged: bool = False  # every potential met the tolerance: f_aa may then be reused (x_fixed)


@dataclass
class Result:
    value: torch.Tensor  # scalar
    grad_x: torch.Tensor | None  # [N, D]
    grad_y: torch.Tensor | None  # [M, D]
    potentials: Potentials
    info: dict = field(default_factory=dict)


def epsilon_schedule(diameter: float, blur: float, scaling: float, p: int = 2) -> list[float]:
    """geomloss' schedule: ``[diameter^p] + exp(arange(p log diameter, p log blur, p log scaling)) + [blur^p]``."""
    diameter = max(diameter, blur)  # a point or identical clouds: diameter 0 -> log(0)
    steps = torch.arange(p * math.log(diameter), p * math.log(blur), p * math.log(scaling), dtype=torch.float64)
    return [diameter**p] + [math.exp(float(e)) for e in steps] + [blur**p]


def diameter_of(x: torch.Tensor, y: torch.Tensor) -> float:
    """Diagonal of the joint bounding box (geomloss' default estimate)."""
    both = torch.cat([x, y])
    return float((both.max(0).values - both.min(0).values).norm())


# ---- soft-min backends ----------------------------------------------------------------------


def softmin_torch(eps: float, x: torch.Tensor, y: torch.Tensor, h: torch.Tensor, bary: bool = False,
                  chunk: int = 2048):
    """f_i = -eps log sum_j exp(h_j - |x_i - y_j|^2 / (2 eps)); optional barycentre sum_j w_ij y_j.

    x: [N, D], y: [M, D], h: [M]. Chunked over rows (chunk x M memory), exponent clamped at -80.
    """
    fs, bs = [], []
    for xc in x.split(chunk):
        s = h[None, :] - torch.cdist(xc, y).square() / (2 * eps)
        m = s.max(dim=1, keepdim=True).values
        e = torch.exp((s - m).clamp_min(-80.0))
        z = e.sum(1)
        fs.append(-eps * (m[:, 0] + z.log()))
        if bary:
            bs.append((e @ y) / z[:, None])
    f = torch.cat(fs)
    return (f, torch.cat(bs)) if bary else f


def softmin_native(eps: float, x: torch.Tensor, y: torch.Tensor, h: torch.Tensor, bary: bool = False):
    from . import _native

    lib = _native.load("sinkhorn_cpu")
    x, h = x.contiguous(), h.contiguous()
    yT = y.T.contiguous()
    N, D = x.shape
    if D > 16:
        raise ValueError("native soft-min supports at most 16 feature dimensions")
    f = x.new_empty(N)
    b = x.new_empty(N, D) if bary else None
    sfx = "_f64" if x.dtype == torch.float64 else "_f32"
    P = _native.ptr
    fn = getattr(lib, "softmin" + sfx)
    import ctypes

    real = ctypes.c_double if x.dtype == torch.float64 else ctypes.c_float
    fn(P(x), P(yT), P(h), ctypes.c_int64(N), ctypes.c_int64(y.shape[0]), ctypes.c_int(D), real(eps),
       ctypes.c_int(torch.get_num_threads()), P(f), P(b) if bary else ctypes.c_void_p(0))
    return (f, b) if bary else f


def pick_backend(cfg: SinkhornConfig, x: torch.Tensor) -> str:
    if cfg.backend != "auto":
        return cfg.backend
    if x.is_cuda:
        return "torch"
    from . import _native

    return "native" if _native.load("sinkhorn_cpu") is not None else "torch"


# ---- the solver -----------------------------------------------------------------------------


@torch.no_grad()
def sinkhorn(x: torch.Tensor, y: torch.Tensor, cfg: SinkhornConfig = SinkhornConfig(),
             a: torch.Tensor | None = None, b: torch.Tensor | None = None, diameter: float | None = None,
             init: Potentials | None = None, grad_x: bool = False, grad_y: bool = True,
             x_fixed: bool = False) -> Result:
    """Debiased Sinkhorn divergence S_eps(x, y) (or OT_eps with ``cfg.debias=False``) and its gradients.

    x: [N, D], y: [M, D] (features; cost |x-y|^2/2); a: [N], b: [M] weights summing to 1 (uniform if
    None). ``diameter`` sets the start of the eps schedule (computed if None). With ``init`` (the
    potentials of a previous, nearby problem at the same final eps) the schedule is skipped and
    ``cfg.warm_iters`` updates are done at the final eps instead. ``x_fixed=True`` with ``init`` says
    x is the same as in the previous problem: its self-potential f_aa is reused, not updated (it
    depends on x alone, and grad_y does not involve it), saving a quarter of the work per iteration.
    """
    if x.ndim != 2 or y.ndim != 2 or x.shape[1] != y.shape[1]:
        raise ValueError(f"sinkhorn: x [N, D] and y [M, D] must share D, got {list(x.shape)} and {list(y.shape)}")
    if len(x) == 0 or len(y) == 0:
        raise ValueError(f"sinkhorn: empty point cloud (N={len(x)}, M={len(y)})")
    if not (torch.isfinite(x).all() and torch.isfinite(y).all()):
        raise ValueError("sinkhorn: non-finite coordinates in the input")
    backend = pick_backend(cfg, x)
    if backend == "geomloss":
        return _sinkhorn_geomloss(x, y, cfg, a, b, diameter, grad_x, grad_y)
    sm = softmin_native if backend == "native" else softmin_torch
    N, M = len(x), len(y)
    a = x.new_full((N,), 1.0 / N) if a is None else a.to(x)
    b = y.new_full((M,), 1.0 / M) if b is None else b.to(y)
    a_log, b_log = a.log(), b.log()
    eps_final = cfg.blur**2
    debias = cfg.debias

    def update(eps, f_ba, g_ab, f_aa, g_bb, avg: bool):
        ft_ba = sm(eps, x, y, b_log + g_ab / eps)
        # schedule levels: symmetric (Jacobi) update as geomloss; at the final eps: alternating
        # (Gauss-Seidel) for the cross potentials, which converges about twice as fast
        gt_ab = sm(eps, y, x, a_log + (f_ba if avg else ft_ba) / eps)
        if debias:
            ft_aa = f_aa if reuse_aa else sm(eps, x, x, a_log + f_aa / eps)
            gt_bb = sm(eps, y, y, b_log + g_bb / eps)
        else:
            ft_aa, gt_bb = f_aa, g_bb
        half = lambda u, v: 0.5 * (u + v)  # noqa: E731
        if avg:
            return half(f_ba, ft_ba), half(g_ab, gt_ab), half(f_aa, ft_aa), half(g_bb, gt_bb)
        return ft_ba, gt_ab, half(f_aa, ft_aa), half(g_bb, gt_bb)

    iters = 0
    if init is not None and abs(init.eps - eps_final) <= 1e-12 * eps_final and len(init.f_ba) == N \
            and len(init.g_ab) == M:
        f_ba, g_ab, f_aa, g_bb = init.f_ba, init.g_ab, init.f_aa, init.g_bb
        schedule = [eps_final] * cfg.warm_iters
        n_sched = 0
        # f_aa depends on x alone; reusing it is exact only once it has converged (a cold eps-scaling
        # solve leaves it off by as much as the divergence itself at large blur, and a stale f_aa
        # biases every later value: the reported loss went negative)
        reuse_aa = x_fixed and not grad_x and init.converged
    else:
        d = diameter_of(x, y) if diameter is None else diameter
        schedule = epsilon_schedule(d, cfg.blur, cfg.scaling)
        n_sched = len(schedule)
        reuse_aa = False  # a cold solve computes f_aa
        schedule = schedule + [eps_final] * cfg.extra_iters
        eps0 = schedule[0]
        # initialization at the largest eps, from zero potentials (geomloss)
        f_ba = sm(eps0, x, y, b_log)
        g_ab = sm(eps0, y, x, a_log)
        f_aa = sm(eps0, x, x, a_log) if debias else torch.zeros_like(f_ba)
        g_bb = sm(eps0, y, y, b_log) if debias else torch.zeros_like(g_ab)
        iters = 1
    for k, eps in enumerate(schedule):
        f_ba, g_ab, f_aa, g_bb = update(eps, f_ba, g_ab, f_aa, g_bb, avg=k < n_sched)
        iters += 1
    converged = False
    if cfg.tol > 0:
        # convergence test at the final eps: the largest change of any potential in one iteration,
        # against tol * eps (floored at a few ulps of the potentials' magnitude for float32)
        floor = 8 * torch.finfo(x.dtype).eps
        for _ in range(cfg.max_iters):
            new = update(eps_final, f_ba, g_ab, f_aa, g_bb, avg=False)
            change = max(float((u - v).abs().max()) for u, v in zip(new, (f_ba, g_ab, f_aa, g_bb)))
            scale = max(float(t.abs().max()) for t in new)
            f_ba, g_ab, f_aa, g_bb = new
            iters += 1
            if change <= max(cfg.tol * eps_final, floor * scale):
                converged = True
                break
    # last extrapolation (full update), with barycentres where a gradient is wanted
    eps = eps_final

    def last(xq, yr, h, bary):
        return sm(eps, xq, yr, h, bary=True) if bary else (sm(eps, xq, yr, h), None)

    f_ba_new, T_ab = last(x, y, b_log + g_ab / eps, grad_x)
    g_ab_new, T_ba = last(y, x, a_log + f_ba / eps, grad_y)
    if debias:
        f_aa_new, T_aa = (f_aa, None) if reuse_aa else last(x, x, a_log + f_aa / eps, grad_x)
        g_bb_new, T_bb = last(y, y, b_log + g_bb / eps, grad_y)
        value = (a * (f_ba_new - f_aa_new)).sum() + (b * (g_ab_new - g_bb_new)).sum()
        gx = a[:, None] * (T_aa - T_ab) if grad_x else None
        gy = b[:, None] * (T_bb - T_ba) if grad_y else None
    else:
        f_aa_new, g_bb_new = f_aa, g_bb
        value = (a * f_ba_new).sum() + (b * g_ab_new).sum()
        gx = a[:, None] * (x - T_ab) if grad_x else None
        gy = b[:, None] * (y - T_ba) if grad_y else None
    iters += 1
    pot = Potentials(f_ba_new, g_ab_new, f_aa_new, g_bb_new, eps_final, iters, converged)
    if not torch.isfinite(value):
        raise FloatingPointError(f"sinkhorn: non-finite divergence (N={N}, M={M}, eps={eps_final:g}, backend={backend})")
    return Result(value, gx, gy, pot, {"iterations": iters, "backend": backend, "converged": converged,
                                       "reused_f_aa": reuse_aa})


def _sinkhorn_geomloss(x, y, cfg, a, b, diameter, grad_x, grad_y) -> Result:
    """The paper's library, as a reference and an option (one call per pair, autograd gradients)."""
    from geomloss import SamplesLoss

    d = max(diameter_of(x, y) if diameter is None else diameter, cfg.blur)
    loss = SamplesLoss("sinkhorn", p=2, blur=cfg.blur, scaling=cfg.scaling, debias=cfg.debias, diameter=d,
                       backend="tensorized")
    with torch.enable_grad():
        xx = x.detach().clone().requires_grad_(grad_x)
        yy = y.detach().clone().requires_grad_(grad_y)
        args = (xx, yy) if a is None else (a, xx, b, yy)
        v = loss(*args)
        ins = [t for t, need in ((xx, grad_x), (yy, grad_y)) if need]
        grads = list(torch.autograd.grad(v, ins)) if ins else []
    gx = grads.pop(0) if grad_x else None
    gy = grads.pop(0) if grad_y else None
    dummy = x.new_zeros(0)
    return Result(v.detach(), gx, gy, Potentials(dummy, dummy, dummy, dummy, cfg.blur**2), {"backend": "geomloss"})


class SinkhornDivergence(torch.autograd.Function):
    """``S = SinkhornDivergence.apply(x, y, cfg)``: autograd wrapper around :func:`sinkhorn`."""

    @staticmethod
    def forward(ctx, x, y, cfg):
        r = sinkhorn(x.detach(), y.detach(), cfg, grad_x=x.requires_grad, grad_y=y.requires_grad)
        ctx.save_for_backward(*(g if g is not None else x.new_zeros(0) for g in (r.grad_x, r.grad_y)))
        return r.value

    @staticmethod
    def backward(ctx, g):
        gx, gy = ctx.saved_tensors
        return (g * gx if gx.numel() else None), (g * gy if gy.numel() else None), None


def exact_w2(x: torch.Tensor, y: torch.Tensor, a=None, b=None) -> float:
    """Exact OT with cost |x-y|^2/2 (so the value is W2^2 / 2) by POT's network simplex ``ot.emd2``."""
    import ot

    xn, yn = x.detach().double().cpu().numpy(), y.detach().double().cpu().numpy()
    M = ot.dist(xn, yn, metric="sqeuclidean") / 2
    a = torch.full((len(x),), 1.0 / len(x), dtype=torch.float64).numpy() if a is None else a.double().numpy()
    b = torch.full((len(y),), 1.0 / len(y), dtype=torch.float64).numpy() if b is None else b.double().numpy()
    return float(ot.emd2(a, b, M, numItermax=10_000_000))

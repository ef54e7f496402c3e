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
from dataclasses import dataclass, field, replace
from typing import NamedTuple

import torch

from .options import checked, option

log = logging.getLogger(__name__)


@dataclass
@checked("sinkhorn")
class SinkhornConfig:
    """Solver settings. ``blur`` is gamma (a length in normalized units); eps = blur^2."""

    blur: float = option(0.05, "gamma, a length in the units of the features (stage 5: of each normalized cluster)",
                               exclusiveMinimum=0)
    scaling: float = option(0.5, "eps-scaling ratio of a cold solve (geomloss' scaling)",
                                 exclusiveMinimum=0, exclusiveMaximum=1)
    debias: bool = option(True, "false: entropic OT without the debiasing terms (eq. 5; the paper's ablation)")
    extra_iters: int = option(0, "extra iterations at the final eps of a cold solve", minimum=0)
    warm_iters: int = option(3, "fixed iterations of a warm-started solve (with tol > 0, followed by more until "
                                "converged)", minimum=0)
    tol: float = option(0.0, "iterate at the final eps until the potentials change by <= tol * eps (0: fixed iteration "
                             "counts)", minimum=0)
    max_iters: int = option(200, "cap on the iterations of a tol-converged solve", minimum=0)
    backend: str = option("auto", "auto (native C kernel on CPU, torch on CUDA), native, torch or geomloss",
                                  enum=["auto", "native", "torch", "geomloss"])

    def __post_init__(self):
        if not (math.isfinite(self.tol) and math.isfinite(self.blur)):
            raise ValueError(f"sinkhorn: tol and blur must be finite, got {self.tol}, {self.blur}")


@dataclass
class Potentials:
    """Dual potentials of K packed problems (rows of problem k at ``x_off[k]:x_off[k+1]``):
    f_ba [R], g_ab [C], f_aa [R], g_bb [C]; per problem: eps [K] (float64), iterations [K],
    converged [K] (every potential met the tolerance: f_aa may then be reused, ``x_fixed``)."""

    f_ba: torch.Tensor
    g_ab: torch.Tensor
    f_aa: torch.Tensor
    g_bb: torch.Tensor
    eps: torch.Tensor
    iterations: torch.Tensor
    converged: torch.Tensor
    x_off: torch.Tensor | None = None
    y_off: torch.Tensor | None = None


@dataclass
class Result:
    value: torch.Tensor  # scalar (sinkhorn) or [K] (sinkhorn_batched)
    grad_x: torch.Tensor | None  # [N, D] ([R, D] packed)
    grad_y: torch.Tensor | None  # [M, D] ([C, D] packed)
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


# ---- ragged (packed) batches -----------------------------------------------------------------


def segment_ids(off: torch.Tensor) -> torch.Tensor:
    """off [K+1] (CSR offsets) -> [off[K]]: the problem of each packed row."""
    return torch.repeat_interleave(torch.arange(len(off) - 1, device=off.device), off.diff())


def segment_reduce(v: torch.Tensor, ids: torch.Tensor, K: int, op: str) -> torch.Tensor:
    """Per-problem ``sum`` / ``amax`` / ``amin`` of v [R] or [R, D] -> [K] or [K, D]."""
    out = v.new_zeros((K,) + v.shape[1:])
    idx = ids.view(-1, *([1] * (v.ndim - 1))).expand_as(v)
    return out.scatter_reduce_(0, idx, v, op, include_self=False)


def diameters_of(x: torch.Tensor, x_off: torch.Tensor, y: torch.Tensor, y_off: torch.Tensor) -> list[float]:
    """:func:`diameter_of` of every packed problem at once."""
    K = len(x_off) - 1
    xi, yi = segment_ids(x_off).to(x.device), segment_ids(y_off).to(y.device)
    hi = torch.maximum(segment_reduce(x, xi, K, "amax"), segment_reduce(y, yi, K, "amax"))
    lo = torch.minimum(segment_reduce(x, xi, K, "amin"), segment_reduce(y, yi, K, "amin"))
    return (hi - lo).norm(dim=1).tolist()


def _check_offsets(off: torch.Tensor | None, n: int, what: str) -> torch.Tensor:
    if off is None:
        return torch.tensor([0, n])
    off = torch.as_tensor(off, dtype=torch.long).cpu()
    if off.ndim != 1 or len(off) < 2 or int(off[0]) != 0 or int(off[-1]) != n or bool((off.diff() < 0).any()):
        raise ValueError(f"sinkhorn: {what} must be CSR offsets [K+1] from 0 to {n}, non-decreasing")
    return off


# ---- soft-min backends ----------------------------------------------------------------------
# f_i = -eps_k log sum_{j in problem k} exp(h_j - |x_i - y_j|^2 / (2 eps_k)) for the rows i of every
# active problem k (the rows of the others are 0); optional barycentre sum_j w_ij y_j. x [R, D], y [C, D],
# h [C]; eps a float or [K]; x_off, y_off [K+1] CSR offsets (None: one problem); active [A] problem ids.


def softmin_torch(eps, x: torch.Tensor, y: torch.Tensor, h: torch.Tensor, bary: bool = False,
                  x_off=None, y_off=None, active=None, budget: int | None = None):
    """Reference and CUDA backend. One problem: chunks of rows (chunk x M memory). Several: the active
    problems padded to a common size in groups of at most ``budget`` matrix entries (4 launches per
    group instead of per problem), padded columns masked. Exponent clamped at -80 as in the C kernel."""
    f = x.new_zeros(len(x))
    b = x.new_zeros(x.shape) if bary else None
    if x_off is None:
        _softmin_dense(float(eps), x[None], y[None], h[None], None, f[None], b[None] if bary else None)
        return (f, b) if bary else f
    budget = budget or (2**26 if x.is_cuda else 2**22)
    eps = torch.as_tensor(eps, dtype=x.dtype, device=x.device).reshape(-1)
    active = torch.arange(len(x_off) - 1) if active is None else torch.as_tensor(active).cpu()
    n, m = x_off.diff(), y_off.diff()
    group: list[int] = []

    def flush():
        if not group:
            return
        if len(group) == 1:  # one problem: views, no padding
            k = group[0]
            xs, ys = slice(int(x_off[k]), int(x_off[k + 1])), slice(int(y_off[k]), int(y_off[k + 1]))
            _softmin_dense(eps[k], x[None, xs], y[None, ys], h[None, ys], None, f[None, xs],
                           b[None, xs] if bary else None)
            group.clear()
            return
        ks = torch.tensor(group)
        nmax, mmax = int(n[ks].max()), int(m[ks].max())
        ri = torch.arange(nmax)
        ci = torch.arange(mmax)
        rmask, cmask = ri[None] < n[ks, None], ci[None] < m[ks, None]  # [G, nmax], [G, mmax]
        rows = (x_off[ks, None] + ri[None]).where(rmask, x_off[ks, None]).to(x.device)
        cols = (y_off[ks, None] + ci[None]).where(cmask, y_off[ks, None]).to(x.device)
        cm = cmask.to(x.device)
        hp = h[cols].masked_fill(~cm, -math.inf)
        fo = x.new_empty(rows.shape)
        bo = x.new_empty(rows.shape + (x.shape[1],)) if bary else None
        _softmin_dense(eps[ks.to(x.device)], x[rows], y[cols], hp, cm, fo, bo)
        keep = rmask.to(x.device)
        f[rows[keep]] = fo[keep]
        if bary:
            b[rows[keep]] = bo[keep]
        group.clear()

    for k in active.tolist():
        if group and (len(group) + 1) * max(int(n[group + [k]].max()), 1) * max(int(m[group + [k]].max()), 1) > budget:
            flush()
        group.append(k)
    flush()
    return (f, b) if bary else f


def _softmin_dense(eps, x, y, h, cmask, f_out, b_out, chunk_budget: int = 2**24):
    """x [G, N, D], y [G, M, D], h [G, M] (-inf on padding), cmask [G, M] or None; eps float or [G].
    Writes f_out [G, N] and b_out [G, N, D]; rows in chunks so that G x chunk x M <= chunk_budget."""
    G, N, _ = x.shape
    M = y.shape[1]
    e_ = torch.as_tensor(eps, dtype=x.dtype, device=x.device).reshape(-1, 1, 1).expand(G, 1, 1)
    chunk = max(1, chunk_budget // max(1, G * M))
    for r0 in range(0, N, chunk):
        xc = x[:, r0:r0 + chunk]
        s = h[:, None, :] - torch.cdist(xc, y).square() / (2 * e_)
        mx = s.amax(dim=2, keepdim=True)
        e = torch.exp((s - mx).clamp_min(-80.0))
        if cmask is not None:
            e = e * cmask[:, None, :]
        z = e.sum(2)
        f_out[:, r0:r0 + chunk] = -e_[:, :, 0] * (mx[:, :, 0] + z.log())
        if b_out is not None:
            b_out[:, r0:r0 + chunk] = (e @ y) / z[:, :, None]


def softmin_native(eps, x: torch.Tensor, y: torch.Tensor, h: torch.Tensor, bary: bool = False,
                   x_off=None, y_off=None, active=None):
    """The fused C kernel (``csrc/sinkhorn_cpu.c``), one call for every active problem (ragged)."""
    import ctypes

    from . import _native

    lib = _native.load("sinkhorn_cpu")
    x, h = x.contiguous(), h.contiguous()
    yT = y.T.contiguous()
    R, D = x.shape
    if D > 16:
        raise ValueError("native soft-min supports at most 16 feature dimensions")
    x_off = torch.tensor([0, R]) if x_off is None else x_off
    y_off = torch.tensor([0, len(y)]) if y_off is None else y_off
    xo, yo = x_off.to(torch.int64).contiguous(), y_off.to(torch.int64).contiguous()
    e = torch.as_tensor(eps, dtype=x.dtype).reshape(-1).expand(len(xo) - 1).contiguous()
    act = (torch.arange(len(xo) - 1) if active is None else torch.as_tensor(active)).to(torch.int64).contiguous()
    f = x.new_zeros(R)
    b = x.new_zeros(R, D) if bary else None
    P = _native.ptr
    fn = getattr(lib, "softmin_ragged" + ("_f64" if x.dtype == torch.float64 else "_f32"))
    rc = fn(P(x), P(xo), P(yT), P(yo), ctypes.c_int64(len(y)), P(h), P(e), P(act), ctypes.c_int64(len(act)),
            ctypes.c_int(D), ctypes.c_int(torch.get_num_threads()), P(f), P(b) if bary else ctypes.c_void_p(0))
    if rc != 0:
        raise MemoryError("native soft-min: could not allocate its work list")
    return (f, b) if bary else f


def pick_backend(cfg: SinkhornConfig, x: torch.Tensor) -> str:
    if cfg.backend != "auto":
        return cfg.backend
    if x.is_cuda:
        return "torch"
    from . import _native

    return "native" if _native.load("sinkhorn_cpu") is not None else "torch"


# ---- the solver -----------------------------------------------------------------------------


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
    One problem of :func:`sinkhorn_batched`.
    """
    if x.ndim != 2 or y.ndim != 2 or x.shape[1] != y.shape[1]:
        raise ValueError(f"sinkhorn: x [N, D] and y [M, D] must share D, got {list(x.shape)} and {list(y.shape)}")
    r = sinkhorn_batched(x, y, None, None, cfg, a, b, diameter=None if diameter is None else [diameter],
                         init=init, grad_x=grad_x, grad_y=grad_y, x_fixed=x_fixed)
    info = {k: (v.item() if torch.is_tensor(v) else v) for k, v in r.info.items()}
    return Result(r.value[0], r.grad_x, r.grad_y, r.potentials, info)


class _Duals(NamedTuple):
    """The four dual potentials of K packed problems during a solve: f_ba [R], g_ab [C], f_aa [R], g_bb [C]."""

    f_ba: torch.Tensor
    g_ab: torch.Tensor
    f_aa: torch.Tensor
    g_bb: torch.Tensor


@dataclass
class _Packed:
    """K problems packed without padding: x [R, D] (problem k at ``xo[k]:xo[k+1]``), y [C, D] likewise,
    their log-weights, and the soft-min kernel of the backend (one call per step over the active
    problems)."""

    x: torch.Tensor
    y: torch.Tensor
    xo: torch.Tensor  # [K+1], host-side: the kernels take the offsets from there
    yo: torch.Tensor
    a_log: torch.Tensor  # [R]
    b_log: torch.Tensor  # [C]
    softmin: object
    debias: bool

    def __post_init__(self):
        self.K = len(self.xo) - 1
        self.xid, self.yid = segment_ids(self.xo).to(self.x.device), segment_ids(self.yo).to(self.x.device)

    def rows(self, t: torch.Tensor, ids: torch.Tensor) -> torch.Tensor:
        """Per-problem values [K] -> per-row [len(ids)]."""
        return t.to(device=self.x.device, dtype=self.x.dtype)[ids]

    def soft(self, eps_k, q, qo, r, ro, h, act, bary=False):
        """``-eps log sum_j exp(h_j - |q_i - r_j|^2 / (2 eps))`` for the problems in ``act`` (ids)."""
        return self.softmin(eps_k.to(self.x.dtype), q, r, h, bary=bary, x_off=qo, y_off=ro, active=act)

    def zeros(self) -> _Duals:
        x, y = self.x, self.y
        return _Duals(x.new_zeros(len(x)), y.new_zeros(len(y)), x.new_zeros(len(x)), y.new_zeros(len(y)))

    def where(self, mask: torch.Tensor, new: _Duals, old: _Duals) -> _Duals:
        """``new`` on the rows of the problems in ``mask`` [K] bool, ``old`` elsewhere."""
        mx, my = self.rows(mask, self.xid).bool(), self.rows(mask, self.yid).bool()
        return _Duals(*(torch.where(m, u, v) for u, v, m in zip(new, old, (mx, my, mx, my))))

    def initial(self, eps0: torch.Tensor, C: torch.Tensor) -> _Duals:
        """The potentials at the largest eps from zero potentials (geomloss), for the problems C (ids)."""
        x, y, xo, yo = self.x, self.y, self.xo, self.yo
        zero_x, zero_y = torch.zeros_like(self.a_log), torch.zeros_like(self.b_log)
        return _Duals(self.soft(eps0, x, xo, y, yo, self.b_log, C), self.soft(eps0, y, yo, x, xo, self.a_log, C),
                      self.soft(eps0, x, xo, x, xo, self.a_log, C) if self.debias else zero_x,
                      self.soft(eps0, y, yo, y, yo, self.b_log, C) if self.debias else zero_y)

    def update(self, eps_k: torch.Tensor, st: _Duals, act: torch.Tensor, avg: torch.Tensor,
               reuse: torch.Tensor) -> _Duals:
        """One Sinkhorn update of the problems in ``act`` [K] bool (the others keep their potentials).
        avg [K]: symmetric (Jacobi, averaged) update as geomloss' schedule levels; else at the final
        eps alternating (Gauss-Seidel) for the cross potentials, which converges about twice as fast.
        reuse [K]: f_aa kept as it is (converged, x fixed)."""
        x, y, xo, yo, xid, yid = self.x, self.y, self.xo, self.yo, self.xid, self.yid
        A = act.nonzero()[:, 0]
        ex, ey = self.rows(eps_k, xid), self.rows(eps_k, yid)
        avg_x, avg_y = self.rows(avg, xid).bool(), self.rows(avg, yid).bool()
        ft_ba = self.soft(eps_k, x, xo, y, yo, self.b_log + st.g_ab / ey, A)
        gt_ab = self.soft(eps_k, y, yo, x, xo, self.a_log + torch.where(avg_x, st.f_ba, ft_ba) / ex, A)
        if self.debias:
            ft_aa = self.soft(eps_k, x, xo, x, xo, self.a_log + st.f_aa / ex, (act & ~reuse).nonzero()[:, 0])
            ft_aa = torch.where(self.rows(reuse, xid).bool(), st.f_aa, ft_aa)
            gt_bb = self.soft(eps_k, y, yo, y, yo, self.b_log + st.g_bb / ey, A)
        else:
            ft_aa, gt_bb = st.f_aa, st.g_bb
        half = lambda u, v: 0.5 * (u + v)  # noqa: E731
        new = _Duals(torch.where(avg_x, half(st.f_ba, ft_ba), ft_ba), torch.where(avg_y, half(st.g_ab, gt_ab), gt_ab),
                     half(st.f_aa, ft_aa), half(st.g_bb, gt_bb))
        return self.where(act, new, st)


def _check_packed(x, y, x_off, y_off, cfg: SinkhornConfig, blur):
    """Validated offsets, sizes and per-problem blur of :func:`sinkhorn_batched`'s inputs:
    (x_off [K+1], y_off [K+1], n [K], m [K], blur_k [K] float64 on the CPU)."""
    if x.ndim != 2 or y.ndim != 2 or x.shape[1] != y.shape[1]:
        raise ValueError(f"sinkhorn: x [R, D] and y [C, D] must share D, got {list(x.shape)} and {list(y.shape)}")
    x_off, y_off = _check_offsets(x_off, len(x), "x_off"), _check_offsets(y_off, len(y), "y_off")
    K = len(x_off) - 1
    if len(y_off) - 1 != K:
        raise ValueError(f"sinkhorn: x_off has {K} problems, y_off {len(y_off) - 1}")
    n, m = x_off.diff(), y_off.diff()
    if bool((n == 0).any() | (m == 0).any()):
        k = int(((n == 0) | (m == 0)).nonzero()[0])
        raise ValueError(f"sinkhorn: empty point cloud (problem {k}: N={int(n[k])}, M={int(m[k])})")
    if not (torch.isfinite(x).all() and torch.isfinite(y).all()):
        raise ValueError("sinkhorn: non-finite coordinates in the input")
    blur_k = torch.full((K,), cfg.blur, dtype=torch.float64) if blur is None else \
        torch.as_tensor(blur, dtype=torch.float64).cpu().reshape(K)
    if not bool(((blur_k > 0) & torch.isfinite(blur_k)).all()):
        raise ValueError("sinkhorn: every problem's blur must be positive and finite")
    return x_off, y_off, n, m, blur_k


def _warm_start(P: _Packed, init: Potentials | None, eps_final: torch.Tensor, x_fixed: bool, grad_x: bool):
    """(duals, warm [K], reuse [K]): ``init``'s potentials where they are of these problems at the same
    final eps (warm), else zeros. reuse: f_aa depends on x alone, so with x fixed it is kept, but only
    where it had converged (a cold eps-scaling solve leaves it off by as much as the divergence itself
    at large blur, and a stale f_aa biases every later value: the reported loss went negative)."""
    K = P.K
    warm = torch.zeros(K, dtype=torch.bool)
    reuse = warm.clone()
    if init is None or len(init.f_ba) != len(P.x) or len(init.g_ab) != len(P.y) \
            or (init.x_off is not None and not torch.equal(init.x_off.cpu(), P.xo)) \
            or (init.y_off is not None and not torch.equal(init.y_off.cpu(), P.yo)):
        return P.zeros(), warm, reuse
    ie = torch.as_tensor(init.eps, dtype=torch.float64).cpu().reshape(-1).expand(K)
    warm = (ie - eps_final).abs() <= 1e-12 * eps_final
    if x_fixed and not grad_x:
        reuse = warm & torch.as_tensor(init.converged).cpu().reshape(-1).expand(K).bool()
    return _Duals(init.f_ba, init.g_ab, init.f_aa, init.g_bb), warm, reuse


def _schedules(P: _Packed, warm: torch.Tensor, eps_final: torch.Tensor, blur_k: torch.Tensor, diameter,
               cfg: SinkhornConfig) -> tuple[list[list[float]], list[int]]:
    """Each problem's eps per step and how many of its first steps are symmetric (averaged): a cold
    problem runs geomloss' schedule (:func:`epsilon_schedule`, diameter^2 down to blur^2) and
    ``extra_iters`` more at the final eps; a warm one ``warm_iters`` alternating steps at the final eps."""
    cold = ~warm
    diams = diameters_of(P.x, P.xo, P.y, P.yo) if bool(cold.any()) and diameter is None else None
    scheds, n_avg = [], []
    for k in range(P.K):
        ef, bk = float(eps_final[k]), float(blur_k[k])
        if cold[k]:
            d = float(diameter[k]) if diameter is not None else diams[k]
            s = epsilon_schedule(d, bk, cfg.scaling)
            scheds.append(s + [ef] * cfg.extra_iters)
            n_avg.append(len(s))
        else:
            scheds.append([ef] * cfg.warm_iters)
            n_avg.append(0)
    return scheds, n_avg


def _converge(P: _Packed, st: _Duals, eps_final: torch.Tensor, reuse: torch.Tensor, cfg: SinkhornConfig,
              iters: torch.Tensor) -> tuple[_Duals, torch.Tensor]:
    """Alternating updates at the final eps until, per problem, the largest change of any potential in
    one iteration is at most ``tol * eps`` (floored at a few ulps of the potentials' magnitude for
    float32), or ``max_iters``. Counts into ``iters`` [K]; returns the duals and converged [K]."""
    no = torch.zeros(P.K, dtype=torch.bool)
    converged, pending = no.clone(), ~no
    floor = 8 * torch.finfo(P.x.dtype).eps
    ids = (P.xid, P.yid, P.xid, P.yid)
    for _ in range(cfg.max_iters):
        if not pending.any():
            break
        new = P.update(eps_final, st, pending, no, reuse)
        change = torch.stack([segment_reduce((u - v).abs(), i, P.K, "amax") for u, v, i in zip(new, st, ids)]).amax(0)
        scale = torch.stack([segment_reduce(u.abs(), i, P.K, "amax") for u, i in zip(new, ids)]).amax(0)
        st = new
        iters += pending.long()
        done = pending & (change.double().cpu() <= torch.maximum(cfg.tol * eps_final, floor * scale.double().cpu()))
        converged |= done
        pending &= ~done
    return st, converged


def _extrapolate(P: _Packed, st: _Duals, eps_final: torch.Tensor, reuse: torch.Tensor, a: torch.Tensor,
                 b: torch.Tensor, grad_x: bool, grad_y: bool):
    """The last full update, with barycentres where a gradient is wanted: (value [K], grad_x [R, D] or
    None, grad_y [C, D] or None, duals). Debiased: ``S = <a, f_ba - f_aa> + <b, g_ab - g_bb>``,
    ``grad_y S = b (T_bb - T_ba)``; without debiasing ``OT = <a, f_ba> + <b, g_ab>``,
    ``grad_y OT = b (y - T_ba)`` (and alike for x)."""
    x, y, xo, yo, xid, yid, K = P.x, P.y, P.xo, P.yo, P.xid, P.yid, P.K
    ex, ey = P.rows(eps_final, xid), P.rows(eps_final, yid)
    every = torch.arange(K)

    def last(q, qo, r, ro, h, bary, act=every):
        return P.soft(eps_final, q, qo, r, ro, h, act, bary=True) if bary else \
            (P.soft(eps_final, q, qo, r, ro, h, act), None)

    f_ba, T_ab = last(x, xo, y, yo, P.b_log + st.g_ab / ey, grad_x)
    g_ab, T_ba = last(y, yo, x, xo, P.a_log + st.f_ba / ex, grad_y)
    if P.debias:
        f_aa, T_aa = last(x, xo, x, xo, P.a_log + st.f_aa / ex, grad_x, (~reuse).nonzero()[:, 0])
        f_aa = torch.where(P.rows(reuse, xid).bool(), st.f_aa, f_aa)
        g_bb, T_bb = last(y, yo, y, yo, P.b_log + st.g_bb / ey, grad_y)
        value = segment_reduce(a * (f_ba - f_aa), xid, K, "sum") + segment_reduce(b * (g_ab - g_bb), yid, K, "sum")
        gx = a[:, None] * (T_aa - T_ab) if grad_x else None
        gy = b[:, None] * (T_bb - T_ba) if grad_y else None
    else:
        f_aa, g_bb = st.f_aa, st.g_bb
        value = segment_reduce(a * f_ba, xid, K, "sum") + segment_reduce(b * g_ab, yid, K, "sum")
        gx = a[:, None] * (x - T_ab) if grad_x else None
        gy = b[:, None] * (y - T_ba) if grad_y else None
    return value, gx, gy, _Duals(f_ba, g_ab, f_aa, g_bb)


@torch.no_grad()
def sinkhorn_batched(x: torch.Tensor, y: torch.Tensor, x_off: torch.Tensor | None, y_off: torch.Tensor | None,
                     cfg: SinkhornConfig = SinkhornConfig(), a: torch.Tensor | None = None,
                     b: torch.Tensor | None = None, blur: torch.Tensor | None = None, diameter=None,
                     init: Potentials | None = None, grad_x: bool = False, grad_y: bool = True,
                     x_fixed: bool = False) -> Result:
    """K independent problems S_eps(x_k, y_k) in one solve (the clusters of eq. 9), packed without padding.

    x: [R, D] rows of every problem, problem k at ``x_off[k]:x_off[k+1]`` (CSR offsets [K+1]; None:
    one problem); y: [C, D] likewise with ``y_off``; a [R], b [C]: weights summing to 1 within each
    problem (uniform if None); blur: [K] per-problem gamma (``cfg.blur`` if None); diameter: [K] or None.
    Each problem follows exactly the steps :func:`sinkhorn` takes on it alone (its own eps schedule,
    warm start, convergence test and iteration count); every soft-min of a step is one kernel call
    over the problems still iterating. Returns values [K], packed gradients, packed potentials.

    The solve: warm start (:func:`_warm_start`), each problem's schedule (:func:`_schedules`), the
    initialization of the cold ones at their largest eps, the schedule's steps, the convergence loop
    at the final eps (:func:`_converge`, ``tol`` > 0), and the last extrapolation (:func:`_extrapolate`).
    """
    x_off, y_off, n, m, blur_k = _check_packed(x, y, x_off, y_off, cfg, blur)
    backend = pick_backend(cfg, x)
    if backend == "geomloss":
        return _batched_geomloss(x, y, x_off, y_off, cfg, a, b, blur_k, diameter, grad_x, grad_y)
    dev = x.device
    K = len(x_off) - 1
    xid, yid = segment_ids(x_off), segment_ids(y_off)
    a = (1.0 / n.to(x))[xid].to(dev) if a is None else a.to(x)
    b = (1.0 / m.to(y))[yid].to(dev) if b is None else b.to(y)
    P = _Packed(x, y, x_off, y_off, a.log(), b.log(), softmin_native if backend == "native" else softmin_torch,
                cfg.debias)
    eps_final = blur_k.square()  # [K] float64, on the CPU (schedules are host-side)
    st, warm, reuse = _warm_start(P, init, eps_final, x_fixed, grad_x)
    scheds, n_avg = _schedules(P, warm, eps_final, blur_k, diameter, cfg)
    iters = torch.zeros(K, dtype=torch.long)
    cold = ~warm
    if cold.any():
        eps0 = torch.tensor([s[0] if s else 1.0 for s in scheds], dtype=torch.float64)
        st = P.where(cold, P.initial(eps0, cold.nonzero()[:, 0]), st)
        iters += cold.long()
    for r in range(max((len(s) for s in scheds), default=0)):
        act = torch.tensor([r < len(s) for s in scheds])
        eps_r = torch.tensor([s[r] if r < len(s) else 1.0 for s in scheds], dtype=torch.float64)
        st = P.update(eps_r, st, act, torch.tensor([r < na for na in n_avg]), reuse)
        iters += act.long()
    converged = torch.zeros(K, dtype=torch.bool)
    if cfg.tol > 0:
        st, converged = _converge(P, st, eps_final, reuse, cfg, iters)
    value, gx, gy, st = _extrapolate(P, st, eps_final, reuse, a, b, grad_x, grad_y)
    iters += 1
    pot = Potentials(st.f_ba, st.g_ab, st.f_aa, st.g_bb, eps_final, iters, converged, x_off, y_off)
    bad = ~torch.isfinite(value)
    if bad.any():
        k = int(bad.nonzero()[0])
        raise FloatingPointError(f"sinkhorn: non-finite divergence (problem {k}: N={int(n[k])}, M={int(m[k])}, "
                                 f"eps={float(eps_final[k]):g}, backend={backend})")
    return Result(value, gx, gy, pot, {"iterations": iters, "backend": backend, "converged": converged,
                                       "reused_f_aa": reuse})


@torch.no_grad()
def grad_y_at(q: torch.Tensor, q_off: torch.Tensor, x: torch.Tensor, y: torch.Tensor, res: Result,
              cfg: SinkhornConfig = SinkhornConfig(), a: torch.Tensor | None = None,
              b: torch.Tensor | None = None) -> torch.Tensor:
    """The gradient field of a solved :func:`sinkhorn_batched` (x fixed, y moving) at any points q [Q, D]
    (problem k's at ``q_off[k]:q_off[k+1]``), per unit mass: ``T_bb(q) - T_ba(q)`` (debiased; ``q - T_ba(q)``
    without), where ``T_ba(q) = sum_i a_i exp((f_ba_i - |q - x_i|^2 / 2) / eps) x_i / Z`` is the barycentre
    of x under the potential f_ba extended to q (geomloss' extrapolation) and ``T_bb`` that of y under
    g_bb. At q = y it is ``res.grad_y / b``. x, y, a, b as the solve had them."""
    pot = res.potentials
    backend = res.info.get("backend", "torch")
    if backend == "geomloss":
        raise ValueError("grad_y_at: the geomloss backend keeps no potentials")
    soft = softmin_native if backend == "native" else softmin_torch
    x_off, y_off = pot.x_off.cpu(), pot.y_off.cpu()
    n, m = x_off.diff(), y_off.diff()
    a = (1.0 / n.to(x))[segment_ids(x_off).to(x.device)] if a is None else a.to(x)
    b = (1.0 / m.to(y))[segment_ids(y_off).to(y.device)] if b is None else b.to(y)
    eps = pot.eps.to(x.dtype)
    ex, ey = eps.to(x.device)[segment_ids(x_off).to(x.device)], eps.to(y.device)[segment_ids(y_off).to(y.device)]
    q_off = q_off.cpu()
    _, t_ba = soft(eps, q, x, a.log() + pot.f_ba / ex, bary=True, x_off=q_off, y_off=x_off)
    if not cfg.debias:
        return q - t_ba
    _, t_bb = soft(eps, q, y, b.log() + pot.g_bb / ey, bary=True, x_off=q_off, y_off=y_off)
    return t_bb - t_ba


def _batched_geomloss(x, y, x_off, y_off, cfg, a, b, blur_k, diameter, grad_x, grad_y) -> Result:
    """geomloss has no ragged batch: one call per problem (the paper's way), packed like the others."""
    vals, gxs, gys = [], [], []
    for k in range(len(x_off) - 1):
        xs, ys = slice(int(x_off[k]), int(x_off[k + 1])), slice(int(y_off[k]), int(y_off[k + 1]))
        ck = cfg if float(blur_k[k]) == cfg.blur else replace(cfg, blur=float(blur_k[k]))
        r = _sinkhorn_geomloss(x[xs], y[ys], ck, None if a is None else a[xs], None if b is None else b[ys],
                               None if diameter is None else float(diameter[k]), grad_x, grad_y)
        vals.append(r.value.reshape(1))
        gxs.append(r.grad_x)
        gys.append(r.grad_y)
    dummy = x.new_zeros(0)
    K = len(vals)
    pot = Potentials(dummy, dummy, dummy, dummy, blur_k.square(), torch.zeros(K, dtype=torch.long),
                     torch.zeros(K, dtype=torch.bool))
    return Result(torch.cat(vals), torch.cat(gxs) if grad_x else None, torch.cat(gys) if grad_y else None, pot,
                  {"backend": "geomloss"})


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
    pot = Potentials(dummy, dummy, dummy, dummy, torch.tensor([cfg.blur**2], dtype=torch.float64),
                     torch.zeros(1, dtype=torch.long), torch.zeros(1, dtype=torch.bool))
    return Result(v.detach(), gx, gy, pot, {"backend": "geomloss"})


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

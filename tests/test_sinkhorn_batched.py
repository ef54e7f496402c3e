"""The packed (ragged) Sinkhorn solve over many clusters against the per-pair path, problem by problem."""

import pytest
import torch

from wast3d.sinkhorn import SinkhornConfig, segment_ids, sinkhorn, sinkhorn_batched, softmin_native, softmin_torch

D64 = torch.float64


def problems(sizes, d=4, seed=0, dtype=D64):
    """Clusters of very different sizes and extents (one a single point, one far and large)."""
    g = torch.Generator().manual_seed(seed)
    xs, ys = [], []
    for k, (n, m) in enumerate(sizes):
        ext = 1.0 + 2.0 * k
        xs.append(torch.rand(n, d, generator=g, dtype=dtype) * ext + 3.0 * k)
        ys.append(torch.rand(m, d, generator=g, dtype=dtype) * ext * 0.8 + 3.0 * k + 0.2)
    return xs, ys


def pack(ts):
    n = torch.tensor([len(t) for t in ts])
    return torch.cat(ts), torch.cat([n.new_zeros(1), n.cumsum(0)])


SIZES = [(40, 55), (1, 30), (25, 1), (70, 60), (8, 9)]


def per_pair(xs, ys, cfg, blurs, inits=None, **kw):
    from dataclasses import replace

    return [sinkhorn(x, y, replace(cfg, blur=bl), init=None if inits is None else inits[k], **kw)
            for k, (x, y, bl) in enumerate(zip(xs, ys, blurs))]


def split(t, off):
    return [t[int(off[k]):int(off[k + 1])] for k in range(len(off) - 1)]


@pytest.mark.parametrize("backend", ["native", "torch"])
@pytest.mark.parametrize("debias", [True, False])
def test_cold_solve_equals_the_per_pair_path(backend, debias):
    """Each problem takes its own schedule (own diameter and blur), its own convergence test: values,
    both gradients, iteration counts and convergence flags are those of one sinkhorn() per pair."""
    xs, ys = problems(SIZES)
    blurs = [0.05, 0.3, 0.1, 0.02, 0.5]
    cfg = SinkhornConfig(scaling=0.5, tol=1e-4, max_iters=60, debias=debias, backend=backend)
    x, xo = pack(xs)
    y, yo = pack(ys)
    r = sinkhorn_batched(x, y, xo, yo, cfg, blur=torch.tensor(blurs, dtype=D64), grad_x=True)
    ref = per_pair(xs, ys, cfg, blurs, grad_x=True)
    assert r.value.shape == (len(SIZES),)
    for k, rk in enumerate(ref):
        assert float(r.value[k]) == pytest.approx(float(rk.value), rel=1e-10, abs=1e-14), k
        assert torch.allclose(split(r.grad_y, yo)[k], rk.grad_y, rtol=1e-9, atol=1e-13), k
        assert torch.allclose(split(r.grad_x, xo)[k], rk.grad_x, rtol=1e-9, atol=1e-13), k
        assert int(r.info["iterations"][k]) == rk.info["iterations"], k
        assert bool(r.info["converged"][k]) == rk.info["converged"], k
    # the schedules differ per problem: the smallest blur needs the most iterations
    its = r.info["iterations"]
    assert int(its[3]) > int(its[4])


@pytest.mark.parametrize("dtype", [torch.float32, D64])
def test_warm_started_steps_equal_the_per_pair_path(dtype):
    """The optimization's use: a cold first step, then warm starts with the content fixed (its f_aa
    reused once converged), one problem unconverged (capped) so that it alone keeps iterating."""
    xs, ys = problems(SIZES, dtype=dtype)
    blurs = [0.1, 0.3, 0.2, 0.05, 0.4]
    cfg = SinkhornConfig(tol=1e-3, max_iters=25, backend="native")
    x, xo = pack(xs)
    y, yo = pack(ys)
    rb = sinkhorn_batched(x, y, xo, yo, cfg, blur=torch.tensor(blurs, dtype=D64), x_fixed=True)
    rp = per_pair(xs, ys, cfg, blurs, x_fixed=True)
    tol = dict(rel=1e-5, abs=1e-7) if dtype == torch.float32 else dict(rel=1e-10, abs=1e-14)
    for step in range(3):
        ys = [yk - 0.02 * split(rb.grad_y, yo)[k] * len(yk) for k, yk in enumerate(ys)]
        y = torch.cat(ys)
        rb = sinkhorn_batched(x, y, xo, yo, cfg, blur=torch.tensor(blurs, dtype=D64), init=rb.potentials,
                              x_fixed=True)
        rp = per_pair(xs, ys, cfg, blurs, inits=[p.potentials for p in rp], x_fixed=True)
        for k, rk in enumerate(rp):
            assert float(rb.value[k]) == pytest.approx(float(rk.value), **tol), (step, k)
            assert torch.allclose(split(rb.grad_y, yo)[k], rk.grad_y, rtol=tol["rel"] * 10, atol=tol["abs"]), (step, k)
            assert int(rb.info["iterations"][k]) == rk.info["iterations"], (step, k)
            assert bool(rb.info["reused_f_aa"][k]) == rk.info["reused_f_aa"], (step, k)
    assert rb.info["reused_f_aa"].any()  # the warm path was exercised
    assert not rb.info["converged"].all() or cfg.max_iters > 100  # the cap made one problem iterate longest


def test_torch_backend_batches_in_padded_groups():
    """The CUDA path (torch): problems padded to a common size in groups under a memory budget; padded
    columns must not leak into any row. Same potentials as the native ragged kernel."""
    xs, ys = problems(SIZES)
    x, xo = pack(xs)
    y, yo = pack(ys)
    h = torch.randn(len(y), dtype=D64, generator=torch.Generator().manual_seed(3))
    eps = torch.tensor([0.01, 0.1, 0.05, 0.3, 0.02], dtype=D64)
    act = torch.tensor([0, 1, 3, 4])
    f_n, b_n = softmin_native(eps, x, y, h, bary=True, x_off=xo, y_off=yo, active=act)
    for budget in (1, 5000, 10**9):  # one problem per group, a few per group, all in one
        f_t, b_t = softmin_torch(eps, x, y, h, bary=True, x_off=xo, y_off=yo, active=act, budget=budget)
        assert torch.allclose(f_t, f_n, rtol=1e-12, atol=1e-12), budget
        assert torch.allclose(b_t, b_n, rtol=1e-10, atol=1e-12), budget
    rows2 = segment_ids(xo) == 2  # inactive problem: untouched (0)
    assert (f_n[rows2] == 0).all() and (b_n[rows2] == 0).all()


def test_one_problem_is_the_plain_softmin():
    xs, ys = problems([(300, 200)], d=3)
    h = torch.randn(200, dtype=D64, generator=torch.Generator().manual_seed(1))
    f1 = softmin_native(0.05, xs[0], ys[0], h)
    f2 = softmin_native(torch.tensor([0.05], dtype=D64), xs[0], ys[0], h, x_off=torch.tensor([0, 300]), y_off=torch.tensor([0, 200]))
    ref = -0.05 * torch.logsumexp(h[None] - torch.cdist(xs[0], ys[0]).square() / 0.1, 1)
    assert torch.equal(f1, f2)
    assert torch.allclose(f1, ref, rtol=1e-12, atol=1e-12)


def test_float32_kernel_at_lane_and_block_edges():
    """The float32 soft-min runs its exp-and-sum 8 lanes at a time over blocks of 256 columns: column
    counts around both edges (a lane's tail masked to zero, blocks not filled), packed at unaligned
    offsets, against the float64 torch soft-min. A lane past a problem's end that counted would add
    exp(-80)-sized terms, or the next problem's columns, and show here as a value or barycentre error."""
    cols = [1, 7, 8, 9, 255, 256, 257, 513]
    xs, ys = problems([(13, m) for m in cols], d=4)
    x, xo = pack(xs)
    y, yo = pack(ys)
    h = torch.randn(len(y), dtype=D64, generator=torch.Generator().manual_seed(5))
    eps = torch.linspace(0.02, 0.5, len(cols), dtype=D64)
    f_ref, b_ref = softmin_torch(eps, x, y, h, bary=True, x_off=xo, y_off=yo)
    f32, b32 = softmin_native(eps.float(), x.float(), y.float(), h.float(), bary=True, x_off=xo, y_off=yo)
    assert float((f32.double() - f_ref).abs().max()) < 2e-5
    assert float((b32.double() - b_ref).abs().max()) < 2e-5 * float(y.abs().max())


def test_bad_batches_are_named():
    xs, ys = problems([(5, 6), (4, 7)])
    x, xo = pack(xs)
    y, yo = pack(ys)
    with pytest.raises(ValueError, match="problem 1: N=0"):
        sinkhorn_batched(x[:5], y, torch.tensor([0, 5, 5]), yo)
    with pytest.raises(ValueError, match="x_off must be CSR offsets"):
        sinkhorn_batched(x, y, torch.tensor([0, 6, 5]), yo)
    with pytest.raises(ValueError, match="x_off has 2 problems, y_off 1"):
        sinkhorn_batched(x, y, xo, torch.tensor([0, len(y)]))
    with pytest.raises(ValueError, match="blur must be positive"):
        sinkhorn_batched(x, y, xo, yo, blur=torch.tensor([0.1, 0.0]))


@pytest.mark.parametrize("opt", [dict(optimizer="flow", lr=0.2), dict(optimizer="adam", lr=0.01),
                                 dict(loss="arap", optimizer="adam", lr=0.01, iterations=4)])
def test_stylize_clusters_together_equals_one_at_a_time(opt):
    """Eq. 9's terms optimized in one packed solve per step = each cluster by itself (stylize_cluster)."""
    from dataclasses import replace

    from wast3d.stylize import ClusterPair, StylizeConfig, stylize_cluster, stylize_clusters

    g = torch.Generator().manual_seed(5)
    sizes = [(60, 80), (30, 20), (1, 12), (45, 45)]
    pairs = [ClusterPair(torch.rand(n, 3, generator=g) + k, torch.rand(n, 3, generator=g),
                         torch.rand(m, 3, generator=g) * 1.2 + k, torch.rand(m, 3, generator=g), bl)
             for k, ((n, m), bl) in enumerate(zip(sizes, [0.3, 0.2, 0.5, 0.1]))]
    cfg = StylizeConfig(dtype="float64", iterations=opt.pop("iterations", 6), **opt)
    together = stylize_clusters(pairs, cfg)
    for k, pr in enumerate(pairs):
        alone = stylize_cluster(pr.x_pos, pr.x_rgb, pr.y_pos, pr.y_rgb,
                                replace(cfg, sinkhorn=replace(cfg.sinkhorn, blur=pr.blur)))
        assert torch.allclose(together[k].positions, alone.positions, rtol=1e-5, atol=1e-6), k
        assert torch.allclose(together[k].colour_offset, alone.colour_offset, rtol=1e-5, atol=1e-6), k
        assert together[k].losses == pytest.approx(alone.losses, rel=1e-6, abs=1e-9), k
        assert not torch.allclose(together[k].positions, pr.y_pos)  # it moved


@pytest.mark.parametrize("opt", [dict(optimizer="flow", lr=0.2), dict(loss="arap", optimizer="flow", lr=0.05)])
def test_flow_steps_equal_torch_sgd(opt, monkeypatch):
    """The flow's plain descent (stylize._Descent) gives torch.optim.SGD's results to the last bit."""
    import wast3d.stylize as stylize

    g = torch.Generator().manual_seed(7)
    pairs = [stylize.ClusterPair(torch.rand(n, 3, generator=g) + k, torch.rand(n, 3, generator=g),
                                 torch.rand(m, 3, generator=g) * 1.2 + k, torch.rand(m, 3, generator=g), 0.3)
             for k, (n, m) in enumerate([(50, 70), (20, 25)])]
    cfg = stylize.StylizeConfig(iterations=5, **opt)
    ours = stylize.stylize_clusters(pairs, cfg)
    monkeypatch.setattr(stylize, "_Descent", torch.optim.SGD)
    sgd = stylize.stylize_clusters(pairs, cfg)
    for a, b, pr in zip(ours, sgd, pairs):
        assert torch.equal(a.positions, b.positions) and torch.equal(a.colour_offset, b.colour_offset)
        assert a.losses == b.losses
        assert (a.positions - pr.y_pos).abs().max() > 1e-3  # it moved

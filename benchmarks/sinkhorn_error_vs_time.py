"""Error against run time of the Sinkhorn divergence (value + gradient of one cluster pair).

    python benchmarks/sinkhorn_error_vs_time.py [--sizes 256 512 1024 2048 4096 8192] [--quick]

For each cluster size N (content N vs style N points, 4-D features: normalized xyz + luminance, a
realistic pair from :func:`benchmarks.common.cluster_pair`) and each solver setting, the wall time of
value + gradient w.r.t. the style points, and

- ``value_err``: |S - S_ref| / |S_ref| against a reference (our solver, float64 up to --ref64-max
  points and float32 above, scaling 0.9 and 200 iterations at the final eps; the change over its last
  100 iterations is reported as ``ref_convergence``);
- ``grad_err``: |g - g_ref| / |g_ref| (Frobenius);
- ``w2_err``: |S - W2^2/2| / (W2^2/2) against exact OT from POT's ``ot.emd2`` (N <= --emd-max), i.e.
  the entropic bias plus the solver error: it says what blur costs, not how good the solver is;
- ``peak_mb``: resident memory above the process's level at the start of the call.

Settings: geomloss tensorized (the paper's library; scaling 0.5 / 0.9), geomloss online (KeOps,
when pykeops builds), ours native (fused C kernel; scaling 0.5 with 0 / 10 / 30 extra iterations,
scaling 0.9; float32 and float64), ours torch backend, and ours warm-started (the potentials of a
solve at style points moved by 1 % of the radius, then ``warm_iters`` iterations: what each step of
the optimization does after the first). Writes ``results/benchmarks/sinkhorn_error_vs_time.csv`` and
``.png``; the last columns give times relative to geomloss tensorized at scaling 0.5 in the same run.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import OUT, Peak, cluster_pair  # noqa: E402


def settings(keops: bool):
    from wast3d.sinkhorn import SinkhornConfig as C

    s = [
        ("geomloss tensorized s=0.5", "geomloss", C(scaling=0.5, backend="geomloss"), torch.float32, None),
        ("geomloss tensorized s=0.9", "geomloss", C(scaling=0.9, backend="geomloss"), torch.float32, None),
        ("ours native s=0.5", "ours", C(scaling=0.5, backend="native"), torch.float32, None),
        ("ours native s=0.5 +10", "ours", C(scaling=0.5, extra_iters=10, backend="native"), torch.float32, None),
        ("ours native s=0.5 +30", "ours", C(scaling=0.5, extra_iters=30, backend="native"), torch.float32, None),
        ("ours native s=0.9", "ours", C(scaling=0.9, backend="native"), torch.float32, None),
        ("ours native s=0.5 +30 f64", "ours", C(scaling=0.5, extra_iters=30, backend="native"), torch.float64, None),
        ("ours torch s=0.5 +10", "ours", C(scaling=0.5, extra_iters=10, backend="torch"), torch.float32, None),
        ("ours native warm 3", "warm", C(scaling=0.5, extra_iters=10, warm_iters=3, backend="native"), torch.float32, None),
        ("ours native warm 10", "warm", C(scaling=0.5, extra_iters=10, warm_iters=10, backend="native"), torch.float32, None),
    ]
    if keops:
        s.append(("geomloss online(keops) s=0.5", "keops", C(scaling=0.5), torch.float32, None))
    return s


def geomloss_online(x, y, cfg):
    from geomloss import SamplesLoss

    from wast3d.sinkhorn import diameter_of

    L = SamplesLoss("sinkhorn", p=2, blur=cfg.blur, scaling=cfg.scaling, debias=True, backend="online",
                    diameter=max(diameter_of(x, y), cfg.blur))
    yy = y.clone().requires_grad_(True)
    v = L(x, yy)
    (g,) = torch.autograd.grad(v, yy)
    return v.detach(), g


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[256, 512, 1024, 2048, 4096, 8192])
    ap.add_argument("--blur", type=float, default=0.05)
    ap.add_argument("--emd-max", type=int, default=4096)
    ap.add_argument("--ref64-max", type=int, default=4096)
    ap.add_argument("--keops", action="store_true", help="include geomloss' online backend (pykeops)")
    ap.add_argument("--quick", action="store_true", help="sizes 256 512 1024 only")
    ap.add_argument("--out", type=Path, default=OUT / "sinkhorn_error_vs_time.csv")
    a = ap.parse_args()
    torch.set_flush_denormal(True)
    import pandas as pd

    from wast3d.sinkhorn import SinkhornConfig, exact_w2, sinkhorn

    sizes = [256, 512, 1024] if a.quick else a.sizes
    rows = []
    for n in sizes:
        x64, y64 = cluster_pair(n, dtype=torch.float64)
        # reference: float64 (float32 above --ref64-max, where float64 takes many minutes), scaling 0.9
        # + 100 iterations, then 100 more warm-started; ref_convergence is the change of the value
        rdt = torch.float64 if n <= a.ref64_max else torch.float32
        rcfg = SinkhornConfig(blur=a.blur, scaling=0.9, extra_iters=100, warm_iters=100)
        ref1 = sinkhorn(x64.to(rdt), y64.to(rdt), rcfg)
        ref = sinkhorn(x64.to(rdt), y64.to(rdt), rcfg, init=ref1.potentials)
        conv = abs(float(ref.value - ref1.value)) / abs(float(ref.value))
        ref.value, ref.grad_y = ref.value.double(), ref.grad_y.double()
        w2 = exact_w2(x64[:, :], y64) if n <= a.emd_max else float("nan")
        # a nearby problem for warm starts: style points moved by 1 % of the radius along -gradient
        step = 0.01 * ref.grad_y / ref.grad_y.norm(dim=1, keepdim=True).clamp_min(1e-30)
        y_prev = y64 + step
        for name, kind, cfg, dt, _ in settings(a.keops):
            cfg.blur = a.blur
            x, y = x64.to(dt), y64.to(dt)
            if kind == "warm":
                init = sinkhorn(x, y_prev.to(dt), cfg).potentials
            if n >= 8192 and "tensorized" in name and cfg.scaling > 0.5:
                continue  # 2+ GiB and minutes: covered by s=0.5
            try:
                with Peak() as p:
                    if kind == "keops":
                        v, g = geomloss_online(x, y, cfg)
                    else:
                        r = sinkhorn(x, y, cfg, init=init if kind == "warm" else None)
                        v, g = r.value, r.grad_y
            except Exception as e:  # keops build failures etc.: reported, not fatal
                print(f"{name} N={n}: failed ({e})", file=sys.stderr)
                continue
            row = {"n": n, "setting": name, "dtype": str(dt).replace("torch.", ""), "seconds": p.seconds,
                   "peak_mb": p.mb, "value": float(v), "value_ref": float(ref.value),
                   "value_err": abs(float(v) - float(ref.value)) / abs(float(ref.value)),
                   "grad_err": float((g.double() - ref.grad_y).norm() / ref.grad_y.norm()),
                   "w2_half": w2, "w2_err": abs(float(v) - w2) / w2 if w2 == w2 else float("nan"),
                   "ref_convergence": conv, "ref_dtype": str(rdt).replace("torch.", "")}
            rows.append(row)
            print(f"N={n:5d} {name:32s} {p.seconds:8.3f}s {p.mb:8.1f}MB value_err={row['value_err']:.2e} "
                  f"grad_err={row['grad_err']:.2e} w2_err={row['w2_err']:.2e}", flush=True)
    df = pd.DataFrame(rows)
    base = df[df.setting == "geomloss tensorized s=0.5"].set_index("n")["seconds"]
    df["time_vs_geomloss_s05"] = df.apply(lambda r: r.seconds / base.get(r.n, float("nan")), axis=1)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    df.to_csv(a.out, index=False)
    plot(df, a.out.with_suffix(".png"))
    print(f"wrote {a.out}")


def plot(df, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ns = sorted(int(n) for n in df.n.unique())
    fig, axes = plt.subplots(1, 2, figsize=(13, 5))
    for setting, g in df.groupby("setting"):
        marker = "o" if "ours" in setting else "s"
        for ax, col in zip(axes, ("value_err", "grad_err")):
            ax.plot(g.seconds, g[col].clip(lower=1e-9), marker=marker, label=setting, alpha=0.8)
    for ax, col in zip(axes, ("value error", "gradient error")):
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("seconds (value + gradient, one pair)")
        ax.set_ylabel(f"relative {col} vs float64 reference")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].set_title(f"error against run time, N in {ns} (each line: growing N)")
    axes[1].legend(fontsize=7, loc="lower left")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()

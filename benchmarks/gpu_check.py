"""The CUDA paths against the CPU ones, and paper-scale timings on the GPU (``scripts/gpu_check.sh``).

    python benchmarks/gpu_check.py [--out results/benchmarks/gpu_check.csv] [--quick] [--device cuda]

Each check runs the same computation on the CPU and on ``--device`` (CUDA; ``cpu`` stands in for it in
the test suite) and records the largest disagreement and both times:

- ``raster``: one 512 px view of a procedural style (30k Gaussians): the CPU's native kernel against
  gsplat on CUDA (the PyTorch rasterizer where gsplat is not installed), forward (RGB, alpha, depth) and
  backward (the gradients of a fixed weighting of the image with respect to means, scales, opacities
  and colours, as relative norms of the difference);
- ``sinkhorn``: the debiased divergence and its gradient on realistic cluster pairs of 1k to 16k points
  (stage 5's settings: gamma 0.3, eps-scaling 0.5, converged to 1e-3 eps);
- ``stylize``: stages 5-6 of the demo's ant x pebbles on one partition, on each device: the results'
  positions (largest difference in content spacings) and times;
- ``paper_scale``: stages 3-6 of a 300k-Gaussian content against a one-million-Gaussian style, 400
  clusters, 30 steps, on the GPU (stages 3-4 run on the CPU there too); its time per stage.

Without CUDA it says so and writes nothing (exit 0). Every row is written as it finishes, so a run cut
by its time limit keeps what it measured.
"""

from __future__ import annotations

import argparse
import sys
import time
import traceback
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import OUT, cluster_pair, write_rows  # noqa: E402


def timed(fn, device: torch.device, repeat: int = 3):
    """fn() once to warm up, then the median of ``repeat`` timed calls (synchronized on CUDA) -> (result, s)."""
    out = fn()
    times = []
    for _ in range(repeat):
        if device.type == "cuda":
            torch.cuda.synchronize()
        t = time.perf_counter()
        out = fn()
        if device.type == "cuda":
            torch.cuda.synchronize()
        times.append(time.perf_counter() - t)
    return out, sorted(times)[len(times) // 2]


def rel(a: torch.Tensor, b: torch.Tensor) -> float:
    """|a - b| / |b| (Frobenius norms), on the CPU in float64."""
    a, b = a.detach().double().cpu(), b.detach().double().cpu()
    return float((a - b).norm() / b.norm().clamp_min(1e-30))


def check_raster(device: torch.device, quick: bool) -> list[dict]:
    from wast3d.cameras import fit_orbit
    from wast3d.procedural import make_scene
    from wast3d.rasterizer import default_backend, rasterize

    scene = make_scene("style", "pebbles", 5000 if quick else 30000)
    cam = fit_orbit(scene, 3, 128 if quick else 512)[1]
    g = torch.Generator().manual_seed(0)
    w = torch.rand(cam.height, cam.width, 3, generator=g)
    rows = []
    out = {}
    for key, dev in (("cpu", torch.device("cpu")), ("device", device)):
        s = scene.to(device=dev).detach().clone()
        params = [s.means, s.log_scales, s.opacity_logits, s.sh_dc]
        for p in params:
            p.requires_grad_(True)
        backend = default_backend(dev)
        c = cam.to(device=dev)

        def forward_backward():
            for p in params:
                p.grad = None
            m = rasterize(s, c, background=(1.0, 1.0, 1.0), backend=backend)
            (m.rgb * w.to(dev)).sum().backward()
            return m

        m, secs = timed(forward_backward, dev)
        out[key] = (m, [p.grad.clone() for p in params], backend, secs)
    (mc, gc, bc, tc), (md, gd, bd, td) = out["cpu"], out["device"]
    rows.append({"check": "raster", "case": f"{len(scene)} Gaussians, {cam.width} px", "cpu_backend": bc,
                 "device_backend": bd, "cpu_s": tc, "device_s": td, "speedup": tc / td,
                 "rgb_max_abs": float((md.rgb.cpu() - mc.rgb).abs().max()),
                 "alpha_max_abs": float((md.alpha.cpu() - mc.alpha).abs().max()),
                 "depth_rel": rel(md.depth * (md.alpha > 0.5), mc.depth * (mc.alpha > 0.5)),
                 **{f"grad_{n}_rel": rel(a, b) for n, a, b in zip(("means", "log_scales", "opacities", "sh_dc"), gd, gc)}})
    return rows


def check_sinkhorn(device: torch.device, quick: bool) -> list[dict]:
    from wast3d.sinkhorn import sinkhorn
    from wast3d.stylize import StylizeSinkhornConfig

    cfg = StylizeSinkhornConfig()  # stage 5's solve: gamma 0.3 of the cluster radius, converged to 1e-3 eps
    rows = []
    for n in ((1000, 2000) if quick else (1000, 4000, 16000)):
        x, y = cluster_pair(n, seed=1)
        res = {}
        for key, dev in (("cpu", torch.device("cpu")), ("device", device)):
            res[key] = timed(lambda: sinkhorn(x.to(dev), y.to(dev), cfg), dev)
        (rc, tc), (rd, td) = res["cpu"], res["device"]
        rows.append({"check": "sinkhorn", "case": f"N = M = {n}, D = {x.shape[1]}", "cpu_backend": rc.info["backend"],
                     "device_backend": rd.info["backend"], "cpu_s": tc, "device_s": td, "speedup": tc / td,
                     "value_rel": abs(float(rd.value) - float(rc.value)) / max(abs(float(rc.value)), 1e-30),
                     "grad_rel": rel(rd.grad_y, rc.grad_y)})
    return rows


def check_stylize(device: torch.device, quick: bool) -> list[dict]:
    from wast3d.geometry import mean_spacing
    from wast3d.pair import partition, stylize_partition
    from wast3d.procedural import make_scene

    content = make_scene("content", "ant", 4000 if quick else 20000)
    style = make_scene("style", "pebbles", 6000 if quick else 30000)
    part = partition(content, style)
    h = mean_spacing(content.means)
    res = {}
    for key, dev in (("cpu", "cpu"), ("device", device.type)):
        t = time.perf_counter()
        out = stylize_partition(part, content, style, {"stylize": {"device": dev}})
        res[key] = (out.final, time.perf_counter() - t)
    (fc, tc), (fd, td) = res["cpu"], res["device"]
    return [{"check": "stylize", "case": f"ant {len(content)} x pebbles {len(style)}, "
                                         f"{int(part.clusters.labels.max()) + 1} clusters",
             "cpu_s": tc, "device_s": td, "speedup": tc / td,
             "positions_max_spacings": float((fd.means.cpu() - fc.means).norm(dim=1).max()) / h,
             "positions_median_spacings": float((fd.means.cpu() - fc.means).norm(dim=1).median()) / h}]


def check_paper_scale(device: torch.device, quick: bool) -> list[dict]:
    from wast3d.pair import partition, stylize_partition
    from wast3d.procedural import make_scene

    n, m, k = (20000, 60000, 40) if quick else (300_000, 1_000_000, 400)
    content, style = make_scene("content", "airplane", n), make_scene("style", "pebbles", m)
    part = partition(content, style, {"cluster": {"n_clusters": k}})
    out = stylize_partition(part, content, style, {"stylize": {"device": device.type}})
    return [{"check": "paper_scale", "case": f"airplane {len(content)} x pebbles {len(style)}, {k} clusters, 30 steps",
             "device_backend": device.type, **{f"{s}_s": v for s, v in {**part.seconds, **out.seconds}.items()},
             "device_s": out.seconds["stylize"], "gaussians_out": len(out.final),
             "peak_gpu_mb": torch.cuda.max_memory_allocated() / 2**20 if device.type == "cuda" else None}]


CHECKS = {"raster": check_raster, "sinkhorn": check_sinkhorn, "stylize": check_stylize, "paper_scale": check_paper_scale}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=OUT / "gpu_check.csv")
    ap.add_argument("--device", default="cuda", help="the device checked against the CPU (cpu: a dry run of the checks)")
    ap.add_argument("--checks", nargs="*", default=list(CHECKS), choices=list(CHECKS))
    ap.add_argument("--quick", action="store_true", help="small sizes (the test suite's)")
    a = ap.parse_args()
    if a.device == "cuda" and not torch.cuda.is_available():
        print("gpu_check: no CUDA device here (torch.cuda.is_available() is false): nothing to check; "
              "run it on a machine with a GPU")
        return 0
    device = torch.device(a.device)
    if device.type == "cuda":
        print(f"gpu_check: {torch.cuda.get_device_name(device)}, torch {torch.__version__}, CUDA {torch.version.cuda}",
              flush=True)
    rows = []
    for name in a.checks:
        t = time.perf_counter()
        try:
            rows += CHECKS[name](device, a.quick)
        except Exception as e:  # a check that fails is a result: its row says why, the others still run
            traceback.print_exc()
            rows.append({"check": name, "error": f"{type(e).__name__}: {e}"})
        print(f"gpu_check: {name} done in {time.perf_counter() - t:.1f} s", flush=True)
        write_rows(rows, a.out)
    df = write_rows(rows, a.out)
    print(df.to_string(index=False))
    print(f"wrote {a.out}")
    return 1 if "error" in df.columns and df["error"].notna().any() else 0


if __name__ == "__main__":
    sys.exit(main())

"""Rasterizer benchmark: forward and forward+backward time and peak memory at 200x200 on CPU.

    python benchmarks/render.py [--sizes 10000 50000 200000] [--backends native torch] [--repeats 5]
                                [--previous REV]

Scenes: N Gaussians on the surface of a procedural content mesh (a trained-object-like layout, scale
matched to the sample spacing), seen by an orbit camera that frames the object. Each (backend, N)
runs in a fresh subprocess so its peak resident memory (VmHWM, reset before the timed part) is its
own. Writes ``results/benchmarks/render.csv``; times are medians over ``--repeats`` after one warm-up.
``--previous REV`` adds the backend ``native@REV``: the whole rasterizer of git revision REV (its
``wast3d`` package, projection and binning included, and its native kernels built from its ``csrc``
into a cache of their own), timed in the same run, each worker importing its own version.
``--scene PLY`` times a given scene (e.g. a trained one: ``results/scenes/lego/scene.ply``, whose
anisotropic Gaussians the procedural mesh does not have) instead of the procedural mesh; ``--sizes``
then caps its Gaussian count (a random subset). Besides the whole rasterizer (projection, binning and
compositing), ``composite_*_s`` time the native compositing kernel alone (the part the C code does).
The ``*_vs_native`` columns give each time relative to the native backend's in the same run.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _rss(field: str) -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def previous_package(rev: str) -> str:
    """A temporary folder holding the ``wast3d`` package of git revision ``rev`` (removed at exit)."""
    import atexit
    import shutil
    import tempfile

    dst = tempfile.mkdtemp(prefix="wast3d-previous-")
    atexit.register(shutil.rmtree, dst, ignore_errors=True)
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", rev, "wast3d"], capture_output=True, check=True).stdout
    subprocess.run(["tar", "-x", "-C", dst], input=archive, check=True)
    return dst


def worker(backend: str, n: int, size: int, repeats: int, mesh: str, scene_ply: str | None = None) -> dict:
    import torch

    torch.set_flush_denormal(True)
    from wast3d.procedural import content_scene
    try:
        from wast3d.rasterizer import bin_tiles, composite_native, project, rasterize
    except ImportError:  # an older revision named the module rendering.py
        from wast3d.rendering import bin_tiles, composite_native, project, rasterize
    try:
        from wast3d.cameras import fit_orbit
    except ImportError:  # an older revision kept the camera rigs in render.py
        from wast3d.render import fit_orbit

    label = backend
    backend = backend.split("@", 1)[0]  # native@REV: this process imports REV's package (main sets PYTHONPATH)
    if scene_ply:
        from wast3d.ply import read_ply

        scene = read_ply(scene_ply)
        if len(scene) > n:
            scene = scene.subset(torch.randperm(len(scene), generator=torch.Generator().manual_seed(0))[:n])
    else:
        scene = content_scene(mesh, n, seed=0)
    cam = fit_orbit(scene, 3, size)[1]
    params = [t.requires_grad_(True) for t in scene.tensors().values()]
    rasterize(scene, cam, backend=backend).rgb.sum().backward()  # warm-up (builds kernels, caches)
    base = _rss("VmRSS")
    Path("/proc/self/clear_refs").write_text("5")  # reset the peak (VmHWM)
    fwd, fb = [], []
    for _ in range(repeats):
        for p in params:
            p.grad = None
        t0 = time.perf_counter()
        r = rasterize(scene, cam, backend=backend)
        t1 = time.perf_counter()
        (r.rgb.sum() + r.depth.sum()).backward()
        t2 = time.perf_counter()
        fwd.append(t1 - t0)
        fb.append(t2 - t0)
    peak = _rss("VmHWM")
    med = lambda xs: sorted(xs)[len(xs) // 2]  # noqa: E731
    cf, cb = [float("nan")], [float("nan")]
    if backend == "native":  # the compositing kernel alone, on the same projected Gaussians
        with torch.no_grad():
            p = project(scene.means, scene.quats, scene.scales, scene.opacities, cam)
            gid, off = bin_tiles(p, cam.width, cam.height)
        feats = torch.rand(len(p.ids), 4)
        cf, cb = [], []
        for _ in range(repeats):
            args = [t.detach().clone().requires_grad_(True) for t in (p.means2d, p.conics, feats, p.opacities)]
            t0 = time.perf_counter()
            out, T = composite_native(*args, gid, off, cam.width, cam.height, radii=p.radii)
            t1 = time.perf_counter()
            (out.sum() + T.sum()).backward()
            cf.append(t1 - t0)
            cb.append(time.perf_counter() - t1)
    import wast3d

    return {"backend": label, "package": str(Path(wast3d.__file__).parent), "gaussians": len(scene), "width": size, "height": size, "threads": torch.get_num_threads(),
            "visible": int(r.visible_ids.numel()), "forward_s": med(fwd), "forward_backward_s": med(fb),
            "composite_forward_s": med(cf), "composite_backward_s": med(cb),
            "peak_mb_above_baseline": peak - base, "peak_rss_mb": peak}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[10000, 50000, 200000])
    ap.add_argument("--backends", nargs="+", default=["native", "torch"])
    ap.add_argument("--resolution", type=int, default=200)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--mesh", default="sphere")
    ap.add_argument("--previous", help="also time the rasterizer of this git revision (backend native@REV)")
    ap.add_argument("--scene", help="a Gaussian PLY to time instead of the procedural mesh")
    ap.add_argument("--out", type=Path, default=ROOT / "results" / "benchmarks" / "render.csv")
    ap.add_argument("--_worker", nargs=2, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a._worker:
        print(json.dumps(worker(a._worker[0], int(a._worker[1]), a.resolution, a.repeats, a.mesh, a.scene)))
        return
    import pandas as pd

    rows = []
    backends = a.backends + ([f"native@{a.previous}"] if a.previous else [])
    env_previous = None
    if a.previous:
        import os

        env_previous = {**os.environ, "PYTHONPATH": previous_package(a.previous)}
    for n in a.sizes:
        for b in backends:
            cmd = [sys.executable, __file__, "--_worker", b, str(n), "--resolution", str(a.resolution),
                   "--repeats", str(a.repeats if b.startswith("native") else max(1, a.repeats // 2)), "--mesh", a.mesh]
            cmd += ["--scene", a.scene] if a.scene else []
            out = subprocess.run(cmd, capture_output=True, text=True, env=env_previous if "@" in b else None)
            if out.returncode:
                print(out.stderr, file=sys.stderr)
                continue
            rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
            print(rows[-1], flush=True)
    df = pd.DataFrame(rows)
    native = df[df.backend == "native"].set_index("gaussians")
    for col, name in (("forward_backward_s", "fb_time_vs_native"), ("composite_forward_s", "composite_fwd_vs_native"),
                      ("composite_backward_s", "composite_bwd_vs_native")):
        df[name] = df.apply(lambda r: r[col] / native[col].get(r.gaussians, float("nan")), axis=1)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    df.to_csv(a.out, index=False)
    print(df.to_string(index=False))


if __name__ == "__main__":
    main()

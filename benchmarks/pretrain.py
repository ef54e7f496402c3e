"""Pretraining benchmark: held-out PSNR against wall time, and the effect of the regularizers.

    python benchmarks/pretrain.py lego  [--iterations 3000] [--eval-every 500] [--previous REV]
    python benchmarks/pretrain.py regularizers [--style pebbles] [--iterations 1500]

``lego``: trains on ``../shared/data/nerf_synthetic_lego_200`` (every 8th view held out, white
background) and evaluates on the held-out views every ``--eval-every`` steps; the evaluation time is
not counted as training time. Rows: step, training seconds, Gaussians, held-out PSNR / SSIM.
``--previous REV`` first runs the same benchmark in a git worktree of revision REV (its own code and
kernels) and adds its rows (``version`` REV against ``current``), so the two compare in one run.
``regularizers``: renders a procedural style scene into 48 posed views (200x200), trains with and
without eq. 1 + eq. 2, and reports quantiles of anisotropy max(s)/min(s) and of the largest scale, and
the held-out PSNR of each. Writes ``results/benchmarks/pretrain.csv`` / ``pretrain_regularizers.csv``.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import OUT, ROOT, worktree  # noqa: E402

LEGO = ROOT.parent / "shared" / "data" / "nerf_synthetic_lego_200"


def previous_rows(a):
    """This benchmark's lego rows at git revision ``a.previous``, run in a temporary worktree."""
    import subprocess

    import pandas as pd

    with worktree(a.previous) as wt:
        subprocess.run([sys.executable, "benchmarks/pretrain.py", "lego", "--iterations", str(a.iterations),
                        "--eval-every", str(a.eval_every), "--sh-degree", str(a.sh_degree),
                        "--max-gaussians", str(a.max_gaussians)], cwd=wt, check=True,
                       env={**os.environ, "PYTHONPATH": str(wt)})
        prev = pd.read_csv(wt / "results" / "benchmarks" / "pretrain.csv")
    prev["version"] = a.previous  # its own run labelled itself "current"
    return prev


def lego(a) -> None:
    import pandas as pd

    from wast3d.datasets import load_blender
    from wast3d.pretrain import PretrainConfig, Trainer

    if not (LEGO / "transforms_train.json").exists():
        sys.exit(f"lego not found at {LEGO}")
    ds = load_blender(LEGO, holdout_every=8)
    cfg = PretrainConfig(iterations=a.iterations, eval_every=a.eval_every, sh_degree=a.sh_degree,
                         max_gaussians=a.max_gaussians)
    tr = Trainer(ds, cfg)
    tr.train(progress=True)
    ev = tr.evaluate()
    rows = [{"step": r["iteration"], "train_seconds": r["seconds"], "gaussians": r["gaussians"],
             "test_psnr": r["test_psnr"], "test_ssim": r["test_ssim"]} for r in tr.log_rows if "test_psnr" in r]
    if not rows or rows[-1]["step"] != ev["steps"]:
        rows.append({"step": ev["steps"], "train_seconds": ev["train_seconds"], "gaussians": ev["gaussians"],
                     "test_psnr": ev["psnr"], "test_ssim": ev["ssim"]})
    df = pd.DataFrame(rows)
    df["threads"] = torch.get_num_threads()
    df.insert(0, "version", "current")
    if a.previous:
        df = pd.concat([previous_rows(a), df], ignore_index=True)
    out = OUT / "pretrain.csv"
    out.parent.mkdir(parents=True, exist_ok=True)
    df.to_csv(out, index=False)
    print(df.to_string(index=False))


def regularizers(a) -> None:
    import pandas as pd

    from wast3d.datasets import load_blender
    from wast3d.gaussians import anisotropy
    from wast3d.pretrain import PretrainConfig, Trainer
    from wast3d.procedural import make_scene
    from wast3d.render import export_blender

    rows = []
    with tempfile.TemporaryDirectory() as td:
        export_blender(make_scene("style", a.style, 30000, seed=0), td, n_views=48, size=200)
        ds = load_blender(td, holdout_every=8)
        for reg in (False, True):
            cfg = PretrainConfig(iterations=a.iterations, regularize=reg, seed=0)
            tr = Trainer(ds, cfg)
            tr.train(progress=True)
            ev = tr.evaluate()
            s = tr.scene().scales
            an = anisotropy(s).double()
            mx = s.max(1).values.double()
            q = lambda t, p: float(torch.quantile(t, p))  # noqa: E731
            rows.append({"style": a.style, "regularized": reg, "psnr": ev["psnr"], "ssim": ev["ssim"],
                         "gaussians": ev["gaussians"], "train_seconds": ev["train_seconds"],
                         **{f"aniso_q{int(p * 100)}": q(an, p) for p in (0.5, 0.9, 0.99)},
                         "aniso_frac_above_3": float((an > 3).double().mean()),
                         **{f"scale_max_q{int(p * 100)}": q(mx, p) for p in (0.5, 0.9, 0.99)}})
            print(rows[-1], flush=True)
    df = pd.DataFrame(rows)
    out = OUT / "pretrain_regularizers.csv"
    out.parent.mkdir(parents=True, exist_ok=True)
    df.to_csv(out, index=False)
    print(df.to_string(index=False))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("what", choices=["lego", "regularizers"])
    ap.add_argument("--iterations", type=int, default=3000)
    ap.add_argument("--eval-every", type=int, default=500)
    ap.add_argument("--sh-degree", type=int, default=0)
    ap.add_argument("--max-gaussians", type=int, default=200_000)
    ap.add_argument("--style", default="pebbles")
    ap.add_argument("--previous", help="lego: also run this git revision's code (a worktree) in the same run")
    a = ap.parse_args()
    torch.set_flush_denormal(True)
    {"lego": lego, "regularizers": regularizers}[a.what](a)


if __name__ == "__main__":
    main()

"""Helpers shared by the benchmark scripts: peak-memory probes, timing, realistic cluster pairs, whole
pairs through the stage functions (:class:`Pairs`)."""

from __future__ import annotations

import time
from contextlib import contextmanager
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "results" / "benchmarks"


@contextmanager
def worktree(rev: str, prefix: str = "wast3d-prev-"):
    """A temporary git worktree of revision ``rev`` with ``../shared`` (the real data) beside it, as
    beside this checkout; yields its path and removes it after. Run its code with ``PYTHONPATH`` set
    to it (``python -m`` from its root imports it too)."""
    import subprocess
    import tempfile

    with tempfile.TemporaryDirectory(prefix=prefix) as td:
        wt = Path(td) / "tree"
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(wt), rev], check=True,
                       capture_output=True)
        try:
            (wt.parent / "shared").symlink_to(ROOT.parent / "shared")
            yield wt
        finally:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(wt)], capture_output=True)


def write_rows(rows: list[dict], out: Path):
    """The benchmark's rows as a DataFrame, written to ``out`` as CSV (a temporary file, renamed)."""
    import pandas as pd

    df = pd.DataFrame(rows)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(".tmp")
    df.to_csv(tmp, index=False)
    tmp.replace(out)
    return df


def rss_mb(field: str = "VmRSS") -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field):
            return int(line.split()[1]) / 1024.0
    return float("nan")


class Peak:
    """Peak resident memory above the level at entry (Linux: VmHWM reset through clear_refs)."""

    def __enter__(self):
        self.base = rss_mb()
        try:
            Path("/proc/self/clear_refs").write_text("5")
        except OSError:
            pass
        self.t0 = time.perf_counter()
        return self

    def __exit__(self, *exc):
        self.seconds = time.perf_counter() - self.t0
        self.mb = max(rss_mb("VmHWM") - self.base, 0.0)


def cluster_pair(n: int, m: int | None = None, seed: int = 0, dtype=torch.float32, features: str = "xyz+lum"):
    """A realistic normalized pair: a content cluster (points on a surface patch of a procedural
    content mesh) and the style Gaussians of a pebbles patch around a point, both as [., 4] features
    (normalized xyz + 0.5 luminance), as stage 5 sees them."""
    from wast3d.gaussians import luminance
    from wast3d.geometry import knn
    from wast3d.procedural import make_scene
    from wast3d.stylize import normalize_pair

    m = m or n
    content = make_scene("content", "sphere", max(4 * n, 4000), seed=seed)
    style = make_scene("style", "pebbles", max(4 * m, 8000), seed=seed)
    g = torch.Generator().manual_seed(seed)
    c0 = content.means[torch.randint(len(content), (1,), generator=g)]
    _, ci = knn(c0, content.means, n)
    s0 = style.means[torch.randint(len(style), (1,), generator=g)] * 0.5
    _, si = knn(s0, style.means, m)
    x, y = content.means[ci[0]].double(), style.means[si[0]].double()
    xr, yr = content.rgb[ci[0]].double(), style.rgb[si[0]].double()
    # bring the style patch to the content's place and size (what registration does)
    cx, rx = normalize_pair(x)
    cy, ry = normalize_pair(y)
    xn = (x - cx) / rx
    yn = (y - cy) / ry
    xf = torch.cat([xn, 0.5 * luminance(xr)[:, None]], 1).to(dtype)
    yf = torch.cat([yn, 0.5 * luminance(yr)[:, None]], 1).to(dtype)
    return xf.contiguous(), yf.contiguous()


# ---- whole pairs (metrics validation, style trade-off) ---------------------------------------

STYLE_KEYS = ("relief_w1", "texture_swd", "style_patch_chamfer", "style_patch_sinkhorn", "tilt_w1_deg", "aniso_w1",
              "colour_sinkhorn")


def demo_scene(name: str, seed: int = 0):
    """A demo scene by name: the procedural content meshes and styles at the demo's sizes, or 'lego'
    (the pretrained surface samples of the workflow, results/scenes/lego/surface.ply)."""
    from wast3d.ply import read_ply
    from wast3d.procedural import CONTENTS, make_scene

    if name == "lego":
        p = ROOT / "results" / "scenes" / "lego" / "surface.ply"
        if not p.exists():
            raise FileNotFoundError(f"{p}: run the workflow with config/lego.yaml first (pretraining + surface)")
        return read_ply(p)
    return make_scene("content", name, 20000, seed) if name in CONTENTS else make_scene("style", name, 30000, seed)


class Pairs:
    """Stages 3-6 on one (content, style) pair through the stage functions the workflow's rules call
    (:mod:`wast3d.pair`), each partition (stages 3-4) made once per distinct set of its blocks:
    ``run(params)`` -> (the result, seconds of selection + stylization + scale readjustment, the loss
    curves). ``params``: the config's blocks (``cluster``, ``register``, ``select``, ``stylize``,
    ``rescale``); a block left out takes the method's defaults."""

    def __init__(self, content, style):
        self.content, self.style, self.partitions = content, style, {}

    def run(self, params: dict):
        import json

        from wast3d.pair import partition, stylize_partition

        key = json.dumps({k: params.get(k) for k in ("cluster", "register", "select")}, sort_keys=True)
        if key not in self.partitions:
            self.partitions[key] = partition(self.content, self.style, params)
        part = self.partitions[key]
        out = stylize_partition(part, self.content, self.style, params)
        secs = part.seconds["select"] + out.seconds["stylize"] + out.seconds["rescale"]
        return out.final, secs, out.stylized.curves


def render_frames(scene, reference, folder: Path, frames: int = 24, size: int = 256):
    """Turntable frames [V, H, W, 4] of ``scene`` with cameras fitted to ``reference`` (written under
    ``folder`` as the workflow's render stage writes them, then read back: the same quantization)."""
    from wast3d.render import RenderConfig, read_frames, render_turntable

    if not (Path(folder) / "render.json").exists():
        render_turntable(scene, reference, folder, RenderConfig(frames=frames, size=size))
    return read_frames(folder)


def texture_reference_frames(style, content, folder: Path, frames: int = 24, size: int = 256):
    """The style's texture reference for results on ``content`` [V, H, W, 4] (as the workflow's
    ``texture_reference`` rule writes it, then read back)."""
    from wast3d.render import RenderConfig, read_frames, render_texture_reference

    if not (Path(folder) / "render.json").exists():
        render_texture_reference(style, content, folder, RenderConfig(frames=frames, size=size))
    return read_frames(folder)


def style_scores(result, result_frames, style, reference_frames, seed: int, fast: bool = False) -> dict:
    """Every style metric of a result at one metric seed (patches, windows and directions all drawn
    from it); ``reference_frames``: the style's texture reference. ``fast`` leaves out the slow
    patch-matching metrics."""
    from wast3d.metrics import MetricsConfig, relief_w1, style_metrics

    m = MetricsConfig(seed=seed)
    if fast:  # no patch matching (seconds per call), no colour Sinkhorn
        from wast3d.gaussians import anisotropy
        from wast3d.metrics import tilt_degrees, wasserstein_1d

        out = {"relief_w1": relief_w1(result.means, style.means, m),
               "tilt_w1_deg": wasserstein_1d(tilt_degrees(result, m.normal_k), tilt_degrees(style, m.normal_k)),
               "aniso_w1": wasserstein_1d(anisotropy(result.scales.double()).log10(),
                                          anisotropy(style.scales.double()).log10())}
    else:
        out = style_metrics(result, style, m)
    out["texture_swd"] = texture_score(result_frames, reference_frames, seed)
    return out


def texture_score(result_frames, reference_frames, seed: int) -> float:
    """texture_swd as the evaluate stage computes it (result frames vs the style's texture reference)."""
    from wast3d.image_metrics import TextureConfig, texture_swd

    return texture_swd(result_frames, reference_frames, TextureConfig(seed=seed))

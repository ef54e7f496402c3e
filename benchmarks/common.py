"""Helpers shared by the benchmark scripts: peak-memory probes, timing, realistic cluster pairs."""

from __future__ import annotations

import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "results" / "benchmarks"


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

"""The viewer against the renderer: ``wast3d view``'s page in headless Chromium (software WebGL) against
:func:`wast3d.rasterizer.rasterize` from the page's initial camera (:func:`wast3d.viewer.view_camera`).

    python benchmarks/viewer_vs_render.py SCENE.ply [SCENE.ply ...] [--browser chromium]

For each scene, two screenshots of the page: the first that shows splats (viser may still be fading
the scene in, drawing its Gaussians shrunken: it is, when the browser catches it early) and the
settled one (equal to the screenshot 2 s before).
Each is compared with the render over the pixels the render draws below the page's panels (the lower
half): mean colour of each and the mean absolute difference per pixel, in levels of 255. Writes
``results/benchmarks/viewer_vs_render.csv`` and, per scene, a PNG of page, settled page and render.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))


def main() -> None:
    import imageio.v3 as iio
    import pandas as pd

    from test_viewer import _free_port, _lower_half_drawn, _screenshot_when, _settled  # the browser test's
    from wast3d.formats import read_scene
    from wast3d.rasterizer import rasterize
    from wast3d.viewer import placed, serve, view_camera

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", type=Path, nargs="+")
    ap.add_argument("--browser", default=shutil.which("chromium") or shutil.which("chromium-browser"))
    ap.add_argument("--out", type=Path, default=ROOT / "results" / "benchmarks" / "viewer_vs_render.csv")
    a = ap.parse_args()
    if not a.browser:
        sys.exit("no chromium (apt-get install -y chromium)")
    a.out.parent.mkdir(parents=True, exist_ok=True)
    rows = []
    for path in a.scenes:
        port = _free_port()
        server = serve([path], port=port)
        try:
            drawn = _lower_half_drawn(0.02)
            first = _screenshot_when(f"http://127.0.0.1:{port}", a.browser, drawn, timeout=300)
            t0 = time.time()
            page = _screenshot_when(f"http://127.0.0.1:{port}", a.browser, _settled(drawn), timeout=600)
            seconds = time.time() - t0
        finally:
            server.stop()
        h, w = page.shape[:2]
        r = rasterize(placed(read_scene(path)), view_camera(w, h), background=(1.0, 1.0, 1.0), sh_degree=0)
        render = (r.rgb.clamp(0, 1) * 255).round().numpy()
        mask = r.alpha.numpy() > 0.5
        mask[: h // 2] = False
        for name, img in (("first splats", first), ("settled", page)):
            rows.append({"scene": path.name, "screenshot": name, "pixels": int(mask.sum()),
                         "render_mean": np.round(render[mask].mean(0), 1).tolist(),
                         "page_mean": np.round(img[mask].astype(float).mean(0), 1).tolist(),
                         "mean_abs_diff": float(np.abs(img[mask].astype(float) - render[mask]).mean()),
                         "settled_after_s": seconds if name == "settled" else None})
            print(rows[-1], flush=True)
        iio.imwrite(a.out.with_name(f"viewer_vs_render_{path.stem}.png"),
                    np.concatenate([first, page, render.astype(np.uint8)], 1))
    df = pd.DataFrame(rows)
    df.to_csv(a.out, index=False)
    print(df.to_string(index=False))


if __name__ == "__main__":
    main()

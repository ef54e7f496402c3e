"""The 3D viewer (``wast3d view``, viser): the arrays it sends, the placement, and a real headless
Chromium that opens the page and shows the splats."""

import asyncio
import base64
import json
import shutil
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import torch

from conftest import random_scene

ROOT = Path(__file__).resolve().parents[1]


def test_splat_arrays_and_placement():
    from wast3d.viewer import splat_arrays, unit_placement

    s = random_scene(500, sh_degree=1, seed=3)
    a = splat_arrays(s)
    assert a["centers"].shape == (500, 3) and a["covariances"].shape == (500, 3, 3)
    assert a["rgbs"].shape == (500, 3) and a["opacities"].shape == (500, 1)
    assert all(v.dtype == np.float32 for v in a.values())
    np.testing.assert_allclose(a["covariances"], s.covariances.numpy(), rtol=1e-5, atol=1e-9)
    np.testing.assert_allclose(a["opacities"][:, 0], s.opacities.numpy(), rtol=1e-6)
    top = splat_arrays(s, max_gaussians=100)
    assert len(top["centers"]) == 100 and top["opacities"].min() >= np.sort(a["opacities"][:, 0])[-100] - 1e-7
    scale, pos = unit_placement(s.transform(translation=torch.tensor([5.0, -3.0, 2.0]), scale=7.0))
    from wast3d.render import scene_bounds

    moved = s.transform(translation=torch.tensor([5.0, -3.0, 2.0]), scale=7.0)
    centre, radius = scene_bounds(moved)
    np.testing.assert_allclose(pos + scale * centre.double().numpy(), 0, atol=1e-6)
    assert abs(scale * radius - 1) < 1e-6


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _screenshot_when(url: str, browser: str, ready, timeout: float = 90.0) -> np.ndarray:
    """Open ``url`` in headless Chromium (software WebGL) and return the first screenshot [H, W, 3]
    for which ``ready(img)`` holds, polling every 2 s (DevTools protocol)."""
    import imageio.v3 as iio
    import websockets

    port = _free_port()
    proc = subprocess.Popen([browser, "--headless", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                             "--window-size=1000,600", f"--remote-debugging-port={port}", "about:blank"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        for _ in range(100):
            try:
                pages = json.load(urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list"))
                break
            except OSError:
                time.sleep(0.2)
        ws_url = next(p for p in pages if p["type"] == "page")["webSocketDebuggerUrl"]

        async def go():
            async with websockets.connect(ws_url, max_size=2 ** 26) as ws:
                ids = iter(range(1, 10 ** 6))

                async def call(method, **params):
                    i = next(ids)
                    await ws.send(json.dumps({"id": i, "method": method, "params": params}))
                    while True:
                        m = json.loads(await ws.recv())
                        if m.get("id") == i:
                            return m["result"]

                await call("Page.navigate", url=url)
                t0, img = time.time(), None
                while time.time() - t0 < timeout:
                    await asyncio.sleep(2.0)
                    png = base64.b64decode((await call("Page.captureScreenshot", format="png"))["data"])
                    img = iio.imread(png)[..., :3]
                    if ready(img):
                        break
                return img

        return asyncio.run(go())
    finally:
        proc.kill()


@pytest.mark.browser
def test_viewer_page_shows_the_splats_in_chromium(tmp_path):
    """``wast3d view`` on a red ball of Gaussians: a real headless Chromium opens the page, connects,
    and the screenshot shows red splats in the middle of the canvas (none before the scene is sent)."""
    pytest.importorskip("viser")
    browser = shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")
    if browser is None:
        pytest.skip("no chromium on this machine (apt-get install -y chromium)")
    from wast3d.gaussians import GaussianScene
    from wast3d.ply import write_ply

    g = torch.Generator().manual_seed(0)
    n = 4000
    pts = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    ball = GaussianScene.from_activated(pts, torch.full((n, 3), 0.05), torch.tensor([[1.0, 0, 0, 0]]).expand(n, 4),
                                        torch.full((n,), 0.9), torch.tensor([[0.9, 0.1, 0.1]]).expand(n, 3))
    write_ply(tmp_path / "ball.ply", ball)
    port = _free_port()
    server = subprocess.Popen([sys.executable, "-m", "wast3d", "view", str(tmp_path / "ball.ply"), "--port", str(port)],
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=ROOT)
    try:
        for _ in range(120):
            try:
                urllib.request.urlopen(f"http://127.0.0.1:{port}")
                break
            except OSError:
                assert server.poll() is None, server.stdout.read()
                time.sleep(0.5)

        def red_in_middle(img):
            h, w = img.shape[:2]
            mid = img[h // 4: 3 * h // 4, w // 4: 3 * w // 4].astype(int)
            red = (mid[..., 0] > 120) & (mid[..., 0] > mid[..., 1] + 60) & (mid[..., 0] > mid[..., 2] + 60)
            return red.mean() > 0.02

        img = _screenshot_when(f"http://127.0.0.1:{port}", browser, red_in_middle)
        import imageio.v3 as iio

        iio.imwrite(tmp_path / "viewer.png", img)
        assert red_in_middle(img), f"no red splats in the page's screenshot ({tmp_path / 'viewer.png'})"
    finally:
        server.terminate()
        server.wait(timeout=10)

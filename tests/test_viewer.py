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
    from wast3d.cameras import scene_bounds

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


def _lower_half_drawn(share: float):
    """A screenshot predicate: more than ``share`` of the page's lower half (below viser's panels) is
    not white."""
    return lambda img: (np.abs(img[img.shape[0] // 2:].astype(int) - 255).sum(-1) > 30).mean() > share


def _settled(drawn):
    """A screenshot predicate for :func:`_screenshot_when`: ``drawn(img)`` and the picture equal to the
    one polled before it (viser's fade-in over)."""
    last = {}

    def ready(img):
        same = "img" in last and last["img"].shape == img.shape and np.abs(last["img"].astype(int) - img).mean() < 0.2
        last["img"] = img
        return drawn(img) and same

    return ready


def _stripes() -> "GaussianScene":
    """A card of colour stripes running away from the viewer's camera (dark brown, near-black, grey,
    near-white, red, green, blue, and a translucent sparse stripe), so that every stripe reaches the
    lower half of the page, below viser's panels."""
    from wast3d.gaussians import GaussianScene

    g = torch.Generator().manual_seed(0)
    colours = [(0.35, 0.22, 0.12), (0.08, 0.08, 0.10), (0.5, 0.5, 0.5), (0.92, 0.9, 0.88),
               (0.8, 0.15, 0.1), (0.15, 0.6, 0.2), (0.2, 0.3, 0.8), (0.1, 0.1, 0.1)]
    means, rgb, opac = [], [], []
    for k, c in enumerate(colours):
        n = 300 if k == 7 else 2500
        xy = torch.rand(n, 2, generator=g) * torch.tensor([0.2, 1.6]) + torch.tensor([0.25 * k - 1.0, -0.8])
        means.append(torch.cat([xy, 0.01 * torch.rand(n, 1, generator=g)], 1))
        rgb.append(torch.tensor(c).expand(n, 3))
        opac.append(torch.full((n,), 0.3 if k == 7 else 0.9))
    n = sum(len(m) for m in means)
    return GaussianScene.from_activated(torch.cat(means), torch.full((n, 3), 0.025),
                                        torch.tensor([[1.0, 0, 0, 0]]).expand(n, 4), torch.cat(opac), torch.cat(rgb))


@pytest.mark.browser
def test_viewer_page_shows_what_the_renderer_shows(tmp_path):
    """``wast3d view`` in a real headless Chromium (software WebGL) against the project's rasterizer
    from the same camera (:func:`wast3d.viewer.view_camera`): once the page has settled (viser fades
    splats in, shrunken, for its first frames), the two agree to a few levels of 255 in the lower half
    of the page (the upper holds viser's panels). A control that must fail: the render blended halfway
    to white (how the viewer looked when caught mid fade-in) is far off by the same measure."""
    pytest.importorskip("viser")
    browser = shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")
    if browser is None:
        pytest.skip("no chromium on this machine (apt-get install -y chromium)")
    import imageio.v3 as iio

    from wast3d.ply import write_ply
    from wast3d.rasterizer import rasterize
    from wast3d.viewer import placed, view_camera

    scene = _stripes()
    write_ply(tmp_path / "stripes.ply", scene)
    port = _free_port()
    server = subprocess.Popen([sys.executable, "-m", "wast3d", "view", str(tmp_path / "stripes.ply"), "--port", str(port)],
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=ROOT)
    try:
        for _ in range(120):
            try:
                urllib.request.urlopen(f"http://127.0.0.1:{port}")
                break
            except OSError:
                assert server.poll() is None, server.stdout.read()
                time.sleep(0.5)
        page = _screenshot_when(f"http://127.0.0.1:{port}", browser, _settled(_lower_half_drawn(0.05)), timeout=240)
    finally:
        server.terminate()
        server.wait(timeout=10)
    h, w = page.shape[:2]
    r = rasterize(placed(scene), view_camera(w, h), background=(1.0, 1.0, 1.0), sh_degree=0)
    render = (r.rgb.clamp(0, 1) * 255).round().numpy()
    iio.imwrite(tmp_path / "viewer_vs_render.png", np.concatenate([page, render.astype(np.uint8)], 1))
    lower = np.zeros((h, w), bool)
    lower[h // 2:] = True
    drawn = lower & (r.alpha.numpy() > 0.02)
    assert drawn.sum() > 0.05 * lower.sum(), "the stripes should fill the lower half of the render"
    err = np.abs(page[lower].astype(float) - render[lower]).mean()
    err_drawn = np.abs(page[drawn].astype(float) - render[drawn]).mean(0)
    pale = 0.5 * render + 0.5 * 255
    err_pale = np.abs(page[lower].astype(float) - pale[lower]).mean()
    assert err < 4.0 and err_drawn.max() < 6.0, (err, err_drawn, tmp_path / "viewer_vs_render.png")
    assert err_pale > 4 * err, (err_pale, err)


def test_the_viewer_answers_only_its_own_host_and_origin(tmp_path):
    """A page of another site (Origin) or one that rebinds its name to this machine (Host) gets 403 and no
    Gaussian; the page's own origin gets both."""
    import http.client

    import viser
    import websockets

    from wast3d.ply import write_ply
    from wast3d.viewer import allowed_hosts, refusal, serve

    write_ply(tmp_path / "s.ply", random_scene(200, seed=1))
    server = serve([tmp_path / "s.ply"], "127.0.0.1", 0, 1000)
    port = server.get_port()
    try:
        def status(host):
            c = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
            c.request("GET", "/", headers={"Host": host})
            return c.getresponse().status

        assert status(f"localhost:{port}") == 200 and status(f"127.0.0.1:{port}") == 200
        assert status("evil.example") == 403 and status(f"evil.example:{port}") == 403

        async def first_message(origin):
            async with websockets.connect(f"ws://127.0.0.1:{port}", origin=origin, subprotocols=[f"viser-v{viser.__version__}"],
                                          open_timeout=10) as ws:
                return await asyncio.wait_for(ws.recv(), 10)

        assert len(asyncio.run(first_message(f"http://localhost:{port}"))) > 0
        with pytest.raises(websockets.exceptions.InvalidStatus, match="403"):
            asyncio.run(first_message("http://evil.example"))
    finally:
        server.stop()
    # opened to the network: any name, but a page only to its own origin
    assert refusal({"Host": "lab-pc:8080", "Origin": "http://lab-pc:8080"}, allowed_hosts("0.0.0.0")) is None
    assert refusal({"Host": "lab-pc:8080", "Origin": "http://evil.example"}, allowed_hosts("0.0.0.0")) is not None
    assert refusal({"Host": "[::1]:8080"}, allowed_hosts("127.0.0.1")) is None
    assert refusal({}, allowed_hosts("127.0.0.1")) == "no Host header"


@pytest.mark.parametrize("args, message", [(["--port", "99999"], "--port 99999"), (["--port", "-1"], "--port -1"),
                                           (["--host", "256.1.1.1"], "not an IP address"),
                                           (["--max-gaussians", "-5"], "--max-gaussians -5"),
                                           (["--host", "192.0.2.1"], "cannot listen on 192.0.2.1")])
def test_viewer_arguments_are_checked_before_it_starts(tmp_path, args, message):
    from wast3d.ply import write_ply

    write_ply(tmp_path / "s.ply", random_scene(50, seed=1))
    r = subprocess.run([sys.executable, "-m", "wast3d", "view", str(tmp_path / "s.ply"), *args], capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 2 and message in r.stderr and "Traceback" not in r.stderr, r.stderr

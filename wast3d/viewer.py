"""An interactive 3D viewer for Gaussian scenes in the browser, on viser (the viewer library of
nerfstudio and gsplat's examples): ``wast3d view CONTENT.ply STYLE.ply RESULT.ply``.

Scenes are shown one at a time, each scaled to the same size (a small style patch and a large
content scene open in the same view); a dropdown in the page switches between them. viser renders
the splats with its own WebGL rasterizer (view-independent colour: the DC term);
``max_gaussians`` keeps the page responsive for large scenes by keeping the most opaque ones.

The page opens at :func:`view_camera`: a render of :func:`placed` from that camera with
:func:`wast3d.rasterizer.rasterize` (DC colour, white background) is what the page shows once viser's
fade-in has ended (its first frames draw the splats shrunken, which reads as pale; in software WebGL
that lasts tens of seconds). ``tests/test_viewer.py`` compares the two in headless Chromium.
"""

from __future__ import annotations

import logging
import math
import time
from pathlib import Path

import numpy as np
import torch

from .cameras import Camera, fov_to_focal, look_at
from .gaussians import GaussianScene
from .cameras import scene_bounds

log = logging.getLogger(__name__)


def splat_arrays(scene: GaussianScene, max_gaussians: int | None = None) -> dict[str, np.ndarray]:
    """What viser's ``add_gaussian_splats`` takes: ``centers`` [N,3], ``covariances`` [N,3,3],
    ``rgbs`` [N,3] in [0,1] (DC colour), ``opacities`` [N,1]; float32. With ``max_gaussians`` the
    most opaque ones are kept."""
    s = scene.to(dtype=torch.float32)
    if max_gaussians is not None and len(s) > max_gaussians:
        keep = torch.topk(s.opacities, max_gaussians).indices.sort().values
        s = s.subset(keep)
    f = lambda t: np.ascontiguousarray(t.detach().cpu().numpy(), dtype=np.float32)  # noqa: E731
    return {"centers": f(s.means), "covariances": f(s.covariances), "rgbs": f(s.rgb.clamp(0, 1)),
            "opacities": f(s.opacities[:, None])}


def unit_placement(scene: GaussianScene) -> tuple[float, np.ndarray]:
    """(scale, position) that shows ``scene`` at unit radius (robust bounds) centred at the origin:
    a point p is shown at ``position + scale * p``, so scenes of any size open in the same view."""
    centre, radius = scene_bounds(scene)
    scale = 1.0 / max(float(radius), 1e-12)
    return scale, -scale * centre.double().numpy()


def placed(scene: GaussianScene) -> GaussianScene:
    """``scene`` as the page shows it: moved and scaled by :func:`unit_placement`."""
    scale, position = unit_placement(scene)
    return scene.transform(translation=torch.as_tensor(position, dtype=scene.dtype), scale=scale)


VIEW_EYE = (0.0, -2.6, 1.3)  # the initial camera, in the placed frame (+z up), looking at the origin
VIEW_FOV_DEG = 50.0  # its vertical field of view


def view_camera(width: int, height: int) -> Camera:
    """The page's initial camera on a ``width`` x ``height`` canvas, as a :class:`Camera` (OpenCV axes,
    vertical field of view ``VIEW_FOV_DEG``, principal point at the centre)."""
    f = fov_to_focal(math.radians(VIEW_FOV_DEG), height)
    return Camera(look_at(VIEW_EYE, (0.0, 0.0, 0.0)), f, f, width / 2, height / 2, width, height, name="view")


LOOPBACK = ("localhost", "127.0.0.1", "::1")
WILDCARD_HOSTS = ("0.0.0.0", "::", "")


def allowed_hosts(host: str) -> set[str] | None:
    """The names a request's ``Host`` may give for a server bound to ``host``: the loopback names, and
    ``host`` itself when it is another address; None (any name) when ``host`` opens every interface."""
    return None if host in WILDCARD_HOSTS else {*LOOPBACK, host.strip("[]").lower()}


def _hostname(value: str) -> str:
    """``example.org:8080`` -> ``example.org``; ``[::1]:8080`` -> ``::1``; lower case."""
    v = value.strip().lower()
    if v.startswith("["):
        return v[1:v.index("]")] if "]" in v else v
    return v.rsplit(":", 1)[0] if v.count(":") == 1 else v


def refusal(headers, hosts: set[str] | None) -> str | None:
    """Why a request (its ``headers``: ``get(name)``) is refused, or None. ``Host`` must be one of
    ``hosts`` (a page of another site that rebinds its name to this machine gives its own name); an
    ``Origin``, which a browser sends with every websocket, must name a host of ``hosts`` too (with
    ``hosts`` None: the ``Host`` itself, so a page is served to its own origin only)."""
    host = headers.get("Host")
    if host is None:
        return "no Host header"
    name = _hostname(host)
    if hosts is not None and name not in hosts:
        return f"Host {host!r} is not this viewer's ({', '.join(sorted(hosts))})"
    origin = headers.get("Origin")
    if origin is not None:
        from urllib.parse import urlsplit

        try:
            oname = (urlsplit(origin).hostname or "").lower()
        except ValueError:
            oname = ""
        if oname not in (hosts if hosts is not None else {name}):
            return f"Origin {origin!r} is another site"
    return None


def check_serve_args(host: str, port: int, max_gaussians: int | None) -> None:
    """ValueErrors for arguments the server cannot start with, before it starts: a port outside 0-65535
    (0: any free one), ``max_gaussians`` under 1, a host that is no address of this machine (an
    address literal that does not parse, a name that does not resolve in 5 s, or one it cannot listen
    on, named with the system's reason)."""
    import ipaddress
    import socket
    from concurrent.futures import ThreadPoolExecutor, TimeoutError as Timeout

    if not 0 <= port <= 65535:
        raise ValueError(f"view: --port {port}: must be 0-65535 (0: any free port)")
    if max_gaussians is not None and max_gaussians < 1:
        raise ValueError(f"view: --max-gaussians {max_gaussians}: must be at least 1")
    if host.replace(".", "").isdigit() or ":" in host:
        try:
            ipaddress.ip_address(host.strip("[]"))
        except ValueError:
            raise ValueError(f"view: --host {host}: not an IP address") from None
    pool = ThreadPoolExecutor(1)
    try:
        infos = pool.submit(socket.getaddrinfo, host.strip("[]") or None, port, type=socket.SOCK_STREAM).result(5)
    except Timeout:
        raise ValueError(f"view: --host {host}: the name did not resolve within 5 s") from None
    except socket.gaierror as e:
        raise ValueError(f"view: --host {host}: {e.strerror}") from None
    finally:
        pool.shutdown(wait=False)
    family, kind, proto, _, addr = infos[0]
    with socket.socket(family, kind, proto) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(addr)
        except OSError as e:
            raise ValueError(f"view: cannot listen on {host}:{port} ({e.strerror})") from None


def guarded(host: str):
    """A context in which viser's server checks every request with :func:`refusal` (403 when refused):
    viser 1.1.1 has no hook for it, so ``websockets.asyncio.server.serve``, which its server thread
    calls once while :class:`viser.ViserServer` is made, is wrapped for that call alone."""
    import contextlib
    import http

    import websockets.asyncio.server as ws

    hosts = allowed_hosts(host)
    real = ws.serve

    def serve_checked(*args, process_request=None, **kw):
        def check(connection, request):
            why = refusal(request.headers, hosts)
            if why is not None:
                log.warning("view: refused a request: %s", why)
                return connection.respond(http.HTTPStatus.FORBIDDEN, f"refused: {why}\n")
            return process_request(connection, request) if process_request is not None else None

        return real(*args, process_request=check, **kw)

    @contextlib.contextmanager
    def ctx():
        ws.serve = serve_checked
        try:
            yield
        finally:
            ws.serve = real

    return ctx()


def serve(paths: list[Path], host: str = "127.0.0.1", port: int = 8080, max_gaussians: int | None = 300_000,
          drop_invalid: bool = False):
    """Start a viser server showing the scenes in ``paths`` one at a time (a dropdown switches);
    returns the server (it runs in threads). Its arguments are checked first (:func:`check_serve_args`),
    and every request's ``Host`` and ``Origin`` (:func:`refusal`): a page of another site gets nothing.

    One splat object is in the scene at a time: with viser 1.1.1 in headless Chromium (software
    WebGL) only the last of several splat objects was drawn, so switching replaces the object.
    """
    import viser

    from .formats import read_scene

    check_serve_args(host, port, max_gaussians)
    scenes = {f"{i}: {Path(p).name}": read_scene(p, drop_invalid) for i, p in enumerate(paths)}
    with guarded(host):
        server = viser.ViserServer(host=host, port=port, verbose=False)
    if port and server.get_port() != port:  # viser moves on to the next port when one is taken
        server.stop()
        raise ValueError(f"view: cannot listen on {host}:{port} (taken)")
    server.scene.set_up_direction("+z")
    server.initial_camera.look_at = (0.0, 0.0, 0.0)
    server.initial_camera.up = (0.0, 0.0, 1.0)
    server.initial_camera.position = VIEW_EYE
    server.initial_camera.fov = math.radians(VIEW_FOV_DEG)
    names = list(scenes)
    pick = server.gui.add_dropdown("scene", options=names, initial_value=names[0])
    stats = server.gui.add_markdown("")
    current = {}

    def show(_=None):
        if "handle" in current:
            current.pop("handle").remove()
        scene = scenes[pick.value]
        arr = splat_arrays(scene, max_gaussians)
        scale, pos = unit_placement(scene)
        current["handle"] = server.scene.add_gaussian_splats("/scene", **arr, scale=float(scale),
                                                             position=tuple(float(v) for v in pos))
        stats.content = f"{len(arr['centers']):,} of {len(scene):,} Gaussians shown"
        log.info("view: %s: %d Gaussians shown (of %d)", pick.value, len(arr["centers"]), len(scene))

    pick.on_update(show)
    show()
    return server


def run_forever(server) -> None:  # pragma: no cover - interactive
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        server.stop()

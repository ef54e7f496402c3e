"""Stage 7, rendering: camera rigs fitted to a scene, previews, turntables and posed-image export (the
pictures made of them: :mod:`wast3d.figures`).

Pure helpers take and return tensors; the ``save_*``/``export_*`` functions are the I/O edge.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import torch

from .cameras import Camera, fit_orbit, scene_bounds
from .datasets import write_blender
from .figures import grid, save_png, subject_box, to_uint8, write_mp4
from .gaussians import GaussianScene, shortest_axis
from .io_utils import atomic_path, write_json
from .options import checked, option
from .rasterizer import Rendering, rasterize

log = logging.getLogger(__name__)


@torch.no_grad()
def render_views(scene: GaussianScene, cams: list[Camera], background=(1.0, 1.0, 1.0), **kw) -> list[Rendering]:
    return [rasterize(scene, c, background=background, **kw) for c in cams]


def save_preview(scene: GaussianScene, path: str | Path, n_views: int = 4, size: int = 256,
                 background=(1.0, 1.0, 1.0)) -> None:
    """A 1 x n_views grid of orbit renders, for a quick look at a scene."""
    cams = fit_orbit(scene, n_views, size)
    imgs = [to_uint8(r.rgb) for r in render_views(scene, cams, background)]
    save_png(path, grid(imgs, n_views))


EXPORT_ELEVATIONS = (15.0, 35.0, 55.0)
VOLUME_ELEVATIONS = (-50.0, -20.0, 10.0, 40.0, 70.0)  # a volume is seen from every side


@torch.no_grad()
def export_blender(scene: GaussianScene, root: str | Path, n_views: int = 48, size: int = 200,
                   holdout_views: int = 0, elevations: tuple[float, ...] | None = None) -> None:
    """Render ``scene`` from orbit cameras into a Blender-format posed image set (train split): ``n_views``
    cameras cycling through ``elevations`` (degrees above the scene's horizon); None: from above
    (EXPORT_ELEVATIONS) for a patch, from every side (VOLUME_ELEVATIONS) for a volume
    (:func:`wast3d.volume.style_form` of its Gaussians).

    The renders are on a transparent background (RGBA with straight alpha), as NeRF-Synthetic.
    """
    if elevations is None:
        from .volume import style_form

        form = style_form(scene.means.detach().numpy())
        elevations = VOLUME_ELEVATIONS if form.form == "volume" else EXPORT_ELEVATIONS
        log.info("export views: a %s (%s): elevations %s", form.form, form.reason, list(elevations))
    cams = fit_orbit(scene, n_views, size, elevations_deg=tuple(elevations), phase_deg=7.0)
    outs = render_views(scene, cams, background=(0.0, 0.0, 0.0))
    write_blender(root, cams, [o.rgb for o in outs], [o.alpha for o in outs])


# ---- stage 7: turntables, close-ups, depth and normals ---------------------------------------


@dataclass
@checked("render")
class RenderConfig:
    """What ``wast3d render`` produces (all cameras fitted to the *reference* scene, so that every
    method rendered against the same content shows the same views and the same close-up fragment).

    frames: turntable frames (one orbit at ``elevation`` degrees); size: frame width = height (px);
    key_views: frames (evenly spaced) that also get depth and normal maps; closeup_zoom: magnification
    of the close-up (the fragment a ``size / zoom`` pixel window of the first key view shows, centred on
    the fragment pixel); closeup_size: the close-up's width = height in px (0: ``size``); normals:
    "depth" (finite differences of the expected-depth map: the rendered surface's relief, domes and
    blades) or "axis" (each Gaussian's shortest axis, alpha-blended; on a trained scene's many small,
    blob-like Gaussians a mosaic of discs whatever the surface's shape); fps: GIF frame rate.
    """

    frames: int = option(24, "turntable frames", minimum=1, maximum=3600)
    size: int = option(256, "frame side in pixels", minimum=8, maximum=16384)
    elevation: float = option(30.0, "orbit elevation, degrees")
    fov: float = option(40.0, "field of view, degrees", exclusiveMinimum=0, exclusiveMaximum=180)
    key_views: int = option(4, "evenly spaced frames that also get depth and normal maps", minimum=1)
    closeup_zoom: float = option(3.0, "magnification of the close-up", minimum=1)
    closeup_size: int = option(0, "close-up side in pixels (0: size)", minimum=0, maximum=16384)
    normals: str = option("depth", "depth: from the depth map (the rendered surface's relief); axis: each Gaussian's "
                                   "shortest axis, alpha-blended", enum=["axis", "depth"])
    fps: float = option(8.0, "GIF frame rate", exclusiveMinimum=0)
    background: tuple = (1.0, 1.0, 1.0)

    def __post_init__(self):
        if self.key_views > self.frames:
            raise ValueError(f"render: need key_views <= frames, got {self.key_views} > {self.frames}")
        if self.closeup_size != 0 and self.closeup_size < 8:
            raise ValueError(f"render.closeup_size must be 0 (= size) or >= 8, got {self.closeup_size}")
        self.background = tuple(self.background)


def turntable_cameras(reference: GaussianScene, cfg: RenderConfig, up="z") -> list[Camera]:
    """``cfg.frames`` cameras on one ring around the reference scene, about its ``up`` (frame 0 at azimuth
    30 deg)."""
    return fit_orbit(reference, cfg.frames, cfg.size, fov_deg=cfg.fov, elevations_deg=(cfg.elevation,), up=up)


def key_indices(cfg: RenderConfig) -> list[int]:
    return [round(i * cfg.frames / cfg.key_views) for i in range(cfg.key_views)]


def fragment_pixel(alpha: torch.Tensor) -> tuple[int, int]:
    """The close-up's centre: the foreground pixel (alpha > 0.5) nearest the alpha-weighted centroid.

    alpha: [H, W] -> (x, y). Falls back to the image centre on an empty render.
    """
    H, W = alpha.shape
    ys, xs = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    a = alpha.detach().double().cpu()
    if float(a.sum()) < 1e-6:
        return W // 2, H // 2
    cy, cx = float((a * ys).sum() / a.sum()), float((a * xs).sum() / a.sum())
    d = (ys - cy) ** 2 + (xs - cx) ** 2
    d[a <= 0.5] = float("inf")
    if not torch.isfinite(d).any():
        return round(cx), round(cy)
    i = int(d.argmin())
    return i % W, i // W


def closeup_camera(cam: Camera, pixel: tuple[int, int], zoom: float, size: int = 0) -> Camera:
    """The part of ``cam``'s image that a ``cam.width / zoom`` x ``cam.height / zoom`` window centred on
    ``pixel`` (x, y) shows (clamped to stay inside the image), rendered ``size`` px wide (0: ``cam.width``,
    i.e. ``zoom`` times the resolution)."""
    f = size / cam.width if size > 0 else 1.0
    z = zoom * f
    w, h = round(cam.width * f), round(cam.height * f)
    big = cam.scaled(z)
    x0 = min(max(0, round((pixel[0] + 0.5) * z - w / 2)), big.width - w)
    y0 = min(max(0, round((pixel[1] + 0.5) * z - h / 2)), big.height - h)
    return big.crop(x0, y0, w, h)


def normal_colors(scene: GaussianScene, cam: Camera) -> torch.Tensor:
    """Each Gaussian's shortest axis in camera coordinates, flipped to face the camera: [N, 3]."""
    n = shortest_axis(scene.quats, scene.scales)
    R = cam.world_to_cam[:3, :3].to(n)
    n_cam = n @ R.T
    view = scene.means @ R.T + cam.world_to_cam[:3, 3].to(n)  # camera-frame position (ray direction)
    flip = ((n_cam * view).sum(-1, keepdim=True) > 0).to(n)
    return n_cam * (1 - 2 * flip)


def pixel_rays(cam: Camera, dtype=torch.float64) -> torch.Tensor:
    """[H, W, 3] camera-frame direction through each pixel's centre, scaled to z = 1 (times a depth
    map's z, the back-projected point)."""
    ys, xs = torch.meshgrid(torch.arange(cam.height, dtype=dtype), torch.arange(cam.width, dtype=dtype), indexing="ij")
    return torch.stack([(xs + 0.5 - cam.cx) / cam.fx, (ys + 0.5 - cam.cy) / cam.fy, torch.ones_like(xs)], -1)


def normals_from_depth(depth: torch.Tensor, alpha: torch.Tensor, cam: Camera) -> torch.Tensor:
    """Camera-frame normals [H, W, 3] from the expected-depth map by central differences of the
    back-projected points (zero where alpha <= 0.5 or a neighbour is background)."""
    P = pixel_rays(cam, depth.dtype) * depth[..., None]
    dx = torch.zeros_like(P)
    dy = torch.zeros_like(P)
    dx[:, 1:-1] = P[:, 2:] - P[:, :-2]
    dy[1:-1] = P[2:] - P[:-2]
    n = torch.linalg.cross(dx, dy)
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    n = torch.where((n[..., 2:] > 0), -n, n)  # face the camera (camera looks along +z)
    fg = alpha > 0.5
    ok = fg.clone()
    ok[:, 1:-1] &= fg[:, 2:] & fg[:, :-2]
    ok[1:-1] &= fg[2:] & fg[:-2]
    ok[0], ok[-1], ok[:, 0], ok[:, -1] = False, False, False, False
    return n * ok[..., None]


def normal_image(n: torch.Tensor, alpha: torch.Tensor, background=(1.0, 1.0, 1.0)) -> torch.Tensor:
    """[H, W, 3] camera-frame normals -> the usual picture: RGB = (x, -y, -z) / 2 + 1/2 (OpenGL look:
    facing the camera is blue), background where alpha is low."""
    rgb = torch.stack([n[..., 0], -n[..., 1], -n[..., 2]], -1) * 0.5 + 0.5
    a = alpha.clamp(0, 1)[..., None]
    return rgb * a + (1 - a) * torch.as_tensor(background, dtype=rgb.dtype)


def depth_image(depth: torch.Tensor, alpha: torch.Tensor, near: float, far: float, cmap: str = "turbo") -> np.ndarray:
    """Expected depth -> uint8 [H, W, 3] through a colour map on [near, far] (white background)."""
    import matplotlib

    t = ((depth - near) / max(far - near, 1e-12)).clamp(0, 1).detach().cpu().numpy()
    rgb = matplotlib.colormaps[cmap](t)[..., :3]
    a = alpha.clamp(0, 1).detach().cpu().numpy()[..., None]
    return ((rgb * a + (1 - a)) * 255 + 0.5).astype(np.uint8)


@torch.no_grad()
def render_maps(scene: GaussianScene, cam: Camera, cfg: RenderConfig) -> Rendering:
    """One view's rendering with its camera-frame normals [H, W, 3] (``normal``) filled in."""
    out = rasterize(scene, cam, background=cfg.background)
    if cfg.normals == "axis":
        nrm = rasterize(scene, cam, background=(0.0, 0.0, 0.0), colors=normal_colors(scene, cam)).rgb
        nrm = nrm / nrm.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    else:
        nrm = normals_from_depth(out.depth, out.alpha, cam)
    return replace(out, normal=nrm)


@torch.no_grad()
def camera_dicts(cams: list[Camera]) -> list[dict]:
    """Cameras as JSON-ready dicts (render.json)."""
    return [{"world_to_cam": c.world_to_cam.tolist(), "fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy,
             "width": c.width, "height": c.height} for c in cams]


def read_cameras(folder: str | Path, n: int | None = None) -> list[Camera]:
    """The first ``n`` (all: None) cameras of ``folder/render.json`` (:func:`camera_dicts`'s inverse)."""
    from .io_utils import read_json

    path = Path(folder) / "render.json"
    cams = read_json(path).get("cameras")
    if not isinstance(cams, list) or (n is not None and len(cams) < n):
        raise ValueError(f"{path}: 'cameras' must list {n or 'the'} cameras")
    try:
        return [Camera(torch.tensor(c["world_to_cam"], dtype=torch.float32), c["fx"], c["fy"], c["cx"], c["cy"],
                       c["width"], c["height"]) for c in cams[:n]]
    except (KeyError, TypeError) as e:
        raise ValueError(f"{path}: a camera lacks a field ({e})") from None


@torch.no_grad()
def element_pieces(scene: GaussianScene, copies: torch.Tensor, cams: list[Camera], tol: float,
                   min_alpha: float = 0.5, area_weight: torch.Tensor | None = None) -> list[np.ndarray]:
    """The visible element pieces of a labelled scene (:func:`wast3d.elements.piece_areas`, per camera):
    ``copies`` [N] each Gaussian's element copy (-1: the ground); the label colours and the copies'
    codes rendered together, one pass per view. ``area_weight`` [N]: what a pixel of each Gaussian's
    copy counts (one value per copy; None: 1)."""
    from .elements import copy_codes, element_pixels, label_colours, piece_areas

    cols, codes = copy_codes(copies, dtype=scene.dtype)
    weight = None
    if area_weight is not None:
        ids, inv = torch.unique(copies, return_inverse=True)
        w = torch.zeros(len(ids), dtype=torch.float64).scatter_(0, inv, area_weight.double())
        weight = w[ids >= 0].numpy()
    lab = label_colours(copies + 1, scene.dtype)
    out = []
    both = torch.cat([lab, cols], 1)  # [N, 3 + elements.PIECE_DIM]
    for cam in cams:
        m = rasterize(scene, cam, colors=both)
        out.append(piece_areas(m.rgb[..., 3:], element_pixels(m.rgb[..., :3], m.alpha), m.alpha, codes, tol, min_alpha,
                               weight))
    return out


def render_turntable(scene: GaussianScene, reference: GaussianScene, out_dir: str | Path, cfg: RenderConfig,
                     progress: bool = False, up="z") -> dict:
    """Write the turntable and close-up of ``scene`` (cameras from ``reference``) under ``out_dir``:

    ``frames/NNN.png`` (RGBA, straight alpha: what the metrics read), ``turntable.gif`` and ``.mp4``
    (:func:`write_mp4`; the frames cropped to the box the subject turns in, :func:`subject_box`),
    ``key_NN_{rgb,depth,normal}.png``,
    ``closeup_{rgb,depth,normal}.png`` and ``render.json`` (cameras, fragment, depth range, settings).
    The orbit turns about the reference's ``up`` (:func:`~wast3d.cameras.up_vector`).
    """
    from tqdm import tqdm

    out_dir = Path(out_dir)
    (out_dir / "frames").mkdir(parents=True, exist_ok=True)
    cams = turntable_cameras(reference, cfg, up)
    centre, radius = scene_bounds(reference)
    dist = float((cams[0].center.to(centre) - centre).norm())
    near, far = dist - radius, dist + radius
    keys = key_indices(cfg)
    ref_alpha = rasterize(reference, cams[keys[0]], background=cfg.background).alpha
    pixel = fragment_pixel(ref_alpha)
    gif = []
    for i, cam in enumerate(tqdm(cams, desc="turntable", disable=not progress)):
        if i in keys:
            m = render_maps(scene, cam, cfg)
            k = keys.index(i)
            save_png(out_dir / f"key_{k:02d}_rgb.png", to_uint8(m.rgb))
            save_png(out_dir / f"key_{k:02d}_depth.png", depth_image(m.depth, m.alpha, near, far))
            save_png(out_dir / f"key_{k:02d}_normal.png", to_uint8(normal_image(m.normal, m.alpha)))
        else:
            m = rasterize(scene, cam, background=cfg.background)
        save_png(out_dir / "frames" / f"{i:03d}.png", to_uint8(straight_rgba(m, cfg.background)))
        save_element_frame(scene, cam, out_dir, i)
        gif.append(to_uint8(m.rgb))
    gif = np.stack(gif)
    y0, y1, x0, x1 = subject_box(list(gif))  # the turntable cropped to where the subject turns
    gif = np.ascontiguousarray(gif[:, y0:y1, x0:x1])
    with atomic_path(out_dir / "turntable.gif") as tmp:
        iio.imwrite(tmp, gif, extension=".gif", duration=1000.0 / cfg.fps, loop=0)
    write_mp4(out_dir / "turntable.mp4", gif, cfg.fps)
    cu = closeup_camera(cams[keys[0]], pixel, cfg.closeup_zoom, cfg.closeup_size)
    m = render_maps(scene, cu, cfg)
    save_png(out_dir / "closeup_rgb.png", to_uint8(m.rgb))
    save_png(out_dir / "closeup_depth.png", depth_image(m.depth, m.alpha, near, far))
    save_png(out_dir / "closeup_normal.png", to_uint8(normal_image(m.normal, m.alpha)))
    info = {"frames": cfg.frames, "key_frames": keys, "fragment_pixel": list(pixel), "depth_range": [near, far],
            "normals": cfg.normals, "gaussians": len(scene), "config": asdict(cfg), "up": up,
            "cameras": camera_dicts(cams + [cu])}
    write_json(out_dir / "render.json", info)
    return info


def save_element_frame(scene: GaussianScene, cam: Camera, out_dir: Path, i: int) -> None:
    """The label channel of a labelled scene (:mod:`wast3d.elements`): ``elements/NNN.png``, the share of
    each pixel drawn by element (not ground) Gaussians, 8-bit grey; nothing for an unlabelled scene."""
    if scene.element is None:
        return
    from .elements import element_pixels, label_colours

    m = rasterize(scene, cam, background=(0.0, 0.0, 0.0), colors=label_colours(scene.element, scene.dtype))
    (out_dir / "elements").mkdir(exist_ok=True)
    save_png(out_dir / "elements" / f"{i:03d}.png", to_uint8(element_pixels(m.rgb, m.alpha)))


def read_element_frames(folder: str | Path) -> torch.Tensor | None:
    """``elements/*.png`` of :func:`save_element_frame` -> [V, H, W] in [0, 1], or None when the scene
    rendered there had no labels."""
    files = sorted((Path(folder) / "elements").glob("*.png"))
    if not files:
        return None
    return torch.from_numpy(np.stack([iio.imread(f) for f in files])).float() / 255.0


def straight_rgba(m: Rendering, background) -> torch.Tensor:
    """A render composited on ``background`` (``m.rgb`` [H, W, 3], ``m.alpha`` [H, W]) -> [H, W, 4]
    straight (un-premultiplied) RGBA, as the frames are stored."""
    a = m.alpha.clamp(0, 1)
    bg = torch.as_tensor(background, dtype=m.rgb.dtype)
    straight = ((m.rgb - (1 - a[..., None]) * bg) / a[..., None].clamp_min(1e-6)).clamp(0, 1)
    return torch.cat([straight, a[..., None]], -1)


def texture_reference_cameras(style: GaussianScene, content: GaussianScene, cfg: RenderConfig,
                              s0: float | None = None, up="z") -> tuple[list[Camera], float]:
    """Cameras for the style's *texture reference* (``texture_swd``): the style's turntable, zoomed by

        z = R_style / (R_content * s0)

    (R: :func:`scene_bounds` radius; s0: the registration's base scale, style units per content unit,
    :func:`wast3d.registration.base_scale`; None: the density rule, h_style / h_content), so that a
    length of the style covers as many pixels as it does once registration has mapped it onto the
    content, in the turntable fitted to the content in which every result of the pair is rendered: the
    style's elements then have the pixel size they have on a result. Returns (cameras, z)."""
    from .geometry import mean_spacing

    _, rs = scene_bounds(style)
    _, rc = scene_bounds(content)
    if s0 is None:
        s0 = mean_spacing(style.means) / mean_spacing(content.means)
    z = rs / (rc * s0)
    cams = [replace(c, fx=c.fx * z, fy=c.fy * z) for c in turntable_cameras(style, cfg, up)]
    return cams, z


def render_texture_reference(style: GaussianScene, content: GaussianScene, out_dir: str | Path, cfg: RenderConfig,
                             progress: bool = False, s0: float | None = None, element_length: float | None = None,
                             up="z", size_factor: float = 1.0) -> dict:
    """Write ``frames/NNN.png`` (RGBA, straight alpha) of the style from :func:`texture_reference_cameras`
    (content-to-style scale ``s0``), ``key_00_rgb.png`` and ``closeup_{rgb,normal}.png`` (the first frame
    and its close-up, as :func:`render_turntable` makes them: the style at the pixel scale of the result's
    close-up, its fair reference) and ``render.json`` (cameras, zoom, the style's element length on the
    content if given, ``size_factor``: the elements' size here against the size the registration asks)
    under ``out_dir``."""
    from tqdm import tqdm

    out_dir = Path(out_dir)
    (out_dir / "frames").mkdir(parents=True, exist_ok=True)
    cams, z = texture_reference_cameras(style, content, cfg, s0, up)
    for i, cam in enumerate(tqdm(cams, desc="texture reference", disable=not progress)):
        m = rasterize(style, cam, background=cfg.background)
        save_png(out_dir / "frames" / f"{i:03d}.png", to_uint8(straight_rgba(m, cfg.background)))
        save_element_frame(style, cam, out_dir, i)
        if i == 0:
            save_png(out_dir / "key_00_rgb.png", to_uint8(m.rgb))
            cu = closeup_camera(cam, fragment_pixel(m.alpha), cfg.closeup_zoom, cfg.closeup_size)
    m = render_maps(style, cu, cfg)
    save_png(out_dir / "closeup_rgb.png", to_uint8(m.rgb))
    save_png(out_dir / "closeup_normal.png", to_uint8(normal_image(m.normal, m.alpha)))
    info = {"frames": len(cams), "zoom": z, "gaussians": len(style), "s0": s0, "size_factor": size_factor,
            "element_length": element_length, "config": asdict(cfg), "up": up, "cameras": camera_dicts(cams + [cu])}
    write_json(out_dir / "render.json", info)
    return info


def read_frames(folder: str | Path) -> torch.Tensor:
    """``frames/*.png`` (RGBA) written by :func:`render_turntable` -> [V, H, W, 4] float in [0, 1]."""
    files = sorted((Path(folder) / "frames").glob("*.png"))
    if not files:
        raise FileNotFoundError(f"{folder}: no turntable frames (frames/*.png); run `wast3d render` first")
    imgs = [iio.imread(f) for f in files]
    for f, im in zip(files, imgs):
        if im.ndim != 3 or im.shape[2] != 4 or im.shape != imgs[0].shape:
            raise ValueError(f"{f}: expected an RGBA frame of shape {imgs[0].shape}, got {im.shape}")
    return torch.from_numpy(np.stack(imgs)).float() / 255.0



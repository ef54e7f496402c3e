"""Pictures: of intermediate artifacts (pyvista off-screen for 3D point sets, matplotlib for curves), and
of renders (grids, captions, comparison sheets, turntable videos and their HTML page)."""

from __future__ import annotations

import logging
import math
import os
from pathlib import Path

import imageio.v3 as iio
import numpy as np

from .io_utils import atomic_path, read_image

log = logging.getLogger(__name__)


def _plotter(size=(900, 700)):
    import pyvista as pv

    pv.OFF_SCREEN = True
    os.environ.setdefault("PYVISTA_OFF_SCREEN", "true")
    p = pv.Plotter(off_screen=True, window_size=size)
    p.set_background("white")
    return p


def _palette(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    hues = rng.permutation(n) / max(n, 1)
    import colorsys

    return np.array([colorsys.hsv_to_rgb(h, 0.75, 0.9) for h in hues])


def clusters_picture(points: np.ndarray, labels: np.ndarray, path: str | Path, title: str = "") -> None:
    """Points coloured by cluster label."""
    import pyvista as pv

    pal = _palette(int(labels.max()) + 1)
    p = _plotter()
    cloud = pv.PolyData(points.astype(np.float32))
    cloud["rgb"] = (pal[labels] * 255).astype(np.uint8)
    p.add_points(cloud, scalars="rgb", rgb=True, point_size=4, render_points_as_spheres=True)
    if title:
        p.add_text(title, font_size=10, color="black")
    p.view_isometric()
    with atomic_path(path) as tmp:
        p.screenshot(str(tmp))
    p.close()


def registration_picture(panels: list[tuple[np.ndarray, np.ndarray, np.ndarray]], path: str | Path) -> None:
    """Each panel: (mapped content points [N,3], nearby style points [M,3], style colours [M,3]);
    content in red over the style patch, one sub-view per panel."""
    import pyvista as pv

    n = len(panels)
    cols = min(n, 3)
    rows = (n + cols - 1) // cols
    p = pv.Plotter(off_screen=True, shape=(rows, cols), window_size=(340 * cols, 320 * rows))
    for i, (c, s, sc) in enumerate(panels):
        p.subplot(i // cols, i % cols)
        p.set_background("white")
        sp = pv.PolyData(s.astype(np.float32))
        sp["rgb"] = (np.clip(sc, 0, 1) * 255).astype(np.uint8)
        p.add_points(sp, scalars="rgb", rgb=True, point_size=3)
        p.add_points(pv.PolyData(c.astype(np.float32)), color="red", point_size=5, render_points_as_spheres=True)
        p.add_text(f"cluster {i}", font_size=8, color="black")
        p.view_isometric()
    with atomic_path(path) as tmp:
        p.screenshot(str(tmp))
    p.close()


def loss_curves_picture(curves: list[list[float]], path: str | Path, title: str = "") -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for c in curves:
        ax.plot(c, color="tab:blue", alpha=0.25, lw=0.8)
    curves = [c for c in curves if len(c)]  # iterations: 0 (the positive control) has no curve
    if curves:
        L = min(len(c) for c in curves)
        ax.plot(np.mean([c[:L] for c in curves], 0), color="black", lw=2, label="mean over clusters")
        ax.legend()
    ax.set_xlabel("iteration")
    ax.set_ylabel("cluster loss (normalized units)")
    if curves and min(min(c) for c in curves) > 0:
        ax.set_yscale("log")
    ax.set_title(title)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp)
    plt.close(fig)


# ---- pictures of renders: grids, captions, comparison sheets, turntable videos and pages ----------------


def to_uint8(img: torch.Tensor) -> np.ndarray:
    """[H, W, C] float in [0, 1] -> uint8."""
    return (img.detach().clamp(0, 1).cpu().numpy() * 255 + 0.5).astype(np.uint8)


def grid(images: list[np.ndarray], cols: int) -> np.ndarray:
    """Tile [H, W, C] images into a grid, row-major; cells as large as the largest image, smaller
    images centred on white (a 512 px close-up beside 256 px key views)."""
    rows = math.ceil(len(images) / cols)
    h, w = max(im.shape[0] for im in images), max(im.shape[1] for im in images)
    c = images[0].shape[2]
    out = np.full((rows * h, cols * w, c), 255, np.uint8)
    for i, im in enumerate(images):
        r, k = divmod(i, cols)
        y, x = r * h + (h - im.shape[0]) // 2, k * w + (w - im.shape[1]) // 2
        out[y:y + im.shape[0], x:x + im.shape[1]] = im
    return out


def save_png(path: str | Path, img: np.ndarray) -> None:
    with atomic_path(path) as tmp:
        iio.imwrite(tmp, img, extension=".png")


def label_image(img: np.ndarray, text: str, height: int = 22, size: int = 11) -> np.ndarray:
    """``img`` with a white caption strip of ``height`` px above it (``size`` px type)."""
    from PIL import Image, ImageDraw, ImageFont

    strip = Image.new("RGB", (img.shape[1], height), (255, 255, 255))
    ImageDraw.Draw(strip).text((4, (height - size) // 2), text, fill=(0, 0, 0), font=ImageFont.load_default(size=size))
    return np.concatenate([np.asarray(strip), img[..., :3]], axis=0)


def subject_box(images: list[np.ndarray], pad: float = 0.06, background: int = 250) -> tuple[int, int, int, int]:
    """(y0, y1, x0, x1): the box every ``images`` [H, W, C] uint8 (one size; white background) draws its
    subject in (any channel below ``background``), widened by ``pad`` of its size on each side and made
    square where the image allows: one crop that frames the subject in all of them (a turntable's
    frames, one view of several methods). The whole image where nothing is drawn."""
    H, W = images[0].shape[:2]
    drawn = np.zeros((H, W), bool)
    for im in images:
        drawn |= (im[..., :3] < background).any(-1)
    if not drawn.any():
        return 0, H, 0, W
    ys, xs = np.nonzero(drawn)
    y0, y1, x0, x1 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
    side = max(y1 - y0, x1 - x0) * (1 + 2 * pad)
    cy, cx = (y0 + y1) / 2, (x0 + x1) / 2
    h, w = min(H, round(side)), min(W, round(side))
    y0 = int(min(max(0, round(cy - h / 2)), H - h))
    x0 = int(min(max(0, round(cx - w / 2)), W - w))
    return y0, y0 + h, x0, x0 + w


def fit_tile(img: np.ndarray, size: int) -> np.ndarray:
    """``img`` scaled (Lanczos) so that its longer side is ``size`` px, centred on a white ``size`` square."""
    from PIL import Image

    h, w = img.shape[:2]
    f = size / max(h, w)
    im = Image.fromarray(img[..., :3]).resize((max(1, round(w * f)), max(1, round(h * f))), Image.LANCZOS)
    out = np.full((size, size, 3), 255, np.uint8)
    y, x = (size - im.height) // 2, (size - im.width) // 2
    out[y:y + im.height, x:x + im.width] = np.asarray(im)
    return out


def side_label(img: np.ndarray, text: str, width: int = 180, size: int = 18) -> np.ndarray:
    """``img`` with a white strip of ``width`` px at its left holding ``text`` (wrapped, ``size`` px type)."""
    import textwrap

    from PIL import Image, ImageDraw, ImageFont

    strip = Image.new("RGB", (width, img.shape[0]), (255, 255, 255))
    ImageDraw.Draw(strip).multiline_text((8, 10), textwrap.fill(text, max(8, width // (size // 2 + 1))), fill=(0, 0, 0),
                                         font=ImageFont.load_default(size=size))
    return np.concatenate([np.asarray(strip), img[..., :3]], axis=1)


SHEET_TILES = (("key_00_rgb", "key view"), ("closeup_rgb", "close-up"), ("closeup_normal", "close-up normals"))


def comparison_sheet(columns: list[tuple[str, str | Path]], out: str | Path, tiles=SHEET_TILES, tile: int = 512) -> None:
    """One row per (label, render folder), one ``tile`` px square per picture of ``tiles`` (name, caption):
    a key view cropped to the box its subject takes in every row rendered from the same cameras
    (:func:`subject_box`: the content and the methods share one crop, the style has its own), the
    close-ups whole; a picture a folder lacks is left white."""
    def read(folder, name):
        p = Path(folder) / f"{name}.png"
        return read_picture(p) if p.exists() else None

    def rig(folder):  # rows rendered from the same cameras share a crop
        p = Path(folder) / "render.json"
        try:
            import json

            return json.dumps(json.loads(p.read_text())["cameras"][0], sort_keys=True)
        except (OSError, ValueError, KeyError, IndexError):
            return str(folder)

    if not any(read(f, name) is not None for _, f in columns for name, _ in tiles):
        raise FileNotFoundError("comparison sheet: none of the render folders has pictures")
    boxes = {}
    for name, _ in tiles:
        if not name.startswith("key_"):
            continue
        groups: dict[str, list] = {}
        for _, f in columns:
            if (im := read(f, name)) is not None:
                groups.setdefault(rig(f), []).append(im)
        for key, imgs in groups.items():
            if len({im.shape for im in imgs}) == 1:
                boxes[(name, key)] = subject_box(imgs)
    head = side_label(np.concatenate([label_image(np.full((0, tile, 3), 255, np.uint8), cap, 30, 18)
                                      for _, cap in tiles], 1), "")
    rows = [head]
    for label, folder in columns:
        cells = []
        for name, _ in tiles:
            im = read(folder, name)
            if im is None:
                cells.append(np.full((tile, tile, 3), 255, np.uint8))
                continue
            box = boxes.get((name, rig(folder)))
            if box is not None:
                y0, y1, x0, x1 = box
                im = im[y0:y1, x0:x1]
            cells.append(fit_tile(im, tile))
        rows.append(side_label(np.concatenate(cells, 1), label))
    save_png(out, np.concatenate(rows, 0))


MAX_PIXELS = 1 << 26  # a picture a figure reads: 64 megapixels at most (a render is a few)


def read_picture(path: str | Path) -> np.ndarray:
    """A picture a figure shows -> [H, W, 3] uint8 (grey and alpha dropped to RGB); a ValueError naming the
    file when it is missing, not a file, no image, or beyond MAX_PIXELS (:func:`~wast3d.io_utils.read_image`)."""
    im = read_image(path, ValueError, MAX_PIXELS)
    if im.dtype.kind == "f":  # values in [0, 1]
        im = (np.nan_to_num(im.astype(np.float64)).clip(0, 1) * 255).round().astype(np.uint8)
    elif im.dtype != np.uint8:  # 16-bit and other integer pictures, by their range
        im = (im.astype(np.float64) * 255 / max(np.iinfo(im.dtype).max, 1)).round().clip(0, 255).astype(np.uint8)
    return im[..., :3]


def strip(tiles: list[tuple[str, str | Path]], out: str | Path, tile: int = 320) -> None:
    """One row of pictures with captions above (a README figure): ``tiles`` are (caption, PNG path); a key
    view (``key_*``) is cropped to its subject (:func:`subject_box`), every picture fitted to a ``tile`` px
    square."""
    cells = []
    for caption, path in tiles:
        im = read_picture(path)
        if Path(path).name.startswith("key_"):
            y0, y1, x0, x1 = subject_box([im])
            im = im[y0:y1, x0:x1]
        cells.append(label_image(fit_tile(im, tile), caption, 30, 16))
    save_png(out, np.concatenate(cells, 1))


def write_mp4(path: str | Path, frames: np.ndarray, fps: float) -> bool:
    """frames [T, H, W, 3] uint8 -> an H.264 MP4 (yuv420p, faststart: what browsers play) at ``path``,
    atomically, with the ffmpeg that the ``imageio-ffmpeg`` wheel carries; odd sizes are padded by one
    edge pixel (yuv420p needs even ones). Without ``imageio-ffmpeg``, logs that and returns False."""
    try:
        import imageio_ffmpeg
    except ImportError:
        log.warning("%s: no MP4 written (imageio-ffmpeg is not installed); the GIF is", path)
        return False
    _, H, W, _ = frames.shape
    frames = np.pad(frames, ((0, 0), (0, H % 2), (0, W % 2), (0, 0)), mode="edge")
    with atomic_path(path) as tmp:
        w = imageio_ffmpeg.write_frames(str(tmp), (frames.shape[2], frames.shape[1]), fps=fps, codec="libx264", pix_fmt_out="yuv420p",
                                        quality=8, macro_block_size=1, ffmpeg_log_level="error",
                                        output_params=["-movflags", "+faststart"])
        w.send(None)
        for f in frames:
            w.send(np.ascontiguousarray(f))
        w.close()
    return True


def turntable_page(columns: list[tuple[str, str | Path]], out: str | Path) -> None:
    """One self-contained HTML page: per (label, render folder), its ``turntable.mp4`` embedded as a
    looping video (the GIF where a folder has no MP4); for the Snakemake report, which shows HTML."""
    import base64
    import html

    cells = []
    for label, folder in columns:
        mp4, gif = Path(folder) / "turntable.mp4", Path(folder) / "turntable.gif"
        if mp4.exists():
            src = base64.b64encode(mp4.read_bytes()).decode()
            media = f'<video autoplay loop muted playsinline src="data:video/mp4;base64,{src}"></video>'
        elif gif.exists():
            media = f'<img src="data:image/gif;base64,{base64.b64encode(gif.read_bytes()).decode()}">'
        else:
            raise FileNotFoundError(f"turntable page: {folder} has neither turntable.mp4 nor turntable.gif")
        cells.append(f"<figure>{media}<figcaption>{html.escape(label)}</figcaption></figure>")
    style = "body{font-family:sans-serif;display:flex;flex-wrap:wrap}figure{margin:4px}video,img{width:256px}"
    with atomic_path(out) as tmp:
        Path(tmp).write_text(f"<!DOCTYPE html>\n<html><head><meta charset=\"utf-8\"><style>{style}</style></head>"
                             f"<body>\n{''.join(cells)}\n</body></html>\n")

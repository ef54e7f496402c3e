"""Posed image sets in the Blender/NeRF-Synthetic format: loading and writing.

Layout: ``<root>/transforms_<split>.json`` with ``camera_angle_x`` (horizontal field of view, radians)
and ``frames``: ``[{"file_path": "./train/r_0", "transform_matrix": 4x4 camera-to-world (OpenGL)}]``;
images are PNGs (``file_path`` without extension, as the original), RGBA with straight alpha.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import torch

from .cameras import Camera, camera_from_blender, camera_to_blender
from .io_utils import atomic_path, read_image

log = logging.getLogger(__name__)


class DatasetError(ValueError):
    """A dataset that cannot be loaded; the message names the file and the field."""


@dataclass
class View:
    camera: Camera
    image: torch.Tensor  # [H, W, 3] float32 in [0, 1], composited on the background
    alpha: torch.Tensor  # [H, W] float32
    name: str


@dataclass
class Dataset:
    train: list[View]
    test: list[View]
    background: tuple[float, float, float]
    root: Path

    @property
    def all_views(self) -> list[View]:
        return self.train + self.test

    def scene_center_radius(self) -> tuple[torch.Tensor, float]:
        """Centre and radius of the camera positions (as the reference 3DGS' ``getNerfppNorm``)."""
        c = torch.stack([v.camera.center for v in self.all_views])
        center = c.mean(0)
        return center, float((c - center).norm(dim=1).max()) * 1.1


def _resolve_image(root: Path, file_path: str) -> Path:
    p = root / file_path
    if p.suffix.lower() in (".png", ".jpg", ".jpeg"):
        return p
    for ext in (".png", ".jpg", ".jpeg"):
        if p.with_name(p.name + ext).exists():
            return p.with_name(p.name + ext)
    return p.with_name(p.name + ".png")


def load_image(path: Path, background: tuple[float, float, float]) -> tuple[torch.Tensor, torch.Tensor]:
    """Read an image -> (rgb composited on background [H, W, 3], alpha [H, W]), float32 in [0, 1].
    Grey, grey + alpha, RGB and RGBA are read (:func:`~wast3d.io_utils.read_image`); anything else is a
    DatasetError naming the file."""
    a = read_image(path, DatasetError)
    scale = 65535.0 if a.dtype == np.uint16 else 255.0 if a.dtype == np.uint8 else 1.0
    a = a.astype(np.float32) / scale
    rgb = a[..., :3]
    alpha = a[..., 3] if a.shape[-1] == 4 else np.ones(a.shape[:2], np.float32)
    bg = np.asarray(background, np.float32)
    rgb = rgb * alpha[..., None] + bg * (1 - alpha[..., None])
    return torch.from_numpy(np.ascontiguousarray(rgb)), torch.from_numpy(np.ascontiguousarray(alpha))


def _number(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def _matrix(value, where: str) -> torch.Tensor:
    """A frame's ``transform_matrix``: 4 rows of 4 finite numbers, an invertible camera-to-world."""
    if not (isinstance(value, list) and len(value) == 4 and all(
            isinstance(r, list) and len(r) == 4 and all(_number(x) for x in r) for r in value)):
        raise DatasetError(f"{where}: must be a 4x4 matrix of numbers (4 lists of 4), got {str(value)[:80]}")
    m = torch.tensor(value, dtype=torch.float64)
    if not torch.isfinite(m).all():
        raise DatasetError(f"{where}: must be a finite 4x4 matrix (it holds NaN or infinity)")
    r = m[:3, :3]
    if abs(float(torch.linalg.det(r))) <= 1e-9 * max(float(r.abs().max()), 1e-300) ** 3 or \
            not torch.allclose(m[3], torch.tensor([0.0, 0, 0, 1], dtype=torch.float64)):
        raise DatasetError(f"{where}: not a camera pose (its rotation part is singular, or its last row is not 0 0 0 1)")
    return m


def load_blender(root: str | Path, split: str = "train", holdout_every: int = 8,
                 background: tuple[float, float, float] = (1.0, 1.0, 1.0), max_views: int | None = None) -> Dataset:
    """Load ``transforms_<split>.json`` and its images; every ``holdout_every``-th view (0, k, 2k, ...)
    goes to the test set (0 disables hold-out; too few views to hold one out and train on the rest:
    none is held out, and the log says so).

    Errors (:class:`DatasetError`) name the file and field: missing JSON, invalid JSON or not an object,
    ``camera_angle_x`` missing or not a number in (0, pi), ``frames`` missing or empty, a frame that is
    not an object, a ``file_path`` that is not a string, a ``transform_matrix`` that is not 4x4 numbers,
    not finite or not invertible, a missing or unreadable image, images of different sizes. A
    ``file_path`` leaving the dataset's folder is read, with a warning.
    """
    import math

    root = Path(root)
    jpath = root / f"transforms_{split}.json"
    if not jpath.is_file():
        raise DatasetError(f"{jpath}: file not found")
    try:
        meta = json.loads(jpath.read_bytes())
    except (json.JSONDecodeError, UnicodeDecodeError, RecursionError) as e:
        raise DatasetError(f"{jpath}: invalid JSON ({str(e)[:200]})") from None
    if not isinstance(meta, dict):
        raise DatasetError(f"{jpath}: must be a JSON object with 'camera_angle_x' and 'frames', not a {type(meta).__name__}")
    for key in ("camera_angle_x", "frames"):
        if key not in meta:
            raise DatasetError(f"{jpath}: missing field '{key}'")
    fov = meta["camera_angle_x"]
    if not _number(fov) or not 0 < fov < math.pi:
        raise DatasetError(f"{jpath}: field 'camera_angle_x': {fov!r}; the horizontal field of view in radians, "
                           "a number between 0 and pi")
    frames = meta["frames"]
    if not isinstance(frames, list) or not frames:
        raise DatasetError(f"{jpath}: field 'frames' must be a non-empty list")
    if max_views:
        frames = frames[:max_views]
    views: list[View] = []
    size = None
    inside = root.resolve()
    for i, fr in enumerate(frames):
        if not isinstance(fr, dict):
            raise DatasetError(f"{jpath}: frames[{i}] must be an object with 'file_path' and 'transform_matrix', "
                               f"not {str(fr)[:40]}")
        for key in ("file_path", "transform_matrix"):
            if key not in fr:
                raise DatasetError(f"{jpath}: frames[{i}] missing field '{key}'")
        if not isinstance(fr["file_path"], str) or not fr["file_path"]:
            raise DatasetError(f"{jpath}: frames[{i}].file_path must be a file name, not {fr['file_path']!r}")
        m = _matrix(fr["transform_matrix"], f"{jpath}: frames[{i}].transform_matrix")
        ipath = _resolve_image(root, fr["file_path"])
        if inside not in ipath.resolve().parents:
            log.warning("%s: frames[%d].file_path %r lies outside the dataset's folder %s (read all the same)", jpath,
                        i, fr["file_path"], root)
        rgb, alpha = load_image(ipath, background)
        h, w = rgb.shape[:2]
        if size is None:
            size = (h, w)
        elif (h, w) != size:
            raise DatasetError(f"{ipath}: image size {w}x{h} differs from the first frame's {size[1]}x{size[0]}")
        cam = camera_from_blender(m, float(fov), w, h, name=Path(fr["file_path"]).name)
        views.append(View(cam, rgb, alpha, cam.name))
    held = {i for i in range(len(views)) if holdout_every and i % holdout_every == 0}
    if len(held) == len(views):
        log.warning("%s: %d view(s): too few to hold one out and train on the rest; none held out", jpath, len(views))
        held = set()
    test = [v for i, v in enumerate(views) if i in held]
    train = [v for i, v in enumerate(views) if i not in held]
    log.info("%s: %d train / %d held-out views at %dx%d", root, len(train), len(test), size[1], size[0])
    return Dataset(train, test, tuple(background), root)


def write_blender(root: str | Path, cameras: list[Camera], images: list[torch.Tensor], alphas: list[torch.Tensor],
                  split: str = "train") -> None:
    """Write a Blender-format posed image set (RGBA PNGs, straight alpha) for ``cameras``.

    images: [H, W, 3] premultiplied renders (as the rasterizer returns on a black background);
    alphas: [H, W]. All cameras must share fx = fy and a centred principal point.
    """
    root = Path(root)
    (root / split).mkdir(parents=True, exist_ok=True)
    frames = []
    for i, (cam, rgb, a) in enumerate(zip(cameras, images, alphas)):
        straight = (rgb / a.clamp_min(1e-6)[..., None]).clamp(0, 1)
        rgba = torch.cat([straight, a[..., None].clamp(0, 1)], dim=-1)
        arr = (rgba.detach().cpu().numpy() * 255.0 + 0.5).astype(np.uint8)
        rel = f"./{split}/r_{i}"
        with atomic_path(root / f"{split}/r_{i}.png") as tmp:
            iio.imwrite(tmp, arr, extension=".png")
        frames.append({"file_path": rel, "transform_matrix": camera_to_blender(cam).tolist()})
    cam0 = cameras[0]
    import math

    meta = {"camera_angle_x": 2 * math.atan(0.5 * cam0.width / cam0.fx), "frames": frames}
    with atomic_path(root / f"transforms_{split}.json") as tmp:
        tmp.write_text(json.dumps(meta, indent=1))

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
from .io_utils import atomic_path

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
    """Read an image -> (rgb composited on background [H, W, 3], alpha [H, W]), float32 in [0, 1]."""
    if not path.exists():
        raise DatasetError(f"{path}: image file not found")
    try:
        a = iio.imread(path)
    except Exception as e:
        raise DatasetError(f"{path}: cannot read image ({e})") from None
    a = np.asarray(a)
    scale = 65535.0 if a.dtype == np.uint16 else 255.0 if a.dtype == np.uint8 else 1.0
    a = a.astype(np.float32) / scale
    if a.ndim == 2:
        a = np.repeat(a[..., None], 3, axis=-1)
    rgb = a[..., :3]
    alpha = a[..., 3] if a.shape[-1] == 4 else np.ones(a.shape[:2], np.float32)
    bg = np.asarray(background, np.float32)
    rgb = rgb * alpha[..., None] + bg * (1 - alpha[..., None])
    return torch.from_numpy(np.ascontiguousarray(rgb)), torch.from_numpy(np.ascontiguousarray(alpha))


def load_blender(root: str | Path, split: str = "train", holdout_every: int = 8,
                 background: tuple[float, float, float] = (1.0, 1.0, 1.0), max_views: int | None = None) -> Dataset:
    """Load ``transforms_<split>.json`` and its images; every ``holdout_every``-th view (0, k, 2k, ...)
    goes to the test set (0 disables hold-out).

    Errors (:class:`DatasetError`) name the file and field: missing JSON, invalid JSON, missing
    ``camera_angle_x``/``frames``/``transform_matrix``/``file_path``, a matrix that is not 4x4, a
    missing image, images of different sizes.
    """
    root = Path(root)
    jpath = root / f"transforms_{split}.json"
    if not jpath.exists():
        raise DatasetError(f"{jpath}: file not found")
    try:
        meta = json.loads(jpath.read_text())
    except json.JSONDecodeError as e:
        raise DatasetError(f"{jpath}: invalid JSON ({e})") from None
    for key in ("camera_angle_x", "frames"):
        if key not in meta:
            raise DatasetError(f"{jpath}: missing field '{key}'")
    frames = meta["frames"]
    if not isinstance(frames, list) or not frames:
        raise DatasetError(f"{jpath}: field 'frames' must be a non-empty list")
    if max_views:
        frames = frames[:max_views]
    views: list[View] = []
    size = None
    for i, fr in enumerate(frames):
        for key in ("file_path", "transform_matrix"):
            if key not in fr:
                raise DatasetError(f"{jpath}: frames[{i}] missing field '{key}'")
        m = torch.tensor(fr["transform_matrix"], dtype=torch.float64)
        if m.shape != (4, 4) or not torch.isfinite(m).all():
            raise DatasetError(f"{jpath}: frames[{i}].transform_matrix must be a finite 4x4 matrix")
        ipath = _resolve_image(root, fr["file_path"])
        rgb, alpha = load_image(ipath, background)
        h, w = rgb.shape[:2]
        if size is None:
            size = (h, w)
        elif (h, w) != size:
            raise DatasetError(f"{ipath}: image size {w}x{h} differs from the first frame's {size[1]}x{size[0]}")
        cam = camera_from_blender(m, float(meta["camera_angle_x"]), w, h, name=Path(fr["file_path"]).name)
        views.append(View(cam, rgb, alpha, cam.name))
    test = [v for i, v in enumerate(views) if holdout_every and i % holdout_every == 0]
    train = [v for i, v in enumerate(views) if not (holdout_every and i % holdout_every == 0)]
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

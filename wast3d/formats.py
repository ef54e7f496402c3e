"""Scene files by extension: ``.ply`` (the reference 3DGS layout, SuperSplat's compressed layout, a
point cloud; :mod:`wast3d.ply`), written in the reference layout, or in the compressed one when the
name ends in ``.compressed.ply``; ``.spz``, Niantic's SPZ (:mod:`wast3d.spz`, version 4 written);
and ``.splat``, the format of the common web viewers (antimatter15/splat and those that followed it).

``.splat``: no header; 32 bytes per Gaussian, little-endian::

    x y z            float32 x 3   position
    s_0 s_1 s_2      float32 x 3   activated scales (exp of the PLY's log-scales)
    r g b a          uint8 x 4     DC colour 0.5 + C0 f_dc, and opacity sigmoid(logit), times 255
    q_w q_x q_y q_z  uint8 x 4     unit quaternion, q * 128 + 128

The format has no count: a size that is no whole number of 32-byte records is refused as truncated,
but a file cut exactly at a record's end cannot be told from a smaller scene. It keeps the
view-independent colour only: a scene with SH degree > 0 is written at degree 0 (the
log says so), colours and opacities are quantized to 1/255 (colours clamped to [0, 1]) and rotations
to 1/128. Element labels are not kept.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import torch

from .gaussians import GaussianScene, rgb_to_sh_dc
from .io_utils import FORMATS, atomic_path
from .ply import PlyError, check_writable, checked, read_ply, write_compressed_ply, write_ply

log = logging.getLogger(__name__)

SPLAT_DTYPE = np.dtype([("position", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rot", "u1", 4)])


def _format(path: Path) -> str:
    ext = path.suffix.lower()
    if ext not in FORMATS:
        raise ValueError(f"{path}: unknown scene format '{ext}' (known: {', '.join(FORMATS)})")
    return ext


def read_scene(path: str | Path, drop_invalid: bool = False) -> GaussianScene:
    """The scene a user gives in ``path``, by its extension (module docstring); one of no Gaussians is a
    PlyError."""
    from .spz import read_spz

    path = Path(path)
    ext = _format(path)
    if ext == ".splat":
        return read_splat(path, drop_invalid)
    scene = (read_spz if ext == ".spz" else read_ply)(path, drop_invalid=drop_invalid)
    if len(scene) == 0:  # a stage's own PLY may hold none; a scene a user gives is something to stylize
        raise PlyError(f"{path}: holds no Gaussians (its count is 0): not a scene to read")
    return scene


def write_scene(path: str | Path, scene: GaussianScene) -> None:
    """Write ``scene`` to ``path`` in the format its extension names, atomically."""
    from .spz import write_spz

    path = Path(path)
    ext = _format(path)
    if ext == ".splat":
        write_splat(path, scene)
    elif ext == ".spz":
        write_spz(path, scene)
    elif path.name.lower().endswith(".compressed.ply"):
        write_compressed_ply(path, scene)
    else:
        write_ply(path, scene)


def write_splat(path: str | Path, scene: GaussianScene) -> None:
    """``scene`` as a ``.splat`` file (module docstring), atomically."""
    check_writable(scene, path, ".splat")
    s = scene.detach().to(device="cpu", dtype=torch.float32)
    if s.sh_degree > 0:
        log.warning("%s: .splat keeps the DC colour only; SH degree %d dropped", path, s.sh_degree)
    rec = np.empty(len(s), dtype=SPLAT_DTYPE)
    rec["position"] = s.means.numpy()
    rec["scale"] = s.scales.numpy()
    rgba = torch.cat([s.rgb.clamp(0, 1), s.opacities[:, None]], 1)
    rec["rgba"] = (rgba * 255).round().clamp(0, 255).to(torch.uint8).numpy()
    q = s.quats / s.quats.norm(dim=1, keepdim=True)
    rec["rot"] = (q * 128 + 128).round().clamp(0, 255).to(torch.uint8).numpy()
    with atomic_path(path) as tmp:
        Path(tmp).write_bytes(rec.tobytes())


def read_splat(path: str | Path, drop_invalid: bool = False) -> GaussianScene:
    """A ``.splat`` file (module docstring); :class:`~wast3d.ply.PlyError` naming the file and the
    field for a size that is no multiple of 32 bytes, and for values unusable once decoded (NaN/inf, a
    scale <= 0, a zero quaternion: :func:`~wast3d.ply.checked`, which ``drop_invalid`` drops)."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: file not found")
    raw = path.read_bytes()
    if len(raw) == 0 or len(raw) % SPLAT_DTYPE.itemsize:
        raise PlyError(f"{path}: .splat: {len(raw)} bytes is not a whole number of {SPLAT_DTYPE.itemsize}-byte "
                       "Gaussians (truncated?)")
    rec = np.frombuffer(raw, dtype=SPLAT_DTYPE)
    q = (rec["rot"].astype(np.float32) - 128) / 128
    rgba = rec["rgba"].astype(np.float32) / 255
    eps = 0.5 / 255  # alpha 0 or 255 has no finite logit
    with np.errstate(invalid="ignore", divide="ignore"):
        scene = GaussianScene(
            means=torch.from_numpy(rec["position"].copy()),
            log_scales=torch.from_numpy(np.log(rec["scale"].astype(np.float32))),
            quats=torch.from_numpy(q),
            opacity_logits=torch.logit(torch.from_numpy(rgba[:, 3].clip(eps, 1 - eps))),
            sh_dc=rgb_to_sh_dc(torch.from_numpy(rgba[:, :3])),
            sh_rest=torch.zeros(len(rec), 0, 3),
        )
    return checked(scene, path, drop_invalid, ".splat:")

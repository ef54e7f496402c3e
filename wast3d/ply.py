"""3DGS PLY I/O in the exact layout of the reference 3DGS code (graphdeco-inria/gaussian-splatting).

Vertex properties, all float32, in this order::

    x y z nx ny nz f_dc_0 f_dc_1 f_dc_2 f_rest_0 .. f_rest_{3K-1} opacity scale_0..2 rot_0..3

with ``K = (d+1)^2 - 1`` rest coefficients per channel for SH degree d. ``f_rest`` is channel-major:
the K red coefficients first, then green, then blue (the reference stores ``features_rest`` as
[N, K, 3] and writes ``transpose(1, 2).flatten``). Values are stored before activation: log-scale,
opacity logit, unnormalized quaternion (w, x, y, z). Normals are written as zeros, as the reference.
A labelled scene (``GaussianScene.element``) gets one more property, ``element`` (int32), after them;
other readers skip it as they skip any extra property, and a scene without labels is written bit for
bit in the reference layout.

Also read, detected from the header (an element ``chunk`` and packed vertices), and written by
:func:`write_compressed_ply`: the PlayCanvas/SuperSplat compressed layout (:mod:`wast3d.ply_compressed`).

A plain point cloud (``x y z`` and optionally ``red green blue``) is read as initial Gaussians with the
reference initialization: isotropic scale = RMS distance to the 3 nearest neighbours, identity
rotation, opacity 0.1.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import torch
from plyfile import PlyData, PlyElement

from .gaussians import GaussianScene, num_sh_rest, rgb_to_sh_dc, sh_degree_from_rest
from .io_utils import atomic_path
from .ply_compressed import decode, encode, is_compressed

log = logging.getLogger(__name__)


class PlyError(ValueError):
    """A PLY file that is not a readable 3DGS or point-cloud file; the message names file and field."""


ELEMENT = "element"  # the optional label property (GaussianScene.element)


def property_names(sh_degree: int) -> list[str]:
    k = num_sh_rest(sh_degree)
    return (
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(3 * k)]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )


def scene_to_array(scene: GaussianScene) -> np.ndarray:
    """Pack a scene into the [N, P] float32 matrix of the reference layout."""
    s = scene.detach().to(device="cpu", dtype=torch.float32)
    n = len(s)
    rest = s.sh_rest.transpose(1, 2).reshape(n, 3 * s.sh_rest.shape[1])  # channel-major
    cols = [s.means, torch.zeros(n, 3), s.sh_dc, rest, s.opacity_logits[:, None], s.log_scales, s.quats]
    return torch.cat(cols, dim=1).numpy()


def write_ply(path: str | Path, scene: GaussianScene) -> None:
    """Write ``scene`` as a binary little-endian 3DGS PLY, atomically (temporary file, then rename)."""
    names = property_names(scene.sh_degree)
    arr = scene_to_array(scene)
    dtype = [(n, "<f4") for n in names]
    if scene.element is not None:
        dtype.append((ELEMENT, "<i4"))
    rec = np.empty(arr.shape[0], dtype=dtype)
    for i, n in enumerate(names):
        rec[n] = arr[:, i]
    if scene.element is not None:
        rec[ELEMENT] = scene.element.detach().cpu().numpy().astype(np.int32)
    with atomic_path(path) as tmp:
        PlyData([PlyElement.describe(rec, "vertex")], text=False, byte_order="<").write(str(tmp))


def write_compressed_ply(path: str | Path, scene: GaussianScene) -> None:
    """Write ``scene`` in SuperSplat's compressed layout (with colour ranges, SH rest as the ``sh``
    element), atomically. Quantized: positions and log-scales to 11-10-11 bits of each 256-Gaussian
    chunk's range, rotations to 10 bits per component, colour and opacity to 8 bits, SH rest to 8 bits
    of [-4, 4]; element labels are not kept."""
    s = scene.detach().to(device="cpu", dtype=torch.float32)
    rec = encode(s.means.numpy(), s.log_scales.numpy(), s.quats.numpy(), s.opacity_logits.numpy(), s.sh_dc.numpy(),
                 s.sh_rest.numpy())
    with atomic_path(path) as tmp:
        PlyData([PlyElement.describe(r, name) for name, r in rec.items()], text=False, byte_order="<").write(str(tmp))


def _read_vertex(path: Path):
    """(vertex element, its property names, the whole PlyData)."""
    if not path.exists():
        raise FileNotFoundError(f"{path}: file not found")
    try:
        ply = PlyData.read(str(path))
    except Exception as e:  # plyfile raises several types for truncated/corrupt data
        raise PlyError(f"{path}: corrupt or truncated PLY ({type(e).__name__}: {e})") from None
    if "vertex" not in ply:
        raise PlyError(f"{path}: no 'vertex' element (elements: {[el.name for el in ply.elements]})")
    v = ply["vertex"]
    return v, [p.name for p in v.properties], ply


def _column(v, path: Path, name: str) -> np.ndarray:
    try:
        return np.asarray(v[name], dtype=np.float64 if v[name].dtype == np.float64 else np.float32)
    except (KeyError, ValueError):
        raise PlyError(f"{path}: missing property '{name}'") from None


def is_gaussian_ply(path: str | Path) -> bool:
    _, names, _ = _read_vertex(Path(path))
    return "opacity" in names or "f_dc_0" in names or "packed_position" in names


def read_ply(path: str | Path, drop_invalid: bool = False) -> GaussianScene:
    """Read a 3DGS PLY, or a plain point cloud as initial Gaussians.

    Raises :class:`PlyError` naming the file and the property for: a truncated or corrupt file, a
    missing property, a count of ``f_rest_*`` that is no SH degree (or has gaps), and NaN/inf values.
    With ``drop_invalid=True`` rows with NaN/inf are dropped instead and the count is logged.
    """
    path = Path(path)
    v, names, ply = _read_vertex(path)
    if is_compressed(ply):
        return _read_compressed(path, ply)
    gaussian_markers = {"opacity", "f_dc_0", "scale_0", "rot_0"}
    if not gaussian_markers & set(names):
        return _read_point_cloud(path, v, names, drop_invalid)

    rest_idx = sorted(int(n[7:]) for n in names if n.startswith("f_rest_") and n[7:].isdigit())
    if rest_idx != list(range(len(rest_idx))):
        missing = sorted(set(range(max(rest_idx) + 1)) - set(rest_idx))
        raise PlyError(f"{path}: f_rest properties have gaps (missing f_rest_{missing[0]})")
    if len(rest_idx) % 3:
        raise PlyError(f"{path}: property f_rest_*: {len(rest_idx)} values is not a multiple of 3 channels")
    try:
        degree = sh_degree_from_rest(len(rest_idx) // 3)
    except ValueError as e:
        raise PlyError(f"{path}: property f_rest_*: {len(rest_idx)} values; {e}") from None

    groups = {
        "means": ["x", "y", "z"],
        "sh_dc": ["f_dc_0", "f_dc_1", "f_dc_2"],
        "rest": [f"f_rest_{i}" for i in rest_idx],
        "opacity_logits": ["opacity"],
        "log_scales": ["scale_0", "scale_1", "scale_2"],
        "quats": ["rot_0", "rot_1", "rot_2", "rot_3"],
    }
    cols = {}
    n = v.count
    valid = np.ones(n, dtype=bool)
    for g, props in groups.items():
        arrs = [_column(v, path, p) for p in props]
        a = np.stack(arrs, axis=1) if arrs else np.zeros((n, 0), np.float32)
        bad = ~np.isfinite(a)
        if bad.any():
            rows, c = np.nonzero(bad)
            if not drop_invalid:
                raise PlyError(
                    f"{path}: property '{props[c[0]]}' has {int(bad.any(1).sum())} rows with NaN/inf "
                    f"(first at vertex {rows[0]}); pass drop_invalid / --drop-invalid to drop them"
                )
            valid &= ~bad.any(1)
        cols[g] = a
    k = num_sh_rest(degree)
    t = lambda a: torch.from_numpy(np.ascontiguousarray(a[valid]))  # noqa: E731
    scene = GaussianScene(
        means=t(cols["means"]),
        log_scales=t(cols["log_scales"]),
        quats=t(cols["quats"]),
        opacity_logits=t(cols["opacity_logits"])[:, 0].contiguous(),
        sh_dc=t(cols["sh_dc"]),
        sh_rest=t(cols["rest"]).reshape(int(valid.sum()), 3, k).transpose(1, 2).contiguous(),
    )
    if ELEMENT in names:
        el = np.asarray(v[ELEMENT])
        if not np.issubdtype(el.dtype, np.integer):
            raise PlyError(f"{path}: property '{ELEMENT}' must be an integer type, got {el.dtype}")
        if (el < 0).any():
            raise PlyError(f"{path}: property '{ELEMENT}': {int((el < 0).sum())} negative labels (0 is the ground)")
        scene.element = torch.from_numpy(el[valid].astype(np.int64))
    if (~valid).any():
        log.warning("%s: dropped %d of %d Gaussians with NaN/inf values", path, int((~valid).sum()), n)
    qn = scene.quats.norm(dim=-1)
    if (qn == 0).any():
        raise PlyError(f"{path}: property 'rot_*': {int((qn == 0).sum())} zero quaternions")
    return scene


def _read_compressed(path: Path, ply) -> GaussianScene:
    try:
        d = decode(ply)
    except ValueError as e:
        raise PlyError(f"{path}: compressed PLY: {e}") from None
    info = d.pop("info")
    log.info("%s: PlayCanvas/SuperSplat compressed layout: %d Gaussians in %d chunks, colour ranges %s, "
             "SH rest %d per channel", path, len(d["means"]), info["chunks"], "yes" if info["colour_ranges"] else "no",
             info["sh_rest"])
    return GaussianScene(**{k: torch.from_numpy(a) for k, a in d.items()})


def _read_point_cloud(path: Path, v, names: list[str], drop_invalid: bool) -> GaussianScene:
    xyz = np.stack([_column(v, path, p) for p in ("x", "y", "z")], 1).astype(np.float32)
    if all(c in names for c in ("red", "green", "blue")):
        rgb = np.stack([np.asarray(v[c]) for c in ("red", "green", "blue")], 1)
        rgb = rgb.astype(np.float32) / (255.0 if np.issubdtype(rgb.dtype, np.integer) else 1.0)
    else:
        rgb = np.full_like(xyz, 0.5)
    valid = np.isfinite(xyz).all(1) & np.isfinite(rgb).all(1)
    if not valid.all():
        if not drop_invalid:
            raise PlyError(f"{path}: property 'x/y/z': {int((~valid).sum())} points with NaN/inf; "
                           "pass drop_invalid / --drop-invalid to drop them")
        log.warning("%s: dropped %d of %d points with NaN/inf values", path, int((~valid).sum()), len(xyz))
        xyz, rgb = xyz[valid], rgb[valid]
    return init_from_points(torch.from_numpy(xyz), torch.from_numpy(rgb))


def init_from_points(xyz: torch.Tensor, rgb: torch.Tensor | None = None, opacity: float = 0.1) -> GaussianScene:
    """Initial Gaussians on points (reference 3DGS init): scale = RMS distance to 3 nearest neighbours.

    xyz: [N, 3]; rgb: [N, 3] in [0, 1] or None (grey).
    """
    from .geometry import knn_mean_sq_dist  # local import keeps ply importable without scipy at import time

    d2 = knn_mean_sq_dist(xyz, k=3).clamp_min(1e-7)
    scales = d2.sqrt()[:, None].expand(-1, 3)
    if rgb is None:
        rgb = torch.full_like(xyz, 0.5)
    return GaussianScene.from_activated(xyz.float(), scales.float(), opacities=opacity, rgb=rgb.float().clamp(0, 1))


__all__ = ["PlyError", "read_ply", "write_ply", "write_compressed_ply", "init_from_points", "property_names", "is_gaussian_ply",
           "rgb_to_sh_dc"]

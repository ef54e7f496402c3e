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

# What every reader checks after decoding, whatever the format: the field as a user knows it, the
# values as the renderer uses them (a log-scale of 1000 is finite in the file and infinite as a scale).
FIELDS = (
    ("position", lambda s: s.means),
    ("scale", lambda s: s.scales),
    ("rotation", lambda s: s.quats),
    ("opacity", lambda s: s.opacity_logits[:, None]),
    ("colour (f_dc)", lambda s: s.sh_dc),
    ("SH rest (f_rest)", lambda s: s.sh_rest.flatten(1)),
)


def _bad_rows(scene: GaussianScene) -> dict[str, torch.Tensor]:
    """Field -> [N] bool, the Gaussians whose decoded values in that field are unusable: NaN or
    infinite, a scale that is not positive, a quaternion of length 0."""
    out = {}
    for name, get in FIELDS:
        v = get(scene)
        bad = ~torch.isfinite(v).all(1)
        if name == "scale":
            bad |= (v <= 0).any(1)
        elif name == "rotation":
            bad |= v.norm(dim=1) == 0
        out[name] = bad
    return out


def checked(scene: GaussianScene, path: str | Path, drop_invalid: bool = False, what: str = "") -> GaussianScene:
    """The one rule of every reader: a Gaussian with an unusable value (:func:`_bad_rows`) is a
    :class:`PlyError` naming the file, the field and the first row, or, with ``drop_invalid``, dropped
    (the count is logged); none left is an error."""
    fmt = f"{what} " if what else ""
    drop = torch.zeros(len(scene), dtype=torch.bool)
    for name, bad in _bad_rows(scene).items():
        if not bad.any():
            continue
        if not drop_invalid:
            row = int(bad.nonzero()[0, 0])
            raise PlyError(f"{path}: {fmt}field '{name}': {int(bad.sum())} Gaussians with values that are NaN, "
                           f"infinite{' or not positive' if name == 'scale' else ''}"
                           f"{' or of length 0' if name == 'rotation' else ''} once decoded (first at row {row}); "
                           "--drop-invalid drops them")
        log.warning("%s: dropped %d Gaussians with an unusable '%s'", path, int(bad.sum()), name)
        drop |= bad
    if drop.any():
        log.warning("%s: dropped %d of %d Gaussians in all (--drop-invalid)", path, int(drop.sum()), len(scene))
        scene = scene.subset(~drop)
        if len(scene) == 0:
            raise PlyError(f"{path}: {fmt}no Gaussians left")
    return scene


def check_writable(scene: GaussianScene, path: str | Path, what: str, dtype=torch.float32, empty: bool = False) -> None:
    """A writer refuses what its format cannot hold: a value that is not finite in ``dtype`` (3e38 x 10
    in a float32 file), named by field and row, as :func:`checked` names them when reading; and a scene
    of no Gaussians unless ``empty`` (a stage's PLY may hold none; the exchange formats may not)."""
    if len(scene) == 0 and not empty:
        raise ValueError(f"{path}: {what} holds at least one Gaussian; this scene has none")
    s = scene.detach().to(device="cpu", dtype=dtype) if dtype is not None else scene
    for name, bad in _bad_rows(s).items():
        if bad.any():
            raise ValueError(f"{path}: {what} cannot hold field '{name}' of {int(bad.sum())} Gaussians (NaN, infinite "
                             f"or beyond {str(dtype).replace('torch.', '')}; first at row {int(bad.nonzero()[0, 0])})")


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
    check_writable(scene, path, "a PLY", empty=True)
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
    check_writable(scene, path, "a compressed PLY")
    s = scene.detach().to(device="cpu", dtype=torch.float32)
    rec = encode(s.means.numpy(), s.log_scales.numpy(), s.quats.numpy(), s.opacity_logits.numpy(), s.sh_dc.numpy(),
                 s.sh_rest.numpy())
    with atomic_path(path) as tmp:
        PlyData([PlyElement.describe(r, name) for name, r in rec.items()], text=False, byte_order="<").write(str(tmp))


MAX_HEADER = 1 << 20  # a 3DGS PLY's header is a few kilobytes; plyfile would read any length line by line


def _header_length(path: Path) -> int:
    """The bytes of ``path``'s header up to its data; a PlyError when no ``end_header`` line ends within
    MAX_HEADER bytes (or the file is not a PLY)."""
    with open(path, "rb") as f:
        head = f.read(MAX_HEADER + 16)
    if not head.startswith(b"ply"):
        raise PlyError(f"{path}: not a PLY file (it does not start with 'ply')")
    at = head.find(b"end_header")
    if at < 0 or at > MAX_HEADER:
        raise PlyError(f"{path}: no 'end_header' within the first {MAX_HEADER >> 20} MiB: "
                       + ("the header is longer than any scene's (a huge comment?)" if len(head) > MAX_HEADER else
                          "truncated inside its header"))
    start = at + len(b"end_header")
    return start + (2 if head[start:start + 2] == b"\r\n" else 1)


def _read_vertex(path: Path):
    """(vertex element, its property names, the whole PlyData)."""
    if not path.exists():
        raise FileNotFoundError(f"{path}: file not found")
    if not path.is_file():
        raise PlyError(f"{path}: not a file")
    head = _header_length(path)
    try:
        ply = PlyData.read(str(path))
    except Exception as e:  # plyfile raises several types for truncated/corrupt data
        raise PlyError(f"{path}: corrupt or truncated PLY ({type(e).__name__}: {e})") from None
    if "vertex" not in ply:
        raise PlyError(f"{path}: no 'vertex' element (elements: {[el.name for el in ply.elements]})")
    _check_length(path, ply, head)
    v = ply["vertex"]
    return v, [p.name for p in v.properties], ply


def _check_length(path: Path, ply, head: int) -> None:
    """A binary PLY's data must be exactly what its header's counts say: more bytes are rows the header
    does not count (a reader would drop them without a word), fewer a truncated file. An element with
    list properties (a mesh's faces) counts each row's lists as read. ``head``: the header's bytes."""
    from plyfile import PlyListProperty

    if ply.text:
        return
    data = path.stat().st_size - head
    expect = 0
    for el in ply.elements:
        lists = [p for p in el.properties if isinstance(p, PlyListProperty)]
        fixed = sum(np.dtype(p.dtype()).itemsize for p in el.properties if not isinstance(p, PlyListProperty))
        expect += el.count * fixed
        for p in lists:
            lengths = np.fromiter((len(r) for r in el.data[p.name]), np.int64, el.count)
            expect += el.count * np.dtype(p.list_dtype()[0]).itemsize + int(lengths.sum()) * np.dtype(p.list_dtype()[1]).itemsize
    if data != expect:
        counts = ", ".join(f"'{el.name}' {el.count} rows" for el in ply.elements)
        raise PlyError(f"{path}: the header's element counts ({counts}) describe {expect} bytes of data, the file holds "
                       f"{data}: {'more rows than the header counts' if data > expect else 'truncated'}")


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

    Raises :class:`PlyError` naming the file and the property for: a truncated or corrupt file, data
    longer than the header's counts, a missing property, a count of ``f_rest_*`` that is no SH degree
    (or has gaps), and values unusable once decoded (:func:`checked`; ``drop_invalid=True`` drops those
    Gaussians instead and logs the count).
    """
    path = Path(path)
    v, names, ply = _read_vertex(path)
    if is_compressed(ply):
        return _read_compressed(path, ply, drop_invalid)
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
    cols = {g: np.stack([_column(v, path, p) for p in props], axis=1) if props else np.zeros((v.count, 0), np.float32)
            for g, props in groups.items()}
    n, k = v.count, num_sh_rest(degree)
    t = lambda a: torch.from_numpy(np.ascontiguousarray(a))  # noqa: E731
    scene = GaussianScene(
        means=t(cols["means"]),
        log_scales=t(cols["log_scales"]),
        quats=t(cols["quats"]),
        opacity_logits=t(cols["opacity_logits"])[:, 0].contiguous(),
        sh_dc=t(cols["sh_dc"]),
        sh_rest=t(cols["rest"]).reshape(n, 3, k).transpose(1, 2).contiguous(),
    )
    if ELEMENT in names:
        el = np.asarray(v[ELEMENT])
        if not np.issubdtype(el.dtype, np.integer):
            raise PlyError(f"{path}: property '{ELEMENT}' must be an integer type, got {el.dtype}")
        if (el < 0).any():
            raise PlyError(f"{path}: property '{ELEMENT}': {int((el < 0).sum())} negative labels (0 is the ground)")
        scene.element = torch.from_numpy(el.astype(np.int64))
    return checked(scene, path, drop_invalid)


def _read_compressed(path: Path, ply, drop_invalid: bool = False) -> GaussianScene:
    try:
        d = decode(ply)
    except ValueError as e:
        raise PlyError(f"{path}: compressed PLY: {e}") from None
    info = d.pop("info")
    log.info("%s: PlayCanvas/SuperSplat compressed layout: %d Gaussians in %d chunks, colour ranges %s, "
             "SH rest %d per channel", path, len(d["means"]), info["chunks"], "yes" if info["colour_ranges"] else "no",
             info["sh_rest"])
    return checked(GaussianScene(**{k: torch.from_numpy(a) for k, a in d.items()}), path, drop_invalid, "compressed PLY:")


def _read_point_cloud(path: Path, v, names: list[str], drop_invalid: bool) -> GaussianScene:
    if v.count == 0:
        return GaussianScene.empty()
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

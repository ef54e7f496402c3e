"""The PlayCanvas / SuperSplat compressed PLY layout, decoded to the reference parameters and encoded
from them (:func:`encode`, with colour ranges and the ``sh`` element when the scene has SH rest).

Layout (detected from the header: an element ``chunk`` and a ``vertex`` element of packed ``uint``):

- ``chunk``: one row per 256 consecutive Gaussians, float32 ``min_x min_y min_z max_x max_y max_z``,
  ``min_scale_x .. max_scale_z`` (log-scales), and in newer files also ``min_r min_g min_b max_r max_g
  max_b`` (colour ranges; 18 properties instead of 12);
- ``vertex``: four uint32 per Gaussian:

  - ``packed_position``: x, y, z as 11, 10, 11 bits (x in the top bits), each ``u / (2^bits - 1)``,
    then ``lerp(chunk min, chunk max, u)``;
  - ``packed_rotation``: 2 bits (the index, in ``rot_0 .. rot_3`` order, of the component of largest
    magnitude, made positive), then the other three in order as 10 bits each,
    ``(u - 0.5) * sqrt(2)`` (they lie in ``[-1/sqrt(2), 1/sqrt(2)]``); the largest is
    ``sqrt(1 - a^2 - b^2 - c^2)``. ``rot_0 .. rot_3`` are the reference (w, x, y, z);
  - ``packed_scale``: 11-10-11 bits as positions, lerp between the chunk's log-scale bounds;
  - ``packed_color``: r, g, b, opacity as 8 bits each (r in the top byte); with colour ranges the
    colour is ``lerp(chunk min, chunk max, u)``; ``f_dc = (colour - 0.5) / SH_C0`` and the opacity
    logit is ``log(a / (1 - a))`` (clamped to +-40 at a = 1 or 0);
- ``sh`` (optional): ``f_rest_0 .. f_rest_{3K-1}`` as uchar, ``u * 8 / 255 - 4``, channel-major like
  the reference layout, K = 3, 8 or 15.

:func:`decode` checks the header and the values and raises ``ValueError`` naming the element and the
property; :func:`wast3d.ply.read_ply` adds the file name.
"""

from __future__ import annotations

import math

import numpy as np

from .gaussians import rgb_to_sh_dc
from .sh import SH_C0

CHUNK = 256
CHUNK_BOUNDS = ("min_x", "min_y", "min_z", "max_x", "max_y", "max_z",
                "min_scale_x", "min_scale_y", "min_scale_z", "max_scale_x", "max_scale_y", "max_scale_z")
CHUNK_COLOUR = ("min_r", "min_g", "min_b", "max_r", "max_g", "max_b")
PACKED = ("packed_position", "packed_rotation", "packed_scale", "packed_color")


def is_compressed(ply) -> bool:
    """True for a PlyData in the compressed layout (a ``chunk`` element and packed vertices)."""
    names = {el.name for el in ply.elements}
    return "chunk" in names and "vertex" in names and "packed_position" in [p.name for p in ply["vertex"].properties]


def unpack_unorm(v: np.ndarray, shift: int, bits: int) -> np.ndarray:
    return ((v >> np.uint32(shift)) & np.uint32((1 << bits) - 1)).astype(np.float64) / ((1 << bits) - 1)


def unpack_111011(v: np.ndarray) -> np.ndarray:
    """[N] uint32 -> [N, 3] in [0, 1] (11, 10, 11 bits)."""
    return np.stack([unpack_unorm(v, 21, 11), unpack_unorm(v, 11, 10), unpack_unorm(v, 0, 11)], axis=1)


def unpack_8888(v: np.ndarray) -> np.ndarray:
    """[N] uint32 -> [N, 4] in [0, 1] (8 bits each, first component in the top byte)."""
    return np.stack([unpack_unorm(v, s, 8) for s in (24, 16, 8, 0)], axis=1)


def unpack_rotation(v: np.ndarray) -> np.ndarray:
    """[N] uint32 "smallest three" -> [N, 4] unit quaternions in ``rot_0 .. rot_3`` order (w, x, y, z)."""
    abc = np.stack([(unpack_unorm(v, s, 10) - 0.5) * math.sqrt(2.0) for s in (20, 10, 0)], axis=1)
    m = np.sqrt(np.clip(1.0 - (abc ** 2).sum(1), 0.0, None))
    largest = (v >> np.uint32(30)).astype(np.int64)
    q = np.empty((len(v), 4))
    for k in range(4):
        rows = largest == k
        others = [j for j in range(4) if j != k]
        q[rows, k] = m[rows]
        q[np.ix_(rows, others)] = abc[rows]
    return q


def _columns(element, names, what: str) -> np.ndarray:
    have = [p.name for p in element.properties]
    for n in names:
        if n not in have:
            raise ValueError(f"element '{element.name}' has no property '{n}' ({what})")
    return np.stack([np.asarray(element[n]) for n in names], axis=1)


def decode(ply) -> dict[str, np.ndarray]:
    """Compressed PlyData -> float32 arrays ``means`` [N,3], ``log_scales`` [N,3], ``quats`` [N,4],
    ``opacity_logits`` [N], ``sh_dc`` [N,3], ``sh_rest`` [N,K,3], and ``info`` (layout facts)."""
    chunk, vert = ply["chunk"], ply["vertex"]
    n = vert.count
    packed = _columns(vert, PACKED, "packed Gaussians")
    for j, name in enumerate(PACKED):
        if packed[:, j].dtype not in (np.uint32, np.int32):
            raise ValueError(f"element 'vertex' property '{name}' is {packed[:, j].dtype}, expected uint32")
    packed = packed.astype(np.uint32)
    if chunk.count != math.ceil(n / CHUNK):
        raise ValueError(f"element 'chunk' has {chunk.count} rows for {n} Gaussians (expected {math.ceil(n / CHUNK)})")
    bounds = _columns(chunk, CHUNK_BOUNDS, "chunk bounds").astype(np.float64)
    chunk_names = [p.name for p in chunk.properties]
    colour_ranges = all(c in chunk_names for c in CHUNK_COLOUR)
    ranges = _columns(chunk, CHUNK_COLOUR, "colour ranges").astype(np.float64) if colour_ranges else None
    for arr, names in ((bounds, CHUNK_BOUNDS), (ranges, CHUNK_COLOUR)):
        if arr is not None and not np.isfinite(arr).all():
            r, c = np.argwhere(~np.isfinite(arr))[0]
            raise ValueError(f"element 'chunk' property '{names[c]}' is NaN/inf (chunk {r})")
    ci = np.arange(n) // CHUNK
    b = bounds[ci]

    def lerp(lo, hi, u):
        return lo * (1 - u) + hi * u

    means = lerp(b[:, 0:3], b[:, 3:6], unpack_111011(packed[:, 0]))
    log_scales = lerp(b[:, 6:9], b[:, 9:12], unpack_111011(packed[:, 2]))
    quats = unpack_rotation(packed[:, 1])
    rgba = unpack_8888(packed[:, 3])
    rgb = lerp(ranges[ci, 0:3], ranges[ci, 3:6], rgba[:, :3]) if colour_ranges else rgba[:, :3]
    a = rgba[:, 3]
    with np.errstate(divide="ignore"):
        opacity = np.where(a <= 0, -40.0, np.where(a >= 1, 40.0, np.log(a / np.clip(1 - a, 1e-12, None))))
    sh_rest = np.zeros((n, 0, 3))
    if "sh" in {el.name for el in ply.elements}:
        sh = ply["sh"]
        names = [p.name for p in sh.properties]
        if sh.count != n:
            raise ValueError(f"element 'sh' has {sh.count} rows for {n} Gaussians")
        if len(names) not in (9, 24, 45):
            raise ValueError(f"element 'sh' has {len(names)} properties; expected 9, 24 or 45 (SH degree 1-3)")
        vals = _columns(sh, [f"f_rest_{i}" for i in range(len(names))], "SH coefficients").astype(np.float64)
        k = len(names) // 3
        sh_rest = (vals * (8.0 / 255.0) - 4.0).reshape(n, 3, k).transpose(0, 2, 1)
    f32 = lambda x: np.ascontiguousarray(x, dtype=np.float32)  # noqa: E731
    return {
        "means": f32(means), "log_scales": f32(log_scales), "quats": f32(quats),
        "opacity_logits": f32(opacity), "sh_dc": f32(rgb_to_sh_dc(rgb)), "sh_rest": f32(sh_rest),
        "info": {"chunks": chunk.count, "colour_ranges": colour_ranges, "sh_rest": sh_rest.shape[1]},
    }


def pack_unorm(x: np.ndarray, bits: int) -> np.ndarray:
    """Values in [0, 1] -> nearest of the 2^bits levels (uint32), the inverse of :func:`unpack_unorm`."""
    t = (1 << bits) - 1
    return np.clip(np.floor(x * t + 0.5), 0, t).astype(np.uint32)


def pack_111011(u: np.ndarray) -> np.ndarray:
    """[N, 3] in [0, 1] -> [N] uint32 (11, 10, 11 bits)."""
    return pack_unorm(u[:, 0], 11) << np.uint32(21) | pack_unorm(u[:, 1], 10) << np.uint32(11) | pack_unorm(u[:, 2], 11)


def pack_rotation(q: np.ndarray) -> np.ndarray:
    """[N, 4] quaternions (w, x, y, z) -> [N] uint32 "smallest three" (:func:`unpack_rotation`)."""
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    big = np.abs(q).argmax(1)
    q = q * np.sign(q[np.arange(len(q)), big])[:, None]
    word = big.astype(np.uint32)
    for j in range(3):  # the other three components, in order
        idx = np.where(np.arange(3)[None, :] >= big[:, None], np.arange(1, 4)[None, :], np.arange(3)[None, :])[:, j]
        word = word << np.uint32(10) | pack_unorm(q[np.arange(len(q)), idx] / math.sqrt(2.0) + 0.5, 10)
    return word


def encode(means: np.ndarray, log_scales: np.ndarray, quats: np.ndarray, opacity_logits: np.ndarray,
           sh_dc: np.ndarray, sh_rest: np.ndarray) -> dict[str, np.ndarray]:
    """The reference parameters (float arrays [N, 3], [N, 3], [N, 4], [N], [N, 3], [N, K, 3]) -> the
    records of the ``chunk``, ``vertex`` and (K > 0) ``sh`` elements (the module docstring's layout,
    with colour ranges). Each chunk's bounds are its Gaussians' own minima and maxima."""
    n = len(means)
    if n == 0:
        raise ValueError("compressed PLY: no Gaussians to encode")
    nch = math.ceil(n / CHUNK)
    ci = np.arange(n) // CHUNK
    rgb = 0.5 + SH_C0 * sh_dc.astype(np.float64)
    chunk = np.zeros(nch, dtype=[(k, "<f4") for k in CHUNK_BOUNDS + CHUNK_COLOUR])
    unit = []
    for a, lo_names, hi_names in ((means, CHUNK_BOUNDS[0:3], CHUNK_BOUNDS[3:6]), (log_scales, CHUNK_BOUNDS[6:9], CHUNK_BOUNDS[9:12]),
                                  (rgb, CHUNK_COLOUR[0:3], CHUNK_COLOUR[3:6])):
        a = a.astype(np.float64)
        lo = np.stack([np.minimum.reduceat(a[:, j], np.arange(0, n, CHUNK)) for j in range(3)], 1)
        hi = np.stack([np.maximum.reduceat(a[:, j], np.arange(0, n, CHUNK)) for j in range(3)], 1)
        for j in range(3):
            chunk[lo_names[j]], chunk[hi_names[j]] = lo[:, j], hi[:, j]
        lo, hi = lo.astype(np.float32).astype(np.float64)[ci], hi.astype(np.float32).astype(np.float64)[ci]
        unit.append(np.clip((a - lo) / np.where(hi > lo, hi - lo, 1.0), 0, 1))
    opacity = 1 / (1 + np.exp(-opacity_logits.astype(np.float64)))
    vertex = np.empty(n, dtype=[(k, "<u4") for k in PACKED])
    vertex["packed_position"] = pack_111011(unit[0])
    vertex["packed_rotation"] = pack_rotation(quats.astype(np.float64))
    vertex["packed_scale"] = pack_111011(unit[1])
    vertex["packed_color"] = (pack_unorm(unit[2][:, 0], 8) << np.uint32(24) | pack_unorm(unit[2][:, 1], 8) << np.uint32(16)
                              | pack_unorm(unit[2][:, 2], 8) << np.uint32(8) | pack_unorm(opacity, 8))
    out = {"chunk": chunk, "vertex": vertex}
    if sh_rest.shape[1]:
        rest = sh_rest.astype(np.float64).transpose(0, 2, 1).reshape(n, -1)  # channel-major
        sh = np.empty(n, dtype=[(f"f_rest_{i}", "u1") for i in range(rest.shape[1])])
        for i in range(rest.shape[1]):
            sh[f"f_rest_{i}"] = pack_unorm((rest[:, i] + 4) / 8, 8)
        out["sh"] = sh
    return out

"""Niantic's SPZ (Scaniverse and many web viewers), read and written in NumPy after the reference
library (github.com/nianticlabs/spz, ``src/cc/load-spz.cc``); no maintained Python package on the
registries reads it (gsply needs Numba; the ``spz`` on PyPI is another project).

Layout. Versions 1-3: one gzip stream of a 16-byte header (magic ``NGSP`` = 0x5053474e, version,
point count: uint32; SH degree, fractional bits, flags, reserved: uint8) and six attribute arrays.
Version 4: a 32-byte header (the same fields, then the stream count uint8, the table's byte offset
uint32, 12 reserved bytes), optional extensions, a table of (compressed, uncompressed) uint64 sizes,
and one Zstandard stream per non-empty array. The arrays, per Gaussian, in this order:

- positions: 3 x 24-bit signed fixed point, little-endian, ``fractional_bits`` (12 when written:
  1/4096 of a unit, a range of +-2048 units);
- alphas: ``round(sigmoid(opacity_logit) * 255)``;
- colours: ``round(f_dc * 0.15 * 255 + 127.5)`` (the DC coefficient, a little beyond [0, 1] fits);
- scales: ``round((log_scale + 10) * 16)`` (log-scales -10 .. 5.9 in steps of 1/16; beyond: clamped,
  with a warning);
- rotations: version 3+ "smallest three" (2 bits: the largest component's index; the other three
  as sign + 9 bits of |q| / sqrt(1/2)); version 2: x, y, z as ``round(q * 127.5 + 127.5)``, w >= 0;
- SH rest: [K, 3] coefficient-major, ``round(c * 128) + 128`` rounded to buckets of 8 (degree 1)
  and 16 (degrees 2-3) when written, as the reference does.

Coordinates: SPZ stores Right-Up-Back; our scenes (the reference 3DGS PLY) are Right-Down-Front.
Both ways, positions take (x, -y, -z), quaternions (w, x, -y, -z), and the SH coefficients the signs
of the reference's ``flipSh`` for y = z = -1. An alpha of 0 or 255 (no finite logit) reads as 0.25 / 255
from 0 or 1 (and is written back as it was); degree-4 SH is read to degree 3 (the log says so); element labels are not kept.
"""

from __future__ import annotations

import gzip
import logging
import struct
import zlib
from pathlib import Path

import numpy as np
import torch

from .gaussians import GaussianScene
from .io_utils import atomic_path, memory_available
from .ply import PlyError, check_writable, checked

log = logging.getLogger(__name__)

MAGIC = 0x5053474E
COLOR_SCALE = 0.15
FRACTIONAL_BITS = 12
VERSIONS = (2, 3, 4)  # written; read: 1 (float16 positions) .. 4
SH_DIM = {0: 0, 1: 3, 2: 8, 3: 15, 4: 24}
LEGACY_HEADER = struct.Struct("<IIIBBBB")  # 16 bytes
HEADER = struct.Struct("<IIIBBBBI12x")  # 32 bytes
FLAG_ANTIALIASED, FLAG_EXTENSIONS = 0x1, 0x2
# RDF <-> RUB (x kept, y and z negated): the reference's flipSh for the 15 coefficients of degrees 1-3
_x, _y, _z = 1.0, -1.0, -1.0
SH_FLIP = np.array([_y, _z, _x, _x * _y, _y * _z, 1, _x * _z, 1, _y, _x * _y * _z, _y, _z, _x, _z, _x], np.float32)
POS_FLIP = np.array([_x, _y, _z], np.float32)
QUAT_FLIP = np.array([1.0, _y * _z, _x * _z, _x * _y], np.float32)  # w, x, y, z
SQRT1_2 = np.float32(0.7071067811865476)
STEP = 1 << 24  # decompression goes in steps of at most this many bytes
EXTENSIONS_MAX = 1 << 20  # bytes a version 1-3 stream may hold beyond its arrays (extensions); more is refused
DECODED_BYTES = 4 * (3 + 3 + 4 + 1 + 3) * 3  # float32 bytes per Gaussian while decoding (arrays and temporaries)


def _round(x: np.ndarray) -> np.ndarray:
    """Half away from zero, as C++ ``std::round`` (NumPy's ``round`` goes to even)."""
    return np.sign(x) * np.floor(np.abs(x) + 0.5)


def _u8(x: np.ndarray) -> np.ndarray:
    return np.clip(_round(x), 0, 255).astype(np.uint8)


# ---- packing (pure, arrays in and out) -----------------------------------------------------------


def pack_positions(p: np.ndarray, bits: int = FRACTIONAL_BITS) -> np.ndarray:
    """[N, 3] float positions (already in SPZ axes) -> [N * 9] uint8: 24-bit fixed point, little-endian."""
    f = _round(p.astype(np.float64) * (1 << bits))
    out = ~(np.abs(f) < 1 << 23)  # NaN too; tested before the cast to int, which would wrap 3e38 to anything
    if out.any():
        row = int(np.argwhere(out)[0, 0])
        raise ValueError(f"SPZ: field 'position': {int(out.any(1).sum())} Gaussians beyond +-{(1 << 23) / (1 << bits):g} "
                         f"units do not fit its 24-bit fixed point (first at row {row}: {p[row].tolist()})")
    q = f.astype(np.int32).reshape(-1).view(np.uint32)
    return np.stack([q & 0xFF, (q >> 8) & 0xFF, (q >> 16) & 0xFF], 1).astype(np.uint8).reshape(-1)


def unpack_positions(b: np.ndarray, n: int, bits: int) -> np.ndarray:
    """[N * 9] uint8 -> [N, 3] float32 (sign-extended 24-bit fixed point)."""
    b = b.reshape(n * 3, 3).astype(np.int32)
    v = b[:, 0] | (b[:, 1] << 8) | (b[:, 2] << 16)
    v = np.where(v & 0x800000, v - (1 << 24), v)
    return (v.astype(np.float32) / np.float32(1 << bits)).reshape(n, 3)


def pack_quats_smallest_three(q: np.ndarray) -> np.ndarray:
    """[N, 4] unit quaternions (x, y, z, w) -> [N * 4] uint8 (the reference's smallest-three code)."""
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    n = len(q)
    big = np.abs(q).argmax(1)
    neg = q[np.arange(n), big] < 0
    comp = big.astype(np.uint32)
    for i in range(4):
        keep = big != i
        negbit = ((q[:, i] < 0) ^ neg).astype(np.uint32)
        mag = np.floor(511.0 * np.abs(q[:, i]) / SQRT1_2 + 0.5).astype(np.uint32)
        comp = np.where(keep, (comp << 10) | (negbit << 9) | np.minimum(mag, 511), comp)
    return comp.astype("<u4").view(np.uint8)


def unpack_quats_smallest_three(b: np.ndarray, n: int) -> np.ndarray:
    """[N * 4] uint8 -> [N, 4] (x, y, z, w)."""
    comp = b.reshape(n, 4).copy().view("<u4").reshape(n).astype(np.uint32)
    big = (comp >> 30).astype(np.int64)
    out = np.zeros((n, 4), np.float32)
    for i in (3, 2, 1, 0):
        keep = big != i
        mag = (comp & 511).astype(np.float32)
        sign = np.where((comp >> 9) & 1, -1.0, 1.0).astype(np.float32)
        out[:, i] = np.where(keep, sign * SQRT1_2 * mag / 511.0, 0.0)
        comp = np.where(keep, comp >> 10, comp)
    out[np.arange(n), big] = np.sqrt(np.clip(1.0 - (out**2).sum(1), 0.0, None))
    return out


def pack_quats_first_three(q: np.ndarray) -> np.ndarray:
    """Version 2: [N, 4] (x, y, z, w) -> [N * 3] uint8 of x, y, z with w made >= 0."""
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    q = np.where(q[:, 3:] < 0, -q, q)
    return _u8(q[:, :3] * 127.5 + 127.5).reshape(-1)


def unpack_quats_first_three(b: np.ndarray, n: int) -> np.ndarray:
    xyz = b.reshape(n, 3).astype(np.float32) / 127.5 - 1.0
    return np.concatenate([xyz, np.sqrt(np.clip(1.0 - (xyz**2).sum(1, keepdims=True), 0.0, None))], 1)


def quantize_sh(c: np.ndarray, bits: int) -> np.ndarray:
    """SH coefficients -> uint8 ``round(c * 128) + 128``, rounded to buckets of 2^(8 - bits)."""
    q = _round(c * 128.0).astype(np.int64) + 128
    bucket = 1 << (8 - bits)
    q = (q + bucket // 2) // bucket * bucket
    return np.clip(q, 0, 255).astype(np.uint8)


# ---- files ---------------------------------------------------------------------------------------


def write_spz(path: str | Path, scene: GaussianScene, version: int = 4) -> None:
    """``scene`` as an SPZ file of ``version`` (4: Zstandard streams; 2, 3: one gzip stream), atomically."""
    path = Path(path)
    if version not in VERSIONS:
        raise ValueError(f"{path}: SPZ version {version} is not written (known: {', '.join(map(str, VERSIONS))})")
    check_writable(scene, path, "SPZ")
    s = scene.detach().to(device="cpu", dtype=torch.float32)
    if s.element is not None:
        log.info("%s: SPZ has no field for element labels; not kept", path)
    n, deg = len(s), s.sh_degree
    try:
        pos = pack_positions(s.means.numpy() * POS_FLIP)
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from None
    alphas = _u8(torch.sigmoid(s.opacity_logits).numpy() * 255)
    colours = _u8(s.sh_dc.numpy() * (COLOR_SCALE * 255) + 127.5).reshape(-1)
    ls = s.log_scales.numpy()
    out = ((ls < -10 - 1 / 32) | (ls > 255 / 16 - 10 + 1 / 32)).any(1)
    if out.any():
        log.warning("%s: %d Gaussians have log-scales outside SPZ's [-10, %.4g]; clamped", path, int(out.sum()), 255 / 16 - 10)
    scales = _u8((ls + 10) * 16).reshape(-1)
    q = s.quats.numpy() * QUAT_FLIP
    xyzw = np.concatenate([q[:, 1:], q[:, :1]], 1)
    rots = pack_quats_smallest_three(xyzw) if version >= 3 else pack_quats_first_three(xyzw)
    k = SH_DIM[deg]
    rest = s.sh_rest.numpy() * SH_FLIP[:k, None]
    sh = np.concatenate([quantize_sh(rest[:, :3], 5), quantize_sh(rest[:, 3:], 4)], 1).reshape(-1) if k else np.zeros(0, np.uint8)
    arrays = [pos, alphas, colours, scales, rots, sh]
    if version < 4:
        body = LEGACY_HEADER.pack(MAGIC, version, n, deg, FRACTIONAL_BITS, 0, 0) + b"".join(a.tobytes() for a in arrays)
        data = gzip.compress(body, compresslevel=6, mtime=0)
    else:
        import zstandard

        cctx = zstandard.ZstdCompressor(level=12)
        raw = [a.tobytes() for a in arrays if a.size]
        chunks = [cctx.compress(r) for r in raw]
        head = HEADER.pack(MAGIC, version, n, deg, FRACTIONAL_BITS, 0, len(chunks), HEADER.size)
        toc = b"".join(struct.pack("<QQ", len(c), len(r)) for c, r in zip(chunks, raw))
        data = head + toc + b"".join(chunks)
    with atomic_path(path) as tmp:
        Path(tmp).write_bytes(data)


def _arrays(path: Path, data: bytes, offset: int, n: int, deg: int, version: int) -> tuple[list[np.ndarray], int]:
    """The six attribute arrays of a legacy body starting at ``offset``; PlyError naming the first
    one the data ends inside."""
    sizes = _sizes(n, deg, version)
    out = []
    for name, size in sizes:
        if offset + size > len(data):
            raise PlyError(f"{path}: SPZ field '{name}': the data ends {offset + size - len(data)} bytes short "
                           f"({n} Gaussians; truncated?)")
        out.append(np.frombuffer(data, np.uint8, size, offset))
        offset += size
    return out, offset


def _sizes(n: int, deg: int, version: int) -> list[tuple[str, int]]:
    return [("positions", n * (6 if version == 1 else 9)), ("alphas", n), ("colors", 3 * n), ("scales", 3 * n),
            ("rotations", n * (4 if version >= 3 else 3)), ("sh", n * SH_DIM[deg] * 3)]


def read_spz(path: str | Path, drop_invalid: bool = False) -> GaussianScene:
    """An SPZ file of version 1-4 (module docstring); :class:`~wast3d.ply.PlyError` naming the file and
    the field for a bad magic, version, count, SH degree, truncation or corrupt compressed data, a
    stream holding more than its header's count implies (decompression stops there: a small file
    cannot inflate into gigabytes), a count the machine's memory cannot hold, and values unusable once
    decoded (:func:`~wast3d.ply.checked`; ``drop_invalid`` drops those Gaussians)."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: file not found")
    data = path.read_bytes()
    if data[:2] == b"\x1f\x8b":  # versions 1-3: one gzip stream
        data, flags, extra = _inflate_legacy(path, data)
        magic, version, n, deg, bits, flags, _ = LEGACY_HEADER.unpack_from(data)
        arrays, _ = _arrays(path, data, LEGACY_HEADER.size, n, deg, version)
        if flags & FLAG_EXTENSIONS or extra:
            log.info("%s: SPZ extensions (%d bytes) skipped", path, extra)
    else:
        if len(data) < HEADER.size:
            raise PlyError(f"{path}: SPZ header: {len(data)} bytes, need {HEADER.size} (not an SPZ file?)")
        magic, version, n, deg, bits, flags, streams, toc = HEADER.unpack_from(data)
        _check_header(path, magic, version, n, deg, legacy=False, bits=bits)
        arrays = _zstd_arrays(path, data, n, deg, version, streams, toc)
        if flags & FLAG_EXTENSIONS:
            log.info("%s: SPZ extensions (%d bytes) skipped", path, toc - HEADER.size)
    if flags & FLAG_ANTIALIASED:
        log.warning("%s: SPZ marked antialiased (trained with a 2D filter); read as a plain 3DGS scene", path)
    return checked(_unpack(arrays, n, deg, bits, version, path), path, drop_invalid, "SPZ:")


def _inflate_legacy(path: Path, data: bytes) -> tuple[bytearray, int, int]:
    """A version 1-3 file's gzip stream, inflated in steps of at most STEP bytes and never beyond what
    its header's count implies (plus EXTENSIONS_MAX) -> (the header and arrays, flags, bytes of
    extensions beyond them, read and dropped)."""
    d = zlib.decompressobj(16 + zlib.MAX_WBITS)

    def more(limit: int, tail: bytes) -> bytes:
        try:
            return d.decompress(tail, limit)
        except zlib.error as e:
            raise PlyError(f"{path}: SPZ: the gzip stream is corrupt ({e})") from None

    head = more(LEGACY_HEADER.size, data)
    if len(head) < LEGACY_HEADER.size:
        raise PlyError(f"{path}: SPZ: the gzip stream ends after {len(head)} bytes, inside its {LEGACY_HEADER.size}-byte "
                       "header (truncated?)")
    magic, version, n, deg, bits, flags, _ = LEGACY_HEADER.unpack_from(head)
    _check_header(path, magic, version, n, deg, legacy=True, bits=bits)
    need = LEGACY_HEADER.size + sum(size for _, size in _sizes(n, deg, version))
    out = bytearray(head)
    while len(out) < need:
        block = more(min(STEP, need - len(out)), d.unconsumed_tail)
        if not block:
            break  # the stream ended: _arrays names the field it ends in
        out += block
    extra = 0
    while not d.eof:
        block = more(min(STEP, EXTENSIONS_MAX + 1 - extra), d.unconsumed_tail)
        if not block:
            break
        extra += len(block)
        if extra > EXTENSIONS_MAX:
            raise PlyError(f"{path}: SPZ: the gzip stream holds more than the {need} bytes its header's count "
                           f"({n} Gaussians, SH degree {deg}) implies, and more than {EXTENSIONS_MAX} bytes of "
                           "extensions beyond them: corrupt, or a decompression bomb; not read further")
    return out, flags, extra


MAX_FRACTIONAL_BITS = 23  # positions are 24-bit signed fixed point: more fractional bits leave no integer part


def _check_header(path: Path, magic: int, version: int, n: int, deg: int, legacy: bool, bits: int) -> None:
    if magic != MAGIC:
        raise PlyError(f"{path}: SPZ header 'magic': {magic:#010x}, expected {MAGIC:#010x} (not an SPZ file)")
    if not (1 <= version <= 3 if legacy else version == 4):
        raise PlyError(f"{path}: SPZ header 'version': {version} in a "
                       + ("gzip stream, which holds versions 1-3" if legacy else
                          "Zstandard container, which holds version 4 (versions 1-3 are gzip streams)"))
    if n == 0:
        raise PlyError(f"{path}: SPZ header 'numPoints': 0 Gaussians")
    if version >= 2 and bits > MAX_FRACTIONAL_BITS:  # version 1 stores float16 positions
        raise PlyError(f"{path}: SPZ header 'fractionalBits': {bits}; 24-bit fixed-point positions hold 0-"
                       f"{MAX_FRACTIONAL_BITS} (12 is usual)")
    if deg not in SH_DIM:
        raise PlyError(f"{path}: SPZ header 'shDegree': {deg} (known: 0-4)")
    need = sum(size for _, size in _sizes(n, deg, version)) + n * (DECODED_BYTES + 12 * SH_DIM[deg])
    free = memory_available()
    if free is not None and need > free:
        raise PlyError(f"{path}: SPZ header 'numPoints': {n} Gaussians need about {need / 2**30:.1f} GiB to read, "
                       f"this machine has {free / 2**30:.1f} GiB available")


def _zstd_arrays(path: Path, data: bytes, n: int, deg: int, version: int, streams: int, toc: int) -> list[np.ndarray]:
    import zstandard

    sizes = _sizes(n, deg, version)
    expect = [(name, size) for name, size in sizes if size]
    if streams != len(expect):
        raise PlyError(f"{path}: SPZ header 'numStreams': {streams}, expected {len(expect)} for SH degree {deg}")
    if toc < HEADER.size or toc + 16 * streams > len(data):
        raise PlyError(f"{path}: SPZ header 'tocByteOffset': {toc} (file of {len(data)} bytes; truncated?)")
    offset, dctx, got = toc + 16 * streams, zstandard.ZstdDecompressor(), {}
    for i, (name, size) in enumerate(expect):
        csize, usize = struct.unpack_from("<QQ", data, toc + 16 * i)
        if usize != size:
            raise PlyError(f"{path}: SPZ stream '{name}': {usize} bytes, expected {size} for {n} Gaussians")
        if offset + csize > len(data):
            raise PlyError(f"{path}: SPZ stream '{name}': the file ends {offset + csize - len(data)} bytes short (truncated?)")
        try:
            raw = _inflate_zstd(dctx, memoryview(data)[offset:offset + csize], size)
        except zstandard.ZstdError as e:
            raise PlyError(f"{path}: SPZ stream '{name}': corrupt Zstandard data ({e})") from None
        if len(raw) > size:
            raise PlyError(f"{path}: SPZ stream '{name}': holds more than the {size} bytes its table of contents and "
                           f"header ({n} Gaussians) give; not read further")
        if len(raw) != size:
            raise PlyError(f"{path}: SPZ stream '{name}': {len(raw)} bytes decompressed, expected {size}")
        got[name] = np.frombuffer(raw, np.uint8)
        offset += csize
    return [got.get(name, np.zeros(0, np.uint8)) for name, _ in sizes]


def _inflate_zstd(dctx, frame, size: int) -> bytearray:
    """One Zstandard stream, read in steps of at most STEP bytes, and at most ``size + 1`` bytes in all
    (one more than expected tells a stream that holds more)."""
    out = bytearray()
    with dctx.stream_reader(frame, read_across_frames=True) as r:
        while len(out) <= size:
            block = r.read(min(STEP, size + 1 - len(out)))
            if not block:
                break
            out += block
    return out


def _unpack(arrays: list[np.ndarray], n: int, deg: int, bits: int, version: int, path: Path) -> GaussianScene:
    pos, alphas, colours, scales, rots, sh = arrays
    if version == 1:
        means = pos.view("<f2").reshape(n, 3).astype(np.float32)
    else:
        means = unpack_positions(pos, n, bits)
    q = unpack_quats_smallest_three(rots, n) if version >= 3 else unpack_quats_first_three(rots, n)
    wxyz = np.concatenate([q[:, 3:], q[:, :3]], 1) * QUAT_FLIP
    a = np.clip(alphas.astype(np.float64) / 255, 0.25 / 255, 1 - 0.25 / 255)  # written back as 0 and 255
    k = SH_DIM[deg]
    rest = (sh.reshape(n, k, 3).astype(np.float32) - 128) / 128 if k else np.zeros((n, 0, 3), np.float32)
    if deg == 4:
        log.warning("%s: SPZ SH degree 4 read to degree 3 (the renderer's highest)", path)
        rest, k = rest[:, :15], 15
    rest = rest * SH_FLIP[:k, None]
    return GaussianScene(
        means=torch.from_numpy(means * POS_FLIP),
        log_scales=torch.from_numpy(scales.reshape(n, 3).astype(np.float32) / 16 - 10),
        quats=torch.from_numpy(wxyz.astype(np.float32)),
        opacity_logits=torch.from_numpy(np.log(a / (1 - a)).astype(np.float32)),
        sh_dc=torch.from_numpy((colours.reshape(n, 3).astype(np.float32) / 255 - 0.5) / COLOR_SCALE),
        sh_rest=torch.from_numpy(np.ascontiguousarray(rest, dtype=np.float32)),
    )


__all__ = ["read_spz", "write_spz", "pack_positions", "unpack_positions", "pack_quats_smallest_three",
           "unpack_quats_smallest_three", "quantize_sh", "VERSIONS"]

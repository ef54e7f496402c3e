"""Small I/O helpers shared by every stage: atomic writes and JSON."""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from pathlib import Path
from typing import Any, Iterator

import numpy as np

FORMATS = (".ply", ".spz", ".splat")  # scene files by extension (wast3d.formats reads and writes them)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; rename it onto ``path`` only if the block succeeds.

    A crash or exception leaves any existing ``path`` untouched and removes the temporary file.
    The temporary keeps the final suffix so that writers choosing a format by extension still work.
    The file gets the permissions a plain ``open`` would give it (0666 less the umask), not the
    owner-only ones of a temporary file: results are read by others on a shared cluster.
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix if suffix is not None else path.suffix,
                                   dir=path.parent)
    except OSError as e:  # a read-only folder, a file where a folder should be: named as the file to write
        up = next((a for a in path.parents if a.exists()), None)
        why = f"{up} is a file, not a folder" if up is not None and not up.is_dir() else e.strerror
        raise OSError(e.errno, f"cannot be written ({why})", str(path)) from None
    os.close(fd)
    tmp = Path(tmp)
    try:
        yield tmp
        if tmp.exists():
            os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def read_image(path: str | os.PathLike, error: type[Exception] = ValueError, max_pixels: int | None = None) -> np.ndarray:
    """An image file -> [H, W, 3] (RGB) or [H, W, 4] (RGBA) array of its own type (uint8, uint16 or float),
    grey spread over the three colours. ``error`` names the file when it is missing, not a file, no image
    imageio reads, over ``max_pixels`` or not grey, grey + alpha, RGB or RGBA."""
    import imageio.v3 as iio

    p = Path(path)
    if not p.is_file():
        raise error(f"{p}: image file not found" if not p.exists() else f"{p}: not an image file")
    try:
        shape = iio.improps(p).shape if max_pixels is not None else None
        a = np.asarray(iio.imread(p)) if shape is None or int(np.prod(shape[:2])) <= max_pixels else None
    except Exception as e:  # imageio raises many types for what is no image
        raise error(f"{p}: cannot read image ({type(e).__name__}: {(str(e).splitlines() or [''])[0][:120]})") from None
    if a is None:
        raise error(f"{p}: {shape[1]}x{shape[0]} pixels; at most {max_pixels >> 20} megapixels are read")
    if a.ndim == 2:
        a = a[..., None]
    if a.dtype.kind not in "uif" or a.ndim != 3 or a.shape[-1] not in (1, 2, 3, 4) or min(a.shape[:2]) < 1:
        raise error(f"{p}: an image of shape {a.shape} and type {a.dtype}; expected grey, grey + alpha, RGB or RGBA")
    if a.shape[-1] in (1, 2):  # grey (+ alpha): the grey on three channels
        a = np.concatenate([np.repeat(a[..., :1], 3, axis=-1), a[..., 1:]], axis=-1)
    return a


def memory_available() -> int | None:
    """Bytes of memory this machine can still give (psutil's ``available``), or None where unknown."""
    try:
        import psutil
    except ImportError:  # pragma: no cover - psutil comes with the dependencies
        return None
    return int(psutil.virtual_memory().available)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _jsonable(o: Any) -> Any:
    if isinstance(o, dict):
        return {str(k): _jsonable(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_jsonable(v) for v in o]
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if hasattr(o, "tolist") and hasattr(o, "dtype"):  # torch tensors
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    if isinstance(o, float) and (o != o or o in (float("inf"), float("-inf"))):
        return str(o)  # JSON has no NaN/inf; keep it visible rather than invalid
    return o


def write_json(path: str | os.PathLike, obj: Any) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(_jsonable(obj), indent=2) + "\n")


def read_json(path: str | os.PathLike) -> Any:
    path = Path(path)
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise FileNotFoundError(f"{path}: file not found") from None
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}: invalid JSON ({e})") from None


def save_npz(path: str | os.PathLike, **arrays: Any) -> None:
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, **{k: np.asarray(v) for k, v in arrays.items()})


def load_npz(path: str | os.PathLike, required: tuple[str, ...] = ()) -> dict[str, np.ndarray]:
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: file not found")
    try:
        with np.load(path, allow_pickle=False) as z:
            out = {k: z[k] for k in z.files}
    except Exception as e:  # zipfile / format errors
        raise ValueError(f"{path}: cannot read npz ({e})") from None
    for k in required:
        if k not in out:
            raise ValueError(f"{path}: missing array '{k}' (has: {', '.join(sorted(out))})")
    return out

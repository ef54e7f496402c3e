"""Build and load the package's C kernels (``wast3d/csrc/*.c``) with the system C compiler.

Kernels are plain C with OpenMP, called through ctypes on torch tensors' data pointers (ctypes
releases the GIL during the call). Each kernel is compiled twice, for float32 (symbol suffix
``_f32``) and float64 (``_f64``), into one shared library cached under ``$WAST3D_CACHE`` (default
``~/.cache/wast3d``), keyed by the source, the flags, the compiler version and the CPU, so a cache on a
shared home directory is never used by a machine it was not built for. A build takes about a second;
``wast3d build-ext`` builds ahead of time. Without a compiler, :func:`load` returns None and callers
fall back to the pure-PyTorch reference (and log that they did).
"""

from __future__ import annotations

import ctypes
import hashlib
import logging
import os
import platform
import shutil
import subprocess
import tempfile
from functools import lru_cache
from pathlib import Path

log = logging.getLogger(__name__)

CSRC = Path(__file__).parent / "csrc"
CFLAGS = ["-O3", "-fPIC", "-fopenmp", "-fno-math-errno", "-march=native", "-std=c11"]


def cache_dir() -> Path:
    return Path(os.environ.get("WAST3D_CACHE", Path.home() / ".cache" / "wast3d")) / "native"


def _cpu_id() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name") or line.startswith("flags"):
                return line
    except OSError:
        pass
    return platform.processor()


def _compiler() -> str | None:
    return os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc")


def build(name: str, force: bool = False, csrc: Path = CSRC) -> Path:
    """Compile ``<csrc>/<name>.c`` (float32 and float64) into a cached shared library; return its path.
    ``csrc`` other than the package's: another version of the sources (the benchmarks' previous one)."""
    cc = _compiler()
    if cc is None:
        raise RuntimeError("no C compiler found (set CC)")
    src = (csrc / f"{name}.c").read_bytes() + b"".join(h.read_bytes() for h in sorted(csrc.glob("*.h")))
    ver = subprocess.run([cc, "--version"], capture_output=True, text=True).stdout.splitlines()[:1]
    key = hashlib.sha256(src + repr((CFLAGS, ver, _cpu_id(), platform.machine())).encode()).hexdigest()[:16]
    out = cache_dir() / f"{name}-{key}.so"
    if out.exists() and not force:
        return out
    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=out.parent) as td:
        objs = []
        for real, sfx in (("float", "_f32"), ("double", "_f64")):
            o = Path(td) / f"{name}{sfx}.o"
            cmd = [cc, *CFLAGS, f"-DREAL={real}", f"-DSFX={sfx}", "-c", str(csrc / f"{name}.c"), "-o", str(o)]
            r = subprocess.run(cmd, capture_output=True, text=True)
            if r.returncode != 0:
                raise RuntimeError(f"compiling {name}.c failed:\n{' '.join(cmd)}\n{r.stderr}")
            objs.append(str(o))
        tmp = Path(td) / "lib.so"
        r = subprocess.run([cc, "-shared", "-fopenmp", *objs, "-o", str(tmp), "-lm"], capture_output=True, text=True)
        if r.returncode != 0:
            raise RuntimeError(f"linking {name} failed:\n{r.stderr}")
        os.replace(tmp, out)
    log.info("built native kernel %s -> %s", name, out)
    return out


@lru_cache(maxsize=None)
def load(name: str) -> ctypes.CDLL | None:
    """The compiled library for ``name``, or None (with a logged reason) when it cannot be built.

    ``WAST3D_NO_NATIVE=1`` disables native kernels (the PyTorch reference is used).
    """
    if os.environ.get("WAST3D_NO_NATIVE"):
        log.info("native kernel %s disabled by WAST3D_NO_NATIVE", name)
        return None
    try:
        return ctypes.CDLL(str(build(name)))
    except Exception as e:  # no compiler, no OpenMP, read-only cache...
        log.warning("native kernel %s unavailable, using the PyTorch reference: %s", name, e)
        return None


def ptr(t) -> ctypes.c_void_p:
    """Data pointer of a contiguous CPU tensor."""
    assert t.is_contiguous() and t.device.type == "cpu"
    return ctypes.c_void_p(t.data_ptr())

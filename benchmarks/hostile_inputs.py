"""Bad files, names and configs against one or more checkouts of wast3d, side by side: what each
command answers (exit code and first line), how long it takes and how much memory it holds.

    python benchmarks/hostile_inputs.py [--tree LABEL=PATH ...] [--out results/benchmarks/hostile_inputs.csv]

Each tree is a checkout (default: this one); its package is put first on PYTHONPATH and its Snakefile
is run, so an older commit can be compared (``git worktree add /tmp/before <commit>``). A case passes
when no command hidden in a name ran, no user file changed, memory stayed bounded and the answer is a
one-line error naming the file (or the config file) and the field.
"""

from __future__ import annotations

import argparse
import gzip
import os
import shutil
import struct
import subprocess
import sys
import tempfile
import time
import zlib
from pathlib import Path

import numpy as np
import pandas as pd
import psutil

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def run(tree: Path, argv: list[str], cwd: Path, timeout: float = 120) -> dict:
    """``argv`` with ``tree``'s package first on the path -> exit code, first error line, seconds, peak MB
    (the process and its children, sampled every 20 ms)."""
    env = {**os.environ, "PYTHONPATH": str(tree)}
    t0, peak = time.monotonic(), 0
    p = subprocess.Popen(argv, cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                         start_new_session=True)
    proc = psutil.Process(p.pid)
    while p.poll() is None:
        try:
            peak = max(peak, sum(q.memory_info().rss for q in [proc, *proc.children(recursive=True)]))
        except psutil.Error:
            pass
        if time.monotonic() - t0 > timeout:
            os.killpg(p.pid, 9)
            p.wait()
            return {"rc": "killed", "message": f"still running after {timeout:.0f} s", "seconds": timeout,
                    "peak_mb": peak / 2**20, "output": ""}
        time.sleep(0.02)
    out = p.stdout.read()
    lines = [ln for ln in out.splitlines() if ln.strip() and not ln.startswith(("Using profile", "Building DAG",
                                                                                 "scene '", "Assuming"))]
    at = next((i for i, ln in enumerate(lines) if any(w in ln for w in ("ERROR", "Error", "error", "refused",
                                                                        "Traceback"))), len(lines) - 1)
    if at >= 0 and lines[at].endswith(":") and at + 1 < len(lines):  # "XError in file ..., line N:" then the message
        at += 1
    msg = lines[at] if lines else ""
    return {"rc": p.returncode, "message": msg.strip()[:220], "seconds": time.monotonic() - t0,
            "peak_mb": peak / 2**20, "output": out}


def wast3d(tree, *args):
    return [sys.executable, "-m", "wast3d", *map(str, args)]


def snakemake(tree, work, *configs):
    return [sys.executable, "-m", "snakemake", "-s", str(tree / "Snakefile"), "-d", str(work), "-n", "-q",
            "--configfile", str(tree / "config" / "config.yaml"), *map(str, configs)]


def scenes(d: Path) -> tuple[Path, Path]:
    from wast3d.ply import write_ply
    from wast3d.procedural import make_scene

    c, s = d / "c.ply", d / "s.ply"
    write_ply(c, make_scene("content", "torus", 600))
    write_ply(s, make_scene("style", "pebbles", 600))
    return c, s


def case_injection(tree, d):
    c, s = scenes(d)
    evil = d / "dir $(touch pwned)"
    evil.mkdir()
    shutil.copy(c, evil / "scene.ply")
    r = run(tree, wast3d(tree, "run", evil / "scene.ply", s, d / "out", "--", "results/scenes/dir_touch_pwned/scene.ply"), d)
    ran = list(d.rglob("pwned"))
    r["verdict"] = "a command in the name RAN" if ran else ("ok" if r["rc"] == 0 else "the job failed")
    return r


def case_space(tree, d):
    c, s = scenes(d)
    (d / "a folder").mkdir()
    shutil.copy(c, d / "a folder" / "my scene.ply")
    r = run(tree, wast3d(tree, "run", d / "a folder" / "my scene.ply", s, d / "out x", "--",
                         "results/scenes/my_scene/scene.ply"), d)
    r["verdict"] = "ok" if r["rc"] == 0 else "the job failed"
    return r


def case_dry_run_edits(tree, d):
    c, s = scenes(d)
    cfg = d / "out" / "config" / "config.yaml"
    run(tree, wast3d(tree, "run", c, s, d / "out", "-n"), d)
    if not cfg.exists():  # a dry run that writes nothing: let a real (tiny) run write it
        run(tree, wast3d(tree, "run", c, s, d / "out", "--", "results/scenes/c/scene.ply"), d)
    cfg.write_text(cfg.read_text() + "# my edit\n")
    edited = cfg.read_text()
    r = run(tree, wast3d(tree, "run", c, s, d / "out", "-n"), d)
    r["verdict"] = "ok: edits kept" if cfg.read_text() == edited else "the user's edits were OVERWRITTEN"
    return r


def case_spz_bomb(tree, d):
    from wast3d.spz import LEGACY_HEADER, MAGIC

    c = zlib.compressobj(9, zlib.DEFLATED, 31)
    parts = [c.compress(LEGACY_HEADER.pack(MAGIC, 2, 10, 0, 12, 0, 0) + bytes(10 * 19))]
    block = bytes(1 << 24)
    parts += [c.compress(block) for _ in range(64)]  # 1 GiB of zeros behind 10 Gaussians
    (d / "bomb.spz").write_bytes(b"".join(parts) + c.flush())
    r = run(tree, wast3d(tree, "info", d / "bomb.spz"), d, timeout=300)
    r["verdict"] = f"file {(d / 'bomb.spz').stat().st_size / 2**20:.1f} MB; " + (
        "ok: refused" if r["rc"] == 1 and "more than" in r["output"] else "read")
    return r


def case_spz_count(tree, d):
    from wast3d.spz import HEADER, MAGIC

    n = 4_000_000_000
    sizes = [n * 9, n, 3 * n, 3 * n, 4 * n]
    toc = b"".join(struct.pack("<QQ", 8, s) for s in sizes)
    (d / "huge.spz").write_bytes(HEADER.pack(MAGIC, 4, n, 0, 12, 0, len(sizes), HEADER.size) + toc + bytes(40))
    r = run(tree, wast3d(tree, "info", d / "huge.spz"), d)
    r["verdict"] = "ok: refused" if "numPoints" in r["output"] and "Traceback" not in r["output"] else "a traceback"
    return r


def case_yaml_bomb(tree, d):
    rows = ["l0: &l0 [" + ", ".join(["x"] * 10) + "]"]
    rows += [f"l{k}: &l{k} [" + ", ".join([f"*l{k - 1}"] * 10) + "]" for k in range(1, 9)]
    (d / "bomb.yaml").write_text("\n".join(rows) + "\n")
    r = run(tree, snakemake(tree, d / "w", d / "bomb.yaml"), d, timeout=90)
    r["verdict"] = f"file {(d / 'bomb.yaml').stat().st_size} B; " + (
        "ok: refused" if "more than 100000 values" in r["output"] else "not refused")
    return r


def _ply(d: Path, name: str, edit) -> Path:
    from plyfile import PlyData

    from wast3d.formats import write_scene
    from wast3d.procedural import make_scene

    src = d / ("src.compressed.ply" if "compressed" in name else "src.ply")
    write_scene(src, make_scene("style", "pebbles", 600))
    ply = PlyData.read(str(src))
    edit(ply)
    ply.write(str(d / name))
    return d / name


def _valid_verdict(r, field):
    return "ok: refused, names the field" if r["rc"] == 1 and field in r["output"] else "reported VALID"


def case_ply_logscale(tree, d):
    p = _ply(d, "logscale.ply", lambda ply: ply["vertex"]["scale_0"].__setitem__(5, 1000.0))
    r = run(tree, wast3d(tree, "info", p), d)
    r["verdict"] = _valid_verdict(r, "'scale'")
    return r


def case_chunk_scale(tree, d):
    p = _ply(d, "chunk.compressed.ply", lambda ply: ply["chunk"]["min_scale_x"].__setitem__(0, 1e30))
    r = run(tree, wast3d(tree, "info", p), d)
    r["verdict"] = _valid_verdict(r, "'scale'")
    return r


def case_spz_v1_nan(tree, d):
    from wast3d.spz import LEGACY_HEADER, MAGIC

    n = 4
    pos = np.zeros((n, 3), np.float16)
    pos[2, 1] = np.nan
    body = (LEGACY_HEADER.pack(MAGIC, 1, n, 0, 12, 0, 0) + pos.tobytes() + bytes(n) + bytes(3 * n)
            + bytes([160] * 3 * n) + bytes([128, 128, 128] * n))
    (d / "v1.spz").write_bytes(gzip.compress(body))
    r = run(tree, wast3d(tree, "info", d / "v1.spz"), d)
    r["verdict"] = _valid_verdict(r, "position")
    return r


def case_export_far(tree, d):
    from wast3d.ply import write_ply
    from wast3d.procedural import make_scene

    s = make_scene("style", "pebbles", 600)
    s.means[3, 0] = 3e38
    write_ply(d / "far.ply", s)
    r = run(tree, wast3d(tree, "export", d / "far.ply", d / "far.spz"), d)
    r["verdict"] = "ok: refused" if r["rc"] == 2 and not (d / "far.spz").exists() else "WRITTEN wrong"
    return r


def _short_header(d: Path, name: str) -> Path:
    from wast3d.formats import write_scene
    from wast3d.procedural import make_scene

    src = d / f"src_{name}"
    s = make_scene("style", "pebbles", 600)
    write_scene(src, s)
    raw = src.read_bytes()
    n = len(s)
    (d / name).write_bytes(raw.replace(f"element vertex {n}\n".encode(), f"element vertex {n - 10}\n".encode(), 1))
    return d / name


def case_header_rows(tree, d):
    r = run(tree, wast3d(tree, "info", _short_header(d, "short.ply")), d)
    r["verdict"] = "ok: refused" if r["rc"] == 1 else "rows DROPPED silently"
    return r


def case_header_rows_compressed(tree, d):
    r = run(tree, wast3d(tree, "info", _short_header(d, "short.compressed.ply")), d)
    r["verdict"] = "ok: refused" if r["rc"] == 1 else "rows DROPPED silently"
    return r


def _config_case(tree, d, text, must):
    (d / "bad.yaml").write_text(text)
    r = run(tree, snakemake(tree, d / "w", d / "bad.yaml"), d)
    named = str(d / "bad.yaml") in r["output"]
    r["verdict"] = ("ok: refused" + (", names the file" if named else ", file NOT named")) if must in r["output"] \
        else ("PASSES validation" if r["rc"] == 0 else "refused, not as expected")
    return r


def case_config_inf(tree, d):
    return _config_case(tree, d, "experiments:\n  default:\n    stylize:\n      lr: .inf\n", "finite")


def case_config_clusters(tree, d):
    return _config_case(tree, d, "partitions:\n  default:\n    cluster: {n_clusters: 1000000000}\n", "n_clusters")


def case_config_gaussians(tree, d):
    return _config_case(tree, d, "scenes:\n  ant: {source: procedural, kind: content, name: ant, "
                                 "n_gaussians: 1000000000000}\n", "n_gaussians")


def case_config_unknown(tree, d):
    return _config_case(tree, d, "experiments:\n  default:\n    stylize:\n      lrr: 0.1\n", "lrr")


def case_out_is_file(tree, d):
    c, s = scenes(d)
    (d / "afile").write_text("x")
    r = run(tree, wast3d(tree, "run", c, s, d / "afile"), d)
    r["verdict"] = "a traceback" if "Traceback" in r["output"] else ("ok: one line" if r["rc"] == 2 else "?")
    return r


def case_export_onto_dir(tree, d):
    c, _ = scenes(d)
    (d / "adir.ply").mkdir()
    r = run(tree, wast3d(tree, "export", c, d / "adir.ply"), d)
    r["verdict"] = "a traceback" if "Traceback" in r["output"] else ("ok: one line" if r["rc"] == 2 else "?")
    return r


def case_drop_invalid(tree, d):
    p = _ply(d, "nan.ply", lambda ply: ply["vertex"]["x"].__setitem__(3, np.nan))
    rs = [run(tree, wast3d(tree, *cmd), d) for cmd in (["info", p, "--drop-invalid"],
                                                      ["export", p, d / "o.spz", "--drop-invalid"])]
    r = rs[-1]
    r["verdict"] = "ok: both take it" if all(x["rc"] == 0 for x in rs) else "NOT an option of info / export"
    return r


def case_spz_version(tree, d):
    from wast3d.spz import HEADER, MAGIC

    (d / "v3.spz").write_bytes(HEADER.pack(MAGIC, 3, 10, 0, 12, 0, 5, HEADER.size) + bytes(100))
    r = run(tree, wast3d(tree, "info", d / "v3.spz"), d)
    r["verdict"] = "contradicts itself" if "known: 1-4" in r["output"] else "ok"
    return r


CASES = {name[5:]: fn for name, fn in globals().items() if name.startswith("case_")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tree", nargs="*", default=[f"now={ROOT}"], help="LABEL=CHECKOUT ...")
    ap.add_argument("--cases", nargs="*", default=list(CASES))
    ap.add_argument("--out", type=Path, default=ROOT / "results" / "benchmarks" / "hostile_inputs.csv")
    a = ap.parse_args()
    rows = []
    for case in a.cases:
        row = {"case": case}
        for spec in a.tree:
            label, path = spec.split("=", 1)
            with tempfile.TemporaryDirectory() as d:
                r = CASES[case](Path(path), Path(d))
            for k in ("verdict", "rc", "seconds", "peak_mb", "message"):
                row[f"{label}_{k}"] = round(r[k], 1) if isinstance(r[k], float) else r[k]
            print(case, label, r["verdict"], r["rc"], f"{r['seconds']:.1f} s", f"{r['peak_mb']:.0f} MB", flush=True)
        rows.append(row)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    df = pd.DataFrame(rows)
    df.to_csv(a.out, index=False)
    a.out.with_suffix(".md").write_text(df.to_markdown(index=False) + "\n")
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()

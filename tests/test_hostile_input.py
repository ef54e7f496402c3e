"""Hostile and careless input: file names that would run commands, a user's edits, dry runs that must
write nothing. The workflow's jobs are real (Snakemake runs them), on paths holding a space, an
apostrophe, ``;``, ``$(...)`` and a backtick, from an interpreter under such a folder."""

import os
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from conftest import random_scene
from wast3d.ply import write_ply

NASTY = "a b'c;d$(touch PWNED_dollar)e`touch PWNED_tick`"


def fake_venv(where: Path) -> Path:
    """An interpreter at ``where/bin/python`` that is this venv (its pyvenv.cfg and lib/ linked in): a venv
    living under a folder with a nasty name, as far as ``sys.executable`` can tell."""
    venv = Path(sys.prefix)
    (where / "bin").mkdir(parents=True)
    (where / "bin" / "python").symlink_to(os.path.realpath(sys.executable))
    (where / "pyvenv.cfg").write_text((venv / "pyvenv.cfg").read_text())
    (where / "lib").symlink_to(venv / "lib")
    return where / "bin" / "python"


def tree(folder: Path) -> dict[str, tuple[int, int]]:
    """Every path under ``folder`` with its size and modification time (what a run may not change)."""
    return {str(p.relative_to(folder)): (p.lstat().st_size, p.lstat().st_mtime_ns) for p in folder.rglob("*")}


def test_paths_that_would_run_commands_reach_the_jobs_as_plain_names(tmp_path):
    """A real import job and preview on a content, style and OUT folder under NASTY, run by an
    interpreter under NASTY: the jobs succeed and no command hidden in a name runs."""
    home = tmp_path / NASTY
    data = home / "scenes $(touch PWNED_file)"
    data.mkdir(parents=True)
    c, s = data / "blob `touch PWNED_c`.ply", data / "peb;touch PWNED_s.ply"
    write_ply(c, random_scene(200, seed=1))
    write_ply(s, random_scene(200, seed=2))
    py = fake_venv(home / "py env")
    out = home / "out'; touch PWNED_out"
    targets = ["results/scenes/blob_touch_PWNED_c/scene.ply", "results/scenes/blob_touch_PWNED_c/preview.png",
               "results/scenes/peb_touch_PWNED_s/scene.ply"]
    r = subprocess.run([str(py), "-m", "wast3d", "run", str(c), str(s), str(out), "--", *targets],
                       capture_output=True, text=True, cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-4000:]
    assert shlex.quote(str(py)) + " -m wast3d" in r.stdout + r.stderr  # the jobs ran by that interpreter, quoted
    for t in targets:
        assert (out / t).stat().st_size > 0, t
    ran = [p for p in tmp_path.rglob("PWNED*")]
    assert not ran, f"a command hidden in a name ran: {ran}"


def test_a_dry_run_writes_nothing_and_a_run_keeps_the_users_edits(tmp_path):
    c, s = tmp_path / "blob.ply", tmp_path / "peb.ply"
    write_ply(c, random_scene(300, seed=1))
    write_ply(s, random_scene(300, seed=2))
    out = tmp_path / "out"
    run = lambda *extra, target="results/scenes/blob/scene.ply": subprocess.run(  # noqa: E731
        [sys.executable, "-m", "wast3d", "run", str(c), str(s), str(out), *extra, "--", target],
        capture_output=True, text=True, cwd=tmp_path)

    r = run("-n")  # no OUT yet: none is made
    assert r.returncode == 0, r.stderr[-3000:]
    assert "rule import_ply:" in r.stdout and not out.exists()

    assert run().returncode == 0  # a real run writes the config and the scene
    cfg_path = out / "config" / "config.yaml"
    mine = yaml.safe_load(cfg_path.read_text())
    mine["experiments"]["default"] = {"stylize": {"iterations": 7}}
    edited = "# my edit: fewer steps\n" + yaml.safe_dump(mine)
    cfg_path.write_text(edited)
    before = tree(out)
    r = run("-n", target="results/stylize/blob__peb/default/final.ply")
    assert r.returncode == 0, r.stderr[-3000:]
    assert "rule sinkhorn:" in r.stdout and "output: results/scenes/blob/scene.ply" not in r.stdout  # cached
    assert '"iterations":7' in r.stdout  # the dry run shows the user's config
    assert tree(out) == before  # and writes nothing at all, .snakemake/ included

    r = run()
    assert r.returncode == 0 and cfg_path.read_text() == edited and "your edits are kept" in r.stderr

    other = tmp_path / "other.ply"
    write_ply(other, random_scene(300, seed=3))
    r = subprocess.run([sys.executable, "-m", "wast3d", "run", str(other), str(s), str(out), "-n"],
                       capture_output=True, text=True)
    assert r.returncode == 2 and "--reset-config" in r.stderr and "other.ply" in r.stderr
    assert cfg_path.read_text() == edited

    r = run("--reset-config")
    assert r.returncode == 0, r.stderr[-3000:]
    assert (out / "config" / "config.yaml.bak").read_text() == edited
    assert yaml.safe_load(cfg_path.read_text())["experiments"]["default"] == {}  # the defaults again

    (tmp_path / "afile").write_text("x")
    r = subprocess.run([sys.executable, "-m", "wast3d", "run", str(c), str(s), str(tmp_path / "afile")],
                       capture_output=True, text=True)
    assert r.returncode == 2 and "must be a folder" in r.stderr and "Traceback" not in r.stderr


def test_an_unedited_config_follows_the_defaults(tmp_path):
    from wast3d.quickstart import config_text, plan_config, written_unchanged

    c, s = tmp_path / "c.ply", tmp_path / "s.ply"
    for p in (c, s):
        write_ply(p, random_scene(20))
    path = tmp_path / "config.yaml"
    old = {"scenes": {"c": {"source": "ply", "path": str(c)}, "s": {"source": "ply", "path": str(s)}}, "x": 1}
    path.write_text(config_text(old))
    assert written_unchanged(path.read_text())
    new = {**old, "x": 2}
    assert plan_config(path, new, c, s).action == "write"  # ours, untouched: today's defaults replace it
    path.write_text(path.read_text() + "# a comment of mine\n")
    plan = plan_config(path, new, c, s)
    assert plan.action == "keep" and "x: 1" in plan.text
    path.write_text("scenes: [unclosed\n")
    with pytest.raises(ValueError, match="not valid YAML"):
        plan_config(path, new, c, s)


# ---- decompression: bounded by what the header's count implies --------------------------------------

PEAK_SCRIPT = """
import resource, sys
from wast3d.spz import read_spz
from wast3d.ply import PlyError
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
try:
    read_spz(sys.argv[1])
    print("READ")
except PlyError as e:
    print("ERROR", e)
print("GROWTH_MB", (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - base) / 1024)
"""


def read_in_child(path: Path) -> tuple[str, float]:
    """read_spz(path) in a fresh process -> (its first output line, how far its peak resident memory grew
    in MB while reading)."""
    r = subprocess.run([sys.executable, "-c", PEAK_SCRIPT, str(path)], capture_output=True, text=True, timeout=300)
    lines = r.stdout.splitlines()
    assert r.returncode == 0 and lines, r.stderr[-2000:]
    return lines[0], float(lines[-1].split()[1])


def legacy_spz(path: Path, n: int, zeros_after: int, version: int = 2) -> None:
    """A version-2 SPZ whose gzip stream holds a header for ``n`` Gaussians, their arrays, and then
    ``zeros_after`` bytes of zeros (compressed in steps: the test never holds them)."""
    import struct
    import zlib

    from wast3d.spz import LEGACY_HEADER, MAGIC

    c = zlib.compressobj(9, zlib.DEFLATED, 31)
    parts = [c.compress(LEGACY_HEADER.pack(MAGIC, version, n, 0, 12, 0, 0))]
    parts.append(c.compress(bytes(n * (9 + 1 + 3 + 3 + 3))))
    block = bytes(1 << 24)
    for _ in range(zeros_after // len(block)):
        parts.append(c.compress(block))
    parts.append(c.flush())
    path.write_bytes(b"".join(parts))
    assert struct.unpack("<I", LEGACY_HEADER.pack(MAGIC, version, n, 0, 12, 0, 0)[8:12])[0] == n


def test_a_gzip_bomb_is_refused_in_bounded_memory(tmp_path):
    bomb = tmp_path / "bomb.spz"
    legacy_spz(bomb, 10, 400 << 20)  # 400 MB of zeros behind 10 Gaussians, in a file of about 400 KB
    assert bomb.stat().st_size < 1 << 20
    first, growth = read_in_child(bomb)
    assert first.startswith("ERROR") and "bomb.spz" in first and "holds more than the" in first, first
    assert growth < 48, f"peak resident memory grew {growth:.0f} MB reading a 400 MB bomb"
    ok = tmp_path / "ok.spz"  # the same Gaussians with a little extension data are read
    legacy_spz(ok, 10, 0)
    assert read_in_child(ok)[0] == "READ"


def test_a_header_count_beyond_memory_is_refused_before_anything_is_allocated(tmp_path):
    import struct

    from wast3d.spz import HEADER, MAGIC, _sizes

    n = 4_000_000_000
    sizes = [s for _, s in _sizes(n, 0, 4) if s]
    toc = b"".join(struct.pack("<QQ", 8, s) for s in sizes)  # consistent with the count, 8 bytes each
    path = tmp_path / "huge.spz"
    path.write_bytes(HEADER.pack(MAGIC, 4, n, 0, 12, 0, len(sizes), HEADER.size) + toc + bytes(8 * len(sizes)))
    first, growth = read_in_child(path)
    assert "header 'numPoints': 4000000000 Gaussians need about" in first and "GiB available" in first, first
    assert growth < 16


# ---- one rule for every format: values unusable once decoded ---------------------------------------


def _run(*args):
    return subprocess.run([sys.executable, "-m", "wast3d", *map(str, args)], capture_output=True, text=True)


def test_values_unusable_once_decoded_are_refused_in_every_format(tmp_path):
    from plyfile import PlyData

    from wast3d.ply import PlyError, read_ply, write_compressed_ply
    import gzip

    from wast3d.spz import LEGACY_HEADER, MAGIC, read_spz

    s = random_scene(300, seed=4)
    write_ply(tmp_path / "s.ply", s)
    ply = PlyData.read(str(tmp_path / "s.ply"))  # log-scale 1000: finite in the file, infinite as a scale
    ply["vertex"]["scale_1"][17] = 1000.0
    ply.write(str(tmp_path / "logscale.ply"))
    with pytest.raises(PlyError, match=r"logscale\.ply: field 'scale': 1 Gaussians .* \(first at row 17\)"):
        read_ply(tmp_path / "logscale.ply")
    assert len(read_ply(tmp_path / "logscale.ply", drop_invalid=True)) == 299

    write_compressed_ply(tmp_path / "c.compressed.ply", s)
    ply = PlyData.read(str(tmp_path / "c.compressed.ply"))
    ply["chunk"]["min_scale_x"][1] = 1e30
    ply.write(str(tmp_path / "chunk.compressed.ply"))
    with pytest.raises(PlyError, match=r"chunk\.compressed\.ply: compressed PLY: field 'scale'"):
        read_ply(tmp_path / "chunk.compressed.ply")

    n = 4  # SPZ version 1: float16 positions, one of them NaN
    pos = np.zeros((n, 3), np.float16)
    pos[2, 1] = np.nan
    body = (LEGACY_HEADER.pack(MAGIC, 1, n, 0, 12, 0, 0) + pos.tobytes() + bytes(n) + bytes(3 * n)
            + bytes([160] * 3 * n) + bytes([128, 128, 128] * n))
    (tmp_path / "v1.spz").write_bytes(gzip.compress(body))
    with pytest.raises(PlyError, match=r"v1\.spz: SPZ: field 'position': 1 Gaussians .* \(first at row 2\)"):
        read_spz(tmp_path / "v1.spz")

    far = s.clone()
    far.means[5, 0] = 3e38
    write_ply(tmp_path / "far.ply", far)  # float32 holds it; SPZ's 24-bit fixed point does not
    r = _run("export", tmp_path / "far.ply", tmp_path / "far.spz")
    assert r.returncode == 2 and "field 'position'" in r.stderr and "first at row 5" in r.stderr, r.stderr
    assert not (tmp_path / "far.spz").exists()


@pytest.mark.parametrize("name", ["s.ply", "s.compressed.ply"])
def test_a_header_that_counts_fewer_rows_than_the_data_is_refused(tmp_path, name):
    from wast3d.formats import write_scene
    from wast3d.ply import PlyError, read_ply

    write_scene(tmp_path / name, random_scene(300, seed=5))
    raw = (tmp_path / name).read_bytes()
    (tmp_path / "short.ply").write_bytes(raw.replace(b"element vertex 300\n", b"element vertex 290\n", 1))
    with pytest.raises(PlyError, match=r"short\.ply: the header's element counts .* more rows than the header counts"):
        read_ply(tmp_path / "short.ply")


def test_user_errors_are_one_line_and_every_reader_takes_drop_invalid(tmp_path):
    from plyfile import PlyData

    write_ply(tmp_path / "s.ply", random_scene(50, seed=6))
    ply = PlyData.read(str(tmp_path / "s.ply"))
    ply["vertex"]["x"][3] = np.nan
    ply.write(str(tmp_path / "nan.ply"))
    from concurrent.futures import ThreadPoolExecutor

    (tmp_path / "adir").mkdir()
    calls = []
    for cmd in ("info", "export", "import-ply", "preview"):
        extra = [] if cmd == "info" else [tmp_path / f"o_{cmd}{'.png' if cmd == 'preview' else '.ply'}"]
        calls += [(cmd, tmp_path / "nan.ply", *extra), (cmd, tmp_path / "nan.ply", *extra, "--drop-invalid")]
    calls.append(("export", tmp_path / "s.ply", tmp_path / "adir"))
    with ThreadPoolExecutor(2) as pool:  # independent commands, two at a time
        done = list(pool.map(lambda c: _run(*c), calls))
    for c, r in zip(calls, done):
        if c[-1] == tmp_path / "adir":
            assert r.returncode == 2 and "is a folder" in r.stderr and "Traceback" not in r.stderr
        elif c[-1] == "--drop-invalid":
            assert r.returncode == 0, (c, r.stderr[-1500:])
        else:
            assert r.returncode in (1, 2) and "--drop-invalid" in r.stdout + r.stderr, c


# ---- the config: bounded, finite, and its errors name the file and the key -------------------------

ROOT = Path(__file__).resolve().parents[1]


def dry_run(tmp_path, *configs: str, workdir_config: str | None = None):
    import tempfile

    work = Path(tempfile.mkdtemp(dir=tmp_path))
    files = []
    for i, text in enumerate(configs):
        files.append(work.with_name(work.name + f"-c{i}.yaml"))
        files[-1].write_text(text)
    if workdir_config is not None:
        (work / "config").mkdir(parents=True)
        (work / "config" / "config.yaml").write_text(workdir_config)
    cmd = [sys.executable, "-m", "snakemake", "-s", str(ROOT / "Snakefile"), "-d", str(work), "-n", "-q"]
    if files:
        cmd += ["--configfile", str(ROOT / "config" / "config.yaml"), *map(str, files)]
    r = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, timeout=120)
    return subprocess.CompletedProcess(r.args, r.returncode, "", r.stdout), files  # Snakemake's messages, whichever stream


def alias_bomb(kind: str) -> str:
    rows = ["l0: &l0 [" + ", ".join(["x"] * 10) + "]"] if kind == "list" else \
        ["l0: &l0 {" + ", ".join(f"k{i}: 1" for i in range(10)) + "}"]
    for d in range(1, 9):
        items = [f"*l{d - 1}"] * 10
        rows.append(f"l{d}: &l{d} [" + ", ".join(items) + "]" if kind == "list" else
                    f"l{d}: &l{d} {{" + ", ".join(f"k{i}: {a}" for i, a in enumerate(items)) + "}")
    return "\n".join(rows) + "\n"


def test_config_bombs_and_bad_values_stop_at_once_naming_the_file_and_key(tmp_path):
    import time

    t = time.monotonic()
    r, files = dry_run(tmp_path, alias_bomb("list"))
    assert r.returncode != 0 and "more than 100000 values" in r.stderr and str(files[0]) in r.stderr
    r, _ = dry_run(tmp_path, workdir_config=alias_bomb("dict"))  # OUT's own config, as `wast3d run` keeps it
    assert r.returncode != 0 and "config config/config.yaml: more than 100000 values" in r.stderr
    assert time.monotonic() - t < 60
    cases = {
        "experiments:\n  default:\n    stylize:\n      lr: .inf\n": "experiments.default.stylize.lr: inf is not a finite",
        "experiments:\n  default:\n    stylize:\n      lrr: 0.1\n": "experiments.default.stylize: Additional properties",
        "scenes:\n  ant: {source: procedural, kind: content, name: ant, n_gaussians: 1000000000000}\n":
            "scenes.ant.n_gaussians: 1000000000000 is greater than the maximum",
        "scenes:\n  ant: {source: procedural, kind: content, name: ant, n_gaussians: 900000000}\n":
            "scenes.ant.n_gaussians: 900000000 Gaussians need at least",
        "partitions:\n  default:\n    cluster: {n_clusters: 50000}\n":
            "partitions.default.cluster.n_clusters: 50000 clusters of the 20000 Gaussians of content 'ant'",
        "evaluation:\n  render: {size: 100000}\n": "evaluation.render.size: 100000 is greater than the maximum of 16384",
    }
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(2) as pool:  # independent dry runs, two at a time
        runs = list(pool.map(lambda text: dry_run(tmp_path, text), cases))
    for (text, message), (r, files) in zip(cases.items(), runs):
        assert r.returncode != 0 and f"config {files[0]}: {message}" in r.stderr, (text, r.stderr[-1500:])
        assert len(r.stderr) < 2000  # one message, not the config printed back


# ---- one run in a folder, and what a run reports -------------------------------------------------------


def _wait_for(cond, seconds=60.0):
    import time

    t = time.monotonic()
    while not cond():
        assert time.monotonic() - t < seconds, "timed out waiting"
        time.sleep(0.05)


def test_a_run_after_a_kill_of_wast3d_is_refused_while_its_snakemake_works(tmp_path):
    """The folder lock is the wast3d process's, inherited by its Snakemake: kill -9 of wast3d leaves it held
    (a second run is refused, naming the holder), the end of that Snakemake frees it (a third run works);
    the result of a run given targets of its own is not reported as built."""
    import signal

    import psutil

    c, s = tmp_path / "blob.ply", tmp_path / "peb.ply"
    write_ply(c, random_scene(3000, seed=1))
    write_ply(s, random_scene(300, seed=2))
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "wast3d", "run", str(c), str(s), str(out), "--", "results/scenes/blob/preview.png",
           "results/scenes/peb/preview.png", "results/scenes/blob/surface.ply"]
    first = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    me = psutil.Process(first.pid)
    _wait_for(lambda: any("snakemake" in " ".join(p.cmdline()) for p in me.children()))
    smk = next(p for p in me.children() if "snakemake" in " ".join(p.cmdline()))
    first.send_signal(signal.SIGKILL)
    first.wait()
    r = subprocess.run(cmd, capture_output=True, text=True)
    alive = smk.is_running()
    assert alive, "the orphaned Snakemake ended before the second run looked: make its jobs longer"
    assert r.returncode == 2 and "another run works in this folder" in r.stderr and f"pid {first.pid}" in r.stderr, r.stderr
    smk.wait(300)
    r = subprocess.run(cmd, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "is not built" in r.stderr and "done. Result" not in r.stderr


def test_a_live_snakemake_in_the_folder_is_found_whatever_its_d(tmp_path):
    """Snakemake changes into its -d folder: a relative -d is found by the process's working folder."""
    from wast3d.quickstart import snakemake_running_in

    out = tmp_path / "out"
    out.mkdir()
    fake = tmp_path / "bin" / "snakemake"
    fake.parent.mkdir()
    fake.write_text("import os, sys, time\nos.chdir(sys.argv[2])\nprint('ready', flush=True)\ntime.sleep(60)\n")
    p = subprocess.Popen([sys.executable, str(fake), "-d", "out"], cwd=tmp_path, stdout=subprocess.PIPE, text=True)
    try:
        assert p.stdout.readline().strip() == "ready"
        assert snakemake_running_in(out) == [p.pid]
        assert snakemake_running_in(tmp_path) == []
    finally:
        p.kill()
        p.wait()


def test_a_reader_that_leaves_gets_no_traceback(tmp_path):
    """``wast3d info x.ply | head -1``: the pipe closes before info has written; nothing more is said."""
    write_ply(tmp_path / "s.ply", random_scene(50, seed=6))
    r_fd, w_fd = os.pipe()
    os.close(r_fd)
    p = subprocess.run([sys.executable, "-m", "wast3d", "info", str(tmp_path / "s.ply")], stdout=w_fd,
                       stderr=subprocess.PIPE, text=True)
    os.close(w_fd)
    assert p.returncode == 0 and "Traceback" not in p.stderr and "BrokenPipe" not in p.stderr, p.stderr

"""A corpus of hostile and careless inputs (small files, names, configs, folders) for every command that
reads what a user gives, and the runner that checks each answer:

- no traceback (an uncaught exception, or ``Traceback`` in what the command or its Snakemake printed);
- a case marked invalid exits non-zero, and its message names what it must (the file, the field);
- a valid case exits 0;
- no input changes (size, modification time and inode of every file under ``inp/``);
- memory stays bounded (the runner's resident memory, with its children's, grows by less than
  MEMORY_LIMIT during a case) and time too (TIME_LIMIT).

A new reader or command joins by a line in :data:`COMMANDS` (it then runs over every scene file of the
corpus) or a :class:`Case` in :func:`cases`. ``tests/test_hostile_corpus.py`` runs it all; as a script it
compares checkouts side by side (an older commit: ``git worktree add /tmp/before COMMIT``):

    python tests/hostile_corpus.py [--tree LABEL=CHECKOUT ...] [--out results/benchmarks/hostile_corpus.csv]
"""

from __future__ import annotations

import argparse
import contextlib
import gzip
import json
import math
import os
import signal
import struct
import subprocess
import sys
import tempfile
import threading
import time
import traceback
import zlib
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
MEMORY_LIMIT = 2 << 30  # bytes a case may add to the resident memory of the runner and its children (a dry run
# of the workflow imports torch to read a scene: 0.8 GB)
HARD_LIMIT = 6 << 30  # address space the runner may add at all: past it an allocation fails, not the machine
TIME_LIMIT = 60  # seconds a case may take (each takes under 6 here); past it the case is stopped


@dataclass(frozen=True)
class Case:
    """One command over one input: ``argv`` of ``wast3d`` (or of ``snakemake`` when ``tool`` says so),
    with ``{d}`` for the corpus folder (inputs under ``{d}/inp``, outputs under ``{d}/out``); ``valid``:
    whether the command must succeed; ``names``: what an invalid case's message must hold."""

    name: str
    argv: tuple[str, ...]
    valid: bool
    names: str = ""
    tool: str = "wast3d"


# ---- the inputs --------------------------------------------------------------------------------------


def _scene(n=300, seed=0):
    from wast3d.procedural import make_scene

    return make_scene("style", "pebbles", n, seed)


def _ply_variant(inp: Path, name: str, edit, compressed: bool = False) -> None:
    from plyfile import PlyData

    src = inp / ("_src.compressed.ply" if compressed else "_src.ply")
    ply = PlyData.read(str(src))
    edit(ply)
    ply.write(str(inp / name))


def _spz_legacy(path: Path, n: int, version=2, bits=12, deg=0, zeros_after=0, body=None) -> None:
    from wast3d.spz import LEGACY_HEADER, MAGIC

    c = zlib.compressobj(6, zlib.DEFLATED, 31)
    parts = [c.compress(LEGACY_HEADER.pack(MAGIC, version, n, deg, bits, 0, 0))]
    parts.append(c.compress(body if body is not None else bytes(n * (9 + 1 + 3 + 3 + 3))))
    for _ in range(zeros_after >> 24):
        parts.append(c.compress(bytes(1 << 24)))
    path.write_bytes(b"".join(parts) + c.flush())


def _blender(root: Path, frames: int = 3, size: int = 16) -> None:
    import torch

    from wast3d.cameras import Camera, look_at
    from wast3d.datasets import write_blender

    cams, imgs, alphas = [], [], []
    for i in range(frames):
        a = 2 * math.pi * i / frames
        cams.append(Camera(look_at((3 * math.cos(a), 3 * math.sin(a), 1.0), (0, 0, 0)), 20.0, 20.0, size / 2, size / 2,
                           size, size))
        imgs.append(torch.rand(size, size, 3) * 0.5)
        alphas.append(torch.full((size, size), 0.5))
    write_blender(root, cams, imgs, alphas)


def _edit_json(root: Path, edit) -> None:
    meta = json.loads((root / "transforms_train.json").read_text())
    meta = edit(meta)
    (root / "transforms_train.json").write_text(json.dumps(meta))


def make_inputs(d: Path) -> None:
    """Write every input of the corpus under ``d/inp`` (a few MB; the decompression bomb is a small file)."""
    import shutil

    import imageio.v3 as iio
    from plyfile import PlyData

    from wast3d.formats import write_scene
    from wast3d.ply import write_ply

    inp = d / "inp"
    inp.mkdir(parents=True)
    s = _scene()
    write_ply(inp / "_src.ply", s)
    write_scene(inp / "_src.compressed.ply", s)
    for ext in ("ply", "compressed.ply", "spz", "splat"):
        write_scene(inp / f"ok.{ext}", s)
    write_ply(inp / "ok2.ply", _scene(300, 1))
    raw = (inp / "_src.ply").read_bytes()
    n = len(s)

    # PLY
    _ply_variant(inp, "nan.ply", lambda p: p["vertex"]["x"].__setitem__(3, np.nan))
    _ply_variant(inp, "logscale.ply", lambda p: p["vertex"]["scale_0"].__setitem__(5, 1000.0))
    _ply_variant(inp, "zero_quat.ply", lambda p: [p["vertex"][f"rot_{i}"].__setitem__(2, 0.0) for i in range(4)])
    _ply_variant(inp, "chunk.compressed.ply", lambda p: p["chunk"]["min_scale_x"].__setitem__(0, 1e30), compressed=True)
    (inp / "short_header.ply").write_bytes(raw.replace(f"element vertex {n}\n".encode(), f"element vertex {n - 10}\n".encode(), 1))
    (inp / "truncated.ply").write_bytes(raw[:len(raw) - 100])
    (inp / "truncated_header.ply").write_bytes(raw[:60])
    (inp / "empty_file.ply").write_bytes(b"")
    (inp / "random.ply").write_bytes(np.random.default_rng(0).integers(0, 256, 4096, np.uint8).tobytes())
    (inp / "text.ply").write_text("hello\n")
    big = raw.replace(b"format binary_little_endian 1.0\n", b"format binary_little_endian 1.0\ncomment " + b"x" * (3 << 20) + b"\n", 1)
    (inp / "long_comment.ply").write_bytes(big)
    v = PlyData.read(str(inp / "_src.ply"))["vertex"]
    from plyfile import PlyData as PD, PlyElement

    PD([PlyElement.describe(np.empty(0, v.data.dtype), "vertex")], text=False, byte_order="<").write(str(inp / "zero.ply"))
    faces = np.empty(100, dtype=[("vertex_indices", object)])
    faces["vertex_indices"] = [np.array([0, 1, 2], np.int32)] * 100
    PD([v, PlyElement.describe(faces, "face")], text=False, byte_order="<").write(str(inp / "faces.ply"))
    fr = (inp / "faces.ply").read_bytes()
    (inp / "faces_short.ply").write_bytes(fr.replace(f"element vertex {n}\n".encode(), f"element vertex {n - 100}\n".encode(), 1)
                                          + bytes(32000))
    names = [p.name for p in v.properties if p.name != "f_dc_1"]
    kept = np.empty(len(v.data), dtype=[(k, v.data.dtype[k]) for k in names])
    for k in names:
        kept[k] = v.data[k]
    PD([PlyElement.describe(kept, "vertex")], text=False, byte_order="<").write(str(inp / "missing_field.ply"))
    # SPZ
    _spz_legacy(inp / "frac200.spz", 10, bits=200)
    _spz_legacy(inp / "frac40.spz", 10, bits=40)
    _spz_legacy(inp / "bomb.spz", 10, zeros_after=64 << 20)
    _spz_legacy(inp / "sh9.spz", 10, deg=9)
    _spz_legacy(inp / "v7.spz", 10, version=7)
    from wast3d.spz import HEADER, MAGIC, _sizes

    sizes = [sz for _, sz in _sizes(4_000_000_000, 0, 4) if sz]
    (inp / "huge_count.spz").write_bytes(HEADER.pack(MAGIC, 4, 4_000_000_000, 0, 12, 0, len(sizes), HEADER.size)
                                         + b"".join(struct.pack("<QQ", 8, sz) for sz in sizes) + bytes(40))
    (inp / "zero_count.spz").write_bytes(gzip.compress(bytes(16)))
    ok = (inp / "ok.spz").read_bytes()
    (inp / "truncated.spz").write_bytes(ok[:len(ok) // 2])
    (inp / "bad_magic.spz").write_bytes(b"\x00" * 64)
    # .splat
    sp = (inp / "ok.splat").read_bytes()
    (inp / "ragged.splat").write_bytes(sp[:-5])
    (inp / "empty.splat").write_bytes(b"")
    rec = bytearray(sp)
    rec[0:4] = struct.pack("<f", float("nan"))
    (inp / "nan.splat").write_bytes(bytes(rec))
    (inp / "unknown.xyz").write_bytes(raw)
    shutil.copy(inp / "ok.ply", inp / "-n.ply")
    shutil.copy(inp / "ok.ply", inp / "a{scene}b.ply")
    (inp / "link.spz").symlink_to("ok.spz")
    (inp / "a_file").write_text("x")
    (inp / "a_folder.ply").mkdir()
    # pictures
    iio.imwrite(inp / "ok.png", np.full((20, 20, 3), 128, np.uint8))
    iio.imwrite(inp / "grey_alpha.png", np.full((20, 20, 2), 200, np.uint8))
    (inp / "corrupt.png").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(200))
    (inp / "text.png").write_text("not a picture\n")
    # Blender folders
    _blender(inp / "bl_ok")
    bad = {
        "bl_singular": lambda m: {**m, "frames": [{**f, "transform_matrix": [[0] * 4] * 3 + [[0, 0, 0, 1]]} for f in m["frames"]]},
        "bl_fov0": lambda m: {**m, "camera_angle_x": 0},
        "bl_fov_pi": lambda m: {**m, "camera_angle_x": math.pi},
        "bl_fov_neg": lambda m: {**m, "camera_angle_x": -0.5},
        "bl_fov_str": lambda m: {**m, "camera_angle_x": "wide"},
        "bl_fov_nan": lambda m: {**m, "camera_angle_x": float("nan")},
        "bl_frame_number": lambda m: {**m, "frames": [7] + m["frames"][1:]},
        "bl_path_number": lambda m: {**m, "frames": [{**m["frames"][0], "file_path": 12}] + m["frames"][1:]},
        "bl_top_string": lambda m: "frames",
        "bl_ragged": lambda m: {**m, "frames": [{**m["frames"][0], "transform_matrix": [[1, 0, 0], [0, 1, 0, 0]]}]},
        "bl_matrix_str": lambda m: {**m, "frames": [{**m["frames"][0], "transform_matrix": "eye"}] + m["frames"][1:]},
        "bl_no_frames": lambda m: {"camera_angle_x": m["camera_angle_x"]},
        "bl_missing_image": lambda m: {**m, "frames": [{**m["frames"][0], "file_path": "./train/nothing"}] + m["frames"][1:]},
    }
    for name, edit in bad.items():
        shutil.copytree(inp / "bl_ok", inp / name)
        _edit_json(inp / name, edit)
    shutil.copytree(inp / "bl_ok", inp / "bl_one_frame")
    _edit_json(inp / "bl_one_frame", lambda m: {**m, "frames": m["frames"][:1]})
    shutil.copytree(inp / "bl_ok", inp / "bl_grey_alpha")
    iio.imwrite(inp / "bl_grey_alpha" / "train" / "r_0.png", np.full((16, 16, 2), 200, np.uint8))
    shutil.copytree(inp / "bl_ok", inp / "bl_outside")
    shutil.copy(inp / "bl_ok" / "train" / "r_0.png", inp / "outside.png")
    _edit_json(inp / "bl_outside", lambda m: {**m, "frames": [{**m["frames"][0], "file_path": "../outside"}] + m["frames"][1:]})
    (inp / "bl_badjson").mkdir()
    (inp / "bl_badjson" / "transforms_train.json").write_text("{ not json")
    # configs and regions files
    deep = "a: " + "[" * 20000 + "]" * 20000 + "\n"
    (inp / "deep.yaml").write_text(deep)
    (inp / "deep_regions.yaml").write_text("- " * 3000 + "1\n")
    (inp / "empty.yaml").write_text("")
    (inp / "list.yaml").write_text("- 1\n- 2\n")
    (inp / "binary.yaml").write_bytes(bytes(range(256)) * 4)
    (inp / "dup.yaml").write_text("experiments:\n  a: {}\nexperiments:\n  b: {}\n")
    rows = ["l0: &l0 [" + ", ".join(["x"] * 10) + "]"]
    rows += [f"l{k}: &l{k} [" + ", ".join([f"*l{k - 1}"] * 10) + "]" for k in range(1, 9)]
    (inp / "alias_bomb.yaml").write_text("\n".join(rows) + "\n")
    (inp / "preview_size.yaml").write_text("preview: {size: 200000}\n")
    (inp / "preview_views.yaml").write_text("preview: {views: 1000000}\n")
    (inp / "lr_inf.yaml").write_text("experiments:\n  default:\n    stylize:\n      lr: .inf\n")
    (inp / "unknown_key.yaml").write_text("experiments:\n  default:\n    stylize:\n      lrr: 0.1\n")
    (inp / "missing_scene.yaml").write_text(f"scenes:\n  ghost: {{source: ply, path: {inp}/nothing.ply}}\n"
                                            "pairs: [[ghost, pebbles]]\ntable1: {pairs: [[ghost, pebbles]]}\n")
    (inp / "own_results.yaml").write_text("scenes:\n  ghost: {source: ply, path: results/scenes/ghost/scene.ply}\n"
                                          "pairs: [[ghost, pebbles]]\ntable1: {pairs: [[ghost, pebbles]]}\n")
    (inp / "regions_offset.yaml").write_text("- {style: 0, half_space: {normal: [0, 0, 1], offset: abc}}\n- {style: 1, rest: true}\n")
    (inp / "regions_bool.yaml").write_text("- {style: true, box: {min: [0, 0, 0], max: [1, 1, 1]}}\n- {style: 1, rest: true}\n")
    (inp / "regions_boolbox.yaml").write_text("- {style: 0, box: {min: [false, 0, 0], max: [true, 1, 1]}}\n- {style: 1, rest: true}\n")
    (inp / "regions_ok.yaml").write_text("- {style: 0, half_space: {normal: [0, 0, 1], offset: 0.0}}\n- {style: 1, rest: true}\n")
    # an OUT whose results hold a scene, and a config edited by hand
    res = inp / "prior" / "results" / "scenes" / "c"
    res.mkdir(parents=True)
    shutil.copy(inp / "ok.ply", res / "scene.ply")
    (inp / "into_results.ply").symlink_to(res / "scene.ply")
    edited = inp / "edited" / "config"
    edited.mkdir(parents=True)
    (edited / "config.yaml").write_text(f"# mine\nscenes:\n  ok: {{source: ply, path: {inp}/ok.ply}}\n"
                                        f"  ok2: {{source: ply, path: {inp}/ok2.ply}}\n  ok_2: {{source: ply, path: {inp}/ok2.ply}}\n"
                                        "pairs: [[ok, ok2]]\n")


# ---- the cases ---------------------------------------------------------------------------------------

# every command that reads a scene file a user gives: (name, argv after the input, whether it writes)
COMMANDS = {
    "info": (),
    "export": ("{d}/out/{case}.spz",),
    "import-ply": ("{d}/out/{case}.ply",),
    "preview": ("{d}/out/{case}.png", "--views", "1", "--size", "32"),
}
# scene files: name -> (valid, what an error must name)
SCENE_FILES = {
    "ok.ply": (True, ""), "ok.compressed.ply": (True, ""), "ok.spz": (True, ""), "ok.splat": (True, ""),
    "faces.ply": (True, ""), "link.spz": (True, ""),
    "nan.ply": (False, "field 'position'"), "logscale.ply": (False, "field 'scale'"),
    "zero_quat.ply": (False, "field 'rotation'"), "chunk.compressed.ply": (False, "field 'scale'"),
    "short_header.ply": (False, "more rows than the header counts"), "truncated.ply": (False, "truncated.ply"),
    "truncated_header.ply": (False, "truncated_header.ply"), "empty_file.ply": (False, "empty_file.ply"),
    "random.ply": (False, "random.ply"), "text.ply": (False, "text.ply"), "long_comment.ply": (False, "end_header"),
    "zero.ply": (False, "no Gaussians"), "faces_short.ply": (False, "more rows than the header counts"),
    "missing_field.ply": (False, "f_dc_1"), "frac200.spz": (False, "fractionalBits"), "frac40.spz": (False, "fractionalBits"),
    "bomb.spz": (False, "holds more than the"), "sh9.spz": (False, "shDegree"), "v7.spz": (False, "version"),
    "huge_count.spz": (False, "numPoints"), "zero_count.spz": (False, "zero_count.spz"), "truncated.spz": (False, "truncated.spz"),
    "bad_magic.spz": (False, "bad_magic.spz"), "ragged.splat": (False, "32-byte"), "empty.splat": (False, "empty.splat"),
    "nan.splat": (False, "field 'position'"), "unknown.xyz": (False, "unknown scene format"), "nothing.ply": (False, "nothing.ply"),
    "a_folder.ply": (False, "a_folder.ply"),
}
BLENDER = {
    "bl_singular": "transform_matrix", "bl_fov0": "camera_angle_x", "bl_fov_pi": "camera_angle_x",
    "bl_fov_neg": "camera_angle_x", "bl_fov_str": "camera_angle_x", "bl_fov_nan": "camera_angle_x",
    "bl_frame_number": "frames[0]", "bl_path_number": "file_path", "bl_top_string": "JSON object",
    "bl_ragged": "transform_matrix", "bl_matrix_str": "transform_matrix", "bl_no_frames": "frames",
    "bl_missing_image": "nothing.png", "bl_badjson": "invalid JSON", "bl_nothing": "transforms_train.json",
}
SNAKEMAKE = ("-s", "{root}/Snakefile", "-d", "{d}/out/{case}", "-n", "-q", "--configfile", "{root}/config/config.yaml")


def cases() -> list[Case]:
    """Every case of the corpus."""
    out = []
    for cmd, rest in COMMANDS.items():
        for f, (valid, names) in SCENE_FILES.items():
            out.append(Case(f"{cmd} {f}", (cmd, f"{{d}}/inp/{f}", *rest), valid, names))
    out += [
        Case("export onto its input", ("export", "{d}/inp/ok.spz", "{d}/inp/ok.spz"), False, "is the input"),
        Case("export onto its input through a link", ("export", "{d}/inp/ok.spz", "{d}/inp/link.spz"), False, "is the input"),
        Case("import-ply onto its input", ("import-ply", "{d}/inp/ok.ply", "{d}/inp/ok.ply"), False, "is the input"),
        Case("export to a folder", ("export", "{d}/inp/ok.ply", "{d}/inp/a_folder.ply"), False, "is a folder"),
        Case("export under a file", ("export", "{d}/inp/ok.ply", "{d}/inp/a_file/x.spz"), False, "a_file is a file"),
        Case("preview under a file", ("preview", "{d}/inp/ok.ply", "{d}/inp/a_file/x.png"), False, "a_file is a file"),
        Case("import-ply under a file", ("import-ply", "{d}/inp/ok.ply", "{d}/inp/a_file/x.ply"), False, "a_file is a file"),
        Case("preview --size 200000", ("preview", "{d}/inp/ok.ply", "{d}/out/p.png", "--size", "200000"), False, "--size"),
        Case("preview --views 1000000", ("preview", "{d}/inp/ok.ply", "{d}/out/p.png", "--views", "1000000"), False, "--views"),
        Case("info -- -n.ply", ("info", "--", "{d}/inp/-n.ply"), True),
        Case("info --drop-invalid nan.ply", ("info", "{d}/inp/nan.ply", "--drop-invalid"), True),
        Case("export --drop-invalid nan.ply", ("export", "{d}/inp/nan.ply", "{d}/out/dropped.spz", "--drop-invalid"), True),
        Case("strip", ("strip", "{d}/out/strip.png", "A={d}/inp/ok.png", "B={d}/inp/grey_alpha.png"), True),
        Case("strip onto its input", ("strip", "{d}/inp/ok.png", "A={d}/inp/ok.png"), False, "is the input"),
        Case("strip corrupt picture", ("strip", "{d}/out/s.png", "A={d}/inp/corrupt.png"), False, "corrupt.png"),
        Case("strip text as picture", ("strip", "{d}/out/s.png", "A={d}/inp/text.png"), False, "text.png"),
        Case("strip a folder as picture", ("strip", "{d}/out/s.png", "A={d}/inp/bl_ok"), False, "bl_ok"),
        Case("strip into a folder", ("strip", "{d}/inp/bl_ok", "A={d}/inp/ok.png"), False, "is a folder"),
        Case("strip a missing picture", ("strip", "{d}/out/s.png", "A={d}/inp/none.png"), False, "none.png"),
        Case("strip no LABEL=", ("strip", "{d}/out/s.png", "{d}/inp/ok.png"), False, "LABEL=FOLDER"),
        Case("compare a corrupt picture", ("compare", "{d}/out/c.png", "A={d}/inp/bad_render"), False, "closeup_rgb.png"),
        Case("view --port 99999", ("view", "{d}/inp/ok.ply", "--port", "99999"), False, "--port"),
        Case("view --port -1", ("view", "{d}/inp/ok.ply", "--port", "-1"), False, "--port"),
        Case("view --host 256.1.1.1", ("view", "{d}/inp/ok.ply", "--host", "256.1.1.1"), False, "--host"),
        Case("view --max-gaussians -5", ("view", "{d}/inp/ok.ply", "--max-gaussians", "-5"), False, "--max-gaussians"),
        Case("view a NaN scene", ("view", "{d}/inp/nan.ply", "--port", "0"), False, "field 'position'"),
        Case("view a missing scene", ("view", "{d}/inp/nothing.ply", "--port", "0"), False, "nothing.ply"),
        Case("stage --params not JSON", ("cluster", "--content", "{d}/inp/ok.ply", "--out-npz", "{d}/out/c.npz",
                                         "--params", "{x"), False, "--params"),
        Case("stage output onto its input", ("cluster", "--content", "{d}/inp/ok.ply", "--out-npz", "{d}/inp/ok.ply"),
             False, "is the input"),
    ]
    pre = ("--out-ply", "{d}/out/{case}/s.ply", "--out-csv", "{d}/out/{case}/s.csv", "--out-json", "{d}/out/{case}/s.json",
           "--no-progress", "--params", '{"iterations": 2, "init_points": 200}')
    for name, names in BLENDER.items():
        out.append(Case(f"pretrain {name}", ("pretrain", "--data", f"{{d}}/inp/{name}", *pre), False, names))
    for name in ("bl_ok", "bl_one_frame", "bl_grey_alpha", "bl_outside"):
        out.append(Case(f"pretrain {name}", ("pretrain", "--data", f"{{d}}/inp/{name}", *pre), True))
    run = ("run",)
    out += [
        Case("run: content inside OUT's results", (*run, "{d}/inp/prior/results/scenes/c/scene.ply", "{d}/inp/ok2.ply",
                                                   "{d}/inp/prior", "-n"), False, "lies inside"),
        Case("run: content linked into OUT's results", (*run, "{d}/inp/into_results.ply", "{d}/inp/ok2.ply", "{d}/inp/prior",
                                                        "-n"), False, "lies inside"),
        Case("run: a wildcard in a name", (*run, "{d}/inp/a{scene}b.ply", "{d}/inp/ok2.ply", "{d}/out/w", "-n"), False,
             "is a wildcard"),
        Case("run: a name not UTF-8", (*run, "{d}/inp/c\udcff.ply", "{d}/inp/ok2.ply", "{d}/out/u", "-n"), False, "not UTF-8"),
        Case("run: OUT ./-out", (*run, "{d}/inp/ok.ply", "{d}/inp/ok2.ply", "./-out", "-n"), True),
        Case("run: OUT a file", (*run, "{d}/inp/ok.ply", "{d}/inp/ok2.ply", "{d}/inp/a_file", "-n"), False, "must be a folder"),
        Case("run: a missing content", (*run, "{d}/inp/nothing.ply", "{d}/inp/ok2.ply", "{d}/out/m", "-n"), False, "nothing.ply"),
        Case("run: --split on an edited config", (*run, "{d}/inp/ok.ply", "{d}/inp/ok2.ply", "{d}/inp/ok2.ply",
                                                  "{d}/inp/edited", "--split=z=0", "-n"), False, "edited by hand"),
        Case("run: --regions /dev/zero", (*run, "{d}/inp/ok.ply", "{d}/inp/ok2.ply", "{d}/inp/ok.spz", "{d}/out/z",
                                          "--regions", "/dev/zero", "-n"), False, "not a regular file"),
        Case("run: a 3,000-deep regions file", (*run, "{d}/inp/ok.ply", "{d}/inp/ok2.ply", "{d}/inp/ok.spz", "{d}/out/r",
                                                "--regions", "{d}/inp/deep_regions.yaml", "-n"), False, "nested more than"),
        Case("run: region offset abc", (*run, "{d}/inp/ok.ply", "{d}/inp/ok2.ply", "{d}/inp/ok.spz", "{d}/out/o",
                                        "--regions", "{d}/inp/regions_offset.yaml", "-n"), False, "offset"),
        Case("run: region style true", (*run, "{d}/inp/ok.ply", "{d}/inp/ok2.ply", "{d}/inp/ok.spz", "{d}/out/b",
                                        "--regions", "{d}/inp/regions_bool.yaml", "-n"), False, "yes/no"),
        Case("run: region box of booleans", (*run, "{d}/inp/ok.ply", "{d}/inp/ok2.ply", "{d}/inp/ok.spz", "{d}/out/bb",
                                             "--regions", "{d}/inp/regions_boolbox.yaml", "-n"), False, "3 finite numbers"),
        Case("run: regions", (*run, "{d}/inp/ok.ply", "{d}/inp/ok2.ply", "{d}/inp/ok.spz", "{d}/out/rr",
                              "--regions", "{d}/inp/regions_ok.yaml", "-n"), True),
    ]
    for f, names in (("deep.yaml", "nested more than"), ("empty.yaml", "empty"), ("list.yaml", "mapping"),
                     ("binary.yaml", "not UTF-8"), ("dup.yaml", "given twice")):
        out.append(Case(f"run -- --configfile {f}", (*run, "{d}/inp/ok.ply", "{d}/inp/ok2.ply", "{d}/out/cf", "-n", "--",
                                                     "--configfile", f"{{d}}/inp/{f}"), False, names))
    for f, names in (("dup.yaml", "given twice"), ("alias_bomb.yaml", "more than 100000 values"),
                     ("preview_size.yaml", "preview.size"), ("preview_views.yaml", "preview.views"),
                     ("lr_inf.yaml", "finite"), ("own_results.yaml", "the scene's own results"), ("unknown_key.yaml", "lrr"), ("missing_scene.yaml", "scenes.ghost.path")):
        out.append(Case(f"snakemake --configfile {f}", (*SNAKEMAKE, f"{{d}}/inp/{f}"), False, names, tool="snakemake"))
    return out


# ---- the runner --------------------------------------------------------------------------------------


def _inputs(d: Path) -> dict[str, tuple]:
    return {str(p): (s.st_size, s.st_mtime_ns, s.st_ino) for p in (d / "inp").rglob("*") for s in [p.lstat()]}


class _Peak:
    """The peak resident memory of this process and its children, sampled every 10 ms in a thread."""

    def __init__(self):
        import psutil

        self.me, self.peak, self.stop = psutil.Process(), 0, threading.Event()

    def rss(self) -> int:
        import psutil

        total = 0
        for p in [self.me, *self.me.children(recursive=True)]:
            try:
                total += p.memory_info().rss
            except psutil.Error:
                pass
        return total

    def __enter__(self):
        self.base = self.rss()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()
        return self

    def _run(self):
        while not self.stop.wait(0.01):
            self.peak = max(self.peak, self.rss())

    def __exit__(self, *exc):
        self.stop.set()
        self.thread.join()
        self.peak = max(self.peak, self.rss())
        self.growth = max(self.peak - self.base, 0)


@contextlib.contextmanager
def _captured():
    """Everything written to file descriptors 1 and 2 (this process's and its children's) into a file."""
    f = tempfile.TemporaryFile()
    sys.stdout.flush()
    sys.stderr.flush()
    saved = os.dup(1), os.dup(2)
    os.dup2(f.fileno(), 1)
    os.dup2(f.fileno(), 2)
    box = {}
    try:
        yield box
    finally:
        sys.stdout.flush()
        sys.stderr.flush()
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        os.close(saved[0])
        os.close(saved[1])
        f.seek(0)
        box["text"] = f.read().decode(errors="replace")
        f.close()


def run_case(case: Case, d: Path, root: Path) -> dict:
    """Run ``case`` in this process (``wast3d``'s main, so each costs no interpreter start) or, for
    ``snakemake``, in a child -> its result row (rc, message, seconds, memory growth, verdict)."""
    import logging

    from wast3d import cli

    sub = {"d": str(d), "case": "".join(c if c.isalnum() else "_" for c in case.name), "root": str(root)}
    argv = [a.replace("{d}", sub["d"]).replace("{case}", sub["case"]).replace("{root}", sub["root"]) for a in case.argv]
    before = _inputs(d)
    t0 = time.monotonic()
    crashed = None

    def stop(*_):
        raise TimeoutError(f"still running after {TIME_LIMIT} s")

    signal.signal(signal.SIGALRM, stop)
    with _Peak() as peak, _captured() as out:
        for h in logging.root.handlers[:]:  # main() installs its handler on the stream of this case
            logging.root.removeHandler(h)
        signal.alarm(TIME_LIMIT)
        try:
            if case.tool == "snakemake":
                rc = subprocess.run([sys.executable, "-m", "snakemake", *argv], timeout=TIME_LIMIT).returncode
            else:
                rc = cli.main(argv)
        except SystemExit as e:  # argparse
            rc = e.code if isinstance(e.code, int) else 1
        except (subprocess.TimeoutExpired, TimeoutError):
            rc = "timeout"
        except BaseException:  # noqa: BLE001 - what escapes main is the finding
            crashed = traceback.format_exc()
            rc = "traceback"
        finally:
            signal.alarm(0)
    seconds = time.monotonic() - t0
    text = out["text"] + (crashed or "")
    after = _inputs(d)
    changed = sorted(k for k in set(before) | set(after) if before.get(k) != after.get(k))
    lines = [ln for ln in text.splitlines() if ln.strip()]
    msg = next((ln for ln in lines if "ERROR" in ln or "Error" in ln or "error:" in ln), lines[-1] if lines else "")
    if rc == "timeout":
        verdict = f"still running after {TIME_LIMIT} s"
    elif any(w in text for w in ("MemoryError", "bad_alloc", "can't allocate memory", "Cannot allocate memory")):
        verdict = f"memory: an allocation past {HARD_LIMIT >> 30} GiB failed"
    elif "Traceback" in text:
        verdict = "traceback"
    elif changed:
        verdict = "changed " + ", ".join(Path(c).name for c in changed[:3])
    elif peak.growth > MEMORY_LIMIT:
        verdict = f"memory grew {peak.growth / 2**20:.0f} MB"
    elif seconds > TIME_LIMIT:
        verdict = f"took {seconds:.0f} s"
    elif case.valid:
        verdict = "ok" if rc == 0 else f"exit {rc} on a valid case"
    elif rc == 0:
        verdict = "exit 0 on an invalid case"
    elif case.names and case.names not in text:
        verdict = f"message does not name {case.names!r}"
    else:
        verdict = "ok"
    return {"case": case.name, "valid": case.valid, "rc": rc, "verdict": verdict, "seconds": round(seconds, 2),
            "memory_mb": round(peak.growth / 2**20, 1), "message": msg.strip()[:240]}


def run_corpus(d: Path, root: Path, names: list[str] | None = None) -> list[dict]:
    """Make the inputs under ``d`` and run the cases (those named, or all) with the package importable
    from this process (the checkout ``root``'s Snakefile for Snakemake)."""
    import torch  # noqa: F401 - imported before the first case, so that no case's memory counts it

    import wast3d.pretrain  # noqa: F401
    import wast3d.render  # noqa: F401

    import psutil
    import resource

    vm = psutil.Process().memory_info().vms + HARD_LIMIT
    resource.setrlimit(resource.RLIMIT_AS, (vm, vm))  # inherited by the Snakemake it starts
    make_inputs(d)
    (d / "out").mkdir()
    os.chdir(d / "out")  # `./-out` is a relative OUT
    bad = d / "inp" / "bad_render"
    bad.mkdir()
    (bad / "closeup_rgb.png").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(64))
    return [run_case(c, d, root) for c in cases() if names is None or c.name in names]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tree", nargs="*", default=[f"now={ROOT}"], help="LABEL=CHECKOUT ...")
    ap.add_argument("--out", type=Path, default=ROOT / "results" / "benchmarks" / "hostile_corpus.csv")
    ap.add_argument("--runner", type=Path, help=argparse.SUPPRESS)  # internal: run here, write JSON rows there
    a = ap.parse_args()
    if a.runner:
        with tempfile.TemporaryDirectory() as d:
            rows = run_corpus(Path(d), Path(os.environ["WAST3D_TREE"]))
        a.runner.write_text(json.dumps(rows))
        return
    import pandas as pd

    table = None
    for spec in a.tree:
        label, path = spec.split("=", 1)
        with tempfile.NamedTemporaryFile(suffix=".json") as f:
            env = {**os.environ, "PYTHONPATH": path, "WAST3D_TREE": path}
            subprocess.run([sys.executable, __file__, "--runner", f.name], env=env, check=True)
            df = pd.DataFrame(json.loads(Path(f.name).read_text())).set_index(["case", "valid"])
        df.columns = [f"{label}_{c}" for c in df.columns]
        table = df if table is None else table.join(df, how="outer")
        print(f"{label}: {int((df[f'{label}_verdict'] == 'ok').sum())} of {len(df)} ok", flush=True)
    from wast3d.io_utils import atomic_path

    with atomic_path(a.out) as tmp:
        table.reset_index().to_csv(tmp, index=False)
    with atomic_path(a.out.with_suffix(".md")) as tmp:
        tmp.write_text(table.reset_index().to_markdown(index=False) + "\n")
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()

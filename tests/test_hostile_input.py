"""Hostile and careless input: file names that would run commands, a user's edits, dry runs that must
write nothing. The workflow's jobs are real (Snakemake runs them), on paths holding a space, an
apostrophe, ``;``, ``$(...)`` and a backtick, from an interpreter under such a folder."""

import os
import shlex
import subprocess
import sys
from pathlib import Path

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
    edited = cfg_path.read_text().replace("iterations: 30", "iterations: 7")
    assert edited != cfg_path.read_text()
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
    assert yaml.safe_load(cfg_path.read_text())["experiments"]["default"]["stylize"]["iterations"] == 30

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

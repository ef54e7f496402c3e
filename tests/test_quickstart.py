"""``wast3d run CONTENT STYLE OUT``: the config it writes and the workflow it starts (dry run)."""

import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from conftest import random_scene
from wast3d.ply import write_ply
from wast3d.quickstart import scene_name, two_scene_config

ROOT = Path(__file__).resolve().parents[1]


def test_names_and_config(tmp_path):
    assert scene_name(Path("/x/guitar.compressed.ply"), set()) == "guitar"
    assert scene_name(Path("/r/scenes/pebbles/scene.ply"), set()) == "pebbles"
    assert scene_name(Path("/o/point_cloud/iteration_7000/point_cloud.ply"), set()) == "o"
    assert scene_name(Path("/x/a.ply"), {"a"}) == "a_2" and scene_name(Path("/x/3d-scan.ply"), set()) == "s_3d_scan"
    c, s = tmp_path / "c.ply", tmp_path / "s.ply"
    for p in (c, s):
        write_ply(p, random_scene(50))
    base = yaml.safe_load((ROOT / "config/config.yaml").read_text())
    cfg = two_scene_config(base, c, s)
    assert cfg["scenes"] == {"c": {"source": "ply", "path": str(c)}, "s": {"source": "ply", "path": str(s)}}
    assert cfg["pairs"] == [["c", "s"]] and cfg["table1"]["pairs"] == [["c", "s"]]
    assert set(cfg["experiments"]) == {"default", "selected"} and "sweeps" not in cfg
    assert cfg["experiments"]["default"] == base["experiments"]["default"]  # the project's defaults
    assert cfg["table1"]["methods"] == {m: base["table1"]["methods"][m]  # and its labels
                                        for m in ("default", "colour_ot", "selected", "input")}
    with pytest.raises(ValueError, match="no label for selected"):
        two_scene_config({**base, "table1": {"methods": {"default": "x", "colour_ot": "y", "input": "z"}}}, c, s)
    with pytest.raises(ValueError, match="transforms_train.json"):
        two_scene_config(base, tmp_path, s)
    with pytest.raises(FileNotFoundError, match="nope.ply"):
        two_scene_config(base, tmp_path / "nope.ply", s)
    views = tmp_path / "moss"  # posed images: pretrained as the pair's position says (eq. 1-2 for a style)
    views.mkdir()
    (views / "transforms_train.json").write_text("{}")
    assert two_scene_config(base, c, views)["scenes"]["moss"] == {"source": "images", "kind": "style", "path": str(views)}
    assert two_scene_config(base, views, s)["scenes"]["moss"]["kind"] == "content"


def test_run_writes_the_config_and_starts_the_workflow(tmp_path):
    c, s = tmp_path / "blob.ply", tmp_path / "peb.ply"
    write_ply(c, random_scene(300, seed=1))
    write_ply(s, random_scene(300, seed=2))
    out = tmp_path / "out"
    r = subprocess.run([sys.executable, "-m", "wast3d", "run", str(c), str(s), str(out), "-n"],
                       capture_output=True, text=True, cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-3000:]
    assert not out.exists()  # a dry run writes nothing (tests/test_hostile_input.py)
    for job in ("import_ply", "surface", "cluster", "register", "sinkhorn", "rescale", "evaluate", "table1"):
        assert f"rule {job}:" in r.stdout, job
    assert "results/stylize/blob__peb/default/final.ply" in r.stdout
    bad = subprocess.run([sys.executable, "-m", "wast3d", "run", str(tmp_path / "missing.ply"), str(s), str(out)],
                         capture_output=True, text=True)
    assert bad.returncode == 2 and "missing.ply: file not found" in bad.stderr


def test_a_wheel_carries_its_workflow(tmp_path):
    """`pip wheel .` holds the Snakefile, the rules, schemas, profiles and the default config; installed
    (not editable) into a temporary venv that sees this venv's dependencies but not its editable
    wast3d, `python -m wast3d run` dry-runs from a folder outside the checkout with the wheel's copy."""
    import sysconfig
    import zipfile

    subprocess.run([sys.executable, "-m", "pip", "wheel", str(ROOT), "--no-deps", "--no-build-isolation", "-q",
                    "-w", str(tmp_path / "dist")], check=True, capture_output=True)
    wheel, = (tmp_path / "dist").glob("wast3d-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    for f in ("Snakefile", "config/config.yaml", "workflow/rules/common.smk", "workflow/schemas/config.schema.yaml",
              "workflow/profiles/local/config.yaml", "workflow/report/workflow.rst"):
        assert f"wast3d/_workflow/{f}" in names, f
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    py = venv / "bin" / "python"
    site = Path(subprocess.run([py, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                               capture_output=True, text=True, check=True).stdout.strip())
    (site / "_deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")  # a plain path: no editable finder
    subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "--no-index", "-q", "--target", str(site),
                    str(wheel)], check=True, capture_output=True)
    where = subprocess.run([py, "-c", "import wast3d; print(wast3d.__file__)"], capture_output=True, text=True,
                           cwd=tmp_path).stdout.strip()
    assert where.startswith(str(site)), where
    c, s = tmp_path / "blob.ply", tmp_path / "peb.ply"
    write_ply(c, random_scene(300, seed=1))
    write_ply(s, random_scene(300, seed=2))
    r = subprocess.run([py, "-m", "wast3d", "run", str(c), str(s), str(tmp_path / "out"), "-n"],
                       capture_output=True, text=True, cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-3000:]
    assert str(site / "wast3d" / "_workflow" / "Snakefile") in r.stderr
    assert "rule sinkhorn:" in r.stdout and "results/stylize/blob__peb/default/final.ply" in r.stdout

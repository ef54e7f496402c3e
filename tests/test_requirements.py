"""The constraints and dependencies install on any machine: no pinned local wheel path, URL or VCS."""

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CHECK = ROOT / "requirements" / "check.py"


def run_check(*files):
    return subprocess.run([sys.executable, str(CHECK), *map(str, files)], capture_output=True, text=True)


def test_constraints_and_pyproject_name_no_url_or_local_path():
    r = run_check()
    assert r.returncode == 0, r.stderr


def test_guard_refuses_local_wheel_url_vcs_and_editable(tmp_path):
    good = ROOT / "requirements" / "constraints.txt"
    lines = good.read_text().splitlines()
    cases = {
        "file": "gsplat @ file:///tmp/gs/gsplat-1.5.3-py3-none-any.whl#sha256=515a",
        "url": "foo @ https://example.invalid/foo-1.0.tar.gz",
        "vcs": "git+https://example.invalid/foo.git@v1#egg=foo",
        "editable": "-e .",
        "path": "./wheels/foo-1.0-py3-none-any.whl",
        "unpinned": "numpy>=1.26",
        "find_links": "--find-links /opt/wheels",
    }
    for name, bad in cases.items():
        f = tmp_path / f"{name}.txt"
        f.write_text("\n".join(lines + [bad]) + "\n")
        r = run_check(f)
        assert r.returncode == 1, (name, r.stdout)
        assert f"{f}:{len(lines) + 1}:" in r.stderr, r.stderr


def test_setup_installs_the_extra_with_the_slurm_plugin():
    """The test command installs 'dev': it must carry what the suite imports (the SLURM plugin)."""
    import tomllib

    proj = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    dev = " ".join(proj["optional-dependencies"]["dev"])
    assert "snakemake-executor-plugin-slurm" in dev and "gsplat" in dev and "pytest" in dev
    assert 'WAST3D_EXTRAS:-dev' in (ROOT / "scripts" / "setup.sh").read_text()


def test_setup_stops_before_a_new_venv_without_disk_space(tmp_path):
    """A disk too full for a new .venv is named before pip starts, and no half-made venv is left."""
    scripts = tmp_path / "scripts"
    scripts.mkdir()
    (scripts / "setup.sh").write_text((ROOT / "scripts" / "setup.sh").read_text())
    env = {**os.environ, "WAST3D_NEED_GB": str(10**9)}
    r = subprocess.run(["bash", str(scripts / "setup.sh")], cwd=tmp_path, env=env, capture_output=True, text=True)
    assert r.returncode == 1
    assert str(tmp_path) in r.stderr and "GB free" in r.stderr and "WAST3D_NEED_GB" in r.stderr
    assert not (tmp_path / ".venv").exists()

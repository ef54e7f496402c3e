import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_readme_starts_with_two_commands_and_ci_runs_the_test_one():
    text = (ROOT / "README.md").read_text()
    blocks = re.findall(r"```bash\n(.*?)\n```", text, flags=re.S)
    main_cmd, test_cmd = blocks[0].strip(), blocks[1].strip()
    head = text.split("\n\n")
    assert head[0].startswith("# wast3d") and head[1].count(". ") == 0 and head[1].endswith(".")  # one sentence
    assert "```bash" in head[2] and "```bash" in head[3]
    assert "snakemake" in main_cmd and "pytest" in test_cmd
    ci = (ROOT / ".ci" / "run").read_text().strip().splitlines()
    assert ci[-1].strip() == test_cmd


def test_readme_is_the_products_page():
    """At most 150 lines: what it does, the two commands, your own scenes, what you get, limits; the
    rest lives in docs/."""
    assert len((ROOT / "README.md").read_text().splitlines()) <= 150


def _fake_bin(tmp_path, uid):
    """A PATH with bash's basic tools, `id -u` answering `uid`, and no chromium, slurmctld or munged."""
    import os
    import shutil

    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    for tool in ("bash", "tail", "cat"):
        os.symlink(shutil.which(tool), bin_dir / tool)
    (bin_dir / "id").write_text(f"#!{shutil.which('bash')}\necho {uid}\n")
    (bin_dir / "id").chmod(0o755)
    return str(bin_dir)


def test_system_packages_script_skips_without_root_and_says_what(tmp_path):
    import subprocess

    path = _fake_bin(tmp_path, 1000)
    out = subprocess.run(
        [path + "/bash", str(ROOT / "scripts" / "system_packages.sh")],
        env={"PATH": path}, capture_output=True, text=True, check=False,
    )
    assert out.returncode == 0, out.stderr
    assert "skipped installing chromium slurm-wlm munge (needs root and apt-get)" in out.stdout
    ci = (ROOT / ".ci" / "run").read_text()
    assert "bash scripts/system_packages.sh" in ci

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_readme_starts_with_two_commands_and_ci_runs_the_test_one():
    text = (ROOT / "README.md").read_text()
    blocks = re.findall(r"```bash\n(.*?)\n```", text, flags=re.S)
    main_cmd, test_cmd = blocks[0].strip(), blocks[1].strip()
    head = text.split("\n\n")
    assert head[0].startswith("# wast3d") and "```bash" in head[1] and "```bash" in head[2]
    assert "snakemake" in main_cmd and "pytest" in test_cmd
    ci = (ROOT / ".ci" / "run").read_text().strip().splitlines()
    assert ci[-1].strip() == test_cmd

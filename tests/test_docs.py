"""The documentation: config/README.md generated from the schema and the stages' dataclasses, and
every relative link of the Markdown files resolving."""

import importlib.util
import re
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]


def _config_docs():
    spec = importlib.util.spec_from_file_location("config_docs", ROOT / "workflow" / "scripts" / "config_docs.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_config_readme_is_generated_and_complete():
    cd = _config_docs()
    schema = yaml.safe_load(cd.SCHEMA.read_text())
    assert cd.missing(schema) == []  # every key described, every stage field accepted by the schema
    assert cd.OUT.read_text() == cd.render(schema), "config/README.md is stale: python workflow/scripts/config_docs.py"


def test_config_docs_see_an_undescribed_key_and_an_unaccepted_field():
    cd = _config_docs()
    schema = yaml.safe_load(cd.SCHEMA.read_text())
    schema["$defs"]["experiment"]["properties"]["stylize"]["properties"]["lr"].pop("description")
    del schema["properties"]["evaluation"]["properties"]["texture"]["properties"]["windows"]
    gaps = cd.missing(schema)
    assert "experiments.*.stylize.lr: no description in the schema" in gaps
    assert "evaluation.texture.windows: a TextureConfig field the schema does not accept (declare it with option())" in gaps


LINK = re.compile(r"(?<!!)\[[^\]]*\]\(([^)\s]+)\)|!\[[^\]]*\]\(([^)\s]+)\)")


def markdown_links(text: str) -> list[str]:
    """Relative link targets of a Markdown text (no URLs, no pure #anchors), without their #anchor."""
    out = []
    for m in LINK.finditer(re.sub(r"```.*?```", "", text, flags=re.S)):
        target = (m.group(1) or m.group(2)).split("#")[0]
        if target and not re.match(r"^[a-z]+:", target):
            out.append(target)
    return out


def test_every_relative_markdown_link_resolves():
    files = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")), *sorted(ROOT.glob("*/README.md"))]
    broken = [f"{f.relative_to(ROOT)}: {t}" for f in files for t in markdown_links(f.read_text())
              if not (f.parent / t).exists()]
    assert broken == []
    assert markdown_links("[a](docs/x.md#y) ![p](img.png) [u](https://x.org) [h](#top)") == ["docs/x.md", "img.png"]


# How the project was made lives in git and the closing notes, never in its files: no numbered work
# session, no ticket number, no "since <date>". The patterns are built from parts so that this file
# does not match itself.
HISTORY = re.compile("|".join([
    r"\b" + "sess" + r"ions? \d+",
    r"\b" + "iss" + r"ues? #?\d+",
    r"(?<![\w/&])#\d{1,4}\b(?![0-9a-fA-F])",
    r"\b" + "si" + r"nce (?:\d{4}-\d\d-\d\d|" + "sess" + "ion)",
]), re.I)
TEXT = (".py", ".smk", ".yaml", ".yml", ".md", ".rst", ".sh", ".toml", ".txt", ".cfg", ".c", ".h", ".in", "")


def project_files() -> list[Path]:
    """The files a clone holds (tracked, and new ones not ignored), as git lists them."""
    import subprocess

    out = subprocess.run(["git", "ls-files", "-co", "--exclude-standard"], cwd=ROOT, capture_output=True, text=True,
                         check=True).stdout.split("\n")
    return [ROOT / f for f in out if f and (ROOT / f).is_file() and (ROOT / f).suffix in TEXT]


def test_no_work_history_in_the_project():
    found = [f"{p.relative_to(ROOT)}:{i}: {m.group(0)}" for p in project_files()
             for i, line in enumerate(p.read_text(errors="replace").splitlines(), 1) for m in HISTORY.finditer(line)]
    assert found == [], "\n".join(found[:40])
    for text in ("as measured in " + "sess" + "ion 12", "see " + "iss" + "ue #" + "23", "(#" + "14)",
                 "the default " + "si" + "nce 2026-12-01"):
        assert HISTORY.search(text), text
    for text in ("colour #ff0000", "a session of Python", "github.com/jeanfeydy/geomloss/issues/51"):
        assert not HISTORY.search(text), text


def _merge(base: dict, over: dict) -> dict:
    """Snakemake's merge of config files: mappings merged key by key, anything else replaced."""
    out = dict(base)
    for k, v in over.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def test_config_holds_what_a_user_runs_and_every_study_is_valid():
    """config/ is at most 9 files; each study (studies/NAME/: config.yaml, README.md with its question,
    command, result and verdict) merged over the configs its first line names passes the workflow's own
    checks (wast3d/config_check.py: size, finite values, the schema), as do the configs a user runs."""
    from wast3d.config_check import check_config

    assert len([p for p in (ROOT / "config").iterdir() if p.is_file()]) <= 9
    schema = yaml.safe_load((ROOT / "workflow" / "schemas" / "config.schema.yaml").read_text())
    base = yaml.safe_load((ROOT / "config" / "config.yaml").read_text())
    for p in sorted((ROOT / "config").glob("*.yaml")):
        check_config(_merge(base, yaml.safe_load(p.read_text())), schema, [str(p)])
    studies = sorted(p for p in (ROOT / "studies").iterdir() if p.is_dir())
    assert len(studies) >= 5
    for d in studies:
        text = (d / "config.yaml").read_text()
        first = text.splitlines()[0]
        assert first.startswith("# merged over: "), f"{d.name}: the first line names the configs it is merged over"
        cfg = {}
        for f in first.removeprefix("# merged over: ").split() + [str((d / "config.yaml").relative_to(ROOT))]:
            cfg = _merge(cfg, yaml.safe_load((ROOT / f).read_text()))
        check_config(cfg, schema, [str(d / "config.yaml")])
        readme = (d / "README.md").read_text()
        for part in ("**Question.**", "**Command.**", "**Result", "erdict"):
            assert part in readme, f"studies/{d.name}/README.md lacks {part}"
        assert f"studies/{d.name}/config.yaml" in readme, f"studies/{d.name}/README.md: its command runs its config"

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

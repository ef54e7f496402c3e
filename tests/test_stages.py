"""The stage declarations (wast3d/stages.py) against what is derived from them: the pipeline functions'
keywords, the command's options, the rules' command lines and docs/stages.md."""

import inspect
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from wast3d import pipeline
from wast3d.cli import build_parser
from wast3d.stages import STAGES, In, Out, Stage

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("command", list(STAGES))
def test_each_stage_function_takes_exactly_its_declared_files(command):
    st = STAGES[command]
    sig = inspect.signature(getattr(pipeline, st.run))
    assert all(p.kind is inspect.Parameter.KEYWORD_ONLY for p in sig.parameters.values()), \
        f"pipeline.{st.run}: files by keyword only, so that two of one format cannot be swapped"
    declared = {p.keyword for p in st.ports if p.beside is None} | {"params"} | ({"progress"} if st.progress else set())
    assert set(sig.parameters) == declared
    for p in st.ports:  # an optional file has a default (None), a required one none
        if p.beside is None:
            assert (sig.parameters[p.keyword].default is inspect.Parameter.empty) == p.required, p.name
    from wast3d.stages import import_spec

    for spec in (st.config.values() if isinstance(st.config, dict) else [st.config] if st.config else []):
        assert import_spec(spec)
    if st.by_form:
        assert isinstance(import_spec(st.by_form), dict) and import_spec(st.by_form)


def test_command_options_come_from_the_declaration():
    parser = build_parser()
    a = parser.parse_args(["stylize", "--content", "c.ply", "--clusters", "k.npz", "--style", "s.ply",
                           "--registration", "r.npz", "--selection", "x.npz", "--out-ply", "o.ply",
                           "--out-npz", "o.npz", "--out-csv", "o.csv", "--no-progress"])
    assert a.registration == Path("r.npz") and a.out_csv == Path("o.csv") and a.no_progress
    with pytest.raises(SystemExit):  # a required file left out
        parser.parse_args(["select", "--content", "c.ply", "--clusters", "k.npz", "--style", "s.ply",
                           "--out-npz", "o.npz"])
    with pytest.raises(SystemExit):  # a file beside another has no option of its own
        parser.parse_args(["cluster", "--content", "c.ply", "--out-npz", "k.npz", "--out-json", "k.json"])
    help_ = subprocess.run([sys.executable, "-m", "wast3d", "cluster", "--help"], capture_output=True, text=True).stdout
    assert "--out-picture PATH" in help_ and "json beside npz" in help_


def test_argv_names_an_unknown_a_missing_and_a_misplaced_file():
    st = STAGES["rescale"]
    ins = {"stylized": "a/stylized.ply", "stylize_npz": "a/stylize.npz"}
    assert st.argv(ins, {"ply": "a/final.ply", "json": "a/final.json"}) == [
        "rescale", "--stylized", "a/stylized.ply", "--stylize-npz", "a/stylize.npz", "--out-ply", "a/final.ply"]
    with pytest.raises(ValueError, match="rescale: no input named 'ply'"):
        st.argv({**ins, "ply": "x.ply"}, {"ply": "a/final.ply"})
    with pytest.raises(ValueError, match="required file.*stylize_npz"):
        st.argv({"stylized": "a.ply"}, {"ply": "b.ply"})
    with pytest.raises(ValueError, match="'json' .* is written beside 'ply'"):
        st.argv(ins, {"ply": "a/final.ply", "json": "a/other.json"})
    ev = STAGES["evaluate"]  # an optional file given as an empty list (a rule's input function) is left out
    files = {n: f"{n}.x" for n in ("result", "content", "style", "result_render", "style_render", "texture_reference",
                                   "content_render")}
    assert "--stylize-npz" not in ev.argv({**files, "stylize_npz": []}, {"json": "e.json"})
    assert ev.argv({**files, "stylize_npz": ["s.npz"]}, {"json": "e.json"})[-4:] == [
        "--stylize-npz", "s.npz", "--out-json", "e.json"]
    line = STAGES["colour-transfer"].command_line({"content": "Bob's c.ply", "style": "s.ply"}, {"ply": "o.ply"})
    assert "'Bob'\"'\"'s c.ply'" in line  # quoted for the shell
    with pytest.raises(ValueError, match="used twice"):
        Stage("x", "x", "run_x", (In("a", ""), Out("a", "")))
    with pytest.raises(ValueError, match="beside 'npz', which is not an output"):
        Stage("x", "x", "run_x", (In("a", ""), Out("json", "", beside="npz")))


def test_stage_reference_page_is_generated_from_the_declarations():
    import importlib.util

    spec = importlib.util.spec_from_file_location("config_docs", ROOT / "workflow" / "scripts" / "config_docs.py")
    cd = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(cd)
    page = cd.stages_page()
    assert cd.STAGES_OUT.read_text() == page, "docs/stages.md is stale: python workflow/scripts/config_docs.py"
    for st in STAGES.values():
        assert f"## `wast3d {st.command}`" in page
        assert all(f"`{p.option}`" in page for p in st.ports if p.beside is None)


def test_artifact_paths_fill_the_wildcards_given_and_keep_the_others():
    from wast3d.stages import PATHS, artifact

    assert artifact("final", "res", content="ant", style="grass", experiment="default") == \
        str(Path("res") / "stylize" / "ant__grass" / "default" / "final.ply")
    assert artifact("eval", content="ant", style="grass") == "eval/ant__grass/{method}.json"  # a rule's pattern
    assert artifact("final", method="colour_ot") == "stylize/{content}__{style}/colour_ot/final.ply"  # a method's files
    assert artifact("rule_benchmark", rule="sinkhorn", job="a__b_c") == "benchmarks/rules/sinkhorn_a__b_c.tsv"
    with pytest.raises(KeyError):
        artifact("finale")
    rules = "".join(p.read_text() for p in (ROOT / "workflow" / "rules").glob("*.smk"))
    for name in PATHS:  # every declared artifact is what some rule reads or writes
        assert f'results("{name}"' in rules or f'beside("{name}"' in rules, name


def test_rules_pass_every_default_so_a_changed_default_reruns_the_stage():
    """resolved_params: the config block with its dataclass's defaults filled in (what the rules pass):
    a key written out at its default gives the same parameters as leaving it out, a default the
    dataclass changes changes them, and a bad key is named before anything runs."""
    from dataclasses import asdict

    from wast3d.clustering import ClusterConfig
    from wast3d.stages import resolved_params
    from wast3d.surface import StyleCleanConfig

    assert resolved_params("cluster", {}) == resolved_params("cluster", {"flatness": ClusterConfig().flatness}) \
        == asdict(ClusterConfig())
    assert resolved_params("style-clean", {})["recolour"] == StyleCleanConfig().recolour
    ev = resolved_params("evaluate", {"metrics": {"patches": 8}})
    assert ev["metrics"]["patches"] == 8 and set(ev) == {"metrics", "texture", "crops", "clip", "elements"}
    p = resolved_params("pretrain", {"holdout_every": 4, "iterations": 10})  # data keys pass through
    assert p["holdout_every"] == 4 and p["iterations"] == 10 and "max_views" not in p
    assert resolved_params("stylize", {"sinkhorn": {"scaling": 0.7}})["sinkhorn"]["blur"] == 0.3
    with pytest.raises(ValueError, match="cluster: unknown parameter.*flat\\b"):
        resolved_params("cluster", {"flat": 1})
    with pytest.raises(ValueError, match="evaluate: unknown parameter block.*metric\\b"):
        resolved_params("evaluate", {"metric": {}})
    with pytest.raises(ValueError, match="stylize.features"):  # the dataclass's own checks run too
        resolved_params("stylize", {"features": "bogus"})


def test_the_values_set_by_the_style_form_are_part_of_the_parameters(monkeypatch):
    """Options left null take their value from the style's form when the stage runs; the rules pass the
    code's form values too (``by_form``), so that changing them re-runs the stage, and the stage itself
    reads the parameters without them."""
    import wast3d.registration as registration
    from wast3d.stages import resolved_params, run_params, stage_configs
    from wast3d.stylize import SHEET_COPIES

    reg = resolved_params("register", {})
    assert reg["element_scale"] is None and reg["by_form"]["element_scale"] == list(registration.FORM_DEFAULTS["element_scale"])
    assert resolved_params("stylize", {})["by_form"] == SHEET_COPIES
    assert stage_configs("register", reg)[None].element_scale is None  # the dataclass never sees the key
    assert "by_form" not in run_params(reg) and "by_form" not in resolved_params("cluster", {})
    monkeypatch.setitem(registration.FORM_DEFAULTS, "element_scale", (0.062, 0.04))
    assert resolved_params("register", {}) != reg


def test_resolved_params_are_remembered_per_block_and_package(tmp_path, monkeypatch):
    """resolved_params_cached: the same parameters as resolved_params, read back from its file without
    resolving again (nothing imported); another package fingerprint or block resolves anew; a bad block
    raises and leaves no file."""
    import json

    from wast3d import stages

    ref = stages.resolved_params("stylize", {"lr": 0.1})
    got = stages.resolved_params_cached("stylize", {"lr": 0.1}, tmp_path, "f1")
    assert json.dumps(got, sort_keys=True) == json.dumps(ref, sort_keys=True)
    assert len(list(tmp_path.glob("stylize-*.json"))) == 1
    stages._RESOLVED.clear()  # a new process: only the file remains
    calls = []
    monkeypatch.setattr(stages, "resolved_params", lambda c, p: calls.append((c, p)) or {"new": 1})
    assert stages.resolved_params_cached("stylize", {"lr": 0.1}, tmp_path, "f1") == got and not calls
    assert stages.resolved_params_cached("stylize", {"lr": 0.1}, tmp_path, "f2") == {"new": 1}
    assert stages.resolved_params_cached("stylize", {"lr": 0.2}, tmp_path, "f1") == {"new": 1}
    assert len(calls) == 2
    monkeypatch.undo()
    with pytest.raises(ValueError, match="stylize.features"):
        stages.resolved_params_cached("stylize", {"features": "bogus"}, tmp_path, "f1")
    assert len(list(tmp_path.glob("stylize-*.json"))) == 3 and not list(tmp_path.glob(".*"))
    (tmp_path / "file").write_text("")  # a cache folder that cannot be made: resolved all the same
    assert stages.resolved_params_cached("cluster", {}, tmp_path / "file" / "c", "f1") == stages.resolved_params("cluster", {})
    pkg = Path(stages.__file__).parent
    assert stages.package_fingerprint(pkg) == stages.package_fingerprint(pkg)
    (tmp_path / "pkg").mkdir()
    (tmp_path / "pkg" / "a.py").write_text("X = 1\n")
    before = stages.package_fingerprint(tmp_path / "pkg")
    (tmp_path / "pkg" / "a.py").write_text("X = 2\n")  # a changed default
    assert stages.package_fingerprint(tmp_path / "pkg") != before


def test_an_option_is_declared_once_and_reaches_the_schema_and_its_checks():
    """option(): the field's help and allowed values give its schema node (type from the annotation) and
    its construction check; the workflow's schema is exactly what config_docs makes from them."""
    import importlib.util
    from dataclasses import dataclass

    import yaml

    from wast3d.options import checked, json_type, option, schema_properties, undocumented

    @dataclass
    @checked("toy")
    class Toy:
        n: int = option(3, "how many", minimum=1)
        rate: float | None = option(None, "a rate (null: off)", exclusiveMinimum=0, maximum=1)
        mode: str = option("a", "which", enum=("a", "b"))
        hidden: bool = True

    assert schema_properties(Toy) == {
        "n": {"type": "integer", "minimum": 1, "description": "how many"},
        "rate": {"type": ["number", "null"], "exclusiveMinimum": 0, "maximum": 1, "description": "a rate (null: off)"},
        "mode": {"enum": ["a", "b"], "description": "which"}}
    assert undocumented(Toy) == ["hidden"]
    Toy(n=1, rate=1.0, mode="b")
    for bad, msg in (({"n": 0}, "toy.n must be >= 1, got 0"), ({"rate": 0.0}, "toy.rate must be > 0"),
                     ({"rate": float("nan")}, "toy.rate must be > 0"), ({"mode": "c"}, "toy.mode must be one of a, b")):
        with pytest.raises(ValueError, match=msg):
            Toy(**bad)
    with pytest.raises(ValueError, match="no JSON type"):
        json_type("dict[str, int]")
    with pytest.raises(ValueError, match="help"):
        option(1)
    spec = importlib.util.spec_from_file_location("config_docs", ROOT / "workflow" / "scripts" / "config_docs.py")
    cd = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(cd)
    assert cd.SCHEMA.read_text() == cd.schema_text(), "the schema is stale: python workflow/scripts/config_docs.py"
    schema = yaml.safe_load(cd.SCHEMA.read_text())
    cluster = schema["properties"]["partitions"]["additionalProperties"]["properties"]["cluster"]["properties"]
    from wast3d.clustering import ClusterConfig

    assert cluster == schema_properties(ClusterConfig)


def test_the_gpu_check_says_it_needs_cuda_and_its_checks_run_with_the_cpu_standing_in(tmp_path):
    """scripts/gpu_check.sh on a machine without CUDA exits 0 and says so; its comparisons run (the CPU
    standing in for the GPU, small sizes) and agree with themselves."""
    import subprocess
    import sys

    import pandas as pd

    root = Path(__file__).resolve().parents[1]
    if not torch.cuda.is_available():
        r = subprocess.run(["bash", str(root / "scripts" / "gpu_check.sh")], capture_output=True, text=True,
                           env={**os.environ, "PYTHON": sys.executable})
        assert r.returncode == 0 and "no CUDA device" in r.stdout
    out = tmp_path / "gpu.csv"
    r = subprocess.run([sys.executable, str(root / "benchmarks" / "gpu_check.py"), "--device", "cpu", "--quick",
                        "--checks", "raster", "sinkhorn", "--out", str(out)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-2000:]
    df = pd.read_csv(out)
    assert list(df.check) == ["raster", "sinkhorn", "sinkhorn"] and "error" not in df.columns
    assert df.rgb_max_abs[0] == 0 and df.grad_means_rel[0] == 0 and (df.value_rel[1:] == 0).all()

"""The Snakemake workflow on a tiny config: schema errors, left-out stages, the whole DAG, caching
(dry-run job lists after a parameter change), sweeps and the SLURM resource mapping."""

import copy
import json
import re
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest
import torch
import yaml

ROOT = Path(__file__).resolve().parents[1]

TINY = {
    "scenes": {
        "blob": {"source": "procedural", "kind": "content", "name": "torus", "n_gaussians": 1500},
        "peb": {"source": "procedural", "kind": "style", "name": "pebbles", "n_gaussians": 3000},
    },
    "preview": {"views": 2, "size": 48},
    "partitions": {"default": {"cluster": {"n_clusters": 3},
                               "register": {"landings": 1, "yaws": 2, "iterations": 4, "refine_iterations": 4},
                               "select": {"k": 2}}},
    "experiments": {"default": {"stylize": {"iterations": 3}}},
    "pairs": [["blob", "peb"]],
    "run": ["default"],
    "sweeps": {"abl": {"base": "default", "variants": {"full": {}, "xyz": {"stylize": {"features": "xyz"}},
                                                        "arap": {"stylize": {"loss": "arap"}}}}},
    "evaluation": {"render": {"frames": 4, "size": 48, "key_views": 2, "closeup_zoom": 2},
                   "crops": {"count": 4, "size": 16},
                   "metrics": {"patches": 8, "candidates": 16, "patch_size": 8, "patch_stride": 1, "rotations": 2,
                               "colour_points": 256},
                   "colour_transfer": {"max_style_points": 500}},
    "table1": {"methods": {"default": "ours", "abl-xyz": "xyz only", "colour_ot": "colour transfer",
                           "input": "content"}},
}


def snake(workdir: Path, *args, config: dict | None = None, check=True):
    if config is not None:
        (workdir / "config").mkdir(parents=True, exist_ok=True)
        (workdir / "config" / "config.yaml").write_text(yaml.safe_dump(config, sort_keys=False))
    cmd = [sys.executable, "-m", "snakemake", "-s", str(ROOT / "Snakefile"), "-d", str(workdir), "--cores", "2", *args]
    r = subprocess.run(cmd, capture_output=True, text=True)
    if check and r.returncode:
        raise AssertionError(f"snakemake failed:\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}")
    return r


def jobs(r) -> dict:
    """Job counts from a dry run's job-stats table."""
    out = {}
    m = re.search(r"job\s+count\n-+\s+-+\n(.*?)\ntotal", r.stdout, re.S)
    for line in (m.group(1).splitlines() if m else []):
        name, n = line.split()
        out[name] = int(n)
    return out


@pytest.mark.parametrize("edit, field", [
    (lambda c: c["scenes"]["blob"].update(n_gausians=5), "n_gausians"),
    (lambda c: c.update(clusterz=1), "clusterz"),
    (lambda c: c["experiments"]["default"]["stylize"].update(features="xyz+depth"), "xyz+depth"),
    (lambda c: c["partitions"]["default"]["cluster"].update(n_clusters=-1), "-1"),
])
def test_schema_errors_name_the_field(tmp_path, edit, field):
    cfg = copy.deepcopy(TINY)
    edit(cfg)
    r = snake(tmp_path, "-n", config=cfg, check=False)
    assert r.returncode != 0
    assert field in (r.stdout + r.stderr)


def test_reference_errors(tmp_path):
    cfg = copy.deepcopy(TINY)
    cfg["pairs"] = [["blob", "nothere"]]
    r = snake(tmp_path, "-n", config=cfg, check=False)
    assert r.returncode != 0 and "scene 'nothere' is not defined" in r.stdout + r.stderr


def test_left_out_what_a_scene_does_not_need(tmp_path):
    from wast3d.ply import write_ply
    from wast3d.procedural import make_scene

    write_ply(tmp_path / "given.ply", make_scene("content", "nut", 800))
    cfg = copy.deepcopy(TINY)
    cfg["scenes"]["given"] = {"source": "ply", "path": str(tmp_path / "given.ply")}
    cfg["pairs"] = [["blob", "peb"], ["given", "peb"]]
    r = snake(tmp_path, "-n", config=cfg)
    j = jobs(r)
    assert j["import_ply"] == 1 and j["surface"] == 1  # only the PLY content is surface-sampled
    assert "pretrain" not in j  # no scene here needs pretraining
    assert j["procedural_scene"] == 2
    log = r.stdout + r.stderr
    assert "scene 'blob': left out surface sampling" in log
    assert "scene 'given': left out pretraining (a trained 3DGS PLY is given)" in log


def tiny_config(wd: Path) -> dict:
    """TINY with CLIP from a tiny random open_clip model saved in the work folder."""
    from conftest import write_tiny_clip

    cfg_path, ckpt = write_tiny_clip(wd / "clip")
    cfg = copy.deepcopy(TINY)
    cfg["evaluation"]["clip"] = {"model": "wast3d-tiny-clip", "checkpoint": str(ckpt), "model_config": str(cfg_path)}
    return cfg


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    wd = tmp_path_factory.mktemp("wf")
    snake(wd, config=tiny_config(wd))
    return wd


def test_whole_dag_artifacts(tiny_run):
    from wast3d.ply import read_ply

    r = tiny_run / "results"
    for scene in ("blob", "peb"):
        assert read_ply(r / "scenes" / scene / "scene.ply").means.isfinite().all()
        assert (r / "scenes" / scene / "preview.png").stat().st_size > 0
    cl = np.load(r / "partition/blob/default/clusters.npz")
    assert cl["labels"].max() == 2
    reg = np.load(r / "register/blob__peb/default/registration.npz")
    assert np.isfinite(reg["R"]).all() and np.allclose(np.linalg.det(reg["R"]), 1)
    sel = np.load(r / "register/blob__peb/default/selection.npz")
    assert sel["offsets"][-1] == len(sel["indices"])
    out = read_ply(r / "stylize/blob__peb/default/final.ply")
    assert len(out) == len(sel["indices"])
    assert all(torch.isfinite(t).all() for t in out.tensors().values())
    for f in ("clusters.png",):
        assert (r / "partition/blob/default" / f).stat().st_size > 0
    assert (r / "register/blob__peb/default/registration.png").stat().st_size > 0
    losses = pd.read_csv(r / "stylize/blob__peb/default/losses.csv")
    assert np.isfinite(losses.loss).all() and losses.iteration.max() == 2
    assert (r / "stylize/blob__peb/default/losses.png").stat().st_size > 0
    table = pd.read_csv(r / "tables/summary.csv")
    assert len(table) == 1 and np.isfinite(table.loss_last).all()
    for f in (r / "benchmarks/rules").glob("*.tsv"):
        assert f.stat().st_size > 0
    assert (r / "logs/sinkhorn/blob__peb_default.log").exists()
    # stages 7-9: renders, evaluation, the baseline, the comparison sheet and Table 1
    for m in ("default", "abl-xyz", "colour_ot", "input"):
        d = r / "render/pairs/blob__peb" / m
        assert len(list((d / "frames").glob("*.png"))) == 4 and (d / "turntable.gif").stat().st_size > 0
        assert (d / "closeup_normal.png").exists() and (d / "key_01_depth.png").exists()
    cams = [json.loads((r / "render/pairs/blob__peb" / m / "render.json").read_text())["cameras"] for m in ("default", "input")]
    assert cams[0] == cams[1]  # every method is seen through the content's cameras
    assert (r / "figures/blob__peb.png").stat().st_size > 0
    t1 = pd.read_csv(r / "tables/table1.csv")
    assert list(t1.method) == ["ours", "xyz only", "colour transfer", "content"]
    assert t1.clip_similarity_pct.astype(float).between(-100, 100).all()  # the tiny model's weights, from a file
    kept = t1.run.isin(["input", "colour_ot"])  # the content's geometry, unchanged
    assert (t1.content_chamfer[kept] == 0).all() and (t1.content_chamfer[~kept] > 0).all()
    assert (t1.colour_sinkhorn[t1.run == "colour_ot"] < t1.colour_sinkhorn[t1.run == "input"].iloc[0]).all()
    assert np.isfinite(t1.time_s[t1.run != "input"]).all() and (t1.peak_mem_mb[t1.run != "input"] > 0).all()
    assert "not computed" not in (r / "tables/table1.md").read_text()
    page = (r / "tables/table1.html").read_text()  # what the report shows inline
    assert page.count("<tr>") == 1 + len(t1) and "<th>content_chamfer</th>" in page and "colour transfer" in page


def test_caching_reruns_only_what_a_change_affects(tiny_run):
    base = tiny_config(tiny_run)
    assert jobs(snake(tiny_run, "-n", config=copy.deepcopy(base))) == {}
    downstream = {"render_method", "evaluate", "comparison_sheet", "table1", "all"}
    cfg = copy.deepcopy(base)
    cfg["experiments"]["default"]["stylize"]["sinkhorn"] = {"blur": 0.1}
    j = jobs(snake(tiny_run, "-n", config=cfg))
    # the default experiment and the sweep variant built on it; the baseline and the input are untouched
    assert set(j) == {"sinkhorn", "rescale", "result_preview", "summary"} | downstream and j["evaluate"] == 2
    cfg = copy.deepcopy(base)
    cfg["partitions"]["default"]["cluster"]["n_clusters"] = 2
    assert set(jobs(snake(tiny_run, "-n", config=cfg))) == {
        "cluster", "register", "select", "sinkhorn", "rescale", "result_preview", "summary"} | downstream
    cfg = copy.deepcopy(base)
    cfg["evaluation"]["metrics"]["patches"] = 9
    assert jobs(snake(tiny_run, "-n", config=cfg)) == {"evaluate": 4, "table1": 1, "all": 1}
    cfg = copy.deepcopy(base)
    cfg["evaluation"]["render"]["frames"] = 5
    assert set(jobs(snake(tiny_run, "-n", config=cfg))) == {"render_method", "render_scene", "texture_reference"} | downstream
    snake(tiny_run, "-n", config=copy.deepcopy(base))  # restore the config file


def test_sweep_runs_each_variant_in_its_own_folder(tiny_run):
    r = snake(tiny_run, "-n", "--config", "sweep=abl", config=tiny_config(tiny_run))
    j = jobs(r)
    assert j["sinkhorn"] == 2 and j["summary"] == 1 and "cluster" not in j  # partition shared; abl-xyz was run
    for v in ("abl-full", "abl-arap"):
        assert f"results/stylize/blob__peb/{v}/stylized.ply" in r.stdout
    assert "results/tables/abl.csv" in r.stdout


def test_slurm_profile_maps_resources_to_sbatch(tmp_path):
    """The sbatch arguments the SLURM plugin builds for each rule, from the profile's site values
    and the rules' declared resources (as a dry run resolves them)."""
    sub = pytest.importorskip("snakemake_executor_plugin_slurm.submit_string")
    utils = pytest.importorskip("snakemake_executor_plugin_slurm.utils")
    r = snake(tmp_path, "-n", "--profile", str(ROOT / "workflow/profiles/slurm"), config=copy.deepcopy(TINY))
    calls = {}
    for rule, res in re.findall(r"^rule (\w+):.*?^    resources: (.*?)$", r.stdout, re.S | re.M):
        kv = dict(x.split("=", 1) for x in res.split(", "))
        vals = {k: (int(v) if v.isdigit() else v) for k, v in kv.items()}

        class Res(SimpleNamespace):
            def get(self, k, d=None):
                return getattr(self, k, d)

        job = SimpleNamespace(resources=Res(**vals), threads=1, is_group=lambda: False, name=rule)
        params = {"run_uuid": "x", "slurm_logfile": "l", "comment_str": "c", "workdir": "",
                  "account": f"-A {vals['slurm_account']}", "partition": f"-p {vals['slurm_partition']}"}
        calls[rule] = sub.get_submit_command(job, params) + " " + utils.set_gres_string(job)
    s = calls["sinkhorn"]
    assert "-p gpu" in s and "-A my_account" in s and "--gpus=a100:1" in s.replace("'", "")
    assert "--mem 8000" in s and "-t 240" in s
    c = calls["cluster"]
    assert "-p cpu" in c and "gpu" not in c.replace("-p cpu", "") and "--cpus-per-task=4" in c


@pytest.mark.browser
def test_report_opens_in_a_browser_with_table1_as_a_table(tiny_run, tmp_path):
    """The Snakemake report of the tiny run, opened by a real headless Chromium: it renders (the
    categories are in the DOM after its scripts ran) and Table 1 is an HTML item shown inline."""
    import shutil

    browser = shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")
    if browser is None:
        pytest.skip("no chromium on this machine (apt-get install -y chromium)")
    report = tmp_path / "report.html"
    snake(tiny_run, "--report", str(report))
    r = subprocess.run([browser, "--headless", "--no-sandbox", "--disable-gpu", "--virtual-time-budget=10000",
                        "--dump-dom", report.as_uri()], capture_output=True, text=True, timeout=120)
    dom = r.stdout
    assert r.returncode == 0 and len(dom) > 1000, r.stderr[-2000:]
    for category in ("Tables", "Figures", "Results"):
        assert category in dom, category
    assert "table1.html" in dom
    # the item itself: the table page the report embeds, as the workflow wrote it
    page = (tiny_run / "results/tables/table1.html").read_text()
    assert "<table>" in page and "<th>content_chamfer</th>" in page

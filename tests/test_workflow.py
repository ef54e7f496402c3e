"""The Snakemake workflow on a tiny config: schema errors, left-out stages, the whole DAG, caching
(dry-run job lists after a parameter change), sweeps and the SLURM resource mapping."""

import copy
import json
import os
import re
import shlex
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
    "partitions": {"default": {"cluster": {"n_clusters": 6},
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


def snake(workdir: Path, *args, config: dict | None = None, check=True, timeout: float | None = None,
          quick_poll=False):
    """Snakemake on ``workdir``; ``quick_poll``: through tests/quick_poll_snakemake.py (SLURM status
    polls at most 2 s apart instead of the plugin's growing back-off)."""
    if config is not None:
        (workdir / "config").mkdir(parents=True, exist_ok=True)
        (workdir / "config" / "config.yaml").write_text(yaml.safe_dump(config, sort_keys=False))
    entry = [str(ROOT / "tests" / "quick_poll_snakemake.py")] if quick_poll else ["-m", "snakemake"]
    cmd = [sys.executable, *entry, "-s", str(ROOT / "Snakefile"), "-d", str(workdir), "--cores", "2", *args]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
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


def test_stage_parameters_survive_the_shell(tmp_path):
    """A stage's JSON parameters are shell-quoted in the command: an apostrophe in a path (a CLIP
    checkpoint under "Bob's models") reaches the stage as written."""
    import shlex

    ckpt = tmp_path / "Bob's models" / "clip.pt"
    ckpt.parent.mkdir()
    ckpt.write_bytes(b"")
    cfg = copy.deepcopy(TINY)
    cfg["evaluation"]["clip"] = {"model": "ViT-B-32", "checkpoint": str(ckpt)}
    r = snake(tmp_path, "-n", "-p", config=cfg)
    cmds = [line for line in r.stdout.splitlines() if " evaluate " in line and "--params" in line]
    assert cmds, r.stdout[-2000:]
    argv = shlex.split(cmds[0].split(" 2> ")[0])
    params = json.loads(argv[argv.index("--params") + 1])
    assert params["clip"]["checkpoint"] == str(ckpt)


FAKE_CONDA = """#!/bin/sh
case "$*" in
  "--version") echo "conda 24.11.0";;
  "info --json") echo '{"conda_prefix": "%(d)s", "envs_dirs": ["%(d)s/envs"], "platform": "linux-64", "root_prefix": "%(d)s"}';;
  "config --get channel_priority --json") echo '{"get": {"channel_priority": "strict"}}';;
  *) exit 1;;
esac
"""


def test_conda_deployment_runs_the_stages_in_the_declared_environment(tmp_path, monkeypatch):
    """With `--sdm conda` every stage runs `python -m wast3d` from workflow/envs/wast3d.yaml, not the
    interpreter that runs Snakemake (a stand-in `conda` answers Snakemake's checks; nothing installs)."""
    fake = tmp_path / "bin" / "conda"
    fake.parent.mkdir()
    fake.write_text(FAKE_CONDA % {"d": tmp_path / "conda"})
    fake.chmod(0o755)
    monkeypatch.setenv("PATH", f"{fake.parent}{os.pathsep}{os.environ['PATH']}")
    wd = tmp_path / "wd"
    r = snake(wd, "-n", "-p", "--sdm", "conda", config=copy.deepcopy(TINY))
    cmds = re.findall(r"(\S+) -m wast3d ", r.stdout)
    assert cmds and set(cmds) == {"python"}, set(cmds)
    assert "envs/wast3d.yaml" in r.stdout + r.stderr
    plain = snake(wd, "-n", "-p", config=copy.deepcopy(TINY))
    assert f"{sys.executable} -m wast3d" in plain.stdout


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


def test_a_style_outside_pairs_is_cleaned_as_in_them(tmp_path):
    """A target for a pair that `pairs` does not list (merged configs: the last file's `pairs` wins) gets
    the style cleaned as it would be in a listed pair, not the raw import (which once fed registration
    an imported style's floaters and haze without a word)."""
    from wast3d.ply import write_ply
    from wast3d.procedural import make_scene

    write_ply(tmp_path / "given.ply", make_scene("style", "pebbles", 800))
    cfg = copy.deepcopy(TINY)
    cfg["scenes"]["given"] = {"source": "ply", "path": str(tmp_path / "given.ply")}
    r = snake(tmp_path, "-n", "-p", "results/register/blob__given/default/registration.npz", config=cfg)
    assert "results/scenes/given/style.ply" in r.stdout and jobs(r).get("style_clean") == 1, r.stdout[-2000:]


def test_a_style_scene_is_pretrained_the_same_in_any_pairs(tmp_path):
    """An images scene's pretraining follows its own `kind`, not the pairs of the config merged last: a
    style once got the regularizers of eq. 1-2 only where `pairs` listed it, and a merged config's cached
    scene was then the other pretraining. Without `kind` the config stops, naming the field."""
    (tmp_path / "views").mkdir()
    (tmp_path / "views" / "transforms_train.json").write_text("{}")
    params = []
    for pairs in ([["blob", "peb"], ["blob", "shot"]], [["blob", "peb"]]):
        cfg = copy.deepcopy(TINY)
        cfg["scenes"]["shot"] = {"source": "images", "kind": "style", "path": str(tmp_path / "views")}
        cfg["pairs"] = pairs
        r = snake(tmp_path, "-n", "-p", "results/scenes/shot/scene.ply", config=cfg)
        cmd = next(line for line in r.stdout.splitlines() if " pretrain " in line and "--params" in line)
        params.append(json.loads(shlex.split(cmd.split(" 2> ")[0])[-1]))
    assert params[0] == params[1] and params[0]["regularize"] is True
    del cfg["scenes"]["shot"]["kind"]
    r = snake(tmp_path, "-n", config=cfg, check=False)
    assert r.returncode != 0 and "scenes.shot: 'kind' (content or style) is required" in r.stdout + r.stderr


def tiny_config(wd: Path) -> dict:
    """TINY with CLIP from a tiny random open_clip model saved in the work folder."""
    from conftest import write_tiny_clip

    cfg_path, ckpt = write_tiny_clip(wd / "clip")
    cfg = copy.deepcopy(TINY)
    cfg["evaluation"]["clip"] = {"model": "wast3d-tiny-clip", "checkpoint": str(ckpt), "model_config": str(cfg_path)}
    return cfg


def test_whole_dag_artifacts(tiny_run):
    from wast3d.ply import read_ply

    r = tiny_run / "results"
    for scene in ("blob", "peb"):
        assert read_ply(r / "scenes" / scene / "scene.ply").means.isfinite().all()
        assert (r / "scenes" / scene / "preview.png").stat().st_size > 0
    cl = np.load(r / "partition/blob/default/clusters.npz")
    info = json.loads((r / "partition/blob/default/clusters.json").read_text())
    # 6 k-means clusters, each split by its normals until flat (cluster.flatness)
    assert info["requested_clusters"] == 6 and cl["labels"].max() + 1 == 6 + info["split_wrapped_clusters"]
    assert cl["normals"].shape == (len(cl["labels"]), 3)
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
    assert (r / "figures/blob__peb_turntables.html").read_text().count("data:video/mp4;base64,") == 5  # content, style, 3 methods
    t1 = pd.read_csv(r / "tables/table1.csv")
    assert list(t1.method) == ["ours", "xyz only", "colour transfer", "content"]
    assert t1.clip_similarity_pct.astype(float).between(-100, 100).all()  # the tiny model's weights, from a file
    kept = t1.run.isin(["input", "colour_ot"])  # the content's geometry, unchanged
    assert (t1.content_chamfer[kept] == 0).all() and (t1.content_chamfer[~kept] > 0).all()
    # the coarse Chamfer smooths at the element length the texture reference records from the registration
    ref = json.loads((r / "render/texture_reference/blob__peb/render.json").read_text())
    assert ref["element_length"] > 0 and ref["s0"] > 0
    assert t1.coarse_chamfer.notna().all() and (t1.coarse_chamfer[kept] < 0.5).all()
    # no copy of a style element in the content or a colour transfer; ours shows pieces of them
    assert (t1.element_whole_ratio[kept] == 0).all() and (t1.element_whole_ratio[~kept] > 0).all()
    # the same with the style's relief basins for elements (no label read): the texture reference writes them
    assert (r / "render/texture_reference/blob__peb/segments.npz").exists()
    assert (t1.segment_whole_ratio[kept] == 0).all() and (t1.segment_whole_ratio[~kept] > 0).all()
    assert t1.segment_intact[kept].isna().all() and t1.segment_intact[~kept].between(0, 1).all()
    assert t1.element_colour_w1.notna().all() and t1.element_thickness_w1.notna().all()  # in Table 1, label-free
    assert (t1.colour_sinkhorn[t1.run == "colour_ot"] < t1.colour_sinkhorn[t1.run == "input"].iloc[0]).all()
    assert np.isfinite(t1.time_s[t1.run != "input"]).all() and (t1.peak_mem_mb[t1.run != "input"] > 0).all()
    assert "not computed" not in (r / "tables/table1.md").read_text()
    page = (r / "tables/table1.html").read_text()  # what the report shows inline
    assert page.count("<tr>") == 1 + len(t1) and "<th>content_chamfer</th>" in page and "colour transfer" in page


def test_caching_reruns_only_what_a_change_affects(tiny_run, tmp_path):
    from concurrent.futures import ThreadPoolExecutor

    base = tiny_config(tiny_run)

    def changed(edit) -> Path:
        """A config file holding the tiny run's config with ``edit`` applied (given over the work folder's)."""
        cfg = copy.deepcopy(base)
        edit(cfg)
        path = tmp_path / f"c{len(list(tmp_path.glob('c*.yaml')))}.yaml"
        path.write_text(yaml.safe_dump(cfg, sort_keys=False))
        return path

    edits = [lambda c: None,
             lambda c: c["experiments"]["default"]["stylize"].update(sinkhorn={"blur": 0.1}),
             lambda c: c["partitions"]["default"]["cluster"].update(n_clusters=2),
             lambda c: c["evaluation"]["metrics"].update(patches=9),
             lambda c: c["evaluation"]["render"].update(frames=5)]
    files = [changed(e) for e in edits]
    with ThreadPoolExecutor(2) as pool:  # dry runs write nothing: two at a time
        same, blur, clusters, metrics, frames = pool.map(
            lambda f: jobs(snake(tiny_run, "-n", "--configfile", str(f))), files)
    assert same == {}
    downstream = {"render_method", "evaluate", "comparison_sheet", "methods_sheet", "turntable_page", "table1", "all"}
    # the default experiment and the sweep variant built on it; the baseline and the input are untouched
    assert set(blur) == {"sinkhorn", "rescale", "result_preview", "summary"} | downstream and blur["evaluate"] == 2
    # the texture reference shows the style at the registration's scale s0, so it follows the partition
    assert set(clusters) == {"cluster", "register", "select", "sinkhorn", "rescale", "result_preview", "summary",
                             "texture_reference"} | downstream
    assert metrics == {"evaluate": 4, "table1": 1, "all": 1}
    assert set(frames) == {"render_method", "render_scene", "texture_reference"} | downstream


def test_a_parse_with_known_blocks_imports_no_torch(tiny_run, monkeypatch):
    """Dry runs and every cluster job parse the workflow again. With each stage's block resolved before
    (the run, remembered under .snakemake/wast3d-params), the parse imports neither torch nor any stage
    module, and finds nothing to do."""
    monkeypatch.setenv("PYTHONPROFILEIMPORTTIME", "1")
    r = snake(tiny_run, "-n", config=tiny_config(tiny_run))
    imported = set(re.findall(r"^import time:.*\|\s+([\w.]+)$", r.stderr, re.M))
    assert "snakemake" in imported and "jsonschema" in imported  # the import log is read
    assert "torch" not in imported and not [m for m in imported if m.split(".")[0] == "wast3d"]
    assert jobs(r) == {}
    assert len(list((tiny_run / ".snakemake" / "wast3d-params").glob("*.json"))) >= 10


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


def test_gpu_requests_are_a_site_setting(tmp_path):
    """No rule hard-wires a GPU: the CPU-only local cluster's profile resolves no `gpu` resource for any
    job, while the site profile asks one for sinkhorn and pretrain."""
    r = snake(tmp_path, "-n", "--profile", str(ROOT / "workflow/profiles/slurm-local"), config=copy.deepcopy(TINY))
    res = dict(re.findall(r"^rule (\w+):.*?^    resources: (.*?)$", r.stdout, re.S | re.M))
    assert "sinkhorn" in res and not any("gpu" in v for v in res.values()), res
    assert "slurm_partition=local" in res["sinkhorn"]
    for rules in (ROOT / "workflow/rules").glob("*.smk"):
        assert "gpu" not in re.sub(r"#.*", "", rules.read_text()), rules.name
    site = yaml.safe_load((ROOT / "workflow/profiles/slurm/config.yaml").read_text())["set-resources"]
    assert site["sinkhorn"]["gpu"] == 1 and site["pretrain"]["gpu"] == 1


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
    for category in ("Tables", "Figures", "Turntables", "Results"):
        assert category in dom, category
    assert "table1.html" in dom and "blob__peb_turntables.html" in dom
    # the item itself: the table page the report embeds, as the workflow wrote it
    page = (tiny_run / "results/tables/table1.html").read_text()
    assert "<table>" in page and "<th>content_chamfer</th>" in page


def test_turntable_videos_play_in_a_browser(tiny_run, tmp_path):
    """The report's turntable page, opened by a real headless Chromium: its H.264 videos decode and
    play (the page seeked to two moments of its videos shows the scene at both, and they differ).
    Seeking (a #t= media fragment) rather than waiting: autoplay under load did not advance in
    headless Chromium's virtual time."""
    import re
    import shutil

    import imageio.v3 as iio

    browser = shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")
    if browser is None:
        pytest.skip("no chromium on this machine (apt-get install -y chromium)")
    html = (tiny_run / "results/figures/blob__peb_turntables.html").read_text()
    assert html.count("<video autoplay loop muted playsinline") == 5
    def shot(t: str, budget_ms: int):
        page = tmp_path / f"at_{t}.html"
        page.write_text(re.sub(r'(src="data:video/mp4;base64,[^"]*)"', lambda m: f'{m.group(1)}#t={t}"', html))
        out = tmp_path / f"shot_{t}.png"
        subprocess.run([browser, "--headless", "--no-sandbox", "--disable-gpu", "--window-size=1400,330",
                        f"--virtual-time-budget={budget_ms}", f"--screenshot={out}", page.as_uri()],
                       capture_output=True, timeout=120)
        return iio.imread(out)[..., :3].astype(int)

    # the tiny run's turntables: 4 frames at 8 fps. Under heavy load the seek can miss the screenshot
    # (both shots the first frame): up to three tries, with a longer virtual-time budget each
    for budget in (2000, 6000, 15000):
        shots = [shot(t, budget) for t in ("0.05", "0.3")]
        moved = (abs(shots[0] - shots[1]).sum(-1) > 30).mean()
        if moved > 0.001:
            break
    drawn = [(s.sum(-1) < 740).mean() for s in shots]
    assert min(drawn) > 0.01, drawn  # not a blank page: the frames are decoded
    assert moved > 0.001  # and they move


@pytest.fixture(scope="module")
def local_slurm():
    """The single-node cluster of scripts/local_slurm.sh: used if already up, else started (as root)
    for this module and stopped after it."""
    import os
    import shutil

    from conftest import use_scontrol_standin

    if shutil.which("slurmctld") is None or shutil.which("sbatch") is None:
        pytest.skip("no SLURM on this machine (apt-get install -y slurm-wlm munge; see docs/install.md)")
    script = ROOT / "scripts/local_slurm.sh"
    use_scontrol_standin(False)  # the cluster's tests talk to the real controller
    try:
        if subprocess.run([script, "status"], capture_output=True).returncode == 0:
            yield
            return
        if os.geteuid() != 0:
            pytest.skip("the local SLURM cluster is not running and starting it needs root (sudo scripts/local_slurm.sh start)")
        r = subprocess.run([script, "start"], capture_output=True, text=True)
        assert r.returncode == 0, r.stdout + r.stderr
        try:
            yield
        finally:
            subprocess.run([script, "stop"], capture_output=True)
    finally:
        use_scontrol_standin(True)


def slurm_job_ids(stdout: str) -> list[int]:
    return [int(i) for i in re.findall(r"submitted with SLURM jobid (\d+)", stdout)]


def slurm_exit_codes(ids: list[int]) -> dict[int, int]:
    """Exit status per job id, from the controller's own log (complete jobs leave squeue after MinJobAge)."""
    log = Path("/var/log/slurm/slurmctld.log").read_text()
    return {i: int(m.group(1)) for i in ids if (m := re.search(rf"_job_complete: JobId={i} WEXITSTATUS (\d+)", log))}


# Each SLURM job runs Snakemake twice (the job step, then srun's), about 15 s a job on this machine's
# 2 cores: the default suite sends the 2 scenes and k-means (3 jobs; the sbatch arguments of every rule
# are test_slurm_profile_maps_resources_to_sbatch's); the stages up to eq. 9 (6 jobs, the Sinkhorn stage
# on 2 CPUs) and the whole DAG (40 jobs, renders, evaluation and Table 1 included) are slow variants.
SLURM_PARTS = {"clustered": (["results/partition/blob/default/clusters.npz", "results/scenes/peb/scene.ply"], 3),
               "stylized": (["results/stylize/blob__peb/default/stylized.ply"], 6),
               "whole": ([], 20)}


@pytest.mark.slurm
@pytest.mark.parametrize("part", ["clustered", pytest.param("stylized", marks=pytest.mark.slow),
                                  pytest.param("whole", marks=pytest.mark.slow)])
def test_tiny_workflow_through_a_real_slurm_cluster_equals_the_local_run(local_slurm, tiny_run, tmp_path, part):
    """The tiny workflow's jobs as sbatch jobs on the local cluster (profile slurm-local): each job id
    is one the controller ran to exit status 0, and the results equal the local run's."""
    from wast3d.ply import read_ply

    targets, min_jobs = SLURM_PARTS[part]
    cfg = tiny_config(tiny_run)  # the same CLIP checkpoint as the local run
    r = snake(tmp_path, "--profile", str(ROOT / "workflow/profiles/slurm-local"), *(["--", *targets] if targets else []),
              config=cfg, timeout=900, quick_poll=True)
    ids = slurm_job_ids(r.stdout + r.stderr)
    assert len(ids) >= min_jobs and len(set(ids)) == len(ids), ids
    codes = slurm_exit_codes(ids)
    assert codes == {i: 0 for i in ids}, "jobs the controller did not run to exit 0"
    ours, local = tmp_path / "results", tiny_run / "results"
    files = {"clustered": [], "stylized": ["stylize/blob__peb/default/stylized.ply"],
             "whole": ["stylize/blob__peb/default/stylized.ply", "stylize/blob__peb/default/final.ply",
                       "stylize/blob__peb/abl-xyz/final.ply"]}[part]
    a, b = (np.load(d / "partition/blob/default/clusters.npz")["labels"] for d in (ours, local))
    np.testing.assert_array_equal(a, b)
    for f in ["scenes/peb/scene.ply", *files]:
        a, b = read_ply(ours / f).tensors(), read_ply(local / f).tensors()
        assert a.keys() == b.keys()
        for k in a:
            torch.testing.assert_close(a[k], b[k], rtol=1e-5, atol=1e-6, msg=f"{f}: {k}")
    if part == "whole":
        ta, tb = pd.read_csv(ours / "tables/table1.csv"), pd.read_csv(local / "tables/table1.csv")
        num = [c for c in ta.columns if ta[c].dtype.kind == "f" and not c.startswith(("time", "peak"))]
        assert list(ta.columns) == list(tb.columns) and len(num) > 5
        np.testing.assert_allclose(ta[num].to_numpy(), tb[num].to_numpy(), rtol=1e-4, atol=1e-6)


@pytest.mark.slurm
def test_a_failing_slurm_job_fails_the_workflow_instead_of_hanging(local_slurm, tmp_path):
    """A scene PLY cut short passes the config schema and fails its first stage inside SLURM: the job
    is reported failed (exit status not 0 in the controller's log) and Snakemake exits non-zero, in
    bounded time, with the stage's error in the failed log."""
    from conftest import random_scene
    from wast3d.ply import write_ply

    good = tmp_path / "good.ply"
    write_ply(good, random_scene(50))
    bad = tmp_path / "cut.ply"
    bad.write_bytes(good.read_bytes()[:-100])
    cfg = copy.deepcopy(TINY)
    cfg["scenes"]["peb"] = {"source": "ply", "path": str(bad)}
    # its first stage only: the DAG's other jobs would only make Snakemake wait for them before it stops
    r = snake(tmp_path / "wd", "--profile", str(ROOT / "workflow/profiles/slurm-local"), "results/scenes/peb/scene.ply",
              config=cfg, check=False, timeout=300, quick_poll=True)
    out = r.stdout + r.stderr
    assert r.returncode != 0
    ids = slurm_job_ids(out)
    codes = slurm_exit_codes(ids)
    assert any(c != 0 for c in codes.values()), (ids, codes)
    assert "cut.ply: corrupt or truncated PLY" in out  # the stage's own error (its log) reaches the user


def comparable(folder: Path) -> dict[str, object]:
    """Every result file under ``folder``/results as what must not change between two runs of the same
    config: the bytes; for JSON reports and the tables, all but the run's own time and memory (and the
    work folder's path). Logs and Snakemake's per-rule timings are left out."""
    volatile = re.compile(r"seconds|^time|_time$|_s$|peak_mem|rss|memory|^mem")

    def strip(o):
        if isinstance(o, dict):
            return {k: strip(v) for k, v in o.items() if not volatile.search(str(k))}
        return [strip(v) for v in o] if isinstance(o, list) else o

    out = {}
    for p in sorted((folder / "results").rglob("*")):
        rel = p.relative_to(folder).as_posix()
        if not p.is_file() or rel.startswith(("results/logs/", "results/benchmarks/rules/")):
            continue
        if p.suffix == ".json":
            out[rel] = strip(json.loads(p.read_text().replace(str(folder), "OUT")))
        elif p.suffix == ".csv" and "tables" in p.parts:
            df = pd.read_csv(p)
            out[rel] = df.drop(columns=[c for c in df.columns if volatile.search(c)]).to_csv(index=False)
        elif p.suffix in (".md", ".html") and "tables" in p.parts:
            continue  # the CSV's rows again, with its times
        else:
            out[rel] = p.read_bytes()
    return out


@pytest.mark.slow  # three runs of the workflow (about 2 minutes): `pytest -m slow`
def test_a_killed_run_resumes_to_the_same_outputs(tmp_path):
    """`wast3d run` killed (SIGKILL, the whole process group) mid-stylization and again mid-render, then
    run again, ends with the outputs of a run never interrupted, byte for byte. The target is the method's
    renders (stages 1-7: a file and a folder output killed mid-job); evaluation and tables write the same
    way and are left out to keep the three runs short."""
    import signal
    import time

    from wast3d.ply import write_ply
    from wast3d.procedural import make_scene

    write_ply(tmp_path / "blob.ply", make_scene("content", "torus", 1500))
    write_ply(tmp_path / "peb.ply", make_scene("style", "pebbles", 3000))
    cfg = tiny_config(tmp_path)
    cfg.pop("sweeps")
    cfg["scenes"] = {"blob": {"source": "ply", "path": str(tmp_path / "blob.ply")},
                     "peb": {"source": "ply", "path": str(tmp_path / "peb.ply")}}
    cfg["table1"]["methods"] = {"default": "ours", "colour_ot": "colour transfer", "input": "content"}

    def start(out: Path) -> subprocess.Popen:
        (out / "config").mkdir(parents=True, exist_ok=True)
        (out / "config" / "config.yaml").write_text(yaml.safe_dump(cfg))  # a config of the user's: kept
        return subprocess.Popen([sys.executable, "-m", "wast3d", "run", str(tmp_path / "blob.ply"),
                                 str(tmp_path / "peb.ply"), str(out), "--", "results/render/pairs/blob__peb/default"],
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)

    def kill_when(out: Path, started: str, done: str) -> None:
        """Run until the job that logs to ``started`` runs and ``done`` is not there yet, then SIGKILL."""
        p = start(out)
        deadline = time.monotonic() + 240
        while not (out / started).exists():
            assert p.poll() is None and time.monotonic() < deadline, f"the run ended before {started}"
            time.sleep(0.02)
        time.sleep(0.5)  # into the job: its interpreter is starting, or it is at work
        os.killpg(p.pid, signal.SIGKILL)
        p.wait()
        assert not (out / done).exists(), f"{done} was written before the kill: not killed mid-job"

    ref, resumed = tmp_path / "ref", tmp_path / "resumed"
    assert start(ref).wait() == 0
    kill_when(resumed, "results/logs/sinkhorn/blob__peb_default.log", "results/stylize/blob__peb/default/stylized.ply")
    kill_when(resumed, "results/logs/render/blob__peb_default.log", "results/render/pairs/blob__peb/default/turntable.gif")
    assert start(resumed).wait() == 0
    a, b = comparable(ref), comparable(resumed)
    assert sorted(a) == sorted(b)
    assert [k for k in a if a[k] != b[k]] == []
    assert len(a) > 30 and "results/stylize/blob__peb/default/final.ply" in a
    assert "results/render/pairs/blob__peb/default/turntable.gif" in a

"""wast3d: WaSt-3D scene-to-scene stylization as a workflow of cached stages.

    snakemake --profile workflow/profiles/local                                 # the demo
    snakemake --profile workflow/profiles/local --config sweep=paper_ablations  # the paper's ablations
    snakemake --profile workflow/profiles/local table1                          # only Table 1 and what it needs
    snakemake --profile workflow/profiles/local -n                              # what would run, and why
"""


import importlib.util
import os
import sys


def _load(name):
    """A light module of the package (declarations, no torch) read by path, whatever else is installed:
    the checkout's wast3d/NAME, or, in a wheel (the workflow is the data package wast3d/_workflow), the
    package's own."""
    paths = [os.path.join(workflow.basedir, "wast3d", name), os.path.join(workflow.basedir, "..", name)]
    path = next((p for p in paths if os.path.isfile(p)), None)
    if path is None:
        raise FileNotFoundError(f"wast3d/{name} is in none of {', '.join(paths)}")
    spec = importlib.util.spec_from_file_location(f"wast3d_{name[:-3]}", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod


# the config checked before anything reads it (wast3d/config_check.py): the default file bounded before
# Snakemake merges it (YAML alias bombs), the merged config in workflow/rules/common.smk
_CHECK = _load("config_check.py")
if os.path.exists("config/config.yaml"):
    _CHECK.check_yaml_file("config/config.yaml")


configfile: "config/config.yaml"


report: "workflow/report/workflow.rst"


include: "workflow/rules/common.smk"
include: "workflow/rules/scenes.smk"
include: "workflow/rules/pretrain.smk"
include: "workflow/rules/partition.smk"
include: "workflow/rules/stylize.smk"
include: "workflow/rules/render.smk"
include: "workflow/rules/evaluate.smk"
include: "workflow/rules/regions.smk"
include: "workflow/rules/benchmarks.smk"


rule all:
    input:
        expand(f"{RESULTS}/scenes/{{scene}}/preview.png", scene=USED_SCENES),
        [f"{RESULTS}/stylize/{c}__{s}/{e}/{f}" for c, s in PAIRS for e in RUN for f in ("preview.png", "losses.png")],
        f"{RESULTS}/tables/{TABLE}.csv",
        [results("render_pair", content=c, style=s, method=e) for c, s in PAIRS for e in RUN],
        [f"{RESULTS}/tables/table1.csv"] if TABLE1_PAIRS else [],  # a config may run region sets only
        [f"{RESULTS}/figures/{c}__{s}{k}.png" for c, s in TABLE1_PAIRS for k in ("", "_methods")],
        [f"{RESULTS}/figures/{c}__{s}_turntables.html" for c, s in TABLE1_PAIRS],
        [f"{RESULTS}/tables/regions.csv"] if REGION_SETS else [],
        [f"{RESULTS}/figures/{c['content']}__{name}_{e}_regions.png" for name, c in REGION_SETS.items() for e in RUN],
    default_target: True

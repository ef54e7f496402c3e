"""wast3d: WaSt-3D scene-to-scene stylization as a workflow of cached stages.

    snakemake --profile workflow/profiles/local                                 # the demo
    snakemake --profile workflow/profiles/local --config sweep=paper_ablations  # the paper's ablations
    snakemake --profile workflow/profiles/local table1                          # only Table 1 and what it needs
    snakemake --profile workflow/profiles/local -n                              # what would run, and why
"""


configfile: "config/config.yaml"


report: "workflow/report/workflow.rst"


include: "workflow/rules/common.smk"
include: "workflow/rules/scenes.smk"
include: "workflow/rules/pretrain.smk"
include: "workflow/rules/partition.smk"
include: "workflow/rules/stylize.smk"
include: "workflow/rules/render.smk"
include: "workflow/rules/evaluate.smk"
include: "workflow/rules/benchmarks.smk"


rule all:
    input:
        expand(f"{RESULTS}/scenes/{{scene}}/preview.png", scene=USED_SCENES),
        [f"{RESULTS}/stylize/{c}__{s}/{e}/{f}" for c, s in PAIRS for e in RUN for f in ("preview.png", "losses.png")],
        f"{RESULTS}/tables/{TABLE}.csv",
        [results("render_pair", content=c, style=s, method=e) for c, s in PAIRS for e in RUN],
        f"{RESULTS}/tables/table1.csv",
        [f"{RESULTS}/figures/{c}__{s}.png" for c, s in TABLE1_PAIRS],
        [f"{RESULTS}/figures/{c}__{s}_turntables.html" for c, s in TABLE1_PAIRS],
    default_target: True

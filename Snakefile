"""wast3d: WaSt-3D scene-to-scene stylization as a workflow of cached stages.

    snakemake --profile workflow/profiles/local            # the demo (config/config.yaml)
    snakemake --profile workflow/profiles/local -n         # what would run, and why
"""


configfile: "config/config.yaml"


include: "workflow/rules/common.smk"
include: "workflow/rules/scenes.smk"


rule all:
    input:
        expand(f"{RESULTS}/scenes/{{scene}}/preview.png", scene=list(SCENES)),
    default_target: True

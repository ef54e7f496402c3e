"""Stage 1: regularized 3DGS pretraining, only for scenes given as posed images."""


rule pretrain:
    input:
        transforms=lambda w: f"{pretrain_data(w)}/transforms_train.json",
    output:
        ply=results("scene"),
        csv=f"{RESULTS}/scenes/{{scene}}/pretrain_log.csv",
        json=f"{RESULTS}/scenes/{{scene}}/pretrain_eval.json",
    wildcard_constraints:
        scene=constraint(scenes_of("images")),
    params:
        exe=WAST3D,
        data=pretrain_data,  # parameters (tracked: a new folder re-runs) as well as the command's files
        ckpt=pretrain_checkpoint,
        cfg=lambda w: stage_params("pretrain", pretrain_params(w.scene)),
        args=stage_args("pretrain", ignore=("transforms",), data=pretrain_data, checkpoint=pretrain_checkpoint),
    threads: HEAVY_THREADS
    resources:
        mem_mb=16000,
        runtime=120,
    priority: first_result
    conda:
        "../envs/wast3d.yaml"
    log:
        f"{RESULTS}/logs/pretrain/{{scene}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/rules/pretrain_{{scene}}.tsv"
    shell:
        "{params.exe} --threads {threads} {params.args} --no-progress --params '{params.cfg}' 2> {log:q}"

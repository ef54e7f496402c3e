"""Scenes: every scene ends up as results/scenes/{scene}/scene.ply, by the one rule its source needs."""


rule procedural_scene:
    output:
        ply=results("scene"),
    wildcard_constraints:
        scene=constraint(scenes_of("procedural")),
    params:
        exe=WAST3D,
        kind=lambda w: SCENES[w.scene]["kind"],
        name=lambda w: SCENES[w.scene]["name"],
        n=lambda w: SCENES[w.scene].get("n_gaussians", 30000),
        seed=lambda w: SCENES[w.scene].get("seed", 0),
    priority: first_result
    conda:
        "../envs/wast3d.yaml"
    log:
        f"{RESULTS}/logs/scenes/{{scene}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/rules/scene_{{scene}}.tsv"
    shell:
        "{params.exe} --threads {threads} scene {params.kind:q} {params.name:q} {output.ply:q} --n {params.n:q} --seed {params.seed:q} 2> {log:q}"


rule import_ply:
    input:
        lambda w: SCENES[w.scene]["path"],
    output:
        ply=results("scene"),
    wildcard_constraints:
        scene=constraint(scenes_of("ply")),
    params:
        exe=WAST3D,
        drop=lambda w: "--drop-invalid" if SCENES[w.scene].get("drop_invalid") else "",
    priority: first_result
    conda:
        "../envs/wast3d.yaml"
    log:
        f"{RESULTS}/logs/scenes/{{scene}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/rules/import_{{scene}}.tsv"
    shell:
        "{params.exe} --threads {threads} import-ply {input:q} {output.ply:q} {params.drop} 2> {log:q}"


rule preview:
    input:
        ply=results("scene"),
    output:
        png=report(f"{RESULTS}/scenes/{{scene}}/preview.png", caption="../report/preview.rst", category="Scenes"),
    params:
        exe=WAST3D,
        views=config.get("preview", {}).get("views", 4),
        size=config.get("preview", {}).get("size", 256),
    conda:
        "../envs/wast3d.yaml"
    log:
        f"{RESULTS}/logs/preview/{{scene}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/rules/preview_{{scene}}.tsv"
    shell:
        "{params.exe} --threads {threads} preview {input.ply:q} {output.png:q} --views {params.views:q} --size {params.size:q} 2> {log:q}"


rule export_views:
    input:
        ply=results("scene"),
    output:
        json=f"{RESULTS}/views/{{scene}}/transforms_train.json",
    params:
        exe=WAST3D,
        folder=lambda w, output: os.path.dirname(output.json),
        views=48,
        size=200,
    conda:
        "../envs/wast3d.yaml"
    log:
        f"{RESULTS}/logs/export_views/{{scene}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/rules/export_views_{{scene}}.tsv"
    shell:
        "{params.exe} --threads {threads} export-views {input.ply:q} {params.folder:q} --views {params.views:q} --size {params.size:q} 2> {log:q}"

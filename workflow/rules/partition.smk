"""Stages 2-4: surface sampling (and style cleaning), k-means, registration (eq. 7), selection (eq. 8)."""


rule surface:
    input:
        scene=f"{RESULTS}/scenes/{{scene}}/scene.ply",
    output:
        ply=f"{RESULTS}/scenes/{{scene}}/surface.ply",
        json=f"{RESULTS}/scenes/{{scene}}/surface.json",
    wildcard_constraints:
        scene=constraint(scenes_needing_surface()),
    params:
        exe=WAST3D,
        cfg=lambda w: stage_json(SCENES[w.scene].get("surface", {})),
        args=stage_args("surface"),
    conda:
        "../envs/wast3d.yaml"
    log:
        f"{RESULTS}/logs/surface/{{scene}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/rules/surface_{{scene}}.tsv"
    shell:
        "{params.exe} --threads {threads} {params.args} --params '{params.cfg}' 2> {log}"


rule style_clean:
    input:
        scene=f"{RESULTS}/scenes/{{scene}}/scene.ply",
        labels_from=lambda w: [f"{RESULTS}/scenes/{SCENES[w.scene]['labels_from']}/scene.ply"] if SCENES[w.scene].get("labels_from") else [],
    output:
        ply=f"{RESULTS}/scenes/{{scene}}/style.ply",
        json=f"{RESULTS}/scenes/{{scene}}/style.json",
    wildcard_constraints:
        scene=constraint([s for s in SCENES if needs_style_clean(s)]),
    params:
        exe=WAST3D,
        cfg=lambda w: stage_json(SCENES[w.scene].get("style_clean", {})),
        args=stage_args("style-clean"),
    conda:
        "../envs/wast3d.yaml"
    log:
        f"{RESULTS}/logs/style_clean/{{scene}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/rules/style_clean_{{scene}}.tsv"
    shell:
        "{params.exe} --threads {threads} {params.args} --params '{params.cfg}' 2> {log}"


rule cluster:
    input:
        content=lambda w: content_points(w.content),
    output:
        npz=f"{RESULTS}/partition/{{content}}/{{partition}}/clusters.npz",
        json=f"{RESULTS}/partition/{{content}}/{{partition}}/clusters.json",
        picture=report(f"{RESULTS}/partition/{{content}}/{{partition}}/clusters.png",
                   caption="../report/clusters.rst", category="Partition"),
    params:
        exe=WAST3D,
        cfg=lambda w: stage_json(PARTITIONS[w.partition].get("cluster", {})),
        args=stage_args("cluster"),
    conda:
        "../envs/wast3d.yaml"
    log:
        f"{RESULTS}/logs/cluster/{{content}}_{{partition}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/rules/cluster_{{content}}_{{partition}}.tsv"
    shell:
        "{params.exe} --threads {threads} {params.args} --params '{params.cfg}' 2> {log}"


rule register:
    input:
        content=lambda w: content_points(w.content),
        clusters=f"{RESULTS}/partition/{{content}}/{{partition}}/clusters.npz",
        style=lambda w: style_points(w.style),
    output:
        npz=f"{RESULTS}/register/{{content}}__{{style}}/{{partition}}/registration.npz",
        json=f"{RESULTS}/register/{{content}}__{{style}}/{{partition}}/registration.json",
        picture=report(f"{RESULTS}/register/{{content}}__{{style}}/{{partition}}/registration.png",
                   caption="../report/registration.rst", category="Partition"),
    params:
        exe=WAST3D,
        cfg=lambda w: stage_json(PARTITIONS[w.partition].get("register", {})),
        args=stage_args("register"),
    conda:
        "../envs/wast3d.yaml"
    log:
        f"{RESULTS}/logs/register/{{content}}__{{style}}_{{partition}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/rules/register_{{content}}__{{style}}_{{partition}}.tsv"
    shell:
        "{params.exe} --threads {threads} {params.args} --params '{params.cfg}' 2> {log}"


rule select:
    input:
        content=lambda w: content_points(w.content),
        clusters=f"{RESULTS}/partition/{{content}}/{{partition}}/clusters.npz",
        style=lambda w: style_points(w.style),
        registration=f"{RESULTS}/register/{{content}}__{{style}}/{{partition}}/registration.npz",
    output:
        npz=f"{RESULTS}/register/{{content}}__{{style}}/{{partition}}/selection.npz",
        json=f"{RESULTS}/register/{{content}}__{{style}}/{{partition}}/selection.json",
    params:
        exe=WAST3D,
        cfg=lambda w: stage_json(PARTITIONS[w.partition].get("select", {})),
        args=stage_args("select"),
    conda:
        "../envs/wast3d.yaml"
    log:
        f"{RESULTS}/logs/select/{{content}}__{{style}}_{{partition}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/rules/select_{{content}}__{{style}}_{{partition}}.tsv"
    shell:
        "{params.exe} --threads {threads} {params.args} --params '{params.cfg}' 2> {log}"

"""Stages 2-4: surface sampling (and style cleaning), k-means, registration (eq. 7), selection (eq. 8)."""


rule surface:
    input:
        scene=results("scene"),
    output:
        ply=results("surface"),
        json=beside("surface", ".json"),
    wildcard_constraints:
        scene=constraint(scenes_needing_surface()),
    params:
        exe=WAST3D,
        cfg=lambda w: stage_params("surface", SCENES[w.scene].get("surface", {})),
        args=stage_args("surface"),
    priority: first_result
    conda:
        "../envs/wast3d.yaml"
    log:
        f"{RESULTS}/logs/surface/{{scene}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/rules/surface_{{scene}}.tsv"
    shell:
        "{params.exe} --threads {threads} {params.args} --params '{params.cfg}' 2> {log:q}"


rule style_clean:
    input:
        scene=results("scene"),
        labels_from=lambda w: [results("scene", scene=SCENES[w.scene]["labels_from"])] if SCENES[w.scene].get("labels_from") else [],
    output:
        ply=results("style"),
        json=beside("style", ".json"),
    wildcard_constraints:
        scene=constraint([s for s in SCENES if needs_style_clean(s)]),
    params:
        exe=WAST3D,
        cfg=lambda w: stage_params("style-clean", SCENES[w.scene].get("style_clean", {})),
        args=stage_args("style-clean"),
    priority: first_result
    conda:
        "../envs/wast3d.yaml"
    log:
        f"{RESULTS}/logs/style_clean/{{scene}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/rules/style_clean_{{scene}}.tsv"
    shell:
        "{params.exe} --threads {threads} {params.args} --params '{params.cfg}' 2> {log:q}"


rule cluster:
    input:
        content=lambda w: content_points(w.content),
    output:
        npz=results("clusters"),
        json=beside("clusters", ".json"),
        picture=report(beside("clusters", ".png"),
                   caption="../report/clusters.rst", category="Partition"),
    wildcard_constraints:
        content=constraint([c for c in SCENES if SCENES[c]["source"] != "region"]),  # regions.smk cuts those
    params:
        exe=WAST3D,
        cfg=lambda w: stage_params("cluster", PARTITIONS[w.partition].get("cluster", {})),
        args=stage_args("cluster"),
    priority: first_result
    conda:
        "../envs/wast3d.yaml"
    log:
        f"{RESULTS}/logs/cluster/{{content}}_{{partition}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/rules/cluster_{{content}}_{{partition}}.tsv"
    shell:
        "{params.exe} --threads {threads} {params.args} --params '{params.cfg}' 2> {log:q}"


rule register:
    input:
        content=lambda w: content_points(w.content),
        clusters=results("clusters"),
        style=lambda w: style_points(w.style),
        region=lambda w: beside("scene", ".json", scene=w.content) if w.content in REGION_CONTENTS else [],
        style_form=lambda w: [beside("style", ".json", scene=w.style)] if needs_style_clean(w.style) else [],
    output:
        npz=results("registration"),
        json=beside("registration", ".json"),
        picture=report(beside("registration", ".png"),
                   caption="../report/registration.rst", category="Partition"),
    params:
        exe=WAST3D,
        cfg=lambda w: stage_params("register", PARTITIONS[w.partition].get("register", {})),
        args=stage_args("register"),
    priority: first_result
    conda:
        "../envs/wast3d.yaml"
    log:
        f"{RESULTS}/logs/register/{{content}}__{{style}}_{{partition}}.log",
    benchmark:
        results("rule_benchmark", rule="register", job="{content}__{style}_{partition}")
    shell:
        "{params.exe} --threads {threads} {params.args} --params '{params.cfg}' 2> {log:q}"


rule select:
    input:
        content=lambda w: content_points(w.content),
        clusters=results("clusters"),
        style=lambda w: style_points(w.style),
        registration=results("registration"),
    output:
        npz=results("selection"),
        json=beside("selection", ".json"),
    params:
        exe=WAST3D,
        cfg=lambda w: stage_params("select", PARTITIONS[w.partition].get("select", {})),
        args=stage_args("select"),
    priority: first_result
    conda:
        "../envs/wast3d.yaml"
    log:
        f"{RESULTS}/logs/select/{{content}}__{{style}}_{{partition}}.log",
    benchmark:
        results("rule_benchmark", rule="select", job="{content}__{style}_{partition}")
    shell:
        "{params.exe} --threads {threads} {params.args} --params '{params.cfg}' 2> {log:q}"

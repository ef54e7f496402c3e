"""Stages 5-6: Sinkhorn stylization (eq. 9) and scale readjustment, per pair and experiment."""


rule sinkhorn:
    input:
        content=lambda w: content_points(w.content),
        clusters=lambda w: results("clusters", content=w.content, partition=partition_of(w)),
        style=lambda w: style_points(w.style),
        registration=lambda w: results("registration", content=w.content, style=w.style, partition=partition_of(w)),
        selection=lambda w: results("selection", content=w.content, style=w.style, partition=partition_of(w)),
        style_form=lambda w: [beside("style", ".json", scene=w.style)] if needs_style_clean(w.style) else [],
    output:
        ply=results("stylized"),
        npz=results("stylize_npz"),
        csv=results("losses"),
        json=beside("losses", ".json"),
        png=report(beside("losses", ".png"),
                   caption="../report/losses.rst", category="Results", subcategory="{experiment}"),
    wildcard_constraints:
        style=constraint(list(SCENES)),  # a region set's result is merged (regions.smk)
    params:
        exe=WAST3D,
        cfg=lambda w: stage_params("stylize", EXPERIMENTS[w.experiment].get("stylize", {})),
        args=stage_args("stylize"),
    threads: HEAVY_THREADS
    resources:
        mem_mb=8000,
        runtime=240,
    priority: first_result
    conda:
        "../envs/wast3d.yaml"
    log:
        f"{RESULTS}/logs/sinkhorn/{{content}}__{{style}}_{{experiment}}.log",
    benchmark:
        results("rule_benchmark", rule="sinkhorn", job="{content}__{style}_{experiment}")
    shell:
        "{params.exe} --threads {threads} {params.args} --params '{params.cfg}' 2> {log:q}"


rule rescale:
    input:
        stylized=results("stylized"),
        stylize_npz=results("stylize_npz"),
    output:
        ply=results("final"),
        json=beside("final", ".json"),
    wildcard_constraints:
        style=constraint(list(SCENES)),  # a region set's result is merged (regions.smk)
    params:
        exe=WAST3D,
        cfg=lambda w: stage_params("rescale", EXPERIMENTS[w.experiment].get("rescale", {})),
        args=stage_args("rescale"),
    priority: first_result
    conda:
        "../envs/wast3d.yaml"
    log:
        f"{RESULTS}/logs/rescale/{{content}}__{{style}}_{{experiment}}.log",
    benchmark:
        results("rule_benchmark", rule="rescale", job="{content}__{style}_{experiment}")
    shell:
        "{params.exe} --threads {threads} {params.args} --params '{params.cfg}' 2> {log:q}"

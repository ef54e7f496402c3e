"""Stages 5-6: Sinkhorn stylization (eq. 9) and scale readjustment, per pair and experiment."""


rule sinkhorn:
    input:
        content=lambda w: content_points(w.content),
        clusters=lambda w: f"{RESULTS}/partition/{w.content}/{partition_of(w)}/clusters.npz",
        style=lambda w: style_points(w.style),
        registration=lambda w: f"{RESULTS}/register/{w.content}__{w.style}/{partition_of(w)}/registration.npz",
        selection=lambda w: f"{RESULTS}/register/{w.content}__{w.style}/{partition_of(w)}/selection.npz",
    output:
        ply=f"{RESULTS}/stylize/{{content}}__{{style}}/{{experiment}}/stylized.ply",
        npz=f"{RESULTS}/stylize/{{content}}__{{style}}/{{experiment}}/stylize.npz",
        csv=f"{RESULTS}/stylize/{{content}}__{{style}}/{{experiment}}/losses.csv",
        json=f"{RESULTS}/stylize/{{content}}__{{style}}/{{experiment}}/losses.json",
        png=report(f"{RESULTS}/stylize/{{content}}__{{style}}/{{experiment}}/losses.png",
                   caption="../report/losses.rst", category="Results", subcategory="{experiment}"),
    params:
        exe=WAST3D,
        cfg=lambda w: stage_json(EXPERIMENTS[w.experiment].get("stylize", {})),
        args=stage_args("stylize"),
    threads: HEAVY_THREADS
    resources:
        mem_mb=8000,
        runtime=240,
    conda:
        "../envs/wast3d.yaml"
    log:
        f"{RESULTS}/logs/sinkhorn/{{content}}__{{style}}_{{experiment}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/rules/sinkhorn_{{content}}__{{style}}_{{experiment}}.tsv"
    shell:
        "{params.exe} --threads {threads} {params.args} --params '{params.cfg}' 2> {log}"


rule rescale:
    input:
        stylized=f"{RESULTS}/stylize/{{content}}__{{style}}/{{experiment}}/stylized.ply",
        stylize_npz=f"{RESULTS}/stylize/{{content}}__{{style}}/{{experiment}}/stylize.npz",
    output:
        ply=f"{RESULTS}/stylize/{{content}}__{{style}}/{{experiment}}/final.ply",
        json=f"{RESULTS}/stylize/{{content}}__{{style}}/{{experiment}}/final.json",
    params:
        exe=WAST3D,
        cfg=lambda w: stage_json(EXPERIMENTS[w.experiment].get("rescale", {})),
        args=stage_args("rescale"),
    conda:
        "../envs/wast3d.yaml"
    log:
        f"{RESULTS}/logs/rescale/{{content}}__{{style}}_{{experiment}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/rules/rescale_{{content}}__{{style}}_{{experiment}}.tsv"
    shell:
        "{params.exe} --threads {threads} {params.args} --params '{params.cfg}' 2> {log}"

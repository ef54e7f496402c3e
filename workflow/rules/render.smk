"""Stage 7: renders of results, and the summary table."""


rule result_preview:
    input:
        ply=results("final"),
    output:
        png=report(f"{RESULTS}/stylize/{{content}}__{{style}}/{{experiment}}/preview.png",
                   caption="../report/result.rst", category="Results", subcategory="{experiment}"),
    params:
        exe=WAST3D,
        views=config.get("preview", {}).get("views", 4),
        size=config.get("preview", {}).get("size", 256),
    conda:
        "../envs/wast3d.yaml"
    log:
        f"{RESULTS}/logs/preview/{{content}}__{{style}}_{{experiment}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/rules/preview_{{content}}__{{style}}_{{experiment}}.tsv"
    shell:
        "{params.exe} --threads {threads} preview {input.ply:q} {output.png:q} --views {params.views:q} --size {params.size:q} 2> {log:q}"


rule summary:
    wildcard_constraints:
        table=constraint(["summary"] + list(config.get("sweeps", {}))),
    input:
        lambda w: [f"{RESULTS}/stylize/{r}/final.json" for r in summary_runs(table_experiments(w.table))],
    output:
        csv=f"{RESULTS}/tables/{{table}}.csv",
        md=f"{RESULTS}/tables/{{table}}.md",
        html=report(f"{RESULTS}/tables/{{table}}.html", caption="../report/summary.rst", category="Tables"),
    params:
        exe=WAST3D,
        results=lambda w, output: os.path.dirname(os.path.dirname(output.csv)),
        runs=lambda w: quoted(summary_runs(table_experiments(w.table))),
    conda:
        "../envs/wast3d.yaml"
    log:
        f"{RESULTS}/logs/tables/{{table}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/rules/table_{{table}}.tsv"
    shell:
        "{params.exe} --threads {threads} summarize {params.results:q} {output.csv:q} --md {output.md:q} --html {output.html:q} --run {params.runs} > {log:q} 2>&1"

"""Benchmarks as workflow targets (not part of `all`: run `snakemake benchmarks`)."""


rule sinkhorn_error_vs_time:
    output:
        csv=f"{RESULTS}/benchmarks/sinkhorn_error_vs_time.csv",
        png=report(f"{RESULTS}/benchmarks/sinkhorn_error_vs_time.png",
                   caption="../report/error_vs_time.rst", category="Benchmarks"),
    params:
        exe=PYTHON,
        script=f"{workflow.basedir}/benchmarks/sinkhorn_error_vs_time.py",
        sizes=" ".join(str(s) for s in config.get("benchmarks", {}).get("sinkhorn_sizes", [256, 512, 1024, 2048, 4096, 8192])),
    conda:
        "../envs/wast3d.yaml"
    log:
        f"{RESULTS}/logs/benchmarks/sinkhorn_error_vs_time.log",
    benchmark:
        f"{RESULTS}/benchmarks/rules/sinkhorn_error_vs_time.tsv"
    shell:
        "{params.exe} {params.script:q} --sizes {params.sizes} "
        "--out {output.csv:q} > {log:q} 2>&1"


rule metrics_validation:
    output:
        csv=f"{RESULTS}/benchmarks/metrics_validation.csv",
        png=report(f"{RESULTS}/benchmarks/metrics_validation.png",
                   caption="../report/metrics_validation.rst", category="Benchmarks"),
    params:
        exe=PYTHON,
        script=f"{workflow.basedir}/benchmarks/metrics_validation.py",
    conda:
        "../envs/wast3d.yaml"
    log:
        f"{RESULTS}/logs/benchmarks/metrics_validation.log",
    benchmark:
        f"{RESULTS}/benchmarks/rules/metrics_validation.tsv"
    shell:
        "{params.exe} {params.script:q} --seeds 5 --out {output.csv:q} > {log:q} 2>&1"


# every variant on ant x pebbles, the previous and the new default and the references on the others
# (about an hour on 2 cores)
rule style_tradeoff:
    output:
        csv=f"{RESULTS}/benchmarks/style_tradeoff.csv",
        png=report(f"{RESULTS}/benchmarks/style_tradeoff.png",
                   caption="../report/style_tradeoff.rst", category="Benchmarks"),
    params:
        exe=PYTHON,
        script=f"{workflow.basedir}/benchmarks/style_tradeoff.py",
    conda:
        "../envs/wast3d.yaml"
    log:
        f"{RESULTS}/logs/benchmarks/style_tradeoff.log",
    benchmark:
        f"{RESULTS}/benchmarks/rules/style_tradeoff.tsv"
    shell:
        "({params.exe} {params.script:q} --pairs ant:pebbles --out {output.csv:q} && "
        "{params.exe} {params.script:q} --pairs ant:grass ant:wicker ant:stones --variants base "
        "footprint_r1.5_flow_gamma_0.3_steps_30_lr_0.2 collage input --out {output.csv:q}) > {log:q} 2>&1"


rule benchmarks:
    input:
        f"{RESULTS}/benchmarks/sinkhorn_error_vs_time.csv",
        f"{RESULTS}/benchmarks/metrics_validation.csv",
        f"{RESULTS}/benchmarks/style_tradeoff.csv",
    default_target: False

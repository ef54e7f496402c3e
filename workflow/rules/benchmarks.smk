"""Benchmarks as workflow targets (not part of `all`: run `snakemake benchmarks`)."""


rule sinkhorn_error_vs_time:
    output:
        csv=f"{RESULTS}/benchmarks/sinkhorn_error_vs_time.csv",
        png=report(f"{RESULTS}/benchmarks/sinkhorn_error_vs_time.png",
                   caption="../report/error_vs_time.rst", category="Benchmarks"),
    params:
        exe=sys.executable,
        script=f"{workflow.basedir}/benchmarks/sinkhorn_error_vs_time.py",
        sizes=" ".join(str(s) for s in config.get("benchmarks", {}).get("sinkhorn_sizes", [256, 512, 1024, 2048, 4096, 8192])),
    conda:
        "../envs/wast3d.yaml"
    log:
        f"{RESULTS}/logs/benchmarks/sinkhorn_error_vs_time.log",
    benchmark:
        f"{RESULTS}/benchmarks/rules/sinkhorn_error_vs_time.tsv"
    shell:
        "{params.exe} {params.script} --sizes {params.sizes} "
        "--out {output.csv} > {log} 2>&1"


rule benchmarks:
    input:
        f"{RESULTS}/benchmarks/sinkhorn_error_vs_time.csv",
    default_target: False

"""Several styles on one content, by region (config `regions`, wast3d/regions.py): each region's points and
clusters cut from the content's (nothing upstream re-runs), each region's pair through stages 4-6, the
results merged into one scene, the seams measured, and a table of every region against its own style."""


def region_set_of(w):
    return REGION_SETS[w.set]


def region_content_of(w):
    """The content scene a region scene (wildcard scene or content) was cut from."""
    return SCENES[getattr(w, "scene", None) or w.content]["content"]


def region_file(scene):
    return f"{RESULTS}/regions/{SCENES[scene]['set']}/regions.npz"


def labels_inputs(w):
    """A labels region's file and the content scene it numbers (tracked: a new file re-runs the split)."""
    regs = [r for r in region_set_of(w)["regions"] if r.kind == "labels"]
    return ([r.spec["path"] for r in regs[:1]]
            + [results("scene", scene=region_set_of(w)["content"])] if regs else [])


rule regions:
    input:
        content=lambda w: content_points(region_set_of(w)["content"]),
        scene=lambda w: labels_inputs(w)[1:],
        labels=lambda w: labels_inputs(w)[:1],
    output:
        npz=f"{RESULTS}/regions/{{set}}/regions.npz",
        json=f"{RESULTS}/regions/{{set}}/regions.json",
        picture=report(f"{RESULTS}/regions/{{set}}/regions.png", caption="../report/clusters.rst", category="Partition"),
    wildcard_constraints:
        set=constraint(list(REGION_SETS)),
    params:
        exe=WAST3D,
        cfg=lambda w: stage_json({"regions": config["regions"][w.set]["styles"]}),
        args=stage_args("regions", ignore=("labels",)),
    conda:
        "../envs/wast3d.yaml"
    log:
        f"{RESULTS}/logs/regions/{{set}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/rules/regions_{{set}}.tsv"
    shell:
        "{params.exe} --threads {threads} {params.args} --params '{params.cfg}' 2> {log:q}"


rule region_content:
    input:
        content=lambda w: content_points(region_content_of(w)),
        regions=lambda w: region_file(w.scene),
    output:
        ply=results("scene"),
        json=beside("scene", ".json"),
    wildcard_constraints:
        scene=constraint(list(REGION_CONTENTS)),
    params:
        exe=WAST3D,
        cfg=lambda w: stage_json({"index": SCENES[w.scene]["index"]}),
        args=stage_args("region-content"),
    conda:
        "../envs/wast3d.yaml"
    log:
        f"{RESULTS}/logs/regions/{{scene}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/rules/region_content_{{scene}}.tsv"
    shell:
        "{params.exe} --threads {threads} {params.args} --params '{params.cfg}' 2> {log:q}"


rule region_clusters:
    input:
        clusters=lambda w: results("clusters", content=region_content_of(w), partition=w.partition),
        regions=lambda w: region_file(w.content),
    output:
        npz=results("clusters"),
        json=beside("clusters", ".json"),
    wildcard_constraints:
        content=constraint(list(REGION_CONTENTS)),
    params:
        exe=WAST3D,
        cfg=lambda w: stage_json({"index": SCENES[w.content]["index"]}),
        args=stage_args("region-clusters"),
    conda:
        "../envs/wast3d.yaml"
    log:
        f"{RESULTS}/logs/regions/{{content}}_{{partition}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/rules/region_clusters_{{content}}_{{partition}}.tsv"
    shell:
        "{params.exe} --threads {threads} {params.args} --params '{params.cfg}' 2> {log:q}"


def region_finals(w):
    """The results of a set's regions for one experiment, in the set's order."""
    return [results("final", content=f"{w.style}-{k}", style=r.style, experiment=w.experiment)
            for k, r in enumerate(REGION_SETS[w.style]["regions"])]


rule merge_regions:
    input:
        region_finals,
    output:
        ply=results("final"),
        json=beside("final", ".json"),
    wildcard_constraints:
        style=constraint(list(REGION_SETS)),
    params:
        exe=WAST3D,
        parts=lambda w, input: quoted(f"{r.style}={p}" for r, p in zip(REGION_SETS[w.style]["regions"], input)),
    conda:
        "../envs/wast3d.yaml"
    log:
        f"{RESULTS}/logs/regions/merge_{{content}}__{{style}}_{{experiment}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/rules/merge_{{content}}__{{style}}_{{experiment}}.tsv"
    shell:
        "{params.exe} --threads {threads} merge-regions {output.ply:q} {params.parts} 2> {log:q}"


rule seams:
    input:
        content=lambda w: content_points(w.content),
        regions=lambda w: f"{RESULTS}/regions/{w.style}/regions.npz",
        result=results("final"),
        alone=lambda w: [results("final", content=w.content, style=r.style, experiment=w.experiment)
                         for r in REGION_SETS[w.style]["regions"]],
        alone_renders=lambda w: [results("render_pair", content=w.content, style=r.style, method=w.experiment)
                                 for r in REGION_SETS[w.style]["regions"]],
        result_render=lambda w: results("render_pair", content=w.content, style=w.style, method=w.experiment),
        content_render=lambda w: results("render_pair", content=w.content, style=w.style, method="input"),
    output:
        json=f"{RESULTS}/eval/{{content}}__{{style}}/{{experiment}}_seams.json",
    wildcard_constraints:
        style=constraint(list(REGION_SETS)),
    params:
        exe=WAST3D,
        cfg=lambda w, input: stage_json({"alone": list(input.alone), "alone_renders": list(input.alone_renders)}),
        args=stage_args("seams", ignore=("alone", "alone_renders")),
    conda:
        "../envs/wast3d.yaml"
    log:
        f"{RESULTS}/logs/regions/seams_{{content}}__{{style}}_{{experiment}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/rules/seams_{{content}}__{{style}}_{{experiment}}.tsv"
    shell:
        "{params.exe} --threads {threads} {params.args} --params '{params.cfg}' 2> {log:q}"


def set_styles(name):
    """A region set's styles, each once, in the set's order (two regions may take one style)."""
    return list(dict.fromkeys(r.style for r in REGION_SETS[name]["regions"]))


rule regions_sheet:
    input:
        content=lambda w: results("render_pair", content=w.content, style=w.style, method="input"),
        result=lambda w: results("render_pair", content=w.content, style=w.style, method=w.experiment),
        alone=lambda w: [results("render_pair", content=w.content, style=st, method=w.experiment)
                         for st in set_styles(w.style)],
    output:
        report(f"{RESULTS}/figures/{{content}}__{{style}}_{{experiment}}_regions.png",
               caption="../report/comparison.rst", category="Figures"),
    wildcard_constraints:
        style=constraint(list(REGION_SETS)),
    params:
        exe=WAST3D,
        columns=lambda w, input: quoted(
            [f"content={input.content}", f"by regions={input.result}"]
            + [f"{st} alone={p}" for st, p in zip(set_styles(w.style), input.alone)]),
    conda:
        "../envs/wast3d.yaml"
    log:
        f"{RESULTS}/logs/figures/{{content}}__{{style}}_{{experiment}}_regions.log",
    shell:
        "{params.exe} --threads {threads} compare {output:q} {params.columns} 2> {log:q}"


def regions_table_rows():
    return quoted(f"{c['content']}__{name}/{e}" for name, c in REGION_SETS.items() for e in RUN)


rule regions_table:
    input:
        [f"{RESULTS}/eval/{c['content']}__{name}/{e}_seams.json" for name, c in REGION_SETS.items() for e in RUN],
        [results("eval", content=f"{name}-{k}", style=r.style, method=e)
         for name, c in REGION_SETS.items() for k, r in enumerate(c["regions"]) for e in RUN],
    output:
        csv=f"{RESULTS}/tables/regions.csv",
        md=f"{RESULTS}/tables/regions.md",
        html=report(f"{RESULTS}/tables/regions.html", caption="../report/table1.rst", category="Tables"),
    params:
        exe=WAST3D,
        results=lambda w, output: os.path.dirname(os.path.dirname(output.csv)),
        rows=regions_table_rows(),
    conda:
        "../envs/wast3d.yaml"
    log:
        f"{RESULTS}/logs/tables/regions.log",
    shell:
        "{params.exe} --threads {threads} regions-table {params.results:q} {output.csv:q} --md {output.md:q} "
        "--html {output.html:q} --run {params.rows} > {log:q} 2>&1"

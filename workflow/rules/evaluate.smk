"""Stages 7-9 for Table 1: renders (turntable, key views, close-up, depth, normals), the colour-transfer
baseline, the evaluation of each method (weights-free metrics, CLIP crop similarity), comparison
sheets and Table 1. Renders of a pair use cameras fitted to its content, so that all methods show the
same views and the same close-up fragment."""


rule render_method:
    input:
        scene=method_ply,
        reference=lambda w: content_points(w.content),
    output:
        folder=directory(results("render_pair")),
    params:
        exe=WAST3D,
        cfg=lambda w: stage_params("render", render_block(w.content)),
        args=stage_args("render"),
    priority: first_result
    conda:
        "../envs/wast3d.yaml"
    log:
        f"{RESULTS}/logs/render/{{content}}__{{style}}_{{method}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/rules/render_{{content}}__{{style}}_{{method}}.tsv"
    shell:
        "{params.exe} --threads {threads} {params.args} --no-progress --params '{params.cfg}' 2> {log:q}"


rule render_scene:
    input:
        scene=results("scene"),
    output:
        folder=directory(results("render_scene")),
    params:
        exe=WAST3D,
        cfg=lambda w: stage_params("render", render_block(w.scene)),
        args=stage_args("render", reference=lambda w: results("scene", scene=w.scene)),  # its own cameras
    priority: first_result
    conda:
        "../envs/wast3d.yaml"
    log:
        f"{RESULTS}/logs/render/scene_{{scene}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/rules/render_scene_{{scene}}.tsv"
    shell:
        "{params.exe} --threads {threads} {params.args} --no-progress --params '{params.cfg}' 2> {log:q}"


rule texture_reference:
    input:
        style=lambda w: style_points(w.style),
        content=lambda w: content_points(w.content),
        registration=results("registration", partition=REFERENCE_PARTITION),
        style_form=lambda w: [beside("style", ".json", scene=w.style)] if needs_style_clean(w.style) else [],
    output:
        folder=directory(results("texture_reference")),
    params:
        exe=WAST3D,
        cfg=lambda w: stage_params("texture-reference", render_block(w.style)),
        args=stage_args("texture-reference"),
    priority: first_result
    conda:
        "../envs/wast3d.yaml"
    log:
        f"{RESULTS}/logs/render/texture_reference_{{content}}__{{style}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/rules/texture_reference_{{content}}__{{style}}.tsv"
    shell:
        "{params.exe} --threads {threads} {params.args} --no-progress --params '{params.cfg}' 2> {log:q}"


rule colour_transfer:
    input:
        content=lambda w: content_points(w.content),
        style=lambda w: style_points(w.style),
    output:
        ply=results("final", method="colour_ot"),
        json=beside("final", ".json", method="colour_ot"),
    params:
        exe=WAST3D,
        cfg=stage_params("colour-transfer", EVALUATION.get("colour_transfer", {})),
        args=stage_args("colour-transfer"),
    priority: first_result
    conda:
        "../envs/wast3d.yaml"
    log:
        f"{RESULTS}/logs/colour_transfer/{{content}}__{{style}}.log",
    benchmark:
        results("rule_benchmark", rule="colour_transfer", job="{content}__{style}")
    shell:
        "{params.exe} --threads {threads} {params.args} --params '{params.cfg}' 2> {log:q}"


rule evaluate:
    input:
        result=method_ply,
        content=lambda w: content_points(w.content),
        style=lambda w: style_points(w.style),
        result_render=results("render_pair"),
        style_render=results("render_scene", scene="{style}"),
        texture_reference=results("texture_reference"),
        content_render=results("render_pair", method="input"),
        stylize_npz=lambda w: [results("stylize_npz", content=w.content, style=w.style, experiment=w.method)] if w.method in EXPERIMENTS else [],
        clip=clip_inputs(),
    output:
        json=results("eval"),
    params:
        exe=WAST3D,
        cfg=stage_params("evaluate", {k: EVALUATION[k] for k in STAGES["evaluate"].config if k in EVALUATION}),
        args=stage_args("evaluate", ignore=("clip",)),
    conda:
        "../envs/wast3d.yaml"
    log:
        f"{RESULTS}/logs/evaluate/{{content}}__{{style}}_{{method}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/rules/evaluate_{{content}}__{{style}}_{{method}}.tsv"
    shell:
        "{params.exe} --threads {threads} {params.args} --params '{params.cfg}' 2> {log:q}"


rule comparison_sheet:
    input:
        content=results("render_pair", method="input"),
        style=results("render_scene", scene="{style}"),
        reference=results("texture_reference"),
        methods=lambda w: sheet_method_renders(w, SHEET_MAIN),
    output:
        report(f"{RESULTS}/figures/{{content}}__{{style}}.png", caption="../report/comparison.rst", category="Figures"),
    wildcard_constraints:
        content=constraint(list(SCENES)),
        style=constraint(list(SCENES)),
    params:
        exe=WAST3D,
        columns=lambda w, input: sheet_columns(input, methods=SHEET_MAIN),
    priority: first_result
    conda:
        "../envs/wast3d.yaml"
    log:
        f"{RESULTS}/logs/figures/{{content}}__{{style}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/rules/figure_{{content}}__{{style}}.tsv"
    shell:
        "{params.exe} --threads {threads} compare {output:q} {params.columns} 2> {log:q}"


rule methods_sheet:
    input:
        content=results("render_pair", method="input"),
        style=results("render_scene", scene="{style}"),
        reference=results("texture_reference"),
        methods=sheet_method_renders,
    output:
        report(f"{RESULTS}/figures/{{content}}__{{style}}_methods.png", caption="../report/comparison.rst",
               category="Figures"),
    wildcard_constraints:
        content=constraint(list(SCENES)),
        style=constraint(list(SCENES)),
    params:
        exe=WAST3D,
        columns=lambda w, input: sheet_columns(input),
    conda:
        "../envs/wast3d.yaml"
    log:
        f"{RESULTS}/logs/figures/{{content}}__{{style}}_methods.log",
    benchmark:
        f"{RESULTS}/benchmarks/rules/figure_{{content}}__{{style}}_methods.tsv"
    shell:
        "{params.exe} --threads {threads} compare {output:q} {params.columns} 2> {log:q}"


rule turntable_page:
    input:
        content=results("render_pair", method="input"),
        style=results("render_scene", scene="{style}"),
        methods=sheet_method_renders,
    output:
        report(f"{RESULTS}/figures/{{content}}__{{style}}_turntables.html", caption="../report/turntables.rst",
               category="Turntables"),
    params:
        exe=WAST3D,
        columns=lambda w, input: sheet_columns(input, reference=False),
    conda:
        "../envs/wast3d.yaml"
    log:
        f"{RESULTS}/logs/figures/{{content}}__{{style}}_turntables.log",
    benchmark:
        f"{RESULTS}/benchmarks/rules/turntables_{{content}}__{{style}}.tsv"
    shell:
        "{params.exe} --threads {threads} turntables {output:q} {params.columns} 2> {log:q}"


rule table1:
    input:
        [results("eval", content=c, style=s, method=m) for c, s in TABLE1_PAIRS for m in TABLE1_METHODS],
    output:
        csv=f"{RESULTS}/tables/table1.csv",
        md=f"{RESULTS}/tables/table1.md",
        html=report(f"{RESULTS}/tables/table1.html", caption="../report/table1.rst", category="Tables"),
    params:
        exe=WAST3D,
        results=lambda w, output: os.path.dirname(os.path.dirname(output.csv)),
        rows=table1_rows(),
    conda:
        "../envs/wast3d.yaml"
    log:
        f"{RESULTS}/logs/tables/table1.log",
    benchmark:
        f"{RESULTS}/benchmarks/rules/table_table1.tsv"
    shell:
        "{params.exe} --threads {threads} table1 {params.results:q} {output.csv:q} --md {output.md:q} --html {output.html:q} --row {params.rows} > {log:q} 2>&1"

"""Stages 7-9 for Table 1: renders (turntable, key views, close-up, depth, normals), the colour-transfer
baseline, the evaluation of each method (weights-free metrics, CLIP crop similarity), comparison
sheets and Table 1. Renders of a pair use cameras fitted to its content, so that all methods show the
same views and the same close-up fragment."""


rule render_method:
    input:
        scene=method_ply,
        reference=lambda w: content_points(w.content),
    output:
        folder=directory(f"{RESULTS}/render/pairs/{{content}}__{{style}}/{{method}}"),
    params:
        exe=WAST3D,
        cfg=stage_json(EVALUATION.get("render", {})),
        args=stage_args("render"),
    conda:
        "../envs/wast3d.yaml"
    log:
        f"{RESULTS}/logs/render/{{content}}__{{style}}_{{method}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/rules/render_{{content}}__{{style}}_{{method}}.tsv"
    shell:
        "{params.exe} --threads {threads} {params.args} --no-progress --params '{params.cfg}' 2> {log}"


rule render_scene:
    input:
        scene=f"{RESULTS}/scenes/{{scene}}/scene.ply",
    output:
        folder=directory(f"{RESULTS}/render/scenes/{{scene}}"),
    params:
        exe=WAST3D,
        cfg=stage_json(EVALUATION.get("render", {})),
        args=stage_args("render", reference=lambda w: f"{RESULTS}/scenes/{w.scene}/scene.ply"),  # its own cameras
    conda:
        "../envs/wast3d.yaml"
    log:
        f"{RESULTS}/logs/render/scene_{{scene}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/rules/render_scene_{{scene}}.tsv"
    shell:
        "{params.exe} --threads {threads} {params.args} --no-progress --params '{params.cfg}' 2> {log}"


rule texture_reference:
    input:
        style=lambda w: style_points(w.style),
        content=lambda w: content_points(w.content),
        registration=f"{RESULTS}/register/{{content}}__{{style}}/{REFERENCE_PARTITION}/registration.npz",
    output:
        folder=directory(f"{RESULTS}/render/texture_reference/{{content}}__{{style}}"),
    params:
        exe=WAST3D,
        cfg=stage_json(EVALUATION.get("render", {})),
        args=stage_args("texture-reference"),
    conda:
        "../envs/wast3d.yaml"
    log:
        f"{RESULTS}/logs/render/texture_reference_{{content}}__{{style}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/rules/texture_reference_{{content}}__{{style}}.tsv"
    shell:
        "{params.exe} --threads {threads} {params.args} --no-progress --params '{params.cfg}' 2> {log}"


rule colour_transfer:
    input:
        content=lambda w: content_points(w.content),
        style=lambda w: style_points(w.style),
    output:
        ply=f"{RESULTS}/stylize/{{content}}__{{style}}/colour_ot/final.ply",
        json=f"{RESULTS}/stylize/{{content}}__{{style}}/colour_ot/final.json",
    params:
        exe=WAST3D,
        cfg=stage_json(EVALUATION.get("colour_transfer", {})),
        args=stage_args("colour-transfer"),
    conda:
        "../envs/wast3d.yaml"
    log:
        f"{RESULTS}/logs/colour_transfer/{{content}}__{{style}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/rules/colour_transfer_{{content}}__{{style}}.tsv"
    shell:
        "{params.exe} --threads {threads} {params.args} --params '{params.cfg}' 2> {log}"


rule evaluate:
    input:
        result=method_ply,
        content=lambda w: content_points(w.content),
        style=lambda w: style_points(w.style),
        result_render=f"{RESULTS}/render/pairs/{{content}}__{{style}}/{{method}}",
        style_render=f"{RESULTS}/render/scenes/{{style}}",
        texture_reference=f"{RESULTS}/render/texture_reference/{{content}}__{{style}}",
        content_render=f"{RESULTS}/render/pairs/{{content}}__{{style}}/input",
        stylize_npz=lambda w: [f"{RESULTS}/stylize/{w.content}__{w.style}/{w.method}/stylize.npz"] if w.method in EXPERIMENTS else [],
        clip=clip_inputs(),
    output:
        json=f"{RESULTS}/eval/{{content}}__{{style}}/{{method}}.json",
    params:
        exe=WAST3D,
        cfg=stage_json({k: EVALUATION[k] for k in ("metrics", "texture", "crops", "clip", "elements") if k in EVALUATION}),
        args=stage_args("evaluate", ignore=("clip",)),
    conda:
        "../envs/wast3d.yaml"
    log:
        f"{RESULTS}/logs/evaluate/{{content}}__{{style}}_{{method}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/rules/evaluate_{{content}}__{{style}}_{{method}}.tsv"
    shell:
        "{params.exe} --threads {threads} {params.args} --params '{params.cfg}' 2> {log}"


rule comparison_sheet:
    input:
        content=f"{RESULTS}/render/pairs/{{content}}__{{style}}/input",
        style=f"{RESULTS}/render/scenes/{{style}}",
        reference=f"{RESULTS}/render/texture_reference/{{content}}__{{style}}",
        methods=sheet_method_renders,
    output:
        report(f"{RESULTS}/figures/{{content}}__{{style}}.png", caption="../report/comparison.rst", category="Figures"),
    params:
        exe=WAST3D,
        columns=lambda w, input: sheet_columns(input),
    conda:
        "../envs/wast3d.yaml"
    log:
        f"{RESULTS}/logs/figures/{{content}}__{{style}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/rules/figure_{{content}}__{{style}}.tsv"
    shell:
        "{params.exe} --threads {threads} compare {output} {params.columns} 2> {log}"


rule turntable_page:
    input:
        content=f"{RESULTS}/render/pairs/{{content}}__{{style}}/input",
        style=f"{RESULTS}/render/scenes/{{style}}",
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
        "{params.exe} --threads {threads} turntables {output} {params.columns} 2> {log}"


rule table1:
    input:
        [f"{RESULTS}/eval/{c}__{s}/{m}.json" for c, s in TABLE1_PAIRS for m in TABLE1_METHODS],
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
        "{params.exe} --threads {threads} table1 {params.results} {output.csv} --md {output.md} --html {output.html} --row {params.rows} > {log} 2>&1"

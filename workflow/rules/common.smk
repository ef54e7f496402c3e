"""Shared by all rule files (config validation, experiments and sweeps) and the decisions about which
stages each scene needs (logged when a stage is left out)."""

import copy
import importlib.util
import os
import json
import shlex
import sys

import yaml


# the config checked before anything else reads it: its size (YAML alias bombs), finite numbers, then
# the schema, each error one line naming the config file and the key (wast3d/config_check.py)
_CONFIG_FILES = [str(f) for f in workflow.configfiles]
for _f in _CONFIG_FILES:  # Snakemake's loader keeps the last of a key given twice, without a word
    _CHECK.check_yaml_file(_f)
_CHECK.check_size(config, f"config ({', '.join(_CONFIG_FILES) or '--config'})")
# the one required key a scene's `source` alone does not say, named before the schema's whole-oneOf message
for _name, _s in (config.get("scenes") or {}).items():
    if isinstance(_s, dict) and _s.get("source") in ("images", "procedural") and "kind" not in _s:
        raise _CHECK.ConfigError(
            f"{_CHECK.source(('scenes', _name), _CONFIG_FILES)}: scenes.{_name}: 'kind' (content or style) is required "
            f"for source {_s['source']}" + (": a style's images are pretrained with the regularizers of eq. 1-2, a "
                                            "content's without" if _s["source"] == "images" else ""))
with open(os.path.join(workflow.basedir, "workflow", "schemas", "config.schema.yaml")) as _f:
    _CHECK.check_config(config, yaml.safe_load(_f), _CONFIG_FILES)

RESULTS = "results"


def uses_conda() -> bool:
    """Whether Snakemake deploys the rules' `conda:` environment (`--sdm conda`)."""
    from snakemake.settings.types import DeploymentMethod

    return DeploymentMethod.CONDA in workflow.deployment_settings.deployment_method


# the interpreter running Snakemake runs the stages too (no PATH set-up needed, same on cluster nodes);
# with `--sdm conda`, the `python` of the rule's environment (workflow/envs/wast3d.yaml). Shell-quoted,
# as is every path in the rules' commands (`{input:q}`): a folder name never splits or runs a command.
PYTHON = "python" if uses_conda() else shlex.quote(sys.executable)
WAST3D = f"{PYTHON} -m wast3d"
# Threads: each job passes its `threads` to the command (`wast3d --threads N`: torch, the native
# kernels and the KD-trees use exactly N, and OpenMP threads sleep when idle), so jobs that share a
# machine never oversubscribe it. The two stages that dominate the run time (Sinkhorn, pretraining)
# take HEAVY_THREADS (capped by --cores; a profile's `set-threads` overrides it); the others 1, so
# that light jobs run side by side.
HEAVY_THREADS = 2

SCENES = dict(config["scenes"])
PARTITIONS = config.get("partitions", {"default": {}})
PAIRS = [tuple(p) for p in config.get("pairs", [])]

# Several styles on one content, by region (wast3d/regions.py): region k of set NAME is a content of its
# own, scene NAME-k (its points: the content points it claims; its clusters: the content's cut by it),
# paired with its style; the pairs' results are merged into results/stylize/CONTENT__NAME/.
_REGIONS = _load("regions.py")
_VOLUME = _load("volume.py")  # the procedural styles that are volumes
REGION_SETS, REGION_CONTENTS = {}, {}
for _set, _r in (config.get("regions") or {}).items():
    _where = _CHECK.source(("regions", _set), _CONFIG_FILES)
    try:
        _parsed = _REGIONS.parse_set(_r["styles"], f"regions.{_set}.styles")
    except ValueError as e:
        raise _CHECK.ConfigError(f"{_where}: {e}") from None
    for _what, _name in [("the set", _set), ("its content", _r["content"])] + [("a style", _x.style) for _x in _parsed]:
        if (_name == _set) == (_name in SCENES):
            raise _CHECK.ConfigError(f"{_where}: regions.{_set}: {_what} '{_name}' "
                                     + ("is a scene's name" if _name == _set else "is not defined under 'scenes'"))
    REGION_SETS[_set] = {"content": _r["content"], "regions": _parsed}
    for _k, _x in enumerate(_parsed):
        _rc = f"{_set}-{_k}"
        if _rc in SCENES:
            raise _CHECK.ConfigError(f"{_where}: region content '{_rc}' would shadow the scene of that name")
        SCENES[_rc] = {"source": "region", "set": _set, "index": _k, "content": _r["content"]}
        REGION_CONTENTS[_rc] = (_set, _k)
        PAIRS.append((_rc, _x.style))
# the texture reference shows the style at the scale this partition's registration puts it on the content
REFERENCE_PARTITION = "default" if "default" in PARTITIONS else next(iter(PARTITIONS))


def deep_merge(base, over):
    out = copy.deepcopy(base)
    for k, v in over.items():
        out[k] = deep_merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def expand_experiments():
    """The named experiments plus every sweep's variants (named SWEEP-VARIANT); the experiments to run
    are ``run``, or the variants of the sweep given by --config sweep=NAME."""
    exps = {name: {"partition": "default", **e} for name, e in config.get("experiments", {"default": {}}).items()}
    sweeps = config.get("sweeps", {})
    variants = {}
    for sname, s in sweeps.items():
        if s["base"] not in exps:
            raise ValueError(f"config: sweeps.{sname}.base '{s['base']}' is not defined under 'experiments'")
        variants[sname] = [f"{sname}-{v}" for v in s["variants"]]
        for vname, over in s["variants"].items():
            exps[f"{sname}-{vname}"] = deep_merge(exps[s["base"]], over)
    sweep = config.get("sweep")
    if not sweep:
        return exps, list(config.get("run", list(exps)))
    if sweep not in sweeps:
        raise ValueError(f"config: sweep '{sweep}' is not defined under 'sweeps' (defined: {', '.join(sweeps) or 'none'})")
    return exps, variants[sweep]


EXPERIMENTS, RUN = expand_experiments()
for _e, _x in EXPERIMENTS.items():
    if _x["partition"] not in PARTITIONS:
        raise ValueError(f"config: experiments.{_e}.partition '{_x['partition']}' is not defined under 'partitions'")


def check_pairs(pairs, key):
    for pair in pairs:
        for name in pair:
            if name not in SCENES:
                raise ValueError(f"config: {key}: scene '{name}' is not defined under 'scenes'")


check_pairs(PAIRS, "pairs")
for _r in RUN:
    if _r not in EXPERIMENTS:
        raise ValueError(f"config: run: experiment '{_r}' is not defined under 'experiments'")

CONTENTS = sorted({c for c, _ in PAIRS})

# stages 7-9: Table 1's methods are experiments, the colour-transfer baseline or the unstylized input
BASELINES = ("colour_ot", "input")
EVALUATION = config.get("evaluation", {})
TABLE1 = config.get("table1", {})
TABLE1_PAIRS = [tuple(p) for p in TABLE1.get("pairs", PAIRS)]
if not TABLE1.get("methods"):  # config/config.yaml labels them; a config of its own must too
    raise ValueError("config: table1.methods is missing: a label for each method of Table 1 (see config/config.yaml)")
TABLE1_METHODS = TABLE1["methods"]
TABLE1_METHODS = {m: label for m, label in TABLE1_METHODS.items() if label is not None}
for _e in EXPERIMENTS:
    if _e in BASELINES:
        raise ValueError(f"config: experiment name '{_e}' is reserved for a baseline ({', '.join(BASELINES)})")
for _m in TABLE1_METHODS:
    if _m not in EXPERIMENTS and _m not in BASELINES:
        raise ValueError(f"config: table1.methods: '{_m}' is neither an experiment nor one of {', '.join(BASELINES)}")
check_pairs(TABLE1_PAIRS, "table1.pairs")
METHODS = list(EXPERIMENTS) + list(BASELINES)



def scenes_of(source):
    return [name for name, s in SCENES.items() if s["source"] == source]


def constraint(names):
    """A wildcard constraint matching exactly ``names`` (never matches when empty)."""
    return "|".join(names) if names else "(?!x)x"


wildcard_constraints:
    experiment=constraint(list(EXPERIMENTS)),
    method=constraint(METHODS),


def needs_surface(scene):
    s = SCENES[scene]
    return s["source"] not in ("procedural", "region") and s.get("surface", {}).get("enabled", True)


def scenes_needing_surface():
    return [c for c in SCENES if needs_surface(c)]


def content_points(scene):
    """The content Gaussians that k-means sees: the surface samples, or the scene itself."""
    return results("surface" if needs_surface(scene) else "scene", scene=scene)


STYLES = sorted({s for _, s in PAIRS + TABLE1_PAIRS})


def needs_style_clean(scene):
    """Trained and imported styles are cleaned (stage 2 for a style) unless style_clean.enabled is false;
    a style with labels_from always goes through the rule (its labels are attached there). Asked of a
    scene in a style's place, listed in `pairs` or not: a target of a pair outside `pairs` (a
    benchmark's, or one merged config's pair under another's `pairs`) gets the same cleaned style."""
    s = SCENES[scene]
    if s["source"] == "procedural":  # a generated patch is clean; a generated volume is laid out on a sheet there
        return bool(s.get("labels_from")) or s["name"] in _VOLUME.PROCEDURAL_VOLUMES
    return bool(s.get("labels_from")) or s.get("style_clean", {}).get("enabled", True)


def style_points(scene):
    """The style Gaussians that registration, selection and stylization see: cleaned, or the scene itself."""
    return results("style" if needs_style_clean(scene) else "scene", scene=scene)


def stage_json(params):
    """A stage's parameters as JSON for the rules' ``--params '{params.cfg}'``: each apostrophe closes the
    quotes, adds an escaped one and reopens them, so a path like "Bob's models" reaches the stage."""
    return json.dumps(params, separators=(",", ":"), sort_keys=True).replace("'", "'\\''")


def stage_params(command, block):
    """:func:`stage_json` of the parameters stage ``command`` runs with: its config block with every
    default of its dataclass filled in (wast3d/stages.py: resolved_params), so that a changed default
    re-runs the stage like a changed key does, and a bad block stops the workflow when it is built."""
    if _RESOLVE_DEFAULTS:
        try:
            return stage_json(_DECLARATIONS.resolved_params_cached(command, block, _PARAMS_CACHE, _FINGERPRINT))
        except ImportError as e:  # wast3d found, but not its dependencies (torch) in Snakemake's environment
            _no_defaults(e)
    return stage_json(block)


_DECLARATIONS = _load("stages.py")  # the stage declarations that go with these rules
STAGES = _DECLARATIONS.STAGES
if os.path.isdir(os.path.join(workflow.basedir, "wast3d")):  # a checkout: its own package, not another install's
    sys.path.insert(0, workflow.basedir)
# the stages' dataclasses give their defaults (wast3d/stages.py: resolved_params); they import torch, so
# resolved blocks are remembered per package fingerprint under .snakemake (dry runs and cluster jobs
# parse the workflow again)
_WAST3D_SPEC = importlib.util.find_spec("wast3d")
_RESOLVE_DEFAULTS = _WAST3D_SPEC is not None
_PARAMS_CACHE = os.path.abspath(os.path.join(".snakemake", "wast3d-params"))
_FINGERPRINT = (_DECLARATIONS.package_fingerprint(_WAST3D_SPEC.submodule_search_locations[0])
                if _RESOLVE_DEFAULTS else None)


def _no_defaults(why):
    global _RESOLVE_DEFAULTS
    _RESOLVE_DEFAULTS = False
    logger.warning(f"wast3d is not importable here ({why}): the rules pass the config blocks as written, so a "
                   "changed default of a stage will not re-run it")


if not _RESOLVE_DEFAULTS:
    _no_defaults("no module named 'wast3d'")


def results(name, **wildcards):
    """An artifact's path under RESULTS (wast3d/stages.py: PATHS); wildcards not given stay {wildcards}."""
    return _DECLARATIONS.artifact(name, RESULTS, **wildcards)


def pretrain_data(w):
    """The Blender-format folder a scene is pretrained from."""
    return SCENES[w.scene]["path"]


def pretrain_checkpoint(w):
    return f"{RESULTS}/scenes/{w.scene}/pretrain.ckpt"


def beside(name, suffix, **wildcards):
    """The file a stage writes beside artifact ``name``, with the same stem (``clusters.json``)."""
    return _DECLARATIONS.beside(name, suffix, RESULTS, **wildcards)


def stage_args(command, ignore=(), **paths):
    """A params function: the stage's files as its command's named options (``cluster --content PATH
    --out-npz PATH ...``, quoted), taken from the rule's input and output files of the same names
    (wast3d/stages.py), and from ``paths`` (name -> a function of the wildcards) for files the rule does
    not track. A rule file the stage does not declare (other than ``ignore``) is an error."""
    stage = STAGES[command]

    def args(wildcards, input, output):
        ins = {k: v for k, v in input.items() if k not in ignore}
        ins.update({k: f(wildcards) for k, f in paths.items()})
        try:
            return stage.command_line(ins, dict(output.items()))
        except ValueError as e:
            raise ValueError(f"the {command} stage's rule: {e}") from None

    return args


# scenes that no pair of the run or of Table 1 uses are defined but not built (a config merged over the
# demo's, like config/lego.yaml, keeps the demo's scenes in `scenes`)
USED_SCENES = [s for s in SCENES if any(s in p for p in PAIRS + TABLE1_PAIRS)
               or any(r["content"] == s for r in REGION_SETS.values())]
USED_SCENES += [src for s in USED_SCENES if (src := SCENES[s].get("labels_from")) and src not in USED_SCENES]

_CHECK.check_scene_paths(SCENES, USED_SCENES, _CONFIG_FILES, RESULTS)

# say what is left out, and why
for _name, _s in SCENES.items():
    if _name not in USED_SCENES:
        logger.info(f"scene '{_name}': left out entirely (in no pair)")
        continue
    if _s["source"] == "region":
        logger.info(f"scene '{_name}': region {_s['index']} of set '{_s['set']}', the points of '{_s['content']}' it "
                    "claims, cut from its surface samples and clusters (nothing upstream re-runs)")
        continue
    if _s["source"] == "procedural":
        logger.info(f"scene '{_name}': left out pretraining (generated as Gaussians)")
    elif _s["source"] == "ply":
        logger.info(f"scene '{_name}': left out pretraining (a trained 3DGS PLY is given)")
    if _name in CONTENTS and not needs_surface(_name):
        why = "a procedural scene is a clean surface" if _s["source"] == "procedural" else "surface.enabled is false"
        logger.info(f"scene '{_name}': left out surface sampling ({why})")
    if _name in STYLES and not needs_style_clean(_name):
        why = "a procedural scene is a clean surface" if _s["source"] == "procedural" else "style_clean.enabled is false"
        logger.info(f"scene '{_name}': left out style cleaning ({why})")
    if _s.get("labels_from") and _s["labels_from"] not in SCENES:
        raise ValueError(f"config: scenes.{_name}.labels_from: scene '{_s['labels_from']}' is not defined under 'scenes'")

# sizes no machine of this run can hold, before the first job (the memory only where jobs run here)
import psutil

_CHECK.check_sizes(SCENES, PARTITIONS, USED_SCENES, CONTENTS, _CONFIG_FILES,
                   psutil.virtual_memory().total if workflow.local_exec else None)


def up_from_cameras(folder):
    """The world axis nearest the mean up of a Blender folder's cameras (transforms_train.json: each
    camera-to-world's second column is its up), or None where the file is not there yet (a folder the
    workflow renders) or its cameras agree on no axis."""
    try:
        with open(os.path.join(folder, "transforms_train.json")) as f:
            frames = json.load(f)["frames"]
        up = [sum(float(fr["transform_matrix"][r][1]) for fr in frames) for r in range(3)]
    except (OSError, ValueError, KeyError, IndexError, TypeError):
        return None
    norm = sum(u * u for u in up) ** 0.5
    if norm < 0.5 * len(frames):  # the cameras look from all sides: no common up
        return None
    axis = max(range(3), key=lambda r: abs(up[r]))
    return ("-" if up[axis] < 0 else "") + "xyz"[axis]


def decide_up(name):
    """(the scene's up axis, why): scenes.NAME.up, or read from the scene (the schema's `up`)."""
    s = SCENES[name]
    if s["source"] == "region":
        up, why = decide_up(s["content"])
        return up, f"its content's: {why}"
    if s.get("up", "auto") != "auto":
        return s["up"], "set in the config"
    if s["source"] == "ply":
        return "-y", "a 3DGS file: the reference layout (graphdeco's trainer, SuperSplat) is y-down"
    if s["source"] == "images":
        up = up_from_cameras(s["path"])
        return (up, "its training cameras' mean up") if up else ("z", "Blender's convention (no camera file to read yet)")
    return "z", "generated z-up"


SCENE_UP = {name: decide_up(name) for name in USED_SCENES}
for _name, (_up, _why) in SCENE_UP.items():
    logger.info(f"scene '{_name}': up {_up} ({_why}); renders turn about it")


def scene_up(name):
    return SCENE_UP[name][0] if name in SCENE_UP else decide_up(name)[0]


def render_block(scene):
    """The render stages' parameters for renders fitted to ``scene``: the evaluation's render block and the
    scene's up (left out at z, the stages' own default, so that a z-up scene's renders keep their
    parameters)."""
    up = scene_up(scene)
    return {**EVALUATION.get("render", {}), **({"up": up} if up != "z" else {})}


def table_experiments(table):
    """'summary' lists the experiments run; a sweep's table lists its variants."""
    return RUN if table in ("summary", config.get("sweep")) else []


TABLE = config.get("sweep") or "summary"


def partition_of(w):
    return EXPERIMENTS[w.experiment]["partition"]


def summary_runs(experiments):
    return [f"{c}__{s}/{e}" for c, s in PAIRS for e in experiments]


def quoted(words):
    """Words as one shell-quoted string, for a params value spliced into a command."""
    return " ".join(shlex.quote(str(w)) for w in words)


def pretrain_params(scene):
    """A scene of kind style is regularized (eq. 1 and 2) unless its pretrain block says otherwise; the kind
    is the scene's, not its pairs', so one scene's cached pretraining does not depend on the config merged."""
    return {"regularize": SCENES[scene]["kind"] == "style", **SCENES[scene].get("pretrain", {})}


for _name, _s in SCENES.items():
    if _s["source"] == "images":
        _reg = pretrain_params(_name)["regularize"]
        logger.info(f"scene '{_name}': pretrained from images"
                    + (" with the anisotropy / uniform-scale regularizers" if _reg else " without regularizers")
                    + f" (kind: {_s['kind']})")


def method_ply(w):
    """The Gaussians a method produced for a pair (the input: the content points k-means saw)."""
    if w.method == "input":
        return content_points(w.content)
    return results("final", content=w.content, style=w.style, experiment=w.method)


def table1_rows():
    """CONTENT__STYLE/METHOD/PARTITION/LABEL per row of Table 1, shell-quoted."""
    return " ".join(shlex.quote(f"{c}__{s}/{m}/{EXPERIMENTS[m]['partition'] if m in EXPERIMENTS else '-'}/{label}")
                    for c, s in TABLE1_PAIRS for m, label in TABLE1_METHODS.items())


def clip_inputs():
    """The CLIP checkpoint (and model config) are inputs of evaluate when set, so a change re-runs it."""
    clip = EVALUATION.get("clip", {})
    return [p for p in (clip.get("checkpoint"), clip.get("model_config")) if p]


SHEET_METHODS = [m for m in TABLE1_METHODS if m != "input"]  # the comparison sheet's and turntable page's methods
# the first sheet's: the method, the collage (its elements before the flow) and the colour-transfer baseline
SHEET_MAIN = [m for m in ("default", "selected", "colour_ot") if m in SHEET_METHODS]


# The first result comes first: the jobs on the way to the first Table 1 pair's result and its comparison
# sheet (the method, the collage, colour transfer and the content's renders) run before everything else,
# Table 1's evaluations and the other pairs after (the scheduler runs the ready job of highest priority).
FIRST_PAIR = (TABLE1_PAIRS or PAIRS or [(None, None)])[0]
FIRST_METHODS = set(SHEET_MAIN) | {"input"}
FIRST_PARTITIONS = {EXPERIMENTS[m]["partition"] for m in SHEET_MAIN if m in EXPERIMENTS}


def first_result(w):
    """A job's priority: 10 on the way to the first pair's result and sheet, else 0."""
    d = dict(w.items())
    content, style = FIRST_PAIR
    if "scene" in d:
        return 10 if d["scene"] in FIRST_PAIR else 0
    if d.get("content", content) != content or d.get("style", style) != style:
        return 0
    if d.get("partition") not in (None, *FIRST_PARTITIONS):
        return 0
    return 10 if all(d.get(k) in (None, *FIRST_METHODS) for k in ("experiment", "method")) else 0


def sheet_method_renders(w, methods=None):
    """The render folders of SHEET_METHODS (those of ``methods``, when given) for one pair (the `methods`
    input of the sheets' rules)."""
    return [results("render_pair", content=w.content, style=w.style, method=m) for m in SHEET_METHODS
            if methods is None or m in methods]


def sheet_columns(input, reference=True, methods=None):
    """LABEL=FOLDER arguments of `wast3d compare` / `wast3d turntables`: content, style, (the style at
    the result's scale), then Table 1's methods (those of ``methods`` only, as sheet_method_renders
    listed them)."""
    head = [("content", input.content), ("style", input.style)]
    head += [("style at the result's scale", input.reference)] if reference else []
    shown = [m for m in SHEET_METHODS if methods is None or m in methods]
    return " ".join(shlex.quote(f"{label}={path}") for label, path in
                    head + [(TABLE1_METHODS[m], p) for m, p in zip(shown, input.methods)])

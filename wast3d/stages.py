"""Every stage of the workflow, declared once: its command, its files by name, its config dataclass
and the :mod:`wast3d.pipeline` function that runs it.

From these declarations come the ``wast3d <command>`` subcommands (one named option per file:
``--content PATH`` for an input, ``--out-npz PATH`` for an output), the Snakemake rules' command lines
(``stage_args`` in ``workflow/rules/common.smk``: a rule's input and output files of the same names)
and ``docs/stages.md``. A file the rule names but the stage does not declare, or
a required one it lacks, is an error when the workflow is built, not a silently swapped argument.

Conventions: a port's name is the rule's input or output key and the pipeline function's keyword
(``out_<name>`` for an output); the function takes ``params`` (the stage's config block as a dict,
checked by the dataclass) and, when the stage has a progress bar, ``progress``. Files a stage writes
beside a declared output (``clusters.json`` beside ``clusters.npz``, same stem) are declared with
``beside``: they have no option, and a rule that names them must name them there.
Plain declarations only: this module imports nothing heavy.
"""

from __future__ import annotations

import copy
import shlex
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping


@dataclass(frozen=True)
class Port:
    """One file (or folder) a stage reads or writes."""

    name: str
    help: str
    output: bool = False
    required: bool = True
    beside: str | None = None  # written next to this output, same stem (no option of its own)

    @property
    def keyword(self) -> str:
        """The pipeline function's keyword for this file."""
        return f"out_{self.name}" if self.output else self.name

    @property
    def option(self) -> str:
        """The command-line option for this file."""
        return "--" + self.keyword.replace("_", "-")


def In(name: str, help: str, required: bool = True) -> Port:  # noqa: N802 - reads as a declaration
    return Port(name, help, False, required)


def Out(name: str, help: str, required: bool = True, beside: str | None = None) -> Port:  # noqa: N802
    return Port(name, help, True, required and beside is None, beside)


@dataclass(frozen=True)
class Stage:
    """A stage: ``command`` (``wast3d <command>``), ``run`` (the function in :mod:`wast3d.pipeline`),
    ``ports`` (its files), ``config`` (``module:Class`` of the dataclass that checks its parameters, or
    one per block where they are several, as evaluate's), ``block`` (their place in the workflow's
    config), ``progress`` (it takes ``--no-progress``), ``passthrough`` (keys outside the dataclass),
    ``by_form`` (``module:NAME`` of the values its options left null take by the style's form)."""

    command: str
    help: str
    run: str
    ports: tuple[Port, ...]
    config: str | dict[str, str] | None = None  # a dict: a stage with several blocks, by name
    block: str | None = None  # where its parameters sit in the workflow's config (``*``: any name)
    progress: bool = False
    passthrough: tuple[str, ...] = ()  # parameter keys the pipeline function takes itself, not the dataclass
    # the values its null options take by the style's form: resolved_params adds them (key ``by_form``), so
    # that a change of them in the code re-runs the stage as a changed default does
    by_form: str | None = None

    def __post_init__(self):
        names = [p.name for p in self.ports]
        if len(set(names)) != len(names):
            raise ValueError(f"stage {self.command}: a port name is used twice ({', '.join(names)})")
        for p in self.ports:
            if p.beside is not None and p.beside not in [q.name for q in self.outputs if q.beside is None]:
                raise ValueError(f"stage {self.command}: '{p.name}' is beside '{p.beside}', which is not an output")

    @property
    def inputs(self) -> tuple[Port, ...]:
        return tuple(p for p in self.ports if not p.output)

    @property
    def outputs(self) -> tuple[Port, ...]:
        return tuple(p for p in self.ports if p.output)

    def argv(self, inputs: Mapping[str, object], outputs: Mapping[str, object]) -> list[str]:
        """The command's options for the files given by port name (``inputs`` and ``outputs``; None or
        an empty list: not given), in declaration order -> ``[command, --opt, path, ...]``. Raises
        ValueError naming an unknown file or a missing required one."""
        given = {}
        for kind, files in (("input", inputs), ("output", outputs)):
            for name, value in files.items():
                if isinstance(value, (list, tuple)):
                    if len(value) > 1:
                        raise ValueError(f"stage {self.command}: {kind} '{name}' is {len(value)} files, not one")
                    value = value[0] if value else None
                if value is None:
                    continue
                p = next((q for q in self.ports if q.name == name), None)
                if p is None or p.output != (kind == "output"):
                    known = ", ".join(q.name for q in (self.outputs if kind == "output" else self.inputs))
                    raise ValueError(f"stage {self.command}: no {kind} named '{name}' (its {kind}s: {known})")
                given[name] = value
        missing = [p.name for p in self.ports if p.required and p.name not in given]
        if missing:
            raise ValueError(f"stage {self.command}: required file(s) {', '.join(missing)} not given")
        out = [self.command]
        for p in self.ports:
            if p.name not in given:
                continue
            if p.beside is None:
                out += [p.option, str(given[p.name])]
                continue
            path, main = Path(str(given[p.name])), Path(str(given.get(p.beside, "")))
            if path != main.with_suffix(path.suffix):
                raise ValueError(f"stage {self.command}: '{p.name}' ({path}) is written beside '{p.beside}' "
                                 f"({main}), as {main.with_suffix(path.suffix)}")
        return out

    def command_line(self, inputs: Mapping[str, object], outputs: Mapping[str, object]) -> str:
        """:meth:`argv` as one shell-quoted string."""
        return " ".join(shlex.quote(a) for a in self.argv(inputs, outputs))


_CONTENT = In("content", "content points: the surface samples, or the content scene (PLY)")
_STYLE = In("style", "style scene, cleaned (PLY)")
_CLUSTERS = In("clusters", "k-means labels of the content points (NPZ, stage 3)")
_REGISTRATION = In("registration", "per-cluster similarity transforms (NPZ, stage 4a)")

STAGES: dict[str, Stage] = {s.command: s for s in (
    Stage("pretrain", "stage 1: regularized 3DGS pretraining from a Blender-format folder", "run_pretrain", (
        In("data", "folder with transforms_train.json and its images"),
        In("checkpoint", "checkpoint file: resumed from when it exists, written every checkpoint_every steps",
           required=False),
        In("init", "initial point cloud or 3DGS PLY (default: init_points random points in a cube around the "
                   "cameras' target)", required=False),
        Out("ply", "the trained scene (PLY)"),
        Out("csv", "training log, one row per logged step (CSV)"),
        Out("json", "held-out evaluation: PSNR, SSIM, time, Gaussians (JSON)"),
    ), "wast3d.pretrain:PretrainConfig", "scenes.*.pretrain", progress=True,
        passthrough=("holdout_every", "background", "max_views")),
    Stage("surface", "stage 2: sample the content's surface (or pass it through when disabled)", "run_surface", (
        In("scene", "trained content scene (PLY)"),
        Out("ply", "surface samples with colour and normal (PLY)"),
        Out("json", "what was sampled, kept and dropped (JSON)"),
    ), "wast3d.surface:SurfaceConfig", "scenes.*.surface"),
    Stage("style-clean", "stage 2 for a style: drop floaters outside the patch, haze and hidden Gaussians",
          "run_style_clean", (
              In("scene", "trained style scene (PLY)"),
              In("labels_from", "labelled PLY the style was rendered from (each Gaussian takes its nearest "
                                "source's element label)", required=False),
              Out("ply", "cleaned style (PLY)"),
              Out("json", "what was dropped and why (JSON)"),
          ), "wast3d.surface:StyleCleanConfig", "scenes.*.style_clean"),
    Stage("cluster", "stage 3: k-means of the content on position and colour", "run_cluster", (
        _CONTENT,
        Out("npz", "labels, centroids, sizes, outward normals (NPZ)"),
        Out("json", "clusters' count and sizes (JSON)", beside="npz"),
        Out("picture", "the clusters in colour (PNG)", required=False),
    ), "wast3d.clustering:ClusterConfig", "partitions.*.cluster"),
    Stage("register", "stage 4a: per-cluster registration to the style scene (eq. 7)", "run_register", (
        _CONTENT, _CLUSTERS, _STYLE,
        In("region", "a region's content: its JSON, with the whole content's diameter its elements are sized by",
           required=False),
        In("style_form", "the style stage's report (JSON, style-clean): on a volume's element sheet the element "
                         "scale follows the content by default (follow_thickness)", required=False),
        Out("npz", "rotation, scale, translation and residual per cluster (NPZ)"),
        Out("json", "residuals before and after, base scale, style spacing (JSON)", beside="npz"),
        Out("picture", "six clusters over their style neighbourhoods (PNG)", required=False),
    ), "wast3d.registration:RegistrationConfig", "partitions.*.register", by_form="wast3d.registration:FORM_DEFAULTS"),
    Stage("select", "stage 4b: style Gaussians of each cluster (eq. 8, or the footprint)", "run_select", (
        _CONTENT, _CLUSTERS, _STYLE, _REGISTRATION,
        Out("npz", "style indices per cluster as offsets + indices (NPZ)"),
        Out("json", "selection sizes and thinning (JSON)", beside="npz"),
    ), "wast3d.selection:SelectConfig", "partitions.*.select"),
    Stage("stylize", "stage 5: minimize the Sinkhorn divergence per cluster (eq. 9)", "run_stylize", (
        _CONTENT, _CLUSTERS, _STYLE, _REGISTRATION,
        In("selection", "style indices per cluster (NPZ, stage 4b)"),
        In("style_form", "the style stage's report (JSON, style-clean): a volume's element sheet flows element by "
                         "element", required=False),
        Out("ply", "the stylized scene before scale readjustment (PLY)"),
        Out("npz", "each Gaussian's cluster, its position before the flow and the style Gaussian it is a copy of (NPZ)"),
        Out("csv", "loss per cluster and step (CSV)"),
        Out("json", "time, device, losses first and last, the config (JSON)", beside="csv"),
        Out("png", "the loss curves (PNG)", beside="csv"),
    ), "wast3d.stylize:StylizeConfig", "experiments.*.stylize", progress=True, by_form="wast3d.stylize:SHEET_COPIES"),
    Stage("rescale", "stage 6: readjust scales from the change of mean nearest-neighbour distance", "run_rescale", (
        In("stylized", "the stylized scene (PLY, stage 5)"),
        In("stylize_npz", "its clusters and positions before the flow (NPZ, stage 5)"),
        Out("ply", "the result (PLY)"),
        Out("json", "the scale ratios' quantiles (JSON)", beside="ply"),
    ), "wast3d.rescale:RescaleConfig", "experiments.*.rescale"),
    Stage("render", "stage 7: turntable (PNG frames + GIF), key views and close-up with depth and normals",
          "run_render", (
              In("scene", "scene to render (PLY)"),
              In("reference", "scene the cameras are fitted to (PLY; the content, so that every method is seen alike)"),
              Out("folder", "render folder"),
          ), "wast3d.render:RenderConfig", "evaluation.render", progress=True, passthrough=("up",)),
    Stage("texture-reference", "stage 7: the style rendered at the pixel scale its elements have on the content's "
          "renders (the reference of texture_swd)", "run_texture_reference", (
              _STYLE, In("content", "content scene the renders are fitted to (PLY)"),
              In("registration", "its base scale s0 sets the elements' size (NPZ)", required=False),
              In("style_form", "the style stage's report (JSON, style-clean): a volume's sheet is segmented by its "
                               "laid-out elements", required=False),
              Out("folder", "render folder; with a registration, segments.npz: the style's label-free elements"),
          ), "wast3d.render:RenderConfig", "evaluation.render", progress=True, passthrough=("up",)),
    Stage("colour-transfer", "baseline: content geometry, colours mapped to the style's by entropic OT",
          "run_colour_transfer", (
              In("content", "content scene (PLY)"), _STYLE,
              Out("ply", "the recoloured content (PLY)"),
              Out("json", "time, device, config (JSON)", beside="ply"),
          ), "wast3d.baselines:ColourTransferConfig", "evaluation.colour_transfer"),
    Stage("regions", "stage 3b: each content point's region of a set of (style, region) (wast3d/regions.py)",
          "run_regions", (
              _CONTENT,
              In("scene", "the content scene a labels region's file numbers (PLY)", required=False),
              Out("npz", "the region of each content point, and the regions' styles (NPZ)"),
              Out("json", "each region's kind, settings and points (JSON)", beside="npz"),
              Out("picture", "the content points in their regions' colours (PNG)", required=False),
          )),
    Stage("region-content", "stage 3b: the content points of one region (params: index)", "run_region_content", (
        _CONTENT, In("regions", "each content point's region (NPZ)"),
        Out("ply", "the region's content points (PLY)"),
        Out("json", "the region, its points and the whole content's diameter, which its elements are sized by "
                    "(JSON)", beside="ply"),
    )),
    Stage("region-clusters", "stage 3b: the content's clusters cut by one region's border (params: index)",
          "run_region_clusters", (
              _CLUSTERS, In("regions", "each content point's region (NPZ)"),
              Out("npz", "the region's points' cluster labels (and normals) (NPZ)"),
              Out("json", "points, clusters, clusters the border cut (JSON)", beside="npz"),
          )),
    Stage("seams", "stage 8: where the styles of a result by regions meet: coverage and density along the seams",
          "run_seams", (
              _CONTENT, In("regions", "each content point's region (NPZ)"),
              In("result", "the merged result (PLY, final.json beside it)"),
              In("result_render", "the merged result's render folder"),
              In("content_render", "the content's render folder, the same cameras"),
              Out("json", "the seam metrics (JSON)"),
          )),
    Stage("evaluate", "stage 8: weights-free metrics and CLIP crop similarity of one result", "run_evaluate", (
        In("result", "the result scene (PLY)"),
        In("content", "content scene (PLY)"),
        _STYLE,
        In("result_render", "the result's render folder (stage 7)"),
        In("style_render", "the style's render folder"),
        In("texture_reference", "the texture reference's render folder"),
        In("content_render", "the unstylized content's render folder, with the result's cameras"),
        In("stylize_npz", "the result's clusters (NPZ, stage 5): element metrics per copy", required=False),
        Out("json", "every metric (JSON)"),
    ), {"metrics": "wast3d.metrics:MetricsConfig", "texture": "wast3d.image_metrics:TextureConfig",
        "crops": "wast3d.clip_eval:CropConfig", "clip": "wast3d.clip_eval:ClipConfig",
        "elements": "wast3d.elements:ElementConfig"}, "evaluation"),
)}


def import_spec(spec: str):
    """The object named by ``module:NAME``: a stage's config dataclass or its form dict (:attr:`Stage.by_form`),
    imported on demand (the stages' modules import torch)."""
    import importlib

    module, name = spec.split(":")
    return getattr(importlib.import_module(module), name)


def run_params(params: dict) -> dict:
    """A stage's parameters as its pipeline function takes them: less ``by_form`` (:attr:`Stage.by_form`,
    there only so that the rules re-run the stage when the code's form values change)."""
    return {k: v for k, v in params.items() if k != "by_form"}


def stage_configs(command: str, params: dict | None) -> dict:
    """The configs stage ``command`` runs with, built from ``params`` by its dataclass(es) (an unknown
    key or block, or a bad value, is a ValueError naming it): ``{None: config}`` for a stage of one
    block, ``{block: config}`` for one of several (evaluate). Keys in ``passthrough`` are left out."""
    from wast3d.options import make_config  # absolute: the workflow loads this module by path

    st = STAGES[command]
    params = {k: v for k, v in run_params(params or {}).items() if k not in st.passthrough}
    if not isinstance(st.config, dict):
        return {None: make_config(import_spec(st.config), params, command)}
    unknown = sorted(set(params) - set(st.config))
    if unknown:
        raise ValueError(f"{command}: unknown parameter block(s) {', '.join(unknown)} (known: {', '.join(st.config)})")
    return {k: make_config(import_spec(spec), params.get(k), f"{command}.{k}") for k, spec in st.config.items()}


def resolved_params(command: str, params: dict | None) -> dict:
    """The parameters stage ``command`` runs with: ``params`` with every default of its config
    dataclass(es) filled in (:func:`stage_configs`). The rules pass these, so that a changed default
    changes a stage's parameters and Snakemake re-runs it (and what depends on it) instead of keeping
    a result made under the old default; with them, under ``by_form``, the values its null options take
    by the style's form (:attr:`Stage.by_form`)."""
    import dataclasses
    import json

    params = dict(params or {})
    if STAGES[command].config is None:
        return params
    out = {k: params[k] for k in STAGES[command].passthrough if k in params}
    for key, cfg in stage_configs(command, params).items():
        if key is None:
            out.update(dataclasses.asdict(cfg))
        else:
            out[key] = dataclasses.asdict(cfg)
    if STAGES[command].by_form:
        out["by_form"] = json.loads(json.dumps(import_spec(STAGES[command].by_form)))  # tuples as lists
    return out


def package_fingerprint(package_dir: str | Path) -> str:
    """A digest of every ``.py`` file under ``package_dir`` (relative path and bytes). The stages'
    defaults live in their dataclasses and the constants beside them, so any edit of the package gives
    a new fingerprint."""
    import hashlib

    root = Path(package_dir)
    h = hashlib.sha256()
    for p in sorted(root.rglob("*.py")):
        h.update(p.relative_to(root).as_posix().encode() + b"\0" + p.read_bytes() + b"\0")
    return h.hexdigest()[:16]


def resolved_params_cached(command: str, params: dict | None, cache_dir: str | Path, fingerprint: str) -> dict:
    """:func:`resolved_params`, remembered in ``cache_dir``: one JSON file per command, parameter block
    and package fingerprint (:func:`package_fingerprint`). Snakemake parses the workflow again for every
    dry run and inside every cluster job, and resolving imports the stages' modules and torch with them
    (about 2.5 s); a remembered block imports nothing. A block the dataclass rejects is never stored, so
    it fails on every parse. Written through ``io_utils.atomic_path`` (jobs may parse at once)."""
    import hashlib
    import json

    key = hashlib.sha256(json.dumps([fingerprint, command, params], sort_keys=True).encode()).hexdigest()[:24]
    path = Path(cache_dir) / f"{command}-{key}.json"
    if path not in _RESOLVED:
        try:
            _RESOLVED[path] = json.loads(path.read_text())
        except (OSError, ValueError):
            from wast3d.io_utils import atomic_path  # absolute: the workflow loads this module by path

            _RESOLVED[path] = json.loads(json.dumps(resolved_params(command, params)))
            try:
                with atomic_path(path) as tmp:
                    tmp.write_text(json.dumps(_RESOLVED[path], sort_keys=True))
            except OSError:  # a read-only working folder: resolve on every parse, as without the cache
                pass
    return copy.deepcopy(_RESOLVED[path])  # the caller may change its copy


_RESOLVED: dict[Path, dict] = {}  # resolved_params_cached's blocks already read or resolved in this process


# ---- artifact paths ---------------------------------------------------------------------------------

# Where the workflow keeps each artifact, relative to its results folder, with Snakemake's wildcards:
# the rules' inputs and outputs, the tables, `wast3d run` and the benchmarks all read them from here.
PATHS: dict[str, str] = {
    "scene": "scenes/{scene}/scene.ply",
    "surface": "scenes/{scene}/surface.ply",
    "style": "scenes/{scene}/style.ply",
    "clusters": "partition/{content}/{partition}/clusters.npz",
    "registration": "register/{content}__{style}/{partition}/registration.npz",
    "selection": "register/{content}__{style}/{partition}/selection.npz",
    "stylized": "stylize/{content}__{style}/{experiment}/stylized.ply",
    "stylize_npz": "stylize/{content}__{style}/{experiment}/stylize.npz",
    "losses": "stylize/{content}__{style}/{experiment}/losses.csv",
    "final": "stylize/{content}__{style}/{experiment}/final.ply",
    "render_pair": "render/pairs/{content}__{style}/{method}",
    "render_scene": "render/scenes/{scene}",
    "texture_reference": "render/texture_reference/{content}__{style}",
    "eval": "eval/{content}__{style}/{method}.json",
    "rule_benchmark": "benchmarks/rules/{rule}_{job}.tsv",
}


class _Keep(dict):
    def __missing__(self, key):
        return "{" + key + "}"


def artifact(name: str, results: str | Path | None = None, **wildcards) -> str:
    """The path of artifact ``name`` (:data:`PATHS`) with the given wildcards filled in (the others stay
    ``{wildcard}``, for a rule), under ``results`` when given. A method's files sit where an
    experiment's do (``method`` fills ``experiment`` too)."""
    if "method" in wildcards:
        wildcards.setdefault("experiment", wildcards["method"])
    path = PATHS[name].format_map(_Keep(**{k: str(v) for k, v in wildcards.items()}))
    return path if results is None else str(Path(results) / path)


def beside(name: str, suffix: str, results: str | Path | None = None, **wildcards) -> str:
    """The file a stage writes beside artifact ``name``, with the same stem and ``suffix``
    (``clusters.json`` beside ``clusters.npz``)."""
    return str(Path(artifact(name, results, **wildcards)).with_suffix(suffix))

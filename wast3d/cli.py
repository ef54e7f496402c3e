"""The ``wast3d`` command: one subcommand per stage; every Snakemake rule calls one of these.

Each subcommand reads its inputs, calls the library's pure functions and writes its outputs
atomically. Errors in inputs are reported as one line naming the file and the field (exit code 2;
with ``-v`` their traceback as well); any other error is a fault and shows its traceback.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

log = logging.getLogger("wast3d")

COMMANDS: dict[str, tuple] = {}


def command(name: str, help: str):
    def deco(fn):
        COMMANDS[name] = (fn, help)
        return fn

    return deco


# ---- info ------------------------------------------------------------------------------------


def scene_summary(scene) -> dict:
    """What a user inspecting a scene wants to see: counts, bounds, quantiles of scale, anisotropy,
    opacity. Pure: takes a scene, returns a dict."""
    import torch

    from .gaussians import anisotropy

    qs = [0.0, 0.05, 0.5, 0.95, 1.0]
    q = lambda t: {f"q{int(p * 100):02d}": float(torch.quantile(t.double(), p)) for p in qs} if len(t) else {}  # noqa: E731
    m = scene.means
    return {
        "count": len(scene),
        "sh_degree": scene.sh_degree,
        "bounds_min": m.min(0).values.tolist() if len(m) else None,
        "bounds_max": m.max(0).values.tolist() if len(m) else None,
        "scale_max_axis": q(scene.scales.max(1).values),
        "scale_min_axis": q(scene.scales.min(1).values),
        "anisotropy": q(anisotropy(scene.scales)),
        "opacity": q(scene.opacities),
    }


@command("info", "summarize a 3DGS or point-cloud PLY")
def cmd_info(sub):
    sub.add_argument("ply", type=Path)
    sub.add_argument("--json", action="store_true", help="print JSON")

    def run(a):
        from .formats import read_scene
        from .ply import PlyError

        try:
            info = {"file": str(a.ply), "valid": True, **scene_summary(read_scene(a.ply))}
        except (PlyError, FileNotFoundError, ValueError) as e:
            info = {"file": str(a.ply), "valid": False, "error": str(e)}
        if a.json:
            print(json.dumps(info, indent=2))
        else:
            for k, v in info.items():
                if isinstance(v, dict):
                    v = "  ".join(f"{kk}={vv:.4g}" for kk, vv in v.items())
                elif isinstance(v, list):
                    v = "[" + ", ".join(f"{x:.4g}" for x in v) + "]"
                print(f"{k:16s} {v}")
        return 0 if info["valid"] else 1

    return run


@command("view", "serve an interactive 3D view of PLY scenes in the browser (viser)")
def cmd_view(sub):
    sub.add_argument("ply", type=Path, nargs="+", help="scenes, e.g. content, style and result (a dropdown switches)")
    sub.add_argument("--host", default="127.0.0.1", help="0.0.0.0 to reach it from other machines")
    sub.add_argument("--port", type=int, default=8080)
    sub.add_argument("--max-gaussians", type=int, default=300_000, help="per scene, most opaque kept")

    def run(a):
        try:
            from .viewer import run_forever, serve
        except ImportError as e:  # pragma: no cover - depends on the install
            raise ValueError(f"wast3d view needs viser ({e}); pip install 'wast3d[viewer]'") from None
        server = serve(a.ply, a.host, a.port, a.max_gaussians)
        log.info("view: open http://%s:%d (Ctrl-C stops)", "localhost" if a.host in ("0.0.0.0", "127.0.0.1") else a.host,
                 server.get_port())
        run_forever(server)
        return 0

    return run


@command("run", "stylize CONTENT with STYLE through the workflow: writes OUT/config/config.yaml and runs Snakemake in OUT")
def cmd_run(sub):
    sub.add_argument("content", type=Path, help="PLY (reference, compressed or point cloud) or Blender folder")
    sub.add_argument("style", type=Path, help="PLY or Blender folder")
    sub.add_argument("out", type=Path, help="working folder: config/ and results/ go here (re-runs reuse its cache)")
    sub.add_argument("--profile", default=None, help="Snakemake profile (default: the workflow's profiles/local)")
    sub.add_argument("-n", "--dry-run", action="store_true", help="only show what would run")
    sub.add_argument("snakemake_args", nargs="*", help="more Snakemake arguments, after --")

    def run(a):
        import subprocess

        import yaml

        from .io_utils import atomic_path
        from .quickstart import two_scene_config, workflow_root

        root = workflow_root()
        base = yaml.safe_load((root / "config" / "config.yaml").read_text())
        cfg = two_scene_config(base, a.content, a.style)
        cfg_path = a.out / "config" / "config.yaml"
        cfg_path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(cfg_path) as tmp:
            Path(tmp).write_text("# written by `wast3d run`; edit and re-run Snakemake in this folder\n"
                                 + yaml.safe_dump(cfg, sort_keys=False))
        (c, s), = cfg["pairs"]
        log.info("run: %s x %s: config in %s", c, s, cfg_path)
        cmd = [sys.executable, "-m", "snakemake", "-s", str(root / "Snakefile"), "-d", str(a.out),
               "--profile", a.profile or str(root / "workflow" / "profiles" / "local"),
               *(["-n"] if a.dry_run else []), *a.snakemake_args]
        log.info("run: %s", " ".join(cmd))
        rc = subprocess.run(cmd).returncode
        if rc == 0 and not a.dry_run:
            res = a.out / "results"
            final = res / "stylize" / f"{c}__{s}" / "default" / "final.ply"
            log.info("run: done. Result: %s; renders: %s; Table 1: %s; view: wast3d view %s %s %s", final,
                     res / "render" / "pairs" / f"{c}__{s}", res / "tables" / "table1.md", a.content, a.style, final)
        return rc

    return run


# ---- scenes ----------------------------------------------------------------------------------


@command("scene", "generate a procedural style or content scene as a 3DGS PLY")
def cmd_scene(sub):
    sub.add_argument("kind", choices=["style", "content"])
    sub.add_argument("name")
    sub.add_argument("out", type=Path)
    sub.add_argument("--n", type=int, default=30000, help="number of Gaussians (approximate)")
    sub.add_argument("--seed", type=int, default=0)

    def run(a):
        from .ply import write_ply
        from .procedural import make_scene

        scene = make_scene(a.kind, a.name, a.n, a.seed)
        write_ply(a.out, scene)
        log.info("wrote %s: %d Gaussians (%s '%s', seed %d)", a.out, len(scene), a.kind, a.name, a.seed)
        return 0

    return run


@command("import-ply", "validate a trained 3DGS scene (.ply, compressed .ply, point cloud, .spz, .splat) and write it "
                       "as a PLY in the canonical layout")
def cmd_import(sub):
    sub.add_argument("ply", type=Path)
    sub.add_argument("out", type=Path)
    sub.add_argument("--drop-invalid", action="store_true", help="drop Gaussians with NaN/inf instead of failing")

    def run(a):
        from .formats import read_scene
        from .ply import write_ply

        scene = read_scene(a.ply, drop_invalid=a.drop_invalid)
        write_ply(a.out, scene)
        log.info("imported %s -> %s: %d Gaussians, SH degree %d", a.ply, a.out, len(scene), scene.sh_degree)
        return 0

    return run


@command("export", "convert a scene between formats, by the extensions of IN and OUT (.ply, .compressed.ply, .spz, .splat)")
def cmd_export(sub):
    sub.add_argument("src", type=Path, metavar="IN")
    sub.add_argument("out", type=Path, metavar="OUT")

    def run(a):
        from .formats import read_scene, write_scene

        scene = read_scene(a.src)
        write_scene(a.out, scene)
        log.info("exported %s -> %s: %d Gaussians", a.src, a.out, len(scene))
        return 0

    return run


def render_command(name: str, help_: str, fn: str, views: int, size: int, out_help: str):
    """A command that renders a PLY from orbit cameras with ``render.<fn>(scene, out, views, size)``."""

    @command(name, help_)
    def cmd(sub):
        sub.add_argument("ply", type=Path)
        sub.add_argument("out", type=Path, help=out_help)
        sub.add_argument("--views", type=int, default=views)
        sub.add_argument("--size", type=int, default=size)

        def run(a):
            from . import render
            from .formats import read_scene

            getattr(render, fn)(read_scene(a.ply), a.out, a.views, a.size)
            return 0

        return run

    return cmd


render_command("preview", "render a 1 x N grid of orbit views of a PLY", "save_preview", 4, 256, "PNG file")
render_command("export-views", "render a PLY into a Blender-format posed image set (orbit cameras)",
               "export_blender", 48, 200, "output folder (transforms_train.json + train/*.png)")


# ---- the stylization stages -----------------------------------------------------------------


def _params(sub):
    sub.add_argument("--params", default="{}", help="stage parameters as a JSON object")


def _load_params(text: str) -> dict:
    try:
        p = json.loads(text)
    except json.JSONDecodeError as e:
        raise ValueError(f"--params is not valid JSON ({e})") from None
    if not isinstance(p, dict):
        raise ValueError("--params must be a JSON object")
    return p


@command("pretrain", "stage 1: regularized 3DGS pretraining from a Blender-format folder")
def cmd_pretrain(sub):
    sub.add_argument("data", type=Path, help="folder with transforms_train.json")
    sub.add_argument("out_ply", type=Path)
    sub.add_argument("out_csv", type=Path, help="training log")
    sub.add_argument("out_json", type=Path, help="held-out evaluation")
    sub.add_argument("--checkpoint", type=Path, help="checkpoint file: resumed from when it exists")
    sub.add_argument("--init", type=Path, help="initial point cloud or 3DGS PLY")
    sub.add_argument("--no-progress", action="store_true")
    _params(sub)

    def run(a):
        from .pipeline import run_pretrain

        run_pretrain(a.data, a.out_ply, a.out_csv, a.out_json, _load_params(a.params), a.checkpoint, a.init,
                     progress=not a.no_progress)

    return run


def stage_command(name: str, help_: str, positionals: tuple[str, ...], fn: str, picture=False, progress=False,
                  options: tuple[str, ...] = ()):
    """A ``wast3d <stage>`` command calling ``pipeline.<fn>(*positionals, [picture,] params[, progress],
    **options)``; ``options`` are optional paths (``--stylize-npz PATH`` for ``stylize_npz``)."""

    @command(name, help_)
    def cmd(sub):
        for n in positionals:
            sub.add_argument(n, type=Path)
        for n in options:
            sub.add_argument("--" + n.replace("_", "-"), dest=n, type=Path)
        if picture:
            sub.add_argument("--picture", type=Path)
        if progress:
            sub.add_argument("--no-progress", action="store_true")
        _params(sub)

        def run(a):
            from . import pipeline

            args = [getattr(a, n) for n in positionals] + ([a.picture] if picture else [])
            kw = {"progress": not a.no_progress} if progress else {}
            kw.update({n: getattr(a, n) for n in options})
            getattr(pipeline, fn)(*args, _load_params(a.params), **kw)

        return run

    return cmd


stage_command("surface", "stage 2: sample the content's surface (or pass it through when disabled)",
              ("scene", "out_ply", "out_json"), "run_surface")
@command("style-clean", "stage 2 for a style: drop floaters outside the patch, haze and hidden Gaussians")
def cmd_style_clean(sub):
    sub.add_argument("scene", type=Path)
    sub.add_argument("out_ply", type=Path)
    sub.add_argument("out_json", type=Path)
    sub.add_argument("--labels-from", type=Path, help="labelled PLY the style was rendered from (element labels)")
    _params(sub)

    def run(a):
        from .pipeline import run_style_clean

        run_style_clean(a.scene, a.out_ply, a.out_json, _load_params(a.params), a.labels_from)

    return run


stage_command("cluster", "stage 3: k-means of the content on position and colour", ("content", "out_npz"),
              "run_cluster", picture=True)
stage_command("register", "stage 4a: per-cluster registration to the style scene (eq. 7)",
              ("content", "clusters", "style", "out_npz"), "run_register", picture=True)
stage_command("select", "stage 4b: style Gaussians of each cluster by kNN (eq. 8)",
              ("content", "clusters", "style", "registration", "out_npz"), "run_select")
stage_command("stylize", "stage 5: minimize the Sinkhorn divergence per cluster (eq. 9)",
              ("content", "clusters", "style", "registration", "selection", "out_ply", "out_npz", "out_csv"),
              "run_stylize", progress=True)
stage_command("rescale", "stage 6: readjust scales from the change of mean nearest-neighbour distance",
              ("stylized", "stylize_npz", "out_ply"), "run_rescale")


stage_command("render", "stage 7: turntable (PNG frames + GIF), key views and close-up with depth and normals",
              ("scene", "reference", "out_dir"), "run_render", progress=True)
stage_command("texture-reference", "stage 7: the style rendered at the pixel scale its elements have on the content's "
              "renders (the reference of texture_swd)", ("style", "content", "out_dir"), "run_texture_reference",
              progress=True, options=("registration",))
stage_command("colour-transfer", "baseline: content geometry, colours mapped to the style's by entropic OT",
              ("content", "style", "out_ply"), "run_colour_transfer")
stage_command("evaluate", "stage 8: weights-free metrics and CLIP crop similarity of one result",
              ("result", "content", "style", "result_render", "style_render", "texture_reference", "content_render",
               "out_json"),
              "run_evaluate", options=("stylize_npz",))


def columns_command(name: str, help_: str, out: str, fn: str):
    """A command writing ``out`` from LABEL=RENDER_FOLDER columns with ``render.<fn>(columns, out)``."""

    @command(name, help_)
    def cmd(sub):
        sub.add_argument(out, type=Path)
        sub.add_argument("columns", nargs="+", help="LABEL=RENDER_FOLDER ...")

        def run(a):
            from . import render

            getattr(render, fn)(_columns(a.columns, name), getattr(a, out))

        return run

    return cmd


columns_command("compare", "side-by-side comparison sheet of render folders (content, style, ours, baselines)",
                "out_png", "comparison_sheet")
columns_command("turntables", "one HTML page of render folders' turntables (MP4, or the GIF), side by side",
                "out_html", "turntable_page")


def _columns(specs: list[str], cmd: str) -> list[tuple[str, Path]]:
    cols = []
    for c in specs:
        if "=" not in c:
            raise ValueError(f"{cmd}: column '{c}' is not LABEL=FOLDER")
        label, folder = c.split("=", 1)
        cols.append((label, Path(folder)))
    return cols


def table_command(name: str, help_: str, flag: str, row_help: str, row_fn: str, hidden: tuple[str, ...] = ()):
    """A command writing a CSV (and Markdown) table with one ``tables.<row_fn>(results, spec)`` row per
    spec given after ``flag``; prints it without the ``hidden`` columns."""

    @command(name, help_)
    def cmd(sub):
        sub.add_argument("results", type=Path)
        sub.add_argument("out_csv", type=Path)
        sub.add_argument("--md", type=Path)
        sub.add_argument("--html", type=Path, help="also an HTML page of the table (the report shows it inline)")
        sub.add_argument(flag, dest="specs", nargs="+", required=True, help=row_help)

        def run(a):
            from . import tables

            rows = [getattr(tables, row_fn)(a.results, spec) for spec in a.specs]
            print(tables.write_table(rows, a.out_csv, a.md, a.html).drop(columns=list(hidden)).to_string(index=False))

        return run

    return cmd


table_command("summarize", "one table row per (content, style, experiment) from the stage reports", "--run",
              "CONTENT__STYLE/EXPERIMENT ...", "summary_spec_row")
table_command("table1", "the paper's Table 1: CLIP similarity, weights-free metrics, time, memory, device per method",
              "--row", "CONTENT__STYLE/METHOD/PARTITION/LABEL ... (PARTITION '-' for baselines and the input)",
              "table1_spec_row", hidden=("clip_status",))


@command("build-ext", "compile the native CPU kernels ahead of time")
def cmd_build(sub):
    sub.add_argument("--force", action="store_true")

    def run(a):
        from . import _native

        for name in ("raster_cpu", "sinkhorn_cpu"):
            print(_native.build(name, force=a.force))
        return 0

    return run


# ---- entry point -----------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="wast3d", description=__doc__.splitlines()[0])
    p.add_argument("-v", "--verbose", action="store_true")
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's)")
    sp = p.add_subparsers(dest="cmd", required=True)
    for name, (fn, help_) in COMMANDS.items():
        sub = sp.add_parser(name, help=help_, description=help_)
        sub.set_defaults(_run=fn(sub))
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    import torch

    torch.set_flush_denormal(True)  # denormals make CPU kernels 50-100x slower
    if args.threads:
        torch.set_num_threads(args.threads)
    from .datasets import DatasetError
    from .ply import PlyError

    try:
        return int(args._run(args) or 0)
    except (PlyError, DatasetError, FileNotFoundError, ValueError) as e:
        if not user_error(e):
            raise
        log.error("%s", e, exc_info=args.verbose)
        return 2


def user_error(e: BaseException) -> bool:
    """Whether ``e`` reports bad input (one line, exit code 2) rather than a fault (its traceback): a
    file or dataset error, or a ValueError that this package raised itself (its validation, which names
    the file and the field). A ValueError from inside numpy, torch or scipy is a fault."""
    from .datasets import DatasetError
    from .ply import PlyError

    if isinstance(e, (PlyError, DatasetError, FileNotFoundError)):
        return True
    tb = e.__traceback__
    while tb is not None and tb.tb_next is not None:
        tb = tb.tb_next
    return tb is not None and Path(tb.tb_frame.f_code.co_filename).resolve().parent == Path(__file__).resolve().parent


if __name__ == "__main__":
    sys.exit(main())

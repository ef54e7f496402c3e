"""The ``wast3d`` command: one subcommand per stage; every Snakemake rule calls one of these.

Each subcommand reads its inputs, calls the library's pure functions and writes its outputs
atomically. Errors in inputs are reported as one line naming the file and the field (exit code 2;
with ``-v`` their traceback as well); any other error is a fault and shows its traceback.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import shlex
import sys
from pathlib import Path

from .stages import STAGES, run_params

log = logging.getLogger("wast3d")

COMMANDS: dict[str, tuple] = {}


def command(name: str, help: str):
    def deco(fn):
        COMMANDS[name] = (fn, help)
        return fn

    return deco


# ---- info ------------------------------------------------------------------------------------


def drop_invalid_option(sub) -> None:
    """``--drop-invalid``, on every command that reads a scene a user gives."""
    sub.add_argument("--drop-invalid", action="store_true",
                     help="drop Gaussians whose values are unusable once decoded (NaN, infinite, a scale <= 0, a zero "
                          "quaternion) instead of failing; the log says how many")


def output_file(path: Path, *inputs: Path) -> Path:
    """``path`` as a file to write: a ValueError naming it when it is a folder, or when it is one of the
    ``inputs`` (after links are resolved): a writer never replaces what it reads."""
    if path.is_dir():
        raise ValueError(f"{path}: is a folder; give the file to write (its extension picks the format)")
    not_an_input(path, *inputs)
    return path


def not_an_input(out: Path, *inputs: Path) -> None:
    """A ValueError when ``out`` (a file or a folder to write) is one of ``inputs`` or, as a folder, holds
    one, links resolved: the command would overwrite what it reads."""
    o = Path(out).resolve()
    for i in inputs:
        r = Path(i).resolve()
        if o == r or o in r.parents:
            raise ValueError(f"{out}: {'is the input' if o == r else 'holds the input'} {i}; the output must be "
                             "another file (inputs are never changed)")


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
    drop_invalid_option(sub)

    def run(a):
        from .formats import read_scene
        from .ply import PlyError

        try:
            info = {"file": str(a.ply), "valid": True, **scene_summary(read_scene(a.ply, a.drop_invalid))}
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
    sub.add_argument("--host", default="127.0.0.1", help="the address to listen on: pages of this machine only by "
                                                         "default; 0.0.0.0 opens it to the network (any page served "
                                                         "from it, never another site's)")
    sub.add_argument("--port", type=int, default=8080, help="0-65535 (0: any free port)")
    sub.add_argument("--max-gaussians", type=int, default=300_000, help="per scene, most opaque kept")
    drop_invalid_option(sub)

    def run(a):
        try:
            from .viewer import run_forever, serve
        except ImportError as e:  # pragma: no cover - depends on the install
            raise ValueError(f"wast3d view needs viser ({e}); pip install 'wast3d[viewer]'") from None
        server = serve(a.ply, a.host, a.port, a.max_gaussians, a.drop_invalid)
        log.info("view: open http://%s:%d (Ctrl-C stops)", "localhost" if a.host in ("0.0.0.0", "127.0.0.1") else a.host,
                 server.get_port())
        run_forever(server)
        return 0

    return run


@command("run", "stylize CONTENT with STYLE (or with several styles, each in its region) through the workflow: "
                "writes OUT/config/config.yaml and runs Snakemake in OUT")
def cmd_run(sub):
    sub.add_argument("paths", type=Path, nargs="+", metavar="CONTENT STYLE [STYLE ...] OUT",
                     help="the content and the style(s): a PLY (reference, compressed or point cloud), .spz, .splat or "
                          "Blender folder each; OUT: the working folder (config/ and results/ go there; re-runs reuse "
                          "its cache)")
    sub.add_argument("--split", metavar="AXIS=VALUE", help="two styles: the first where the content's coordinate "
                                                           "along AXIS (x, y, z, -x, -y, -z) is at least VALUE, the "
                                                           "second elsewhere")
    sub.add_argument("--regions", type=Path, metavar="FILE", help="several styles: a YAML list of regions, each "
                                                                  "{style: INDEX, box | half_space | colour | labels "
                                                                  "| rest: ...} (docs/method.md, regions)")
    sub.add_argument("--profile", default=None, help="Snakemake profile (default: the workflow's profiles/local)")
    sub.epilog = "Snakemake's own arguments (targets, options) go after --: wast3d run C S OUT -- -p TARGET"
    sub.add_argument("-n", "--dry-run", action="store_true",
                     help="only show what would run; writes nothing (not even the config)")
    sub.add_argument("--reset-config", action="store_true",
                     help="rewrite OUT/config/config.yaml from the defaults even if you edited it (yours is kept as "
                          "config.yaml.bak)")
    sub.set_defaults(snakemake_args=[], torch_free=True)  # more Snakemake arguments: after --

    def run(a):
        import contextlib
        import os
        import subprocess

        import yaml

        from .io_utils import atomic_path
        from .config_check import load_yaml
        from .quickstart import (ConfigPlan, backup_path, check_path_text, config_text, configfiles, hold_folder,
                                 inside_results, plan_config, run_config, stale_locks, workflow_root)

        if len(a.paths) < 3:
            raise ValueError("run: give CONTENT STYLE [STYLE ...] OUT")
        content, styles, a.out = a.paths[0], a.paths[1:-1], a.paths[-1].absolute()
        for path, what in [(content, "the content"), *((s, "a style") for s in styles), (a.out, "OUT"),
                           *([(a.regions, "--regions")] if a.regions else [])]:
            check_path_text(path, what)
        if a.out.exists() and not a.out.is_dir():
            raise ValueError(f"{a.out}: OUT must be a folder (it is a file)")
        for path in (content, *styles):
            if inside_results(path, a.out):
                raise ValueError(f"{path}: lies inside {a.out}'s results ({path.resolve()}), which this run writes and "
                                 "may remove; copy it elsewhere first, or give another OUT")
        root = workflow_root()
        base = yaml.safe_load((root / "config" / "config.yaml").read_text())
        cfg = run_config(base, content, styles, a.split, a.regions)
        cfg_path = a.out / "config" / "config.yaml"
        if a.reset_config and cfg_path.is_file() and cfg_path.read_bytes() != config_text(cfg).encode():
            plan = ConfigPlan("write", config_text(cfg), "reset to the defaults")  # whatever it held, unreadable too
        else:
            plan = plan_config(cfg_path, cfg, content, *styles)
        for f in configfiles(a.snakemake_args):  # Snakemake's own loader would fail on them with a traceback
            load_yaml(f)
        used = yaml.safe_load(plan.text)
        if plan.action == "keep" and (a.split or a.regions) and used.get("regions") != cfg.get("regions"):
            raise ValueError(f"{cfg_path}: edited by hand, and its regions are not those {'--split' if a.split else '--regions'} "
                             "asks for; edit its 'regions' block, or start over from the defaults with --reset-config "
                             "(your file is kept beside it as a .bak)")
        pair = next(iter(used.get("pairs") or [[None, None]]))
        rset = next(iter(used.get("regions") or {}), None)
        with contextlib.ExitStack() as stack:
            lock = None
            if a.dry_run:
                workdir = dry_run_folder(a.out, plan.text, stack)
                log.info("run: dry run: nothing is written in %s (config: %s, %s)", a.out, cfg_path, plan.why)
            else:
                workdir = a.out
                lock = hold_folder(a.out)
                stack.callback(os.close, lock)
                if plan.action == "write":
                    if cfg_path.exists() and a.reset_config:
                        bak = backup_path(cfg_path)
                        cfg_path.rename(bak)
                        log.warning("run: your config is kept as %s", bak)
                    with atomic_path(cfg_path) as tmp:
                        Path(tmp).write_text(plan.text)
                log.info("run: %s x %s: config %s (%s)", *pair, cfg_path, plan.why)
            # absolute paths: a folder named `-out` never reaches Snakemake as an option
            cmd = [sys.executable, "-m", "snakemake", "-s", str(root / "Snakefile"), "-d", str(workdir.absolute()),
                   "--profile", a.profile or str(root / "workflow" / "profiles" / "local"),
                   *(["-n", "--nolock"] if a.dry_run else []), *a.snakemake_args]
            if not a.dry_run and stale_locks(a.out):
                log.warning("run: %s holds the locks of a run that was killed (no Snakemake works there now): "
                            "unlocked; the profile's rerun-incomplete redoes the jobs it left unfinished", a.out)
                subprocess.run([*cmd, "--unlock"], capture_output=True, check=True)
            log.info("run: %s", " ".join(shlex.quote(c) for c in cmd))
            rc = subprocess.run(cmd, pass_fds=() if lock is None else (lock,)).returncode
        if rc == 0 and not a.dry_run and None not in pair:
            from .stages import artifact

            c, s = pair
            s = rset or s
            res = a.out / "results"
            final = Path(artifact("final", res, content=c, style=s, experiment="default"))
            if not final.exists():  # targets of their own after --: the result was not asked for
                log.info("run: done (the targets asked for); the result %s is not built", final)
                return rc
            log.info("run: done. Result: %s; renders: %s; table: %s; view: wast3d view %s", final,
                     Path(artifact("render_pair", res, content=c, style=s, method="default")).parent,
                     res / "tables" / ("regions.md" if rset else "table1.md"),
                     " ".join(shlex.quote(str(p)) for p in (content, *styles, final)))
        return rc

    return run


def dry_run_folder(out: Path, config_text: str, stack) -> Path:
    """A temporary working folder for a dry run that writes nothing in ``out``: the config to run with in
    its config/, every other entry of ``out`` linked in (results/ above all), and of Snakemake's state in
    ``out`` only what it reads (the metadata and the incomplete markers: why a job would re-run)."""
    import tempfile

    tmp = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="wast3d-dry-run-")))
    (tmp / "config").mkdir()
    (tmp / "config" / "config.yaml").write_text(config_text)
    if out.is_dir():
        for entry in out.iterdir():
            if entry.name not in ("config", ".snakemake"):
                (tmp / entry.name).symlink_to(entry.resolve())
        for d in ("metadata", "incomplete"):
            if (out / ".snakemake" / d).is_dir():
                (tmp / ".snakemake").mkdir(exist_ok=True)
                (tmp / ".snakemake" / d).symlink_to((out / ".snakemake" / d).resolve())
    return tmp


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
    drop_invalid_option(sub)

    def run(a):
        from .formats import read_scene
        from .ply import write_ply

        out = output_file(a.out, a.ply)
        scene = read_scene(a.ply, drop_invalid=a.drop_invalid)
        write_ply(out, scene)
        log.info("imported %s -> %s: %d Gaussians, SH degree %d", a.ply, a.out, len(scene), scene.sh_degree)
        return 0

    return run


@command("export", "convert a scene between formats, by the extensions of IN and OUT (.ply, .compressed.ply, .spz, .splat)")
def cmd_export(sub):
    sub.add_argument("src", type=Path, metavar="IN")
    sub.add_argument("out", type=Path, metavar="OUT")
    drop_invalid_option(sub)

    def run(a):
        from .formats import read_scene, write_scene

        out = output_file(a.out, a.src)
        scene = read_scene(a.src, a.drop_invalid)
        write_scene(out, scene)
        log.info("exported %s -> %s: %d Gaussians", a.src, a.out, len(scene))
        return 0

    return run


def render_command(name: str, help_: str, fn: str, views: int, size: int, out_help: str, limits: dict[str, int]):
    """A command that renders a PLY from orbit cameras with ``render.<fn>(scene, out, views, size)``;
    ``limits`` bounds ``--views`` and ``--size`` (what one picture, or one view at a time, can hold)."""

    @command(name, help_)
    def cmd(sub):
        sub.add_argument("ply", type=Path)
        sub.add_argument("out", type=Path, help=out_help)
        sub.add_argument("--views", type=int, default=views)
        sub.add_argument("--size", type=int, default=size)
        drop_invalid_option(sub)

        def run(a):
            from . import render
            from .formats import read_scene

            not_an_input(a.out, a.ply)
            for opt in ("views", "size"):
                if not 1 <= getattr(a, opt) <= limits[opt]:
                    raise ValueError(f"{name}: --{opt} {getattr(a, opt)}: must be 1-{limits[opt]}")
            getattr(render, fn)(read_scene(a.ply, a.drop_invalid), a.out, a.views, a.size)
            return 0

        return run

    return cmd


render_command("preview", "render a 1 x N grid of orbit views of a PLY", "save_preview", 4, 256, "PNG file",
               {"views": 16, "size": 2048})  # the config schema's bounds of preview.views and preview.size
render_command("export-views", "render a PLY into a Blender-format posed image set (orbit cameras)",
               "export_blender", 48, 200, "output folder (transforms_train.json + train/*.png)",
               {"views": 1024, "size": 4096})


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


def stage_command(st) -> None:
    """The ``wast3d <command>`` of a :class:`~wast3d.stages.Stage`: one named option per file (``--content
    PATH``, ``--out-npz PATH``), ``--params``, and ``--no-progress`` where the stage has a progress bar;
    it calls ``pipeline.<run>`` with the files as keywords."""

    @command(st.command, st.help)
    def cmd(sub):
        for p in st.ports:
            if p.beside is not None:
                continue
            sub.add_argument(p.option, dest=p.keyword, type=Path, required=p.required, metavar="PATH",
                             help=p.help + ("" if p.required else " (optional)"))
        if st.progress:
            sub.add_argument("--no-progress", action="store_true")
        _params(sub)
        beside = [f"{p.name} beside {p.beside} ({p.help})" for p in st.ports if p.beside is not None]
        sub.epilog = ("Also writes, with the same stem: " + "; ".join(beside)) if beside else None

        def run(a):
            from . import pipeline

            kw = {p.keyword: getattr(a, p.keyword) for p in st.ports if p.beside is None}
            ins = [kw[p.keyword] for p in st.ports if not p.output and kw.get(p.keyword) is not None]
            for p in st.ports:
                if p.output and kw.get(p.keyword) is not None:
                    not_an_input(kw[p.keyword], *ins)
            if st.progress:
                kw["progress"] = not a.no_progress
            getattr(pipeline, st.run)(**kw, params=run_params(_load_params(a.params)))

        return run


for _stage in STAGES.values():
    stage_command(_stage)


def columns_command(name: str, help_: str, out: str, fn: str):
    """A command writing ``out`` from LABEL=RENDER_FOLDER columns with ``figures.<fn>(columns, out)``."""

    @command(name, help_)
    def cmd(sub):
        sub.add_argument(out, type=Path)
        sub.add_argument("columns", nargs="+", help="LABEL=RENDER_FOLDER ...")

        def run(a):
            from . import figures

            cols = _columns(a.columns, name)
            output_file(getattr(a, out), *(p for _, p in cols))
            getattr(figures, fn)(cols, getattr(a, out))

        return run

    return cmd


columns_command("compare", "side-by-side comparison sheet of render folders (content, style, ours, baselines)",
                "out_png", "comparison_sheet")
columns_command("strip", "one row of pictures with captions (a figure): CAPTION=PNG ...", "out_png", "strip")
columns_command("turntables", "one HTML page of render folders' turntables (MP4, or the GIF), side by side",
                "out_html", "turntable_page")


@command("merge-regions", "one scene of the results of a set of regions: OUT.ply STYLE=FINAL.ply ... (in the set's "
                          "order; final.json beside OUT lists each part)")
def cmd_merge(sub):
    sub.add_argument("out", type=Path)
    sub.add_argument("parts", nargs="+", help="STYLE=FINAL.ply ...")

    def run(a):
        from .pipeline import merge_regions

        parts = _columns(a.parts, "merge-regions")
        merge_regions(parts, output_file(a.out, *(p for _, p in parts)))
        return 0

    return run


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

            rows = []
            for spec in a.specs:  # a row function gives one row, or a list of them
                r = getattr(tables, row_fn)(a.results, spec)
                rows += r if isinstance(r, list) else [r]
            rows = tables.without_empty_metrics(rows)
            print(tables.write_table(rows, a.out_csv, a.md, a.html).drop(columns=list(hidden)).to_string(index=False))

        return run

    return cmd


table_command("summarize", "one table row per (content, style, experiment) from the stage reports", "--run",
              "CONTENT__STYLE/EXPERIMENT ...", "summary_spec_row")
table_command("regions-table", "one row per region of each set: its pair against its own style, and the seams",
              "--run", "CONTENT__SET/EXPERIMENT ...", "regions_spec_row")
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


def subcommand(argv: list[str]) -> str | None:
    """The subcommand ``argv`` names: its first word that is not a global option (``-v``, ``--threads N``)."""
    i = 0
    while i < len(argv):
        w = argv[i]
        if w == "--threads":
            i += 2
            continue
        if w.startswith("-"):
            i += 1
            continue
        return w
    return None


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    # `wast3d run`: what follows `--` is Snakemake's (`wast3d run C S OUT -n -- TARGET`), wherever the options
    # stand; any other command takes `--` as argparse does (the end of options: `wast3d info -- -n.ply`)
    cut = argv.index("--") if "--" in argv and subcommand(argv) == "run" else None
    extra = [] if cut is None else argv[cut + 1:]
    args = parser.parse_args(argv if cut is None else argv[:cut])
    if extra:
        args.snakemake_args = [*args.snakemake_args, *extra]
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    if not getattr(args, "torch_free", False):  # `run` only starts Snakemake: 3 s of importing torch saved
        import torch

        torch.set_flush_denormal(True)  # denormals make CPU kernels 50-100x slower
        if args.threads:
            torch.set_num_threads(args.threads)
    try:
        return int(args._run(args) or 0)
    except BrokenPipeError:  # `wast3d info x.ply | head`: the reader left; nothing more to say
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no second error when Python flushes
        return 0
    except (FileNotFoundError, ValueError) as e:  # PlyError and DatasetError are ValueErrors
        if not user_error(e):
            raise
        log.error("%s", e, exc_info=args.verbose)
        return 2
    except OSError as e:  # a folder that cannot be written (read-only, a file in its path, a full disk)
        if e.filename is None:
            raise
        where = e.filename if e.filename2 is None else f"{e.filename} -> {e.filename2}"
        log.error("%s: %s", where, e.strerror or e, exc_info=args.verbose)
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

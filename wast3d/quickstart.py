"""``wast3d run CONTENT STYLE OUT``: the workflow's config for a user with two scenes, no YAML to write.

The config is the project's defaults (``config/config.yaml``: partitions, experiments, evaluation)
with the demo's scenes, pairs and tables replaced by the two given scenes: one pair, the default
experiment, and a Table 1 with ours against the references a reader needs to read it (colour
transfer, the collage, the unstylized content). It is written to ``OUT/config/config.yaml`` and the
workflow runs with ``OUT`` as its working directory, so a second ``wast3d run`` into the same folder
reuses every cached stage.
"""

from __future__ import annotations

import copy
import hashlib
import re
from dataclasses import dataclass
from pathlib import Path

TABLE1_METHODS = ("default", "colour_ot", "selected", "input")  # labelled as the project's config labels them


def workflow_root() -> Path:
    """The folder holding the ``Snakefile``, ``workflow/`` and ``config/config.yaml``: the repository
    checkout this package sits in, else the copy an installed wheel carries (``wast3d/_workflow``)."""
    here = Path(__file__).resolve().parent
    for root in (here.parent, here / "_workflow"):
        if (root / "Snakefile").is_file() and (root / "workflow" / "rules").is_dir():
            return root
    raise FileNotFoundError(f"{here}: neither a repository checkout nor a wheel's wast3d/_workflow holds the "
                            "Snakefile (a broken install: reinstall wast3d)")


def scene_entry(path: Path, kind: str) -> dict:
    """A ``scenes`` entry for a scene file (any format :func:`~wast3d.formats.read_scene` reads) or a
    Blender folder of posed images (``kind`` content or style: a style's images are pretrained with eq. 1-2)."""
    path = Path(path).resolve()
    if path.is_dir():
        if not (path / "transforms_train.json").exists():
            raise ValueError(f"{path}: a folder must hold Blender-format posed images (transforms_train.json)")
        return {"source": "images", "kind": kind, "path": str(path)}
    if not path.exists():
        raise FileNotFoundError(f"{path}: file not found")
    from .io_utils import FORMATS  # the suffixes alone: wast3d.formats would import torch

    if path.suffix.lower() not in FORMATS:
        raise ValueError(f"{path}: expected a scene file ({', '.join(FORMATS)}) or a folder with transforms_train.json")
    return {"source": "ply", "path": str(path)}  # any scene file: the import_ply rule reads them all


GENERIC = {"scene", "point_cloud", "splat", "final", "stylized"}


def scene_name(path: Path, taken: set[str]) -> str:
    """A workflow-safe name from the file or folder name (``guitar.compressed.ply`` -> ``guitar``;
    a generic file name such as ``scene.ply`` or ``point_cloud.ply`` takes its nearest telling folder:
    ``results/scenes/pebbles/scene.ply`` -> ``pebbles``)."""
    path = Path(path).resolve()
    stem = path.name.split(".")[0]
    if stem in GENERIC:
        stem = next((p.name for p in path.parents if p.name and p.name not in GENERIC
                     and not p.name.startswith("iteration_")), stem)
    name = re.sub(r"[^A-Za-z0-9]+", "_", stem).strip("_") or "scene"
    if name[0].isdigit():
        name = f"s_{name}"
    base, k = name, 2
    while name in taken:
        name, k = f"{base}_{k}", k + 1
    return name


AXES = {"x": (1, 0, 0), "y": (0, 1, 0), "z": (0, 0, 1), "-x": (-1, 0, 0), "-y": (0, -1, 0), "-z": (0, 0, -1)}


def split_regions(split: str, styles: list[str]) -> list[dict]:
    """``--split AXIS=VALUE`` for two styles -> the region entries: the first style where the coordinate
    along AXIS (x, y, z or -x, -y, -z) is at least VALUE, the second everywhere else."""
    axis, _, value = split.partition("=")
    if axis not in AXES or not value:
        raise ValueError(f"--split {split}: expected AXIS=VALUE with AXIS one of {', '.join(AXES)}")
    if len(styles) != 2:
        raise ValueError(f"--split cuts the content in two: give two styles, not {len(styles)}")
    try:
        offset = float(value)
    except ValueError:
        raise ValueError(f"--split {split}: {value!r} is not a number") from None
    return [{"style": styles[0], "half_space": {"normal": list(AXES[axis]), "offset": offset}},
            {"style": styles[1], "rest": True}]


def regions_file(path: Path, styles: list[str], style_paths: list[Path]) -> list[dict]:
    """``--regions FILE``: a YAML list of region entries (wast3d/regions.py) whose ``style`` is the index of a
    style given on the command line (0: the first) or its path -> the entries with the styles' scene names."""
    from .config_check import load_yaml

    entries = load_yaml(path, "regions file", top=None)
    if not isinstance(entries, list):
        raise ValueError(f"{path}: a YAML list of regions, each {{style: INDEX, <kind>: ...}}")
    out = []
    for i, e in enumerate(entries):
        if not isinstance(e, dict) or "style" not in e:
            raise ValueError(f"{path}: entry {i} needs 'style' (the index of a style given, or its path)")
        st = e["style"]
        if isinstance(st, bool):
            raise ValueError(f"{path}: entry {i}: style {st!r} is a yes/no, not the index or the path of a style given")
        if isinstance(e.get("labels"), dict) and isinstance(e["labels"].get("path"), str):  # beside the regions file
            e = {**e, "labels": {**e["labels"], "path": str((Path(path).parent / e["labels"]["path"]).resolve())}}
        if isinstance(st, int) and 0 <= st < len(styles):
            name = styles[st]
        elif isinstance(st, str) and Path(st).resolve() in [Path(p).resolve() for p in style_paths]:
            name = styles[[Path(p).resolve() for p in style_paths].index(Path(st).resolve())]
        else:
            raise ValueError(f"{path}: entry {i}: style {st!r} is neither the index nor the path of a style given")
        out.append({**e, "style": name})
    return out


def run_config(base: dict, content: Path, styles: list[Path], split: str | None = None,
               regions: Path | None = None) -> dict:
    """The workflow's config for ``wast3d run``: one style, :func:`two_scene_config`; several, the content
    rebuilt from each in its region (``split`` or a ``regions`` file), each style alone beside it."""
    if len(styles) == 1:
        if split or regions:
            raise ValueError("--split and --regions need two styles or more")
        return two_scene_config(base, content, styles[0])
    if bool(split) == bool(regions):
        raise ValueError(f"{len(styles)} styles: say where each goes with --split AXIS=VALUE (two styles) or "
                         "--regions FILE")
    cfg = two_scene_config(base, content, styles[0])
    c = next(iter(cfg["scenes"]))
    names = [next(k for k in cfg["scenes"] if k != c)]
    for st in styles[1:]:
        names.append(scene_name(st, set(cfg["scenes"])))
        cfg["scenes"][names[-1]] = scene_entry(st, "style")
    entries = split_regions(split, names) if split else regions_file(regions, names, styles)
    cfg["regions"] = {f"{c}_by_region": {"content": c, "styles": entries}}
    cfg["pairs"] = [[c, n] for n in names]
    cfg["table1"]["pairs"] = []
    return cfg


def two_scene_config(base: dict, content: Path, style: Path) -> dict:
    """``base`` (the project's config) with the scenes, pairs, runs and tables of one content x style pair."""
    cfg = copy.deepcopy(base)
    c = scene_name(content, set())
    s = scene_name(style, {c})
    cfg["scenes"] = {c: scene_entry(content, "content"), s: scene_entry(style, "style")}
    cfg["pairs"] = [[c, s]]
    cfg["run"] = ["default"]
    labels = base.get("table1", {}).get("methods") or {}
    missing = [m for m in TABLE1_METHODS if not labels.get(m)]
    if missing:
        raise ValueError(f"config: table1.methods of the project's config has no label for {', '.join(missing)}")
    cfg["table1"] = {"pairs": [[c, s]], "methods": {m: labels[m] for m in TABLE1_METHODS}}
    cfg.pop("sweeps", None)
    cfg["experiments"] = {k: v for k, v in cfg.get("experiments", {}).items() if k in ("default", "selected")}
    used = {v.get("partition", "default") for v in cfg["experiments"].values()}
    cfg["partitions"] = {k: v for k, v in cfg.get("partitions", {}).items() if k in used}
    return cfg


# ---- the config file in OUT: written from the defaults, a user's edits never overwritten ----------------

MARK = "# written by `wast3d run` from the project's defaults"


def config_text(cfg: dict) -> str:
    """The text of ``OUT/config/config.yaml``: a first line with the digest of the rest, so that a later
    run can tell a file it wrote and nobody touched (safe to rewrite) from one a user edited."""
    import yaml

    body = yaml.safe_dump(cfg, sort_keys=False)
    return f"{MARK} (digest {_digest(body)}); edit it and run again: your edits are kept\n" + body


def _digest(body: str) -> str:
    return hashlib.sha256(body.encode()).hexdigest()[:16]


def written_unchanged(text: str) -> bool:
    """Whether ``text`` is a config :func:`config_text` wrote that nobody edited since."""
    first, _, body = text.partition("\n")
    m = re.fullmatch(re.escape(MARK) + r" \(digest ([0-9a-f]{16})\).*", first)
    return bool(m) and m.group(1) == _digest(body)


@dataclass(frozen=True)
class ConfigPlan:
    """What ``wast3d run`` does with ``OUT/config/config.yaml``: ``write`` the defaults' ``text`` (no file
    yet, or one it wrote unchanged whose defaults moved on), or ``keep`` the file there (``why``)."""

    action: str  # "write" | "keep"
    text: str  # the config the workflow runs with
    why: str


def plan_config(path: Path, cfg: dict, *scenes: Path) -> ConfigPlan:
    """Decide about the config file ``path`` for a run of the ``scenes`` (content, style, ...) whose defaults are
    ``cfg``. A file a user edited (or wrote) is kept when it names both scenes, and refused otherwise:
    a ValueError says how to start over. Never writes."""
    new = config_text(cfg)
    if path.is_dir():
        raise ValueError(f"{path}: is a folder, not the config file")
    if not path.exists():
        return ConfigPlan("write", new, "new")
    try:
        old = path.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise ValueError(f"{path}: cannot read the config ({e})") from None
    if old == new:
        return ConfigPlan("keep", old, "as written")
    if written_unchanged(old):
        return ConfigPlan("write", new, "unedited, rewritten from today's defaults")
    from .config_check import ConfigError, load_yaml

    try:
        mine = load_yaml(path)
    except ConfigError as e:
        raise ValueError(f"{e}: edited, and not a config the workflow reads; fix it, or start over from the defaults "
                         "with --reset-config (your file is kept beside it as a .bak)") from None
    paths = {str(Path(v["path"]).resolve()) for v in ((mine or {}).get("scenes") or {}).values()
             if isinstance(v, dict) and v.get("path")} if isinstance(mine, dict) else set()
    missing = [str(p) for p in (Path(x).resolve() for x in scenes) if str(p) not in paths]
    if missing:
        raise ValueError(f"{path}: edited by hand, and its scenes do not include {' and '.join(missing)}; run its "
                         "workflow with snakemake in that folder, or start over from the defaults with "
                         "--reset-config (your file is kept beside it as a .bak)")
    return ConfigPlan("keep", old, "edited by hand: your edits are kept")


def backup_path(path: Path) -> Path:
    """``config.yaml.bak`` beside ``path``, or ``config.yaml.bak2``, ... : a name not taken."""
    k, out = 1, path.with_name(path.name + ".bak")
    while out.exists():
        k += 1
        out = path.with_name(f"{path.name}.bak{k}")
    return out


# ---- one run in a folder at a time ------------------------------------------------------------------

LOCK = ".wast3d-run.lock"  # in OUT: held (flock) by `wast3d run` and, inherited, by the Snakemake it starts


def hold_folder(out: Path) -> int:
    """Take ``out``'s run lock: an exclusive ``flock`` on ``out/.wast3d-run.lock``, as an open descriptor
    that the Snakemake a run starts inherits. The lock lives as long as either process does (a
    ``kill -9`` of ``wast3d`` leaves its Snakemake holding it) and no longer (nothing stale to remove).
    A ValueError names the folder and the holder when another run has it."""
    import fcntl
    import os
    import time

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    fd = os.open(out / LOCK, os.O_RDWR | os.O_CREAT, 0o666)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = os.read(fd, 256).decode(errors="replace").strip()
        os.close(fd)
        raise ValueError(f"{out}: another run works in this folder ({holder or 'a wast3d run'}, or the Snakemake it "
                         "started, which goes on after a kill of wast3d); wait for it to end or stop it") from None
    os.ftruncate(fd, 0)
    os.write(fd, f"wast3d run, pid {os.getpid()}, since {time.strftime('%Y-%m-%d %H:%M:%S')}\n".encode())
    return fd


def snakemake_running_in(out: Path) -> list[int]:
    """PIDs of live Snakemake processes working on folder ``out``, this process's ancestors left out: its
    working directory (Snakemake changes into its ``-d`` folder), or ``-d``/``--directory`` naming it
    (absolute, or relative to that working directory or to ``/``)."""
    import os

    import psutil

    out = Path(out).resolve()
    mine = {p.pid for p in psutil.Process().parents()} | {os.getpid()}
    found = []
    for p in psutil.process_iter(["pid", "cmdline", "cwd"]):
        try:
            cmd = p.info["cmdline"] or []
            if p.info["pid"] in mine or not any("snakemake" in Path(c).name for c in cmd[:3]):
                continue
            cwd = Path(p.info["cwd"] or "/")
            dirs = [Path(cmd[i + 1]) for i, c in enumerate(cmd[:-1]) if c in ("-d", "--directory")]
            where = [cwd, *(d if d.is_absolute() else cwd / d for d in dirs)]
            if any(w.resolve() == out for w in where):
                found.append(p.info["pid"])
        except (psutil.Error, OSError):
            continue
    return found


def stale_locks(out: Path) -> bool:
    """Whether Snakemake's locks in ``out`` belong to no live process: a run killed (SIGKILL, a power
    loss) before it could remove them. Then they only stop the next run, which resumes the killed one.
    Asked by a run that holds :func:`hold_folder`'s lock (no run of ours is alive there), of the
    Snakemakes started by hand."""
    locks = Path(out) / ".snakemake" / "locks"
    return locks.is_dir() and any(locks.iterdir()) and not snakemake_running_in(out)


def inside_results(path: Path, out: Path) -> bool:
    """Whether ``path`` (links resolved) lies inside what a run in ``out`` writes: ``out/results`` or
    Snakemake's ``out/.snakemake``."""
    p = Path(path).resolve()
    return any(p == d or d in p.parents for d in ((Path(out) / "results").resolve(), (Path(out) / ".snakemake").resolve()))


def check_path_text(path: Path, what: str) -> None:
    """A ValueError for a path the workflow cannot carry: one that is not UTF-8 (Snakemake reads its
    config as text), that holds a line break, or a Snakemake wildcard."""
    text = str(path)
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        raise ValueError(f"{ascii(text)}: {what}: the name is not UTF-8 text; rename it") from None
    if "\n" in text or "\r" in text:
        raise ValueError(f"{ascii(text)}: {what}: the name holds a line break; rename it")
    from .config_check import check_no_wildcard

    check_no_wildcard(text, what)


def configfiles(snakemake_args: list[str]) -> list[str]:
    """The files ``--configfile``/``--configfiles`` names among Snakemake's arguments (``A B`` or ``=A``)."""
    out, take = [], False
    for w in snakemake_args:
        if w.startswith("-"):
            take = w in ("--configfile", "--configfiles")
            if "=" in w and w.split("=", 1)[0] in ("--configfile", "--configfiles"):
                out.append(w.split("=", 1)[1])
        elif take:
            out.append(w)
    return out

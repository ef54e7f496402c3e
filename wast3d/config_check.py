"""The workflow's config checked before anything runs, with errors a user can act on: one line naming
the config file and the key.

Order matters. A YAML file of a kilobyte can expand, through nested aliases, into billions of
values: each alias is one shared object when loaded, but anything that walks the config (a schema
validator, its error message printing the instance) walks every copy. So the size is bounded first
(:func:`check_size`, which stops counting at the bound), then every number must be finite
(:func:`check_finite`: YAML's ``.inf`` and ``.nan`` are numbers to a schema), then the schema
(:func:`check_schema`: its best-matching error, shortened). Plain declarations: imports nothing heavy
(the workflow loads this module by path).
"""

from __future__ import annotations

import functools
import math
from pathlib import Path
from typing import Any, Iterable

MAX_VALUES = 100_000  # a config this project runs holds about 500; a bomb holds billions
# peak memory per content Gaussian across the stages, a lower bound (docs/measurements.md, content sizes):
# a scene that needs more than the machine has is refused before the first job
PEAK_BYTES_PER_GAUSSIAN = 300


class ConfigError(ValueError):
    """A config the workflow will not run; the message names the file and the key."""


def _walk(node: Any, path: tuple = ()) -> Iterable[tuple[tuple, Any]]:
    yield path, node
    if isinstance(node, dict):
        for k, v in node.items():
            yield from _walk(v, path + (k,))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            yield from _walk(v, path + (i,))


def key(path: Iterable) -> str:
    """``('scenes', 'ant', 'n_gaussians')`` -> ``scenes.ant.n_gaussians`` (list items as ``[i]``)."""
    out = ""
    for p in path:
        out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out else str(p))
    return out or "(top level)"


def check_size(config: Any, where: str, limit: int = MAX_VALUES) -> None:
    """A ConfigError once more than ``limit`` values are counted (counting stops there)."""
    for n, _ in enumerate(_walk(config), 1):
        if n > limit:
            raise ConfigError(f"{where}: more than {limit} values once YAML aliases are expanded (nested anchors?); "
                              "refused before it is validated")


def check_finite(config: Any, files: list[str]) -> None:
    """A ConfigError naming the first number that is NaN or infinite, and the file that sets it."""
    for path, v in _walk(config):
        if isinstance(v, float) and not math.isfinite(v):
            raise ConfigError(f"{source(path, files)}: {key(path)}: {v} is not a finite number")


def check_schema(config: Any, schema: dict, files: list[str]) -> None:
    """A ConfigError for the schema's best-matching error: the file that sets the key, the key, and the
    message (the offending value shortened: a message never prints a whole block)."""
    from jsonschema import Draft202012Validator
    from jsonschema.exceptions import best_match

    err = best_match(Draft202012Validator(schema).iter_errors(config))
    if err is None:
        return
    path = tuple(err.absolute_path)
    msg = err.message
    if len(msg) > 300:
        msg = msg[:300] + " ..."
    if err.validator == "oneOf" and isinstance(err.instance, dict):  # the whole-oneOf message says little
        msg = f"matches none of its allowed forms ({', '.join(_forms(err.schema))}); its keys: {', '.join(map(str, err.instance))}"
    raise ConfigError(f"{source(path, files)}: {key(path)}: {msg}")


def _forms(schema: dict) -> list[str]:
    out = []
    for alt in schema.get("oneOf", []):
        req = alt.get("required", [])
        const = (alt.get("properties", {}).get("source") or {}).get("const")
        out.append(f"source {const} with {', '.join(r for r in req if r != 'source')}" if const else
                   "with " + ", ".join(req))
    return out


def source(path: tuple, files: list[str]) -> str:
    """``config FILE`` for the last of ``files`` that sets ``path`` (the one whose value counts), or
    ``config (FILE, ...)`` when none does alone (a --config override, or a key made by merging)."""
    import yaml

    for f in reversed(files):
        try:
            node = yaml.safe_load(Path(f).read_text())
        except (OSError, yaml.YAMLError):
            continue
        try:
            for p in path:
                node = node[p]
        except (KeyError, IndexError, TypeError):
            continue
        return f"config {f}"
    return f"config ({', '.join(files) or '--config'})"


def check_config(config: Any, schema: dict, files: list[str]) -> None:
    """Size, then finite numbers, then the schema (module docstring)."""
    check_size(config, f"config ({', '.join(files) or '--config'})")
    check_finite(config, files)
    check_schema(config, schema, files)


MAX_DEPTH = 64  # a config this project runs nests 7 deep; YAML's parser recurses once per level
MAX_BYTES = 4 << 20  # a config or regions file of this project is a few kilobytes


@functools.lru_cache(maxsize=None)
def _strict_loader():
    """yaml.SafeLoader that refuses a key given twice in one mapping (PyYAML keeps the last silently: a
    second ``experiments:`` block would replace the first)."""
    import yaml

    class Loader(yaml.SafeLoader):
        pass

    def mapping(loader, node, deep=False):
        seen = {}
        for k, _ in node.value:
            if k.tag == "tag:yaml.org,2002:merge":
                continue
            name = loader.construct_object(k, deep=True)
            try:
                first = seen.setdefault(name, k.start_mark.line + 1)
            except TypeError:  # an unhashable key: the constructor refuses it
                continue
            if first != k.start_mark.line + 1:
                raise ConfigError(f"line {k.start_mark.line + 1}: key '{name}' is given twice in one mapping "
                                  f"(first at line {first}); the second would silently replace the first")
        return loader.construct_mapping(node, deep)

    Loader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, mapping)
    return Loader


def load_yaml(path: str | Path, what: str = "config", top: type | None = dict) -> Any:
    """A YAML file a user gives, read within bounds, each refusal a ConfigError naming ``what`` and the
    file: a regular file of at most MAX_BYTES (``/dev/zero`` is no config), UTF-8 text, nested at most
    MAX_DEPTH deep (counted on the parser's events, which do not recurse), no key twice in one mapping,
    at most MAX_VALUES values once aliases are expanded, and of type ``top`` at its top level."""
    import yaml

    path = Path(path)
    where = f"{what} {path}"
    if not path.is_file():
        raise ConfigError(f"{where}: {'not found' if not path.exists() else 'not a regular file'}")
    if path.stat().st_size > MAX_BYTES:
        raise ConfigError(f"{where}: {path.stat().st_size} bytes; a config holds at most {MAX_BYTES >> 20} MiB")
    try:
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as e:
        raise ConfigError(f"{where}: not UTF-8 text (byte {e.start}); a config is a YAML file") from None
    except OSError as e:
        raise ConfigError(f"{where}: cannot be read ({e.strerror})") from None
    try:
        depth = 0
        for ev in yaml.parse(text, Loader=yaml.SafeLoader):
            if isinstance(ev, (yaml.MappingStartEvent, yaml.SequenceStartEvent)):
                depth += 1
                if depth > MAX_DEPTH:
                    raise ConfigError(f"{where}: line {ev.start_mark.line + 1}: nested more than {MAX_DEPTH} deep")
            elif isinstance(ev, (yaml.MappingEndEvent, yaml.SequenceEndEvent)):
                depth -= 1
        data = yaml.load(text, Loader=_strict_loader())  # noqa: S506 - a SafeLoader
    except yaml.YAMLError as e:
        raise ConfigError(f"{where}: not valid YAML ({str(e).splitlines()[0]})") from None
    except ConfigError as e:
        raise ConfigError(str(e) if str(e).startswith(where) else f"{where}: {e}") from None
    check_size(data, where)
    if top is not None and not isinstance(data, top):
        kind = {dict: "a mapping of keys", list: "a list"}.get(top, top.__name__)
        raise ConfigError(f"{where}: must be {kind} at its top level, not {'nothing (empty)' if data is None else type(data).__name__}")
    return data


def check_yaml_file(path: str | Path) -> None:
    """A config file Snakemake is about to merge (or has merged): :func:`load_yaml`'s bounds, before
    Snakemake's merge walks every copy of an alias."""
    load_yaml(path)


WILDCARD = r"\{\s*[.\w]+\s*(,[^}]*)?\}"  # what Snakemake reads as a wildcard in a path


def check_no_wildcard(path: str | Path, where: str) -> None:
    """A ConfigError (``where``: what names the path) when ``path`` holds what Snakemake reads as a
    wildcard: it has no escape for one in an input's path, and would read another file."""
    import re

    if m := re.search(WILDCARD, str(path)):
        raise ConfigError(f"{where}: '{m.group()}' in {path} is a wildcard to Snakemake, which would read another "
                          "file; rename it (or link it under another name)")


def check_scene_paths(scenes: dict, used: list[str], files: list[str], results: str = "results") -> None:
    """Each used scene's ``path`` (relative to the working folder): no Snakemake wildcard in it, present
    unless a rule writes it (a path under ``results``), and never inside the scene's own results
    (``results/scenes/NAME/``, which its import removes before it reads)."""
    out = Path(results).resolve()
    for name in used:
        s = scenes[name]
        if not isinstance(s, dict) or "path" not in s or s.get("source") not in ("ply", "images"):
            continue
        p, where = Path(str(s["path"])), f"{source(('scenes', name, 'path'), files)}: scenes.{name}.path"
        check_no_wildcard(p, where)
        r = p.resolve()
        own = out / "scenes" / name
        if r == own or own in r.parents:
            raise ConfigError(f"{where}: {p} lies in the scene's own results ({own}), which its import replaces")
        if out not in r.parents and not p.exists():
            raise ConfigError(f"{where}: {p} does not exist")


def check_sizes(scenes: dict, partitions: dict, used: list[str], contents: list[str], files: list[str],
                memory: int | None) -> None:
    """Bounds no machine of this run can meet, before the first job: a procedural scene whose Gaussians
    need more memory than ``memory`` bytes (None: not checked), and a partition asking for more clusters
    than a procedural content has Gaussians (k-means would clamp it)."""
    for name in used:
        s = scenes[name]
        if s.get("source") != "procedural":
            continue
        n = s.get("n_gaussians", 30000)
        if memory is not None and n * PEAK_BYTES_PER_GAUSSIAN > memory:
            raise ConfigError(f"{source(('scenes', name, 'n_gaussians'), files)}: scenes.{name}.n_gaussians: {n} "
                              f"Gaussians need at least {n * PEAK_BYTES_PER_GAUSSIAN / 2**30:.0f} GiB, this machine has "
                              f"{memory / 2**30:.0f} GiB")
        if name not in contents:
            continue
        for pname, p in partitions.items():
            k = ((p or {}).get("cluster") or {}).get("n_clusters", 0)
            if k > n:
                raise ConfigError(f"{source(('partitions', pname, 'cluster', 'n_clusters'), files)}: "
                                  f"partitions.{pname}.cluster.n_clusters: {k} clusters of the {n} Gaussians of "
                                  f"content '{name}'")

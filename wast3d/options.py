"""Stage options declared once: each field of a stage's config dataclass carries its description and
its allowed values (JSON-schema keywords) as metadata, :func:`option`.

From them come the workflow's config schema (``workflow/schemas/config.schema.yaml``, written by
``workflow/scripts/config_docs.py`` from the template ``config.schema.in.yaml``) and ``config/README.md``;
the types come from the annotations (``int`` -> integer, ``float`` -> number, ``X | None`` -> X or
null). A new option is one line in its dataclass. Imports nothing heavy.
"""

from __future__ import annotations

import dataclasses
import json
from typing import Any

_TYPES = {"int": "integer", "float": "number", "bool": "boolean", "str": "string", "tuple": "array"}


def option(default: Any = dataclasses.MISSING, help: str = "", *, factory=None, **schema) -> Any:
    """A dataclass field: ``default`` (or ``factory`` for a mutable one), ``help`` (what it changes, as
    config/README.md shows it) and ``schema``: JSON-schema keywords for its allowed values (``minimum``,
    ``exclusiveMinimum``, ``maximum``, ``exclusiveMaximum``, ``enum``, ``items``, ``minItems``, ...)."""
    if not help:
        raise ValueError("option: every option needs its help text")
    md = {"help": help, "schema": schema}
    if factory is not None:
        return dataclasses.field(default_factory=factory, metadata=md)
    return dataclasses.field(default=default, metadata=md)


def group(cls, help: str) -> Any:
    """A dataclass field holding a group of options (a dataclass of its own, its block in the config:
    ``stylize.parts``); a dict given for it is built into ``cls`` and checked there (:func:`checked`)."""
    if not help:
        raise ValueError("group: every group needs its help text")
    return dataclasses.field(default_factory=cls, metadata={"help": help, "group": cls})


def groups(cls) -> dict[str, type]:
    """``{field: its dataclass}`` of the option groups of dataclass ``cls`` (:func:`group`)."""
    return {f.name: f.metadata["group"] for f in dataclasses.fields(cls) if "group" in f.metadata}


def json_type(annotation: str) -> str | list[str]:
    """The JSON-schema type of a field annotation (a string under ``from __future__ import annotations``)."""
    text = annotation if isinstance(annotation, str) else getattr(annotation, "__name__", None) or str(annotation)
    parts = [p.strip() for p in text.split("|")]
    types = [_TYPES.get(p.split("[")[0]) for p in parts if p != "None"]
    if None in types or len(types) != 1:
        raise ValueError(f"options: no JSON type for the annotation '{annotation}'")
    return [types[0], "null"] if "None" in parts else types[0]


def schema_properties(cls) -> dict[str, dict]:
    """``{field: JSON-schema node}`` of the documented fields of dataclass ``cls`` (those made with
    :func:`option`), in declaration order; an ``enum`` stands for the type."""
    out = {}
    for f in dataclasses.fields(cls):
        if "help" not in f.metadata:
            continue
        if "group" in f.metadata:
            out[f.name] = {"type": "object", "additionalProperties": False, "description": f.metadata["help"],
                           "properties": schema_properties(f.metadata["group"])}
            continue
        extra = json.loads(json.dumps(f.metadata["schema"]))  # tuples (an enum from a constant) as lists
        node = {} if "enum" in extra else {"type": json_type(f.type)}
        node.update(extra)
        node["description"] = f.metadata["help"]
        out[f.name] = node
    return out


def undocumented(cls) -> list[str]:
    """Fields of ``cls`` made without :func:`option` (each needs a help text to be configurable)."""
    return [f.name for f in dataclasses.fields(cls) if "help" not in f.metadata]


def make_config(cls, params: dict | None, where: str):
    """Dataclass ``cls`` built from the dict ``params``: an unknown key is a ValueError naming ``where``,
    the key and the known ones (the options' own values are checked by :func:`checked`)."""
    params = dict(params or {})
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(params) - names)
    if unknown:
        raise ValueError(f"{where}: unknown parameter(s) {', '.join(unknown)} (known: {', '.join(sorted(names))})")
    return cls(**params)


_BOUNDS = {"minimum": (">=", lambda v, b: v >= b), "exclusiveMinimum": (">", lambda v, b: v > b),
           "maximum": ("<=", lambda v, b: v <= b), "exclusiveMaximum": ("<", lambda v, b: v < b)}


def check_options(obj, where: str) -> None:
    """Check every option of dataclass instance ``obj`` against its allowed values (``enum`` and the
    bounds of its :func:`option`): a ValueError names ``where.field``, the rule and the value. NaN fails
    every bound."""
    for f in dataclasses.fields(obj):
        schema = f.metadata.get("schema")
        if schema is None:
            continue
        v = getattr(obj, f.name)
        if "enum" in schema and v not in schema["enum"]:
            raise ValueError(f"{where}.{f.name} must be one of {', '.join(map(str, schema['enum']))}, got {v!r}")
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            for key, (op, ok) in _BOUNDS.items():
                if key in schema and not ok(v, schema[key]):
                    raise ValueError(f"{where}.{f.name} must be {op} {schema[key]}, got {v!r}")


def checked(where: str):
    """Class decorator, below ``@dataclass``: construction first builds its option groups given as dicts
    (:func:`group`; unknown keys named ``where.group.key``), checks the options (:func:`check_options`,
    errors named ``where.field``), then runs the class's own ``__post_init__`` (checks across fields)."""

    def deco(cls):
        own = cls.__dict__.get("__post_init__")

        def __post_init__(self):
            for name, sub in groups(cls).items():
                value = getattr(self, name)
                if isinstance(value, dict):
                    setattr(self, name, make_config(sub, value, f"{where}.{name}"))
                elif not dataclasses.is_dataclass(value):
                    raise ValueError(f"{where}.{name} must be a mapping of its options, got {value!r}")
            check_options(self, where)
            if own is not None:
                own(self)

        cls.__post_init__ = __post_init__
        return cls

    return deco

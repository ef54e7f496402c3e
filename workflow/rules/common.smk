"""Shared by every rule file: config validation and the helpers that decide which stages a scene needs."""

from snakemake.utils import validate


validate(config, schema="../schemas/config.schema.yaml")

SCENES = config["scenes"]
RESULTS = "results"


def scenes_of(source):
    return [name for name, s in SCENES.items() if s["source"] == source]


def constraint(names):
    """A wildcard constraint matching exactly ``names`` (never matches when empty)."""
    return "|".join(names) if names else "(?!x)x"


for _name, _s in SCENES.items():
    _skip = {"procedural": "pretraining (the scene is generated as Gaussians)",
             "ply": "pretraining (a trained 3DGS PLY is given)",
             "images": None}[_s["source"]]
    if _skip:
        logger.info(f"scene '{_name}': left out {_skip}")

import sys

# the interpreter running Snakemake runs the stages too (no PATH set-up needed, same on cluster nodes)
WAST3D = f"{sys.executable} -m wast3d"

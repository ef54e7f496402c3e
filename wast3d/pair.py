"""Stages 3-6 on one (content, style) pair in memory: the same stage functions the workflow's rules call
(:mod:`wast3d.pipeline`), for benchmarks and tests that vary the stylization without files.

    part = partition(content, style, params)          # stages 3-4: k-means, eq. 7, eq. 8
    out = stylize_partition(part, content, style, params)  # stages 5-6: eq. 9, scale readjustment

``params`` holds the workflow config's blocks (``cluster``, ``register``, ``select``: a partition's;
``stylize``, ``rescale``: an experiment's), each checked by its stage's dataclass; a block left out takes
the defaults. A partition does not depend on the stylization, so one serves every variant of it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import torch

from .clustering import ClusterConfig, Clusters, cluster_content
from .gaussians import GaussianScene
from .options import make_config
from .registration import Registration, RegistrationConfig, register
from .rescale import RescaleConfig, rescale
from .selection import SelectConfig, Selection, select_style
from .stylize import StylizeConfig, Stylized, stylize


@dataclass
class Partition:
    """Stages 3-4 of a pair: the content's clusters, their registrations and selections, and the
    seconds each stage took."""

    clusters: Clusters
    registration: Registration
    selection: Selection
    seconds: dict[str, float]


@dataclass
class PairResult:
    """Stages 5-6 on a :class:`Partition`: the result (``final``), the stylization before the scale
    readjustment (``stylized``), the readjusted scales' ratios (None: disabled) and the seconds."""

    final: GaussianScene
    stylized: Stylized
    ratio: torch.Tensor | None
    seconds: dict[str, float]


def partition(content: GaussianScene, style: GaussianScene, params: dict | None = None,
              sheet: bool = False) -> Partition:
    """``sheet``: the style is a volume's element sheet (the style stage's report says so)."""
    params = params or {}
    t, secs = time.perf_counter(), {}
    clusters = cluster_content(content, make_config(ClusterConfig, params.get("cluster"), "cluster"))
    secs["cluster"], t = time.perf_counter() - t, time.perf_counter()
    reg = register(content.means, clusters.labels, style.means,
                   make_config(RegistrationConfig, params.get("register"), "register"), normals=clusters.normals,
                   sheet=sheet)
    secs["register"], t = time.perf_counter() - t, time.perf_counter()
    sel = select_style(make_config(SelectConfig, params.get("select"), "select"), content, clusters.labels, style, reg)
    secs["select"] = time.perf_counter() - t
    return Partition(clusters, reg, sel, secs)


def stylize_partition(part: Partition, content: GaussianScene, style: GaussianScene, params: dict | None = None,
                      progress: bool = False, sheet: bool = False) -> PairResult:
    params = params or {}
    t = time.perf_counter()
    res = stylize(content, part.clusters.labels, style, part.registration, part.selection,
                  make_config(StylizeConfig, params.get("stylize"), "stylize"), progress, sheet=sheet)
    t1 = time.perf_counter()
    final, ratio = rescale(res.scene, res.before_means, res.labels,
                           make_config(RescaleConfig, params.get("rescale"), "rescale"))
    return PairResult(final, res, ratio, {"stylize": t1 - t, "rescale": time.perf_counter() - t1})

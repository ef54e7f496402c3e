"""Several styles on one content, by region: which content points each style rebuilds, the content's
clusters split where a region's border crosses them, and the seam where two styles meet.

A region set is an ordered list of (style, region). A region is one of

- ``box``: ``{min: [x, y, z], max: [x, y, z]}``, in the content's frame;
- ``half_space``: ``{normal: [nx, ny, nz], offset: d}``, the points with ``n . x >= d``;
- ``colour``: ``{groups: G, take: [i, ...]}``, colour groups of the content: k-means on the points'
  RGB into G groups, numbered by luminance (0 the darkest);
- ``labels``: ``{path: FILE, take: [v, ...]}``, a per-Gaussian label file of the content scene (``.npy``
  or a text file of integers, one per Gaussian in the scene file's order, as a segmentation gives them);
  each content point takes the label of its nearest scene Gaussian;
- ``rest``: every point no region before it claimed.

Each point belongs to the first region that claims it; a point no region claims is an error, so a set
that does not end with ``rest`` must cover the content. Stages 1-3 (pretraining, surface sampling,
k-means) do not depend on the regions: each region's clusters are the content's clusters cut by the
region (:func:`split_clusters`), so a cluster that straddles a border becomes one cluster on each side.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

log = logging.getLogger(__name__)

KINDS = ("box", "half_space", "colour", "labels", "rest")


@dataclass(frozen=True)
class Region:
    """One entry of a region set: its style and what it claims (``kind`` of KINDS, ``spec`` its keys)."""

    style: str
    kind: str
    spec: dict

    @staticmethod
    def parse(entry: dict, where: str) -> "Region":
        """A config entry ``{style: NAME, <kind>: {...}}`` (``rest: true``); a ValueError names ``where``."""
        if not isinstance(entry, dict) or "style" not in entry:
            raise ValueError(f"{where}: a region needs 'style' and one of {', '.join(KINDS)}")
        if not isinstance(entry["style"], str):
            raise ValueError(f"{where}.style: the name of a style scene, got {entry['style']!r}")
        kinds = [k for k in KINDS if k in entry]
        extra = sorted(set(entry) - {"style", *KINDS})
        if len(kinds) != 1 or extra:
            raise ValueError(f"{where}: a region names exactly one of {', '.join(KINDS)} (got "
                             f"{', '.join(kinds) or 'none'}{'; unknown ' + ', '.join(extra) if extra else ''})")
        kind, spec = kinds[0], entry[kinds[0]]
        if kind == "rest":
            if spec is not True:
                raise ValueError(f"{where}.rest: must be true")
            return Region(entry["style"], kind, {})
        need = {"box": ("min", "max"), "half_space": ("normal", "offset"), "colour": ("groups", "take"),
                "labels": ("path", "take")}[kind]
        if not isinstance(spec, dict) or any(k not in spec for k in need) or set(spec) - set(need):
            raise ValueError(f"{where}.{kind}: needs exactly {', '.join(need)}")
        vec = [spec[k] for k in ("min", "max", "normal") if k in spec]
        for v in vec:
            if not (isinstance(v, (list, tuple)) and len(v) == 3 and all(_number(x) for x in v)):
                raise ValueError(f"{where}.{kind}: vectors are 3 finite numbers, got {v!r}")
        if kind == "half_space" and not _number(spec["offset"]):
            raise ValueError(f"{where}.half_space.offset: a finite number, got {spec['offset']!r}")
        if kind == "labels" and not isinstance(spec["path"], str):
            raise ValueError(f"{where}.labels.path: a file name, got {spec['path']!r}")
        if kind in ("colour", "labels") and isinstance(spec["take"], list) and not all(
                isinstance(x, int) and not isinstance(x, bool) for x in spec["take"]):
            raise ValueError(f"{where}.{kind}.take: integers, got {spec['take']!r}")
        if kind == "half_space" and float(np.linalg.norm(spec["normal"])) == 0:
            raise ValueError(f"{where}.half_space.normal: must not be zero")
        if kind == "box" and any(a > b for a, b in zip(spec["min"], spec["max"])):
            raise ValueError(f"{where}.box: min must not exceed max")
        if kind in ("colour", "labels") and not (isinstance(spec["take"], list) and spec["take"]):
            raise ValueError(f"{where}.{kind}.take: a non-empty list")
        if kind == "colour" and not (isinstance(spec["groups"], int) and not isinstance(spec["groups"], bool)
                                     and 1 <= spec["groups"] <= 64
                                     and all(isinstance(t, int) and 0 <= t < spec["groups"] for t in spec["take"])):
            raise ValueError(f"{where}.colour: groups 1-64, take ids below it")
        return Region(entry["style"], kind, dict(spec))


def _number(x) -> bool:
    """A finite int or float, not a yes/no (YAML's ``true`` is an int to Python)."""
    return isinstance(x, (int, float)) and not isinstance(x, bool) and bool(np.isfinite(x))


def parse_set(entries: list, where: str) -> list[Region]:
    """A region set's entries -> [Region]; a ValueError names ``where`` (at least two styles' regions, at most
    one ``rest``, last)."""
    if not isinstance(entries, list) or len(entries) < 2:
        raise ValueError(f"{where}: a region set lists two regions or more")
    regions = [Region.parse(e, f"{where}[{i}]") for i, e in enumerate(entries)]
    rest = [i for i, r in enumerate(regions) if r.kind == "rest"]
    if rest and rest != [len(regions) - 1]:
        raise ValueError(f"{where}: 'rest' is the last region, and there is one at most")
    return regions


def colour_groups(rgb: np.ndarray, groups: int, seed: int = 0) -> np.ndarray:
    """[N, 3] colours -> [N] group ids 0..groups-1 by k-means, numbered by the groups' luminance."""
    from sklearn.cluster import KMeans

    if groups == 1:
        return np.zeros(len(rgb), np.int64)
    km = KMeans(groups, random_state=seed, n_init=3).fit(rgb)
    lum = km.cluster_centers_ @ np.array([0.299, 0.587, 0.114])
    rank = np.empty(groups, np.int64)
    rank[np.argsort(lum)] = np.arange(groups)
    return rank[km.labels_]


def assign(points: np.ndarray, rgb: np.ndarray, regions: list[Region], scene_labels: np.ndarray | None = None,
           where: str = "regions") -> np.ndarray:
    """points [N, 3], rgb [N, 3] (the content points), ``scene_labels`` [N] each point's label from a
    ``labels`` region's file (:func:`nearest_labels`) -> [N] region index per point (the first region that
    claims it). A ValueError names ``where`` for a point no region claims and for a region that claims
    no point."""
    n = len(points)
    out = np.full(n, -1, np.int64)
    for i, r in enumerate(regions):
        if r.kind == "box":
            claim = ((points >= np.asarray(r.spec["min"])) & (points <= np.asarray(r.spec["max"]))).all(1)
        elif r.kind == "half_space":
            nrm = np.asarray(r.spec["normal"], np.float64)
            claim = points @ (nrm / np.linalg.norm(nrm)) >= float(r.spec["offset"])
        elif r.kind == "colour":
            claim = np.isin(colour_groups(rgb, r.spec["groups"]), r.spec["take"])
        elif r.kind == "labels":
            if scene_labels is None:
                raise ValueError(f"{where}[{i}].labels: the labels were not read")
            claim = np.isin(scene_labels, r.spec["take"])
        else:
            claim = np.ones(n, bool)
        new = claim & (out < 0)
        if not new.any():
            raise ValueError(f"{where}[{i}] ({r.style}, {r.kind}): claims no content point not claimed before")
        out[new] = i
    if (out < 0).any():
        raise ValueError(f"{where}: {int((out < 0).sum())} of {n} content points lie in no region (end the set "
                         "with a 'rest' region)")
    return out


def read_labels(path: str, count: int) -> np.ndarray:
    """A per-Gaussian label file (``.npy``, or text with one integer per Gaussian) of a scene of ``count``
    Gaussians; a ValueError names the file."""
    from pathlib import Path

    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"{p}: label file not found")
    if not p.is_file():
        raise ValueError(f"{p}: not a label file (not a regular file)")
    if p.suffix == ".npy":  # its header first: a count or type that does not fit is refused before reading
        try:
            with open(p, "rb") as f:
                major, _ = np.lib.format.read_magic(f)
                read = np.lib.format.read_array_header_1_0 if major == 1 else np.lib.format.read_array_header_2_0
                shape, _, dtype = read(f, max_header_size=1 << 16)
        except (ValueError, OSError, SyntaxError) as e:
            raise ValueError(f"{p}: not a .npy label file ({e})") from None
        if dtype.kind not in "iu" or int(np.prod(shape, dtype=np.float64)) != count:
            raise ValueError(f"{p}: header: {int(np.prod(shape, dtype=np.float64))} labels of type {dtype} for a scene of "
                             f"{count} Gaussians (one integer per Gaussian, in its order)")
    elif p.stat().st_size > 32 * (count + 1):
        raise ValueError(f"{p}: {p.stat().st_size} bytes is more text than {count} labels hold")
    try:
        lab = np.load(p, allow_pickle=False) if p.suffix == ".npy" else np.loadtxt(p, dtype=np.int64, ndmin=1)
    except (ValueError, OSError) as e:
        raise ValueError(f"{p}: not a label file ({str(e)[:200]})") from None
    lab = np.asarray(lab).reshape(-1)
    if not np.issubdtype(lab.dtype, np.integer):
        raise ValueError(f"{p}: labels must be integers, got {lab.dtype}")
    if len(lab) != count:
        raise ValueError(f"{p}: {len(lab)} labels for a scene of {count} Gaussians (one per Gaussian, in its order)")
    return lab.astype(np.int64)


def nearest_labels(points: np.ndarray, scene_means: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Each content point [N, 3] takes the label of its nearest scene Gaussian (means [M, 3], labels [M])."""
    from .geometry import kdtree

    return labels[kdtree(scene_means).query(points)[1]]


def split_clusters(labels: np.ndarray, region: np.ndarray, k: int, normals: np.ndarray | None = None,
                   min_size: int = 4) -> tuple[np.ndarray, np.ndarray, dict]:
    """The content's clusters (labels [N]) cut by region ``k`` (region [N] per point) -> (the indices of
    region k's points, their cluster labels 0..K'-1, a report). A cluster the border crosses is one
    cluster on each side; a piece under ``min_size`` points joins the piece of the same region whose
    centroid is nearest (by its normals' mean where ``normals`` [N, 3] are given, so it stays on its side
    of a thin part; else by the cluster ids' own order)."""
    idx = np.nonzero(region == k)[0]
    lab = labels[idx]
    ids, inv, counts = np.unique(lab, return_inverse=True, return_counts=True)
    whole = np.bincount(labels, minlength=int(labels.max()) + 1)
    cut = int((counts < whole[ids]).sum())
    small = counts < min_size
    if small.any() and (~small).any():
        keep = np.nonzero(~small)[0]
        if normals is not None:
            n = normals[idx]
            mean_n = np.stack([n[inv == j].mean(0) for j in range(len(ids))])
            for j in np.nonzero(small)[0]:
                inv[inv == j] = keep[np.argmax(mean_n[keep] @ mean_n[j])]
        else:
            for j in np.nonzero(small)[0]:
                inv[inv == j] = keep[np.argmin(np.abs(keep - j))]
    _, inv = np.unique(inv, return_inverse=True)
    report = {"points": len(idx), "clusters": int(inv.max()) + 1 if len(inv) else 0,
              "clusters_cut_by_the_border": cut, "pieces_merged": int(small.sum()) if (~small).any() else 0}
    return idx, inv.astype(np.int64), report


def per_point(points: np.ndarray, means: np.ndarray) -> np.ndarray:
    """[N] how many of the Gaussians [M, 3] have each content point as their nearest."""
    from .geometry import kdtree

    return np.bincount(kdtree(points).query(means)[1], minlength=len(points))


def band_of(points: np.ndarray, region: np.ndarray, band: float) -> np.ndarray:
    """[N] bool: the content points within ``band`` of a point of another region (the seam's band)."""
    from .geometry import kdtree

    other_d = np.full(len(points), np.inf)
    for r in np.unique(region):
        mine, theirs = region == r, region != r
        if theirs.any():
            other_d[mine] = kdtree(points[theirs]).query(points[mine])[0]
    return other_d <= band


def seam_density(points: np.ndarray, region: np.ndarray, in_band: np.ndarray, result: np.ndarray,
                 alone: dict) -> dict:
    """Per region, the merged result's Gaussians [M, 3] per band point of its side (:func:`per_point`),
    against the same of its style alone on the whole content (``alone``: region index -> means): the ratio
    is 1 as the style alone, below for a gap along the seam, above for a doubled layer (the bar: 1/1.5 ..
    1.5). A result of one style scores 1 on every side by construction (its control)."""
    merged = per_point(points, result)
    out = {}
    for r in np.unique(region):
        b = (region == r) & in_band
        e = {"points": int((region == r).sum()), "band_points": int(b.sum()),
             "density_band": float(merged[b].mean()) if b.any() else None}
        if int(r) in alone and b.any():
            a = per_point(points, alone[int(r)])[b].mean()
            e["density_band_alone"] = float(a)
            e["density_ratio"] = float(merged[b].mean() / a) if a > 0 else None
        out[int(r)] = e
    return out


def band_coverage(result_alpha, content_alpha, band_share) -> float | None:
    """Coverage along the seam: over the frames [V, H, W], the share of the pixels where the content's
    render shows its band (``band_share`` > 0.5: the band's points draw most of the pixel; ``content_alpha``
    > 0.5) that the result covers (``result_alpha`` > 0.5). None where no pixel shows the band."""
    m = (content_alpha > 0.5) & (band_share > 0.5)
    n = int(m.sum())
    return float(((result_alpha > 0.5) & m).sum()) / n if n else None

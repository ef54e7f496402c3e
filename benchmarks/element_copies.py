"""How much of each style element a result's element copies hold, against the clusters' size.

    python benchmarks/element_copies.py PAIR[:METHOD[:PARTITION]] ... [--out results/benchmarks/element_copies.csv]

Reads what the workflow wrote for each pair (its artifacts, :func:`wast3d.stages.artifact`; METHOD and
PARTITION, the method's partition as its experiment declares it, default to ``default``). A *copy* is the Gaussians of one style element selected by one cluster
(:func:`wast3d.elements.copy_ids`), which ``element_intact`` compares with itself in the collage: a
copy cut to a sliver at its cluster's edge scores as intact as a whole element. Here each copy is
compared with its element in the style: its *completeness* is its Gaussians over the element's. Per
pair: the median completeness over element Gaussians, the share of them in copies that hold at least
half and at least 0.8 of their element, and the median cluster span, the in-plane RMS diameter (twice
the RMS distance to the cluster's centre over its two widest axes) of the content's clusters over the
element length on the content (``element_length`` of the texture reference: the style's relief length
/ s0). Writes the CSV and, per pair, ``element_copies_PAIR_METHOD.png``: the result's first key view
and its close-up with each copy in its own colour and the ground black, beside the close-up in RGB.

``--thickness`` splits the completeness by the content's *local thickness* where each copy lies
(:func:`wast3d.geometry.local_thickness`: the distance through the content along its normal) against
the style element's diameter on the content (:func:`wast3d.elements.element_diameter` / s0): a whole
element cannot lie where the content is thinner than it without widening the content there.

``--copies N`` writes ``element_copies_PAIR_METHOD_copies.png``: N clusters (drawn with seed 0), each
as its Gaussians on the result beside the same Gaussians in the style, the two cameras related by the
cluster's registration map (eq. 7), so that a copy that keeps what its style region shows looks the same.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import OUT, ROOT, write_rows  # noqa: E402

RESULTS = ROOT / "results"


def first(*paths: Path) -> Path:
    for p in paths:
        if p.exists():
            return p
    raise FileNotFoundError(f"none of {', '.join(map(str, paths))} exists: run the pair through the workflow first")


def cluster_span(points: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """[K] in-plane RMS diameter of each cluster: 2 sqrt(l1 + l2), l1 >= l2 >= l3 its covariance's eigenvalues."""
    out = []
    for k in np.unique(labels):
        p = points[labels == k]
        p = p - p.mean(0)
        ev = np.sort(np.linalg.eigvalsh(p.T @ p / len(p)))[::-1]
        out.append(2 * np.sqrt(ev[0] + ev[1]))
    return np.asarray(out)


def completeness(style_element: np.ndarray, selected: np.ndarray, clusters: np.ndarray) -> np.ndarray:
    """Per element Gaussian of a result: the share of its style element that its copy holds.
    style_element [M] labels of the style; selected [N] style index of each result Gaussian; clusters [N]."""
    el = style_element[selected]
    m = el > 0
    base = int(el.max()) + 1
    copies, inv, cnt = np.unique(clusters[m].astype(np.int64) * base + el[m], return_inverse=True, return_counts=True)
    return (cnt / np.bincount(style_element)[copies % base])[inv]


def copy_picture(result, clusters: np.ndarray, render_json: Path, out: Path) -> None:
    from PIL import Image

    from wast3d.elements import copy_ids
    from wast3d.figures import grid, save_png
    from wast3d.rasterizer import rasterize
    from wast3d.render import read_cameras

    cid = copy_ids(result.element, torch.from_numpy(clusters))
    _, inv = torch.unique(cid, return_inverse=True)
    colours = torch.rand(int(inv.max()) + 1, 3, generator=torch.Generator().manual_seed(0)) * 0.8 + 0.2
    col = colours[inv].to(result.means.dtype)
    col[cid < 0] = 0.0
    cams = read_cameras(render_json.parent)
    tiles = []
    for cam, colors in ((cams[0], col), (cams[-1], col), (cams[-1], None)):
        m = rasterize(result, cam, background=(1.0, 1.0, 1.0), colors=colors)
        tile = Image.fromarray((m.rgb.clamp(0, 1).numpy() * 255).astype(np.uint8)).resize((384, 384))
        tiles.append(np.asarray(tile))
    save_png(out, grid(tiles, len(tiles)))


def _or_nan(f, v: np.ndarray) -> float:
    """f(v) as a float, nan for an empty v."""
    return float(f(v)) if len(v) else float("nan")


def copy_sheet(result, style, clusters: np.ndarray, selected: np.ndarray, registration: Path, n: int,
               out: Path, size: int = 256) -> None:
    """Cluster k's result Gaussians seen along its outward normal from 4 radii away, beside the style
    Gaussians it selected seen from the camera the registration maps that one onto (y = S R (x - mu) + p)."""
    from PIL import Image

    from wast3d.cameras import Camera, look_at
    from wast3d.rasterizer import rasterize

    reg = np.load(registration)
    R, S, mu, p, up = reg["R"], reg["s"], reg["mu"], reg["p"], reg["style_up"]
    ids = np.unique(clusters)
    ks = np.random.default_rng(0).choice(ids, min(n, len(ids)), replace=False)
    rows = []
    for k in ks:
        mine = np.flatnonzero(clusters == k)
        x = result.means.detach().double().numpy()[mine]
        centre = x.mean(0)
        radius = float(np.percentile(np.linalg.norm(x - centre, axis=1), 90)) + 1e-9
        normal = R[k].T @ (up / S[k])  # the style's up pulled back to the content
        normal /= np.linalg.norm(normal)
        side = np.cross(normal, [0.0, 0.0, 1.0] if abs(normal[2]) < 0.9 else [0.0, 1.0, 0.0])
        eye = centre + 4 * radius * normal
        up_c = np.cross(side, normal)

        def to_style(v):
            return S[k] * (R[k] @ (v - mu[k])) + p[k]

        f = size / 2 * 4 / 1.2  # the cluster's 90 % radius at 1 / 1.2 of the half frame
        # in the style, the same radius in the plane at the mapped distance: the same framing
        r_s = np.linalg.norm(to_style(centre + radius * side) - to_style(centre))
        d_s = np.linalg.norm(to_style(eye) - to_style(centre))
        tiles = []
        for scene, e, c, u, fx in ((result.subset(torch.from_numpy(mine)), eye, centre, up_c, f),
                                   (style.subset(torch.from_numpy(selected[mine])), to_style(eye), to_style(centre),
                                    S[k] * (R[k] @ up_c), f * d_s / (4 * r_s))):
            cam = Camera(look_at(e.tolist(), c.tolist(), u.tolist()), fx, fx, size / 2, size / 2, size, size)
            tiles.append(rasterize(scene, cam, background=(1.0, 1.0, 1.0)).rgb.clamp(0, 1).numpy())
        rows.append(np.concatenate(tiles, 1))
    half = (len(rows) + 1) // 2
    rows += [np.ones_like(rows[0])] * (2 * half - len(rows))
    img = np.concatenate([np.concatenate(rows[:half], 0), np.concatenate(rows[half:], 0)], 1)
    Image.fromarray((img * 255).astype(np.uint8)).save(out)


def measure(pair: str, method: str, partition: str, out_dir: Path, thickness: bool = False, copies: int = 0) -> dict:
    from wast3d.formats import read_scene
    from wast3d.stages import artifact

    content, style = pair.split("__")
    at = dict(content=content, style=style, method=method, partition=partition)
    s = read_scene(first(Path(artifact("style", RESULTS, scene=style)), Path(artifact("scene", RESULTS, scene=style))))
    if s.element is None:
        raise ValueError(f"{style}: the style has no element labels")
    selected = np.load(artifact("selection", RESULTS, **at))["indices"]
    st = np.load(artifact("stylize_npz", RESULTS, **at))
    comp = completeness(s.element.numpy(), selected, st["labels"])
    points = read_scene(first(Path(artifact("surface", RESULTS, scene=content)),
                              Path(artifact("scene", RESULTS, scene=content)))).means
    cl = np.load(artifact("clusters", RESULTS, **at))["labels"]
    reference = json.loads((Path(artifact("texture_reference", RESULTS, **at)) / "render.json").read_text())
    # the texture reference is rendered at the reference partition's s0: rescaled to this partition's
    s0 = json.loads(Path(artifact("registration", RESULTS, **at)).with_suffix(".json").read_text())["s0"]
    length = reference["element_length"] * reference["s0"] / s0
    span = cluster_span(points.double().numpy(), cl) / length
    result = read_scene(artifact("final", RESULTS, **at))
    if copies:
        copy_sheet(result, s, st["labels"], selected, Path(artifact("registration", RESULTS, **at)), copies,
                   out_dir / f"element_copies_{pair}_{method}_copies.png")
    copy_picture(result, st["labels"], Path(artifact("render_pair", RESULTS, **at)) / "render.json",
                 out_dir / f"element_copies_{pair}_{method}.png")
    row = {"pair": pair, "method": method, "clusters": len(span), "cluster_span_median": float(np.median(span)),
           "complete_median": float(np.median(comp)), "complete_0.5": float((comp >= 0.5).mean()),
           "complete_0.8": float((comp >= 0.8).mean())}
    if thickness:
        from wast3d.elements import element_diameter
        from wast3d.geometry import kdtree, local_thickness

        x = points.double().numpy()
        diameter = element_diameter(s.means, s.element) / s0
        on = np.flatnonzero(s.element.numpy()[selected] > 0)  # the result's element Gaussians, as comp
        pick = np.sort(np.random.default_rng(0).choice(on, min(4000, len(on)), replace=False))
        near = kdtree(x).query(result.means.detach().double().numpy()[pick])[1]
        thick = local_thickness(x, x[near])
        thin = thick < diameter
        c = comp[np.searchsorted(on, pick)]
        row.update({"element_diameter": diameter, "thin_share": float(thin.mean()),
                    "thickness_median_thin": _or_nan(np.median, thick[thin])})
        for name, f in (("median", lambda v: _or_nan(np.median, v)), ("0.5", lambda v: _or_nan(np.mean, v >= 0.5))):
            for side, at in (("thin", thin), ("thick", ~thin)):
                row[f"complete_{name}_{side}"] = f(c[at])
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("pairs", nargs="+", help="PAIR[:METHOD[:PARTITION]], e.g. guitar__stones_s20:default_c2:c2")
    ap.add_argument("--out", type=Path, default=OUT / "element_copies.csv")
    ap.add_argument("--thickness", action="store_true", help="split the completeness by the content's local "
                    "thickness against the element's diameter (slower: a ray per sampled copy Gaussian)")
    ap.add_argument("--copies", type=int, default=0, help="a sheet of this many clusters' copies beside the same "
                    "Gaussians in the style")
    a = ap.parse_args()
    rows = []
    for item in a.pairs:
        pair, method, partition = (item.split(":") + ["default", "default"])[:3]
        rows.append(measure(pair, method, partition, a.out.parent, a.thickness, a.copies))
        print(" ".join(f"{k} {v:.3f}" if isinstance(v, float) else f"{k} {v}" for k, v in rows[-1].items()), flush=True)
    write_rows(rows, a.out)


if __name__ == "__main__":
    main()

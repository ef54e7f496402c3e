"""The element metrics against controls, on the workflow's own results for each pair given:

- the collage (registration + selection, no optimization): element_intact 1 by construction;
- the result (default experiment), and with other k-means and registration seeds (``--seed-experiment``,
  studies/seeds: seeds-seed1) for the spread between seeds;
- confetti (negative): the result's Gaussians shuffled within each cluster, so that every position is
  still on the result but the element copies are torn apart; intact must fall to ~0;
- the unstylized content and the colour transfer (negatives): element_share 0.
- element_whole's known answers, on the style itself (its texture reference's cameras): every element
  cut in two by the median plane across its longest axis (its visible pieces halve: ratio ~0.5), in
  four by its two longest axes (~0.25); the confetti's pieces fall to a few pixels (ratio ~0).
- chips (negative): the result with every element copy flattened to a fifth of its height along its
  least-variance axis, in place (what a content thinner than an element makes of pebbles): intact
  must fall, and a style metric that sees whole elements must put it farther from the style.

Every control is also scored by the label-free whole-element metrics (element_colour_w1, element_thickness_w1,
wast3d.metrics), with the same verdict over their spread across metric seeds on ours (``--seeds``).

Every control is also scored label-free: ``segment_intact`` and ``segment_whole_ratio``, with the
style's relief basins (the texture reference's segments.npz) for elements (wast3d.elements); the
known answers hold for them where they hold for the labelled pair.

With ``--texture`` the style metrics that claim to see the style's texture (texture_swd, relief_w1)
face the same two controls: the confetti is rendered by the render stage's own function
(``pipeline.run_render``, the result's render settings and content reference) and scored by the
evaluate stage's functions against the pair's texture reference. A metric that sees elements must
put the collage (whole elements) closer to the style than the confetti (the same Gaussians, torn)
by >= 10x its spread over metric seeds (on ours: texture_swd's window and direction seeds on its
frames, relief_w1's centre seeds on its Gaussians); the verdict columns say whether it does.

    .venv/bin/python benchmarks/element_validation.py ant__pebbles ant__pebbles_trained [--seed-experiment seed1] [--texture]

reads results/eval/PAIR/METHOD.json (element_share_ratio, element_intact; run them through the workflow
first) and computes the confetti control with wast3d.elements; writes results/benchmarks/element_validation.csv.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import write_rows  # noqa: E402


def main(argv=None) -> None:
    from wast3d.elements import ElementConfig, copy_ids, element_intact, element_whole
    from wast3d.render import element_pieces, read_cameras
    from wast3d.io_utils import load_npz
    from wast3d.pipeline import piece_weight
    from wast3d.ply import read_ply
    from wast3d.stages import artifact

    ap = argparse.ArgumentParser()
    ap.add_argument("pairs", nargs="+")
    ap.add_argument("--seed-experiment", default="seed1")
    ap.add_argument("--results", type=Path, default=ROOT / "results")
    ap.add_argument("--texture", action="store_true", help="also render the confetti and score texture_swd, relief_w1")
    ap.add_argument("--seeds", type=int, default=5, help="texture_swd seeds for its spread (--texture)")
    a = ap.parse_args(argv)
    rows = []
    for pair in a.pairs:
        content, style = pair.split("__")
        for method, role in (("selected", "collage (positive)"), ("default", "ours"), ("no_parts", "ours without parts"),
                             (a.seed_experiment, "ours, other seeds"), ("input", "content (negative)"),
                             ("colour_ot", "colour transfer (negative)")):
            f = Path(artifact("eval", a.results, content=content, style=style, method=method))
            if not f.exists():
                continue
            m = json.loads(f.read_text())
            rows.append({"pair": pair, "control": role, "method": method, "element_share_ratio": m.get("element_share_ratio"),
                         "element_intact": m.get("element_intact"), "element_whole_ratio": m.get("element_whole_ratio"),
                         "segment_intact": m.get("segment_intact"), "segment_whole_ratio": m.get("segment_whole_ratio"),
                         "coverage": m.get("coverage"),
                         "texture_swd": m.get("texture_swd"), "relief_w1": m.get("relief_w1"),
                         **{k: m.get(k) for k in WHOLE}})
        ours = dict(results=a.results, content=content, style=style, experiment="default")
        res = read_ply(artifact("final", **ours))
        stylize_npz = Path(artifact("stylize_npz", **ours))
        ref_dir = Path(artifact("texture_reference", a.results, content=content, style=style))
        npz = load_npz(stylize_npz)
        clusters = torch.from_numpy(npz["labels"])
        # each copy's pixels counted at the texture reference's element size, as the evaluate stage counts ours
        weight = piece_weight(npz, stylize_npz, ref_dir)
        before = torch.from_numpy(npz["before_means"])
        g = torch.Generator().manual_seed(0)
        shuffled = res.means.clone()
        for c in clusters.unique():
            idx = (clusters == c).nonzero().squeeze(1)
            shuffled[idx] = res.means[idx[torch.randperm(len(idx), generator=g)]]
        cfg = ElementConfig()
        conf = element_intact(before, shuffled, copy_ids(res.element, clusters), cfg)
        own = json.loads(Path(artifact("eval", a.results, content=content, style=style, method="default")).read_text())
        whole_style = own["element_whole_style"]
        render_dir = Path(artifact("render_pair", a.results, content=content, style=style, method="default"))
        cams = read_cameras(render_dir, json.loads((render_dir / "render.json").read_text())["frames"])
        whole = element_whole(element_pieces(replace(res, means=shuffled), copy_ids(res.element, clusters), cams,
                                             cfg.piece_tol, cfg.min_alpha, weight)) or 0.0
        chips = flattened(res.means, copy_ids(res.element, clusters))
        sty = read_ply(own["style"])
        whole_rows = whole_controls(own, ref_dir, res, sty, {"confetti": replace(res, means=shuffled),
                                                             "chips": replace(res, means=chips)}, pair, rows, a.seeds)
        row = {"pair": pair, "control": "confetti (negative)", "method": "default, shuffled in each cluster",
               "element_share_ratio": None, "element_intact": conf["intact"],
               "element_whole_ratio": whole / whole_style, "coverage": None}
        if a.texture:
            row.update(texture_controls(a.results, pair, replace(res, means=shuffled), rows, a.seeds))
        row.update(whole_rows["confetti"])
        row.update(segment_scores(a.results, content, style, replace(res, means=shuffled), before, clusters, cams))
        rows.append(row)
        row = {"pair": pair, "control": "chips (negative)", "method": "default, each copy flattened to 1/5 height",
               "element_intact": element_intact(before, chips, copy_ids(res.element, clusters), cfg)["intact"],
               "element_whole_ratio": (element_whole(element_pieces(replace(res, means=chips), copy_ids(res.element, clusters),
                                                                    cams, cfg.piece_tol, cfg.min_alpha, weight)) or 0.0) / whole_style}
        if a.texture:
            row.update(texture_controls(a.results, pair, replace(res, means=chips), rows, a.seeds, "chips"))
        row.update(whole_rows["chips"])
        row.update(segment_scores(a.results, content, style, replace(res, means=chips), before, clusters, cams))
        rows.append(row)
        ref_cams = read_cameras(ref_dir, json.loads((ref_dir / "render.json").read_text())["frames"])
        for axes, role in ((1, "style, elements cut in two (known ~0.5)"), (2, "style, elements cut in four (~0.25)")):
            cut = cut_elements(sty.means, sty.element, axes)
            w = element_whole(element_pieces(sty, cut, ref_cams, cfg.piece_tol, cfg.min_alpha)) or 0.0
            row = {"pair": pair, "control": role, "method": "the style's texture reference",
                   "element_whole_ratio": w / whole_style}
            if own.get("segment_whole_style"):
                seg = torch.from_numpy(load_npz(ref_dir / "segments.npz")["segments"])
                w = element_whole(element_pieces(sty, cut_elements(sty.means, seg + 1, axes), ref_cams, cfg.piece_tol,
                                                 cfg.min_alpha)) or 0.0
                row["segment_whole_ratio"] = w / own["segment_whole_style"]
            rows.append(row)
    df = write_rows(rows, a.results / "benchmarks" / "element_validation.csv")
    print(df.to_string(index=False))


def segment_scores(results: Path, content: str, style: str, scene, before, clusters, cams) -> dict:
    """segment_intact and segment_whole_ratio of a control ``scene`` (the default result's Gaussians, moved):
    the evaluate stage's own function on the pair's texture reference and the default run's stylize npz."""
    from wast3d.elements import ElementConfig, element_intact, element_whole, segment_copies
    from wast3d.io_utils import load_npz
    from wast3d.pipeline import piece_weight
    from wast3d.render import element_pieces
    from wast3d.stages import artifact

    own = json.loads(Path(artifact("eval", results, content=content, style=style, method="default")).read_text())
    ref = Path(artifact("texture_reference", results, content=content, style=style))
    if not own.get("segment_whole_style") or not (ref / "segments.npz").exists():
        return {}
    cfg = ElementConfig()
    seg = torch.from_numpy(load_npz(ref / "segments.npz")["segments"])
    stylize_npz = Path(artifact("stylize_npz", results, content=content, style=style, experiment="default"))
    npz = load_npz(stylize_npz)
    copies = segment_copies(seg, torch.from_numpy(npz["source"]), clusters)
    whole = element_whole(element_pieces(scene, copies, cams, cfg.piece_tol, cfg.min_alpha,
                                         piece_weight(npz, stylize_npz, ref))) or 0.0
    return {"segment_intact": element_intact(before, scene.means, copies, cfg)["intact"],
            "segment_whole_ratio": whole / own["segment_whole_style"]}


def flattened(means: torch.Tensor, copies: torch.Tensor, height: float = 0.2) -> torch.Tensor:
    """[N, 3] with each copy (id >= 0) squashed to ``height`` of itself along its least-variance axis,
    about its centroid: chips of the same outline."""
    out = means.clone()
    for j in copies[copies >= 0].unique():
        idx = (copies == j).nonzero().squeeze(1)
        if len(idx) < 4:
            continue
        p = means[idx].double()
        c = p.mean(0)
        n = torch.linalg.eigh((p - c).T @ (p - c))[1][:, 0]
        along = (p - c) @ n
        out[idx] = (p - (1 - height) * along[:, None] * n).to(means.dtype)
    return out


def cut_elements(means: torch.Tensor, element: torch.Tensor, axes: int) -> torch.Tensor:
    """[N] copy ids with every element (label > 0) cut by the median planes across its ``axes`` longest
    principal axes (2 ** axes pieces each; the ground -1)."""
    out = torch.full_like(element.long(), -1)
    for j in element[element > 0].unique():
        idx = (element == j).nonzero().squeeze(1)
        p = means[idx].double() - means[idx].double().mean(0)
        vecs = torch.linalg.eigh(p.T @ p)[1].flip(1)[:, :axes]  # longest first
        proj = p @ vecs
        bits = (proj > proj.median(0).values).long() @ (2 ** torch.arange(axes))
        out[idx] = int(j) * 2 ** axes + bits
    return out


WHOLE = ("element_colour_w1", "element_thickness_w1")


def whole_controls(ours: dict, ref: Path, result, style, controls: dict, pair: str, rows: list[dict],
                   seeds: int) -> dict[str, dict]:
    """element_colour_w1 and element_thickness_w1 of each control scene (``controls``: name -> scene) by the
    evaluate stage's own function (the pair's texture reference ``ref``, the metrics settings of ours' eval
    JSON ``ours``), their spread over ``seeds`` metric seeds on ours (``result`` against ``style``, computed
    once for all controls), and each one's verdict (module docstring)."""
    import statistics

    from wast3d.metrics import MetricsConfig
    from wast3d.pipeline import evaluate_whole_elements

    mcfg = MetricsConfig(**ours["config"]["metrics"])
    own = [evaluate_whole_elements(result, style, ref, replace(mcfg, seed=k)) for k in range(seeds)]
    collage = next((r for r in rows if r["pair"] == pair and r["method"] == "selected"), {})
    out = {}
    for name, scene in controls.items():
        control, out[name] = evaluate_whole_elements(scene, style, ref, mcfg), {}
        for key in WHOLE:
            spread = statistics.stdev(o[key] for o in own) if seeds > 1 and control[key] is not None else float("nan")
            out[name].update({key: control[key], f"{key}_spread": spread,
                              f"{key}_verdict": verdict(collage.get(key), control[key], spread, name)})
    return out


def verdict(pos, neg, spread, name: str) -> str:
    """A metric sees the control if it puts it farther from the style than the collage by >= 10x its spread."""
    if pos is None or neg is None:
        return "no collage to compare"
    return "valid" if neg - pos >= 10 * spread else f"invalid: {name} - collage = {neg - pos:.3g} < 10 x spread"


def texture_controls(results: Path, pair: str, confetti, rows: list[dict], seeds: int, name: str = "confetti") -> dict:
    """texture_swd and relief_w1 of the confetti scene (rendered as the pair's result was), the spread of
    texture_swd over ``seeds`` on ours' frames, and each metric's verdict (module docstring)."""
    import statistics
    import tempfile

    from wast3d.image_metrics import TextureConfig, texture_levels
    from wast3d.metrics import MetricsConfig, relief_w1
    from wast3d.pipeline import run_render
    from wast3d.ply import read_ply, write_ply
    from wast3d.render import read_frames
    from wast3d.stages import artifact

    names = dict(zip(("content", "style"), pair.split("__")))
    ours = json.loads(Path(artifact("eval", results, **names, method="default")).read_text())
    render_dir = Path(artifact("render_pair", results, **names, method="default"))
    params = json.loads((render_dir / "render.json").read_text())["config"]
    tcfg = TextureConfig(**ours["config"]["texture"])
    reference = read_frames(artifact("texture_reference", results, **names))
    with tempfile.TemporaryDirectory(prefix="wast3d_confetti_") as tmp:
        ply = Path(tmp) / "confetti.ply"
        write_ply(ply, confetti)
        run_render(scene=ply, reference=Path(ours["content"]), out_folder=Path(tmp) / "render", params=params,
                   progress=False)
        frames = read_frames(Path(tmp) / "render")
    tex = texture_levels(frames, reference, tcfg)["texture_swd"]
    mcfg = MetricsConfig(**ours["config"]["metrics"])
    style = read_ply(ours["style"]).means
    relief = relief_w1(confetti.means, style, mcfg)
    own = read_frames(render_dir)
    swds = [texture_levels(own, reference, replace(tcfg, seed=k))["texture_swd"] for k in range(seeds)]
    result = read_ply(ours["result"]).means
    reliefs = [relief_w1(result, style, replace(mcfg, seed=k)) for k in range(seeds)]
    spread = statistics.stdev(swds) if seeds > 1 else float("nan")
    relief_spread = statistics.stdev(reliefs) if seeds > 1 else float("nan")
    collage = next((r for r in rows if r["pair"] == pair and r["method"] == "selected"), {})
    return {"texture_swd": tex, "relief_w1": relief, "texture_swd_spread": spread, "relief_w1_spread": relief_spread,
            "texture_swd_verdict": verdict(collage.get("texture_swd"), tex, spread, name),
            "relief_w1_verdict": verdict(collage.get("relief_w1"), relief, relief_spread, name)}


if __name__ == "__main__":
    main()

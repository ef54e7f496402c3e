"""Several styles on one content, by region: the regions' parsing and assignment, the clusters cut at a
border, the seam metrics against their control, and the whole workflow on a tiny scene."""

import copy
import json

import numpy as np
import pytest
import yaml

from wast3d.regions import (Region, assign, band_coverage, band_of, colour_groups, parse_set, read_labels,
                            seam_density, split_clusters)


def test_a_region_set_is_parsed_strictly():
    regs = parse_set([{"style": "a", "box": {"min": [0, 0, 0], "max": [1, 1, 1]}}, {"style": "b", "rest": True}], "r")
    assert [r.kind for r in regs] == ["box", "rest"]
    bad = [
        ([{"style": "a", "rest": True}], "two regions or more"),
        ([{"style": "a", "rest": True}, {"style": "b", "box": {"min": [0, 0, 0], "max": [1, 1, 1]}}], "'rest' is the last"),
        ([{"style": "a", "box": {"min": [0, 0], "max": [1, 1, 1]}}, {"style": "b", "rest": True}], "3 finite numbers"),
        ([{"style": "a", "box": {"min": [2, 0, 0], "max": [1, 1, 1]}}, {"style": "b", "rest": True}], "min must not exceed"),
        ([{"style": "a", "half_space": {"normal": [0, 0, 0], "offset": 0}}, {"style": "b", "rest": True}], "not be zero"),
        ([{"style": "a", "colour": {"groups": 2, "take": [5]}}, {"style": "b", "rest": True}], "take ids below"),
        ([{"style": "a", "box": {}, "rest": True}, {"style": "b", "rest": True}], "exactly one of"),
        ([{"box": {"min": [0, 0, 0], "max": [1, 1, 1]}}, {"style": "b", "rest": True}], "needs 'style'"),
    ]
    for entries, message in bad:
        with pytest.raises(ValueError, match=message):
            parse_set(entries, "regions.x.styles")


def test_the_first_region_that_claims_a_point_wins_and_every_point_needs_one():
    x = np.array([[0.0, 0, -1], [0, 0, 1], [0, 0, 2], [5, 5, -5]])
    rgb = np.zeros((4, 3))
    regs = [Region("a", "half_space", {"normal": [0, 0, 1], "offset": 0.5}),
            Region("b", "box", {"min": [-1, -1, -2], "max": [1, 1, 3]}), Region("c", "rest", {})]
    assert assign(x, rgb, regs).tolist() == [1, 0, 0, 2]
    with pytest.raises(ValueError, match="1 of 4 content points lie in no region"):
        assign(x, rgb, regs[:2])
    with pytest.raises(ValueError, match=r"regions\[1\] \(b, box\): claims no content point"):
        assign(x, rgb, [regs[0], Region("b", "box", {"min": [9, 9, 9], "max": [9, 9, 9]}), regs[2]])
    dark, light = np.full((5, 3), 0.1), np.full((5, 3), 0.9)
    assert colour_groups(np.concatenate([light, dark]), 2).tolist() == [1] * 5 + [0] * 5  # numbered by luminance


def test_label_files_are_checked_against_the_scene(tmp_path):
    np.save(tmp_path / "l.npy", np.array([0, 1, 1]))
    assert read_labels(str(tmp_path / "l.npy"), 3).tolist() == [0, 1, 1]
    with pytest.raises(ValueError, match="3 labels of type int64 for a scene of 4 Gaussians"):
        read_labels(str(tmp_path / "l.npy"), 4)
    (tmp_path / "l.txt").write_text("0\n2\nx\n")
    with pytest.raises(ValueError, match="not a label file"):
        read_labels(str(tmp_path / "l.txt"), 3)


def test_a_cluster_the_border_crosses_becomes_one_on_each_side():
    labels = np.array([0, 0, 0, 0, 1, 1, 1, 1, 2, 2, 2])
    region = np.array([0, 0, 1, 1, 0, 0, 0, 0, 1, 1, 1])
    idx, lab, rep = split_clusters(labels, region, 0, min_size=1)
    assert idx.tolist() == [0, 1, 4, 5, 6, 7] and lab.tolist() == [0, 0, 1, 1, 1, 1]
    assert rep["clusters_cut_by_the_border"] == 1 and rep["clusters"] == 2
    idx, lab, rep = split_clusters(labels, region, 1, min_size=3)  # a piece of 2 joins its region's other piece
    assert idx.tolist() == [2, 3, 8, 9, 10] and len(set(lab.tolist())) == 1 and rep["pieces_merged"] == 1


def test_the_seam_metrics_score_a_result_of_one_style_as_its_control():
    g = np.random.default_rng(0)
    uv = g.uniform(0, 1, (4000, 2))
    pts = np.c_[uv, np.zeros(4000)]  # a plane, cut in two at x = 0.5
    region = (pts[:, 0] >= 0.5).astype(int)
    band = band_of(pts, region, 0.05)
    assert 0.05 < band.mean() < 0.15
    style = np.c_[g.uniform(0, 1, (6000, 2)), np.zeros(6000)]
    same = seam_density(pts, region, band, style, {0: style, 1: style})
    assert all(abs(v["density_ratio"] - 1) < 1e-12 for v in same.values())  # one style: 1 by construction
    gap = style[np.abs(style[:, 0] - 0.5) > 0.06]  # a gap along the seam
    assert all(v["density_ratio"] < 0.5 for v in seam_density(pts, region, band, gap, {0: style, 1: style}).values())
    doubled = np.concatenate([style, style[np.abs(style[:, 0] - 0.5) <= 0.05]])  # a doubled layer
    assert all(v["density_ratio"] > 1.5 for v in seam_density(pts, region, band, doubled, {0: style, 1: style}).values())
    import torch

    a = torch.ones(1, 4, 4)
    share = torch.zeros(1, 4, 4)
    share[0, :, :2] = 1
    hole = a.clone()
    hole[0, 0, 0] = 0
    assert band_coverage(a, a, share) == 1.0 and band_coverage(hole, a, share) == 7 / 8
    assert band_coverage(a, a, torch.zeros(1, 4, 4)) is None


def regions_config() -> dict:
    """The tiny config (tests/test_workflow.py) with a set of two regions on its torus: pebbles above
    z = 0, grass below."""
    from test_workflow import TINY

    cfg = copy.deepcopy(TINY)
    cfg.pop("sweeps")
    cfg["scenes"]["grs"] = {"source": "procedural", "kind": "style", "name": "grass", "n_gaussians": 3000}
    cfg["pairs"] = [["blob", "peb"]]
    cfg["table1"] = {"pairs": [], "methods": {"default": "ours"}}
    cfg["regions"] = {"mix": {"content": "blob", "styles": [
        {"style": "peb", "half_space": {"normal": [0, 0, 1], "offset": 0.0}}, {"style": "grs", "rest": True}]}}
    return cfg


def test_regions_reuse_the_single_style_run(tiny_run, tmp_path):
    """Over the tiny run (the torus with pebbles alone), the regions' DAG runs no k-means again and clusters
    again only where the grass, which the single-style run never saw, needs its own registration input."""
    from conftest import copy_of_tiny_run
    from test_workflow import jobs, snake

    wd = copy_of_tiny_run(tiny_run, tmp_path / "wf")
    assert jobs(snake(wd, "-n", "--", "results/stylize/blob__peb/default/final.ply", config=regions_config())) == {}
    todo = jobs(snake(wd, "-n", "--", "results/tables/regions.csv"))
    assert "cluster" not in todo and "procedural_scene" in todo and todo["region_clusters"] == 2  # grass only
    assert todo["merge_regions"] == 1 and todo["seams"] == 1 and todo["regions_table"] == 1


@pytest.mark.slow  # about 40 jobs, 2 minutes: `pytest -m slow`
def test_two_styles_on_a_tiny_content_through_the_workflow(tiny_run, tmp_path):
    """A torus, pebbles above z = 0 and grass below, through the workflow, from the tiny run's results (the
    torus with pebbles alone): the content's k-means is the one a single style uses (nothing upstream
    re-runs for the regions), each region's Gaussians come from its style and lie over its region, the
    merged result counts both, and the seams hold the bar."""
    from conftest import copy_of_tiny_run
    from test_workflow import jobs, snake

    from wast3d.geometry import kdtree
    from wast3d.ply import read_ply

    wd = copy_of_tiny_run(tiny_run, tmp_path / "wf")
    assert jobs(snake(wd, "-n", "--", "results/stylize/blob__peb/default/final.ply", config=regions_config())) == {}
    todo = jobs(snake(wd, "-n", "--", "results/tables/regions.csv"))
    assert "cluster" not in todo and "procedural_scene" in todo and todo["region_clusters"] == 2  # grass only
    snake(wd, "--", "results/tables/regions.csv")
    r = wd / "results"
    region = np.load(r / "regions/mix/regions.npz")["region"]
    content = read_ply(r / "scenes/blob/scene.ply")
    assert len(region) == len(content) and set(region.tolist()) == {0, 1}
    assert ((content.means[:, 2].numpy() >= 0) == (region == 0)).all()
    merged = read_ply(r / "stylize/blob__mix/default/final.ply")
    parts = json.loads((r / "stylize/blob__mix/default/final.json").read_text())["parts"]
    assert [p["style"] for p in parts] == ["peb", "grs"] and sum(p["gaussians"] for p in parts) == len(merged)
    for k, st in enumerate(("peb", "grs")):
        part = read_ply(r / f"stylize/mix-{k}__{st}/default/final.ply")
        own = region[kdtree(content.means.numpy()).query(part.means.numpy())[1]] == k
        assert own.mean() > 0.9, (st, own.mean())  # its Gaussians over its own region
    # a region's elements come out as large as the style alone makes them on the whole content
    s0 = {c: json.loads((r / f"register/{c}__peb/default/registration.json").read_text())["s0"] for c in ("blob", "mix-0")}
    assert s0["mix-0"] == pytest.approx(s0["blob"], rel=1e-9), s0
    seams = json.loads((r / "eval/blob__mix/default_seams.json").read_text())
    assert seams["coverage_band"] >= min(seams["coverage_band_alone"]) - 0.05
    for v in seams["regions"].values():
        assert 1 / 1.5 <= v["density_ratio"] <= 1.5, seams["regions"]
    table = (r / "tables/regions.md").read_text()
    assert "| blob | mix | 0 | peb |" in table and "| blob | mix | 1 | grs |" in table
    yaml.safe_load((wd / "config/config.yaml").read_text())


def test_a_label_header_claiming_more_labels_than_the_scene_is_refused_unread(tmp_path):
    import struct

    h = "{'descr': '<i8', 'fortran_order': False, 'shape': (100000000000,), }"
    h += " " * (118 - len(h)) + "\n"
    (tmp_path / "big.npy").write_bytes(b"\x93NUMPY\x01\x00" + struct.pack("<H", len(h)) + h.encode() + bytes(80))
    with pytest.raises(ValueError, match=r"big\.npy: header: 100000000000 labels of type int64 for a scene of 10"):
        read_labels(str(tmp_path / "big.npy"), 10)
    np.save(tmp_path / "f.npy", np.zeros(10, np.float32))
    with pytest.raises(ValueError, match="of type float32"):
        read_labels(str(tmp_path / "f.npy"), 10)


def test_a_regions_file_names_its_labels_beside_itself_and_takes_no_yes_no(tmp_path):
    from wast3d.quickstart import regions_file

    (tmp_path / "segs").mkdir()
    f = tmp_path / "segs" / "regions.yaml"
    f.write_text("- {style: 0, labels: {path: seg.npy, take: [1]}}\n- {style: 1, rest: true}\n")
    entries = regions_file(f, ["a", "b"], [tmp_path / "a.ply", tmp_path / "b.ply"])
    assert entries[0]["labels"]["path"] == str(tmp_path / "segs" / "seg.npy") and entries[0]["style"] == "a"
    f.write_text("- {style: true, rest: true}\n- {style: 1, rest: true}\n")
    with pytest.raises(ValueError, match="yes/no"):
        regions_file(f, ["a", "b"], [tmp_path / "a.ply", tmp_path / "b.ply"])
    with pytest.raises(ValueError, match="offset: a finite number"):
        Region.parse({"style": "a", "half_space": {"normal": [0, 0, 1], "offset": "abc"}}, "r")
    with pytest.raises(ValueError, match="3 finite numbers"):
        Region.parse({"style": "a", "box": {"min": [False, 0, 0], "max": [True, 1, 1]}}, "r")

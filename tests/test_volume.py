"""Styles that are objects (wast3d.volume): the patch-or-volume test, the element sheet, and the style and
stylize stages reading a volume through it."""

import json
import logging

import numpy as np
import pytest
import torch

from wast3d.procedural import make_scene
from wast3d.volume import FLAT, element_axes, element_sheet, style_form, thickness


@pytest.mark.parametrize("name, form", [("pebbles", "patch"), ("grass", "patch"), ("wicker", "patch"),
                                        ("stones", "patch"), ("bouquet", "volume"), ("pinecone", "volume")])
def test_the_form_is_read_from_the_scene(name, form):
    s = make_scene("style", name, 4000, seed=0)
    f = style_form(s.means.numpy())
    assert f.form == form, f
    assert (f.thickness < FLAT) == (form == "patch")
    # far from the bar either way: a patch below half of it, a volume above twice it
    assert f.thickness < 0.5 * FLAT if form == "patch" else f.thickness > 2 * FLAT
    assert style_form(s.means.numpy(), "patch" if form == "volume" else "volume").reason.startswith("asked")


def test_the_workflow_knows_which_procedural_styles_are_volumes():
    """common.smk sends the procedural volumes through the style stage by this list (it reads no scene):
    it must be exactly the generator's styles that the form test reads as volumes."""
    from wast3d.procedural import STYLES
    from wast3d.volume import PROCEDURAL_VOLUMES

    read = {n for n in STYLES if style_form(make_scene("style", n, 3000, seed=0).means.numpy()).form == "volume"}
    assert read == set(PROCEDURAL_VOLUMES)


def test_thickness_is_the_least_extent_over_the_middle_one():
    g = np.random.default_rng(0)
    slab = g.uniform(-1, 1, (4000, 3)) * [3.0, 2.0, 0.2]  # a long strip: e_3 / e_2 = 0.1, whatever e_1
    assert thickness(slab) == pytest.approx(0.1, rel=0.05)
    rod = g.uniform(-1, 1, (4000, 3)) * [3.0, 0.5, 0.5]  # a rod (a pine cone): not flat
    assert thickness(rod) == pytest.approx(1.0, rel=0.1)
    rotated = slab @ torch.linalg.qr(torch.randn(3, 3, generator=torch.Generator().manual_seed(1)))[0].numpy().T
    assert thickness(rotated) == pytest.approx(thickness(slab), rel=1e-6)
    with pytest.raises(ValueError, match="too few"):
        thickness(slab[:3])
    with pytest.raises(ValueError, match="must be one of"):
        style_form(slab, "blob")


@pytest.mark.parametrize("name", ["bouquet", "pinecone"])
def test_the_sheet_lays_every_element_out_whole_outer_side_up(name):
    s = make_scene("style", name, 6000, seed=0)
    el = element_axes(s.means.double().numpy(), s.element.numpy())
    sheet, report = element_sheet(s)
    assert report["elements"] == len(el.ids) and report["left_off_unlabelled"] == int((s.element == 0).sum())
    assert len(sheet) == int((s.element > 0).sum()) and bool((sheet.element > 0).all())
    assert style_form(sheet.means.numpy()).form == "patch"  # what every later stage reads
    for u, axis in zip(el.ids[:12], el.axes):
        a, b = s.means[s.element == u].double(), sheet.means[sheet.element == u].double()
        torch.testing.assert_close(torch.cdist(a, a), torch.cdist(b, b), atol=1e-4, rtol=1e-4)  # rigid
        before = torch.linalg.svd(a - a.mean(0), full_matrices=False)[2][2]
        after = torch.linalg.svd(b - b.mean(0), full_matrices=False)[2][2]
        assert abs(float(after[2])) > 0.999  # its least-variance axis is now the sheet's up
        # and the side that faced out faces up: the element's outward offset, turned, has a positive height
        R = torch.linalg.lstsq(a - a.mean(0), b - b.mean(0)).solution.T
        assert float((R @ torch.as_tensor(axis))[2]) > 0.99
        assert abs(float(before @ torch.as_tensor(axis))) > 0.999
    # side by side: neighbouring centres about a pitch apart, the sheet one element thick
    centres = torch.stack([sheet.means[sheet.element == u].mean(0) for u in el.ids])
    d = torch.cdist(centres[:, :2], centres[:, :2]) + 1e9 * torch.eye(len(centres))
    assert float(d.min(1).values.median()) == pytest.approx(report["pitch"], rel=0.2)


def test_a_sheet_needs_labels():
    s = make_scene("style", "bouquet", 3000, seed=0)
    s.element = None
    with pytest.raises(ValueError, match="no element labels"):
        element_sheet(s)


def test_the_style_stage_reads_a_volume_through_its_sheet(tmp_path, caplog):
    from wast3d.pipeline import run_style_clean
    from wast3d.ply import read_ply, write_ply

    write_ply(tmp_path / "bouquet.ply", make_scene("style", "bouquet", 4000, seed=0))
    with caplog.at_level(logging.INFO):
        run_style_clean(scene=tmp_path / "bouquet.ply", out_ply=tmp_path / "style.ply", out_json=tmp_path / "style.json",
                        params={})
    report = json.loads((tmp_path / "style.json").read_text())
    assert report["form"] == "volume" and report["thickness"] > FLAT and "sheet" in report
    assert "removed_hidden" not in report and "removed_below_ground" not in report  # no ground, every side seen
    assert "style form: volume" in caplog.text and "laid side by side" in caplog.text
    sheet = read_ply(tmp_path / "style.ply")
    assert report["sheet"]["gaussians"] == len(sheet) and style_form(sheet.means.numpy()).form == "patch"
    # a patch is cleaned as before: the ground and visibility tests run, no sheet
    write_ply(tmp_path / "pebbles.ply", make_scene("style", "pebbles", 4000, seed=0))
    run_style_clean(scene=tmp_path / "pebbles.ply", out_ply=tmp_path / "p.ply", out_json=tmp_path / "p.json", params={})
    p = json.loads((tmp_path / "p.json").read_text())
    assert p["form"] == "patch" and "removed_hidden" in p and "sheet" not in p
    # asked to read the pebbles as a volume: laid out by their labels
    run_style_clean(scene=tmp_path / "pebbles.ply", out_ply=tmp_path / "v.ply", out_json=tmp_path / "v.json",
                    params={"form": "volume"})
    assert json.loads((tmp_path / "v.json").read_text())["form_reason"].startswith("asked")
    # a volume without labels: its elements are label-free pieces, every Gaussian on the sheet
    unlabelled = make_scene("style", "pinecone", 3000, seed=0)
    unlabelled.element = None
    write_ply(tmp_path / "cone.ply", unlabelled)
    run_style_clean(scene=tmp_path / "cone.ply", out_ply=tmp_path / "c.ply", out_json=tmp_path / "c.json", params={})
    c = json.loads((tmp_path / "c.json").read_text())
    assert c["elements_from"] == "pieces" and c["sheet"]["left_off_unlabelled"] == 0
    assert c["sheet"]["gaussians"] == len(read_ply(tmp_path / "c.ply"))
    assert c["sheet"]["gaussians"] + c["sheet"]["left_off_small_elements"] == c["kept"]
    assert c["sheet"]["left_off_small_elements"] < 0.02 * c["kept"]


def test_label_free_pieces_are_about_an_element_across():
    """On the bouquet the pieces come out about a flower each: most of a piece's labelled Gaussians are of one
    flower, and the median flower lies mostly in one piece."""
    from wast3d.volume import piece_size, volume_pieces

    s = make_scene("style", "bouquet", 6000, seed=0)
    piece = volume_pieces(s.means.numpy(), s.rgb.numpy())
    assert piece.min() == 1 and len(np.unique(piece)) == piece.max()
    lab = s.element.numpy()
    on = lab > 0
    joint = np.zeros((piece.max() + 1, lab.max() + 1))
    np.add.at(joint, (piece[on], lab[on]), 1)
    big = joint.sum(1) >= 20
    purity = joint.max(1)[big] / joint.sum(1)[big]
    held = joint.max(0)[1:] / np.maximum(joint.sum(0)[1:], 1)
    assert np.median(purity) > 0.8 and np.median(held) > 0.6, (np.median(purity), np.median(held))
    assert 0.5 < piece_size(s.means.numpy()) / 0.2 < 2.0  # the flowers are about 0.2 across


def test_a_volume_whose_labels_hold_no_element_is_an_error_naming_the_file(tmp_path):
    from wast3d.pipeline import run_style_clean
    from wast3d.ply import write_ply

    s = make_scene("style", "bouquet", 3000, seed=0)
    s.element = torch.zeros_like(s.element)  # every Gaussian "stem": nothing to lay out
    write_ply(tmp_path / "stems.ply", s)
    with pytest.raises(ValueError, match=r"stems\.ply: read as a volume .*no element of 3 Gaussians"):
        run_style_clean(scene=tmp_path / "stems.ply", out_ply=tmp_path / "o.ply", out_json=tmp_path / "o.json", params={})
    assert not (tmp_path / "o.ply").exists() and not (tmp_path / "o.json").exists()


def test_a_sheet_flows_element_by_element():
    from wast3d.stylize import StylizeConfig, flow_parts

    sheet, _ = element_sheet(make_scene("style", "bouquet", 4000, seed=0))
    part = flow_parts(sheet, "z", StylizeConfig(), sheet=True)
    assert int(part.max()) + 1 == len(torch.unique(sheet.element))
    for p in torch.unique(part):  # a part is one element
        assert len(torch.unique(sheet.element[part == p])) == 1
    assert flow_parts(sheet, "z", StylizeConfig(parts={"size": 0.0}), sheet=True) is None  # parts off: off


def test_a_volume_is_exported_from_every_side(tmp_path):
    from wast3d.cameras import scene_bounds
    from wast3d.render import EXPORT_ELEVATIONS, VOLUME_ELEVATIONS, export_blender

    for name, lowest in (("pinecone", min(VOLUME_ELEVATIONS)), ("pebbles", min(EXPORT_ELEVATIONS))):
        scene = make_scene("style", name, 2000, seed=0)
        export_blender(scene, tmp_path / name, n_views=10, size=16)
        frames = json.loads((tmp_path / name / "transforms_train.json").read_text())["frames"]
        pos = np.array([np.array(f["transform_matrix"])[:3, 3] for f in frames])
        centre = np.asarray(scene_bounds(scene)[0])
        elev = np.degrees(np.arcsin((pos[:, 2] - centre[2]) / np.linalg.norm(pos - centre, axis=1)))
        assert elev.min() == pytest.approx(lowest, abs=3.0), (name, elev)


def test_the_share_ratio_is_not_read_on_a_sheet():
    """Every Gaussian of a sheet is an element, so the element share of any result of it is 1: the
    evaluation says so instead of scoring it; a patch (its ground label 0) keeps the ratio."""
    from wast3d.elements import share_blind

    sheet, _ = element_sheet(make_scene("style", "bouquet", 3000, seed=0))
    assert "volume's sheet" in share_blind(sheet.element)
    assert share_blind(make_scene("style", "pebbles", 3000, seed=0).element) is None


def test_the_texture_reference_segments_a_sheet_by_its_laid_out_elements(tmp_path):
    """A volume read without labels (its elements label-free pieces): the texture reference writes one
    segment per laid-out element, what segment_intact and segment_whole read; without the style's report
    and without a registration (no relief length) it writes none."""
    from wast3d.io_utils import load_npz
    from wast3d.pipeline import run_style_clean, run_texture_reference
    from wast3d.ply import read_ply, write_ply

    cone = make_scene("style", "pinecone", 2000, seed=0)
    cone.element = None
    write_ply(tmp_path / "cone.ply", cone)
    write_ply(tmp_path / "c.ply", make_scene("content", "torus", 500))
    run_style_clean(scene=tmp_path / "cone.ply", out_ply=tmp_path / "s.ply", out_json=tmp_path / "s.json", params={})
    params = {"frames": 1, "size": 32, "key_views": 1}
    run_texture_reference(style=tmp_path / "s.ply", content=tmp_path / "c.ply", out_folder=tmp_path / "rx",
                          params=params, progress=False, style_form=tmp_path / "s.json")
    seg = load_npz(tmp_path / "rx" / "segments.npz")
    sheet = read_ply(tmp_path / "s.ply")
    assert str(seg["how"]).startswith("laid-out elements") and len(seg["segments"]) == len(sheet)
    assert seg["segments"].max() + 1 == len(np.unique(sheet.element.numpy())) > 10
    run_texture_reference(style=tmp_path / "s.ply", content=tmp_path / "c.ply", out_folder=tmp_path / "ry",
                          params=params, progress=False)
    assert not (tmp_path / "ry" / "segments.npz").exists()


def test_by_default_a_sheet_comes_out_in_whole_element_copies_and_a_patch_as_set():
    """Null copies, follow_thickness and element_scale are set by the style's form: on a sheet every
    element copy a cluster keeps is its whole element (completed from 30 %, dropped below), each over its
    own cluster, at a smaller element scale; explicit values win; a patch keeps copies and follow off."""
    from wast3d.pair import partition, stylize_partition
    from wast3d.registration import RegistrationConfig, by_form
    from wast3d.stylize import SHEET_COPIES, StylizeConfig, resolved_copies

    sheet, patch = by_form(RegistrationConfig(), sheet=True), by_form(RegistrationConfig(), sheet=False)
    assert (sheet.follow_thickness, sheet.element_scale) == (0.5, 0.045)
    assert (patch.follow_thickness, patch.element_scale) == (0.0, 0.062)
    assert by_form(RegistrationConfig(follow_thickness=0.0, element_scale=0.05), sheet=True).follow_thickness == 0.0
    assert by_form(RegistrationConfig(element_scale=0.05), sheet=True).element_scale == 0.05
    on_sheet = resolved_copies(StylizeConfig(), sheet=True).copies
    assert {k: getattr(on_sheet, k) for k in SHEET_COPIES} == SHEET_COPIES
    assert resolved_copies(StylizeConfig(), sheet=False).copies.trim == 0.0
    assert resolved_copies(StylizeConfig(copies={"trim": 0.2}), sheet=True).copies.trim == 0.2

    sheet, _ = element_sheet(make_scene("style", "bouquet", 4000, seed=0))
    content = make_scene("content", "torus", 1500, seed=0)
    params = {"cluster": {"n_clusters": 6}, "register": {"landings": 1, "yaws": 2, "iterations": 4,
                                                          "refine_iterations": 4}, "stylize": {"iterations": 2}}
    size = torch.bincount(sheet.element.long())

    def copies(sheet_flag):
        part = partition(content, sheet, params, sheet=sheet_flag)
        res = stylize_partition(part, content, sheet, params, sheet=sheet_flag).stylized
        el = sheet.element.long()[res.source]
        m = int(el.max()) + 1
        key, n = torch.unique(res.labels.long() * m + el, return_counts=True)  # (cluster, element) copies
        held = n.double() / size[key % m].double()
        return held, part

    held, part = copies(True)
    thinned = bool((part.selection.log_gain != 0).any())
    assert not thinned and bool((held == 1).all()), held[held < 1][:10]  # every copy its whole element
    held_patch, _ = copies(False)
    assert bool((held_patch < 1).any())  # read as a patch, the footprints cut flowers

"""Element labels (procedural styles, PLY round trip, selection/stylize/rescale) and the element metrics."""

import math
import numpy as np
import pytest
import torch
from conftest import random_scene

from wast3d.elements import (ElementConfig, copy_codes, copy_ids, element_diameter, element_intact, element_pixels,
                             element_share, element_whole, label_colours, piece_areas, segment_copies,
                             transfer_elements)
from wast3d.gaussians import GaussianScene
from wast3d.ply import PlyError, read_ply, write_ply
from wast3d.procedural import style_scene


@pytest.mark.parametrize("name,ground", [("pebbles", True), ("grass", True), ("wicker", False), ("stones", True)])
def test_procedural_styles_label_every_gaussian_by_element(name, ground):
    s = style_scene(name, 6000)
    e = s.element
    assert e is not None and e.shape == (len(s),) and int(e.min()) >= 0
    assert bool((e == 0).any()) == ground  # the ground is 0; a weave has none
    # each element is one compact thing: its Gaussians lie closer together than the patch is wide
    for j in e.unique()[e.unique() > 0][:5]:
        p = s.means[e == j]
        assert float((p - p.mean(0)).norm(dim=1).max()) < 1.0 if name != "wicker" else True


def test_element_labels_round_trip_through_ply_and_are_optional(tmp_path):
    s = style_scene("pebbles", 3000)
    write_ply(tmp_path / "a.ply", s)
    r = read_ply(tmp_path / "a.ply")
    assert torch.equal(r.element, s.element)
    plain = random_scene(50)
    write_ply(tmp_path / "b.ply", plain)
    assert read_ply(tmp_path / "b.ply").element is None
    # a scene without labels is written in the reference layout: no extra property
    assert b"property int element" not in (tmp_path / "b.ply").read_bytes()[:2000]
    assert b"property int element" in (tmp_path / "a.ply").read_bytes()[:2000]


def test_negative_labels_name_the_file_and_property(tmp_path):
    s = style_scene("pebbles", 2000)
    s.element = s.element.clone()
    s.element[3] = -1
    write_ply(tmp_path / "bad.ply", s)
    with pytest.raises(PlyError, match=r"bad\.ply.*'element'.*negative"):
        read_ply(tmp_path / "bad.ply")


def test_labels_follow_subset_concat_and_transform():
    s = style_scene("stones", 3000)
    idx = torch.tensor([5, 1, 900, 17])
    assert torch.equal(s.subset(idx).element, s.element[idx])
    assert torch.equal(s.subset(s.element > 0).element, s.element[s.element > 0])
    both = GaussianScene.concat([s.subset(idx), s.subset(idx)])
    assert torch.equal(both.element, s.element[idx].repeat(2))
    R = torch.tensor([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    assert torch.equal(s.transform(R, torch.ones(3), torch.tensor([1.0, 2.0, 0.5])).element, s.element)
    # a part without labels drops them all (a half-labelled result would mislead the metrics)
    assert GaussianScene.concat([s.subset(idx), random_scene(4)]).element is None
    with pytest.raises(ValueError, match="element"):
        GaussianScene(**s.tensors(), element=s.element[:-1])


def test_transfer_takes_the_nearest_source_label():
    s = style_scene("pebbles", 4000)
    g = torch.Generator().manual_seed(0)
    jitter = s.means + 1e-4 * torch.randn(s.means.shape, generator=g)
    assert torch.equal(transfer_elements(jitter, s.means, s.element), s.element)


def _camera_above():
    """A 128 px camera 3 units above the origin, looking down -z."""
    from wast3d.cameras import Camera, look_at

    return Camera(look_at(torch.tensor([0.0, 0.0, 3.0]), torch.zeros(3), torch.tensor([0.0, 1.0, 0.0])),
                  fx=100.0, fy=100.0, cx=64.0, cy=64.0, width=128, height=128)


def test_element_share_of_rendered_label_channel():
    from wast3d.rasterizer import rasterize

    s = style_scene("pebbles", 6000)
    cam = _camera_above()
    def share(scene):
        m = rasterize(scene, cam, colors=label_colours(scene.element))
        return element_share(element_pixels(m.rgb, m.alpha)[None], m.alpha[None])
    full = share(s)
    assert 0.4 < full < 0.95  # pebbles over sand, seen from above
    assert share(s.subset(s.element == 0)) == 0.0  # the ground alone: no element pixel
    assert share(s.subset(s.element > 0)) > 0.97  # the pebbles alone
    with pytest.raises(ValueError, match="no foreground"):
        element_share(torch.zeros(1, 4, 4), torch.zeros(1, 4, 4))


def test_piece_areas_count_connected_pixels_of_one_copy_and_leave_blends_out():
    copies = torch.tensor([-1, 0, 1])
    cols, codes = copy_codes(copies, dtype=torch.float64)
    assert torch.equal(cols[0], torch.zeros(6)) and codes.shape == (2, 6)
    img = torch.zeros(8, 8, 6, dtype=torch.float64)
    img[:, :3] = codes[0]          # copy 0: 24 pixels
    img[:, 5:] = codes[1]          # copy 1: 24 pixels, not touching copy 0
    img[:4, 3] = 0.5 * (codes[0] + codes[1])  # a blend of both: in no piece
    img[4:, 3:5] = codes[0]         # copy 0 again, joined to its first piece along rows 4..7: 32 pixels
    img[7, 4] = 0.9 * codes[0] + 0.1 * codes[1]  # copy 1 weighs 0.1 < tol: still copy 0's
    el, alpha = torch.ones(8, 8), torch.ones(8, 8)
    el[:4, 4] = 0                   # the ground
    a = piece_areas(img, el, alpha, codes, tol=0.25)
    assert sorted(np.unique(a).tolist()) == [24, 32]
    assert len(a) == 8 * 8 - 4 - 4  # every pixel but the blend and the ground
    assert element_whole([a]) == pytest.approx((32 * 32 + 24 * 24) / 56)
    # the codes scaled by a pixel's element weight read the same (the copy is seen through a haze)
    assert np.array_equal(piece_areas(img * 0.48, el * 0.6, alpha * 0.8, codes, tol=0.25), a)
    assert element_whole([]) is None


def test_element_whole_halves_for_cut_elements_and_falls_for_confetti():
    from wast3d.render import element_pieces

    s = style_scene("pebbles", 6000)
    cam = _camera_above()
    whole_copies = torch.where(s.element > 0, s.element.long(), -1)
    whole = element_whole(element_pieces(s, whole_copies, [cam], tol=0.25))
    # every pebble cut in two across x through its centre: pieces half as large
    centre = torch.zeros(int(s.element.max()) + 1, 3).index_add_(0, s.element.long(), s.means)
    centre = centre / torch.bincount(s.element.long()).clamp_min(1)[:, None]
    halves = torch.where(s.element > 0, 2 * s.element.long() + (s.means[:, 0] > centre[s.element.long(), 0]).long(), -1)
    half = element_whole(element_pieces(s, halves, [cam], tol=0.25))
    assert 0.3 < half / whole < 0.6  # half, less the seam's blended pixels (0.39 here)
    # the same Gaussians with their positions shuffled among the pebbles: no piece larger than a few pixels
    g = torch.Generator().manual_seed(0)
    idx = (s.element > 0).nonzero().squeeze(1)
    means = s.means.clone()
    means[idx] = s.means[idx[torch.randperm(len(idx), generator=g)]]
    from dataclasses import replace
    confetti = element_whole(element_pieces(replace(s, means=means), whole_copies, [cam], tol=0.25))
    assert confetti / whole < 0.1


def test_element_whole_of_elements_made_smaller_on_purpose_counts_them_at_full_size():
    """A copy f times the size (follow_thickness) shows f^2 the pixels; weighted 1 / f^2 it reads whole."""
    from dataclasses import replace

    from wast3d.render import element_pieces

    s = style_scene("pebbles", 6000)
    cam = _camera_above()
    copies = torch.where(s.element > 0, s.element.long(), -1)
    whole = element_whole(element_pieces(s, copies, [cam], tol=0.25))
    small = replace(s, means=0.5 * s.means, log_scales=s.log_scales + math.log(0.5))  # the patch half as wide
    unweighted = element_whole(element_pieces(small, copies, [cam], tol=0.25))
    weighted = element_whole(element_pieces(small, copies, [cam], tol=0.25, area_weight=torch.full((len(s),), 4.0)))
    assert 0.15 < unweighted / whole < 0.35  # a quarter of the pixels
    assert 0.8 < weighted / whole < 1.25


def _copies(n_el=6, per=40, seed=0):
    """Element copies as random blobs: positions [N, 3], copy ids [N]."""
    g = torch.Generator().manual_seed(seed)
    centres = torch.randn(n_el, 3, generator=g) * 3
    x = (centres[:, None] + 0.3 * torch.randn(n_el, per, 3, generator=g)).reshape(-1, 3)
    return x, torch.arange(n_el).repeat_interleave(per)


def test_element_intact_controls():
    cfg = ElementConfig()
    x, ids = _copies()
    same = element_intact(x, x, ids, cfg)
    assert same["intact"] == 1.0 and same["copies"] == 6  # the collage: whole by construction
    R = torch.linalg.qr(torch.randn(3, 3, generator=torch.Generator().manual_seed(1)))[0]
    moved = torch.cat([x[ids == j] @ R.T + 5 * j for j in range(6)])
    assert element_intact(x, moved, ids, cfg)["intact"] == 1.0  # each copy moved rigidly: intact
    g = torch.Generator().manual_seed(2)
    confetti = x[torch.randperm(len(x), generator=g)]
    assert element_intact(x, confetti, ids, cfg)["intact"] < 0.05  # Gaussians shuffled between elements
    assert element_intact(x, x * torch.tensor([1.0, 1.0, 0.2]), ids, cfg)["intact"] < 0.6  # squashed
    small = x + 0.03 * torch.randn(x.shape, generator=g)  # jitter of 10 % of an element's size
    assert element_intact(x, small, ids, cfg)["intact"] > 0.9
    # the ground (-1) and slivers below min_size are left out
    ids2 = ids.clone()
    ids2[:40] = -1
    assert element_intact(x, x, ids2, cfg)["copies"] == 5
    assert element_intact(x[:3], x[:3], ids[:3], cfg)["intact"] is None


def test_copy_ids_separate_clusters_and_the_ground():
    el = torch.tensor([0, 1, 1, 2, 1])
    cl = torch.tensor([0, 0, 1, 1, 1])
    c = copy_ids(el, cl)
    assert c[0] == -1 and c[1] != c[2] and c[2] == c[4] and c[3] != c[4]


def test_element_diameter_of_pebbles():
    s = style_scene("pebbles", 20000)
    d = element_diameter(s.means, s.element)
    assert 0.15 < d < 0.4  # radii 0.08-0.18 in a 2 x 2 patch
    with pytest.raises(ValueError, match="no element"):
        element_diameter(s.means[:3], torch.zeros(3, dtype=torch.long))


def test_segment_copies_take_the_source_gaussians_segment_per_cluster():
    segments = torch.tensor([0, 0, 1, 2])
    source = torch.tensor([1, 0, 2, 2, 3])
    clusters = torch.tensor([0, 0, 0, 1, 1])
    c = segment_copies(segments, source, clusters)
    assert (c >= 0).all() and c[0] == c[1] and c[1] != c[2] and c[2] != c[3] and c[3] != c[4]
    with pytest.raises(ValueError, match="source indices outside the style's 4 Gaussians"):
        segment_copies(segments, torch.tensor([4]), torch.tensor([0]))


def test_segment_whole_of_relief_basins_sees_cuts_and_confetti_without_labels():
    """The label-free segments on a patch of pebbles: the relief's basins score like the labelled pebbles
    on the known controls (halves ~0.5 of whole, confetti ~0)."""
    from dataclasses import replace

    from wast3d.registration import relief_basins, relief_length
    from wast3d.render import element_pieces

    s = style_scene("pebbles", 6000)
    cam = _camera_above()
    seg = relief_basins(s.means, "z", relief_length(s.means))
    whole = element_whole(element_pieces(s, seg, [cam], tol=0.25))
    labelled = element_whole(element_pieces(s, torch.where(s.element > 0, s.element.long(), -1), [cam], tol=0.25))
    assert 0.5 < whole / labelled < 3  # a basin: its pebble and the ground around it
    centre = torch.zeros(int(seg.max()) + 1, 3).index_add_(0, seg, s.means) / torch.bincount(seg)[:, None]
    halves = 2 * seg + (s.means[:, 0] > centre[seg, 0]).long()
    assert 0.3 < element_whole(element_pieces(s, halves, [cam], tol=0.25)) / whole < 0.65
    means = s.means[torch.randperm(len(s), generator=torch.Generator().manual_seed(0))]
    assert element_whole(element_pieces(replace(s, means=means), seg, [cam], tol=0.25)) / whole < 0.1


def test_piece_weights_count_each_copy_at_the_texture_references_size(tmp_path):
    import json

    from wast3d.pipeline import piece_weight

    (tmp_path / "render.json").write_text(json.dumps({"size_factor": 0.25}))
    d = {"size_factor": np.array([1.0, 0.25]), "labels": np.array([0, 1, 1])}
    w = piece_weight(d, tmp_path / "stylize.npz", tmp_path)
    assert torch.allclose(w, torch.tensor([1 / 16, 1.0, 1.0], dtype=torch.float64))  # a full-size copy: 16x the pixels
    assert piece_weight({"labels": d["labels"]}, tmp_path / "stylize.npz", tmp_path) is None  # an older file
    (tmp_path / "render.json").write_text(json.dumps({"size_factor": 1.0}))
    assert piece_weight({"size_factor": np.ones(2), "labels": d["labels"]}, tmp_path / "stylize.npz", tmp_path) is None
    with pytest.raises(ValueError, match="stylize.npz: 'size_factor'"):
        piece_weight({"size_factor": np.array([1.0, np.nan]), "labels": d["labels"]}, tmp_path / "stylize.npz", tmp_path)

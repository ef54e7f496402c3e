"""Stages 7-9: renders (turntable, close-ups, depth, normals), CLIP crop similarity with a tiny random
open_clip model, the weights-free metrics, the colour-transfer baseline and Table 1."""

import json
import math

import numpy as np
import pytest
import torch
from conftest import random_scene, write_tiny_clip

from wast3d.cameras import Camera, look_at
from wast3d.clip_eval import (ClipConfig, ClipUnavailable, CropConfig, clip_similarity, embed, load_clip,
                              random_crops)
from wast3d.gaussians import GaussianScene, quat_multiply
from wast3d.metrics import (MetricsConfig, chamfer, content_chamfer, element_metrics, principal_frames, style_metrics,
                            weights_free_metrics)
from wast3d.procedural import make_scene
from wast3d.geometry import knn


def frames_with_blob(V=3, H=40, W=50, seed=0):
    """RGBA frames [V, H, W, 4] with an opaque disc in each (random colours)."""
    g = torch.Generator().manual_seed(seed)
    f = torch.zeros(V, H, W, 4)
    ys, xs = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    for v in range(V):
        disc = ((ys - 20) ** 2 + (xs - 15 - 5 * v) ** 2) < 12**2
        f[v, ..., :3] = torch.rand(H, W, 3, generator=g)
        f[v, ..., 3] = disc.float()
    return f


# ---- crops -----------------------------------------------------------------------------------


def test_crops_are_deterministic_by_seed_and_on_the_foreground():
    f = frames_with_blob()
    cfg = CropConfig(count=12, size=8, min_alpha=0.9, seed=3)
    a, ba = random_crops(f, cfg)
    b, bb = random_crops(f, cfg)
    assert torch.equal(a, b) and torch.equal(ba, bb)
    c, bc = random_crops(f, CropConfig(count=12, size=8, min_alpha=0.9, seed=4))
    assert not torch.equal(ba, bc)
    assert a.shape == (12, 8, 8, 3)
    for v, y, x in ba.tolist():
        assert f[v, y:y + 8, x:x + 8, 3].mean() >= 0.9
        w = f[v, y:y + 8, x:x + 8]
        on_white = w[..., :3] * w[..., 3:] + (1 - w[..., 3:])
        assert torch.allclose(a[list(map(tuple, ba.tolist())).index((v, y, x))], on_white)


def test_crops_errors():
    f = frames_with_blob()
    with pytest.raises(ValueError, match="exceeds the frame size"):
        random_crops(f, CropConfig(size=64))
    f[..., 3] = 0
    with pytest.raises(ValueError, match="no foreground"):
        random_crops(f, CropConfig(count=2, size=8))


# ---- CLIP ------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def tiny_clip(tmp_path_factory):
    return write_tiny_clip(tmp_path_factory.mktemp("clip"))


def test_clip_tiny_model_end_to_end_and_checkpoint_round_trip(tiny_clip):
    import open_clip

    cfg_path, ckpt = tiny_clip
    torch.manual_seed(0)
    fresh = open_clip.create_model("wast3d-tiny-clip", pretrained=None).eval()  # the same random init
    loaded = load_clip(ClipConfig(model="wast3d-tiny-clip", checkpoint=str(ckpt), model_config=str(cfg_path)))
    crops_a, _ = random_crops(frames_with_blob(seed=0), CropConfig(count=6, size=16))
    crops_b, _ = random_crops(frames_with_blob(seed=1), CropConfig(count=5, size=16, seed=1))
    ea = embed(loaded, crops_a)
    assert ea.shape == (6, 16) and torch.allclose(ea.norm(dim=1), torch.ones(6, dtype=ea.dtype))
    assert torch.allclose(ea, embed(fresh, crops_a), atol=1e-6)  # weights really came from the file
    s_ab, s_ba = clip_similarity(loaded, crops_a, crops_b), clip_similarity(loaded, crops_b, crops_a)
    assert math.isfinite(s_ab) and -100 <= s_ab <= 100 and s_ab == pytest.approx(s_ba, abs=1e-9)
    ea, eb = embed(loaded, crops_a), embed(loaded, crops_b)
    assert s_ab == pytest.approx(100 * float((ea @ eb.T).mean()), abs=1e-9)
    # a different random model gives different embeddings: the checkpoint is what decides
    torch.manual_seed(1)
    other = open_clip.create_model("wast3d-tiny-clip", pretrained=None).eval()
    assert not torch.allclose(embed(other, crops_a), ea, atol=1e-3)


def test_clip_unavailable_is_reported_never_downloaded(tmp_path, tiny_clip):
    with pytest.raises(ClipUnavailable, match="no clip.checkpoint"):
        load_clip(ClipConfig())
    with pytest.raises(ClipUnavailable, match="is not a file"):
        load_clip(ClipConfig(checkpoint=str(tmp_path / "missing.pt")))
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="bad.pt"):
        load_clip(ClipConfig(model="wast3d-tiny-clip", checkpoint=str(bad), model_config=str(tiny_clip[0])))
    with pytest.raises(ValueError, match="unknown open_clip architecture"):
        load_clip(ClipConfig(model="no-such-net", checkpoint=str(tiny_clip[1])))


# ---- weights-free metrics --------------------------------------------------------------------

SMALL = MetricsConfig(patches=24, candidates=48, patch_size=12, patch_stride=2, rotations=4, colour_points=512)


@pytest.fixture(scope="module")
def pebbles():
    return make_scene("style", "pebbles", 3000, seed=0)


def test_metrics_are_zero_for_identical_inputs(pebbles):
    m = weights_free_metrics(pebbles, pebbles.means, pebbles, SMALL)
    assert m["content_chamfer"] == 0
    for k in ("style_patch_chamfer", "tilt_w1_deg", "aniso_w1"):
        assert m[k] == 0, k
    for k in ("style_patch_sinkhorn", "colour_sinkhorn"):
        assert abs(m[k]) < 1e-6, k
    # at the default (patches 0) the patch metrics are not computed
    d = weights_free_metrics(pebbles, pebbles.means, pebbles, MetricsConfig(colour_points=512))
    assert d["style_patch_chamfer"] is None and d["style_patch_sinkhorn"] is None and d["tilt_w1_deg"] == 0


def perturb(scene: GaussianScene, what: str, amount: float, seed=1) -> GaussianScene:
    g = torch.Generator().manual_seed(seed)
    s = scene.clone()
    n = len(s)
    if what == "means":
        h = float(content_spacing(scene))
        s.means = s.means + amount * h * torch.randn(n, 3, generator=g)
    elif what == "rotation":  # random rotations of angle ~amount (radians)
        axis = torch.randn(n, 3, generator=g)
        axis = axis / axis.norm(dim=1, keepdim=True)
        half = 0.5 * amount * torch.rand(n, 1, generator=g)
        q = torch.cat([half.cos(), axis * half.sin()], 1)
        s.quats = quat_multiply(q, s.quats)
    elif what == "scale":
        s.log_scales = s.log_scales + amount * torch.randn(n, 3, generator=g)
    elif what == "colour":
        s.sh_dc = s.sh_dc + amount * torch.randn(n, 3, generator=g)
    return s


def content_spacing(scene):
    from wast3d.geometry import knn_mean_dist

    return knn_mean_dist(scene.means.double(), 1).mean()


@pytest.mark.parametrize("what, keys", [
    ("means", ("content_chamfer", "style_patch_chamfer", "style_patch_sinkhorn")),
    ("rotation", ("tilt_w1_deg",)),
    ("scale", ("aniso_w1",)),
    ("colour", ("colour_sinkhorn",)),
])
def test_metrics_grow_with_perturbation(pebbles, what, keys):
    vals = []
    for amount in (0.0, 0.3, 1.5):
        r = perturb(pebbles, what, amount)
        vals.append(weights_free_metrics(r, pebbles.means, pebbles, SMALL))
    for k in keys:
        v = [x[k] for x in vals]
        assert v[0] < 1e-6 and v[0] < v[1] < v[2], (k, v)


def _bumpy_sphere(n: int, amplitude: float, freq: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    u = torch.randn(n, 3, generator=g, dtype=torch.float64)
    u = u / u.norm(dim=1, keepdim=True)
    r = 1 + amplitude * torch.sin(freq * u[:, 0]) * torch.sin(freq * u[:, 1]) * torch.sin(freq * u[:, 2])
    return u * r[:, None]


def test_gaussian_smooth_removes_relief_below_sigma():
    from wast3d.geometry import gaussian_smooth

    g = torch.Generator().manual_seed(0)
    xy = torch.rand(6000, 2, generator=g, dtype=torch.float64) * 4
    z = 0.05 * torch.sin(2 * math.pi * xy[:, 0] / 0.2)  # ripples of wavelength 0.2
    pts = torch.cat([xy, z[:, None]], 1)
    inner = ((xy > 1) & (xy < 3)).all(1)
    flat = gaussian_smooth(pts, pts, 0.1)
    # relief at sigma's scale averaged away (sampling noise of ~50 points per kernel is what remains)
    assert flat[inner, 2].abs().mean() < 0.25 * z[inner].abs().mean()
    assert (flat[inner, :2] - xy[inner]).norm(dim=1).mean() < 0.03  # points stay about where they were
    plane = torch.cat([xy, torch.zeros(len(xy), 1, dtype=torch.float64)], 1)
    assert gaussian_smooth(plane, plane, 0.1)[:, 2].abs().max() == 0
    far = torch.tensor([[100.0, 0.0, 0.0]], dtype=torch.float64)  # no support within 2 sigma: kept
    assert torch.equal(gaussian_smooth(far, plane, 0.1), far)
    with pytest.raises(ValueError, match="sigma must be > 0"):
        gaussian_smooth(plane, plane, 0.0)


def test_coarse_chamfer_ignores_relief_and_sees_shape():
    from wast3d.metrics import coarse_chamfer, surface_distance

    content = _bumpy_sphere(6000, 0.0, 1)
    L = 0.5  # the element length: bumps of about this size are relief, not shape
    relief = _bumpy_sphere(9000, 0.08, 12, seed=1)  # bumps about 0.5 wide, 0.08 high, at another density
    larger = 1.06 * _bumpy_sphere(6000, 0.0, 1, seed=2)
    blob = _bumpy_sphere(6000, 0.0, 1, seed=3) * torch.tensor([1.6, 1.0, 0.6], dtype=torch.float64)  # an ellipsoid
    same = coarse_chamfer(_bumpy_sphere(6000, 0.0, 1, seed=4), content, L)
    bumps = coarse_chamfer(relief, content, L)
    plain_bumps = content_chamfer(relief, content)
    assert same < 0.3 and bumps < 1.0 < plain_bumps
    assert coarse_chamfer(larger, content, L) > 2 * bumps
    assert coarse_chamfer(blob, content, L) > 2 * coarse_chamfer(larger, content, L)
    # point-to-surface: a sparser sample of the same surface is as close as a dense one
    sparse = _bumpy_sphere(1500, 0.0, 1, seed=5)
    assert surface_distance(sparse, content).mean() < 0.5 * knn(sparse, content, 1)[0].mean() + 1e-3
    with pytest.raises(ValueError, match="smoothing length"):
        coarse_chamfer(content, content, 0.0)


def test_chamfer_and_patch_normalization_invariances():
    g = torch.Generator().manual_seed(0)
    x = torch.randn(200, 3, generator=g, dtype=torch.float64)
    # a shift far below the point spacing: every nearest neighbour is the point's own copy
    assert chamfer(x, x) == 0 and chamfer(x, x + 1e-4) == pytest.approx(1e-4 * math.sqrt(3), rel=1e-6)
    assert content_chamfer(2 * x, 2 * x + 2e-4) == pytest.approx(content_chamfer(x, x + 1e-4), rel=1e-6)  # spacing units
    p = torch.randn(5, 30, 3, generator=g, dtype=torch.float64) * torch.tensor([3.0, 1.0, 0.2], dtype=torch.float64)
    q, _ = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=torch.float64))
    moved = 7.0 * p @ q.T + torch.tensor([1.0, -2.0, 5.0], dtype=torch.float64)
    assert torch.allclose(principal_frames(p), principal_frames(moved), atol=1e-9)  # position, scale, rotation


def test_style_metrics_tell_styles_apart(pebbles):
    """Compared to pebbles, the grass scene (tilted blades, green) is further than pebbles of another seed."""
    other = make_scene("style", "pebbles", 3000, seed=5)
    grass = make_scene("style", "grass", 3000, seed=0)
    mo, mg = style_metrics(other, pebbles, SMALL), style_metrics(grass, pebbles, SMALL)
    for k in ("tilt_w1_deg", "colour_sinkhorn", "style_patch_chamfer"):
        assert mg[k] > mo[k], (k, mg[k], mo[k])


# ---- colour-transfer baseline ----------------------------------------------------------------


def test_colour_transfer_keeps_geometry_and_matches_the_style_colours():
    from wast3d.baselines import ColourTransferConfig, colour_map, colour_transfer
    from wast3d.sinkhorn import SinkhornConfig, exact_w2, sinkhorn

    content, style = make_scene("content", "torus", 1500, seed=0), make_scene("style", "grass", 3000, seed=0)
    out = colour_transfer(content, style, ColourTransferConfig())
    for k in ("means", "log_scales", "quats", "opacity_logits", "sh_rest"):
        assert torch.equal(getattr(out, k), getattr(content, k)), k
    S = lambda a, b: float(sinkhorn(a.double(), b.double(), SinkhornConfig(blur=0.02), grad_y=False).value)  # noqa: E731
    assert S(out.rgb, style.rgb) < 0.1 * S(content.rgb, style.rgb)
    # the map's transport cost is the exact OT cost (POT's network simplex), up to the entropic blur
    g = torch.Generator().manual_seed(0)
    x = torch.rand(400, 3, generator=g, dtype=torch.float64)
    y = torch.rand(400, 3, generator=g, dtype=torch.float64) * 0.5 + 0.3
    T = colour_map(x, y, ColourTransferConfig(blur=0.01, extra_iters=50))
    cost = float(((x - T) ** 2).sum(1).mean() / 2)
    assert cost == pytest.approx(exact_w2(x, y), rel=0.05)


def test_colour_transfer_rejects_empty_scenes():
    from wast3d.baselines import ColourTransferConfig, colour_transfer

    with pytest.raises(ValueError, match="empty scene"):
        colour_transfer(GaussianScene.empty(), random_scene(10), ColourTransferConfig())


# ---- rendering extras ------------------------------------------------------------------------


def test_closeup_is_a_crop_of_the_zoomed_render():
    from wast3d.cameras import fit_orbit
    from wast3d.render import closeup_camera
    from wast3d.rasterizer import rasterize

    scene = random_scene(300, seed=2)
    cam = fit_orbit(scene, 1, 40)[0]
    cu = closeup_camera(cam, (25, 14), 2.0)
    full = rasterize(scene, cam.scaled(2.0), background=(1.0, 1.0, 1.0)).rgb
    crop = rasterize(scene, cu, background=(1.0, 1.0, 1.0)).rgb
    x0, y0 = round(cam.cx * 2 - cu.cx), round(cam.cy * 2 - cu.cy)
    assert (x0, y0) == (31, 9) and crop.shape == (40, 40, 3)
    assert torch.allclose(crop, full[y0:y0 + 40, x0:x0 + 40], atol=1e-5)
    # closeup_size: the same fragment at twice the pixels (a crop of the render at 4x)
    big = closeup_camera(cam, (25, 14), 2.0, size=80)
    full4 = rasterize(scene, cam.scaled(4.0), background=(1.0, 1.0, 1.0)).rgb
    crop2 = rasterize(scene, big, background=(1.0, 1.0, 1.0)).rgb
    x1, y1 = round(cam.cx * 4 - big.cx), round(cam.cy * 4 - big.cy)
    assert (x1, y1) == (2 * x0, 2 * y0) and crop2.shape == (80, 80, 3)
    assert torch.allclose(crop2, full4[y1:y1 + 80, x1:x1 + 80], atol=1e-5)


def test_fragment_pixel_is_on_the_foreground():
    from wast3d.render import fragment_pixel

    a = torch.zeros(30, 40)
    a[5:10, 2:8] = 1  # two blobs: the centroid falls between them, on the background
    a[20:25, 30:38] = 1
    x, y = fragment_pixel(a)
    assert a[y, x] == 1
    assert fragment_pixel(torch.zeros(30, 40)) == (20, 15)


def plane_scene(n=400, tilt_deg=0.0):
    """Flat Gaussians on the plane z = x tan(tilt), normals along the plane's normal."""
    g = torch.Generator().manual_seed(0)
    t = math.radians(tilt_deg)
    uv = torch.rand(n, 2, generator=g) * 2 - 1
    means = torch.stack([uv[:, 0] * math.cos(t), uv[:, 1], uv[:, 0] * math.sin(t)], 1)
    half = -t / 2  # rotate about y so the flat (z) axis follows the plane's normal
    quats = torch.tensor([math.cos(half), 0.0, math.sin(half), 0.0]).expand(n, 4).clone()
    return GaussianScene.from_activated(means, torch.tensor([0.08, 0.08, 0.005]).expand(n, 3).clone(), quats,
                                        torch.full((n,), 0.99), torch.full((n, 3), 0.5))


@pytest.mark.parametrize("mode", ["axis", "depth"])
def test_normals_of_a_plane(mode):
    from wast3d.render import RenderConfig, render_maps

    scene = plane_scene(3000, tilt_deg=30.0)
    eye = torch.tensor([0.0, 0.0, 4.0], dtype=torch.float64)
    cam = Camera(look_at(eye, torch.zeros(3, dtype=torch.float64), up=(0.0, 1.0, 0.0)), 60.0, 60.0, 32, 32, 64, 64)
    m = render_maps(scene, cam, RenderConfig(normals=mode, size=64, frames=1, key_views=1))
    R = cam.world_to_cam[:3, :3].float()
    n_world = torch.tensor([-math.sin(math.radians(30)), 0.0, math.cos(math.radians(30))])
    expect = R @ n_world
    expect = -expect if expect[2] > 0 else expect  # facing the camera
    inner = (m.alpha > 0.99)[4:-4, 4:-4]
    got = m.normal[4:-4, 4:-4][inner]
    got = got[got.norm(dim=1) > 0.5]  # depth normals are 0 where a neighbour is background
    assert len(got) > 500
    cos = (got / got.norm(dim=1, keepdim=True) @ expect).median()
    assert cos > 0.99, float(cos)


def test_render_turntable_artifacts_and_sheet(tmp_path):
    import imageio.v3 as iio

    from wast3d.figures import comparison_sheet
    from wast3d.render import RenderConfig, read_frames, render_turntable

    scene = make_scene("content", "torus", 800)
    cfg = RenderConfig(frames=6, size=48, key_views=2, closeup_zoom=2)
    info = render_turntable(scene, scene, tmp_path / "a", cfg)
    assert info["key_frames"] == [0, 3]
    fr = read_frames(tmp_path / "a")
    assert fr.shape == (6, 48, 48, 4) and float(fr[..., 3].max()) == 1.0
    gif = iio.imread(tmp_path / "a" / "turntable.gif", index=None)
    assert gif.shape[0] == 6 and gif.shape[1] <= 48 and gif.shape[2] <= 48  # cropped to where the torus turns
    import imageio_ffmpeg  # the MP4 beside it: H.264, yuv420p, the same frames

    reader = imageio_ffmpeg.read_frames(str(tmp_path / "a" / "turntable.mp4"))
    meta = next(reader)
    assert meta["size"][0] >= gif.shape[2] and meta["size"][0] <= gif.shape[2] + 1 and meta["codec"] == "h264" and meta["pix_fmt"].startswith("yuv420p")
    assert sum(1 for _ in reader) == 6
    for name in ("key_00_rgb", "key_01_normal", "closeup_rgb", "closeup_depth", "closeup_normal"):
        assert iio.imread(tmp_path / "a" / f"{name}.png").shape[:2] == (48, 48)
    json.loads((tmp_path / "a" / "render.json").read_text())
    # the same reference -> the same cameras for another scene
    info2 = render_turntable(make_scene("content", "sphere", 500), scene, tmp_path / "b", cfg)
    assert info2["cameras"] == info["cameras"]
    comparison_sheet([("a", tmp_path / "a"), ("b", tmp_path / "b")], tmp_path / "sheet.png", tile=64)
    sheet = iio.imread(tmp_path / "sheet.png")
    assert sheet.shape[1] == 180 + 3 * 64 and sheet.shape[0] == 30 + 2 * 64  # a row per folder, a tile per picture
    from wast3d.figures import turntable_page, write_mp4

    (tmp_path / "b" / "turntable.mp4").unlink()  # a folder without an MP4 shows its GIF
    turntable_page([("ours <a>", tmp_path / "a"), ("b", tmp_path / "b")], tmp_path / "page.html")
    page = (tmp_path / "page.html").read_text()
    assert page.count("data:video/mp4;base64,") == 1 and page.count("data:image/gif;base64,") == 1
    assert "ours &lt;a&gt;" in page
    with pytest.raises(FileNotFoundError, match="neither turntable.mp4"):
        turntable_page([("x", tmp_path)], tmp_path / "none.html")
    odd = np.zeros((3, 33, 41, 3), np.uint8)  # odd sizes: padded by one edge pixel for yuv420p
    assert write_mp4(tmp_path / "odd.mp4", odd, 4.0)
    assert next(imageio_ffmpeg.read_frames(str(tmp_path / "odd.mp4")))["size"] == (42, 34)
    with pytest.raises(FileNotFoundError, match="no turntable frames"):
        read_frames(tmp_path)


# ---- evaluate stage and Table 1 ----------------------------------------------------------------


def test_evaluate_stage_with_and_without_clip(tmp_path, tiny_clip):
    from wast3d.pipeline import run_evaluate, run_render, run_texture_reference
    from wast3d.ply import write_ply

    content, style = make_scene("content", "torus", 800), make_scene("style", "pebbles", 1500)
    write_ply(tmp_path / "c.ply", content)
    write_ply(tmp_path / "s.ply", style)
    rp = {"frames": 3, "size": 48, "key_views": 1}
    run_render(scene=tmp_path / "c.ply", reference=tmp_path / "c.ply", out_folder=tmp_path / "rc", params=rp, progress=False)
    run_render(scene=tmp_path / "s.ply", reference=tmp_path / "s.ply", out_folder=tmp_path / "rs", params=rp, progress=False)
    run_texture_reference(style=tmp_path / "s.ply", content=tmp_path / "c.ply", out_folder=tmp_path / "rx", params=rp,
                          progress=False)

    def evaluate(result, result_render, out, params):
        run_evaluate(result=tmp_path / result, content=tmp_path / "c.ply", style=tmp_path / "s.ply",
                     result_render=tmp_path / result_render, style_render=tmp_path / "rs",
                     texture_reference=tmp_path / "rx", content_render=tmp_path / "rc", out_json=tmp_path / out,
                     params=params)

    small = {"patches": 8, "candidates": 16, "patch_size": 8, "rotations": 2, "colour_points": 128}
    base = {"metrics": small, "crops": {"count": 4, "size": 16}, "texture": {"windows": 64, "levels": 1, "min_windows": 8}}
    evaluate("c.ply", "rc", "none.json", base)
    ev = json.loads((tmp_path / "none.json").read_text())
    assert ev["clip_similarity"] is None and ev["clip_status"].startswith("not computed: no clip.checkpoint")
    # the texture reference had no registration, so no element length: the coarse Chamfer says why not
    assert ev["coarse_chamfer"] is None and "no element_length" in ev["coarse_status"]
    assert ev["content_chamfer"] == 0 and ev["style_patch_chamfer"] > 0
    assert ev["coverage"] == 1.0 and ev["texture_swd"] > 0 and ev["relief_w1"] > 0
    clip = {"model": "wast3d-tiny-clip", "checkpoint": str(tiny_clip[1]), "model_config": str(tiny_clip[0])}
    evaluate("c.ply", "rc", "clip.json", {**base, "clip": clip})
    ev = json.loads((tmp_path / "clip.json").read_text())
    assert ev["clip_status"] == "computed" and -100 <= ev["clip_similarity"] <= 100
    evaluate("c.ply", "rc", "coarse.json", {**base, "metrics": {**small, "coarse_scale": 0.1}})
    ev = json.loads((tmp_path / "coarse.json").read_text())
    assert ev["coarse_chamfer"] < 0.2 and "metrics.coarse_scale" in ev["coarse_status"] and ev["coarse_length"] > 0
    # a collapsed result (what entropic OT without debiasing does at a large blur): no crop has enough
    # foreground; evaluate still writes its metrics, coverage says how little is left, crops say why not
    c0 = content.means.mean(0)
    write_ply(tmp_path / "tiny.ply", content.transform(translation=c0 - 0.02 * c0, scale=0.02))
    run_render(scene=tmp_path / "tiny.ply", reference=tmp_path / "c.ply", out_folder=tmp_path / "rt", params=rp,
               progress=False)
    evaluate("tiny.ply", "rt", "tiny.json", base)
    ev = json.loads((tmp_path / "tiny.json").read_text())
    assert ev["coverage"] < 0.1 and ev["texture_swd"] is None and ev["crops"]["result"] == 0
    assert "5x5 windows inside the foreground" in ev["texture_status"] and "result 0" in ev["texture_status"] and "no crop with mean alpha" in ev["clip_status"]
    assert ev["content_chamfer"] > 1
    with pytest.raises(ValueError, match="evaluate.metrics: unknown parameter.*patchez"):
        evaluate("c.ply", "rc", "x.json", {"metrics": {"patchez": 3}})
    assert not (tmp_path / "x.json").exists()


def test_table1_row_reads_eval_and_benchmarks(tmp_path):
    from wast3d.tables import table1_row, write_table

    r = tmp_path / "results"
    (r / "eval/c__s").mkdir(parents=True)
    (r / "benchmarks/rules").mkdir(parents=True)
    (r / "stylize/c__s/e").mkdir(parents=True)
    (r / "eval/c__s/e.json").write_text(json.dumps({"clip_similarity": None, "clip_status": "not computed: x",
                                                    "content_chamfer": 1.5, "gaussians": 10}))
    (r / "stylize/c__s/e/losses.json").write_text(json.dumps({"device": "cpu"}))
    head = "s\th:m:s\tmax_rss\tmax_vms\tmax_uss\tmax_pss\tio_in\tio_out\tmean_load\tcpu_time\n"
    for name, s, mem in (("register_c__s_p", 2.0, 100), ("select_c__s_p", 1.0, 50), ("sinkhorn_c__s_e", 10.0, 300),
                         ("rescale_c__s_e", 0.5, 40)):
        (r / f"benchmarks/rules/{name}.tsv").write_text(head + f"{s}\t0\t{mem}\t0\t0\t0\t0\t0\t0\t0\n")
    row = table1_row(r, "c", "s", "e", "p", "ours")
    assert row["clip_similarity_pct"] == "not computed" and row["content_chamfer"] == 1.5
    assert row["time_s"] == pytest.approx(13.5) and row["peak_mem_mb"] == 300 and row["device"] == "cpu"
    (r / "benchmarks/rules/rescale_c__s_e.tsv").unlink()
    assert table1_row(r, "c", "s", "e", "p", "ours")["time_s"] is None  # never a partial sum
    df = write_table([row], tmp_path / "t.csv", tmp_path / "t.md")
    assert "not computed" in (tmp_path / "t.md").read_text() and len(df) == 1
    # a missing or corrupt report is an error naming it, not an empty row
    (r / "stylize/c__s/e/losses.json").write_text("{not json")
    with pytest.raises(ValueError, match="losses.json: invalid JSON"):
        table1_row(r, "c", "s", "e", "p", "ours")
    with pytest.raises(FileNotFoundError, match="eval/c__s/other.json"):
        table1_row(r, "c", "s", "other", "p", "ours")


def test_metrics_on_degenerate_inputs_are_finite():
    """Duplicated points (zero-radius patches), a collinear cloud (no unique normal), a scene smaller
    than a patch, needle-like Gaussians: finite values, no NaN."""
    g = torch.Generator().manual_seed(0)
    n = 60
    dup = GaussianScene.from_activated(torch.zeros(n, 3), torch.full((n, 3), 0.01), torch.randn(n, 4, generator=g),
                                       torch.full((n,), 0.5), torch.rand(n, 3, generator=g))
    t = torch.linspace(0, 1, n)[:, None]
    line = GaussianScene.from_activated(t * torch.tensor([1.0, 2.0, 3.0]),
                                        torch.tensor([1e-6, 0.05, 0.05]).expand(n, 3).clone(),
                                        torch.randn(n, 4, generator=g), torch.full((n,), 0.5), torch.rand(n, 3, generator=g))
    few = random_scene(5, seed=3)
    for a, b in ((dup, line), (line, dup), (few, line), (dup, dup)):
        m = weights_free_metrics(a, b.means, b, SMALL)
        assert all(math.isfinite(v) for v in m.values()), m
        for n_e in (1, 40, 10_000):  # one Gaussian an element, and elements larger than either scene
            w = element_metrics(a, b, n_e, SMALL)
            assert all(v is None or math.isfinite(v) for v in w.values()), w
    one_colour = GaussianScene.from_activated(line.means, line.scales, line.quats, line.opacities,
                                              torch.full((n, 3), 0.4))  # tau 0: every neighbour of the same colour
    assert math.isfinite(element_metrics(one_colour, one_colour, 40, SMALL)["element_thickness_w1"])
    with pytest.raises(ValueError, match="at least 2 Gaussians"):
        style_metrics(random_scene(1), line, SMALL)


def test_evaluate_names_the_file_of_an_empty_result(tmp_path):
    from wast3d.cli import main
    from wast3d.ply import write_ply

    write_ply(tmp_path / "empty.ply", GaussianScene.empty())
    write_ply(tmp_path / "s.ply", random_scene(50))
    rc = main(["evaluate", "--result", str(tmp_path / "empty.ply"), "--content", str(tmp_path / "s.ply"),
               "--style", str(tmp_path / "s.ply"), "--result-render", str(tmp_path), "--style-render", str(tmp_path),
               "--texture-reference", str(tmp_path), "--content-render", str(tmp_path),
               "--out-json", str(tmp_path / "out.json")])
    assert rc == 2 and not (tmp_path / "out.json").exists()


def test_cli_reports_bad_input_in_one_line_and_faults_with_their_traceback(tmp_path, caplog, monkeypatch):
    """Bad input: one line naming the file, exit 2, the traceback only with -v. A fault (a ValueError
    raised inside numpy, a KeyError): its traceback, whatever the flags."""
    import numpy as np

    from wast3d import cli

    missing, out = tmp_path / "nothere.ply", tmp_path / "out.ply"
    assert cli.main(["import-ply", str(missing), str(out)]) == 2
    rec = [r for r in caplog.records if r.levelname == "ERROR"][-1]
    assert str(missing) in rec.getMessage() and not rec.exc_info
    caplog.clear()
    assert cli.main(["-v", "import-ply", str(missing), str(out)]) == 2
    assert [r for r in caplog.records if r.levelname == "ERROR"][-1].exc_info

    def fault_numpy(a):
        np.zeros(3).reshape(2, 2)

    def fault_key(a):
        return {}["k"]

    fn, help_ = cli.COMMANDS["import-ply"]
    for fault, exc in ((fault_numpy, ValueError), (fault_key, KeyError)):
        def deco(sub, fault=fault):
            fn(sub)  # the subcommand's arguments; its run function replaced by the fault
            return fault
        monkeypatch.setitem(cli.COMMANDS, "import-ply", (deco, help_))
        with pytest.raises(exc):
            cli.main(["import-ply", str(missing), str(out)])


def test_table_row_specs():
    from wast3d.tables import parse_spec

    assert parse_spec("lego__grass/default", ("EXPERIMENT",)) == ["lego", "grass", "default"]
    assert parse_spec("a__b/m/-/xyz / RGB", ("M", "P", "L")) == ["a", "b", "m", "-", "xyz / RGB"]
    for bad in ("lego-grass/default", "a__b"):
        with pytest.raises(ValueError, match="is not CONTENT__STYLE/EXPERIMENT"):
            parse_spec(bad, ("EXPERIMENT",))


# ---- relief, texture and coverage ---------------------------------------------------


def test_relief_w1_zero_for_identical_and_orders_floor_below_a_flat_sheet():
    from wast3d.metrics import MetricsConfig, relief_w1

    cfg = MetricsConfig(relief_centres=256)
    a = make_scene("style", "pebbles", 4000, seed=0).means
    b = make_scene("style", "pebbles", 4000, seed=1).means
    g = torch.Generator().manual_seed(0)
    flat = torch.cat([torch.rand(4000, 2, generator=g) * 2 - 1, torch.zeros(4000, 1)], 1)
    assert relief_w1(a, a, cfg) == 0
    floor, negative = relief_w1(b, a, cfg), relief_w1(flat, a, cfg)
    assert 0 < 5 * floor < negative, (floor, negative)


def test_whole_element_metrics_see_torn_and_flattened_elements(tmp_path):
    """element_colour_w1 sees the elements torn apart (confetti), element_thickness_w1 the elements
    flattened into chips, each at >= 5x the other seed's sheet of the same style (the floor)."""
    from dataclasses import replace

    from wast3d.metrics import element_metrics
    from wast3d.pipeline import evaluate_whole_elements
    from wast3d.volume import element_sheet

    style, _ = element_sheet(make_scene("style", "bouquet", 6000, seed=0))
    other, _ = element_sheet(make_scene("style", "bouquet", 6000, seed=1), seed=1)
    el = style.element.long()
    n_e = int(torch.bincount(el)[torch.bincount(el) > 0].median())
    confetti = replace(style, means=style.means[torch.randperm(len(style), generator=torch.Generator().manual_seed(0))])
    chips = style.means.clone()
    for j in el.unique():  # each element pressed to a fifth of its height along its least-variance axis
        i = (el == j).nonzero().squeeze(1)
        p = style.means[i].double() - style.means[i].double().mean(0)
        n = torch.linalg.eigh(p.T @ p)[1][:, 0]
        chips[i] = (style.means[i].double() - 0.8 * (p @ n)[:, None] * n).float()
    cfg = MetricsConfig()
    score = {name: element_metrics(sc, style, n_e, cfg) for name, sc in
             (("same", style), ("floor", other), ("confetti", confetti), ("chips", replace(style, means=chips)))}
    assert score["same"]["element_colour_w1"] == 0 and score["same"]["element_thickness_w1"] == 0
    floor = score["floor"]
    assert 0 < 5 * floor["element_colour_w1"] < score["confetti"]["element_colour_w1"], score
    assert 0 < 5 * floor["element_thickness_w1"] < score["chips"]["element_thickness_w1"], score
    # the evaluate stage reads the element size from the texture reference's segments, and says when it has none
    missing = evaluate_whole_elements(other, style, tmp_path, cfg)
    assert missing["element_colour_w1"] is None and "segments.npz does not exist" in missing["whole_status"]
    from wast3d.io_utils import save_npz

    save_npz(tmp_path / "segments.npz", segments=(el - 1).numpy())
    got = evaluate_whole_elements(other, style, tmp_path, cfg)
    assert got["element_size_gaussians"] == n_e and got["element_colour_w1"] == floor["element_colour_w1"]
    save_npz(tmp_path / "segments.npz", segments=(el - 1).numpy()[:10])
    with pytest.raises(ValueError, match="segments.npz: 'segments' has 10 entries"):
        evaluate_whole_elements(other, style, tmp_path, cfg)
    with pytest.raises(ValueError, match="element size must be >= 1"):
        element_metrics(other, style, 0, cfg)


def test_whole_element_descriptors_are_per_centre_across_memory_chunks():
    """Large elements split the centres into chunks (memory); each centre's descriptors are its own."""
    from wast3d.metrics import element_descriptors

    sc = random_scene(6000, seed=2)
    every = torch.arange(6000)  # n_e 4000: 1000 neighbours, chunks of 4194 centres
    col, thick = element_descriptors(sc.means, sc.rgb, 4000, 0.5, every)
    for i in (0, 4193, 4194, 5999):
        c1, t1 = element_descriptors(sc.means, sc.rgb, 4000, 0.5, every[i:i + 1])
        assert torch.allclose(col[i], c1[0]) and torch.allclose(thick[i], t1[0], equal_nan=True)


def test_texture_swd_zero_for_identical_sees_a_flat_image_and_ignores_silhouettes():
    from wast3d.image_metrics import TextureConfig, texture_swd

    g = torch.Generator().manual_seed(0)
    opaque = lambda rgb: torch.cat([rgb, torch.ones(*rgb.shape[:-1], 1)], -1)  # noqa: E731
    rough = opaque(torch.rand(4, 48, 48, 3, generator=g))
    rough2 = opaque(torch.rand(4, 48, 48, 3, generator=g))
    flat = opaque(torch.full((4, 48, 48, 3), 0.3) + 0.01 * torch.rand(4, 48, 48, 3, generator=g))
    cfg = TextureConfig(windows=256, directions=32, min_windows=1)
    assert texture_swd(rough, rough, cfg) == 0
    assert 5 * texture_swd(rough2, rough, cfg) < texture_swd(flat, rough, cfg)
    # the same flat surface as a disc on the white background: its outline is no texture
    yy, xx = torch.meshgrid(torch.arange(48.0), torch.arange(48.0), indexing="ij")
    inside = (((yy - 24) ** 2 + (xx - 24) ** 2) < 18 ** 2).float()
    disc, flat2 = flat.clone(), opaque(torch.full((4, 48, 48, 3), 0.3) + 0.01 * torch.rand(4, 48, 48, 3, generator=g))
    disc[..., 3] = inside
    painted = opaque(disc[..., :3] * inside[..., None] + (1 - inside[..., None]))  # the outline baked into an opaque image
    assert texture_swd(disc, flat, cfg) < 1.5 * texture_swd(flat2, flat, cfg) < 0.2 * texture_swd(painted, flat, cfg)
    # a scattered result: no window inside the foreground -> a clear error naming the level
    dots = rough.clone()
    dots[..., 3] = ((yy % 4 == 0) & (xx % 4 == 0)).float()
    with pytest.raises(ValueError, match="no pyramid level has 1 distinct 5x5 windows.*level 0: result 0"):
        texture_swd(dots, rough, cfg)
    with pytest.raises(ValueError, match="min_alpha"):
        TextureConfig(min_alpha=0.0)


def test_texture_swd_leaves_out_a_level_with_too_few_reference_windows():
    """A reference whose foreground holds a few windows at level 1 (a small patch with soft edges): that
    level would compare against one window drawn again and again; it is left out and said so, and the
    score is level 0's alone."""
    from wast3d.image_metrics import TextureConfig, texture_levels

    g = torch.Generator().manual_seed(1)
    frames = torch.cat([torch.rand(4, 64, 64, 3, generator=g), torch.ones(4, 64, 64, 1)], -1)
    ref = torch.cat([torch.rand(4, 64, 64, 3, generator=g), torch.zeros(4, 64, 64, 1)], -1)
    ref[:, 20:38, 20:38, 3] = 1.0  # 18 px: 100 windows a frame at level 0, 1 at level 1
    out = texture_levels(frames, ref, TextureConfig(windows=256, directions=32, min_windows=128))
    lv = {r["level"]: r for r in out["levels"]}
    assert lv[0]["style_windows"] == 4 * 10 * 10 and lv[0]["swd"] is not None
    assert lv[1]["style_windows"] == 4 and lv[1]["swd"] is None
    assert out["texture_swd"] == lv[0]["swd"]
    both = texture_levels(frames, ref, TextureConfig(windows=256, directions=32, min_windows=1))
    assert all(r["swd"] is not None for r in both["levels"])


def test_texture_reference_puts_style_elements_at_the_results_pixel_scale():
    """z = (R_style h_content) / (R_content h_style): 1 for a scaled copy; the zoom applied to the focal."""
    from wast3d.render import RenderConfig, texture_reference_cameras, turntable_cameras

    content, style = make_scene("content", "torus", 800), make_scene("style", "pebbles", 1500)
    cfg = RenderConfig(frames=2, size=32, key_views=1)
    cams, z = texture_reference_cameras(content.transform(scale=3.0), content, cfg)
    assert z == pytest.approx(1.0, rel=1e-4)
    cams, z = texture_reference_cameras(style, content, cfg)
    plain = turntable_cameras(style, cfg)
    assert cams[0].fx == pytest.approx(z * plain[0].fx) and torch.equal(cams[0].world_to_cam, plain[0].world_to_cam)
    dense = make_scene("style", "pebbles", 6000)  # the same patch, half the spacing: elements 2x larger vs a spacing
    assert texture_reference_cameras(dense, content, cfg)[1] == pytest.approx(2 * z, rel=0.15)


def test_valid_metrics_order_floor_positive_negative(tmp_path):
    """What benchmarks/metrics_validation.py checks at demo size, on small scenes: for relief_w1,
    aniso_w1 and texture_swd, the style's other seed (floor) < the collage of the style's elements on
    the content (positive) < the plain content (negative)."""
    from wast3d.clustering import ClusterConfig, kmeans
    from wast3d.gaussians import anisotropy
    from wast3d.metrics import MetricsConfig, relief_w1, wasserstein_1d
    from wast3d.registration import RegistrationConfig, register
    from wast3d.selection import Selection, select_footprint
    from wast3d.stylize import StylizeConfig, stylize

    content = make_scene("content", "ant", 4000)
    style, other = make_scene("style", "pebbles", 6000, seed=0), make_scene("style", "pebbles", 6000, seed=1)
    labels = torch.from_numpy(kmeans(content.means, content.rgb, ClusterConfig(span=0, coherence=0, target_cluster_size=400, flatness=0))[0]).long()
    reg = register(content.means, labels, style.means, RegistrationConfig(landings=1, yaws=4, iterations=20,
                                                                           refine_iterations=30))
    off, idx = select_footprint(reg.apply(content.means.double(), labels), labels, style.means.double(), 1.0,
                                reg.style_spacing)
    collage = stylize(content, labels, style, reg, Selection(off, idx, torch.zeros(len(off) - 1, dtype=torch.float64)),
                      StylizeConfig(iterations=0), progress=False).scene
    cfg = MetricsConfig(relief_centres=1024)
    aniso = lambda sc: wasserstein_1d(anisotropy(sc.scales.double()).log10(),  # noqa: E731
                                      anisotropy(style.scales.double()).log10())
    for name, score in (("relief_w1", lambda sc: relief_w1(sc.means, style.means, cfg)), ("aniso_w1", aniso)):
        floor, positive, negative = score(other), score(collage), score(content)
        assert floor < positive < negative, (name, floor, positive, negative)
    # the image metric: result renders (cameras fitted to the content) against the style's texture reference
    from wast3d.image_metrics import TextureConfig, texture_swd
    from wast3d.render import RenderConfig, read_frames, render_texture_reference, render_turntable

    rc = RenderConfig(frames=8, size=256, key_views=1)
    fr = {}
    for name, sc in (("style", style), ("floor", other)):
        render_texture_reference(sc, content, tmp_path / name, rc)
        fr[name] = read_frames(tmp_path / name)
    for name, sc in (("positive", collage), ("negative", content)):
        render_turntable(sc, content, tmp_path / name, rc)
        fr[name] = read_frames(tmp_path / name)
    tc = TextureConfig(windows=1024, levels=1)  # a 4,000-Gaussian ant is mostly too thin for level 1
    floor, positive, negative = (texture_swd(fr[n], fr["style"], tc) for n in ("floor", "positive", "negative"))
    assert floor < positive < negative, (floor, positive, negative)  # (the margins: metrics_validation, demo size)


def test_coverage_counts_holes_where_the_content_is():
    from wast3d.image_metrics import coverage

    ref = torch.zeros(2, 10, 10)
    ref[:, 2:8, 2:8] = 1.0
    assert coverage(ref, ref) == 1.0
    holed = ref.clone()
    holed[:, 2:5, 2:8] = 0.0  # half of the foreground
    assert coverage(holed, ref) == pytest.approx(0.5)
    assert coverage(torch.ones(2, 10, 10), ref) == 1.0  # extra foreground is no hole
    assert coverage(ref, torch.zeros(2, 10, 10)) == 1.0
    with pytest.raises(ValueError, match="differ in shape"):
        coverage(ref[:1], ref)


def test_coverage_at_the_element_scale_closes_gaps_not_holes():
    """coverage_element: gaps narrower than an element (a style's own gaps between its elements) are
    closed before counting, a hole larger than an element (a lost part of the content) still counts."""
    from wast3d.image_metrics import close_mask, coverage, coverage_at_scale, projected_radii

    ref = torch.zeros(1, 64, 64)
    ref[:, 8:56, 8:56] = 1.0
    stripes = ref.clone()
    stripes[:, :, 10:56:6] = 0.0  # 1-pixel gaps every 6 pixels: an element 5 px wide
    assert coverage(stripes, ref) < 0.85
    assert coverage_at_scale(stripes, ref, [2.5]) == 1.0  # radius half an element: the gaps close
    assert coverage_at_scale(stripes, ref, [0.5]) == coverage(stripes, ref)  # under a pixel: nothing closes
    holed = stripes.clone()
    holed[:, 20:40, 20:40] = 0.0  # a hole 4 elements across
    closed = coverage_at_scale(holed, ref, [2.5])
    assert closed == pytest.approx(1 - 400 / 48**2, abs=0.02)
    # the closing adds nothing beyond the mask's own outline (the frame's edge is background)
    m = torch.zeros(20, 20, dtype=torch.bool)
    m[5:15, 0:10] = True
    assert torch.equal(close_mask(m, 3.0), m)
    # the radius: half the length in pixels at the centre's depth
    cam = {"world_to_cam": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4.0], [0, 0, 0, 1]], "fx": 100.0}
    assert projected_radii([cam], [0.0, 0.0, 1.0], 0.2) == [pytest.approx(2.0)]
    with pytest.raises(ValueError, match="radii"):
        coverage_at_scale(ref, ref, [1.0, 2.0])


def test_close_mask_is_the_closing_by_a_disc():
    """close_mask (distance transforms) equals the closing by the disc {dx^2 + dy^2 <= radius^2} written
    as two convolutions, frame edge as background, on random masks, sizes and radii (integer radii too,
    where a pixel lies exactly on the disc's rim)."""
    import math

    import torch.nn.functional as F

    from wast3d.image_metrics import close_mask

    def by_convolution(mask, radius):
        r = int(math.floor(radius))
        if r < 1:
            return mask.clone()
        yy, xx = torch.meshgrid(torch.arange(-r, r + 1), torch.arange(-r, r + 1), indexing="ij")
        disc = ((xx * xx + yy * yy) <= radius * radius).double()[None, None]
        dilated = F.conv2d(F.pad(mask.double()[None, None], (2 * r,) * 4), disc) > 0.5
        return (F.conv2d(F.pad((~dilated).double(), (r,) * 4), disc) < 0.5)[0, 0, r:-r, r:-r]

    g = torch.Generator().manual_seed(0)
    for t in range(120):
        h, w = (int(v) for v in torch.randint(1, 33, (2,), generator=g))
        mask = torch.rand(h, w, generator=g) < float(torch.rand(1, generator=g))
        radius = float(torch.rand(1, generator=g)) * 7
        radius = float(int(radius)) if t % 3 == 0 else radius
        assert torch.equal(close_mask(mask, radius), by_convolution(mask, radius)), (h, w, radius)


def test_loss_picture_of_a_run_without_steps(tmp_path):
    """The positive control 'selected' runs stylize with iterations: 0 (no loss curves at all)."""
    from wast3d.figures import loss_curves_picture

    loss_curves_picture([[], []], tmp_path / "l.png", "no steps")
    loss_curves_picture([[0.3, 0.2], []], tmp_path / "m.png", "one")
    assert (tmp_path / "l.png").stat().st_size > 0 and (tmp_path / "m.png").stat().st_size > 0

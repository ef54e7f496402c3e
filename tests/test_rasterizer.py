import math
from dataclasses import replace

import pytest
import torch
from torch.overrides import TorchFunctionMode

from conftest import random_scene
from wast3d.cameras import Camera, orbit_cameras
from wast3d.gaussians import GaussianScene
from wast3d.rasterizer import ALPHA_MIN, bin_tiles, project, rasterize

BACKENDS = ["torch", "native"]


def _identity_cam(w=40, h=30, f=50.0, dtype=torch.float64):
    return Camera(torch.eye(4, dtype=dtype), f, f, w / 2, h / 2, w, h)


@pytest.mark.parametrize("backend", BACKENDS)
def test_closed_form_single_gaussian(backend):
    """One isotropic Gaussian facing the camera: alpha(p) = o exp(-|p - mu|^2 / (2 s^2)),
    s^2 = (f sigma / z)^2 + 0.3 (the low-pass dilation), composited on the background."""
    z0, sigma, o, f = 4.0, 0.15, 0.8, 50.0
    cam = _identity_cam(f=f)
    scene = GaussianScene.from_activated(torch.tensor([[0.0, 0.0, z0]], dtype=torch.float64),
                                         torch.full((1, 3), sigma, dtype=torch.float64), opacities=o,
                                         rgb=torch.tensor([[0.9, 0.2, 0.1]], dtype=torch.float64))
    bg = torch.tensor([0.1, 0.3, 0.5], dtype=torch.float64)
    r = rasterize(scene, cam, background=bg, backend=backend)
    ys, xs = torch.meshgrid(torch.arange(30, dtype=torch.float64) + 0.5, torch.arange(40, dtype=torch.float64) + 0.5,
                            indexing="ij")
    s2 = (f * sigma / z0) ** 2 + 0.3
    a = o * torch.exp(-((xs - 20) ** 2 + (ys - 15) ** 2) / (2 * s2))
    a = torch.where(a >= ALPHA_MIN, a.clamp_max(0.99), torch.zeros_like(a))
    expect = a[..., None] * torch.tensor([0.9, 0.2, 0.1], dtype=torch.float64) + (1 - a[..., None]) * bg
    assert torch.allclose(r.alpha, a, atol=1e-12)
    assert torch.allclose(r.rgb, expect, atol=1e-12)
    assert torch.allclose(r.depth[a > 0], torch.full_like(r.depth[a > 0], z0))
    assert (r.depth[a == 0] == 0).all()


@pytest.mark.parametrize("backend", BACKENDS)
def test_gradcheck_float64(backend):
    scene = random_scene(6, sh_degree=1, seed=3, dtype=torch.float64, spread=0.3)
    scene.opacity_logits.clamp_(-3, 0.5)  # stay away from the 0.99 clamp
    cam = orbit_cameras(1, 3.0, 24, 20, fov_deg=40)[0].to(dtype=torch.float64)
    names = list(scene.tensors())
    w = torch.rand(20, 24, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))

    def f(*ts):
        s = GaussianScene(**dict(zip(names, ts)))
        r = rasterize(s, cam, background=(0.2, 0.4, 0.6), backend=backend)
        return (r.rgb * w).sum(), r.alpha.square().sum(), (r.depth * r.alpha).sum()

    inputs = [t.clone().requires_grad_(True) for t in scene.tensors().values()]
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_native_matches_torch():
    scene = random_scene(1500, sh_degree=2, seed=1)
    cam = orbit_cameras(3, 3.5, 70, 50)[1]
    outs = {}
    for b in BACKENDS:
        s = scene.clone()
        for t in s.tensors().values():
            t.requires_grad_(True)
        r = rasterize(s, cam, background=(1.0, 1.0, 1.0), backend=b)
        ((r.rgb * torch.linspace(0, 1, 3)).sum() + r.depth.sum() * 0.1 + r.alpha.sum()).backward()
        outs[b] = (r, {k: v.grad for k, v in s.tensors().items()})
    for k in ("rgb", "alpha", "depth"):
        assert torch.allclose(getattr(outs["torch"][0], k), getattr(outs["native"][0], k), atol=2e-4), k
    for k, g in outs["torch"][1].items():
        assert torch.allclose(g, outs["native"][1][k], atol=1e-3 * (1 + g.abs().max())), k


@pytest.mark.parametrize("backend", BACKENDS)
def test_several_channels_in_one_pass_equal_separate_renders(backend):
    """colors [N, 9] rendered at once equal three 3-channel renders (the channels composite alone);
    a uniform background spreads over the channels, a mixed 3-value one is refused."""
    scene = random_scene(800, seed=3)
    cam = orbit_cameras(2, 3.5, 60, 40)[0]
    cols = torch.rand(len(scene), 9, dtype=scene.dtype, generator=torch.Generator().manual_seed(0))
    both = rasterize(scene, cam, background=(0.5, 0.5, 0.5), backend=backend, colors=cols)
    assert both.rgb.shape == (40, 60, 9)
    for i in range(0, 9, 3):
        one = rasterize(scene, cam, background=(0.5, 0.5, 0.5), backend=backend, colors=cols[:, i:i + 3].contiguous())
        assert torch.allclose(both.rgb[..., i:i + 3], one.rgb, atol=1e-6), i
        assert torch.equal(both.alpha, one.alpha) and torch.allclose(both.depth, one.depth, atol=1e-6)
    with pytest.raises(ValueError, match="background"):
        rasterize(scene, cam, background=(1.0, 0.0, 0.0), backend=backend, colors=cols)


@pytest.mark.parametrize("tile", [5, 8, 13, 16, 32])
def test_native_vector_lanes_match_torch_at_every_tile_size(tile):
    """The native compositor runs 8 pixels a vector: tiles whose pixel count is no multiple of 8 (5, 13),
    images that end mid-tile (37 x 29), the 0.99 alpha clamp and the early stop at T < 1e-4 (opaque
    Gaussians stacked) give the float64 PyTorch reference's images and gradients, in float64 and in
    float32."""
    from wast3d.rasterizer import composite_native, composite_torch

    scene = random_scene(300, seed=7, dtype=torch.float64, spread=0.6)
    scene.opacity_logits[:100] = 8.0  # alpha at the 0.99 clamp; stacked, they stop the tiles early
    cam = orbit_cameras(1, 3.0, 37, 29, fov_deg=45)[0].to(dtype=torch.float64)
    p = project(scene.means, scene.quats, scene.scales, scene.opacities, cam)
    gid, off = bin_tiles(p, 37, 29, tile)
    g = torch.Generator().manual_seed(0)
    colors = torch.rand(len(p.ids), 4, dtype=torch.float64, generator=g)
    w_out, w_T = torch.rand(29, 37, 4, dtype=torch.float64, generator=g), torch.rand(29, 37, dtype=torch.float64, generator=g)
    results = {}
    for name, fn, dtype in (("torch", composite_torch, torch.float64), ("native64", composite_native, torch.float64),
                            ("native32", composite_native, torch.float32)):
        args = [t.detach().to(dtype).requires_grad_(True) for t in (p.means2d, p.conics, colors, p.opacities)]
        out, T = fn(*args, gid, off, 37, 29, tile=tile, radii=p.radii)
        ((out * w_out.to(dtype)).sum() + (T * w_T.to(dtype)).sum()).backward()
        results[name] = (out.double(), T.double(), [a.grad.double() for a in args])
    ref = results["torch"]
    assert (ref[1] < 1e-3).any() and (ref[1] > 0.5).any()  # both opaque and see-through pixels
    for name, atol in (("native64", 1e-9), ("native32", 2e-5)):
        out, T, grads = results[name]
        assert torch.allclose(out, ref[0], atol=atol) and torch.allclose(T, ref[1], atol=atol), name
        for a, b in zip(grads, ref[2]):
            assert torch.allclose(a, b, atol=atol * 50 * (1 + b.abs().max())), (name, (a - b).abs().max())


def test_binning_is_exact_culling():
    """Every pixel a Gaussian reaches with alpha >= 1/255 lies in a tile it is binned into."""
    scene = random_scene(300, seed=2)
    cam = orbit_cameras(1, 3.0, 64, 48)[0]
    p = project(scene.means, scene.quats, scene.scales, scene.opacities, cam)
    gid, off = bin_tiles(p, 64, 48)
    ys, xs = torch.meshgrid(torch.arange(48) + 0.5, torch.arange(64) + 0.5, indexing="ij")
    d = p.means2d[:, None, None, :] - torch.stack([xs, ys], -1)[None]
    a, b, c = p.conics.T[:, :, None, None]
    sig = 0.5 * (a * d[..., 0] ** 2 + c * d[..., 1] ** 2) + b * d[..., 0] * d[..., 1]
    reach = p.opacities[:, None, None] * torch.exp(-sig) >= ALPHA_MIN
    tiles_x = 4
    for g in range(len(p.ids)):
        yy, xx = reach[g].nonzero(as_tuple=True)
        for t in set(((yy // 16) * tiles_x + xx // 16).tolist()):
            assert g in gid[off[t]:off[t + 1]].tolist()


class _ExpRange(TorchFunctionMode):
    def __init__(self):
        super().__init__()
        self.min_arg = math.inf

    def __torch_function__(self, func, types, args=(), kwargs=None):
        if func in (torch.exp, torch.Tensor.exp) and args[0].numel():
            self.min_arg = min(self.min_arg, float(args[0].min()))
        return func(*args, **(kwargs or {}))


def test_no_exp_of_large_negative_arguments():
    """exp of arguments below about -87 gives denormals in float32 and was 50-100x slower here:
    the PyTorch compositor clamps the Gaussian exponent (>= -12) and log-transmittance (>= -30)."""
    scene = random_scene(400, seed=4)
    scene.opacity_logits.fill_(8.0)  # opaque: transmittance collapses fast
    cam = orbit_cameras(1, 3.0, 32, 32)[0]
    with _ExpRange() as m:
        rasterize(scene, cam, backend="torch")
    assert m.min_arg >= -30.0


def test_empty_and_offscreen():
    cam = orbit_cameras(1, 3.0, 16, 16)[0]
    for b in BACKENDS:
        r = rasterize(GaussianScene.empty(), cam, background=(0.5, 0.5, 0.5), backend=b)
        assert torch.equal(r.rgb, torch.full((16, 16, 3), 0.5)) and (r.alpha == 0).all()
        behind = random_scene(10)
        behind.means[:] = torch.tensor([100.0, 0, 0])  # far outside the view
        r = rasterize(behind, cam, backend=b)
        assert (r.alpha == 0).all()


def test_projection_matches_gsplat_reference():
    """gsplat's pure-PyTorch projection (_fully_fused_projection) runs on CPU: same means2d, conics, depths."""
    ref = pytest.importorskip("gsplat.cuda._torch_impl")
    scene = random_scene(500, seed=5, dtype=torch.float64)
    cam = orbit_cameras(1, 3.0, 80, 60)[0].to(dtype=torch.float64)
    p = project(scene.means, scene.quats, scene.scales, scene.opacities, cam)
    radii, means2d, depths, conics, _ = ref._fully_fused_projection(
        scene.means, scene.covariances, cam.world_to_cam[None], cam.K[None], 80, 60, eps2d=0.3)
    assert torch.allclose(means2d[0, p.ids], p.means2d, atol=1e-9)
    assert torch.allclose(conics[0, p.ids], p.conics, rtol=1e-7, atol=1e-9)
    assert torch.allclose(depths[0, p.ids], p.depths)


def test_boxes_per_axis_and_clones_drawn_in_a_fixed_order():
    """A Gaussian's box has its own x and y half-widths (k sqrt(Sigma_xx), k sqrt(Sigma_yy) of the
    dilated 2D covariance: an elongated Gaussian is binned into the tiles along it only), and
    Gaussians at one depth (clones, as densification makes them) are drawn in their index order, so a
    Gaussian culled elsewhere in the scene changes no pixel."""
    from wast3d.cameras import Camera
    from wast3d.gaussians import GaussianScene

    cam = Camera(torch.eye(4), 100.0, 100.0, 32.0, 40.0, 64, 64)  # the mean mid-way down a tile row
    one = GaussianScene.from_activated(torch.tensor([[0.0, 0.0, 5.0]]), torch.tensor([[0.4, 0.02, 0.02]]),
                                       torch.tensor([[1.0, 0.0, 0.0, 0.0]]), torch.tensor([0.9]), torch.rand(1, 3))
    p = project(one.means, one.quats, one.scales, one.opacities, cam)
    k = math.sqrt(2 * math.log(0.9 * 255))
    assert p.radii[0].tolist() == [math.ceil(k * math.sqrt((100 * 0.4 / 5) ** 2 + 0.3)),
                                   math.ceil(k * math.sqrt((100 * 0.02 / 5) ** 2 + 0.3))]
    assert len(bin_tiles(p, 64, 64)[0]) == 4  # the row of tiles it lies along, not all 16

    scene = random_scene(4000, seed=5, spread=0.3)
    scene.means[:] = scene.means[:200].repeat(20, 1)  # clones: 20 at each depth, of other colours
    cam = orbit_cameras(1, 3.0, 48, 48)[0]
    extra = random_scene(1, seed=6)
    R, t = cam.world_to_cam[:3, :3], cam.world_to_cam[:3, 3]
    extra.means[0] = R.T @ (torch.tensor([0.3, 0.3, 1.0]) * 2.0 - t)  # drawn in the image's corner only
    extra.log_scales[:] = math.log(0.005)
    more = GaussianScene.concat([extra, scene])
    a, b = rasterize(scene, cam), rasterize(more, cam)
    assert len(b.visible_ids) == len(a.visible_ids) + 1
    far = (b.rgb - a.rgb).abs().amax(-1) > 0
    assert far.any() and not far[:36, :36].any()  # the extra drew its corner, and nothing of the clones changed


@pytest.mark.parametrize("backend", BACKENDS)
def test_named_result_and_densification_layout(backend):
    """``visible_ids`` index the scene (not the visible subset), ``means2d``/``radii`` follow them, and
    ``densify`` (gsplat's strategy layout) holds every Gaussian's screen-space gradient, 0 off-screen."""
    scene = random_scene(300, seed=11, spread=0.4)
    cam = orbit_cameras(1, 3.0, 48, 48)[0]
    scene.means[::3] += 100.0  # a third far outside the view
    plain = rasterize(scene, cam, backend=backend)
    assert plain.densify is None and plain.normal is None
    ids = plain.visible_ids
    assert 0 < len(ids) < len(scene) and not (ids % 3 == 0).any()
    assert plain.means2d.shape == (len(ids), 2) and plain.radii.shape == (len(ids),)
    moved = replace(scene, means=scene.means.clone().requires_grad_(True))
    r = rasterize(moved, cam, backend=backend, full_means2d=True)
    assert torch.equal(r.visible_ids, ids) and torch.allclose(r.rgb, plain.rgb)
    d = r.densify
    assert d["means2d"].shape == (1, len(scene), 2) and d["radii"].shape == (1, len(scene), 2)
    assert (d["width"], d["height"], d["n_cameras"]) == (48, 48, 1)
    assert torch.equal(d["means2d"][0, ids], r.means2d) and (d["radii"][0, ::3] == 0).all()
    d["means2d"].retain_grad()
    r.rgb.sum().backward()
    g = d["means2d"].grad[0]
    assert (g[::3] == 0).all() and g[ids].abs().sum() > 0

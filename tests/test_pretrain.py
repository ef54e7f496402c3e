import math
import subprocess
import sys

import numpy as np
import pytest
import torch

from wast3d.datasets import load_blender
from wast3d.pretrain import PretrainConfig, Trainer, aniso_loss, ssim, unif_loss
from wast3d.procedural import make_scene
from wast3d.render import export_blender


def test_aniso_loss_value_and_gradient():
    """Eq. 1 on hand-made Gaussians: ratios 1, 2, 6 with r = 3 -> (0 + 0 + 3) / 3 = 1."""
    s = torch.tensor([[1.0, 1.0, 1.0], [2.0, 1.0, 1.5], [6.0, 1.0, 2.0]], dtype=torch.float64)
    ls = s.log().requires_grad_(True)
    v = aniso_loss(ls, 3.0)
    assert v.item() == pytest.approx(1.0)
    v.backward()
    # only the third Gaussian is penalized: d/dlog s_max (s_max/s_min) = ratio = 6, /3 Gaussians
    assert torch.allclose(ls.grad[:2], torch.zeros(2, 3, dtype=torch.float64))
    assert torch.allclose(ls.grad[2], torch.tensor([2.0, -2.0, 0.0], dtype=torch.float64))


def test_unif_loss_value_and_gradient():
    """Eq. 2 with target 1: ||(2,1,1) - 1||^2 = 1 and ||(1,1,1) - 1||^2 = 0 -> mean 0.5."""
    s = torch.tensor([[2.0, 1.0, 1.0], [1.0, 1.0, 1.0]], dtype=torch.float64)
    ls = s.log().requires_grad_(True)
    v = unif_loss(ls, 1.0)
    assert v.item() == pytest.approx(0.5)
    v.backward()
    # d/dlog s of (s - 1)^2 / 2 = (s - 1) s  -> 2 for the first axis of the first Gaussian
    assert torch.allclose(ls.grad, torch.tensor([[2.0, 0, 0], [0, 0, 0]], dtype=torch.float64))
    # target 0: the median of the scales (1 here), detached
    assert float(unif_loss(s.log(), 0.0)) == pytest.approx(0.5)


def test_unif_loss_cap_counts_only_the_excess():
    """unif_cap: a thin axis (0.25 under a target of 1) costs nothing and gets no gradient; an axis of
    2 costs (2 - 1)^2 as in the two-sided eq. 2, whose thin axis costs (0.25 - 1)^2 more."""
    s = torch.tensor([[2.0, 0.25, 1.0]], dtype=torch.float64)
    ls = s.log().requires_grad_(True)
    v = unif_loss(ls, 1.0, cap=True)
    assert v.item() == pytest.approx(1.0)
    v.backward()
    assert torch.allclose(ls.grad, torch.tensor([[4.0, 0, 0]], dtype=torch.float64))
    assert unif_loss(s.log(), 1.0).item() == pytest.approx(1.0 + 0.75**2)


def test_ssim_matches_the_reference_11x11_window():
    """The separable SSIM equals the reference 3DGS code's (one 11x11 depthwise window per moment)."""
    import torch.nn.functional as F

    g = torch.Generator().manual_seed(1)
    a = torch.rand(37, 45, 3, dtype=torch.float64, generator=g)
    b = (a + 0.2 * torch.randn(37, 45, 3, dtype=torch.float64, generator=g)).clamp(0, 1)
    x = torch.arange(11, dtype=torch.float64) - 5
    w1 = torch.exp(-x**2 / (2 * 1.5**2))
    w1 = w1 / w1.sum()
    w = (w1[:, None] * w1[None, :]).expand(3, 1, 11, 11)
    X, Y = a.permute(2, 0, 1)[None], b.permute(2, 0, 1)[None]
    blur = lambda t: F.conv2d(t, w, padding=5, groups=3)  # noqa: E731
    mx, my = blur(X), blur(Y)
    sxx, syy, sxy = blur(X * X) - mx**2, blur(Y * Y) - my**2, blur(X * Y) - mx * my
    c1, c2 = 0.01**2, 0.03**2
    ref = (((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx**2 + my**2 + c1) * (sxx + syy + c2))).mean()
    assert float(ssim(a, b)) == pytest.approx(float(ref), abs=1e-12)
    assert float(ssim(a, b)) < 0.9


def test_ssim_identity_and_drop():
    a = torch.rand(20, 24, 3)
    assert float(ssim(a, a)) == pytest.approx(1.0, abs=1e-5)
    assert float(ssim(a, (a + 0.3 * torch.randn_like(a)).clamp(0, 1))) < 0.8


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("ds")
    export_blender(make_scene("style", "stones", 3000, seed=0), root, n_views=16, size=32)
    return root


def _cfg(**kw):
    base = dict(iterations=120, init_points=600, refine_start=40, refine_every=40, reset_every=10_000,
                checkpoint_every=50, sh_degree=0, max_gaussians=3000, seed=3)
    base.update(kw)
    return PretrainConfig(**base)


def test_tiny_training_psnr_rises(tiny_dataset):
    ds = load_blender(tiny_dataset, holdout_every=4, background=(1.0, 1.0, 1.0))
    tr = Trainer(ds, _cfg())
    before = tr.evaluate()["psnr"]
    tr.train(progress=False)
    ev = tr.evaluate()
    assert ev["psnr"] > 17.0 and ev["psnr"] > before + 4
    assert math.isfinite(ev["ssim"]) and ev["gaussians"] <= 3000


def test_resume_equals_uninterrupted(tiny_dataset, tmp_path, caplog):
    ds = load_blender(tiny_dataset, holdout_every=4)
    full = Trainer(ds, _cfg(iterations=100))
    full.train(progress=False)
    ck = tmp_path / "run.ckpt"
    part = Trainer(ds, _cfg(iterations=100))
    part.train(ck, progress=False, stop_at=60)  # interrupted at 60; the last checkpoint is from step 50
    assert ck.exists()
    resumed = Trainer(ds, _cfg(iterations=100))
    resumed.train(ck, progress=False)
    assert resumed.step == 100
    for k in full.params:
        assert torch.equal(full.params[k], resumed.params[k]), k
    other = Trainer(ds, _cfg(iterations=100, regularize=True))  # the checkpoint is another configuration's
    with caplog.at_level("WARNING", logger="wast3d.pretrain"):
        other.train(ck, progress=False, stop_at=3)
    assert other.step == 3 and "regularize" in caplog.text and "starts over" in caplog.text


def test_regularizers_reduce_anisotropy(tiny_dataset):
    ds = load_blender(tiny_dataset, holdout_every=4)
    plain = Trainer(ds, _cfg(iterations=80))
    plain.train(progress=False)
    reg = Trainer(ds, _cfg(iterations=80, regularize=True, aniso_weight=1.0, unif_weight=10.0))
    reg.train(progress=False)
    ratio = lambda t: float((t.params["scales"].detach().exp().max(1).values / t.params["scales"].detach().exp().min(1).values).mean())  # noqa: E731
    assert ratio(reg) < ratio(plain)


def test_target_pixels_sets_eq2_target_from_the_views_and_pulls_the_scales_there(tiny_dataset):
    """s_hat = target_pixels x (median camera distance to the look-at point / focal length); with a
    weight that counts, the trained scales end nearer that size than without the term."""
    from wast3d.pretrain import look_at_centre, pixel_footprint

    ds = load_blender(tiny_dataset, holdout_every=4)
    c = look_at_centre(ds)
    fp = pixel_footprint(ds, c)
    v = ds.train[0].camera
    assert fp == pytest.approx(float(np.median([float((w.camera.center - c).norm()) / w.camera.fx for w in ds.train])))
    assert 0 < fp < float((v.center - c).norm())
    tr = Trainer(ds, _cfg(iterations=40, regularize=True, target_pixels=0.5, unif_weight=1000.0, lr_scales=0.04))
    assert tr.target_scale == pytest.approx(0.5 * fp)
    assert Trainer(ds, _cfg(regularize=True, target_pixels=0.5, target_scale=0.02)).target_scale == 0.02
    tr.train(progress=False)
    plain = Trainer(ds, _cfg(iterations=40, lr_scales=0.04))
    plain.train(progress=False)
    # |log(s / s_hat)|: Adam moves a log-scale by at most about lr_scales per step (1.6 in 40 steps)
    err = lambda t: float((t.params["scales"].detach() - math.log(0.5 * fp)).abs().median())  # noqa: E731
    assert err(tr) < err(plain) - 0.25  # measured 0.64 against 0.95


def test_cli_bad_dataset(tmp_path):
    (tmp_path / "transforms_train.json").write_text('{"camera_angle_x": 0.7}')
    r = subprocess.run([sys.executable, "-m", "wast3d", "pretrain", "--data", str(tmp_path), "--out-ply", str(tmp_path / "o.ply"),
                        "--out-csv", str(tmp_path / "o.csv"), "--out-json", str(tmp_path / "o.json")],
                       capture_output=True, text=True)
    assert r.returncode == 2 and "missing field 'frames'" in r.stderr
    assert not (tmp_path / "o.ply").exists()

"""Spherical harmonics: the basis is the renderer's, and rotating a scene rotates its view-dependent
colour with it (renders of ``scene.transform(R, t)`` equal renders of ``scene`` from the camera mapped
back by the inverse transform)."""

import pytest
import torch

from conftest import random_scene, real_3dgs
from wast3d.cameras import Camera, look_at
from wast3d.gaussians import quat_to_rotmat
from wast3d.rasterizer import rasterize
from wast3d.sh import eval_sh, rotate_sh_rest, sh_basis, sh_rotation_matrices


def random_rotation(seed: int, dtype=torch.float64) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return quat_to_rotmat(torch.randn(1, 4, generator=g, dtype=dtype))[0]


def test_rotation_matrices_are_orthogonal_compose_and_match_the_basis():
    R1, R2 = random_rotation(1), random_rotation(2)
    M1, M2, M12 = (sh_rotation_matrices(R[None], 3) for R in (R1, R2, R1 @ R2))
    for l, (a, b, ab) in enumerate(zip(M1, M2, M12), start=1):
        eye = torch.eye(2 * l + 1, dtype=torch.float64)
        torch.testing.assert_close(a[0] @ a[0].T, eye, atol=1e-12, rtol=0)   # the band's norm is kept
        torch.testing.assert_close(ab[0], a[0] @ b[0], atol=1e-12, rtol=0)    # rotating by R1 R2 = by R2, then R1
        torch.testing.assert_close(sh_rotation_matrices(torch.eye(3, dtype=torch.float64)[None], l)[-1][0], eye,
                                   atol=1e-12, rtol=0)
    # the defining property on directions the fit never saw: c' . Y(v) = c . Y(R^T v)
    g = torch.Generator().manual_seed(3)
    v = torch.nn.functional.normalize(torch.randn(500, 3, generator=g, dtype=torch.float64), dim=-1)
    c = torch.randn(500, 15, 3, generator=g, dtype=torch.float64)
    c_rot = rotate_sh_rest(c, R1)
    full = lambda rest: torch.cat([torch.zeros(500, 1, 3, dtype=torch.float64), rest], dim=1)  # noqa: E731
    torch.testing.assert_close(eval_sh(full(c_rot), v, 3), eval_sh(full(c), v @ R1, 3), atol=1e-12, rtol=0)
    assert sh_basis(v, 3).shape == (500, 16)


def transformed_renders(scene, R, t, eyes, backend):
    """Max |render(scene.transform(R, t), cam) - render(scene, cam mapped back)| over the eyes, and the
    same with the SH left unrotated (what the code did before)."""
    dt = scene.means.dtype
    T = torch.eye(4, dtype=dt)
    T[:3, :3], T[:3, 3] = R, t
    moved = scene.transform(R, t)
    unrotated = type(moved)(**{**moved.__dict__, "sh_rest": scene.sh_rest})
    centre = scene.means.mean(0)
    radius = (scene.means - centre).norm(dim=-1).quantile(0.9).item()
    err = err_unrotated = 0.0
    for eye in eyes:
        target = R @ centre + t
        w2c = look_at(target + 3 * radius * torch.tensor(eye, dtype=dt), target).to(dt)
        cam, cam_back = (Camera(w, 64.0, 64.0, 32.0, 32.0, 64, 64) for w in (w2c, w2c @ T))
        ref = rasterize(scene, cam_back, backend=backend).rgb
        err = max(err, (rasterize(moved, cam, backend=backend).rgb - ref).abs().max().item())
        err_unrotated = max(err_unrotated, (rasterize(unrotated, cam, backend=backend).rgb - ref).abs().max().item())
    return err, err_unrotated


EYES = [(1.0, 0.0, 0.3), (0.0, -1.0, 0.5), (-0.7, 0.7, -0.4), (0.2, 0.2, 1.0)]


@pytest.mark.parametrize("backend", ["torch", "native"])
def test_transform_rotates_view_dependent_colour(backend):
    s = random_scene(300, sh_degree=3, dtype=torch.float64)
    if backend == "native":
        s = s.to(dtype=torch.float32)
    R = random_rotation(0, s.means.dtype)
    err, err_unrotated = transformed_renders(s, R, torch.tensor([0.3, -0.2, 0.5], dtype=s.means.dtype), EYES, backend)
    assert err < 1e-5, err
    assert err_unrotated > 0.1  # the check can fail: without the SH rotation the colours differ


def test_transform_rotates_view_dependent_colour_of_a_real_sh3_scene():
    from wast3d.ply import read_ply

    s = read_ply(real_3dgs("fruit_drops_sh3.ply")).to(dtype=torch.float64)
    assert s.sh_degree == 3
    R = random_rotation(5)
    err, err_unrotated = transformed_renders(s, R, torch.tensor([1.0, 2.0, -0.5], dtype=torch.float64), EYES, "torch")
    assert err < 1e-5, err
    assert err_unrotated > 1e-2, err_unrotated

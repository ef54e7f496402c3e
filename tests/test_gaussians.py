import torch

from conftest import random_scene
from wast3d.gaussians import GaussianScene, quat_to_rotmat, rotmat_to_quat


def _random_rotation(seed):
    q = torch.randn(1, 4, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    return quat_to_rotmat(q)[0]


def test_quaternion_round_trip():
    q = torch.randn(500, 4, dtype=torch.float64)
    q = q / q.norm(dim=1, keepdim=True)
    q = torch.where(q[:, :1] < 0, -q, q)
    assert torch.allclose(rotmat_to_quat(quat_to_rotmat(q)), q, atol=1e-10)
    R = quat_to_rotmat(q)
    assert torch.allclose(torch.linalg.det(R), torch.ones(500, dtype=torch.float64))


def test_transform_means_and_covariances():
    s = random_scene(50, dtype=torch.float64)
    R = _random_rotation(0)
    t = torch.tensor([0.3, -1.0, 2.0], dtype=torch.float64)
    for scale in (2.0, torch.tensor([0.5, 2.0, 1.3], dtype=torch.float64)):
        out = s.transform(R, t, scale)
        A = R * torch.as_tensor(scale, dtype=torch.float64).expand(3)[None, :]
        assert torch.allclose(out.means, s.means @ A.T + t)
        assert torch.allclose(out.covariances, A @ s.covariances @ A.T, atol=1e-10)
        assert torch.allclose(torch.linalg.det(out.rotations), torch.ones(50, dtype=torch.float64))


def test_subset_concat_sh_degree():
    a, b = random_scene(10, sh_degree=0), random_scene(5, sh_degree=2)
    c = GaussianScene.concat([a, b])
    assert len(c) == 15 and c.sh_degree == 2
    assert torch.equal(c.sh_rest[:10], torch.zeros(10, 8, 3))
    assert torch.equal(c.subset(torch.arange(10, 15)).means, b.means)

import os
from pathlib import Path

import pytest
import torch

torch.set_flush_denormal(True)
os.environ.setdefault("WAST3D_CACHE", str(Path(__file__).resolve().parents[1] / ".venv" / "wast3d-cache"))

ROOT = Path(__file__).resolve().parents[1]
LEGO = ROOT.parent / "shared" / "data" / "nerf_synthetic_lego_200"


@pytest.fixture
def lego_path():
    if not (LEGO / "transforms_train.json").exists():
        pytest.skip(f"real data not present at {LEGO}")
    return LEGO


def random_scene(n=200, sh_degree=0, seed=0, dtype=torch.float32, spread=0.5):
    from wast3d.gaussians import GaussianScene

    g = torch.Generator().manual_seed(seed)
    s = GaussianScene.from_activated(
        torch.randn(n, 3, generator=g, dtype=dtype) * spread,
        torch.rand(n, 3, generator=g, dtype=dtype) * 0.08 + 0.02,
        torch.randn(n, 4, generator=g, dtype=dtype),
        torch.rand(n, generator=g, dtype=dtype) * 0.9 + 0.05,
        torch.rand(n, 3, generator=g, dtype=dtype),
        sh_degree=sh_degree,
    )
    s.sh_rest.normal_(0, 0.2, generator=g)
    return s

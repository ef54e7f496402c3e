import os
from pathlib import Path

import pytest
import torch

torch.set_flush_denormal(True)
os.environ.setdefault("WAST3D_CACHE", str(Path(__file__).resolve().parents[1] / ".venv" / "wast3d-cache"))

ROOT = Path(__file__).resolve().parents[1]
LEGO = ROOT.parent / "shared" / "data" / "nerf_synthetic_lego_200"
REAL_3DGS = ROOT.parent / "shared" / "data" / "real_3dgs"


def real_3dgs(name: str) -> Path:
    """A file of ../shared/data/real_3dgs (see its README); skips the test where it is absent."""
    p = REAL_3DGS / name
    if not p.exists():
        pytest.skip(f"real data not present at {p}")
    return p


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


TINY_CLIP = {"embed_dim": 16, "vision_cfg": {"image_size": 32, "layers": 1, "width": 32, "patch_size": 8, "head_width": 16},
             "text_cfg": {"context_length": 8, "vocab_size": 64, "width": 16, "heads": 1, "layers": 1}}


def write_tiny_clip(folder: Path, seed: int = 0) -> tuple[Path, Path]:
    """A tiny randomly initialised open_clip model: its config (``wast3d-tiny-clip.json``) and weights
    saved to a local file, as a real checkpoint would be (written once: an existing file is kept, so its
    modification time stays). Returns (config path, checkpoint path)."""
    import json

    import open_clip

    folder.mkdir(parents=True, exist_ok=True)
    cfg, ckpt = folder / "wast3d-tiny-clip.json", folder / "tiny-clip.pt"
    if not cfg.exists():
        cfg.write_text(json.dumps(TINY_CLIP))
    open_clip.add_model_config(cfg)
    if not ckpt.exists():
        torch.manual_seed(seed)
        torch.save(open_clip.create_model("wast3d-tiny-clip", pretrained=None).state_dict(), ckpt)
    return cfg, ckpt

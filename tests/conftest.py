import os
from pathlib import Path

import pytest
import torch

torch.set_flush_denormal(True)
os.environ.setdefault("WAST3D_CACHE", str(Path(__file__).resolve().parents[1] / ".venv" / "wast3d-cache"))

ROOT = Path(__file__).resolve().parents[1]
LEGO = ROOT.parent / "shared" / "data" / "nerf_synthetic_lego_200"
REAL_3DGS = ROOT.parent / "shared" / "data" / "real_3dgs"


def slurm_controller_answers() -> bool:
    """Whether ``scontrol ping`` reaches a SLURM controller (False where SLURM's client is absent, or
    the controller is down or unconfigured: scontrol then retries for up to a minute, hence the timeout)."""
    import shutil
    import subprocess

    if shutil.which("scontrol") is None:
        return False
    try:
        return subprocess.run(["scontrol", "ping"], capture_output=True, timeout=3).returncode == 0
    except subprocess.TimeoutExpired:
        return False


SCONTROL_STANDIN: dict = {"dir": None}


def use_scontrol_standin(on: bool) -> None:
    """Put the stand-in ``scontrol`` of :func:`_no_wait_on_an_absent_slurm_controller` first on PATH, or
    take it off (the local SLURM cluster's tests need the real one)."""
    d = SCONTROL_STANDIN["dir"]
    if d is None:
        return
    parts = [x for x in os.environ["PATH"].split(os.pathsep) if x != d]
    os.environ["PATH"] = os.pathsep.join(([d] if on else []) + parts)


@pytest.fixture(scope="session", autouse=True)
def _no_wait_on_an_absent_slurm_controller(tmp_path_factory):
    """Snakemake loads its SLURM executor plugin on every start, and the plugin runs ``scontrol show
    config`` then (10 s timeout): with SLURM's client installed and no controller up (slurm-wlm
    installed by .ci/run, the local cluster not started) every Snakemake run of the suite waited about
    9 s for it, 4-5 minutes in all. Where no controller answers, a stand-in ``scontrol`` that fails at
    once goes first on PATH for the session (the plugin then assumes its defaults, as without SLURM)."""
    import shutil

    if shutil.which("scontrol") is None or slurm_controller_answers():
        yield
        return
    d = tmp_path_factory.mktemp("scontrol-standin")
    (d / "scontrol").write_text("#!/bin/sh\necho 'scontrol stand-in (tests/conftest.py): no SLURM controller' >&2\nexit 1\n")
    (d / "scontrol").chmod(0o755)
    SCONTROL_STANDIN["dir"] = str(d)
    use_scontrol_standin(True)
    try:
        yield
    finally:
        use_scontrol_standin(False)
        SCONTROL_STANDIN["dir"] = None


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


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory):
    """The tiny workflow (tests/test_workflow.py's TINY, CLIP from a tiny random model) run once: a
    session's tests read it, and the ones that run more copy it first (:func:`copy_of_tiny_run`)."""
    from test_workflow import snake, tiny_config

    wd = tmp_path_factory.mktemp("wf")
    snake(wd, config=tiny_config(wd))
    return wd


def copy_of_tiny_run(tiny_run: Path, to: Path) -> Path:
    """The tiny run's work folder copied to ``to`` (times kept, so that Snakemake finds its outputs up to
    date there): a test that runs more of the workflow starts from it without touching the original."""
    import shutil

    shutil.copytree(tiny_run, to, symlinks=True, copy_function=shutil.copy2)
    return to

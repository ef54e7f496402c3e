"""Scene files by extension (wast3d.formats): the .splat format of the common web viewers."""

import numpy as np
import pytest
import torch

from conftest import random_scene
from wast3d.formats import SPLAT_DTYPE, read_scene, read_splat, write_scene
from wast3d.ply import PlyError


def test_splat_round_trip_keeps_what_the_format_holds(tmp_path, caplog):
    """Positions and scales exactly (float32), colours and opacities to 1/255, rotations to 1/128 (as
    the same rotation: q and -q are one), SH rest dropped with a warning; a second round trip is exact."""
    s = random_scene(400, sh_degree=1, seed=3)
    write_scene(tmp_path / "a.splat", s)
    assert (tmp_path / "a.splat").stat().st_size == 32 * len(s)
    assert "SH degree 1 dropped" in caplog.text
    r = read_scene(tmp_path / "a.splat")
    assert r.sh_degree == 0 and len(r) == len(s)
    assert torch.equal(r.means, s.means)
    assert torch.allclose(r.scales, s.scales, rtol=1e-6)
    assert (r.rgb - s.rgb.clamp(0, 1)).abs().max() <= 0.5 / 255 + 1e-6
    assert (r.opacities - s.opacities).abs().max() <= 0.5 / 255 + 1e-6
    qa = s.quats / s.quats.norm(dim=1, keepdim=True)
    qb = r.quats / r.quats.norm(dim=1, keepdim=True)
    assert (qa * qb).sum(1).abs().min() > 0.99
    write_scene(tmp_path / "b.splat", r)
    a = np.frombuffer((tmp_path / "a.splat").read_bytes(), dtype=SPLAT_DTYPE)
    b = np.frombuffer((tmp_path / "b.splat").read_bytes(), dtype=SPLAT_DTYPE)
    for field in ("position", "scale", "rgba"):
        assert np.array_equal(a[field], b[field]), field
    # a quantized quaternion is renormalized before it is quantized again: one step at most
    assert np.abs(a["rot"].astype(int) - b["rot"].astype(int)).max() <= 1


def test_splat_layout(tmp_path):
    """The bytes of one Gaussian, as the web viewers read them."""
    from wast3d.gaussians import GaussianScene

    s = GaussianScene.from_activated(torch.tensor([[1.0, 2.0, 3.0]]), torch.tensor([[0.1, 0.2, 0.3]]),
                                     torch.tensor([[1.0, 0.0, 0.0, 0.0]]), opacities=0.5,
                                     rgb=torch.tensor([[1.0, 0.0, 0.5]]))
    write_scene(tmp_path / "one.splat", s)
    rec = np.frombuffer((tmp_path / "one.splat").read_bytes(), dtype=SPLAT_DTYPE)[0]
    assert rec["position"].tolist() == [1.0, 2.0, 3.0]
    assert np.allclose(rec["scale"], [0.1, 0.2, 0.3])
    assert rec["rgba"].tolist() == [255, 0, 128, 128]
    assert rec["rot"].tolist() == [255, 128, 128, 128]


def test_ply_and_splat_through_the_cli(tmp_path):
    from wast3d.cli import main
    from wast3d.ply import read_ply, write_ply

    s = random_scene(50, seed=1)
    write_ply(tmp_path / "s.ply", s)
    assert main(["export", str(tmp_path / "s.ply"), str(tmp_path / "s.splat")]) == 0
    assert main(["import-ply", str(tmp_path / "s.splat"), str(tmp_path / "back.ply")]) == 0
    back = read_ply(tmp_path / "back.ply")
    assert torch.equal(back.means, s.means)
    assert main(["export", str(tmp_path / "s.ply"), str(tmp_path / "s.obj")]) == 2  # unknown format: one line


@pytest.mark.parametrize("case, field", [
    ("truncated", "not a whole number"), ("empty", "not a whole number"), ("nan", "'position'"),
    ("scale", "'scale'"), ("rot", "'rot'"),
])
def test_bad_splat_files_name_the_file_and_the_field(tmp_path, case, field):
    rec = np.zeros(4, dtype=SPLAT_DTYPE)
    rec["scale"] = 0.1
    rec["rot"] = [255, 128, 128, 128]
    if case == "nan":
        rec["position"][2, 1] = np.nan
    if case == "scale":
        rec["scale"][1, 0] = 0
    if case == "rot":
        rec["rot"][3] = 128
    raw = rec.tobytes()
    raw = raw[:-5] if case == "truncated" else b"" if case == "empty" else raw
    path = tmp_path / f"{case}.splat"
    path.write_bytes(raw)
    with pytest.raises(PlyError, match=field) as e:
        read_splat(path)
    assert str(path) in str(e.value)
    with pytest.raises(FileNotFoundError, match="nothere.splat"):
        read_scene(tmp_path / "nothere.splat")

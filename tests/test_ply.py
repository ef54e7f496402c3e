import subprocess
import sys

import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement

from conftest import random_scene
from wast3d.ply import PlyError, property_names, read_ply, write_ply


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_round_trip_bit_exact(tmp_path, degree):
    s = random_scene(300, sh_degree=degree, seed=degree)
    p1, p2 = tmp_path / "a.ply", tmp_path / "b.ply"
    write_ply(p1, s)
    r = read_ply(p1)
    assert r.sh_degree == degree
    for k, v in s.tensors().items():
        assert torch.equal(getattr(r, k), v), k  # bit-exact float32
    write_ply(p2, r)
    assert p1.read_bytes() == p2.read_bytes()


def test_layout_matches_reference(tmp_path):
    s = random_scene(5, sh_degree=1)
    write_ply(tmp_path / "a.ply", s)
    v = PlyData.read(str(tmp_path / "a.ply"))["vertex"]
    assert [p.name for p in v.properties] == property_names(1)
    assert all(v[p.name].dtype == np.float32 for p in v.properties)
    # f_rest is channel-major: f_rest_0..2 are the red coefficients 1..3, f_rest_3 is green's first
    assert np.array_equal(v["f_rest_1"], s.sh_rest[:, 1, 0].numpy())
    assert np.array_equal(v["f_rest_3"], s.sh_rest[:, 0, 1].numpy())
    assert np.array_equal(v["opacity"], s.opacity_logits.numpy())
    assert np.array_equal(v["scale_2"], s.log_scales[:, 2].numpy())


def _write_props(path, props: dict):
    rec = np.empty(len(next(iter(props.values()))), dtype=[(k, "<f4") for k in props])
    for k, a in props.items():
        rec[k] = a
    PlyData([PlyElement.describe(rec, "vertex")]).write(str(path))


def _props(s):
    from wast3d.ply import scene_to_array

    a = scene_to_array(s)
    return {n: a[:, i] for i, n in enumerate(property_names(s.sh_degree))}


def test_truncated(tmp_path):
    write_ply(tmp_path / "a.ply", random_scene(100))
    data = (tmp_path / "a.ply").read_bytes()
    (tmp_path / "t.ply").write_bytes(data[: len(data) - 200])
    with pytest.raises(PlyError, match=r"t\.ply.*truncated"):
        read_ply(tmp_path / "t.ply")


def test_garbage_and_missing_file(tmp_path):
    (tmp_path / "g.ply").write_bytes(b"not a ply at all\n" * 10)
    with pytest.raises(PlyError, match="g.ply"):
        read_ply(tmp_path / "g.ply")
    with pytest.raises(FileNotFoundError, match="nope.ply"):
        read_ply(tmp_path / "nope.ply")


@pytest.mark.parametrize("prop", ["opacity", "scale_1", "rot_3", "f_dc_2", "y"])
def test_missing_property(tmp_path, prop):
    p = _props(random_scene(10))
    del p[prop]
    _write_props(tmp_path / "m.ply", p)
    with pytest.raises(PlyError, match=rf"m\.ply: missing property '{prop}'"):
        read_ply(tmp_path / "m.ply")


def test_wrong_rest_count(tmp_path):
    p = _props(random_scene(10, sh_degree=1))
    del p["f_rest_8"], p["f_rest_7"], p["f_rest_6"]  # 6 values: 2 per channel, no SH degree
    _write_props(tmp_path / "r.ply", p)
    with pytest.raises(PlyError, match=r"r\.ply: property f_rest_\*: 6 values"):
        read_ply(tmp_path / "r.ply")
    p = _props(random_scene(10, sh_degree=1))
    del p["f_rest_4"]
    _write_props(tmp_path / "gap.ply", p)
    with pytest.raises(PlyError, match="gap.ply.*missing f_rest_4"):
        read_ply(tmp_path / "gap.ply")


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_nan_inf(tmp_path, bad, caplog):
    p = _props(random_scene(20))
    p["scale_0"][[3, 7]] = bad
    _write_props(tmp_path / "n.ply", p)
    with pytest.raises(PlyError, match=r"n\.ply: field 'scale': 2 Gaussians with values that are NaN, infinite or not positive once decoded \(first at row 3\)"):
        read_ply(tmp_path / "n.ply")
    s = read_ply(tmp_path / "n.ply", drop_invalid=True)
    assert len(s) == 18 and torch.isfinite(s.log_scales).all()
    assert "dropped 2 of 20" in caplog.text


def test_point_cloud(tmp_path):
    xyz = np.random.default_rng(0).normal(size=(50, 3)).astype(np.float32)
    rec = np.empty(50, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    rec["x"], rec["y"], rec["z"] = xyz.T
    rec["red"], rec["green"], rec["blue"] = 255, 0, 128
    PlyData([PlyElement.describe(rec, "vertex")]).write(str(tmp_path / "pc.ply"))
    s = read_ply(tmp_path / "pc.ply")
    assert len(s) == 50 and s.sh_degree == 0
    assert torch.allclose(s.rgb[0], torch.tensor([1.0, 0.0, 128 / 255]), atol=1e-5)
    assert torch.allclose(s.opacities, torch.full((50,), 0.1), atol=1e-6)
    assert (s.scales > 0).all() and torch.equal(s.means, torch.from_numpy(xyz))


def test_atomic_write_keeps_old_file(tmp_path, monkeypatch):
    p = tmp_path / "a.ply"
    write_ply(p, random_scene(10))
    before = p.read_bytes()

    def boom(*a, **k):
        raise RuntimeError("disk full")

    monkeypatch.setattr("wast3d.ply.PlyData.write", boom)
    with pytest.raises(RuntimeError):
        write_ply(p, random_scene(20))
    assert p.read_bytes() == before
    assert [f.name for f in tmp_path.iterdir()] == ["a.ply"]  # no temporary left behind


def test_atomic_write_gives_the_permissions_of_a_plain_open(tmp_path):
    """Not the owner-only mode of a temporary file: 0666 less the umask (0644 under umask 022)."""
    import os

    old = os.umask(0o022)
    try:
        write_ply(tmp_path / "a.ply", random_scene(5))
        with open(tmp_path / "plain", "w"):
            pass
    finally:
        os.umask(old)
    assert (tmp_path / "a.ply").stat().st_mode & 0o777 == (tmp_path / "plain").stat().st_mode & 0o777 == 0o644


def test_info_cli(tmp_path):
    import json

    write_ply(tmp_path / "a.ply", random_scene(64, sh_degree=2))
    out = subprocess.run([sys.executable, "-m", "wast3d", "info", str(tmp_path / "a.ply"), "--json"],
                         capture_output=True, text=True, check=True).stdout
    info = json.loads(out)
    assert info["valid"] and info["count"] == 64 and info["sh_degree"] == 2
    assert info["anisotropy"]["q00"] >= 1.0 and 0 < info["opacity"]["q50"] < 1
    (tmp_path / "bad.ply").write_bytes((tmp_path / "a.ply").read_bytes()[:500])
    r = subprocess.run([sys.executable, "-m", "wast3d", "info", str(tmp_path / "bad.ply"), "--json"],
                       capture_output=True, text=True)
    assert r.returncode == 1 and json.loads(r.stdout)["valid"] is False


def test_empty_scene_round_trip(tmp_path):
    """A stage can produce no Gaussians (e.g. everything filtered): the file is valid and keeps the SH degree."""
    from wast3d.gaussians import GaussianScene

    for deg in (0, 3):
        write_ply(tmp_path / f"e{deg}.ply", GaussianScene.empty(sh_degree=deg))
        s = read_ply(tmp_path / f"e{deg}.ply")
        assert len(s) == 0 and s.sh_degree == deg

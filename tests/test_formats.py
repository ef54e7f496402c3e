"""Scene files by extension (wast3d.formats): the .splat format of the common web viewers and
Niantic's SPZ (wast3d.spz)."""

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
    ("scale", "'scale'"), ("rot", "'rotation'"),
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
    _refused(tmp_path / f"{case}.splat", raw, read_splat, field)


def _refused(path, raw, reader, field):
    """``raw`` written to ``path`` is refused by ``reader`` with an error naming the file and ``field``;
    a missing file of that extension is a FileNotFoundError naming it."""
    path.write_bytes(raw)
    with pytest.raises(PlyError, match=field) as e:
        reader(path)
    assert str(path) in str(e.value)
    missing = path.with_name("nothere" + path.suffix)
    with pytest.raises(FileNotFoundError, match=missing.name):
        read_scene(missing)


# ---- SPZ (wast3d.spz) ----------------------------------------------------------------------------


def _spz_body(n, deg, version, pos, alpha, colour, scale, rot, sh=b""):
    import struct

    return struct.pack("<IIIBBBB", 0x5053474E, version, n, deg, 12, 0, 0) + pos + alpha + colour + scale + rot + sh


def _fixed24(v):
    return int(round(v * 4096)).to_bytes(4, "little", signed=True)[:3]


def test_spz_layout_and_axes_by_an_independent_encoder(tmp_path):
    """One Gaussian written byte by byte as the reference library lays it out (version 3, gzip;
    version 4, Zstandard streams), in SPZ's Right-Up-Back axes: it reads back in the PLY's
    Right-Down-Front ones (y and z negated, the quaternion's y and z, the SH signs of y and z)."""
    import gzip
    import struct

    import zstandard

    pos = b"".join(_fixed24(v) for v in (1.0, 2.0, -0.5))
    alpha, colour = bytes([255]), bytes([128, 166, 90])  # DC (c / 255 - 0.5) / 0.15
    scale = bytes([160, 144, 128])  # log-scales s / 16 - 10 = 0, -1, -2
    # smallest three: largest = w (index 3); x = +0.5 / sqrt(1/2) * 511, y = -0.25..., z = 0
    mag = lambda v: int(511 * abs(v) / 0.7071067811865476 + 0.5)  # noqa: E731
    comp = 3
    for v in (0.5, -0.25, 0.0):
        comp = (comp << 10) | ((v < 0) << 9) | mag(v)
    rot = struct.pack("<I", comp)
    sh = bytes([192, 128, 64, 128, 128, 128, 128, 128, 128])  # coefficient 0: (0.5, 0, -0.5) in R, G, B; 1, 2: 0
    body = _spz_body(1, 1, 3, pos, alpha, colour, scale, rot, sh)
    (tmp_path / "v3.spz").write_bytes(gzip.compress(body))
    arrays = [pos, alpha, colour, scale, rot, sh]
    chunks = [zstandard.ZstdCompressor().compress(a) for a in arrays]
    head = struct.pack("<IIIBBBBI12x", 0x5053474E, 4, 1, 1, 12, 0, len(chunks), 32)
    toc = b"".join(struct.pack("<QQ", len(c), len(a)) for c, a in zip(chunks, arrays))
    (tmp_path / "v4.spz").write_bytes(head + toc + b"".join(chunks))
    w = np.sqrt(1 - 0.5**2 - 0.25**2)
    for name in ("v3.spz", "v4.spz"):
        s = read_scene(tmp_path / name)
        assert len(s) == 1 and s.sh_degree == 1
        assert np.allclose(s.means[0].numpy(), [1.0, -2.0, 0.5])
        assert np.allclose(s.log_scales[0].numpy(), [0.0, -1.0, -2.0])
        assert np.allclose(s.sh_dc[0].numpy(), (np.array([128, 166, 90]) / 255 - 0.5) / 0.15, atol=1e-6)
        assert s.opacities[0] > 0.999
        q = s.quats[0].numpy() / np.linalg.norm(s.quats[0].numpy())
        assert np.allclose(q, [w, 0.5, 0.25, -0.0], atol=2e-3), q  # (w, x, -y, -z)
        # degree 1: coefficient 0 (Y_1,-1, odd in y) and 1 (Y_1,0, odd in z) change sign, 2 (x) does not
        assert np.allclose(s.sh_rest[0].numpy(), [[-0.5, 0.0, 0.5], [0, 0, 0], [0, 0, 0]], atol=1e-6)


@pytest.mark.parametrize("version", [2, 3, 4])
def test_spz_round_trip_keeps_what_the_format_holds(tmp_path, version):
    """Each field to its quantization step (positions 1/4096, log-scales 1/16, opacity and DC 1/255,
    SH rest a bucket of 16/128), rotations as the same rotation; a second round trip gives the same
    scene (rotations to within one step of their code)."""
    from wast3d.spz import read_spz, write_spz

    s = random_scene(300, sh_degree=3, seed=4)
    write_spz(tmp_path / "a.spz", s, version=version)
    r = read_spz(tmp_path / "a.spz")
    assert len(r) == len(s) and r.sh_degree == 3
    assert (r.means - s.means).abs().max() <= 0.5 / 4096 + 1e-6
    assert (r.log_scales - s.log_scales).abs().max() <= 0.5 / 16 + 1e-6
    assert (r.opacities - s.opacities).abs().max() <= 0.5 / 255 + 1e-6
    assert (r.sh_dc - s.sh_dc).abs().max() <= 0.5 / (0.15 * 255) + 1e-6
    assert (r.sh_rest - s.sh_rest).abs().max() <= (8 + 0.5) / 128 + 1e-6
    qa = s.quats / s.quats.norm(dim=1, keepdim=True)
    qb = r.quats / r.quats.norm(dim=1, keepdim=True)
    assert (qa * qb).sum(1).abs().min() > (0.9999 if version >= 3 else 0.99)
    write_spz(tmp_path / "b.spz", r, version=version)
    r2 = read_spz(tmp_path / "b.spz")
    for f in ("means", "log_scales", "opacity_logits", "sh_dc", "sh_rest"):
        assert torch.equal(getattr(r2, f), getattr(r, f)), f
    assert (r2.quats * r.quats).sum(1).abs().min() > 0.9999


def test_spz_through_the_cli(tmp_path):
    from wast3d.cli import main
    from wast3d.ply import read_ply, write_ply

    s = random_scene(50, sh_degree=1, seed=1)
    write_ply(tmp_path / "s.ply", s)
    assert main(["export", str(tmp_path / "s.ply"), str(tmp_path / "s.spz")]) == 0
    assert main(["import-ply", str(tmp_path / "s.spz"), str(tmp_path / "back.ply")]) == 0
    back = read_ply(tmp_path / "back.ply")
    assert back.sh_degree == 1 and (back.means - s.means).abs().max() <= 0.5 / 4096 + 1e-6


@pytest.mark.parametrize("case, field", [
    ("empty", "header"), ("magic", "'magic'"), ("version", "'version'"), ("truncated", "stream 'sh'"),
    ("gzip_truncated", "gzip stream"), ("legacy_short", "field 'rotations'"), ("corrupt", "stream 'positions'"),
    ("degree", "'shDegree'"),
])
def test_bad_spz_files_name_the_file_and_the_field(tmp_path, case, field):
    import gzip
    import struct

    from wast3d.spz import read_spz, write_spz

    write_spz(tmp_path / "good.spz", random_scene(20, sh_degree=1, seed=0))
    raw = (tmp_path / "good.spz").read_bytes()
    legacy = _spz_body(4, 0, 3, bytes(36), bytes(4), bytes(12), bytes(12), bytes(16))
    raw = {
        "empty": b"",
        "magic": b"XXXX" + raw[4:],
        "version": raw[:4] + struct.pack("<I", 5) + raw[8:],
        "truncated": raw[:-3],
        "gzip_truncated": gzip.compress(legacy)[:-10],
        "legacy_short": gzip.compress(legacy[:-10]),
        "corrupt": raw[:32 + 16 * 6] + bytes(20) + raw[32 + 16 * 6 + 20:],
        "degree": raw[:12] + bytes([7]) + raw[13:],
    }[case]
    _refused(tmp_path / f"{case}.spz", raw, read_spz, field)
    with pytest.raises(ValueError, match="version 9"):
        write_spz(tmp_path / "x.spz", random_scene(2, seed=0), version=9)


def test_spz_clamps_log_scales_beyond_its_range_and_says_so(tmp_path, caplog):
    from wast3d.spz import read_spz, write_spz

    s = random_scene(10, seed=0)
    s.log_scales[3, 1] = -11.0
    write_spz(tmp_path / "c.spz", s)
    assert "1 Gaussians have log-scales outside" in caplog.text
    assert read_spz(tmp_path / "c.spz").log_scales[3, 1] == -10.0

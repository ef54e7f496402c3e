"""The PlayCanvas/SuperSplat compressed PLY: a real SuperSplat export (the guitar) and files written by
an independent encoder below (both chunk layouts, with and without the ``sh`` element)."""

import math

import numpy as np
import pytest
from numpy.lib.recfunctions import repack_fields
import torch
from plyfile import PlyData, PlyElement

from conftest import random_scene, real_3dgs
from wast3d.gaussians import quat_to_rotmat
from wast3d.ply import PlyError, is_gaussian_ply, read_ply

SH_C0 = 0.28209479177387814


def _unorm(x, bits):
    t = (1 << bits) - 1
    return np.clip(np.floor(x * t + 0.5), 0, t).astype(np.uint32)


def encode(scene, colour_ranges: bool, with_sh: bool) -> list[PlyElement]:
    """A compressed PLY as SuperSplat's exporter writes it (written from its description: chunks of
    256, 11-10-11 positions and log-scales, 2+3x10-bit rotations, 8888 colour and opacity)."""
    n = len(scene)
    nch = math.ceil(n / 256)
    mean, ls = scene.means.double().numpy(), scene.log_scales.double().numpy()
    q = torch.nn.functional.normalize(scene.quats.double(), dim=-1).numpy()
    rgb, op = scene.rgb.double().numpy(), scene.opacities.double().numpy()
    chunk = {k: np.zeros(nch, np.float32) for k in ("min_x", "min_y", "min_z", "max_x", "max_y", "max_z",
                                                    "min_scale_x", "min_scale_y", "min_scale_z",
                                                    "max_scale_x", "max_scale_y", "max_scale_z")}
    if colour_ranges:
        chunk.update({k: np.zeros(nch, np.float32) for k in ("min_r", "min_g", "min_b", "max_r", "max_g", "max_b")})
    packed = np.zeros((n, 4), np.uint32)
    for c in range(nch):
        r = slice(c * 256, min(n, (c + 1) * 256))

        def norm(a, lo_names, hi_names):
            lo, hi = a.min(0), a.max(0)
            for j in range(3):
                chunk[lo_names[j]][c], chunk[hi_names[j]][c] = lo[j], hi[j]
            lo, hi = np.array([chunk[k][c] for k in lo_names], float), np.array([chunk[k][c] for k in hi_names], float)
            return (a - lo) / np.where(hi > lo, hi - lo, 1)

        p = norm(mean[r], ("min_x", "min_y", "min_z"), ("max_x", "max_y", "max_z"))
        s = norm(ls[r], ("min_scale_x", "min_scale_y", "min_scale_z"), ("max_scale_x", "max_scale_y", "max_scale_z"))
        col = norm(rgb[r], ("min_r", "min_g", "min_b"), ("max_r", "max_g", "max_b")) if colour_ranges else rgb[r]
        packed[r, 0] = _unorm(p[:, 0], 11) << 21 | _unorm(p[:, 1], 10) << 11 | _unorm(p[:, 2], 11)
        packed[r, 2] = _unorm(s[:, 0], 11) << 21 | _unorm(s[:, 1], 10) << 11 | _unorm(s[:, 2], 11)
        packed[r, 3] = (_unorm(col[:, 0], 8) << 24 | _unorm(col[:, 1], 8) << 16 | _unorm(col[:, 2], 8) << 8
                        | _unorm(op[r], 8))
        qq = q[r].copy()
        big = np.abs(qq).argmax(1)
        qq *= np.sign(qq[np.arange(len(qq)), big])[:, None]
        word = big.astype(np.uint32)
        for i in range(len(qq)):
            w = int(big[i])
            for j in range(4):
                if j != big[i]:
                    w = (w << 10) | int(_unorm(qq[i, j] * math.sqrt(2) * 0.5 + 0.5, 10))
            word[i] = w
        packed[r, 1] = word
    rec = np.empty(nch, dtype=[(k, "<f4") for k in chunk])
    for k, v in chunk.items():
        rec[k] = v
    vrec = np.empty(n, dtype=[(k, "<u4") for k in ("packed_position", "packed_rotation", "packed_scale", "packed_color")])
    for j, k in enumerate(vrec.dtype.names):
        vrec[k] = packed[:, j]
    els = [PlyElement.describe(rec, "chunk"), PlyElement.describe(vrec, "vertex")]
    if with_sh:
        rest = scene.sh_rest.double().numpy().transpose(0, 2, 1).reshape(n, -1)  # channel-major
        srec = np.empty(n, dtype=[(f"f_rest_{i}", "u1") for i in range(rest.shape[1])])
        for i in range(rest.shape[1]):
            srec[f"f_rest_{i}"] = np.clip(np.floor((rest[:, i] + 4) / 8 * 255 + 0.5), 0, 255)
        els.append(PlyElement.describe(srec, "sh"))
    return els


@pytest.mark.parametrize("colour_ranges, with_sh", [(False, False), (True, False), (True, True)])
def test_decodes_what_the_encoder_wrote(tmp_path, colour_ranges, with_sh):
    s = random_scene(700, sh_degree=3 if with_sh else 0, seed=1)  # 3 chunks, the last one partial
    path = tmp_path / "c.ply"
    PlyData(encode(s, colour_ranges, with_sh), text=False).write(str(path))
    assert is_gaussian_ply(path)
    d = read_ply(path)
    assert len(d) == 700 and d.sh_degree == s.sh_degree
    ext = (s.means.max(0).values - s.means.min(0).values).max()
    assert (d.means - s.means).abs().max() <= ext / 1023  # 10-11 bits per axis
    assert (d.log_scales - s.log_scales).abs().max() <= 0.01
    torch.testing.assert_close(quat_to_rotmat(d.quats), quat_to_rotmat(s.quats), atol=5e-3, rtol=0)
    assert (d.rgb - s.rgb).abs().max() <= 1 / 255 + 1e-6
    assert (d.opacities - s.opacities).abs().max() <= 1 / 255 + 1e-6
    if with_sh:
        assert (d.sh_rest - s.sh_rest).abs().max() <= 8 / 255
    assert (d.quats.norm(dim=-1) - 1).abs().max() < 1e-6


def test_malformed_compressed_files_name_the_field(tmp_path):
    s = random_scene(300)
    els = encode(s, True, False)
    cases = {
        "element .chunk. has 1 rows": [PlyElement.describe(els[0].data[:1], "chunk"), els[1]],
        "min_scale_y": [PlyElement.describe(repack_fields(els[0].data[[n for n in els[0].data.dtype.names
                                                                      if n != "min_scale_y"]]), "chunk"), els[1]],
    }
    bad = els[0].data.copy()
    bad["max_x"][1] = np.nan
    cases["max_x"] = [PlyElement.describe(bad, "chunk"), els[1]]
    for field, elements in cases.items():
        p = tmp_path / f"{len(field)}.ply"
        PlyData(elements, text=False).write(str(p))
        with pytest.raises(PlyError, match=field) as e:
            read_ply(p)
        assert p.name in str(e.value)
    good = tmp_path / "good.ply"
    PlyData(els, text=False).write(str(good))
    cut = tmp_path / "cut.ply"
    cut.write_bytes(good.read_bytes()[:-50])
    with pytest.raises(PlyError, match="cut.ply: corrupt or truncated"):
        read_ply(cut)


def test_reads_the_supersplat_guitar():
    """The real export: count, finite values, unit quaternions, positions inside the chunk bounds, and
    rotations in the right component order: the thinnest axis of flat Gaussians lies along the local
    surface normal (PCA of 16 neighbours) far more often than for a wrong order or random rotations."""
    from wast3d.geometry import knn

    path = real_3dgs("guitar.compressed.ply")
    s = read_ply(path)
    chunk = PlyData.read(str(path))["chunk"]
    assert len(s) == 90854 and s.sh_degree == 0 and chunk.count == 355
    assert all(torch.isfinite(t).all() for t in s.tensors().values())
    assert (s.quats.norm(dim=-1) - 1).abs().max() < 1e-5
    lo = np.stack([chunk["min_x"], chunk["min_y"], chunk["min_z"]], 1).min(0)
    hi = np.stack([chunk["max_x"], chunk["max_y"], chunk["max_z"]], 1).max(0)
    assert (s.means.numpy() >= lo - 1e-6).all() and (s.means.numpy() <= hi + 1e-6).all()
    assert 0 < s.opacities.min() and s.opacities.max() <= 1 and (s.rgb > -0.5).all()

    srt = s.scales.sort(dim=-1).values
    flat = torch.nonzero((srt[:, 0] < 0.2 * srt[:, 1]) & (s.opacities > 0.5))[:, 0]
    flat = flat[torch.randperm(len(flat), generator=torch.Generator().manual_seed(0))[:3000]]
    _, nn = knn(s.means[flat], s.means, 16)
    p = s.means[nn] - s.means[nn].mean(1, keepdim=True)
    normal = torch.linalg.eigh(p.transpose(1, 2) @ p).eigenvectors[:, :, 0]

    def alignment(q):
        axis = quat_to_rotmat(q[flat])[torch.arange(len(flat)), :, s.scales[flat].argmin(-1)]
        return (axis * normal).sum(-1).abs().mean().item()

    ours = alignment(s.quats)
    assert ours > 0.6, ours  # measured 0.64
    for wrong in ([3, 0, 1, 2], [1, 2, 3, 0]):  # (x, y, z, w) read as (w, x, y, z), and the other roll
        assert alignment(s.quats[:, wrong]) < ours - 0.08
    assert alignment(torch.randn_like(s.quats)) < ours - 0.08  # random: ~0.5


@pytest.mark.parametrize("degree", [0, 2])
def test_the_package_encoder_writes_what_the_independent_one_writes(tmp_path, degree):
    """wast3d's own encoder (write_compressed_ply, vectorized) against the one above (per Gaussian, from
    the layout's description): the same packed words and chunk bounds; read back within its quanta."""
    from wast3d.formats import read_scene, write_scene

    s = random_scene(700, sh_degree=degree, seed=5)
    write_scene(tmp_path / "a.compressed.ply", s)
    ours = PlyData.read(str(tmp_path / "a.compressed.ply"))
    ref = {el.name: el.data for el in encode(s, True, degree > 0)}
    for name in ("packed_position", "packed_rotation", "packed_scale", "packed_color"):
        diff = np.abs(ours["vertex"][name].astype(np.int64) - ref["vertex"][name].astype(np.int64))
        assert (diff == 0).mean() > 0.999, name  # a value on a rounding boundary may differ by float64 noise
    for name in ref["chunk"].dtype.names:  # colours: from f_dc in float64 here, float32 there
        assert np.allclose(ours["chunk"][name], ref["chunk"][name], rtol=1e-5, atol=1e-7), name
    if degree:
        assert all(np.array_equal(ours["sh"][k], ref["sh"][k]) for k in ref["sh"].dtype.names)
    r = read_scene(tmp_path / "a.compressed.ply")
    ext = (s.means.max(0).values - s.means.min(0).values)
    assert ((r.means - s.means).abs() <= ext / 1023 + 1e-6).all()
    assert (r.opacities - s.opacities).abs().max() <= 0.5 / 255 + 1e-6
    assert r.sh_degree == degree

import json
import shutil

import numpy as np
import pytest
import torch

from conftest import random_scene
from wast3d.cameras import camera_from_blender, camera_to_blender
from wast3d.datasets import DatasetError, load_blender
from wast3d.render import export_blender


def test_lego_loader(lego_path):
    ds = load_blender(lego_path, holdout_every=8)
    assert len(ds.train) + len(ds.test) == 80 and len(ds.test) == 10
    v = ds.train[0]
    assert v.image.shape == (200, 200, 3) and v.alpha.shape == (200, 200)
    assert 0 <= float(v.image.min()) and float(v.image.max()) <= 1
    assert float(v.alpha.min()) == 0.0 and float(v.alpha.max()) == 1.0  # transparent background
    # white background compositing: transparent pixels are white
    assert torch.allclose(v.image[v.alpha == 0], torch.ones(1, 3))
    # NeRF-Synthetic cameras sit about 4.03 from the origin and look at it
    for view in ds.all_views[:10]:
        c = view.camera
        assert abs(float(c.center.norm()) - 4.031) < 0.01
        z_axis = c.world_to_cam[2, :3]  # camera forward in world
        assert float(z_axis @ (-c.center / c.center.norm())) > 0.95
    assert abs(ds.train[0].camera.fx - 0.5 * 200 / np.tan(0.5 * 0.6911112070083618)) < 1e-3


def test_blender_axes_round_trip():
    m = torch.tensor([[0.0, 0.0, 1.0, 4.0], [1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.5], [0, 0, 0, 1.0]])
    cam = camera_from_blender(m, 0.7, 100, 80)
    assert torch.allclose(camera_to_blender(cam), m, atol=1e-6)
    # OpenGL camera looks down its -z: a point in front of it has positive OpenCV depth
    p = m[:3, 3] - m[:3, 2]  # one unit along the viewing direction
    assert float((cam.world_to_cam[:3, :3] @ p + cam.world_to_cam[:3, 3])[2]) == pytest.approx(1.0)


def test_export_then_load(tmp_path):
    scene = random_scene(400, seed=1)
    export_blender(scene, tmp_path / "ds", n_views=6, size=32)
    ds = load_blender(tmp_path / "ds", holdout_every=3, background=(0.0, 0.0, 0.0))
    assert len(ds.train) == 4 and len(ds.test) == 2
    assert ds.train[0].image.shape == (32, 32, 3)
    assert float(ds.train[0].alpha.max()) > 0.5


def _copy(lego_or_tmp, tmp_path, n=4):
    src = tmp_path / "src"
    scene = random_scene(200)
    export_blender(scene, src, n_views=n, size=16)
    return src


def test_bad_datasets(tmp_path):
    src = _copy(None, tmp_path)
    with pytest.raises(DatasetError, match="transforms_train.json: file not found"):
        load_blender(tmp_path / "nothing")
    bad = tmp_path / "badjson"
    shutil.copytree(src, bad)
    (bad / "transforms_train.json").write_text("{ not json")
    with pytest.raises(DatasetError, match="badjson/transforms_train.json: invalid JSON"):
        load_blender(bad)
    for field in ("camera_angle_x", "frames"):
        d = tmp_path / f"no_{field}"
        shutil.copytree(src, d)
        meta = json.loads((d / "transforms_train.json").read_text())
        del meta[field]
        (d / "transforms_train.json").write_text(json.dumps(meta))
        with pytest.raises(DatasetError, match=f"missing field '{field}'"):
            load_blender(d)
    d = tmp_path / "missing_image"
    shutil.copytree(src, d)
    (d / "train" / "r_2.png").unlink()
    with pytest.raises(DatasetError, match=r"r_2\.png: image file not found"):
        load_blender(d)
    d = tmp_path / "sizes"
    shutil.copytree(src, d)
    import imageio.v3 as iio

    iio.imwrite(d / "train" / "r_1.png", np.zeros((20, 16, 4), np.uint8))
    with pytest.raises(DatasetError, match=r"r_1\.png: image size 16x20 differs"):
        load_blender(d)
    d = tmp_path / "matrix"
    shutil.copytree(src, d)
    meta = json.loads((d / "transforms_train.json").read_text())
    meta["frames"][0]["transform_matrix"] = [[1, 0], [0, 1]]
    (d / "transforms_train.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match=r"frames\[0\]\.transform_matrix: must be a 4x4 matrix"):
        load_blender(d)

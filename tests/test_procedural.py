import pytest
import torch

from wast3d.gaussians import anisotropy
from wast3d.procedural import CONTENTS, STYLES, make_scene


@pytest.mark.parametrize("name", sorted(STYLES))
def test_style_scenes(name):
    a = make_scene("style", name, 4000, seed=0)
    b = make_scene("style", name, 4000, seed=0)
    c = make_scene("style", name, 4000, seed=1)
    assert 0.6 * 4000 <= len(a) <= 1.1 * 4000
    for k, v in a.tensors().items():
        assert torch.isfinite(v).all(), k
        assert torch.equal(v, getattr(b, k)), k  # deterministic by seed
    assert not torch.equal(a.means[: min(len(a), len(c))], c.means[: min(len(a), len(c))])
    # real local geometry, not colour noise on a plane: relief above the ground and tilted normals
    z = a.means[:, 2]
    assert float(torch.quantile(z, 0.95) - torch.quantile(z, 0.05)) > 0.04
    normal_z = a.rotations[:, 2, 2].abs()  # third axis is the disc normal
    assert float((normal_z < 0.7).float().mean()) > 0.1
    assert float(anisotropy(a.scales).max()) < 6  # discs, no needles
    assert float(a.rgb.std(0).mean()) > 0.02


@pytest.mark.parametrize("name", CONTENTS)
def test_content_scenes(name):
    a = make_scene("content", name, 3000, seed=0)
    assert len(a) == 3000
    assert torch.isfinite(a.means).all() and float(a.means.norm(dim=1).max()) <= 1.0 + 1e-5
    assert torch.equal(a.means, make_scene("content", name, 3000, seed=0).means)
    # shaped as a trained scene's Gaussians, not as the styles' discs: in-plane elongation (log-normal,
    # median 1.5) and thin; so that a metric on Gaussian shape can tell a stylized result from the content
    sc = a.scales.sort(dim=1, descending=True).values
    assert 1.3 < float((sc[:, 0] / sc[:, 1]).median()) < 1.7
    assert float((sc[:, 2] / sc[:, 0]).max()) <= 0.1 + 1e-5
    st = make_scene("style", "pebbles", 3000, seed=0).scales.sort(dim=1, descending=True).values
    assert float((st[:, 0] / st[:, 1]).median()) < 1.05


def test_unknown_names():
    with pytest.raises(ValueError, match="unknown procedural style 'moss'"):
        make_scene("style", "moss", 100)
    with pytest.raises(ValueError, match="unknown content mesh 'teapot'"):
        make_scene("content", "teapot", 100)


@pytest.mark.parametrize("name, elements", [("bouquet", 25), ("pinecone", 100)])
def test_volume_styles_are_objects_with_labelled_elements(name, elements):
    """The volumes have no ground and extend in every direction; each flower or scale is one element."""
    s = make_scene("style", name, 6000, seed=0)
    assert int(s.element.max()) >= elements and 0.6 < float((s.element > 0).float().mean()) < 0.9
    ext = s.means.max(0).values - s.means.min(0).values
    assert float(ext.min() / ext.max()) > 0.5  # an object, not a flat patch
    sizes = torch.bincount(s.element)[1:]
    assert int(sizes.min()) >= 10  # every element has Gaussians enough to be seen whole

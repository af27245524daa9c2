"""The sparse kernel and the filters built from it (paper Eqs. 5-7)."""

import math
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from helpers import kernel_from_file, tap_offsets
from hypothesis import given
from hypothesis import strategies as st
from reference import sparse_kernel_np

from convbki_core import ConvBKIKernel, KernelConfig
from convbki_core.inference.kernels import sparse_kernel
from convbki_core.io.kernel_file import (
    KernelFileError,
    kernel_config_from_dict,
    kernel_config_to_dict,
    load_kernel_file,
    save_kernel_file,
)
from convbki_core.paths import kernel_path

lengths = st.floats(min_value=0.01, max_value=5.0, allow_nan=False)
distances = st.floats(min_value=0.0, max_value=10.0, allow_nan=False)


@given(distances, lengths)
def test_kernel_is_in_unit_interval(distance, ell):
    value = sparse_kernel(torch.tensor(distance, dtype=torch.float64), torch.tensor(ell, dtype=torch.float64))
    assert 0.0 <= float(value) <= 1.0


@given(lengths)
def test_kernel_is_one_at_zero_distance(ell):
    assert float(sparse_kernel(torch.tensor(0.0), torch.tensor(ell))) == pytest.approx(1.0, abs=1e-7)


@given(lengths, st.floats(min_value=1.0, max_value=10.0))
def test_kernel_is_zero_beyond_its_length(ell, factor):
    distance = torch.tensor(ell * factor, dtype=torch.float64)
    assert float(sparse_kernel(distance, torch.tensor(ell, dtype=torch.float64))) == 0.0


@given(lengths, st.lists(distances, min_size=2, max_size=20))
def test_kernel_matches_equation_and_decreases(ell, ds):
    ds = sorted(ds)
    values = sparse_kernel(torch.tensor(ds, dtype=torch.float64), torch.tensor(ell, dtype=torch.float64)).numpy()
    np.testing.assert_allclose(values, sparse_kernel_np(ds, ell), atol=1e-12)
    assert (np.diff(values) <= 1e-12).all(), "k(d) must not increase with distance"


variant_params = st.sampled_from(["single", "per_class", "compound"])


def random_kernel(kind, num_classes, filter_size, resolution, rng, low=0.05, high=1.5):
    draw = lambda n: rng.uniform(low, high, n).tolist()  # noqa: E731
    if kind == "compound":
        return ConvBKIKernel(kind, num_classes, filter_size, resolution, ell_h=draw(num_classes),
                             ell_z=draw(num_classes))
    return ConvBKIKernel(kind, num_classes, filter_size, resolution, ell=draw(1 if kind == "single" else num_classes))


@given(variant_params, st.sampled_from([3, 5, 7, 9]), st.integers(0, 2**31 - 1))
def test_filters_are_symmetric_with_unit_centre(kind, filter_size, seed):
    kernel = random_kernel(kind, 4, filter_size, 0.2, np.random.default_rng(seed))
    filters = kernel.filters().detach()
    assert filters.shape == (4, 1, filter_size, filter_size, filter_size)
    centre = filter_size // 2
    assert torch.all(filters[:, 0, centre, centre, centre] == 1.0)
    assert torch.all((filters >= 0) & (filters <= 1))
    for axis in (2, 3, 4):
        assert torch.equal(filters, filters.flip(axis)), f"filter not symmetric along axis {axis}"
    assert torch.allclose(filters, filters.transpose(2, 3)), "x and y must be interchangeable"
    if kind != "compound":  # spherical kernels are also invariant under any axis permutation
        assert torch.allclose(filters, filters.transpose(2, 4))


@given(st.sampled_from([3, 5, 7]), st.integers(0, 2**31 - 1))
def test_compound_is_product_of_horizontal_and_vertical_parts(filter_size, seed):
    rng = np.random.default_rng(seed)
    kernel = random_kernel("compound", 5, filter_size, 0.2, rng)
    dx, dy, dz = (t.numpy().astype(np.float64) for t in tap_offsets(filter_size, 0.2, torch.float64))
    filters = kernel.filters().detach().numpy()[:, 0]
    for c in range(5):
        horizontal = sparse_kernel_np(np.hypot(dx, dy), kernel.ell_h[c].item())
        vertical = sparse_kernel_np(np.abs(dz), kernel.ell_z[c].item())
        product = horizontal * vertical
        np.testing.assert_allclose(filters[c], np.where(product >= 1e-6, product, 0.0), atol=1e-6)


@given(variant_params, st.integers(0, 2**31 - 1))
def test_gradients_reach_every_length(kind, seed):
    rng = np.random.default_rng(seed)
    kernel = random_kernel(kind, 6, 5, 0.2, rng, low=0.25, high=1.2)  # every length spans > 1 voxel
    weights = torch.from_numpy(rng.uniform(0.5, 1.5, (6, 1, 5, 5, 5))).float()
    (kernel.filters() * weights).sum().backward()
    for name in ("ell_h", "ell_z") if kind == "compound" else ("ell",):  # the class lengths the filters use
        parameter = getattr(kernel, name)
        assert parameter.grad is not None, name
        assert torch.isfinite(parameter.grad).all(), name
        assert torch.all(parameter.grad.abs() > 0), f"some {name} got no gradient: {parameter.grad}"


@given(variant_params, st.floats(min_value=0.001, max_value=0.2))
def test_length_at_or_below_one_voxel_is_identity(kind, ell):
    kernel = ConvBKIKernel(kind, 3, 5, 0.2, ell=ell)
    expected = torch.zeros(3, 1, 5, 5, 5)
    expected[:, 0, 2, 2, 2] = 1.0
    assert torch.equal(kernel.filters().detach(), expected)


def test_lengths_are_kept_positive():
    kernel = ConvBKIKernel("per_class", 3, 5, 0.2, ell=[0.5, -1.0, 0.0])
    filters = kernel.filters().detach()
    assert torch.isfinite(filters).all()
    assert filters[1].sum() == 1.0 and filters[2].sum() == 1.0  # non-positive lengths behave as the identity
    kernel.clamp_lengths_()
    assert torch.all(kernel.ell > 0)


@pytest.mark.parametrize("kind", ["single", "per_class", "compound"])
def test_kernel_file_round_trip(tmp_path, kind):
    kernel = random_kernel(kind, 20, 7, 0.1, np.random.default_rng(3))
    path = tmp_path / f"{kind}.yaml"
    save_kernel_file(kernel.to_config(), path)
    loaded = kernel_from_file(path)
    assert (loaded.kind, loaded.num_classes, loaded.filter_size, loaded.resolution) == (kind, 20, 7, 0.1)
    torch.testing.assert_close(loaded.filters(), kernel.filters(), atol=1e-5, rtol=0)
    assert not list(tmp_path.glob(".*tmp")), "no temporary file may be left behind"


PUBLISHED = yaml.safe_load((Path(__file__).resolve().parents[1] / "data" / "published_kernel_lengths.yaml").read_text())


@pytest.mark.parametrize("kind", ["single", "per_class", "compound"])
def test_shipped_kernels_hold_the_published_lengths(kind):
    """Every length of each shipped SemanticKITTI kernel equals the published value
    (test/data/published_kernel_lengths.yaml: 20 classes, 0.2 m, f = 5)."""
    config = load_kernel_file(kernel_path(f"semantic_kitti_{kind}"))
    assert (config.kernel, config.num_classes, config.resolution, config.filter_size) == (kind, 20, 0.2, 5)
    published = PUBLISHED[kind]
    names = ("ell_h", "ell_z") if kind == "compound" else ("ell",)
    assert set(published) == set(names)
    for name in names:
        expected = published[name] if isinstance(published[name], list) else [published[name]]
        assert len(expected) == (1 if kind == "single" else 20)
        assert getattr(config, name) == expected, name


def test_shipped_sbki_kernel_is_the_untrained_baseline():
    """S-BKI: one 0.3 m length for every class, on the same grid as the trained kernels."""
    config = load_kernel_file(kernel_path("semantic_kitti_sbki"))
    assert (config.kernel, config.num_classes, config.resolution, config.filter_size) == ("single", 20, 0.2, 5)
    assert config.ell == [0.3]


@pytest.mark.parametrize("change, message", [
    ({"filter_size": 4}, "odd"),
    ({"filter_size": -3}, "odd"),
    ({"kernel": "gaussian"}, "kernel must be one of"),
    ({"ell": [0.3, -0.1, 0.3]}, "positive"),
    ({"ell": [0.3, 0.3]}, "needs 3"),
    ({"num_classes": 0}, "num_classes"),
    ({"resolution": 0}, "resolution"),
    ({"colour": "red"}, "unknown key"),
])
def test_bad_kernel_files_are_refused_with_a_reason(tmp_path, change, message):
    data = {"kernel": "per_class", "resolution": 0.2, "filter_size": 5, "num_classes": 3, "ell": [0.3, 0.4, 0.5]}
    data.update(change)
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(KernelFileError, match=message) as error:
        load_kernel_file(path)
    assert str(path) in str(error.value)


def test_unreadable_kernel_file_names_the_file(tmp_path):
    with pytest.raises(KernelFileError, match="cannot read"):
        load_kernel_file(tmp_path / "missing.yaml")
    (tmp_path / "junk.yaml").write_text("kernel: [unclosed")
    with pytest.raises(KernelFileError, match="not valid YAML"):
        load_kernel_file(tmp_path / "junk.yaml")
    (tmp_path / "list.yaml").write_text("- 1\n- 2\n")
    with pytest.raises(KernelFileError, match="mapping"):
        load_kernel_file(tmp_path / "list.yaml")


def test_config_round_trip_is_exact():
    config = KernelConfig("compound", 0.2, 5, 3, ell_h=[0.3, 0.4, 0.5], ell_z=[0.6, 0.7, 0.8])
    assert kernel_config_from_dict(kernel_config_to_dict(config)) == config
    assert math.isclose(ConvBKIKernel.from_config(config).to_config().ell_h[1], 0.4, rel_tol=1e-6)

"""The ConvBKI update equals the brute-force S-BKI sum over points (paper Eqs. 1 and 4)."""

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st
from reference import brute_force_alpha

from convbki_core import ConvBKIKernel, ConvBKILayer, ConvBKIMapper

NUM_CLASSES = 5
RESOLUTION = 0.2
BOUNDS = ((-1.0, -0.8, -0.6), (0.8, 0.8, 0.8))  # a 9 x 8 x 7 window


def make_kernel(kind, filter_size, rng):
    draw = lambda n: rng.uniform(0.1, 1.0, n).tolist()  # noqa: E731  (some below one voxel: identity)
    if kind == "compound":
        return ConvBKIKernel(kind, NUM_CLASSES, filter_size, RESOLUTION, ell_h=draw(NUM_CLASSES),
                             ell_z=draw(NUM_CLASSES))
    return ConvBKIKernel(kind, NUM_CLASSES, filter_size, RESOLUTION, ell=draw(1 if kind == "single" else NUM_CLASSES))


def kernel_lengths(kernel):
    if kernel.kind == "compound":
        return {"ell_h": kernel.ell_h.tolist(), "ell_z": kernel.ell_z.tolist()}
    return {"ell": kernel.ell.tolist()}


def random_scan(rng, count):
    """Points spread over the window and a margin outside it, plus a few invalid ones."""
    points = rng.uniform(-1.4, 1.2, (count, 3))
    points[rng.random(count) < 0.05] = np.nan
    labels = rng.integers(0, NUM_CLASSES + 1, count)  # includes 0 (ignored) and C (unknown)
    return points, labels


def assert_map_equals(mapper, expected, prior=1e-3):
    """Every voxel with evidence is stored with the brute-force concentrations (1e-5 relative).

    Evidence below 1e-9 of a point (a tap a hair inside the kernel's support, where float64
    and float32 may disagree on "inside") may or may not create a voxel.
    """
    voxels = mapper.voxels()
    stored = {tuple(index): alpha for index, alpha in zip(voxels.indices.tolist(), voxels.alpha)}
    significant = {key for key, alpha in expected.items() if (alpha - prior).max() > 1e-9}
    assert significant <= set(stored), "every voxel that received evidence must be in the map"
    for key, alpha in stored.items():
        reference = expected.get(key, np.full(len(alpha), prior))
        np.testing.assert_allclose(alpha, reference, rtol=1e-5, atol=0)


@pytest.mark.parametrize("kind", ["single", "per_class", "compound"])
@pytest.mark.parametrize("filter_size", [3, 5, 7])
@given(seed=st.integers(0, 2**31 - 1))
def test_mapper_update_equals_brute_force_sum(kind, filter_size, seed):
    rng = np.random.default_rng(seed)
    kernel = make_kernel(kind, filter_size, rng)
    mapper = ConvBKIMapper(kernel, local_bounds=BOUNDS, prior=1e-3, device="cpu")
    points, labels = random_scan(rng, 60)
    result = mapper.integrate(points, labels, np.eye(4))
    origin, dims = mapper.geometry.origin_for(np.zeros(3)), mapper.geometry.dims
    expected = brute_force_alpha(points, labels, NUM_CLASSES, RESOLUTION, origin, dims, filter_size, 1e-3, kind,
                                 **kernel_lengths(kernel))
    assert_map_equals(mapper, expected)
    assert result.stats.non_finite == int(np.isnan(points).any(axis=1).sum())
    assert result.stats.unknown_label == int(((labels == NUM_CLASSES) & np.isfinite(points).all(axis=1)).sum())

    # A second scan adds to what is there (alpha_t = alpha_{t-1} + update).
    points2, labels2 = random_scan(rng, 40)
    mapper.integrate(points2, labels2, np.eye(4))
    both = brute_force_alpha(np.concatenate([points, points2]), np.concatenate([labels, labels2]), NUM_CLASSES,
                             RESOLUTION, origin, dims, filter_size, 1e-3, kind, **kernel_lengths(kernel))
    assert_map_equals(mapper, both)


@pytest.mark.parametrize("kind", ["single", "per_class", "compound"])
@pytest.mark.parametrize("filter_size", [3, 5, 7])
def test_dense_layer_equals_direct_convolution_sum(kind, filter_size):
    """The layer on a random dense F equals the explicit Eq. 4 sum, zero padding included."""
    rng = np.random.default_rng(filter_size)
    kernel = make_kernel(kind, filter_size, rng)
    features = torch.from_numpy(rng.random((NUM_CLASSES, 6, 5, 4)) * (rng.random((NUM_CLASSES, 6, 5, 4)) < 0.3))
    prior = torch.full_like(features, 0.5)
    alpha = ConvBKILayer(kernel).double()(prior, features).detach().numpy()
    filters = kernel.double().filters().detach().numpy()[:, 0]
    half = filter_size // 2
    padded = np.pad(features.numpy(), ((0, 0), (half, half), (half, half), (half, half)))
    expected = np.full(features.shape, 0.5)
    for c in range(NUM_CLASSES):
        for x in range(6):
            for y in range(5):
                for z in range(4):
                    expected[c, x, y, z] += (filters[c] * padded[c, x:x + filter_size, y:y + filter_size,
                                                                 z:z + filter_size]).sum()
    np.testing.assert_allclose(alpha, expected, rtol=1e-10)


def test_probabilities_equal_one_hot_labels():
    rng = np.random.default_rng(7)
    kernel = make_kernel("compound", 5, rng)
    points, labels = random_scan(rng, 80)
    labels = np.clip(labels, 0, NUM_CLASSES - 1)
    by_label = ConvBKIMapper(kernel, local_bounds=BOUNDS, device="cpu")
    by_label.integrate(points, labels, np.eye(4))
    one_hot = np.eye(NUM_CLASSES, dtype=np.float32)[labels]
    by_probability = ConvBKIMapper(kernel, local_bounds=BOUNDS, device="cpu")
    by_probability.integrate(points, one_hot, np.eye(4))
    a, b = by_label.voxels(), by_probability.voxels()
    np.testing.assert_array_equal(a.indices, b.indices)
    np.testing.assert_allclose(a.alpha, b.alpha, rtol=1e-6)


def test_soft_probabilities_spread_fractional_evidence():
    kernel = ConvBKIKernel("single", 3, 3, RESOLUTION, ell=0.1)  # identity: evidence stays in its voxel
    mapper = ConvBKIMapper(kernel, local_bounds=BOUNDS, prior=0.01, device="cpu", ignore_classes=())
    points = np.array([[0.05, 0.05, 0.05], [0.07, 0.01, 0.1]])
    probabilities = np.array([[0.2, 0.5, 0.3], [0.1, 0.1, 0.8]], np.float32)
    mapper.integrate(points, probabilities, np.eye(4))
    voxels = mapper.voxels()
    assert len(voxels) == 1
    np.testing.assert_allclose(voxels.alpha[0], [0.01 + 0.3, 0.01 + 0.6, 0.01 + 1.1], rtol=1e-6)
    assert voxels.label[0] == 2


@pytest.mark.parametrize("kind", ["single", "per_class", "compound"])
@pytest.mark.parametrize("filter_size", [3, 5, 7])
def test_sparse_plan_equals_dense_layer_and_is_differentiable(kind, filter_size):
    """The training path (increment at chosen voxels) equals the dense convolution there."""
    from convbki_core.training.sparse_plan import SparsePlan
    from convbki_core.volume import unravel_linear

    rng = np.random.default_rng(filter_size * 7 + len(kind))
    kernel = make_kernel(kind, filter_size, rng)
    dims = np.array([9, 8, 7])
    origin = np.array([-4, 3, -2])
    occupied = np.unique(rng.integers(0, int(np.prod(dims)), 60))
    features = (rng.random((occupied.size, NUM_CLASSES)) < 0.3) * rng.integers(1, 4, (occupied.size, NUM_CLASSES))
    dense = torch.zeros(NUM_CLASSES, int(np.prod(dims)), dtype=torch.float64)
    dense[:, occupied] = torch.from_numpy(features.T.astype(np.float64))
    expected = ConvBKILayer(kernel).double().increment(dense.view(NUM_CLASSES, *dims)).reshape(NUM_CLASSES, -1)
    queries = rng.choice(int(np.prod(dims)), 40, replace=False)
    source_indices = unravel_linear(occupied, dims) + origin
    plan = SparsePlan.build(unravel_linear(queries, dims) + origin, source_indices, features, filter_size,
                            window=(origin, dims))
    filters = kernel.double().filters()
    got = plan.increment(filters)
    np.testing.assert_allclose(got.detach().numpy(), expected[:, queries].T.detach().numpy(), rtol=1e-10, atol=1e-12)
    got.sum().backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in kernel.parameters())

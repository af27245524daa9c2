"""The ConvBKI update equals the brute-force S-BKI sum over points (paper Eqs. 1 and 4)."""

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from reference import BruteForceMap, filter_table, pose_matrix

from convbki_core import ConvBKIKernel, ConvBKILayer, ConvBKIMapper
from convbki_core.config import MapperConfig

NUM_CLASSES = 5
RESOLUTION = 0.2
PRIOR = 1e-3
# A 10 x 8 x 7 window; the bounds lie half a voxel off the grid, so rounding them outwards
# to whole voxels is unambiguous.
BOUNDS = ((-0.9, -0.7, -0.5), (0.9, 0.7, 0.7))


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


def random_rotation(rng):
    """A pose rotation with yaw, pitch and roll all far from zero (any of them may exceed 90 degrees)."""
    yaw, pitch, roll = rng.choice([-1, 1], 3) * rng.uniform(0.3, 3.0, 3)
    return yaw, pitch, roll


def trajectory(rng):
    """Sensor positions (map frame, m) that move the 10 x 8 x 7 window: a partial shift, a jump
    far enough that the first window leaves entirely, a return that brings its voxels back
    from the store, and a partial shift again."""
    base = rng.uniform(-0.5, 0.5, 3)
    partial = lambda: rng.choice([-1, 1], 3) * rng.uniform(0.25, 0.7, 3)  # noqa: E731
    far = base + np.array([rng.choice([-1, 1]) * rng.uniform(2.5, 4.0), rng.uniform(-2.0, 2.0), 0.0])
    back = base + rng.uniform(-0.15, 0.15, 3)
    return [base, base + partial(), far, back, back + partial()]


def random_values(rng, count, evidence):
    """Labels (including 0, ignored, and C, unknown) or probability rows: sparse Dirichlet draws
    plus rows that are dropped (all zero, negative, NaN) and rows whose mass is all in class 0."""
    if evidence == "labels":
        return rng.integers(0, NUM_CLASSES + 1, count)
    rows = rng.dirichlet(np.full(NUM_CLASSES, 0.7), count) * (rng.random((count, NUM_CLASSES)) < 0.7)
    kind = rng.random(count)
    rows[kind < 0.04] = 0.0
    rows[(kind >= 0.04) & (kind < 0.07), 1] = -0.2
    rows[(kind >= 0.07) & (kind < 0.10), 2] = np.nan
    rows[(kind >= 0.10) & (kind < 0.14)] = np.eye(NUM_CLASSES)[0]
    return rows.astype(np.float32)


def assert_map_is(mapper, oracle):
    """The mapper holds exactly the oracle's voxels, each with its concentrations to 1e-5 relative."""
    indices, alpha = mapper.items()
    order = np.lexsort(indices.T[::-1])  # x, then y, then z: the order of the oracle's sorted keys
    indices, alpha = indices[order], alpha[order]
    assert not (np.diff(indices, axis=0) == 0).all(axis=1).any(), "a voxel is stored twice"
    keys = sorted(oracle.alpha)
    if not np.array_equal(indices, np.array(keys, np.int64).reshape(-1, 3)):
        stored = set(map(tuple, indices.tolist()))
        missing, extra = set(oracle.alpha) - stored, stored - set(oracle.alpha)
        raise AssertionError(f"{len(missing)} voxels missing, {len(extra)} not expected")
    np.testing.assert_allclose(alpha, np.array([oracle.alpha[k] for k in keys]).reshape(alpha.shape), rtol=1e-5,
                               atol=0)


@pytest.mark.parametrize("kind", ["single", "per_class", "compound"])
@pytest.mark.parametrize("filter_size", [3, 5, 7])
@pytest.mark.parametrize("evidence", ["labels", "probabilities"])
@settings(max_examples=12)  # 18 combinations of the above: 216 drives, both paths and every temperature drawn
@given(seed=st.integers(0, 2**31 - 1), update_path=st.sampled_from(["fast", "dense"]),
       temperature=st.sampled_from([None, 1.0, 0.6, 1.7]))
def test_mapper_equals_brute_force_sum_over_a_drive(kind, filter_size, evidence, seed, update_path, temperature):
    """Rotated poses, a window that moves away and back, labels or probabilities, either update
    path, with or without a temperature (it calibrates probabilities and leaves labels alone):
    after every scan the map is exactly the brute-force sum of ``reference.BruteForceMap``."""
    rng = np.random.default_rng(seed)
    kernel = make_kernel(kind, filter_size, rng)
    kernel.temperature = temperature
    mapper = ConvBKIMapper(MapperConfig.paper(local_bounds=BOUNDS, prior=PRIOR, device="cpu", update_path=update_path),
                           kernel)
    oracle = BruteForceMap(kind, NUM_CLASSES, RESOLUTION, filter_size, BOUNDS, PRIOR,
                           temperature=temperature if evidence == "probabilities" else None, **kernel_lengths(kernel))
    np.testing.assert_array_equal(mapper.geometry.dims, oracle.dims)
    first_map_points, drive_counts = None, []
    for scan, position in enumerate(trajectory(rng)):
        pose = pose_matrix(*random_rotation(rng), position)
        points = rng.uniform(-1.3, 1.3, (150, 3))  # sensor frame; the corners fall outside the window
        points[rng.choice(np.arange(1, len(points), 2), 6, replace=False)] = np.nan  # odd rows: scan 3 resets even
        if scan == 0:
            first_map_points = points @ pose[:3, :3].T + pose[:3, 3]
        if scan == 3:  # the return: half the points re-observe the first scan's places from the new pose
            points[::2] = (first_map_points[::2] - pose[:3, 3]) @ pose[:3, :3]
        values = random_values(rng, len(points), evidence)
        before = set(oracle.alpha)
        counts = oracle.integrate(points, values, pose)
        result = mapper.integrate(points, values, pose)
        for name, expected in counts.items():
            assert getattr(result.stats, name) == expected, name
        drive_counts.append(counts)
        assert result.new_voxels == len(oracle.touched[-1] - before)
        assert_map_is(mapper, oracle)
    # The drive did what it is meant to: the third window shares no voxel with the first;
    # voxels given evidence by the first scan were given more after coming back from the store;
    # every scan had points to use, points outside its window and points to drop.
    (first, dims), (far, _) = oracle.windows[0], oracle.windows[2]
    assert ((far >= first + dims) | (first >= far + dims)).any()
    assert oracle.touched[0] & oracle.touched[3]
    assert all(c["used"] > 0 and c["outside_window"] > 0 and c["non_finite"] > 0 for c in drive_counts)
    dropped = ("bad_probabilities",) if evidence == "probabilities" else ("unknown_label", "ignored_class")
    assert all(sum(c[name] for c in drive_counts) > 0 for name in dropped)


@pytest.mark.parametrize("kind", ["single", "per_class", "compound"])
@pytest.mark.parametrize("filter_size", [3, 5, 7])
def test_dense_layer_equals_direct_convolution_sum(kind, filter_size):
    """The layer on a random dense F equals the explicit Eq. 4 sum, zero padding included, with
    filters re-computed from Eq. 5 by the test (``reference.filter_table``), not the code's."""
    rng = np.random.default_rng([filter_size, len(kind)])
    kernel = make_kernel(kind, filter_size, rng)
    features = torch.from_numpy(rng.random((NUM_CLASSES, 6, 5, 4)) * (rng.random((NUM_CLASSES, 6, 5, 4)) < 0.3))
    prior = torch.full_like(features, 0.5)
    alpha = ConvBKILayer(kernel).double()(prior, features).detach().numpy()
    filters = filter_table(kind, NUM_CLASSES, RESOLUTION, filter_size, **kernel_lengths(kernel))
    assert (filters > 0).sum() > NUM_CLASSES, "some filter spreads evidence beyond its centre tap"
    half = filter_size // 2
    padded = np.pad(features.numpy(), ((0, 0), (half, half), (half, half), (half, half)))
    expected = np.full(features.shape, 0.5)
    for c in range(NUM_CLASSES):
        for x in range(6):
            for y in range(5):
                for z in range(4):
                    expected[c, x, y, z] += (filters[c] * padded[c, x:x + filter_size, y:y + filter_size,
                                                                 z:z + filter_size]).sum()
    np.testing.assert_allclose(alpha, expected, rtol=1e-10, atol=1e-12)


def test_probabilities_equal_one_hot_labels():
    rng = np.random.default_rng(7)
    kernel = make_kernel("compound", 5, rng)
    points, labels = random_scan(rng, 80)
    labels = np.clip(labels, 0, NUM_CLASSES - 1)
    by_label = ConvBKIMapper(MapperConfig.paper(local_bounds=BOUNDS, device="cpu"), kernel)
    by_label.integrate(points, labels, np.eye(4))
    one_hot = np.eye(NUM_CLASSES, dtype=np.float32)[labels]
    by_probability = ConvBKIMapper(MapperConfig.paper(local_bounds=BOUNDS, device="cpu"), kernel)
    by_probability.integrate(points, one_hot, np.eye(4))
    a, b = by_label.voxels(), by_probability.voxels()
    np.testing.assert_array_equal(a.indices, b.indices)
    np.testing.assert_allclose(a.alpha, b.alpha, rtol=1e-6)


def test_soft_probabilities_spread_fractional_evidence():
    kernel = ConvBKIKernel("single", 3, 3, RESOLUTION, ell=0.1)  # identity: evidence stays in its voxel
    mapper = ConvBKIMapper(MapperConfig.paper(local_bounds=BOUNDS, prior=0.01, device="cpu", ignore_classes=()), kernel)
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
    from convbki_core.geometry.grid import unravel_linear
    from convbki_core.training.sparse_plan import SparsePlan

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
    for name in kernel_lengths(kernel):  # the class lengths the filters are built from
        gradient = getattr(kernel, name).grad
        assert gradient is not None and torch.isfinite(gradient).all() and (gradient != 0).any(), name

"""The CPU fast path (compiled scatter into the rolling window) equals the dense reference."""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from kitti_fixture import write_drive

from convbki_core import ConvBKIKernel, ConvBKIMapper
from convbki_core.config import MapperConfig
from convbki_core.memory.store import VoxelStore
from convbki_core.memory.window import RollingWindow, box_difference
from convbki_core.tools import evaluate

NUM_CLASSES = 6


def random_kernel(kind, filter_size, rng):
    draw = lambda n: rng.uniform(0.1, 1.2, n).tolist()  # noqa: E731
    if kind == "compound":
        return ConvBKIKernel(kind, NUM_CLASSES, filter_size, 0.2, ell_h=draw(NUM_CLASSES), ell_z=draw(NUM_CLASSES))
    return ConvBKIKernel(kind, NUM_CLASSES, filter_size, 0.2, ell=draw(1 if kind == "single" else NUM_CLASSES))


def voxel_dict(mapper):
    indices, alpha = mapper.items()
    return {tuple(i): a for i, a in zip(indices.tolist(), alpha)}


@given(seed=st.integers(0, 2**31 - 1), kind=st.sampled_from(["single", "per_class", "compound"]),
       filter_size=st.sampled_from([3, 5, 7, 9]), probabilities=st.booleans())
def test_fast_path_equals_dense_reference(seed, kind, filter_size, probabilities):
    rng = np.random.default_rng(seed)
    kernel = random_kernel(kind, filter_size, rng)
    low = -rng.uniform(0.8, 1.6, 3)
    bounds = (tuple(low), tuple(low + rng.uniform(1.0, 2.4, 3)))  # small windows: scans reach every border
    fast = ConvBKIMapper(MapperConfig.paper(local_bounds=bounds, device="cpu", update_path="fast"), kernel)
    dense = ConvBKIMapper(MapperConfig.paper(local_bounds=bounds, device="cpu", update_path="dense"), kernel)
    position = np.zeros(3)
    for _ in range(4):
        position = position + rng.uniform(-0.7, 0.7, 3)  # moves of a few voxels: slabs leave and enter
        pose = np.eye(4)
        pose[:3, 3] = position
        points = rng.uniform(-2.0, 2.0, (150, 3))
        if probabilities:
            values = rng.dirichlet(np.ones(NUM_CLASSES) * 0.3, 150).astype(np.float32)
        else:
            values = rng.integers(0, NUM_CLASSES, 150)
        a = fast.integrate(points, values, pose)
        b = dense.integrate(points, values, pose)
        assert a.new_voxels == b.new_voxels
    got, want = voxel_dict(fast), voxel_dict(dense)
    assert set(got) == set(want)
    np.testing.assert_allclose(np.array([got[key] for key in want]), np.array(list(want.values())), rtol=1e-5)
    probe = rng.uniform(-2, 2, (300, 3)) + position
    # Equal labels wherever the two largest concentrations are farther apart than the paths'
    # rounding (a near tie, within the tolerance above, may fall either way).
    alpha, has_evidence = dense.concentrations_at(probe)
    top_two = np.sort(alpha, axis=1)[:, -2:]
    decided = ~has_evidence | (top_two[:, 1] - top_two[:, 0] > 1e-5 * top_two[:, 1])
    assert decided.mean() > 0.9
    np.testing.assert_array_equal(fast.labels_at(probe)[0][decided], dense.labels_at(probe)[0][decided])


@given(st.integers(0, 2**31 - 1))
def test_rolling_window_matches_a_dict_of_voxels(seed):
    rng = np.random.default_rng(seed)
    dims = np.array([7, 6, 4])
    store = VoxelStore(3, prior=0.5)
    window = RollingWindow(dims, 3, 0.5, store)
    naive = {}
    origin = np.array([0, 0, 0])
    for _ in range(15):
        origin = origin + rng.integers(-9, 10, 3) * (rng.random() < 0.8)  # small moves and jumps, sometimes none
        window.move_to(origin)
        # Add evidence to random window voxels, as an update would.
        local = rng.integers(0, dims, (int(rng.integers(0, 20)), 3))
        for x, y, z in local:
            g = origin + (x, y, z)
            p = g % dims
            add = rng.random(3).astype(np.float32)
            window.alpha[:, p[0], p[1], p[2]] += add
            window.mask[p[0], p[1], p[2]] = 1
            naive[tuple(g.tolist())] = naive.get(tuple(g.tolist()), np.full(3, 0.5, np.float32)) + add
        in_window, stored = window.items(), store.items()
        everything = {tuple(i): a for i, a in zip(np.concatenate([in_window[0], stored[0]]).tolist(),
                                                  np.concatenate([in_window[1], stored[1]]))}
        assert len(everything) == len(in_window[0]) + len(stored[0]), "a voxel may live in one place only"
        assert set(everything) == set(naive)
        np.testing.assert_allclose(np.array([everything[key] for key in naive]), np.array(list(naive.values())),
                                   rtol=1e-6)
    assert window.count() + len(store) == len(naive)


def test_box_difference_covers_exactly_the_difference():
    rng = np.random.default_rng(0)
    for _ in range(200):
        a_lo, b_lo = rng.integers(-5, 5, 3), rng.integers(-5, 5, 3)
        a_hi, b_hi = a_lo + rng.integers(1, 6, 3), b_lo + rng.integers(1, 6, 3)
        cells = set()
        for lo, hi in box_difference(a_lo, a_hi, b_lo, b_hi):
            box = {(x, y, z) for x in range(lo[0], hi[0]) for y in range(lo[1], hi[1]) for z in range(lo[2], hi[2])}
            assert not box & cells, "boxes must be disjoint"
            cells |= box

        def inside(lo, hi, c):
            return all(lo[i] <= c[i] < hi[i] for i in range(3))

        everything = {(x, y, z) for x in range(a_lo[0], a_hi[0]) for y in range(a_lo[1], a_hi[1])
                      for z in range(a_lo[2], a_hi[2])}
        assert cells == {c for c in everything if not inside(b_lo, b_hi, c)}


def test_evaluate_writes_identical_labels_on_both_paths(tmp_path):
    write_drive(tmp_path / "data", "08", frames=4)
    outputs = {}
    for path in ("fast", "dense"):
        code = evaluate.main(["--dataset", str(tmp_path / "data"), "--sequence", "08", "--quiet", "--device", "cpu",
                              "--update-path", path, "--report", str(tmp_path / f"{path}.json"),
                              "--write-labels", str(tmp_path / path),
                              "--local-bounds", "-20", "-12", "-3", "20", "12", "4"])
        assert code == 0
        folder = tmp_path / path / "sequences" / "08" / "predictions"
        outputs[path] = {f.name: f.read_bytes() for f in sorted(folder.iterdir())}
    assert len(outputs["fast"]) == 4
    assert outputs["fast"] == outputs["dense"]


@given(seed=st.integers(0, 2**31 - 1), probabilities=st.booleans(), temperature=st.sampled_from([None, 0.4, 2.5]))
def test_compiled_voxeliser_equals_numpy_voxeliser(seed, probabilities, temperature):
    from convbki_core.geometry.grid import transform_points
    from convbki_core.geometry.volume import voxelize, voxelize_scan

    rng = np.random.default_rng(seed)
    count = int(rng.integers(0, 400))
    points = rng.uniform(-3, 3, (count, 3)).astype(np.float32)
    points[rng.random(count) < 0.05] = np.nan
    points[rng.random(count) < 0.02, 1] = np.inf
    if probabilities:
        values = rng.dirichlet(np.ones(NUM_CLASSES), count).astype(np.float32)
        values[rng.random(count) < 0.03, 2] = np.nan
        values[rng.random(count) < 0.03, 3] = -np.inf
        values[rng.random(count) < 0.05, 1] = -rng.uniform(0, 1)  # negative, with or without a positive sum
        values[rng.random(count) < 0.02, 4] = -0.0
        values[rng.random(count) < 0.05] = 0.0  # rows summing to zero
        if rng.random() < 0.5:  # float64 input: judged after the cast to float32 on both paths
            values = values.astype(np.float64)
            values[rng.random(count) < 0.03, 0] = 1e300  # inf in float32
            values[rng.random(count) < 0.03] = np.where(rng.random(NUM_CLASSES) < 0.5, 1e-300, 0.0)  # 0 in float32
    else:
        values = rng.integers(-1, NUM_CLASSES + 2, count)  # negative and unknown labels too
    pose = np.eye(4)
    rotation = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    pose[:3, :3] = rotation * np.sign(np.linalg.det(rotation))  # a proper rotation (det +1)
    pose[:3, 3] = rng.uniform(-1, 1, 3)
    origin, dims = np.array([-9, -8, -7]), np.array([15, 14, 12])
    slot = np.full(int(np.prod(dims)), -1, np.int32)
    fast = voxelize_scan(points, values, pose, origin, dims, 0.2, NUM_CLASSES, (0,), slot, temperature)
    reference = voxelize(transform_points(points, pose), values, origin, dims, 0.2, NUM_CLASSES, (0,), temperature)
    assert (slot == -1).all(), "the scratch table must be left clean"
    np.testing.assert_array_equal(fast.linear, reference.linear)
    np.testing.assert_array_equal(fast.point_linear, reference.point_linear)
    np.testing.assert_allclose(fast.features, reference.features, rtol=1e-6, atol=1e-6)
    assert fast.stats == reference.stats
    if probabilities:
        with np.errstate(over="ignore", invalid="ignore"):  # float32 overflow and inf - inf in the sums
            judged = values.astype(np.float32)
            sums = judged.sum(axis=1, dtype=np.float64)
        rows_ok = np.isfinite(points).all(axis=1) & np.isfinite(judged).all(axis=1)
        bad = rows_ok & ((judged < 0).any(axis=1) | (sums <= 0))
        assert fast.stats.non_finite == int(count - rows_ok.sum())
        assert fast.stats.bad_probabilities == int(bad.sum())
        assert (fast.point_linear[bad | ~rows_ok] == -1).all()


@given(seed=st.integers(0, 2**31 - 1), filter_size=st.sampled_from([1, 3, 5]), probabilities=st.booleans())
def test_compiled_scatter_handles_any_zero_pattern_in_the_filters(seed, filter_size, probabilities):
    """Filters with holes (not a ball around the centre) give the numpy scatter's result exactly."""
    from convbki_core.inference import update as fast_update

    rng = np.random.default_rng(seed)
    filters = rng.uniform(0.0, 1.0, (NUM_CLASSES, filter_size, filter_size, filter_size)).astype(np.float32)
    filters[rng.random(filters.shape) < 0.5] = 0.0  # zero taps anywhere, also inside a row
    dims = rng.integers(2, 7, 3)
    origin = rng.integers(-20, 20, 3)
    occupied = np.unique(origin + rng.integers(-2, dims + 2, (40, 3)), axis=0)
    if probabilities:
        features = rng.uniform(0.0, 1.0, (len(occupied), NUM_CLASSES)).astype(np.float32)
        features[rng.random(features.shape) < 0.3] = 0.0
    else:
        features = np.eye(NUM_CLASSES, dtype=np.float32)[rng.integers(0, NUM_CLASSES, len(occupied))]
    start = rng.uniform(0.5, 2.0, (NUM_CLASSES, *dims)).astype(np.float32)
    compiled_alpha, numpy_alpha = start.copy(), start.copy()
    compiled_mask = np.zeros(dims, np.uint8)
    numpy_mask = compiled_mask.copy()
    created = fast_update.scatter_update(occupied, features, filters, origin, dims, compiled_alpha, compiled_mask)
    expected = fast_update._scatter_numpy(occupied, features, filters, origin, dims, numpy_alpha, numpy_mask)
    assert created == expected
    np.testing.assert_array_equal(compiled_mask, numpy_mask)
    np.testing.assert_allclose(compiled_alpha, numpy_alpha, rtol=1e-6)


@pytest.mark.parametrize("bound", [1, 2047, 2048, 4_160_000, 1 << 30])
def test_the_voxelisers_radix_sort_equals_numpy_sort(bound):
    from convbki_core.compiled import HAVE_NUMBA
    if not HAVE_NUMBA:
        pytest.skip("the radix sort is part of the compiled voxeliser")
    from convbki_core.geometry.volume import _radix_sort

    rng = np.random.default_rng(bound)
    values = rng.choice(bound, size=min(bound, 30_000), replace=False).astype(np.int64)
    np.testing.assert_array_equal(_radix_sort(values, bound), np.sort(values))
    assert _radix_sort(values[:0], bound).size == 0

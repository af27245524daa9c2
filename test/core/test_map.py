"""The global map: sums, poses, the store, statistics, persistence and export."""

import itertools
import json

import numpy as np
import pytest
import torch
from helpers import read_ply
from hypothesis import given
from hypothesis import strategies as st

from convbki_core import ConvBKIKernel, ConvBKIMapper, MapFileError, dirichlet_statistics
from convbki_core.config import MapperConfig
from convbki_core.devices import resolve_device
from convbki_core.geometry.grid import WindowGeometry
from convbki_core.io.labels import load_label_map
from convbki_core.memory.store import VoxelStore
from convbki_core.paths import kernel_path

NUM_CLASSES = 6
ROAD = 9  # SemanticKITTI learning id of road
BOUNDS = ((-3.0, -3.0, -1.0), (3.0, 3.0, 1.0))


def small_mapper(**overrides):
    kernel = ConvBKIKernel("compound", NUM_CLASSES, 5, 0.2, ell_h=[0.5, 0.3, 0.6, 0.9, 0.25, 0.7],
                           ell_z=[0.5, 0.8, 0.3, 0.45, 0.6, 0.2])
    options = {"local_bounds": BOUNDS, "prior": 1e-3, "device": "cpu"}
    options.update(overrides)
    return ConvBKIMapper(MapperConfig.paper(**options), kernel)


def random_scan(rng, count, extent=2.0):
    return rng.uniform(-extent, extent, (count, 3)) * [1, 1, 0.3], rng.integers(1, NUM_CLASSES, count)


def random_pose(rng, translation_scale=20.0):
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    rotation = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                         [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                         [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    pose = np.eye(4)
    pose[:3, :3] = rotation
    pose[:3, 3] = rng.uniform(-translation_scale, translation_scale, 3)
    return pose


def voxel_dict(mapper):
    voxels = mapper.voxels()
    return {tuple(i): a for i, a in zip(voxels.indices.tolist(), voxels.alpha)}


def assert_same_maps(a, b, rtol=1e-5):
    da, db = voxel_dict(a), voxel_dict(b)
    assert set(da) == set(db)
    np.testing.assert_allclose(np.array([da[key] for key in da]), np.array([db[key] for key in da]), rtol=rtol)


def test_paper_window_geometry():
    geometry = WindowGeometry(0.2)
    assert geometry.dims.tolist() == [400, 400, 26]
    assert geometry.offset.tolist() == [-200, -200, -13]
    # The window follows the sensor in whole voxels and covers the bounds around it.
    origin = geometry.origin_for(np.array([10.05, -3.3, 1.0]))
    assert origin.tolist() == [50 - 200, -17 - 200, 5 - 13]


@given(st.integers(0, 2**31 - 1))
def test_two_scans_equal_their_union(seed):
    rng = np.random.default_rng(seed)
    pose = random_pose(rng, 5.0)
    (p1, l1), (p2, l2) = random_scan(rng, 300), random_scan(rng, 200)
    apart, together = small_mapper(), small_mapper()
    apart.integrate(p1, l1, pose)
    apart.integrate(p2, l2, pose)
    together.integrate(np.concatenate([p1, p2]), np.concatenate([l1, l2]), pose)
    assert_same_maps(apart, together)


@given(st.integers(0, 2**31 - 1))
def test_scan_lands_in_the_same_voxels_from_any_pose(seed):
    """World points seen from an arbitrary SE(3) pose give the map they give from identity."""
    rng = np.random.default_rng(seed)
    resolution = 0.2
    # World points at voxel centres plus at most 0.3 voxel: no rounding can move them across a face.
    centres = rng.integers(-8, 8, (200, 3)) * [1, 1, 0.25]
    world = (np.floor(centres) + 0.5 + rng.uniform(-0.3, 0.3, (200, 3))) * resolution
    labels = rng.integers(1, NUM_CLASSES, 200)
    pose = random_pose(rng, 1.0)  # the sensor is near the points, so both windows hold all of them
    sensor_points = (world - pose[:3, 3]) @ pose[:3, :3]  # inverse transform
    wide = ((-6.0, -6.0, -6.0), (6.0, 6.0, 6.0))
    from_identity, from_pose = small_mapper(local_bounds=wide), small_mapper(local_bounds=wide)
    from_identity.integrate(world, labels, np.eye(4))
    result = from_pose.integrate(sensor_points, labels, pose)
    assert result.stats.used == 200
    assert_same_maps(from_identity, from_pose)


def test_voxelize_counts_every_dropped_point():
    mapper = small_mapper()
    points = np.array([[0.1, 0.1, 0.1], [np.nan, 0, 0], [0, np.inf, 0], [50.0, 0, 0], [0.2, 0.2, 0.2], [0.3, 0, 0]])
    labels = np.array([1, 1, 1, 1, 0, 99])
    result = mapper.integrate(points, labels, np.eye(4))
    s = result.stats
    assert (s.points_in, s.used, s.non_finite, s.outside_window, s.ignored_class, s.unknown_label) == (6, 1, 2, 1, 1, 1)
    assert s.dropped == 5


def bad_probability_scan(rng, count):
    """A scan of good probability rows with every kind of bad row mixed in: (points, probabilities,
    (N,) bool good rows)."""
    points = rng.uniform(-2.0, 2.0, (count, 3)) * [1, 1, 0.3]
    probabilities = rng.dirichlet(np.ones(NUM_CLASSES), count).astype(np.float32)
    kinds = rng.integers(0, 8, count)  # about half the rows bad, of each kind
    probabilities[kinds == 1, 2] = -5.0  # negative: would drive concentrations below zero
    probabilities[kinds == 2, 1] = -0.01  # negative, still a positive sum
    probabilities[kinds == 3, 3] = np.nan
    probabilities[kinds == 4, 0] = np.inf
    probabilities[kinds == 5] = 0.0  # sums to zero
    probabilities[kinds == 6, 4] = -np.inf
    return points, probabilities, (kinds == 0) | (kinds == 7)


def sorted_items(mapper):
    indices, alpha = mapper.items()
    order = np.lexsort(indices.T)
    return indices[order], alpha[order]


@pytest.mark.parametrize("update_path", ["fast", "dense"])
@pytest.mark.parametrize("voxeliser", ["compiled", "numpy"])
def test_bad_probability_rows_leave_the_map_of_the_good_rows(update_path, voxeliser, tmp_path, monkeypatch):
    """Rows with a NaN/inf, a negative value or a zero sum are dropped and counted; the map is
    exactly the map of the good rows alone, and it saves and loads."""
    if voxeliser == "numpy":
        monkeypatch.setattr("convbki_core.parts.HAVE_NUMBA", False)  # the voxeliser used without numba
    rng = np.random.default_rng(12)
    with_bad, good_only = small_mapper(update_path=update_path), small_mapper(update_path=update_path)
    for _ in range(3):
        pose = random_pose(rng, 0.5)
        points, probabilities, good = bad_probability_scan(rng, 400)
        result = with_bad.integrate(points, probabilities, pose)
        reference = good_only.integrate(points[good], probabilities[good], pose)
        finite = np.isfinite(probabilities).all(axis=1)
        assert result.stats.non_finite == int((~finite).sum()) > 0
        assert result.stats.bad_probabilities == int((finite & ~good).sum()) > 0
        assert result.stats.used == reference.stats.used > 0
        assert result.new_voxels == reference.new_voxels
    indices, alpha = sorted_items(with_bad)
    want_indices, want_alpha = sorted_items(good_only)
    assert len(indices) > 100
    np.testing.assert_array_equal(indices, want_indices)
    np.testing.assert_array_equal(alpha, want_alpha)
    assert (alpha > 0).all()

    with_bad.save(tmp_path / "map.npz")
    loaded = small_mapper(update_path=update_path)
    loaded.load(tmp_path / "map.npz")
    loaded_indices, loaded_alpha = sorted_items(loaded)
    np.testing.assert_array_equal(loaded_indices, indices)
    np.testing.assert_array_equal(loaded_alpha, alpha)


def test_a_scan_of_only_bad_probabilities_changes_nothing():
    mapper = small_mapper()
    mapper.integrate(*random_scan(np.random.default_rng(2), 100), np.eye(4))
    before = sorted_items(mapper)
    probabilities = np.array([[-1.0, 2, 0, 0, 0, 0], [0] * 6, [np.nan, 1, 0, 0, 0, 0]], np.float32)
    result = mapper.integrate(np.zeros((3, 3)), probabilities, np.eye(4))
    s = result.stats
    assert (s.points_in, s.used, s.non_finite, s.bad_probabilities, s.dropped) == (3, 0, 1, 2, 3)
    assert result.occupied_voxels == 0
    after = sorted_items(mapper)
    np.testing.assert_array_equal(before[0], after[0])
    np.testing.assert_array_equal(before[1], after[1])


def test_bad_inputs_raise_and_leave_the_map_untouched():
    mapper = small_mapper()
    mapper.integrate(*random_scan(np.random.default_rng(0), 100), np.eye(4))
    before = voxel_dict(mapper)
    bad_pose = np.eye(4)
    bad_pose[0, 0] = 2.0
    nan_pose = np.eye(4)
    nan_pose[0, 3] = np.nan
    points, labels = random_scan(np.random.default_rng(1), 50)
    for args, message in [((points, labels, bad_pose), "rotation"), ((points, labels, nan_pose), "NaN"),
                          ((points, labels[:10], np.eye(4)), "labels"), ((points[:, :2], labels, np.eye(4)), "shape"),
                          ((points, labels.astype(float), np.eye(4)), "integers"),
                          ((points, np.ones((50, 3)), np.eye(4)), "columns")]:
        with pytest.raises(ValueError, match=message):
            mapper.integrate(*args)
    after = voxel_dict(mapper)
    assert set(before) == set(after) and all(np.array_equal(before[k], after[k]) for k in before)


def test_resolve_device_accepts_auto_and_cpu():
    assert resolve_device("auto") == resolve_device("") == torch.device("cuda" if torch.cuda.is_available() else "cpu")
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device(torch.device("cpu")) == torch.device("cpu")


@pytest.mark.parametrize("name", ["tpu", "abc", "CUDA", "cuda:x", "cuda:-1", " cpu"])
def test_resolve_device_names_an_unknown_device(name):
    with pytest.raises(ValueError) as error:
        resolve_device(name)
    assert str(error.value) == f"unknown device {name!r}: use auto, cpu or cuda[:N]"
    with pytest.raises(ValueError, match="unknown device"):
        small_mapper(device=name)


@pytest.mark.parametrize("name", ["meta", "mps", "xpu"])
def test_resolve_device_refuses_device_types_other_than_cpu_and_cuda(name):
    with pytest.raises(ValueError) as error:
        resolve_device(name)
    assert str(error.value) == f"device {name!r} is not supported: use auto, cpu or cuda[:N]"


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a CUDA device, so 'cuda' is valid here")
@pytest.mark.parametrize("name", ["cuda", "cuda:0", "cuda:3"])
def test_resolve_device_without_cuda_is_one_clear_error(name):
    with pytest.raises(ValueError) as error:
        resolve_device(name)
    message = str(error.value)
    assert message.startswith(f"device {name!r} requested, but this torch ({torch.__version__}) has no CUDA device")
    assert message.endswith("; use device auto or cpu") and "\n" not in message
    with pytest.raises(ValueError, match="no CUDA device"):
        small_mapper(device=name)


def test_resolve_device_refuses_a_cuda_index_beyond_the_devices_present():
    count = torch.cuda.device_count() if torch.cuda.is_available() else 0
    with pytest.raises(ValueError, match=rf"^device 'cuda:{count}' requested, but "):
        resolve_device(f"cuda:{count}")
    if count:
        assert resolve_device(f"cuda:{count - 1}") == torch.device(f"cuda:{count - 1}")


def test_statistics_follow_the_dirichlet_formulas():
    alpha = np.array([[1.0, 3.0, 6.0], [2.0, 2.0, 0.5]])
    stats = dirichlet_statistics(alpha)
    assert stats.label.tolist() == [2, 0]
    np.testing.assert_allclose(stats.confidence, [0.6, 2 / 4.5], rtol=1e-6)
    np.testing.assert_allclose(stats.variance, [0.6 * 0.4 / 11, (2 / 4.5) * (2.5 / 4.5) / 5.5], rtol=1e-6)


def test_more_evidence_lowers_the_variance():
    mapper = small_mapper()
    point = np.array([[0.1, 0.1, 0.1]])
    variances = []
    for _ in range(4):
        mapper.integrate(point, np.array([3]), np.eye(4))
        voxels = mapper.voxels()
        variances.append(float(voxels.variance[np.argmax(voxels.alpha[:, 3])]))
    assert all(a > b for a, b in itertools.pairwise(variances))


def test_labels_at_reads_the_expected_class_inside_the_window():
    mapper = small_mapper()
    rng = np.random.default_rng(4)
    points, labels = random_scan(rng, 400)
    mapper.integrate(points, labels, np.eye(4))
    found_labels, found = mapper.labels_at(points)
    assert found.all()
    voxels = {tuple(i): c for i, c in zip(mapper.voxels().indices.tolist(), mapper.voxels().label)}
    expected = [voxels[tuple(i)] for i in np.floor(points / 0.2).astype(int).tolist()]
    assert found_labels.tolist() == expected
    far, far_found = mapper.labels_at(np.array([[100.0, 0, 0], [np.nan, 0, 0]]))
    assert far.tolist() == [-1, -1] and not far_found.any()


class NaiveStore:
    """Reference: a plain dict from voxel index to concentrations."""

    def __init__(self):
        self.voxels = {}

    def query(self, origin, dims):
        return {k: v for k, v in self.voxels.items()
                if all(origin[a] <= k[a] < origin[a] + dims[a] for a in range(3))}


@given(st.integers(0, 2**31 - 1))
def test_store_matches_a_dict_of_voxels(seed):
    rng = np.random.default_rng(seed)
    store, naive = VoxelStore(3, prior=1e-3), NaiveStore()
    dims = np.array([20, 18, 6])
    origin = np.array([-10, -9, -3])
    for _ in range(12):
        origin = origin + rng.integers(-12, 13, 3) * [1, 1, 0]  # move, sometimes far
        count = int(rng.integers(0, 200))
        linear = np.unique(rng.integers(0, int(np.prod(dims)), count))
        alpha = rng.random((linear.size, 3)).astype(np.float32)
        store.write_window(origin, dims, linear, alpha)
        for lin, row in zip(linear.tolist(), alpha):
            x, rest = divmod(lin, dims[1] * dims[2])
            y, z = divmod(rest, dims[2])
            naive.voxels[(origin[0] + x, origin[1] + y, origin[2] + z)] = row
        probe = origin + rng.integers(-15, 15, 3)
        got_linear, got_alpha = store.query_window(probe, dims)
        expected = naive.query(probe, dims)
        assert got_linear.size == len(expected)
        for lin, row in zip(got_linear.tolist(), got_alpha):
            x, rest = divmod(lin, dims[1] * dims[2])
            y, z = divmod(rest, dims[2])
            assert np.array_equal(expected[(probe[0] + x, probe[1] + y, probe[2] + z)], row)
    assert len(store) == len(naive.voxels)
    indices, alpha = store.items()
    assert {tuple(i) for i in indices.tolist()} == set(naive.voxels)
    keys = list(naive.voxels)
    looked_up, found = store.lookup(np.array(keys + [(10**6, 0, 0)]))
    assert found[:-1].all() and not found[-1]
    assert all(np.array_equal(looked_up[n], naive.voxels[k]) for n, k in enumerate(keys))


def test_voxels_left_behind_are_kept_and_found_again():
    mapper = small_mapper()
    rng = np.random.default_rng(5)
    points, labels = random_scan(rng, 200)
    mapper.integrate(points, labels, np.eye(4))
    first_area = voxel_dict(mapper)
    for step in range(1, 6):  # drive away, 30 m a step
        pose = np.eye(4)
        pose[0, 3] = 30.0 * step
        mapper.integrate(points, labels, pose)
    assert mapper.store.lookup(np.array(list(first_area)))[1].all()  # the first area left the window for the store
    everything = voxel_dict(mapper)
    assert all(np.array_equal(everything[k], v) for k, v in first_area.items())
    mapper.integrate(points, labels, np.eye(4))  # come back: the old evidence is the prior
    back = voxel_dict(mapper)
    assert all((back[k] >= v).all() and (back[k] > v).any() for k, v in first_area.items())


def test_save_load_gives_identical_statistics(tmp_path):
    mapper = small_mapper()
    rng = np.random.default_rng(6)
    for _ in range(3):
        pose = random_pose(rng, 2.0)
        mapper.integrate(*random_scan(rng, 300), pose)
    path = tmp_path / "map.npz"
    mapper.save(path)
    assert not [p for p in tmp_path.iterdir() if p.name != "map.npz"], "no temporary file may stay behind"
    loaded = small_mapper()
    loaded.load(path)
    a, b = mapper.voxels(), loaded.voxels()
    order_a, order_b = np.lexsort(a.indices.T), np.lexsort(b.indices.T)
    np.testing.assert_array_equal(a.indices[order_a], b.indices[order_b])
    np.testing.assert_array_equal(a.alpha[order_a], b.alpha[order_b])
    np.testing.assert_array_equal(a.label[order_a], b.label[order_b])
    np.testing.assert_array_equal(a.variance[order_a], b.variance[order_b])
    with np.load(path) as archive:
        metadata = json.loads(archive["metadata"].tobytes())
    assert metadata["format"] == "convbki_map" and metadata["version"] == 3
    assert metadata["resolution"] == 0.2 and metadata["num_classes"] == NUM_CLASSES and metadata["frame_id"] == "map"
    assert metadata["kernel"]["kernel"] == "compound" and metadata["num_voxels"] == len(mapper)


def test_broken_map_files_are_refused_and_the_map_kept(tmp_path):
    mapper = small_mapper()
    mapper.integrate(*random_scan(np.random.default_rng(8), 100), np.eye(4))
    good = tmp_path / "good.npz"
    mapper.save(good)
    before = voxel_dict(mapper)
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    foreign = tmp_path / "foreign.npz"
    np.savez(foreign, something=np.zeros(3))
    text = tmp_path / "text.npz"
    text.write_text("hello")
    picture = tmp_path / "picture.npz"  # a PNG saved under a map's name
    picture.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(100))
    other_classes = tmp_path / "other.npz"
    ConvBKIMapper(MapperConfig.paper(local_bounds=BOUNDS, device="cpu"),
                  kernel_path("semantic_kitti_sbki")).save(other_classes)
    for path, message in [(truncated, "not a readable"), (foreign, "missing"),
                          (text, r"not a NumPy \.npz archive: text\)$"),
                          (picture, r"not a NumPy \.npz archive: a PNG image\)$"),
                          (tmp_path / "absent.npz", "no such"), (other_classes, "20 classes")]:
        with pytest.raises(MapFileError, match=message) as error:
            mapper.load(path)
        assert str(path) in str(error.value)
    after = voxel_dict(mapper)
    assert set(after) == set(before)


def test_reset_empties_the_map():
    mapper = small_mapper()
    mapper.integrate(*random_scan(np.random.default_rng(9), 100), np.eye(4))
    assert len(mapper) > 0
    mapper.reset()
    assert len(mapper) == 0 and len(mapper.voxels()) == 0 and mapper.labels_at(np.zeros((1, 3)))[0][0] == -1


def test_ply_export_holds_every_voxel_in_class_colours(tmp_path):
    mapper = ConvBKIMapper(MapperConfig.paper(local_bounds=BOUNDS, device="cpu"),
                           kernel_path("semantic_kitti_compound"))
    rng = np.random.default_rng(10)
    road_points = np.column_stack([rng.uniform(-1, 1, (400, 2)), rng.uniform(-0.55, -0.45, 400)])
    points = np.concatenate([rng.uniform(-2, 2, (300, 3)), road_points])  # scattered classes and a road patch
    labels = np.concatenate([rng.integers(1, 20, 300), np.full(400, ROAD)])
    mapper.integrate(points, labels, np.eye(4))
    path = tmp_path / "map.ply"
    written = mapper.export_ply(path)
    vertices = read_ply(path)
    voxels = mapper.voxels()
    assert written == len(voxels) == vertices.shape[0]
    header = path.read_bytes().split(b"end_header")[0].decode()
    for name in ("x", "y", "z", "red", "green", "blue", "label", "variance"):
        assert f" {name}\n" in header
    np.testing.assert_array_equal(vertices["label"], voxels.label)
    np.testing.assert_allclose(vertices["x"], voxels.centres[:, 0])
    palette = load_label_map().colors
    np.testing.assert_array_equal(np.column_stack([vertices["red"], vertices["green"], vertices["blue"]]),
                                  palette[voxels.label])
    road = vertices[vertices["label"] == ROAD]
    assert road.shape[0] >= 100, "the 2 m x 2 m road patch covers 10 x 10 voxels"
    assert (road["red"] == 255).all() and (road["green"] == 0).all() and (road["blue"] == 255).all()  # magenta
    limited = mapper.export_ply(tmp_path / "limited.ply", max_variance=float(np.median(voxels.variance)))
    assert 0 < limited < written


# ----------------------------------------------------------------------------- forgetting a box, loading


@pytest.mark.parametrize("update_path", ["fast", "torch"])
def test_forget_box_removes_exactly_the_voxels_whose_centres_lie_in_it(update_path):
    rng = np.random.default_rng(21)
    mapper = small_mapper(update_path=update_path, track_changes=True)
    reference = small_mapper()  # the same scans on the compiled path, never forgetting: what stays must equal it
    for x in (0.0, 2.5, 5.0):  # the window moves, so voxels are both in the store and in the window
        pose = np.eye(4)
        pose[0, 3] = x
        scan = random_scan(rng, 400)
        mapper.integrate(*scan, pose)
        reference.integrate(*scan, pose)
    mapper.take_changes()
    last = random_scan(rng, 50, extent=0.5)
    mapper.integrate(*last, np.eye(4))  # changes left in the store, untaken
    reference.integrate(*last, np.eye(4))
    before = voxel_dict(mapper)
    kept = voxel_dict(reference)
    assert set(kept) == set(before)
    box_min, box_max = np.array([-0.7, -1.1, -0.3]), np.array([3.1, 0.9, 0.5])
    centres = {key: (np.array(key) + 0.5) * 0.2 for key in before}
    inside = {key for key, centre in centres.items() if ((centre >= box_min) & (centre <= box_max)).all()}
    assert 0 < len(inside) < len(before)
    forgotten = mapper.forget_box(box_min, box_max)
    assert set(map(tuple, forgotten.tolist())) == inside and len(forgotten) == len(inside)
    after = voxel_dict(mapper)
    assert set(after) == set(before) - inside
    untouched = np.array([after[key] for key in after])  # as before, and as the map that never forgot holds them
    np.testing.assert_array_equal(untouched, np.array([before[key] for key in after]))
    np.testing.assert_allclose(untouched, np.array([kept[key] for key in after]), rtol=1e-5)
    # What the outputs learn: the forgotten voxels left the map, and no change brings one back.
    changes = mapper.take_changes()
    assert set(map(tuple, changes.removed.tolist())) == inside
    assert not inside & set(map(tuple, changes.indices.tolist()))
    assert len(mapper.forget_box(box_min, box_max)) == 0
    assert len(mapper.forget_box([1, 1, 1], [0, 0, 0])) == 0  # an empty box
    with pytest.raises(ValueError, match="finite"):
        mapper.forget_box([0, 0, np.nan], [1, 1, 1])


def test_a_loaded_map_sits_in_the_window_around_the_sensor_position_it_recorded(tmp_path):
    rng = np.random.default_rng(22)
    mapper = small_mapper()
    pose = np.eye(4)
    pose[:3, 3] = [12.3, -4.5, 0.7]
    mapper.integrate(*random_scan(rng, 300), pose)
    mapper.save(tmp_path / "map.npz")
    loaded = small_mapper()
    metadata = loaded.load(tmp_path / "map.npz")
    np.testing.assert_allclose(metadata["sensor_position"], [12.3, -4.5, 0.7])
    np.testing.assert_allclose(loaded.sensor_position, [12.3, -4.5, 0.7])
    assert loaded.window.count() == len(loaded) == len(mapper)  # the map around the sensor is in the window
    assert_same_maps(loaded, mapper)
    # A file without the position (an older file) places the window on the centre of its voxels.
    indices, alpha = mapper.items()
    from convbki_core.io.map_file import MapSnapshot

    snapshot = mapper.snapshot()
    del snapshot.metadata["sensor_position"]
    MapSnapshot(snapshot.metadata, indices, alpha).write(tmp_path / "old.npz")
    older = small_mapper()
    older.load(tmp_path / "old.npz")
    centre = ((indices.min(axis=0) + indices.max(axis=0)) // 2 + 0.5) * 0.2
    np.testing.assert_array_equal(older.window.origin, older.geometry.origin_for(centre))
    assert older.window.count() > 0
    # Another prior is refused: the classes a voxel never saw would hold the wrong concentration.
    with pytest.raises(MapFileError, match=r"map prior 0\.001 differs from the mapper.s 0\.01"):
        small_mapper(prior=1e-2).load(tmp_path / "map.npz")

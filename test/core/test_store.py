"""The compact global store and the map file: exact against a dict of voxels, small, and readable in both versions."""

import json
import sys

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from convbki_core.config import MapperConfig
from convbki_core.io.map_file import MAP_VERSION, MapSnapshot, read_map
from convbki_core.memory import compact_rows
from convbki_core.memory import store as store_module
from convbki_core.memory.compact_rows import compress_rows, expand_rows
from convbki_core.memory.store import VoxelStore

PRIOR = np.float32(1e-3)
# Bit patterns a row may hold besides ordinary values: both zeros, the smallest subnormal, the
# prior's neighbours and a NaN with a payload. The store keeps every pattern as it was given.
SPECIAL = np.array([0x00000000, 0x80000000, 0x00000001, PRIOR.view(np.uint32) + 1, PRIOR.view(np.uint32) - 1,
                    0x7FC00123], np.uint32).view(np.float32)


def random_rows(rng: np.random.Generator, count: int, num_classes: int, prior: np.float32 = PRIOR) -> np.ndarray:
    """Rows at the prior except in 0..C classes: some all prior, some with every class set."""
    rows = np.full((count, num_classes), prior, np.float32)
    for row in rows:
        kind = rng.random()
        chosen = (0 if kind < 0.15 else num_classes if kind < 0.3 else int(rng.integers(1, num_classes + 1)))
        classes = rng.choice(num_classes, chosen, replace=False)
        row[classes] = prior + rng.random(chosen).astype(np.float32) * 5
        if chosen and rng.random() < 0.1:
            row[classes[0]] = SPECIAL[rng.integers(len(SPECIAL))]
    return rows


def bits(row: np.ndarray) -> bytes:
    return np.asarray(row, np.float32).tobytes()


def window_keys(origin: np.ndarray, dims: np.ndarray, linear: np.ndarray) -> list[tuple]:
    local = np.stack(np.unravel_index(linear, tuple(dims.tolist())), axis=1) + origin
    return list(map(tuple, local.tolist()))


def check_against(store: VoxelStore, reference: dict, rng: np.random.Generator) -> None:
    """len, items (fresh and into given arrays) and lookup (with absent voxels) equal the reference."""
    assert len(store) == len(reference)
    indices, alpha = store.items()
    assert {tuple(i): bits(a) for i, a in zip(indices.tolist(), alpha)} == {k: bits(v) for k, v in reference.items()}
    into_indices = np.full((len(store) + 2, 3), -7, np.int64)
    into_alpha = np.full((len(store) + 2, store.num_classes), -7, np.float32)
    store.items(into_indices[1:-1], into_alpha[1:-1])
    assert (into_indices[[0, -1]] == -7).all() and (into_alpha[[0, -1]] == -7).all()
    assert np.array_equal(into_indices[1:-1], indices) and into_alpha[1:-1].tobytes() == alpha.tobytes()
    keys = list(reference)
    absent = [(int(x), 0, 0) for x in rng.integers(10**5, 10**6, 3)] + [(-1, -1, -1000)]
    absent = [key for key in absent if key not in reference]
    probe = np.array(keys + absent, np.int64).reshape(-1, 3)
    got, found = store.lookup(probe)
    assert found[:len(keys)].all() and not found[len(keys):].any() and not got[len(keys):].any()
    assert all(bits(got[n]) == bits(reference[key]) for n, key in enumerate(keys))
    for chunk in store._chunks.values():  # the memory count holds only if no chunk keeps a view of a larger buffer
        assert chunk.offsets.size and all(a.flags.owndata for a in (chunk.offsets, chunk.counts, chunk.classes,
                                                                   chunk.values))
        assert (np.diff(chunk.offsets.astype(np.int64)) > 0).all()


def run_random_operations(seed: int, num_classes: int) -> None:
    rng = np.random.default_rng(seed)
    store, reference = VoxelStore(num_classes, prior=PRIOR), {}
    dims = np.array([int(rng.integers(1, 40)), int(rng.integers(1, 30)), int(rng.integers(1, 20))])
    origin = rng.integers(-40, 40, 3)
    for _ in range(25):
        origin = origin + rng.integers(-20, 21, 3) * (rng.random() < 0.8)
        operation = rng.choice(["write", "write_window", "take", "query", "clear"], p=[0.3, 0.25, 0.2, 0.2, 0.05])
        if operation == "write":  # anywhere, indices may repeat (the last row counts)
            indices = origin + rng.integers(-30, 50, (int(rng.integers(0, 300)), 3))
            rows = random_rows(rng, len(indices), num_classes)
            store.write(indices, rows)
            reference.update(zip(map(tuple, indices.tolist()), rows))
        elif operation == "write_window":
            linear = np.unique(rng.integers(0, int(np.prod(dims)), int(rng.integers(0, 200))))
            rows = random_rows(rng, len(linear), num_classes)
            store.write_window(origin, dims, linear, rows)
            reference.update(zip(window_keys(origin, dims, linear), rows))
        elif operation in ("take", "query"):
            probe = origin + rng.integers(-10, 10, 3)
            linear, alpha = (store.take_window if operation == "take" else store.query_window)(probe, dims)
            assert linear.dtype == np.int64 and alpha.dtype == np.float32 and alpha.shape == (len(linear), num_classes)
            assert (np.diff(linear) > 0).all() and (linear >= 0).all() and (linear < np.prod(dims)).all()
            expected = {k for k in reference if all(probe[a] <= k[a] < probe[a] + dims[a] for a in range(3))}
            keys = window_keys(probe, dims, linear)
            assert set(keys) == expected
            assert all(bits(row) == bits(reference[key]) for key, row in zip(keys, alpha))
            if operation == "take":
                for key in keys:
                    del reference[key]
        else:
            store.clear()
            reference.clear()
        assert len(store) == len(reference)
    check_against(store, reference, rng)


@given(st.integers(0, 2**31 - 1), st.sampled_from([1, 5, 20]))
def test_store_equals_a_dict_of_voxels_after_random_operations(seed, num_classes):
    run_random_operations(seed, num_classes)


@given(st.integers(0, 2**31 - 1))
def test_numpy_path_equals_a_dict_of_voxels_too(seed):
    """Without numba the same operations run as numpy: same answers."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(store_module, "HAVE_NUMBA", False)
        patch.setattr(compact_rows, "HAVE_NUMBA", False)
        run_random_operations(seed, 5)


def test_rows_at_the_prior_take_no_class_entries_and_all_classes_take_all():
    store = VoxelStore(20, prior=PRIOR)
    rows = np.full((3, 20), PRIOR, np.float32)
    rows[1] += 1.0
    rows[2, [3, 17]] = [2.5, 7.0]
    store.write(np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0]]), rows)
    (chunk,) = store._chunks.values()
    assert chunk.counts.tolist() == [0, 20, 2] and chunk.classes.tolist()[-2:] == [3, 17]
    assert chunk.values.view(np.float32)[-2:].tolist() == [2.5, 7.0]
    linear, alpha = store.query_window(np.zeros(3, np.int64), np.array([4, 1, 1]))
    assert linear.tolist() == [0, 1, 2] and alpha.tobytes() == rows.tobytes()


@pytest.mark.parametrize("prior", [np.float32(1e-3), np.float32(0.0), np.float32(-0.0), np.float32(0.5)])
def test_compress_and_expand_are_exact_for_every_bit_pattern(prior):
    """A value is left out only if its bit pattern is the prior's: -0.0 is not 0.0, NaNs keep their payload."""
    rng = np.random.default_rng(3)
    rows = random_rows(rng, 500, 7, prior)
    rows[:6, 0] = SPECIAL
    rows[6] = prior
    for path in (True, False):
        with pytest.MonkeyPatch.context() as patch:
            patch.setattr(compact_rows, "HAVE_NUMBA", path and compact_rows.HAVE_NUMBA)
            counts, classes, values = compress_rows(rows, prior)
            kept = rows.view(np.uint32) != prior.view(np.uint32)
            assert counts.tolist() == kept.sum(axis=1).tolist() and classes.size == values.size == kept.sum()
            assert expand_rows(counts, classes, values, prior, 7).tobytes() == rows.tobytes()


def drive_like_voxels(rng: np.random.Generator, length: int) -> np.ndarray:
    """Unique voxels of a street strip along x at 0.2 m: ground, two walls, scattered objects."""
    x = np.arange(length)
    ground = np.stack(np.meshgrid(x, np.arange(-100, 100), [-9, -8], indexing="ij"), -1).reshape(-1, 3)
    ground = ground[rng.random(len(ground)) < 0.7]
    walls = np.stack(np.meshgrid(x, [-111, -110, 110, 111], np.arange(-9, 12), indexing="ij"), -1).reshape(-1, 3)
    objects = np.stack([rng.integers(0, length, 20 * length), rng.integers(-100, 100, 20 * length),
                        rng.integers(-7, 3, 20 * length)], axis=1)
    return np.unique(np.concatenate([ground, walls, objects]), axis=0)


def test_a_drive_like_map_takes_at_most_40_bytes_a_voxel():
    """20 classes, rows with evidence in 1-3 of them, voxels on surfaces: resident bytes / voxel <= 40."""
    rng = np.random.default_rng(0)
    voxels = drive_like_voxels(rng, 600)
    rows = np.full((len(voxels), 20), PRIOR, np.float32)
    evidence = rng.choice([1, 2, 3], len(voxels), p=[0.5, 0.3, 0.2])
    for k in range(3):
        chosen = np.flatnonzero(evidence > k)
        rows[chosen, rng.integers(0, 20, len(chosen))] = PRIOR + rng.random(len(chosen), dtype=np.float32) * 9
    store = VoxelStore(20, prior=PRIOR)
    for start in range(0, len(voxels), 40_000):  # in slabs, as the moving window evicts them
        store.write(voxels[start:start + 40_000], rows[start:start + 40_000])
    assert len(store) == len(voxels) > 200_000
    bytes_per_voxel = store.resident_bytes / len(store)
    assert bytes_per_voxel <= 40, bytes_per_voxel
    # Dense float32 rows alone would be 80 bytes a voxel; the compact store is not merely dense in disguise.
    assert store.nbytes < len(store) * (2 + 1 + 5 * 3)


def test_resident_bytes_counts_the_python_objects_of_every_chunk():
    store = VoxelStore(20, prior=PRIOR)
    store.write(np.array([[10**6, 10**6, 10**6], [5, 5, 5]]), np.ones((2, 20), np.float32))
    ((key, chunk), _) = store._chunks.items()
    objects = sys.getsizeof(chunk) + sys.getsizeof(key) + sum(sys.getsizeof(v) for v in key)
    headers = sum(sys.getsizeof(a) - a.nbytes for a in (chunk.offsets, chunk.counts, chunk.classes, chunk.values))
    assert store.resident_bytes - store.nbytes - sys.getsizeof(store._chunks) >= 2 * (objects + headers)
    assert store.nbytes == 2 * (2 + 1 + 20 * 5)


def test_write_checks_row_shape_and_clear_empties():
    store = VoxelStore(4, prior=PRIOR)
    with pytest.raises(ValueError, match="alpha must be"):
        store.write(np.zeros((2, 3), np.int64), np.ones((2, 5), np.float32))
    store.write(np.zeros((1, 3), np.int64), np.ones((1, 4), np.float32))
    store.write(np.zeros((0, 3), np.int64), np.ones((0, 4), np.float32))
    assert len(store) == 1 and store.nbytes > 0
    store.clear()
    assert len(store) == 0 and store.nbytes == 0 and store.items()[0].shape == (0, 3)
    linear, alpha = store.take_window(np.zeros(3, np.int64), np.array([5, 5, 5]))
    assert linear.shape == (0,) and alpha.shape == (0, 4)


# ----------------------------------------------------------------------------- map files

def map_metadata(num_classes: int, version: int = MAP_VERSION, prior: float = float(PRIOR)) -> dict:
    return {"format": "convbki_map", "version": version, "resolution": 0.2, "num_classes": num_classes,
            "num_voxels": 0, "frame_id": "map", "prior": prior, "scans_integrated": 3}


def sample_map(seed: int, num_classes: int = 20, count: int = 3000) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    indices = np.unique(rng.integers(-500, 500, (count, 3)), axis=0)
    return indices, random_rows(rng, len(indices), num_classes)


@pytest.mark.parametrize("num_classes", [1, 20])
def test_a_map_without_a_log_round_trips_exactly(tmp_path, num_classes):
    indices, alpha = sample_map(1, num_classes)
    alpha = np.where(np.isnan(alpha), np.float32(2.0), np.abs(alpha))  # a file holds finite, non-negative values
    path = tmp_path / "map.npz"
    MapSnapshot(map_metadata(num_classes, version=1), indices, alpha).write(path)  # written as the current version
    with np.load(path) as archive:
        members = {name: archive[name] for name in archive.files}
    assert set(members) == {"metadata", "voxel_index", "class_count", "class_id", "value"}
    assert json.loads(members["metadata"].tobytes())["version"] == MAP_VERSION == 3
    assert members["class_count"].dtype == np.uint8 and members["class_id"].dtype == np.uint8
    assert members["value"].dtype == np.float32 and members["voxel_index"].dtype == np.int32
    assert members["value"].size == (alpha.view(np.uint32) != PRIOR.view(np.uint32)).sum()
    metadata, got_indices, got_alpha = read_map(path)
    assert metadata["version"] == 3 and metadata["prior"] == float(PRIOR) and "scan_log" not in metadata
    assert read_map(path, with_scan_log=True)[0]["scan_log"] is None
    assert np.array_equal(got_indices, indices) and got_indices.dtype == np.int64
    assert got_alpha.dtype == np.float32 and got_alpha.tobytes() == alpha.tobytes()


def test_version_1_files_still_load(tmp_path):
    """A file in the old layout (dense ``alpha``, version 1) reads as the same map, and loads into a mapper."""
    from convbki_core import ConvBKIKernel, ConvBKIMapper

    indices, alpha = sample_map(2, 4, 500)
    alpha = np.abs(np.nan_to_num(alpha))
    path = tmp_path / "old.npz"
    np.savez(path, metadata=np.frombuffer(json.dumps(map_metadata(4, version=1)).encode(), np.uint8),
             voxel_index=indices.astype(np.int32), alpha=alpha)
    metadata, got_indices, got_alpha = read_map(path)
    assert metadata["version"] == 1 and np.array_equal(got_indices, indices)
    assert got_alpha.tobytes() == alpha.tobytes()
    mapper = ConvBKIMapper(MapperConfig.paper(local_bounds=((-1, -1, -1), (1, 1, 1)), device="cpu"),
                           ConvBKIKernel("single", 4, 3, 0.2, ell=0.3))
    mapper.load(path)
    assert mapper.scans_integrated == 3 and len(mapper) == len(indices)
    loaded_indices, loaded_alpha = mapper.items()
    order = np.lexsort(loaded_indices.T[::-1])
    assert np.array_equal(loaded_indices[order], indices) and loaded_alpha[order].tobytes() == alpha.tobytes()
    resaved = tmp_path / "new.npz"
    mapper.save(resaved)
    _, indices_again, alpha_again = read_map(resaved)
    order = np.lexsort(indices_again.T[::-1])
    assert np.array_equal(indices_again[order], indices) and alpha_again[order].tobytes() == alpha.tobytes()


def test_version_2_values_equal_to_the_prior_may_be_listed(tmp_path):
    """Another writer may list a class at the prior explicitly: same map."""
    path = tmp_path / "explicit.npz"
    np.savez(path, metadata=np.frombuffer(json.dumps(map_metadata(3)).encode(), np.uint8),
             voxel_index=np.array([[0, 0, 0], [1, 1, 1]], np.int32), class_count=np.array([3, 0], np.uint8),
             class_id=np.array([0, 1, 2], np.uint8), value=np.array([PRIOR, 2.0, PRIOR], np.float32))
    _, _, alpha = read_map(path)
    assert alpha.tobytes() == np.array([[PRIOR, 2.0, PRIOR], [PRIOR] * 3], np.float32).tobytes()


def test_snapshot_without_a_usable_prior_is_not_written(tmp_path):
    indices, alpha = sample_map(4, 3, 10)
    for prior in (None, 0, -1.0, float("nan"), True, "0.001"):
        metadata = map_metadata(3)
        metadata["prior"] = prior
        with pytest.raises(ValueError, match="prior"):
            MapSnapshot(metadata, indices, alpha).write(tmp_path / "map.npz")
    assert not list(tmp_path.iterdir())

"""The map's memory budget: under it the map is the unbounded one bit for bit; at it the map stops
growing, keeps the old ground it lent the window, maps on in the window and never passes the
ceiling; the running byte total is a recount; reset, load and corrections keep the budget."""

import functools

import numpy as np
import pytest

from convbki_core import ConvBKIKernel, ConvBKIMapper
from convbki_core.config import MapperConfig
from convbki_core.geometry.grid import voxel_keys
from convbki_core.mapper import CEILING_FACTOR
from convbki_core.memory import budget as budget_module
from convbki_core.memory.store import VoxelStore

NUM_CLASSES = 6
BOUNDS = ((-3.0, -3.0, -1.0), (3.0, 3.0, 1.0))  # a 30 x 30 x 10 window of 0.2 m voxels


def mapper_of(max_map_megabytes: float = 0.0, **overrides) -> ConvBKIMapper:
    kernel = ConvBKIKernel("compound", NUM_CLASSES, 5, 0.2, ell_h=[0.5, 0.3, 0.6, 0.9, 0.25, 0.7],
                           ell_z=[0.5, 0.8, 0.3, 0.45, 0.6, 0.2])
    options = {"local_bounds": BOUNDS, "prior": 1e-3, "device": "cpu", "scan_log": False,
               "max_map_megabytes": max_map_megabytes}
    options.update(overrides)
    return ConvBKIMapper(MapperConfig.paper(**options), kernel)


def scan(rng: np.random.Generator, label: int | None = None, count: int = 300) -> tuple[np.ndarray, np.ndarray]:
    """Ground under the sensor and a few posts, in the sensor frame; ``label``: every point's class."""
    ground = np.column_stack([rng.uniform(-2.8, 2.8, (count, 2)), rng.uniform(-0.85, -0.75, count)])
    posts = np.column_stack([rng.integers(-2, 3, (count // 3, 2)) + rng.uniform(-0.1, 0.1, (count // 3, 2)),
                             rng.uniform(-0.8, 0.8, count // 3)])
    labels = np.concatenate([np.full(count, 1), rng.integers(2, NUM_CLASSES - 1, count // 3)])
    return np.concatenate([ground, posts]), labels if label is None else np.full(labels.shape, label)


def pose_at(x: float, y: float = 0.0) -> np.ndarray:
    pose = np.eye(4)
    pose[:2, 3] = x, y
    return pose


def drive(mapper: ConvBKIMapper, xs, seed: int = 0, label: int | None = None, watch=None) -> None:
    rng = np.random.default_rng(seed)
    for x in xs:
        points, labels = scan(rng, label)
        mapper.integrate(points, labels, pose_at(x))
        if watch is not None:
            watch(mapper)


def voxel_bits(mapper: ConvBKIMapper) -> dict:
    indices, alpha = mapper.items()
    return {tuple(i): a.tobytes() for i, a in zip(indices.tolist(), alpha)}


ROUTE = np.arange(0.0, 30.0, 1.0)  # 30 m of new ground, 30 scans


@functools.cache
def unbounded_store_bytes() -> int:
    mapper = mapper_of()
    drive(mapper, ROUTE)
    mapper.window.flush()
    return mapper.store.resident_bytes


def test_under_the_budget_the_map_is_the_unbounded_one_bit_for_bit():
    free, bounded = mapper_of(), mapper_of(max_map_megabytes=50.0)
    drive(free, ROUTE[:20])
    drive(bounded, ROUTE[:20])
    assert voxel_bits(free) == voxel_bits(bounded)
    state = bounded.memory_state()
    assert not state.full and state.voxels_dropped == state.times_full == 0
    assert state.budget_bytes == 50_000_000 and state.ceiling_bytes == int(50_000_000 * CEILING_FACTOR)
    assert state.store_bytes == bounded.store.resident_bytes
    assert free.memory_state().budget_bytes == free.memory_state().ceiling_bytes == 0


@pytest.mark.parametrize("update_path", ["fast", "torch"])
def test_a_drive_over_new_ground_stops_growing_and_the_window_maps_on(update_path):
    budget = unbounded_store_bytes() // 3
    mapper = mapper_of(budget / 1e6, update_path=update_path, track_changes=True)
    ceiling = mapper.memory_state().ceiling_bytes
    events = []  # the changes in the order taken: (indices, rows or None for removals)
    highest = []

    def watch(m):
        highest.append(m.store.resident_bytes)
        changes = m.take_changes()
        events.extend([(changes.removed, None), (changes.indices, changes.alpha)])

    drive(mapper, ROUTE, watch=watch)
    state = mapper.memory_state()
    assert max(highest) <= ceiling and state.full and state.times_full == 1 and state.voxels_dropped > 0
    assert state.store_bytes + state.lent_bytes >= budget
    # A map kept from the changes alone (removals, then rows), as the node's outputs keep it, is
    # the map: the dropped voxels left it too. Each voxel's last event decides.
    keys = np.concatenate([voxel_keys(indices) for indices, _ in events])
    rows = np.concatenate([np.zeros((len(i), NUM_CLASSES), np.float32) if a is None else a for i, a in events])
    kept = np.concatenate([np.full(len(indices), alpha is not None) for indices, alpha in events])
    last = len(keys) - 1 - np.unique(keys[::-1], return_index=True)[1]
    indices, alpha = mapper.items()
    order = np.argsort(voxel_keys(indices))
    assert np.array_equal(keys[last][kept[last]], voxel_keys(indices)[order])
    assert rows[last][kept[last]].tobytes() == alpha[order].tobytes()
    # The window maps on: scans of a new class at the sensor's position are read back there.
    rng = np.random.default_rng(7)
    points, labels = scan(rng, label=NUM_CLASSES - 1)
    for _ in range(4):
        mapper.integrate(points, labels, pose_at(ROUTE[-1]))
    read, held = mapper.labels_at(points + pose_at(ROUTE[-1])[:3, 3])
    assert held.all() and np.mean(read == NUM_CLASSES - 1) > 0.95


def region(mapper: ConvBKIMapper, lo_x: float, hi_x: float) -> dict:
    indices, alpha = mapper.items()
    inside = (indices[:, 0] >= lo_x / 0.2) & (indices[:, 0] < hi_x / 0.2)
    return {tuple(i): a for i, a in zip(indices[inside].tolist(), alpha[inside])}


def test_revisiting_old_ground_while_full_keeps_its_map():
    budget = unbounded_store_bytes() // 3
    mapper = mapper_of(budget / 1e6)
    drive(mapper, ROUTE)  # A -> B: full on the way
    assert mapper.memory_state().full
    old = region(mapper, -3.0, 3.0)  # A, in the store by now
    assert len(old) > 500
    drive(mapper, ROUTE[::-1], seed=1)  # back to A: its chunks are lent to the window, then written back
    drive(mapper, ROUTE[:10], seed=2)  # and away again: A leaves the window once more
    now = region(mapper, -3.0, 3.0)
    assert set(old) <= set(now)  # nothing of A was dropped; the paper's map only gains evidence
    assert all((now[voxel] >= alpha).all() for voxel, alpha in old.items())
    assert any((now[voxel] > alpha).any() for voxel, alpha in old.items())
    assert mapper.store.resident_bytes <= mapper.memory_state().ceiling_bytes


def test_without_the_lent_chunks_rule_a_revisit_would_erase_old_ground(monkeypatch):
    """The check above has teeth: admitting only chunks the store holds loses A on the way back."""
    original = budget_module.StoreBudget.admits
    monkeypatch.setattr(budget_module.StoreBudget, "admits",
                        lambda self, key, held, resident: original(self, (1 << 40,) * 3, held, resident))
    budget = unbounded_store_bytes() // 3
    mapper = mapper_of(budget / 1e6)
    drive(mapper, ROUTE)
    old = region(mapper, -3.0, 3.0)
    drive(mapper, ROUTE[::-1], seed=1)
    drive(mapper, ROUTE[:10], seed=2)
    assert not set(old) <= set(region(mapper, -3.0, 3.0))


def check_totals(store: VoxelStore) -> None:
    assert store.resident_bytes == store.recount_resident_bytes()
    assert store.nbytes == sum(c.offsets.nbytes + c.counts.nbytes + c.classes.nbytes + c.values.nbytes
                               for c in store._chunks.values())
    assert store.budget.lent_bytes == sum(store.budget.lent.values()) >= 0


@pytest.mark.parametrize("budget", [0, 60_000])
def test_the_running_byte_total_is_a_recount_after_any_operation(budget):
    rng = np.random.default_rng(budget)
    store = VoxelStore(NUM_CLASSES, 1e-3, budget, budget + budget // 4)
    for _ in range(150):
        kind = rng.random()
        if kind < 0.5:
            count = int(rng.integers(1, 400))
            indices = rng.integers(-40, 40, (count, 3))
            alpha = np.full((count, NUM_CLASSES), np.float32(1e-3))
            alpha[np.arange(count), rng.integers(0, NUM_CLASSES, count)] += rng.random(count).astype(np.float32)
            dropped = store.write(indices, alpha)
            assert dropped.size == 0 or budget
        elif kind < 0.75:
            store.take_window(rng.integers(-40, 30, 3), rng.integers(1, 30, 3))
        elif kind < 0.9:
            lo = rng.integers(-40, 30, 3)
            store.forget_box(lo, lo + rng.integers(1, 40, 3))
        elif kind < 0.97:
            store = store.copy()
        else:
            store.clear()
        check_totals(store)
        if budget:
            assert store.resident_bytes <= budget + budget // 4 + 64 * 1024  # one chunk's write past it at most
    assert budget == 0 or store.memory_state().voxels_dropped > 0


def test_reset_clears_the_full_state_and_a_corrected_map_keeps_the_budget():
    budget = unbounded_store_bytes() // 3
    mapper = mapper_of(budget / 1e6, scan_log=True)
    drive(mapper, ROUTE)
    assert mapper.memory_state().full
    moved = {k: pose_at(x, 0.2) for k, x in enumerate(ROUTE) if k >= len(ROUTE) - 10}
    corrected, result = mapper.corrected(moved)
    assert corrected is not mapper and result.scans == 10
    state = corrected.memory_state()
    assert (state.budget_bytes, state.ceiling_bytes) == (mapper.memory_state().budget_bytes,
                                                         mapper.memory_state().ceiling_bytes)
    assert state.full and corrected.store.resident_bytes <= state.ceiling_bytes
    mapper.reset()
    state = mapper.memory_state()
    assert not state.full and state.voxels_dropped == state.times_full == state.lent_bytes == 0
    assert abs(state.budget_bytes - budget) <= 1  # the budget stays (MB as a float, back to bytes)
    drive(mapper, ROUTE[:5])  # maps again from empty, under the budget
    assert not mapper.memory_state().full


def test_a_map_file_bigger_than_the_budget_loads_whole_and_is_full(tmp_path):
    free = mapper_of()
    drive(free, ROUTE)
    free.save(tmp_path / "big.map")
    small = mapper_of(unbounded_store_bytes() / 3e6)
    small.load(tmp_path / "big.map")
    assert voxel_bits(small) == voxel_bits(free)
    state = small.memory_state()
    assert state.full and state.times_full == 1 and state.voxels_dropped == 0


def test_the_budget_is_a_setting_of_the_store_group():
    config = MapperConfig().replace(max_map_megabytes=2)
    assert config.store.max_megabytes == 2.0 and config.flat()["max_map_megabytes"] == 2.0
    assert MapperConfig().store.max_megabytes == 4000.0  # the node's default: a robot's map is bounded
    assert MapperConfig.from_parameters({"max_map_megabytes": 512}).store.max_megabytes == 512.0
    with pytest.raises(ValueError, match="max_map_megabytes"):
        mapper_of(-1.0)
    with pytest.raises(ValueError, match="budget"):
        VoxelStore(NUM_CLASSES, 1e-3, 100, 50)

"""The map's changes: a receiver that applies every updates message rebuilds the shown map exactly.

The mapper marks every voxel whose concentrations change (in the window, and when it leaves
the window before the change was taken) and every voxel that leaves the map (a reset, a
load); ``change_records`` turns them into point records with the shown map's rules (the
variance filter included). Random sequences of operations over moving windows check the
rebuilt map against the whole map, record for record.
"""

import numpy as np
import pytest

from convbki_core.config import MapperConfig
from convbki_core.io.labels import load_label_map
from convbki_core.mapper import ConvBKIMapper
from convbki_core.outputs.records import apply_records, change_records, packed_palette, records_from_alpha, view_records
from convbki_core.outputs.shown_map import ShownMap
from convbki_core.paths import kernel_path

PALETTE = packed_palette(load_label_map("semantic_kitti").colors)
BOUNDS = ((-4.0, -4.0, -1.0), (4.0, 4.0, 1.0))


def shown_map(mapper: ConvBKIMapper, max_variance: float) -> dict:
    indices, alpha = mapper.items()
    records = records_from_alpha(indices, alpha, mapper.resolution, PALETTE)
    if max_variance > 0:
        records = records[records["variance"] <= max_variance]
    return {(float(r["x"]), float(r["y"]), float(r["z"])): r for r in records}


def assert_same(rebuilt: dict, shown: dict) -> None:
    assert rebuilt.keys() == shown.keys(), (len(rebuilt), len(shown))
    for key, record in shown.items():
        assert rebuilt[key].tobytes() == record.tobytes(), key


@pytest.mark.parametrize("update_path", ["fast", "dense"])
@pytest.mark.parametrize("seed", [0, 1])
def test_updates_rebuild_the_shown_map_after_random_operations(update_path, seed, tmp_path):
    rng = np.random.default_rng(seed)
    mapper = ConvBKIMapper(MapperConfig.paper(local_bounds=BOUNDS, device="cpu", update_path=update_path,
                                              track_changes=True), kernel_path("semantic_kitti_compound"))
    rebuilt: dict = {}
    chunked = ShownMap()  # the node's whole map, kept chunk by chunk from the same records
    max_variance = 0.0
    position = np.zeros(3)
    for step in range(40):
        operation = rng.choice(["scan", "scan", "scan", "scan", "take", "take", "reset", "filter", "load"],
                               p=[0.15, 0.15, 0.15, 0.15, 0.1, 0.1, 0.06, 0.07, 0.07]) if step < 39 else "scan"
        if operation == "scan":  # moves the window by up to a few metres: slabs leave and come back
            position = position + rng.uniform(-2.5, 2.5, 3) * [1, 1, 0.2]
            pose = np.eye(4)
            pose[:3, 3] = position
            count = int(rng.integers(50, 800))
            points = rng.uniform(-3.5, 3.5, (count, 3)) * [1, 1, 0.25]
            values = rng.integers(1, 20, count) if rng.random() < 0.5 else rng.dirichlet(np.ones(20), count)
            mapper.integrate(points, values, pose)
        elif operation == "reset":
            mapper.reset()
        elif operation == "load":  # a map file replaces the map: everything is a change
            other = ConvBKIMapper(MapperConfig.paper(local_bounds=BOUNDS, device="cpu"),
                                  kernel_path("semantic_kitti_compound"))
            other.integrate(rng.uniform(-3, 3, (300, 3)), rng.integers(1, 20, 300), np.eye(4))
            other.save(tmp_path / "other.npz")
            mapper.load(tmp_path / "other.npz")
        everything = operation == "filter"  # the shown map changes as a whole: every voxel is sent
        if operation == "filter":
            max_variance = float(rng.choice([0.0, 0.02, 0.05, 0.1]))
        if operation in ("take", "filter", "reset", "load") or step == 39:
            changes = mapper.take_changes(everything)
            records = change_records(changes.removed, changes.indices, changes.alpha, mapper.resolution, PALETTE,
                                     max_variance)
            apply_records(rebuilt, records)
            chunked.apply(np.concatenate([changes.removed, changes.indices]), records)
            shown = shown_map(mapper, max_variance)
            assert_same(rebuilt, shown)
            assert len(chunked) == len(shown)
            assert_same({(float(r["x"]), float(r["y"]), float(r["z"])): r for r in chunked.records()}, shown)
    assert rebuilt, "the sequence must leave something to compare"


def test_no_change_means_an_empty_update():
    mapper = ConvBKIMapper(MapperConfig.paper(local_bounds=BOUNDS, device="cpu", track_changes=True),
                           kernel_path("semantic_kitti_compound"))
    mapper.integrate(np.random.default_rng(3).uniform(-3, 3, (500, 3)), np.full(500, 9), np.eye(4))
    first = mapper.take_changes()
    assert len(first.indices) == len(mapper) and len(first.removed) == 0
    second = mapper.take_changes()
    assert len(second.indices) == 0 and len(second.removed) == 0
    untracked = ConvBKIMapper(MapperConfig.paper(local_bounds=BOUNDS, device="cpu"),
                              kernel_path("semantic_kitti_compound"))
    with pytest.raises(RuntimeError, match="does not track changes"):
        untracked.take_changes()


def test_view_keeps_the_nearest_voxels_within_its_radius_and_budget():
    rng = np.random.default_rng(4)
    records = np.zeros(5000, records_from_alpha(np.zeros((0, 3), np.int64), np.zeros((0, 20), np.float32), 0.2,
                                                PALETTE).dtype)
    records["x"], records["y"] = rng.uniform(-50, 50, (2, 5000)).astype(np.float32)
    distance = np.hypot(records["x"] - 3.0, records["y"] + 1.0)
    inside = np.count_nonzero(distance <= 20.0)
    assert len(view_records(records, np.array([3.0, -1.0]), 20.0, 10**6)) == inside
    budget = inside // 3
    view = view_records(records, np.array([3.0, -1.0]), 20.0, budget)
    assert len(view) == budget
    kept = np.hypot(view["x"] - 3.0, view["y"] + 1.0)
    assert kept.max() <= np.sort(distance)[budget - 1] + 1e-6


@pytest.mark.parametrize("update_path", ["fast", "dense"])
def test_window_records_equal_the_records_of_the_window_voxels(update_path):
    """The local window and the view are computed from the window's class planes in one pass;
    they must be the records of the same voxels computed from their concentrations, bit for bit."""
    rng = np.random.default_rng(6)
    mapper = ConvBKIMapper(MapperConfig.paper(local_bounds=BOUNDS, device="cpu", update_path=update_path),
                           kernel_path("semantic_kitti_compound"))
    for step in range(6):
        pose = np.eye(4)
        pose[:3, 3] = [1.3 * step, -0.7 * step, 0.1]
        values = rng.integers(1, 20, 600) if step % 2 else rng.dirichlet(np.ones(20), 600)
        mapper.integrate(rng.uniform(-3.5, 3.5, (600, 3)) * [1, 1, 0.25], values, pose)
    indices, alpha = mapper.window.items()
    expected = records_from_alpha(indices, alpha, mapper.resolution, PALETTE)
    assert len(expected) > 1000
    assert mapper.window_records(PALETTE).tobytes() == expected.tobytes()

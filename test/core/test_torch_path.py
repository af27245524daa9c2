"""The torch update path (the window resident on a torch device) against the compiled CPU path.

Run here on the CPU device, so ``make test`` covers the code a GPU runs: the same voxels,
labels identical and concentrations within 1e-5 relative, over moving windows, every kernel
variant, labels and probabilities, f = 3 .. 9, with and without free space.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from convbki_core import ConvBKIKernel, ConvBKIMapper
from convbki_core.config import MapperConfig
from convbki_core.datasets.semantic_kitti import SemanticKittiSequence
from convbki_core.inference.statistics import dirichlet_statistics
from convbki_core.outputs.records import packed_palette
from convbki_core.paths import config_dir
from convbki_core.tools import synth
from convbki_core.torch_path.window import TorchWindow

BOUNDS = ((-3.0, -3.0, -1.5), (3.0, 3.0, 1.5))


def kernel(kind: str, filter_size: int) -> ConvBKIKernel:
    rng = np.random.default_rng(filter_size)
    if kind == "compound":
        return ConvBKIKernel("compound", 6, filter_size, 0.25, ell_h=rng.uniform(0.2, 0.9, 6).tolist(),
                             ell_z=rng.uniform(0.2, 0.9, 6).tolist())
    if kind == "per_class":
        return ConvBKIKernel("per_class", 6, filter_size, 0.25, ell=rng.uniform(0.2, 0.9, 6).tolist())
    return ConvBKIKernel("single", 6, filter_size, 0.25, ell=0.6)


def pose(rng: np.random.Generator, position: np.ndarray) -> np.ndarray:
    yaw, pitch = rng.uniform(-math.pi, math.pi), rng.uniform(-0.2, 0.2)
    rotation = np.array([[math.cos(yaw), -math.sin(yaw), 0], [math.sin(yaw), math.cos(yaw), 0], [0, 0, 1]]) @ \
        np.array([[math.cos(pitch), 0, math.sin(pitch)], [0, 1, 0], [-math.sin(pitch), 0, math.cos(pitch)]])
    result = np.eye(4)
    result[:3, :3], result[:3, 3] = rotation, position
    return result


def drive(mapper: ConvBKIMapper, seed: int, probabilities: bool, scans: int = 5) -> None:
    """Scans along a path that leaves and comes back, so slabs go to the store and return."""
    rng = np.random.default_rng(seed)
    for position in ([0, 0, 0], [2.0, 0.5, 0.2], [8.0, 1.0, 0], [1.0, -0.5, 0.1], [1.5, 0.2, -0.2])[:scans]:
        points = rng.uniform(-2.8, 2.8, (500, 3)) * [1, 1, 0.45]
        labels = rng.integers(0, 6, 500)
        values = rng.dirichlet(np.full(6, 0.3), 500).astype(np.float32) if probabilities else labels
        mapper.integrate(points, values, pose(rng, np.array(position, float)))


def sorted_items(mapper: ConvBKIMapper) -> tuple[np.ndarray, np.ndarray]:
    indices, alpha = mapper.items()
    order = np.lexsort(indices.T)
    return indices[order], alpha[order]


@pytest.mark.parametrize("kind", ["single", "per_class", "compound"])
@pytest.mark.parametrize("filter_size", [3, 5, 7, 9])
@pytest.mark.parametrize("probabilities", [False, True])
def test_the_torch_path_equals_the_fast_path(kind, filter_size, probabilities):
    maps = {}
    for path in ("fast", "torch"):
        mapper = ConvBKIMapper(MapperConfig.paper(local_bounds=BOUNDS, device="cpu", update_path=path,
                                                  track_changes=True), kernel(kind, filter_size))
        drive(mapper, filter_size, probabilities)
        maps[path] = sorted_items(mapper)
        if path == "torch":
            assert isinstance(mapper.window, TorchWindow) and isinstance(mapper.window.alpha, torch.Tensor)
    (fast_indices, fast_alpha), (torch_indices, torch_alpha) = maps["fast"], maps["torch"]
    assert np.array_equal(fast_indices, torch_indices)  # the same voxels: the same marking rule
    np.testing.assert_allclose(torch_alpha, fast_alpha, rtol=1e-5)
    assert np.array_equal(dirichlet_statistics(torch_alpha).label, dirichlet_statistics(fast_alpha).label)


@pytest.mark.parametrize("free_ell, limit, ground", [(None, 300.0, ()), (0.4, 300.0, (2, 3)), (None, 3.0, (2, 3)),
                                                     (0.4, 3.0, ())])
def test_the_torch_path_with_free_space_equals_the_fast_path(free_ell, limit, ground):
    """Free space and its clamping (a low limit clamps many voxels) give the same map on both
    paths, with and without ground classes (whose voxels take no free evidence)."""
    maps, changes = {}, {}
    for path in ("fast", "torch"):
        chosen = ConvBKIKernel("compound", 6, 5, 0.25, ell_h=0.6, ell_z=0.5, free_ell=free_ell)
        config = MapperConfig.paper(local_bounds=BOUNDS, device="cpu", update_path=path, free_space=True,
                                    ignore_classes=(0,), track_changes=True, max_concentration=limit,
                                    ground_classes=ground)
        mapper = ConvBKIMapper(config, chosen)
        drive(mapper, 3, False)
        maps[path] = sorted_items(mapper)
        taken = mapper.take_changes()
        changes[path] = {tuple(v) for v in taken.indices}
    assert np.array_equal(maps["fast"][0], maps["torch"][0])
    np.testing.assert_allclose(maps["torch"][1], maps["fast"][1], rtol=1e-5)
    assert (maps["fast"][1][:, 0] > 1e-3).sum() > 20  # free space did something
    assert changes["fast"] == changes["torch"]
    if ground:  # surface voxels there are, and the rays left some of them
        chosen = ConvBKIKernel("compound", 6, 5, 0.25, ell_h=0.6, ell_z=0.5, free_ell=free_ell)
        unguarded = ConvBKIMapper(MapperConfig.paper(local_bounds=BOUNDS, device="cpu", free_space=True,
                                                     ignore_classes=(0,), max_concentration=limit), chosen)
        drive(unguarded, 3, False)
        indices, alpha = sorted_items(unguarded)
        assert np.array_equal(indices, maps["fast"][0])
        assert (alpha[:, 0] > maps["fast"][1][:, 0]).sum() > 0
    if limit < 10:  # clamping did something: against the unclamped map, voxels were scaled down
        chosen = ConvBKIKernel("compound", 6, 5, 0.25, ell_h=0.6, ell_z=0.5, free_ell=free_ell)
        unclamped = ConvBKIMapper(MapperConfig.paper(local_bounds=BOUNDS, device="cpu", free_space=True,
                                                     ignore_classes=(0,), max_concentration=0.0), chosen)
        drive(unclamped, 3, False)
        indices, alpha = sorted_items(unclamped)
        assert np.array_equal(indices, maps["fast"][0])
        assert (maps["fast"][1][:, 1:] < alpha[:, 1:] * 0.99).any(axis=1).sum() > 5


def test_slabs_leaving_and_entering_the_device_window_round_trip_exactly():
    mapper = ConvBKIMapper(MapperConfig.paper(local_bounds=BOUNDS, device="cpu", update_path="torch"),
                           kernel("compound", 5))
    drive(mapper, 9, True, scans=2)
    before = sorted_items(mapper)
    window_before = mapper.window.count()
    rng = np.random.default_rng(0)
    far = pose(rng, np.array([40.0, 40.0, 0.0]))
    mapper.integrate(np.zeros((0, 3)), np.zeros(0, np.int64), far)  # every voxel leaves for the store
    assert mapper.window.count() == 0 and len(mapper.store) == len(before[0])
    mapper.integrate(np.zeros((0, 3)), np.zeros(0, np.int64), pose(rng, np.array([1.5, 0.2, 0.0])))  # and back
    assert mapper.window.count() > 0.5 * window_before
    after = sorted_items(mapper)
    assert np.array_equal(before[0], after[0]) and before[1].tobytes() == after[1].tobytes()


def test_building_a_mapper_leaves_the_callers_kernel_unchanged():
    given = kernel("compound", 5)
    state = {name: value.clone() for name, value in given.state_dict().items()}
    mapper = ConvBKIMapper(MapperConfig.paper(local_bounds=BOUNDS, device="cpu", update_path="torch", resolution=0.5,
                                              filter_size=3), given)
    assert mapper.kernel is not given and mapper.resolution == 0.5 and mapper.kernel.filter_size == 3
    assert given.resolution == 0.25 and given.filter_size == 5
    assert all(torch.equal(state[name], value) for name, value in given.state_dict().items())
    assert all(p.device.type == "cpu" for p in given.parameters())


def test_cuda_asked_for_without_cuda_is_one_clear_error():
    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    with pytest.raises(ValueError, match="no CUDA device"):
        ConvBKIMapper(MapperConfig.paper(local_bounds=BOUNDS, device="cuda", update_path="torch"), kernel("single", 3))


DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="no GPU"))]


@pytest.fixture(scope="module")
def movers_drive(tmp_path_factory):
    """A short synthetic drive with moving and parked traffic (and the node's defaults' classes)."""
    root = tmp_path_factory.mktemp("movers")
    assert synth.main(["--out", str(root), "--sequence", "00", "--frames", "10", "--seed", "31", "--speed", "12",
                       "--beams", "16", "--azimuth-steps", "500", "--movers", "8", "--traffic", "varied",
                       "--quiet"]) == 0
    return SemanticKittiSequence(root, "00")


@pytest.mark.parametrize("device", DEVICES)
def test_the_defaults_on_a_torch_device_equal_the_compiled_path_over_a_drive_with_movers(movers_drive, device):
    """The node's defaults (free space walked on the device, clamping, the ground rule, the
    movers' rules) on the torch path give the compiled path's map: the same voxels, every label,
    every concentration within 1e-5 relative, every costmap cell, the same rule counts, and the
    records made where the window lives (the view's, and the updates' after every scan) equal
    to the compiled ones."""
    from convbki_core.costmap.device import device_window_grid
    from convbki_core.costmap.profile import load_profile
    from convbki_core.costmap.window_pass import grid_of_window
    from convbki_core.io.labels import load_label_map

    labels = load_label_map("semantic_kitti")
    config = MapperConfig.from_params_file(config_dir() / "mapper.yaml").replace(
        device=device, local_bounds=((-20.0, -12.0, -3.0), (20.0, 12.0, 4.0)), scan_log=False, track_changes=True)
    palette = packed_palette(labels.colors)
    profile = load_profile(config_dir() / "traversability" / "car.yaml", labels.class_names)
    maps, updates = {}, {}
    for path in ("fast", "torch"):
        mapper = ConvBKIMapper(config.replace(device="cpu" if path == "fast" else device, update_path=path))
        for frame in movers_drive:
            raw = frame.raw_input_labels
            moving = labels.is_moving(raw)
            mapper.integrate(frame.points, labels.to_learning(raw), frame.pose, moving if moving.any() else None)
            # What semantic_map/updates sends after each scan (on the torch path made on the device).
            removed, changed, records = mapper.take_change_records(palette)
            exact = device == "cpu"  # on a GPU the sums' order differs: within 1e-5, the same labels
            updates.setdefault(path, []).append((removed.tobytes(), {
                tuple(v): r.tobytes() if exact else int(r["label"]) for v, r in zip(changed, records)}))
        indices, alpha = sorted_items(mapper)
        window = mapper.window
        if path == "fast":
            grid = grid_of_window(window, mapper.resolution, profile, mapper.prior)
        else:  # the costmap as it is computed where the window lives (a GPU), here on the torch device given
            grid = device_window_grid(window.alpha, window.mask, window.origin, mapper.resolution, profile,
                                      mapper.prior)
            region = (window.origin[:2] + [37, -5], (120, 90))  # a rolling grid's part, over the window's edge
            assert np.array_equal(device_window_grid(window.alpha, window.mask, window.origin, mapper.resolution,
                                                     profile, mapper.prior, region).values,
                                  grid_of_window(window, mapper.resolution, profile, mapper.prior, region).values)
        rules = mapper.forgetting
        records = mapper.window_records(palette)  # what the view publishes
        maps[path] = indices, alpha, grid.values, (rules.reset_voxels, rules.emptied_voxels), records
    (fast_indices, fast_alpha, fast_grid, fast_rules, fast_records), (indices, alpha, grid, rules, records) = \
        maps["fast"], maps["torch"]
    assert len(records) > 10_000 and np.array_equal(records["label"], fast_records["label"])
    if device == "cpu":  # made on the device, bit for bit
        assert records.tobytes() == fast_records.tobytes()
    assert updates["torch"] == updates["fast"] and sum(len(changed) for _, changed in updates["fast"]) > 10_000
    assert np.array_equal(indices, fast_indices)
    np.testing.assert_allclose(alpha, fast_alpha, rtol=1e-5)
    assert np.array_equal(dirichlet_statistics(alpha).label, dirichlet_statistics(fast_alpha).label)
    assert (dirichlet_statistics(fast_alpha).label == 0).sum() > 1000  # rays emptied voxels
    assert rules == fast_rules and fast_rules[1] > 0, (rules, fast_rules)  # the movers' rules emptied voxels
    assert np.array_equal(grid, fast_grid) and (fast_grid >= 0).sum() > 1000

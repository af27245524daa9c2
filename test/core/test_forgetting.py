"""The movers' rules (``forgetting``) on scenes cast by a simple LiDAR: what moved is forgotten
within a bounded number of scans however long the drive was, what stays stays, and the three
implementations (compiled, numpy, torch) agree."""

from __future__ import annotations

import functools

import numpy as np
import pytest
from helpers import BUILDING, BUILDING_ACROSS, CAR, ROAD, cast

from convbki_core import ConvBKIMapper
from convbki_core.config import MapperConfig
from convbki_core.free_space.device_forgetting import _unsupported_torch
from convbki_core.free_space.host_forgetting import (
    _EMPTIED,
    _FLAGGED,
    _contradicted_numba,
    _contradicted_numpy,
    _unsupported_numba,
    _unsupported_numpy,
)
from convbki_core.memory.column_classes import classes_held
from convbki_core.memory.window import CHANGED, EVIDENCE, TOUCHED

TRUCK, BICYCLIST = 4, 7
MOVABLE = (1, 4, 5, 6, 7, 8)  # SemanticKITTI's: car, truck, other-vehicle, person, bicyclist, motorcyclist
KERNEL = "config/kernels/semantic_kitti_compound.yaml"
BOUNDS = ((-16.0, -16.0, -3.0), (16.0, 16.0, 3.0))
PARKED = (np.array([4.0, 5.0, 0.35]), np.array([8.5, 6.8, 1.5]), CAR)  # a car parked at the kerb, all along
AHEAD = ((-4.0, -8.0, -3.0), (16.0, 8.0, 3.0))  # the street ahead of the sensor, a little of it behind
LOW_WALL = (np.array([13.0, -12.0, 0.0]), np.array([13.5, 12.0, 1.0]), BUILDING)  # nothing tall behind the lane


@functools.lru_cache(maxsize=128)  # a scan is about 1 MB: a bounded cache, emptied when the module ends
def _cast(sensor: tuple, boxes: tuple, max_range: float):
    return cast(np.array(sensor), [(np.array(low), np.array(high), label) for low, high, label in boxes], max_range)


def cast_once(sensor: np.ndarray, boxes, max_range: float = 16.0):
    """``helpers.cast``, each scene cast once: the drives below see the same street from the same
    place many times (a robot that waits, runs with other rules, the torch and fast paths), and the
    LiDAR's rays cost more than the mapper's update. Copies, which the caller may change."""
    key = tuple(np.asarray(sensor).tolist()), tuple(
        (tuple(np.asarray(low).tolist()), tuple(np.asarray(high).tolist()), label) for low, high, label in boxes)
    points, labels = _cast(*key, max_range)
    return points.copy(), labels.copy()


@pytest.fixture(scope="module", autouse=True)
def _forget_the_casts():
    yield
    _cast.cache_clear()


def mapper(forget: bool = True, bounds=BOUNDS, **options) -> ConvBKIMapper:
    return ConvBKIMapper(MapperConfig.paper(local_bounds=bounds, free_space=True, device="cpu",
                                            movable_classes=MOVABLE if forget else (), **options), KERNEL)


def scan(m: ConvBKIMapper, sensor: np.ndarray, boxes, max_range: float = 16.0):
    points, labels = cast_once(sensor, boxes, max_range)
    pose = np.eye(4)
    pose[:3, 3] = sensor
    m.integrate(points - sensor, labels, pose)
    return points, labels


def count_in(m: ConvBKIMapper, label: int, low: np.ndarray, high: np.ndarray) -> int:
    voxels = m.voxels()
    inside = ((voxels.centres > low) & (voxels.centres < high)).all(axis=1)
    return int(np.count_nonzero(inside & (voxels.label == label)))


def creeping(scan_number: int) -> np.ndarray:
    return np.array([0.02 * scan_number, 0.05, 1.73])  # the ego vehicle creeps along x


@pytest.mark.parametrize("forget", [True, False])
def test_a_truck_that_waits_at_a_light_leaves_no_trail_and_a_parked_car_stays(forget):
    """A truck waits 30 scans in the lane ahead, then drives off out of view; 20 scans follow.
    Behind it is only a low wall, so no ray with a return crosses the truck's upper part once
    it has gone: free space empties its lower part, and only the support rule its top. The car
    parked at the kerb stays whole."""
    m = mapper(forget)
    waiting = (np.array([6.0, -2.0, 0.35]), np.array([10.5, -0.2, 3.2]), TRUCK)
    for number in range(60):
        boxes = [LOW_WALL, PARKED]
        if number < 30:
            boxes.append(waiting)
        elif number < 40:  # driving off along -y, out of the window
            shift = np.array([0.0, -1.5 * (number - 29), 0.0])
            boxes.append((waiting[0] + shift, waiting[1] + shift, TRUCK))
        scan(m, creeping(number), boxes)
    swept = count_in(m, TRUCK, waiting[0], waiting[1])
    top = count_in(m, TRUCK, waiting[0] + [0, 0, 1.8], waiting[1])
    parked = count_in(m, CAR, PARKED[0] - 0.2, PARKED[1] + 0.2)
    if forget:
        assert swept == 0
    else:
        assert top > 30  # free space alone leaves the top that no ray crosses
    assert parked > 150  # the parked car is there, rules or not
    assert count_in(m, BUILDING, LOW_WALL[0] - 0.2, LOW_WALL[1] + 0.2) > 100


def scans_to_forget(static_scans: int) -> int:
    """A bicyclist rides slowly along the kerb for 20 scans after ``static_scans`` scans of the
    street alone, then is gone: how many scans after it left until no voxel shows it."""
    m = mapper()
    for _ in range(static_scans):  # the robot waits, the street alone in view
        scan(m, creeping(0), [BUILDING_ACROSS, PARKED])
    for step in range(20):
        centre = np.array([5.0, -4.0 + 0.25 * step, 0.0])
        rider = (centre - [0.3, 0.9, 0.0], centre + [0.3, 0.9, 1.8], BICYCLIST)
        scan(m, creeping(step), [BUILDING_ACROSS, PARKED, rider])
    region = (np.array([4.0, -6.0, -0.1]), np.array([6.0, 2.0, 2.0]))
    for after in range(1, 40):
        scan(m, creeping(20 + after), [BUILDING_ACROSS, PARKED])
        if count_in(m, BICYCLIST, *region) == 0:
            return after
    return 10_000


def test_a_slow_cyclist_is_forgotten_as_soon_on_a_long_drive_as_on_a_short_one():
    short, long = scans_to_forget(20), scans_to_forget(280)
    assert short <= 20 and long <= 20, (short, long)
    assert abs(short - long) <= 2, (short, long)


OTHER_VEHICLE = 5


def test_a_parked_van_whose_label_flickers_stays_while_a_car_that_drives_off_leaves_no_trail():
    """A van (other-vehicle) parked at the kerb for 40 scans; the input calls it car in every
    third scan (the last one among them) and other-vehicle in the others, as segmentation
    networks do. A car waits in the lane for 20 scans, then drives off out of view, the
    building across the street behind it. With the shipped rules every voxel of the van reads
    other-vehicle, the majority of what the input said, and the car leaves no voxel behind; with
    the first rule as it was (every contradicting return resets the voxel,
    ``contradiction_radius`` 0) the flicker is read as motion: a third of the van reads what the
    last scan said."""
    van = (np.array([4.0, 5.0, 0.35]), np.array([9.0, 6.8, 2.4]), OTHER_VEHICLE)
    waiting = (np.array([6.0, -2.0, 0.35]), np.array([10.0, -0.2, 1.6]), CAR)
    kept = {}
    for radius in (2.0, 0.0):
        m = mapper(contradiction_radius=radius)
        for number in range(40):
            boxes = [BUILDING_ACROSS, van]
            if number < 20:
                boxes.append(waiting)
            elif number < 28:  # driving off along -y, out of the window
                shift = np.array([0.0, -2.0 * (number - 19), 0.0])
                boxes.append((waiting[0] + shift, waiting[1] + shift, CAR))
            sensor = creeping(number)
            points, labels = cast_once(sensor, boxes)
            in_van = ((points >= van[0] - 1e-6) & (points <= van[1] + 1e-6)).all(axis=1)
            labels[in_van] = CAR if number % 3 == 0 else OTHER_VEHICLE
            pose = np.eye(4)
            pose[:3, 3] = sensor
            m.integrate(points - sensor, labels, pose)
        voxels = m.voxels()
        inside = ((voxels.centres > van[0]) & (voxels.centres < van[1])).all(axis=1) & (voxels.label != 0)
        kept[radius] = (int((voxels.label[inside] == OTHER_VEHICLE).sum()), int(inside.sum()))
        if radius:
            assert count_in(m, CAR, waiting[0], waiting[1]) == 0  # the car that drove off left no trail
    van_voxels, occupied = kept[2.0]
    assert occupied > 150 and van_voxels == occupied, kept
    assert kept[0.0][0] < 0.8 * kept[0.0][1], kept  # the earlier rule: the last scan's "car" in a third


def test_a_car_arriving_where_a_truck_stood_reads_car_once_the_lane_was_seen_empty():
    """A truck stands 25 scans in a lane, leaves; the lane is empty for two seconds (20 scans);
    a car stops in its place. Near a movable return a voxel is reset only where rays found it
    empty: here, once the lane was seen empty, the map answers "car" at the car's returns at
    once. The first rule as it was (``contradiction_radius`` 0) answers car at once even without
    the empty lane in between; without the rules the truck's evidence out-votes much of it."""
    shares = {}
    spot_low, spot_high = np.array([6.0, -2.0, 0.35]), np.array([10.0, -0.2, 1.6])
    runs = (("shipped", {}, 20), ("without gap", {}, 0), ("earlier rule", {"contradiction_radius": 0.0}, 0),
            ("no rules", {"forget": False}, 20))
    for name, options, gap in runs:
        m = mapper(**options)
        for number in range(25):
            scan(m, creeping(number), [BUILDING_ACROSS, PARKED, (spot_low, spot_high + [0, 0, 1.5], TRUCK)])
        for number in range(gap):
            scan(m, creeping(25 + number), [BUILDING_ACROSS, PARKED])
        points, labels = scan(m, creeping(25 + gap), [BUILDING_ACROSS, PARKED, (spot_low, spot_high, CAR)])
        answered, _ = m.labels_at(points[labels == CAR])
        shares[name] = float(np.mean(answered == CAR))
    assert shares["shipped"] >= 0.95 and shares["earlier rule"] >= 0.95, shares
    # Without the empty lane the truck's evidence holds where the car's returns agree with it in
    # place (its label is noise until seen otherwise): a part only.
    assert shares["without gap"] <= shares["shipped"] - 0.3, shares
    assert shares["no rules"] <= shares["shipped"] - 0.3, shares


def random_window(seed: int):
    """A window's arrays with columns that exercise every branch: empty voxels, movable ones
    over them, static ones in between, voxels this scan touched."""
    rng = np.random.default_rng(seed)
    classes, size = 9, (6, 5, 12)
    alpha = np.full((classes, *size), 1e-3, np.float32)
    held = rng.integers(1, classes, size)
    strength = rng.uniform(0.0, 20.0, size).astype(np.float32)
    strength[rng.uniform(size=size) < 0.1] = 0.0  # voxels whose classes all hold the prior: no mover
    for c in range(1, classes):
        alpha[c][held == c] += strength[held == c]
    alpha[0] += np.where(rng.uniform(size=size) < 0.35, rng.uniform(0, 60, size), rng.uniform(0, 2, size)).astype(
        np.float32)
    mask = np.where(rng.uniform(size=size) < 0.8, EVIDENCE, 0).astype(np.uint8)
    mask |= np.where(rng.uniform(size=size) < 0.2, TOUCHED, 0).astype(np.uint8) & (mask * 0xFF)
    return alpha, mask


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("min_empty", [1, 2])
@pytest.mark.parametrize("use_bits", [False, True])
def test_the_compiled_rules_equal_the_numpy_rules(seed, min_empty, use_bits):
    movable = np.zeros(9, np.bool_)
    movable[[1, 4, 5]] = True
    origin = np.array([3, -2, 7], np.int64)
    alpha, mask = random_window(seed)
    # Every column flagged; some with a movable return near (no fringe clearing there).
    columns = (1 | 2 * (np.random.default_rng(seed + 10).uniform(size=mask.shape[:2]) < 0.3)).astype(np.uint8)
    compiled_alpha, compiled_mask, compiled_columns = alpha.copy(), mask.copy(), columns.copy()
    prior = np.float32(1e-3)
    emptied = _unsupported_numpy(alpha, mask, origin, movable, columns, prior, min_empty)
    flagged = np.flatnonzero(compiled_columns).astype(np.int64)
    # With the window's class bits the compiled rule skips the runs at the prior: the same result.
    held = classes_held(alpha, prior) if use_bits else np.zeros((1, 1), np.uint64)
    if use_bits:
        assert (held != np.iinfo(np.uint64).max >> np.uint64(64 - alpha.shape[0])).any()  # some runs skipped
    assert emptied == _unsupported_numba(compiled_alpha, compiled_mask, origin, movable, compiled_columns, flagged,
                                         prior, min_empty, 2, held, use_bits)
    assert emptied > (5 if min_empty == 1 else 0)  # the random columns hold trails
    np.testing.assert_allclose(compiled_alpha, alpha, rtol=1e-6)
    np.testing.assert_array_equal(compiled_mask, mask)
    np.testing.assert_array_equal(compiled_columns, columns)
    assert ((mask & CHANGED) != 0).sum() == emptied
    rng = np.random.default_rng(seed)
    physical = np.stack([rng.integers(0, n, 40) for n in mask.shape], axis=1)
    physical = np.unique(physical, axis=0)
    seen = rng.integers(0, 9, len(physical))
    compiled = alpha.copy()
    reset = _contradicted_numpy(alpha, physical, seen, movable, 1e-3)
    assert reset == _contradicted_numba(compiled, physical, seen, movable, np.float32(1e-3)) and reset > 0
    np.testing.assert_array_equal(compiled, alpha)


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("use_bits", [False, True])
@pytest.mark.parametrize("near_radius", [0.0, 0.2, 0.6])
def test_the_compiled_contradiction_pass_equals_the_numpy_one(seed, use_bits, near_radius, monkeypatch):
    """The compiled pass (unravel, argmax, flags, the columns near movable returns, reset)
    leaves the window and the column flags as the numpy path does, on a scan whose voxels mix
    classes and wrap around the torus; with the window's class bits (runs at the prior not
    read) as without; with the condition that near a movable return only empty voxels reset
    (``near_radius`` 0.2 m: one column each way) and without it."""
    from types import SimpleNamespace

    import convbki_core.free_space.forgetting as forgetting
    from convbki_core.geometry.volume import voxelize

    alpha, _ = random_window(seed)
    dims = np.array(alpha.shape[1:], np.int64)
    rng = np.random.default_rng(seed)
    points = rng.uniform(0.0, 1.0, (300, 3)) * dims * 0.2 * [0.3, 1.0, 1.0]  # a third of the x rows
    labels = rng.integers(1, alpha.shape[0], len(points))
    origin = np.array([4, 3, 9], np.int64)  # the window's torus wraps inside the scan's volume
    volume = voxelize(points + origin * 0.2, labels, origin, dims, 0.2, alpha.shape[0])
    results = []
    for compiled in (True, False):
        monkeypatch.setattr(forgetting, "HAVE_NUMBA", compiled)
        rules = forgetting.MoverForgetting((1, 4, 5), alpha.shape[0], 1e-3, dims, 1, 0.2, near_radius)
        rules.columns[:] = 1
        window = SimpleNamespace(alpha=alpha.copy(),
                                 classes_by_column=lambda: classes_held(alpha, 1e-3) if use_bits else None)
        results.append((rules.contradicted(volume, window), window.alpha, rules.columns.copy()))
    (count, compiled_alpha, compiled_columns), (expected, numpy_alpha, numpy_columns) = results
    assert count == expected and count > 0
    np.testing.assert_array_equal(compiled_alpha, numpy_alpha)
    np.testing.assert_array_equal(compiled_columns, numpy_columns)
    assert (numpy_columns == 3).any() and (numpy_columns == 1).any()


def test_a_mover_the_rays_emptied_and_static_spread_made_occupied_again_is_still_found():
    """One column: road at the bottom, three empty voxels, then a car voxel the rays emptied.
    A visit that finds only that emptied car keeps the column in view; when a later scan's
    static spread (no return in the voxel) makes it occupied again, a car floating over empty
    space, the next scan that does not reach it empties it. The compiled rule (which visits
    flagged columns, and kept-in-view ones only where the scan's evidence made a mover occupied
    again), the numpy rule and the torch rule (every column) do the same at every step."""
    import torch

    road, car, prior = 2, 1, np.float32(1e-3)
    movable = np.zeros(9, np.bool_)
    movable[[1, 4, 5]] = True
    origin = np.zeros(3, np.int64)
    alpha = np.full((9, 4, 4, 8), prior, np.float32)
    mask = np.zeros((4, 4, 8), np.uint8)
    mask[1, 1, :5] = EVIDENCE
    alpha[road, 1, 1, 0] = 10.0
    alpha[0, 1, 1, 1:4] = 10.0
    alpha[0, 1, 1, 4], alpha[car, 1, 1, 4] = 6.0, 5.0  # empty: class 0 holds more than half
    columns = np.zeros((4, 4), np.uint8)
    columns[1, 1] = _FLAGGED
    rules = {"compiled": [alpha.copy(), mask.copy(), columns.copy()], "numpy": [alpha.copy(), mask.copy(),
                                                                             columns.copy()],
             "torch": [torch.from_numpy(alpha.copy()), torch.from_numpy(mask.copy()), None]}

    def visit() -> dict:
        emptied = {}
        for name, (a, m, c) in rules.items():
            if name == "compiled":
                emptied[name] = _unsupported_numba(a, m, origin, movable, c, np.flatnonzero(c).astype(np.int64),
                                                   prior, 2, 2, classes_held(a, prior), True)
            elif name == "numpy":
                emptied[name] = _unsupported_numpy(a, m, origin, movable, c, prior, 2)
            else:
                emptied[name] = _unsupported_torch(a, m, origin, movable, float(prior),
                                                   torch.zeros((4, 4), dtype=torch.bool), 2)
        return emptied

    def everywhere(change) -> None:
        for a, m, _ in rules.values():
            change(a, m)

    assert visit() == {"compiled": 0, "numpy": 0, "torch": 0}
    assert rules["compiled"][2][1, 1] == _EMPTIED and rules["numpy"][2][1, 1] == _EMPTIED

    # A scan whose evidence reaches the voxel but leaves it empty: nothing to do, still in view.
    def reached(a, m):
        a[road, 1, 1, 4] += 0.5
        m[1, 1, 4] |= TOUCHED
    everywhere(reached)
    assert visit() == {"compiled": 0, "numpy": 0, "torch": 0}
    assert rules["compiled"][2][1, 1] == _EMPTIED

    # The road's spread makes it occupied again, a car (5 > 3.5) over 0.6 m of empty space: this
    # scan reached it, so it stays for now, and the column is flagged again.
    def spread(a, m):
        a[road, 1, 1, 4] += 3.0
    everywhere(spread)
    assert visit() == {"compiled": 0, "numpy": 0, "torch": 0}
    assert rules["compiled"][2][1, 1] & _FLAGGED and rules["numpy"][2][1, 1] & _FLAGGED

    # The next scan does not reach it (free space cleared the marks): a trail, emptied.
    def not_reached(a, m):
        m[1, 1, 4] &= ~TOUCHED if isinstance(m, torch.Tensor) else np.uint8(0xFF & ~TOUCHED)
    everywhere(not_reached)
    assert visit() == {"compiled": 1, "numpy": 1, "torch": 1}
    expected = 5.0 + 3.5 + 1.0 + 7 * float(prior)  # the classes 1 .. 8 (car, road, six at the prior), plus one
    for a, _, _ in rules.values():
        assert float(a[0, 1, 1, 4]) == pytest.approx(expected, rel=1e-6)
    np.testing.assert_array_equal(rules["compiled"][0], rules["torch"][0].numpy())
    np.testing.assert_array_equal(rules["numpy"][0], rules["torch"][0].numpy())
    assert rules["compiled"][2][1, 1] == _EMPTIED


@pytest.mark.parametrize("mislabelled", [0.0, 0.05])
@pytest.mark.parametrize("radius", [2.0, 0.0])
def test_the_torch_path_forgets_as_the_fast_path(mislabelled, radius):
    """The fast path visits only the columns that may hold a mover, the torch path every one:
    equal maps say the fast path's bookkeeping misses none, also where a segmentation's stray
    mover labels (``mislabelled``: a share of the points called car or bicyclist) put movable
    evidence in voxels whose majority is static; with the first rule near movable returns
    (``contradiction_radius`` 2 m, the shipped one) and without that condition (0). The window
    holds what lies ahead of the sensor, where the truck, the car, the parked car and most of the
    house front are (behind it is only road): a third of the street's columns, which the torch path
    visits at every scan."""
    maps = {}
    for path in ("fast", "torch"):
        m = mapper(update_path=path, contradiction_radius=radius, bounds=AHEAD)
        rng = np.random.default_rng(3)
        for number in range(14):
            boxes = [BUILDING_ACROSS, PARKED]
            if number < 6:
                boxes.append((np.array([6.0, -2.0, 0.0]), np.array([10.5, -0.2, 3.0]), TRUCK))
            elif number < 8:
                boxes.append((np.array([6.0, -2.0, 0.35]), np.array([10.0, -0.2, 1.6]), CAR))
            points, labels = cast_once(creeping(number), boxes, 16.0)
            stray = rng.random(len(labels)) < mislabelled
            labels = np.where(stray, rng.choice([CAR, BICYCLIST], len(labels)), labels)
            pose = np.eye(4)
            pose[:3, 3] = creeping(number)
            m.integrate(points - creeping(number), labels, pose)
        indices, alpha = m.items()
        order = np.lexsort(indices.T[::-1])
        maps[path] = (indices[order], alpha[order], m.forgetting.reset_voxels, m.forgetting.emptied_voxels)
    assert np.array_equal(maps["fast"][0], maps["torch"][0])
    np.testing.assert_allclose(maps["torch"][1], maps["fast"][1], rtol=1e-5, atol=1e-6)
    assert maps["fast"][2:] == maps["torch"][2:] and maps["fast"][3] > 0
    # Resets happen: everywhere without the condition, and with it where no stray mover label is near.
    assert maps["fast"][2] > 0 or (radius and mislabelled), maps["fast"][2:]


def test_without_free_space_or_movable_classes_there_are_no_rules():
    assert ConvBKIMapper(MapperConfig.paper(local_bounds=BOUNDS, device="cpu", movable_classes=MOVABLE),
                         KERNEL).forgetting is None
    assert mapper(forget=False).forgetting is None
    m = mapper()
    scan(m, creeping(0), [BUILDING_ACROSS])
    m.reset()
    assert m.forgetting.origin is None and not m.forgetting.columns.any()
    assert ROAD not in MOVABLE

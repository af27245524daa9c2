"""Moving labels in the input: a point the segmentation marks as moving is evidence for its own
scan only (``present_movers``), so a mover leaves no trail even where no later ray passes."""

from __future__ import annotations

import numpy as np
import pytest
from free_space_helpers import BOUNDS
from helpers import BUILDING, BUILDING_ACROSS, CAR, ROAD, cast

from convbki_core import ConvBKIMapper
from convbki_core.config import MapperConfig
from convbki_core.free_space.present_movers import JOIN_CELL, MOVER_REACH, labels_now, present_movers, whole_movers

CAR_LOW, CAR_HIGH = np.array([-2.0, -0.9, 0.35]), np.array([2.0, 0.9, 1.85])
TRUCK, PERSON = 4, 6
MOVABLE = (1, 2, 3, 4, 5, 6, 7, 8)  # SemanticKITTI's movable learning classes


def drive_past(mapper: ConvBKIMapper, with_moving_labels: bool, rear_as_truck: bool = False) -> list[float]:
    """A car crosses in front of the sensor for 10 scans; then 15 scans see only 4 m around
    the sensor, so no later ray reaches the space the car swept. Returns, per scan with the
    car, the share of its points labelled car that the map labels car right after that scan.
    ``rear_as_truck``: the segmentation calls the car's rear metre "truck", a static id, and
    marks only the rest as moving."""
    car_shares = []
    for scan in range(25):
        sensor = np.array([0.1 * scan, 0.05, 1.73])
        boxes = [BUILDING_ACROSS]
        if scan < 10:
            centre = np.array([7.0, -5.0 + 1.0 * scan, 0.0])
            boxes.append((centre + CAR_LOW, centre + CAR_HIGH, CAR))
        points, labels = cast(sensor, boxes, max_range=16.0 if scan < 10 else 4.0)
        pose = np.eye(4)
        pose[:3, 3] = sensor
        moving = (labels == CAR) if with_moving_labels else None
        if rear_as_truck and scan < 10:
            rear = (labels == CAR) & (points[:, 1] < centre[1] + CAR_LOW[1] + 1.0)
            labels = np.where(rear, TRUCK, labels)
            moving = moving & ~rear
        mapper.integrate(points - sensor, labels, pose, moving)
        if scan < 10:
            map_labels, _ = mapper.labels_at(points[labels == CAR])
            car_shares.append(float(np.mean(map_labels == CAR)))
    return car_shares


@pytest.mark.parametrize("free_space", [False, True])
def test_a_car_marked_moving_leaves_no_trail_where_no_later_ray_passes(free_space):
    marked = ConvBKIMapper(MapperConfig.paper(local_bounds=BOUNDS, free_space=free_space, device="cpu"),
                           "config/kernels/semantic_kitti_compound.yaml")
    unmarked = ConvBKIMapper(MapperConfig.paper(local_bounds=BOUNDS, free_space=free_space, device="cpu"),
                             "config/kernels/semantic_kitti_compound.yaml")
    shares = drive_past(marked, with_moving_labels=True)
    drive_past(unmarked, with_moving_labels=False)
    marked_voxels, unmarked_voxels = marked.voxels(), unmarked.voxels()
    # Without moving labels the car's voxels stay (no ray came back to empty them) ...
    assert np.count_nonzero(unmarked_voxels.label == CAR) > 500
    # ... with them, the map never held the car, and the street and the house are there as before.
    assert np.count_nonzero(marked_voxels.label == CAR) == 0
    assert np.count_nonzero(marked_voxels.label == ROAD) >= 0.9 * np.count_nonzero(unmarked_voxels.label == ROAD)
    assert np.count_nonzero(marked_voxels.label == BUILDING) > 500
    # In the scan that sees it, every point of the car reads car: the present evidence, not the
    # street's evidence from before the car came.
    assert min(shares) == 1.0
    assert marked.present_movers is None  # the last scan had no moving points


def test_the_layer_sums_the_moving_points_of_each_voxel_and_holds_only_those():
    points = np.array([[0.05, 0.05, 0.05], [0.15, 0.1, 0.1], [0.1, 0.1, 0.15], [1.05, 0.05, 0.05],
                       [np.nan, 0.0, 0.0]])
    labels = np.array([1, 1, 9, 0, 1])  # the class-0 point and the NaN point add nothing
    layer = present_movers(points, labels, num_classes=20, resolution=0.2, ignore_classes=(0,))
    assert len(layer.keys) == 1
    np.testing.assert_array_equal(layer.alpha[0, [1, 9]], [2.0, 1.0])
    found, held = labels_now(layer, np.array([[0, 0, 0], [5, 0, 0], [0, 0, 1]]))
    np.testing.assert_array_equal(held, [True, False, False])
    np.testing.assert_array_equal(found, [1, -1, -1])


def test_moving_flags_of_the_wrong_length_are_refused_and_leave_the_map_as_it_was():
    mapper = ConvBKIMapper(MapperConfig.paper(local_bounds=BOUNDS, device="cpu"),
                           "config/kernels/semantic_kitti_compound.yaml")
    points, labels = cast(np.array([0.0, 0.0, 1.73]), [BUILDING_ACROSS])
    pose = np.eye(4)
    pose[:3, 3] = [0.0, 0.0, 1.73]
    mapper.integrate(points - pose[:3, 3], labels, pose)
    before = mapper.items()
    with pytest.raises(ValueError, match="moving flags"):
        mapper.integrate(points - pose[:3, 3], labels, pose, np.zeros(len(points) - 1, bool))
    after = mapper.items()
    np.testing.assert_array_equal(before[0], after[0])
    np.testing.assert_array_equal(before[1], after[1])


@pytest.mark.parametrize("free_space", [False, True])
def test_the_static_labelled_parts_of_a_car_marked_moving_leave_no_trail_either(free_space):
    """The car's rear metre is labelled "truck" (a static id) and not marked moving: it is part
    of the moving object, so it stays out of the map as the rest of the car does; a mapper
    without movable classes maps it."""
    whole = ConvBKIMapper(MapperConfig.paper(local_bounds=BOUNDS, free_space=free_space, device="cpu",
                                             movable_classes=MOVABLE), "config/kernels/semantic_kitti_compound.yaml")
    parts = ConvBKIMapper(MapperConfig.paper(local_bounds=BOUNDS, free_space=free_space, device="cpu"),
                          "config/kernels/semantic_kitti_compound.yaml")
    shares = drive_past(whole, with_moving_labels=True, rear_as_truck=True)
    drive_past(parts, with_moving_labels=True, rear_as_truck=True)
    whole_voxels, parts_voxels = whole.voxels(), parts.voxels()
    parts_trucks = np.count_nonzero(parts_voxels.label == TRUCK)
    assert parts_trucks > 1000  # the rear, mapped as a static truck
    assert np.count_nonzero(whole_voxels.label == CAR) == 0
    # All but the scans that see the car's side edge-on, where its points lie more than a cell
    # apart: those few points are not connected to the car.
    assert np.count_nonzero(whole_voxels.label == TRUCK) < 0.1 * parts_trucks
    assert np.count_nonzero(whole_voxels.label == BUILDING) > 500
    assert np.count_nonzero(whole_voxels.label == ROAD) >= 0.9 * np.count_nonzero(parts_voxels.label == ROAD)
    assert min(shares) == 1.0  # the car's marked points read car in the scan that sees them


def test_a_mover_takes_along_the_touching_points_of_movable_classes_and_nothing_else():
    car = np.array([[x, y, 0.5] for x in np.arange(0.0, 4.0, 0.1) for y in (0.0, 0.1)])
    car_labels = np.full(len(car), 1)
    car_moving = np.ones(len(car), bool)
    car_labels[-6:] = TRUCK  # the car's front, "truck" and not marked moving
    car_moving[-6:] = False
    road_under = np.array([[1.0, 0.0, 0.35], [2.0, 0.1, 0.3]])  # touching the car, a static class
    parked = np.array([[0.0, 3.0, 0.5], [0.2, 3.0, 0.5]])  # a parked car 3 m away
    bridge = np.array([[4.1, 0.0, 0.5], [4.3, 0.0, 0.5], [4.5, 0.0, 0.5]])  # a person touching the front
    points = np.concatenate([car, road_under, parked, bridge, [[np.nan, 0.0, 0.5]]])
    labels = np.concatenate([car_labels, [ROAD, ROAD], [1, 1], [PERSON] * 3, [1]])
    moving = np.concatenate([car_moving, [False] * 2, [False] * 2, [False] * 3, [False]])
    grown = whole_movers(points, labels, moving, MOVABLE)
    n = len(car)
    assert grown[:n].all()  # the truck-labelled front joined the car
    assert not grown[n:n + 2].any()  # the road under it did not
    assert not grown[n + 2:n + 4].any()  # nor the parked car
    assert grown[n + 4:n + 7].all()  # the person joined through touching points
    assert not grown[-1]  # nor a point that is not finite
    np.testing.assert_array_equal(moving[:n - 6], grown[:n - 6])  # the marked ones stay marked
    # Without movable classes, or without a moving point, nothing changes.
    np.testing.assert_array_equal(whole_movers(points, labels, moving, ()), moving)
    none = np.zeros(len(points), bool)
    np.testing.assert_array_equal(whole_movers(points, labels, none, MOVABLE), none)


def test_the_marking_spreads_no_further_than_the_reach():
    """A row of points of a movable class, one a cell, the first marked moving: the marking
    moves one cell a step and stops MOVER_REACH metres from it."""
    cells = np.arange(int(np.ceil(MOVER_REACH / JOIN_CELL)) + 4)
    points = np.stack([(cells + 0.5) * JOIN_CELL, np.full(len(cells), 0.1), np.full(len(cells), 0.1)], axis=1)
    labels = np.full(len(cells), 1)
    moving = np.zeros(len(cells), bool)
    moving[0] = True
    grown = whole_movers(points, labels, moving, MOVABLE)
    steps = int(np.ceil(MOVER_REACH / JOIN_CELL))
    assert grown[:steps + 1].all()
    assert not grown[steps + 1:].any()
    # A gap of one empty cell breaks the row.
    gapped = np.delete(points, 3, axis=0)
    grown = whole_movers(gapped, np.delete(labels, 3), np.delete(moving, 3), MOVABLE)
    assert grown[:3].all() and not grown[3:].any()


def test_the_joined_points_stay_out_of_both_the_map_and_the_layer():
    """One scan of the car, its rear labelled "truck" and not marked: the layer holds the marked
    points' car evidence only, the map holds no truck evidence, and the rear's points read the
    layer where they share a voxel with marked ones and the map (the street, or nothing) elsewhere."""
    mapper = ConvBKIMapper(MapperConfig.paper(local_bounds=BOUNDS, free_space=True, device="cpu",
                                              movable_classes=MOVABLE), "config/kernels/semantic_kitti_compound.yaml")
    sensor = np.array([0.0, 0.05, 1.73])
    centre = np.array([7.0, 0.0, 0.0])
    points, labels = cast(sensor, [BUILDING_ACROSS, (centre + CAR_LOW, centre + CAR_HIGH, CAR)])
    rear = (labels == CAR) & (points[:, 1] < centre[1] + CAR_LOW[1] + 1.0)
    assert rear.sum() > 100 and (labels == CAR).sum() > rear.sum() + 100
    moving = (labels == CAR) & ~rear
    labels = np.where(rear, TRUCK, labels)
    pose = np.eye(4)
    pose[:3, 3] = sensor
    mapper.integrate(points - sensor, labels, pose, moving)
    layer = mapper.present_movers
    assert layer.alpha[:, CAR].sum() == moving.sum() and layer.alpha[:, TRUCK].sum() == 0
    assert np.count_nonzero(np.isin(mapper.voxels().label, [CAR, TRUCK])) == 0
    read, _ = mapper.labels_at(points[rear])
    # By hand: the voxels of the marked points; a rear point in one of them reads car (the
    # layer), any other reads the map there: the street, or nothing (-1), never car or truck.
    def voxel_keys(world):
        return [tuple(v) for v in np.floor(world / mapper.resolution).astype(np.int64)]

    marked = set(voxel_keys(points[moving]))
    shares = np.array([key in marked for key in voxel_keys(points[rear])])
    assert shares.sum() > 10 and (~shares).sum() > 10, shares.sum()
    assert (read[shares] == CAR).all(), np.unique(read[shares], return_counts=True)
    assert np.isin(read[~shares], [ROAD, -1]).all(), np.unique(read[~shares], return_counts=True)

"""Moving labels in the input: a point the segmentation marks as moving is evidence for its own
scan only (``present_movers``), so a mover leaves no trail even where no later ray passes."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import BUILDING, BUILDING_ACROSS, CAR, ROAD, cast
from test_free_space import BOUNDS

from convbki_core import ConvBKIMapper
from convbki_core.config import MapperConfig
from convbki_core.present_movers import labels_now, present_movers

CAR_LOW, CAR_HIGH = np.array([-2.0, -0.9, 0.35]), np.array([2.0, 0.9, 1.85])


def drive_past(mapper: ConvBKIMapper, with_moving_labels: bool) -> list[float]:
    """A car crosses in front of the sensor for 10 scans; then 15 scans see only 4 m around
    the sensor, so no later ray reaches the space the car swept. Returns, per scan with the
    car, the share of its points that the map labels car right after that scan."""
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

"""Free space in the node, over DDS: a car that has gone is emptied by the rays of the scans
that see through its place. A subscriber that applies semantic_map/updates receives label 0
for its voxels and ends with no car voxel, like semantic_map itself."""

import numpy as np
import pytest
from mapper_rig import WAIT, Rig, close_together, fields
from test_node_updates import records_of, shown

from convbki_core.outputs.records import apply_records

CAR, TRUCK = 1, 4  # learning ids


def street(with_car: bool) -> tuple[np.ndarray, np.ndarray]:
    """Sensor-frame points and raw labels: road (40) ahead, a house front (50) at x = 9 m, and
    optionally a car body (10) 0.5 m above the road at x 4-7 m."""
    grid = np.stack(np.meshgrid(np.arange(-4.0, 9.0, 0.25), np.arange(-5.0, 5.0, 0.25)), -1).reshape(-1, 2)
    ground = np.column_stack([grid, np.full(len(grid), -1.6)])
    wall_grid = np.stack(np.meshgrid(np.arange(-5.0, 5.0, 0.15), np.arange(-1.5, 2.5, 0.15)), -1).reshape(-1, 2)
    wall = np.column_stack([np.full(len(wall_grid), 9.0), wall_grid])
    parts, labels = [ground, wall], [np.full(len(ground), 40), np.full(len(wall), 50)]
    if with_car:
        car = np.random.default_rng(3).uniform([4.0, -1.0, -1.1], [7.0, 1.0, -0.2], (250, 3))
        # only the side that faces the sensor returns, about as densely as the road and the house
        car[:, 0] = 4.0 + np.abs(np.random.default_rng(4).normal(0, 0.05, len(car)))
        parts.append(car)
        labels.append(np.full(len(car), 10))
        ahead = ~((ground[:, 0] > 4.0) & (np.abs(ground[:, 1]) < 1.0 + 4.0 * (ground[:, 0] - 4.0) / 4.0))
        parts[0], labels[0] = ground[ahead], labels[0][ahead]  # the car hides the road behind it
    return np.concatenate(parts).astype(np.float32), np.concatenate(labels).astype(np.uint32)


@pytest.fixture(scope="module")
def nodes(tmp_path_factory):
    """The module's nodes, started side by side (each test takes its own): "rays" (free space
    on: the node's default), and moving_labels True and False."""
    folder = tmp_path_factory.mktemp("free_space")
    nodes = {"rays": Rig(folder / "rays", diagnostics_period=0.05, wait=False),
             **{moving_labels: Rig(folder / str(moving_labels), "-p", f"moving_labels:={str(moving_labels).lower()}",
                                   diagnostics_period=0.05, wait=False) for moving_labels in (True, False)}}
    yield nodes
    close_together(*nodes.values())


def test_the_rays_empty_a_car_that_has_gone_and_the_updates_say_so(nodes):
    from sensor_msgs.msg import PointCloud2

    from convbki_ros.outputs.cloud_encoding import encode_cloud

    rig = nodes["rays"].wait_ready()
    try:
        updates = rig.probe.subscribe(PointCloud2, "/semantic_map/updates")
        rebuilt: dict = {}
        applied = 0
        removed_cars: set = set()

        def apply_new() -> None:
            nonlocal applied
            for msg in updates[applied:]:
                records = records_of(msg)
                for record in records[records["label"] == 0]:
                    key = (float(record["x"]), float(record["y"]), float(record["z"]))
                    if key in rebuilt and rebuilt[key]["label"] == CAR:
                        removed_cars.add(key)
                apply_records(rebuilt, records)
            applied = len(updates)

        def cars(voxels: dict) -> int:
            return sum(1 for record in voxels.values() if record["label"] == CAR)

        def integrate(with_car: bool) -> None:
            before = rig.stats().integrated
            stamp = rig.next_stamp()
            points, labels = street(with_car)
            from mapper_rig import odometry

            rig.publish(odometry(stamp), encode_cloud(stamp, "velo_link", fields(points, labels)))
            rig.wait_stats(lambda s: s.integrated == before + 1)

        for _ in range(2):
            integrate(with_car=True)
        assert rig.probe.spin_until(lambda: (apply_new(), cars(rebuilt) > 100)[1], WAIT), cars(rebuilt)
        had = cars(rebuilt)
        for _ in range(4):
            integrate(with_car=False)

        def settled() -> bool:
            apply_new()
            return cars(rebuilt) == 0 and bool(rig.maps) and shown(rig.maps[-1]).keys() == rebuilt.keys()

        assert rig.probe.spin_until(settled, WAIT), (cars(rebuilt), had, sorted(
            (round(k[2], 2), round(k[0], 1)) for k, r in rebuilt.items() if r["label"] == CAR))
        assert len(removed_cars) >= 0.9 * had  # sent as removals (label 0), not left behind
        whole = shown(rig.maps[-1])
        assert cars(whole) == 0 and sum(1 for r in whole.values() if r["label"] == 13) > 100  # the house stays
    finally:
        output = rig.close()
    assert "Traceback" not in output, output


def test_points_labelled_moving_stay_out_of_the_map_unless_moving_labels_is_off(nodes):
    """A multi-scan network's moving-car label (raw 252) on the car's points: with the default
    moving_labels the node's map never holds the car (no trail, whatever rays follow), nor its
    half the network called "truck" without marking it as moving; with moving_labels:=false the
    same points are mapped as car and truck."""
    from mapper_rig import odometry

    from convbki_core.io.map_file import read_map
    from convbki_ros.outputs.cloud_encoding import encode_cloud

    points, labels = street(with_car=True)
    car = labels == 10
    # The car's left half is "truck" (raw 18), a static id: part of the moving car all the same.
    left = car & (points[:, 1] > 0.0)
    labels = np.where(left, 18, np.where(car, 252, labels)).astype(np.uint32)
    counts = {}
    rigs = nodes[True].wait_ready(), nodes[False].wait_ready()
    try:
        for moving_labels, rig in zip((True, False), rigs, strict=True):
            for scan in range(2):
                stamp = rig.next_stamp()
                rig.publish(odometry(stamp), encode_cloud(stamp, "velo_link", fields(points, labels)))
                rig.wait_stats(lambda s, scan=scan: s.integrated == scan + 1)
            saved = rig.call("save_map")
            assert saved.success, saved.message
            _, _, alpha = read_map(rig.map_file)
            alpha[:, 0] = 0.0  # the class of the surface, as the map's queries read it
            label = alpha.argmax(axis=1)
            counts[moving_labels] = (int(np.count_nonzero(np.isin(label, [CAR, TRUCK]))),
                                     int(np.count_nonzero(label == 13)))
    finally:
        outputs = close_together(*rigs)
    assert not any("Traceback" in output for output in outputs), outputs
    assert counts[True][0] == 0 and counts[True][1] > 100, counts  # no car; the house is there
    assert counts[False][0] > 100, counts

"""The node's map outputs over DDS: a subscriber that applies every semantic_map/updates message
from the start holds exactly semantic_map, through moves of the window, a reset and a change
of the variance filter at run time; semantic_map/view stays within its radius and budget."""

import numpy as np
from mapper_rig import TRANSLATION, WAIT, Rig

from convbki_core.outputs.records import RECORD, apply_records


def records_of(msg) -> np.ndarray:
    fields = {f.name: f.offset for f in msg.fields}
    assert fields == {name: RECORD.fields[name][1] for name in RECORD.names} and msg.point_step == RECORD.itemsize
    return np.frombuffer(bytes(msg.data), RECORD, count=msg.width)


def shown(msg) -> dict:
    return {(float(r["x"]), float(r["y"]), float(r["z"])): r for r in records_of(msg)}


def test_updates_rebuild_the_map_and_the_view_is_bounded(tmp_path):
    from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
    from rcl_interfaces.srv import SetParameters
    from sensor_msgs.msg import PointCloud2

    # Without free space every stored voxel is shown, so the counters' voxel count says which
    # map message reflects the last scan (test_node_free_space covers the updates with it).
    rig = Rig(tmp_path, "-p", "view_radius:=12.0", "-p", "view_max_points:=3000", "-p", "free_space:=false",
              diagnostics_period=0.05)
    try:
        updates = rig.probe.subscribe(PointCloud2, "/semantic_map/updates")
        views = rig.probe.subscribe(PointCloud2, "/semantic_map/view", latched=True)
        rebuilt: dict = {}
        applied = 0

        def apply_new() -> None:
            nonlocal applied
            for msg in updates[applied:]:
                apply_records(rebuilt, records_of(msg))
            applied = len(updates)

        def in_step(expected_voxels: int) -> bool:
            apply_new()
            return bool(rig.maps) and rig.maps[-1].width == expected_voxels and shown(rig.maps[-1]).keys() == \
                rebuilt.keys()

        # Along x, 15 m a scan: the window (40 m long) leaves voxels behind in the store.
        for step in range(4):
            stats = rig.integrate_good_cloud(translation=TRANSLATION + [15.0 * step, 0.0, 0.0])
        assert rig.probe.spin_until(lambda: in_step(stats.voxels), WAIT), (len(rebuilt), stats)
        assert rig.call("reset").success
        stats = rig.integrate_good_cloud(translation=TRANSLATION + [45.0, 0.0, 0.0])
        stats = rig.integrate_good_cloud(translation=TRANSLATION + [50.0, 3.0, 0.0])
        assert rig.probe.spin_until(lambda: in_step(stats.voxels), WAIT), (len(rebuilt), stats)

        client = rig.probe.node.create_client(SetParameters, "/convbki_mapper/set_parameters")
        assert rig.probe.spin_until(client.service_is_ready, WAIT)
        future = client.call_async(SetParameters.Request(parameters=[Parameter(
            name="max_variance", value=ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=0.005))]))
        assert rig.probe.spin_until(future.done, WAIT) and future.result().results[0].successful

        def filtered_and_rebuilt() -> bool:
            apply_new()
            return bool(rig.maps) and 0 < rig.maps[-1].width < stats.voxels and \
                shown(rig.maps[-1]).keys() == rebuilt.keys()

        assert rig.probe.spin_until(filtered_and_rebuilt, WAIT), (len(rebuilt), rig.maps[-1].width)
        final = shown(rig.maps[-1])
        assert all(rebuilt[key].tobytes() == record.tobytes() for key, record in final.items())
        assert (records_of(rig.maps[-1])["variance"] <= 0.005).all()

        assert rig.probe.spin_until(lambda: views and views[-1].width > 0, WAIT)
        view = records_of(views[-1])
        centre = TRANSLATION + [50.0, 3.0, 0.0]
        assert len(view) <= 3000
        assert (np.hypot(view["x"] - centre[0], view["y"] - centre[1]) <= 12.0 + 1e-4).all()

        # A smaller view at run time: the next scan's view keeps to it. view_max_points, a resource
        # limit, cannot be raised or changed at run time.
        raised = rig.set_parameters(view_max_points=50)[0]
        assert not raised.successful and "read-only" in raised.reason, raised
        wide = len(view)
        assert rig.set_parameters(view_radius=5.0)[0].successful

        def within_five_metres() -> bool:
            latest = records_of(views[-1])
            return bool((np.hypot(latest["x"] - centre[0], latest["y"] - centre[1]) <= 5.0 + 1e-4).all())

        rig.integrate_good_cloud(translation=TRANSLATION + [50.0, 3.0, 0.0])
        assert rig.probe.spin_until(within_five_metres, WAIT), views[-1].width
        assert 0 < views[-1].width < wide
    finally:
        output = rig.close()
    assert "Traceback" not in output and "[ERROR]" not in output, output

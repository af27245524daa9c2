"""Parameters no other test sets, each with an effect a test can see, over DDS: one node maps with
non-default map settings (dense path, prior, clamping, movers' rules, variance filter, best-effort
inputs, no local window, its PLY file and costmap limit); another changes the queue, timing and
robustness settings while it runs. The history depth of semantic_map/updates is not carried by
DDS discovery (the graph says UNKNOWN), so it is read from the publisher of a node in this process."""

import signal

import numpy as np
from mapper_rig import LABELS, POINTS, POSE, TRANSLATION, WAIT, Rig, cloud, fields, node_default_mapper, odometry
from ros_helpers import domain_id
from test_node_free_space import street

from convbki_core.io.labels import load_label_map
from convbki_core.io.map_file import read_map
from convbki_ros.outputs.cloud_encoding import encode_cloud

MAP_OPTIONS = {"prior": 0.01, "max_concentration": 20.0, "forget_movers": False}
DEFAULT_OPTIONS = {"prior": 1e-3, "max_concentration": 300.0, "forget_movers": True}


def street_scans() -> list[tuple[np.ndarray, np.ndarray]]:
    """A car, then a house where it stood (a return of another class), then the street without it:
    the prior, clamping and the movers' rules each change the map this leaves."""
    points, labels = street(with_car=True)
    return [(points, labels), (points, np.where(labels == 10, 50, labels).astype(np.uint32)), street(with_car=False)]


def offline(**options):
    """(indices, alpha) sorted, of the street scans mapped offline (fast path) with ``options``."""
    label_map = load_label_map("semantic_kitti")
    mapper = node_default_mapper(**options)
    for points, labels in street_scans():
        mapper.integrate(points, label_map.to_learning(labels), POSE)
    indices, alpha = mapper.items()
    order = np.lexsort(indices.T)
    return mapper, indices[order], alpha[order]


def same_map(a, b) -> bool:
    return a[1].shape == b[1].shape and np.array_equal(a[1], b[1]) and np.allclose(a[2], b[2], rtol=1e-5)


def test_map_settings_at_start_shape_the_map_and_its_outputs(tmp_path):
    from nav_msgs.srv import GetMap
    from rclpy.qos import ReliabilityPolicy
    from sensor_msgs.msg import PointCloud2

    ply = tmp_path / "street.ply"
    rig = Rig(tmp_path, "-p", "update_path:=dense", "-p", "prior:=0.01", "-p", "max_concentration:=20.0",
              "-p", "forget_movers:=false", "-p", "max_variance:=0.05", "-p", "input_qos:=sensor_data",
              "-p", "publish_local:=false", "-p", f"ply_file:={ply}", "-p", "costmap_max_cells:=10",
              "-p", "scan_log:=false", diagnostics_period=0.05, wait=False)
    try:
        # The maps offline, while the node starts: with these settings, and with each of them at its default.
        expected = offline(**MAP_OPTIONS)
        with_default = {name: offline(**{**MAP_OPTIONS, name: default}) for name, default in DEFAULT_OPTIONS.items()}
        rig.wait_ready()
        node = rig.probe.node
        for topic in ("/cloud_in", "/odom"):  # sensor_data: the node reads its inputs best effort
            def info(topic=topic) -> list:
                return [i for i in node.get_subscriptions_info_by_topic(topic) if i.node_name == "convbki_mapper"]

            assert rig.probe.spin_until(info, WAIT), topic
            assert [i.qos_profile.reliability for i in info()] == [ReliabilityPolicy.BEST_EFFORT], (topic, info())
        updates = rig.probe.subscribe(PointCloud2, "/semantic_map/updates")
        local = rig.probe.subscribe(PointCloud2, "/semantic_map/local")
        for scan, (points, labels) in enumerate(street_scans()):
            stamp = rig.next_stamp()
            rig.publish(odometry(stamp), encode_cloud(stamp, "velo_link", fields(points, labels)))
            rig.wait_stats(lambda s, scan=scan: s.integrated == scan + 1)

        # The dense path maps what the fast path maps offline, with this prior, clamping and no movers' rules.
        assert rig.call("save_map").success
        metadata, indices, alpha = read_map(rig.map_file)
        order = np.lexsort(indices.T)
        got = (None, indices[order], alpha[order])
        assert metadata["prior"] == 0.01, metadata
        assert read_map(rig.map_file, with_scan_log=True)[0]["scan_log"] is None  # scan_log false: none kept
        assert same_map(got, expected)
        for name in DEFAULT_OPTIONS:  # each setting made a difference
            assert not same_map(got, with_default[name]), name

        # max_variance 0.05: the published map and the PLY export hold the confident voxels only.
        voxels = expected[0].voxels()
        shown = voxels.label != 0
        confident = int((shown & (voxels.variance <= 0.05)).sum())
        assert 0 < confident < shown.sum()
        assert rig.map_message(confident).width == confident
        exported = rig.call("export_ply")
        assert exported.success and exported.message == f"wrote {confident} voxels to {ply}", exported.message
        assert ply.stat().st_size > 0

        # publish_local false: updates came with every scan, the local window never.
        assert rig.probe.spin_until(lambda: len(updates) > 0, WAIT)
        assert local == []

        # costmap_max_cells 10: the whole map's grid is refused; a resource limit, it cannot be raised at run time.
        mark = rig.log.mark()
        refused = rig.probe.call(GetMap, "/convbki_mapper/get_costmap")
        assert refused.map.info.width * refused.map.info.height == 0, refused.map.info
        rig.wait_log(r"\[WARN\].*more than costmap_max_cells = 10: answered an empty grid", mark)
        raised = rig.set_parameters(costmap_max_cells=25_000_000)[0]
        assert not raised.successful and "read-only" in raised.reason, raised

        # ply_file at run time: the next export goes there.
        moved = tmp_path / "elsewhere.ply"
        assert rig.set_parameters(ply_file=str(moved))[0].successful
        exported = rig.call("export_ply")
        assert exported.success and exported.message == f"wrote {confident} voxels to {moved}", exported.message
        assert moved.stat().st_size == ply.stat().st_size
    finally:
        output = rig.close()
    assert "Traceback" not in output, output


# ----------------------------------------------------------------------------- run-time changes


def tiny_cloud(stamp: int, points: int = 50):
    """``points`` points of the good cloud: 16 bytes each (800 bytes of data for 50)."""
    return cloud(stamp, **fields(points=POINTS[:points], labels=LABELS[:points]))


def report(rig: Rig, done) -> dict:
    """The key-values of the first /diagnostics report from now on for which ``done(values)`` holds."""
    seen = len(rig.diagnostics)
    found: list[dict] = []

    def check() -> bool:
        nonlocal seen
        while seen < len(rig.diagnostics):
            values = {item.key: item.value for item in rig.diagnostics[seen].status[0].values}
            seen += 1
            found.append(values)
            if done(values):
                return True
        return False

    assert rig.probe.spin_until(check, WAIT), f"no report reached the expected state: {found[-1:] }"
    return found[-1]


def counts(values: dict) -> tuple[int, int, int]:
    """(scans in, dropped, queued) of a report."""
    return int(values["scans_in"]), int(values["dropped"]), int(values["queue"])


PERIOD = 0.05  # the /diagnostics period of the node below: its reports are the test's clock


def wait_reports(rig: Rig, seconds: float) -> None:
    """Let ``seconds`` pass as the node counts them: its /diagnostics reports, one each PERIOD."""
    seen = len(rig.diagnostics)
    assert rig.probe.spin_until(lambda: len(rig.diagnostics) >= seen + round(seconds / PERIOD), WAIT)


def test_queue_timing_and_robustness_settings_at_start_and_at_run_time(tmp_path):
    from sensor_msgs.msg import PointCloud2

    rig = Rig(tmp_path, "-p", "cloud_queue_size:=3", "-p", "cloud_queue_megabytes:=0.002",
              "-p", "pose_wait_timeout:=0.0", "-p", "odometry_timeout:=3600.0",
              "-p", f"max_points_per_cloud:={len(POINTS) + 10}",
              "-p", "local_period:=1000.0", "-p", "stamp_backwards_tolerance:=5.0", "-p", "max_pose_jump:=0.0",
              diagnostics_period=PERIOD)
    try:
        local = rig.probe.subscribe(PointCloud2, "/semantic_map/local")
        updates = rig.probe.subscribe(PointCloud2, "/semantic_map/updates")

        def clouds(number: int, expected: tuple[int, int, int], points: int = 50) -> None:
            """Publish ``number`` tiny clouds (no odometry: they wait); the counters then."""
            before = counts(report(rig, lambda v: True))[0]
            for _ in range(number):
                rig.publish(tiny_cloud(rig.next_stamp(), points))
            assert counts(report(rig, lambda v: counts(v)[0] == before + number)) == expected

        # -- the queue: 2000 bytes hold two clouds of 800; then clouds of 160 bytes: 3 clouds at most.
        clouds(3, (3, 1, 2))  # the oldest pushed out by the byte limit
        for limit, value in (("cloud_queue_megabytes", 0.0), ("cloud_queue_size", 5)):  # resource limits: read-only
            raised = rig.set_parameters(**{limit: value})[0]
            assert not raised.successful and "read-only" in raised.reason, (limit, raised)
        clouds(1, (4, 1, 3), points=10)  # 1760 bytes: three fit
        clouds(1, (5, 2, 3), points=10)  # cloud_queue_size 3 pushes out the oldest
        # pose_wait_timeout 0 kept them waiting; 0.3 s drops them (they waited longer).
        assert rig.set_parameters(pose_wait_timeout=0.3)[0].successful
        values = report(rig, lambda v: counts(v) == (5, 5, 0))
        assert values["dropped.no pose"] == "5", values
        assert not rig.log.find("no odometry at all")  # odometry_timeout 3600 s

        # -- odometry_timeout 0.5 s at run time: clouds without odometry are warned about.
        assert rig.set_parameters(odometry_timeout=0.5)[0].successful
        mark = rig.log.mark()
        for _ in range(int(WAIT / 0.2)):
            if rig.log.find(r"\[WARN\].*no odometry at all on /odom", mark):
                break
            rig.publish(tiny_cloud(rig.next_stamp(0.1)))
            wait_reports(rig, PERIOD)  # the pace of the clouds
        rig.wait_log(r"\[WARN\].*no odometry at all on /odom", mark)
        assert rig.set_parameters(odometry_timeout=5.0)[0].successful

        # -- diagnostics_period at run time: no reports for six counter lines (0.1 s each, 12 reports
        # before), then again.
        mark = rig.log.mark()
        assert all(result.successful for result in rig.set_parameters(diagnostics_period=1000.0, stats_period=0.1))
        rig.wait_log(r"parameter stats_period is now 0.1", mark)
        seen = len(rig.diagnostics)
        rig.wait_log(r"scans in \d+, integrated", mark, count=6)
        assert len(rig.diagnostics) - seen <= 1, len(rig.diagnostics) - seen  # one may have been on its way
        assert all(result.successful for result in rig.set_parameters(diagnostics_period=PERIOD, stats_period=10.0))
        wait_reports(rig, 3 * PERIOD)  # three reports

        # -- max_points_per_cloud (10 more than the good cloud's) drops a cloud of twice as many on arrival,
        # and cannot be raised at run time (a resource limit).
        stamp = rig.next_stamp()
        rig.publish(odometry(stamp), cloud(stamp, **fields(points=np.concatenate([POINTS, POINTS]),
                                                           labels=np.concatenate([LABELS, LABELS]))))
        assert report(rig, lambda v: v.get("dropped.too large") == "1")["integrated"] == "0"
        raised = rig.set_parameters(max_points_per_cloud=0)[0]
        assert not raised.successful and "read-only" in raised.reason, raised
        rig.integrate_good_cloud()

        # -- local_period 1000 s: the first window is sent, none after it; 0: after every update.
        assert rig.probe.spin_until(lambda: len(local) == 1, WAIT)
        wait_reports(rig, 1.0)  # the default 0.5 s would have passed twice
        sent = len(updates)
        rig.integrate_good_cloud()
        assert rig.probe.spin_until(lambda: len(updates) > sent, WAIT)  # the scan's updates
        wait_reports(rig, 0.6)
        assert len(local) == 1
        assert rig.set_parameters(local_period=0.0)[0].successful
        rig.integrate_good_cloud()
        assert rig.probe.spin_until(lambda: len(local) >= 2, WAIT)  # the window held back, and this scan's
        wait_reports(rig, 0.6)
        windows = len(local)
        # publish_local false at run time: updates, no window.
        assert rig.set_parameters(publish_local=False)[0].successful
        sent = len(updates)
        rig.integrate_good_cloud()
        assert rig.probe.spin_until(lambda: len(updates) > sent, WAIT)
        wait_reports(rig, 0.6)
        assert len(local) == windows

        # -- stamp_backwards_tolerance 5 s: odometry 2.5 s older than the newest is not time going back.
        newest = rig.stamp
        mark = rig.log.mark()
        rig.publish(odometry(newest - 2_500_000_000))
        assert all(result.successful for result in rig.set_parameters(stamp_backwards_tolerance=0.5,
                                                                         reset_on_stamp_backwards=True))
        rig.wait_log(r"parameter reset_on_stamp_backwards is now True", mark)  # after the odometry was taken
        assert not rig.log.find("time went backwards", mark), rig.log.text(mark)
        # 0.5 s at run time: it is, and reset_on_stamp_backwards (at run time) clears the map.
        rig.publish(odometry(newest - 2_500_000_000))
        rig.wait_log(r"\[WARN\].*time went backwards by 2\.500 s .*map reset \(reset_on_stamp_backwards\)", mark)
        rig.wait_stats(lambda s: s.voxels == 0)

        # -- max_pose_jump 0: no check, a cloud between poses 50 m apart is placed half way.
        mark = rig.log.mark()
        before = rig.stats()
        rig.publish(odometry(rig.next_stamp()))
        jumped = rig.next_stamp()
        rig.publish(odometry(jumped, translation=TRANSLATION + [50.0, 0.0, 0.0]), cloud(jumped - 500_000_000))
        after = rig.wait_stats(lambda s: s.integrated == before.integrated + 1)
        assert after.dropped == before.dropped, after
        assert rig.set_parameters(max_pose_jump=10.0)[0].successful
        rig.wait_log(r"parameter max_pose_jump is now 10.0", mark)
        assert not rig.log.find("jumped", mark), rig.log.text(mark)
        # 10 m at run time: the next 50 m is a jump.
        rig.publish(odometry(rig.next_stamp(), translation=TRANSLATION + [100.0, 0.0, 0.0]))
        rig.wait_log(r"\[WARN\].*odometry jumped 50.00 m in 1.00 s .*max_pose_jump = 10.0 m", mark)

        # -- autosave_period at run time writes the map (never saved so far).
        assert not rig.map_file.exists()
        too_often = rig.set_parameters(autosave_period=0.2)[0]
        assert not too_often.successful and "at least 1 s" in too_often.reason, too_often
        assert rig.set_parameters(autosave_period=1.0)[0].successful
        assert rig.probe.spin_until(rig.map_file.exists, WAIT)
        rig.wait_log(r"autosave: saved \d+ voxels", mark)
        # -- save_on_shutdown false at run time: a changed map is not saved at Ctrl-C.
        assert all(result.successful for result in rig.set_parameters(autosave_period=0.0, save_on_shutdown=False))
        saved = rig.map_file.read_bytes()
        rig.integrate_good_cloud(translation=TRANSLATION + [100.0, 0.0, 0.0])
        rig.process.send_signal(signal.SIGINT)
        assert rig.process.wait(timeout=WAIT) == 0
    finally:
        output = rig.close()
    assert "Traceback" not in output, output
    assert "on shutdown" not in output, output
    assert rig.map_file.read_bytes() == saved


def test_updates_depth_is_the_history_of_the_updates_publisher():
    """A node in this process (rclpy, its own context): DDS discovery does not carry a reader's or
    writer's history depth, so the graph cannot show it."""
    import rclpy
    from rclpy.parameter import Parameter

    from convbki_ros.node import MapperNode

    context = rclpy.Context()
    rclpy.init(context=context, domain_id=domain_id())
    node = None
    try:
        node = MapperNode(context=context, parameter_overrides=[
            Parameter("updates_depth", value=3), Parameter("device", value="cpu"),
            Parameter("local_bounds", value=[-4.0, -4.0, -2.0, 4.0, 4.0, 2.0])])
        assert node.outputs.updates.qos_profile.depth == 3
        assert node.outputs.map.qos_profile.depth == 1  # the others keep their own
    finally:
        if node is not None:
            node.stop()
            node.destroy_node()
        context.try_shutdown()

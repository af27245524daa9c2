"""The mapper node end to end: real processes, real DDS, real bag files."""

import signal

import numpy as np
import pytest
from helpers import read_ply
from mapper_rig import BOUNDS, Rig, node_default_mapper
from ros_helpers import Probe, domain_id, start, stop

from convbki_core.config import MapperConfig
from convbki_core.datasets.semantic_kitti import SemanticKittiSequence
from convbki_core.io.labels import load_label_map
from convbki_core.mapper import ConvBKIMapper
from convbki_core.paths import kernel_path
from convbki_core.tools.synth import main as synth
from convbki_ros.inputs.cloud_decoding import FLOAT32, UINT32, decode_cloud
from convbki_ros.tools.kitti_to_bag import main as kitti_to_bag

FRAMES = 5


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    """A short synthetic drive (``synth``, a sparse 16-beam LiDAR to keep it quick) and its bag."""
    root = tmp_path_factory.mktemp("drive")
    assert synth(["--out", str(root / "data"), "--sequence", "08", "--frames", str(FRAMES), "--seed", "3",
                  "--beams", "16", "--azimuth-steps", "360", "--noise-strength", "0.35", "--quiet"]) == 0
    assert kitti_to_bag(["--dataset", str(root / "data"), "--sequence", "08", "--out", str(root / "bag")]) == 0
    return root


def offline_map(root):
    """What ``evaluate``'s mapper object holds after the same frames, set up as the node is by
    default (free space and the movers' rules as its parameters say)."""
    dataset = SemanticKittiSequence(root / "data", "08")
    mapper = node_default_mapper(local_bounds=(BOUNDS[:3], BOUNDS[3:]))
    for frame in dataset:
        mapper.integrate(frame.points, frame.input_labels, frame.pose)
    return mapper


def start_mapper(domain, tmp_path, *parameters):
    """The node on the bag's topics; its /diagnostics every 0.05 s, which the player's
    --wait-for-inputs waits for."""
    return start("convbki_ros.main", domain, "--ros-args", "-r", "cloud_in:=/kitti/velo/pointcloud",
                 "-r", "odom:=/kitti/odom", "-p", f"local_bounds:={BOUNDS}", "-p", "publish_period:=0.3",
                 "-p", "map_period:=0.3", "-p", "diagnostics_period:=0.05",
                 "-p", f"map_file:={tmp_path / 'map.npz'}", "-p", "device:=cpu", *parameters)


def sorted_voxels(centres, labels):
    order = np.lexsort(centres.T)
    return centres[order], labels[order]


def test_node_maps_a_bag_like_the_offline_mapper_and_serves_its_map(drive, tmp_path):
    from sensor_msgs.msg import PointCloud2
    from std_srvs.srv import Trigger

    domain = domain_id()
    mapper = start_mapper(domain, tmp_path)
    probe = Probe(domain)
    try:
        maps = probe.subscribe(PointCloud2, "/semantic_map", latched=True)
        variances = probe.subscribe(PointCloud2, "/semantic_map/variance", latched=True)
        player = start("convbki_ros.tools.play_bag", domain, drive / "bag", "--rate", "2", "--wait-for-inputs")
        expected = offline_map(drive)
        voxels = expected.voxels()
        shown = voxels.label != 0  # the published map leaves out voxels seen empty (class 0)
        assert shown.sum() > 1000
        assert player.wait(timeout=60) == 0, stop(player)

        def complete():
            return bool(maps) and maps[-1].width == shown.sum()

        assert probe.spin_until(complete, timeout=60), f"map has {maps[-1].width if maps else 0} voxels, " \
                                                       f"expected {shown.sum()}"
        cloud = maps[-1]
        assert cloud.header.frame_id == "map" and cloud.height == 1
        fields = {f.name: f.datatype for f in cloud.fields}
        assert fields == {"x": FLOAT32, "y": FLOAT32, "z": FLOAT32, "rgb": FLOAT32, "label": UINT32,
                          "variance": FLOAT32, "confidence": FLOAT32}
        decoded = decode_cloud(cloud, 20)
        got_centres, got_labels = sorted_voxels(decoded.points.astype(np.float32), decoded.labels)
        want_centres, want_labels = sorted_voxels(voxels.centres[shown], voxels.label[shown])
        np.testing.assert_array_equal(got_centres, want_centres)
        np.testing.assert_array_equal(got_labels, want_labels)
        assert probe.spin_until(lambda: variances and variances[-1].width == shown.sum(), timeout=10)
        assert {f.name for f in variances[-1].fields} == {"x", "y", "z", "intensity"}

        saved = probe.call(Trigger, "/convbki_mapper/save_map")
        assert saved.success, saved.message
        reloaded = ConvBKIMapper(MapperConfig.paper(local_bounds=(BOUNDS[:3], BOUNDS[3:]), device="cpu"),
                                 kernel_path("semantic_kitti_compound"))
        reloaded.load(tmp_path / "map.npz")
        a, b = reloaded.voxels(), voxels
        order_a, order_b = np.lexsort(a.indices.T), np.lexsort(b.indices.T)
        np.testing.assert_array_equal(a.indices[order_a], b.indices[order_b])
        np.testing.assert_allclose(a.alpha[order_a], b.alpha[order_b], rtol=1e-6)

        ply = probe.call(Trigger, "/convbki_mapper/export_ply")
        assert ply.success and ply.message == f"wrote {shown.sum()} voxels to {tmp_path / 'map.ply'}", ply.message
        # The PLY holds the shown voxels of the offline map: centres, labels, class colours, variances.
        vertices = read_ply(tmp_path / "map.ply")
        assert len(vertices) == shown.sum()
        ply_centres = np.column_stack([vertices["x"], vertices["y"], vertices["z"]])
        order = np.lexsort(ply_centres.T)
        np.testing.assert_array_equal(ply_centres[order], want_centres)
        np.testing.assert_array_equal(vertices["label"][order], want_labels)
        colours = np.column_stack([vertices["red"], vertices["green"], vertices["blue"]])[order]
        np.testing.assert_array_equal(colours, load_label_map("semantic_kitti").colors[want_labels])
        want_variance = voxels.variance[shown][np.lexsort(voxels.centres[shown].T)]
        np.testing.assert_allclose(vertices["variance"][order], want_variance, rtol=1e-5)

        reset = probe.call(Trigger, "/convbki_mapper/reset")
        assert reset.success
        assert probe.spin_until(lambda: maps[-1].width == 0, timeout=10), "after reset the map must be empty"
    finally:
        probe.close()
        output = stop(mapper)
    assert "Traceback" not in output and "[ERROR]" not in output, output


def test_sigint_stops_the_node_cleanly_and_saves_nothing_when_told_not_to(tmp_path):
    # A map that changed, so that the default (save_on_shutdown true) would write map_file.
    rig = Rig(tmp_path, "-p", "save_on_shutdown:=false", diagnostics_period=0.05)
    try:
        assert rig.integrate_good_cloud().voxels > 0
        rig.process.send_signal(signal.SIGINT)
        code = rig.process.wait(timeout=30)  # a bound for a hung node, not a measurement
    finally:
        output = rig.close()
    assert code == 0, output
    assert "Traceback" not in output and "[ERROR]" not in output, output
    assert not rig.map_file.exists() and not list(rig.map_file.parent.iterdir()), output
    assert "on shutdown" not in output, output


def test_bad_parameters_exit_2_with_a_message(tmp_path):
    domain = domain_id()
    mapper = start_mapper(domain, tmp_path, "-p", "num_classes:=7")
    code = mapper.wait(timeout=60)
    output = stop(mapper)
    assert code == 2 and "kernel has 20 classes, num_classes is 7" in output and "Traceback" not in output

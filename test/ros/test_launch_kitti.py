"""A KITTI bag as a user runs it: `ros2 launch convbki_ros mapper.launch.py` after sourcing
install/setup.bash, `play_bag BAG --clock`, and the map read by a client of its own.

The node takes every pose from the bag's TF alone (pose_source tf: /tf_static's mount of the
LiDAR on the vehicle, /tf's vehicle pose), so the launch file, the replay of /tf and
/tf_static and the node's TF buffer are all on the path; the map must equal the one built
offline from the sequence's LiDAR poses.
"""

import os
import shutil
import signal
import subprocess
import sys

import numpy as np
import pytest
import yaml
from kitti_fixture import pose_about_z, write_sequence
from mapper_rig import node_default_mapper
from ros_helpers import (
    REPO,
    Probe,
    domain_id,
    require_current_install,
    ros2_tools_expected,
    ros2_tools_missing,
    ros_env,
)
from test_node_frames import assert_same_voxels, shown_voxels

from convbki_core.datasets.semantic_kitti import SemanticKittiSequence
from convbki_core.io.labels import load_label_map
from convbki_ros.tools import kitti_to_bag

BOUNDS = [-20.0, -20.0, -3.0, 20.0, 20.0, 3.0]
WAIT = 90.0


def _ros2_launch_available() -> str | None:
    """Why `ros2 launch` cannot run here, or None (decided by finding the modules, as the ros2
    tools' tests do: importing launch_ros needs install/ on the path)."""
    if not (REPO / "install" / "setup.bash").is_file():
        return "no install/setup.bash (run make setup)"
    missing = ros2_tools_missing()
    if missing:
        return f"the ros2 tools are not installed ({', '.join(missing)} not found)"
    if shutil.which("ros2", path=os.path.dirname(sys.executable)) is None and shutil.which("ros2") is None:
        return "the ros2 command (ros2cli) is not on the path"
    return None


def test_a_kitti_bag_through_ros2_launch_and_play_bag_maps_from_tf(tmp_path):
    missing = _ros2_launch_available()
    if missing:
        tarball = ros2_tools_expected()
        if tarball:  # set-up had the tools' sources to install them from: their absence is a failure
            pytest.fail(f"{missing}, although set-up had their sources at {tarball}: run `make setup`")
        pytest.skip(missing)
    require_current_install()
    rng = np.random.default_rng(23)
    frames, poses = [], []
    for number in range(4):
        points = rng.uniform([-15, -15, -2], [15, 15, 2], (400, 3)).astype(np.float32)
        labels = rng.choice([10, 40, 50, 70], len(points)).astype(np.uint32)
        frames.append((points, labels, labels))
        poses.append(pose_about_z(0.2 + 0.1 * number, [2.0 * number, 0.5 * number, 0.1]))
    write_sequence(tmp_path / "kitti", "08", frames, poses, times=[0.1 * i for i in range(4)])
    bag = tmp_path / "bag"
    assert kitti_to_bag.main(["--dataset", str(tmp_path / "kitti"), "--sequence", "08", "--out", str(bag)]) == 0

    params = tmp_path / "robot.yaml"
    params.write_text(yaml.safe_dump({"/**": {"ros__parameters": {
        "pose_source": "tf", "map_frame": "map", "local_bounds": BOUNDS, "device": "cpu", "map_period": 0.2,
        "publish_period": 0.2, "diagnostics_period": 0.2, "save_on_shutdown": False, "map_file": ""}}}))
    domain = domain_id()
    launch = subprocess.Popen(
        ["bash", "-c", "source install/setup.bash && exec ros2 launch convbki_ros mapper.launch.py "
         f"params_file:={params} use_sim_time:=true cloud_topic:=/kitti/velo/pointcloud odom_topic:=/kitti/odom"],
        cwd=REPO, env=ros_env(domain), stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
        text=True, start_new_session=True)
    probe = Probe(domain, "map_client")
    from sensor_msgs.msg import PointCloud2

    maps = probe.subscribe(PointCloud2, "/semantic_map", latched=True)
    player = None
    try:
        player = subprocess.Popen(
            [sys.executable, "-m", "convbki_ros.tools.play_bag", str(bag), "--clock", "--wait-for-node"], cwd=REPO,
            env=ros_env(domain), stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        # The map expected, made while the launch starts and the player waits for its node.
        label_map = load_label_map("semantic_kitti")
        expected = node_default_mapper(local_bounds=(BOUNDS[:3], BOUNDS[3:]))
        sequence = SemanticKittiSequence(tmp_path / "kitti", "08")
        for number, (points, _, predicted) in enumerate(frames):
            expected.integrate(points, label_map.to_learning(predicted), sequence[number].pose)
        voxels = len(shown_voxels(expected)[0])

        _, stderr = player.communicate(timeout=240)
        assert player.returncode == 0, stderr
        assert "/convbki_mapper received 4 of 4 clouds, integrated 4, dropped 0" in stderr, stderr
        assert probe.spin_until(lambda: maps and maps[-1].width == voxels, WAIT), \
            f"/semantic_map has {maps[-1].width if maps else None} voxels, expected {voxels}"
        assert maps[-1].header.frame_id == "map"
        assert_same_voxels(maps[-1], expected)
    finally:
        if player is not None and player.poll() is None:  # a check failed before it ended
            player.kill()
            player.communicate()
        probe.close()
        if launch.poll() is None:
            os.killpg(launch.pid, signal.SIGINT)
        try:
            output, _ = launch.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(launch.pid, signal.SIGKILL)
            output, _ = launch.communicate()
    assert "poses from TF ('map' -> each cloud's frame)" in output, output
    assert launch.returncode == 0, output
    assert "Traceback" not in output, output

"""The node through the ros2 commands a user types, after `source install/setup.bash`.

`ros2 param set/get` (a float parameter given as an integer too), `ros2 service call` for every
service, `ros2 topic info -v` for the QoS of one topic of each kind, and the ROS graph for the QoS
of every topic the reference documents. Each command
runs as its own process (bash, ros2cli, rclpy) against a node in its own process, over DDS,
without the ros2 daemon (so no process outlives the test).
"""

import re
import subprocess
from concurrent.futures import ThreadPoolExecutor

import pytest
from mapper_rig import Rig
from ros_helpers import REPO, ros_env

WAIT = 60.0


def _why_no_ros2cli() -> str | None:
    if not (REPO / "install" / "setup.bash").is_file():
        return "no install/setup.bash (run make setup)"
    try:
        import ros2cli  # noqa: F401
    except ImportError:
        return "ros2cli is not installed (set-up installs it where its sources' tarball is at hand)"
    return None


# The node runs from install/, which must hold the tree's files (the ``current_install`` fixture).
pytestmark = [pytest.mark.skipif(_why_no_ros2cli() is not None, reason=_why_no_ros2cli() or ""),
              pytest.mark.usefixtures("current_install")]


def ros2(domain: int, command: str, timeout: float = WAIT) -> subprocess.CompletedProcess:
    """``ros2 <command>`` in a bash that sourced install/setup.bash, as a user types it."""
    return subprocess.run(["bash", "-c", f"source install/setup.bash && ros2 {command}"], cwd=REPO,
                          env=ros_env(domain), stdin=subprocess.DEVNULL, capture_output=True, text=True,
                          timeout=timeout)


def topic_info(domain: int, topic: str, publishers: int, subscribers: int) -> str:
    """``ros2 topic info -v`` once the graph shows the expected counts and every endpoint's node
    by name (a fresh process discovers endpoints before their nodes' names): polled with a
    deadline. Each try spins 1.5 s for discovery (`--spin-time`; 0.5 s by default, which a
    loaded machine often needs several tries to make up for, each a new process)."""
    import time

    deadline = time.monotonic() + WAIT
    while True:
        result = ros2(domain, f"topic info -v --no-daemon --spin-time 1.5 {topic}")
        text = result.stdout
        if (f"Publisher count: {publishers}" in text and f"Subscription count: {subscribers}" in text
                and "_NODE_NAME_UNKNOWN_" not in text) or time.monotonic() > deadline:
            return text
        # the next try is the wait: each command is a new process that discovers the graph again


# The topics whose QoS `ros2 topic info -v` shows here: one of each kind of the node's endpoints
# (a reliable and a transient-local subscription, a transient-local and a volatile publisher);
# the graph gives every topic's.
ROS2_TOPICS = ("/cloud_in", "/tf_static", "/semantic_map", "/semantic_map/updates")


def qos_of(text: str, node: str) -> dict[str, str]:
    """The QoS lines of ``node``'s endpoint in a ``ros2 topic info -v`` output."""
    for block in text.split("\n\n"):
        if f"Node name: {node}" in block:
            return {key.strip(): value.strip() for key, value in re.findall(r"^\s+(\w[\w ]*): (.+)$", block, re.M)}
    raise AssertionError(f"no endpoint of {node} in:\n{text}")


def test_ros2_param_service_and_topic_commands_work_against_the_node(tmp_path):
    rig = Rig(tmp_path, "-p", "clear_box_min:=[-1.0, -1.0, -1.0]", "-p", "clear_box_max:=[1.0, 1.0, 1.0]",
              diagnostics_period=0.05)
    domain, node = rig.domain, "/convbki_mapper"
    try:
        rig.integrate_good_cloud()

        # Each `ros2` command is a process of its own that mostly waits on discovery: the command
        # sequences below, which do not touch each other's state, and the `topic info` of every
        # topic (what they read, the topics' endpoints, no command here changes) all run side by side.
        def set_and_get() -> None:  # a float given as an integer is taken
            result = ros2(domain, f"param set --no-daemon --timeout 30 {node} publish_period 2")
            assert result.returncode == 0 and "Set parameter successful" in result.stdout, result
            result = ros2(domain, f"param get --no-daemon --timeout 30 {node} publish_period")
            assert "Double value is: 2.0" in result.stdout, result

        def refuse() -> None:  # a bad value refused with the reason
            result = ros2(domain, f"param set --no-daemon --timeout 30 {node} on_pose_jump sometimes")
            assert result.stderr.strip() == ("Setting parameter failed: parameter on_pose_jump: 'sometimes' is not "
                                             "one of keep, reset, new_file"), result

        def describe() -> None:
            result = ros2(domain, f"param describe --no-daemon --timeout 30 {node} transform_timeout")
            assert "Type: double" in result.stdout and "Min value: 0.0" in result.stdout, result

        def get_costmap() -> None:
            result = ros2(domain, f"service call {node}/get_costmap nav_msgs/srv/GetMap")
            assert result.returncode == 0 and "map=nav_msgs.msg.OccupancyGrid(" in result.stdout, result
            assert re.search(r"frame_id='map'.*resolution=0\.2", result.stdout.replace("\n", " ")), \
                result.stdout[:2000]

        def services() -> None:
            # every Trigger service, as `ros2 service call` prints the answer, in an order whose answers are known
            answers = {}
            for service in ("save_map", "load_map", "export_ply", "clear_box", "reset"):
                result = ros2(domain, f"service call {node}/{service} std_srvs/srv/Trigger")
                assert result.returncode == 0, result
                answers[service] = result.stdout
            assert re.search(r"success=True, message=.saved \d+ voxels to ", answers["save_map"]), answers
            assert re.search(r"success=True, message=.loaded \d+ voxels", answers["load_map"]), answers
            assert re.search(r"success=True, message=.wrote \d+ voxels to .*\.ply.\)", answers["export_ply"]), answers
            assert re.search(r"success=True, message=.forgot \d+ voxels in the box", answers["clear_box"]), answers
            assert re.search(r"success=True, message=.map reset: forgot \d+ voxels", answers["reset"]), answers

        # -- the QoS of every topic, as docs/node.md's table says
        expected = {  # topic: (publishers, subscribers, node's endpoint: reliability, durability)
            "/cloud_in": (1, 1, "RELIABLE", "VOLATILE"),
            "/odom": (1, 1, "RELIABLE", "VOLATILE"),
            "/tf": (0, 1, "RELIABLE", "VOLATILE"),
            "/tf_static": (0, 1, "RELIABLE", "TRANSIENT_LOCAL"),
            "/semantic_map": (1, 1, "RELIABLE", "TRANSIENT_LOCAL"),
            "/semantic_map/variance": (1, 0, "RELIABLE", "TRANSIENT_LOCAL"),
            "/semantic_map/view": (1, 0, "RELIABLE", "TRANSIENT_LOCAL"),
            "/semantic_map/updates": (1, 0, "RELIABLE", "VOLATILE"),
            "/semantic_map/local": (1, 0, "RELIABLE", "VOLATILE"),
            "/semantic_map/costmap": (1, 0, "RELIABLE", "TRANSIENT_LOCAL"),
        }
        sequences = (set_and_get, refuse, describe, get_costmap, services)
        with ThreadPoolExecutor(max_workers=len(sequences) + len(ROS2_TOPICS)) as pool:
            infos = {topic: pool.submit(topic_info, domain, topic, *expected[topic][:2]) for topic in ROS2_TOPICS}
            for done in [pool.submit(check) for check in sequences]:
                done.result()  # a failed assertion is raised here
            texts = {topic: info.result() for topic, info in infos.items()}
        for topic in ROS2_TOPICS:
            qos = qos_of(texts[topic], "convbki_mapper")
            assert (qos.get("Reliability"), qos.get("Durability")) == expected[topic][2:], (topic, texts[topic])
        # Every topic's, as the ROS graph gives it to any node (what `ros2 topic info -v` prints).
        graph = rig.probe.node

        def endpoints(topic: str) -> tuple[list, list]:
            return graph.get_publishers_info_by_topic(topic), graph.get_subscriptions_info_by_topic(topic)

        counts = {topic: want[:2] for topic, want in expected.items()}
        assert rig.probe.spin_until(lambda: all(tuple(map(len, endpoints(t))) == c for t, c in counts.items()), WAIT), \
            {topic: tuple(map(len, endpoints(topic))) for topic in expected}
        for topic, (_, _, reliability, durability) in expected.items():
            publishers, subscribers = endpoints(topic)
            mine = [e for e in publishers + subscribers if e.node_name == "convbki_mapper"]
            assert [(e.qos_profile.reliability.name, e.qos_profile.durability.name) for e in mine] == \
                [(reliability, durability)], (topic, mine)
    finally:
        output = rig.close()
    assert "Traceback" not in output, output

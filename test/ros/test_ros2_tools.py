"""ROS 2's own tools against the installed workspace, each run in a fresh bash that sources
install/setup.bash and nothing else (as a user's terminal): `ros2 interface show` for every
interface the node and launch_ros use (tf2_msgs and composition_interfaces are built by
set-up where ROS 2 comes from the PyPI wheels), and `ros2 launch convbki_ros
mapper.launch.py` bringing the node up over DDS and stopping cleanly on Ctrl-C.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
from pathlib import Path

import pytest
from ros_helpers import (
    REPO,
    NodeLog,
    Probe,
    domain_id,
    ros2_tools_expected,
    ros2_tools_missing,
    selected_tests,
)

SETUP_BASH = REPO / "install" / "setup.bash"
missing = ros2_tools_missing()
pytestmark = [
    pytest.mark.skipif(bool(missing) and not ros2_tools_expected(),
                       reason=f"ros2cli/launch not installed ({', '.join(missing)} not found; with the PyPI wheels "
                              "`make setup` installs them from their sources' tarball, CONVBKI_ROS2_TOOLS)"),
    pytest.mark.skipif(not SETUP_BASH.exists(), reason="install/setup.bash missing: run `make setup`"),
    pytest.mark.usefixtures("current_install"),  # the tools run install/, which must hold the tree's files
]


@pytest.fixture(autouse=True)
def _tools_installed():
    """Where set-up had the tools' sources, their absence fails every test here rather than skipping it."""
    if missing:
        pytest.fail(f"ros2cli/launch not installed ({', '.join(missing)} not found), although set-up had their "
                    f"sources at {ros2_tools_expected()}: run `make setup`")


# Top-level lines (comments dropped) of `ros2 interface show`: Jazzy's definitions.
INTERFACES = {
    # the node's inputs, outputs and services (docs/node.md)
    "sensor_msgs/msg/PointCloud2": ["std_msgs/Header header", "uint32 height", "uint32 width",
                                    "PointField[] fields", "bool is_bigendian", "uint32 point_step",
                                    "uint32 row_step", "uint8[] data", "bool is_dense"],
    "nav_msgs/msg/Odometry": ["std_msgs/Header header", "string child_frame_id",
                              "geometry_msgs/PoseWithCovariance pose", "geometry_msgs/TwistWithCovariance twist"],
    "diagnostic_msgs/msg/DiagnosticArray": ["std_msgs/Header header", "DiagnosticStatus[] status"],
    "std_srvs/srv/Trigger": ["---", "bool success", "string message"],
    "rosgraph_msgs/msg/Clock": ["builtin_interfaces/Time clock"],
    "nav_msgs/msg/OccupancyGrid": ["std_msgs/Header header", "MapMetaData info", "int8[] data"],
    "nav_msgs/srv/GetMap": ["---", "OccupancyGrid map"],
    # TF (the pose source `tf`, a cloud's mount)
    "tf2_msgs/msg/TFMessage": ["geometry_msgs/TransformStamped[] transforms"],
    # what launch_ros imports
    "composition_interfaces/srv/LoadNode": [
        "string package_name", "string plugin_name", "string node_name", "string node_namespace", "uint8 log_level",
        "string[] remap_rules", "rcl_interfaces/Parameter[] parameters", "rcl_interfaces/Parameter[] extra_arguments",
        "---", "bool success", "string error_message", "string full_node_name", "uint64 unique_id"],
    "composition_interfaces/srv/UnloadNode": ["uint64 unique_id", "---", "bool success", "string error_message"],
    "composition_interfaces/srv/ListNodes": ["---", "string[] full_node_names", "uint64[] unique_ids"],
}
# Messages whose type hash is compared with Jazzy's (rosbags' Jazzy type store).
HASHED = ["tf2_msgs/msg/TFMessage", "sensor_msgs/msg/PointCloud2", "nav_msgs/msg/Odometry"]

NODE = "convbki_mapper"
START_TIMEOUT = 60.0  # the node imports torch and loads its compiled kernels
STOP_TIMEOUT = 30.0


def terminal_env(domain: int, log_dir: Path) -> dict[str, str]:
    """A fresh terminal's environment: no ROS, venv or colcon variables, the venv off PATH."""
    keep = ("HOME", "USER", "LANG", "LC_ALL", "TMPDIR", "TERM", "RMW_IMPLEMENTATION")
    env = {name: os.environ[name] for name in keep if name in os.environ}
    venv = str(REPO / ".venv")
    env["PATH"] = os.pathsep.join(p for p in os.environ.get("PATH", "/usr/bin:/bin").split(os.pathsep)
                                  if p and not p.startswith(venv))
    env.update(ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", ROS_LOG_DIR=str(log_dir),
               PYTHONUNBUFFERED="1")
    return env


def in_terminal(script: str) -> list[str]:
    """bash running ``script`` after `source install/setup.bash` (and no start-up files)."""
    return ["bash", "--noprofile", "--norc", "-c", f'source "{SETUP_BASH}" && {script}']


def _default_sigint() -> None:
    # A shell that starts a pipeline in the background ignores SIGINT in it, and that
    # disposition is inherited; the launch must get Ctrl-C as a terminal delivers it.
    signal.signal(signal.SIGINT, signal.SIG_DFL)


@pytest.fixture(scope="module")
def shown(tmp_path_factory: pytest.TempPathFactory) -> dict[str, str]:
    """``ros2 interface show`` of each interface, and ``ros2 pkg prefix`` of their packages,
    from one terminal (each ros2 call is a Python start-up; one bash keeps it to those)."""
    packages = sorted({name.split("/")[0] for name in INTERFACES} | {"convbki_ros", "rviz2"})
    script = "; ".join([*(f'echo "=== show {name}"; ros2 interface show {name}' for name in INTERFACES),
                        *(f'echo "=== prefix {name}"; ros2 pkg prefix {name}' for name in packages)])
    log_dir = tmp_path_factory.mktemp("ros_log")
    result = subprocess.run(in_terminal(script), env=terminal_env(domain_id(), log_dir), cwd=log_dir,
                            stdin=subprocess.DEVNULL, capture_output=True, text=True, timeout=120)
    sections = dict(re.findall(r"^=== (\w+ \S+)\n(.*?)(?=^=== |\Z)", result.stdout, re.M | re.S))
    assert len(sections) == len(INTERFACES) + len(packages), f"{result.stdout}\n{result.stderr}"
    return {**sections, "stderr": result.stderr}


def top_level(definition: str) -> list[str]:
    """The interface's own lines, blanks collapsed: nested definitions (indented) and comments left out."""
    lines = (line.split("#", 1)[0].split() for line in definition.splitlines() if not line.startswith(("\t", " ")))
    return [" ".join(words) for words in lines if words]


@pytest.mark.parametrize("name", list(INTERFACES))
def test_interface_show(shown: dict[str, str], name: str) -> None:
    assert top_level(shown[f"show {name}"]) == INTERFACES[name], shown[f"show {name}"] + shown["stderr"]


def test_pkg_prefix_finds_the_installed_package(shown: dict[str, str]) -> None:
    assert shown["prefix convbki_ros"].strip() == str(REPO / "install" / "convbki_ros")


@pytest.mark.parametrize("name", HASHED)
def test_type_hash_is_jazzys(shown: dict[str, str], name: str) -> None:
    """The type hash (what DDS peers compare) of the installed definition is Jazzy's."""
    from rosbags.typesys import Stores, get_typestore

    package, _, message = name.split("/")
    description = Path(shown[f"prefix {package}"].strip()) / "share" / package / "msg" / f"{message}.json"
    hashes = {entry["type_name"]: entry["hash_string"] for entry in json.loads(description.read_text())["type_hashes"]}
    assert hashes[name] == get_typestore(Stores.ROS2_JAZZY).hash_rihs01(name)


class Launch:
    """``ros2 launch convbki_ros mapper.launch.py ARGS`` in a terminal, on its own domain."""

    def __init__(self, tmp_path: Path, *arguments: str):
        self.domain = domain_id()
        command = "exec ros2 launch convbki_ros mapper.launch.py " + " ".join(arguments)
        self.process = subprocess.Popen(in_terminal(command), env=terminal_env(self.domain, tmp_path), cwd=tmp_path,
                                        stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                        text=True, preexec_fn=_default_sigint)
        self.log = NodeLog(self.process)
        self.probe = Probe(self.domain, name="launch_probe")

    def wait_for_node(self, namespace: str) -> None:
        def up() -> bool:
            return (NODE, namespace) in self.probe.node.get_node_names_and_namespaces()

        assert self.probe.spin_until(lambda: up() or self.process.poll() is not None, START_TIMEOUT) and up(), \
            f"{namespace.rstrip('/')}/{NODE} did not come up:\n{self.log.text()}"

    def subscriptions(self, namespace: str, expected: dict[str, list[str]]) -> dict[str, list[str]]:
        """The node's subscriptions once ``expected`` are among them (it subscribes when it is
        ready, after its node exists), or when the time is up."""
        def current() -> dict[str, list[str]]:
            return dict(self.probe.node.get_subscriber_names_and_types_by_node(NODE, namespace))

        self.probe.spin_until(lambda: expected.items() <= current().items(), START_TIMEOUT)
        return current()

    def stop(self) -> str:
        """Ctrl-C, as in the terminal; the launch's whole output once it has ended."""
        self.process.send_signal(signal.SIGINT)
        try:
            self.process.wait(timeout=STOP_TIMEOUT)
        finally:
            self.probe.close()
            output = self.log.close()
        return output


def _rviz_installed(shown: dict[str, str]) -> bool:
    return bool(shown["prefix rviz2"].strip())  # `ros2 pkg prefix` prints nothing on stdout otherwise


LAUNCH_ARGUMENTS = {  # test: the arguments of its launch, given ``shown``
    "test_launch_brings_the_node_up_and_stops_on_ctrl_c": lambda shown: ["use_sim_time:=false"],
    "test_launch_arguments_reach_the_node": lambda shown: [
        "namespace:=robot1", "cloud_topic:=lidar/points", "odom_topic:=/robot1/odometry", "use_sim_time:=true",
        "log_level:=debug", *([] if _rviz_installed(shown) else ["rviz:=true"])],  # rviz: says so, mapper alone
}


@pytest.fixture(scope="module")
def launches(request, shown: dict[str, str], tmp_path_factory: pytest.TempPathFactory):
    """``launches(test name)``: that test's launch. The launches of every selected test here start
    together, each on its own domain (a launch mostly waits for its node to start); one not
    started yet starts when asked for. A launch its test did not stop is stopped at the end."""
    started: dict[str, Launch] = {}

    def launch(test: str) -> Launch:
        if test not in started:
            started[test] = Launch(tmp_path_factory.mktemp("launch"), *LAUNCH_ARGUMENTS[test](shown))
        return started[test]

    try:
        for test in sorted(LAUNCH_ARGUMENTS.keys() & selected_tests(request)):
            launch(test)
        yield launch
    finally:
        for each in started.values():
            if each.process.poll() is None:
                each.stop()


def test_launch_brings_the_node_up_and_stops_on_ctrl_c(launches, request) -> None:
    launch = launches(request.node.name)
    try:
        launch.wait_for_node("/")
        # The node works: it reports on /diagnostics (every second, in the system clock).
        from diagnostic_msgs.msg import DiagnosticArray

        reports = launch.probe.subscribe(DiagnosticArray, "/diagnostics")
        mine = f"/{NODE}: mapping"
        assert launch.probe.spin_until(lambda: any(s.name == mine for r in reports for s in r.status), 15.0), \
            f"no /diagnostics from the launched node:\n{launch.log.text()}"
        expected = {"/cloud_in": ["sensor_msgs/msg/PointCloud2"], "/odom": ["nav_msgs/msg/Odometry"]}
        inputs = launch.subscriptions("/", expected)
        assert expected.items() <= inputs.items(), inputs
        started = launch.log.wait_for(r"\[mapper-1\]: process started with pid \[(\d+)\]", timeout=5.0)
        assert started, launch.log.text()
    finally:
        output = launch.stop()
    assert launch.process.returncode == 0, output
    assert re.search(r"\[mapper-1\]: process has finished cleanly", output), output
    # launch waited for the node: nothing is left running.
    assert not Path(f"/proc/{started[0].group(1)}").exists(), output


def test_launch_arguments_reach_the_node(launches, request, shown: dict[str, str]) -> None:
    rviz_installed = _rviz_installed(shown)
    launch = launches(request.node.name)  # started with rviz:=true where rviz2 is not installed
    try:
        launch.wait_for_node("/robot1")
        # The relative cloud topic follows the namespace; /clock: use_sim_time:=true.
        expected = {"/robot1/lidar/points": ["sensor_msgs/msg/PointCloud2"],
                    "/robot1/odometry": ["nav_msgs/msg/Odometry"], "/clock": ["rosgraph_msgs/msg/Clock"]}
        inputs = launch.subscriptions("/robot1", expected)
        assert expected.items() <= inputs.items(), inputs
        # log_level:=debug reaches the node: rclpy logs its debug lines.
        assert launch.log.wait_for(r"\[mapper-1\] \[DEBUG\]", timeout=10.0), launch.log.text()
    finally:
        output = launch.stop()
    assert launch.process.returncode == 0, output
    if not rviz_installed:
        assert len(re.findall(r"rviz2 is not installed", output)) == 1, output
    assert re.search(r"\[mapper-1\]: process has finished cleanly", output), output

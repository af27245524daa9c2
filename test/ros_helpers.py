"""Helpers for tests that talk to real ROS 2 processes over DDS."""

import itertools
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from convbki_core.geometry.poses import pose_from_translation_quaternion
from convbki_ros.dds import use_large_data_profile

REPO = Path(__file__).resolve().parents[1]
_domains = itertools.count()

# The test process talks to the node with the same Fast DDS profile the node uses (large
# shared-memory segment, large socket buffers), or a big cloud crawls through 64 KB UDP
# fragments. Fast DDS reads the profile when the process creates its first participant,
# so it is set when this module is imported, before any test runs.
use_large_data_profile()


ROS2_TOOLS = ("ros2cli", "ros2interface", "ros2pkg", "launch", "launch_ros", "ros2launch")


def ros2_tools_missing() -> list[str]:
    """The ros2 tools' packages that are not installed, found without importing them (launch_ros
    needs install/ on the path to import). A namespace package does not count: the repo's own
    launch/ folder would."""
    import importlib.util

    def installed(package: str) -> bool:
        spec = importlib.util.find_spec(package)
        return spec is not None and spec.origin is not None

    return [name for name in ROS2_TOOLS if not installed(name)]


def ros2_tools_expected() -> str | None:
    """Where set-up was to install the ros2 tools from (their sources' tarball, as
    scripts/setup.sh finds it), or None where it had none to install."""
    tarball = Path(os.environ.get("CONVBKI_ROS2_TOOLS") or REPO.parent / "shared" / "vendor" /
                   "ros2-jazzy-python-tools.tar.gz")
    return str(tarball) if tarball.is_file() else None


def domain_id() -> int:
    """A ROS_DOMAIN_ID in 1..100, different per test and per pytest process."""
    return 1 + (os.getpid() * 13 + next(_domains)) % 100


def selected_tests(request) -> set[str]:
    """The names (with their parameters) of this run's selected tests (after -k, -m, node ids) in
    the module of ``request``: what a module fixture that starts their slow parts together starts."""
    return {item.name for item in request.session.items if item.path == request.path}


def stale_install(root: Path = REPO) -> str | None:
    """The first package file whose copy in ``root``/install (what `source install/setup.bash`
    runs: colcon copies the sources) differs from the tree's, or None when the install is current.
    Python sources are compared with the installed site-packages, config/ and launch/ with share/."""
    prefix = root / "install" / "convbki_ros"
    sites = sorted(prefix.glob("lib/python*/site-packages"))
    if not sites:
        return "install/convbki_ros (not built)"
    pairs = [(package, sites[0] / package, "*.py") for package in ("convbki_core", "convbki_ros")]
    pairs += [(folder, prefix / "share" / "convbki_ros" / folder, "*") for folder in ("config", "launch")]
    for folder, installed_folder, pattern in pairs:
        for source in sorted((root / folder).rglob(pattern)):
            if not source.is_file() or "__pycache__" in source.parts:
                continue
            installed = installed_folder / source.relative_to(root / folder)
            if not installed.is_file() or installed.read_bytes() != source.read_bytes():
                return str(source.relative_to(root))
    return None


def require_current_install() -> None:
    """Fail (one line) when install/ is older than the sources: a test that runs the installed
    node would otherwise compare an old node with the new code."""
    stale = stale_install()
    if stale is not None:
        pytest.fail(f"install/ is older than the sources ({stale} differs): run `make setup`", pytrace=False)


# Added to a process's environment: Python logs each module it imports ("import time: ... | name").
IMPORT_LOG = {"PYTHONPROFILEIMPORTTIME": "1"}


def split_import_log(output: str) -> tuple[str, list[str]]:
    """The output of a process run with ``IMPORT_LOG``: (its other lines, the modules it imported)."""
    lines = output.splitlines()
    imported = [line.rsplit("|", 1)[-1].strip() for line in lines if line.startswith("import time:")]
    return "\n".join(line for line in lines if not line.startswith("import time:")), imported


def ros_env(domain: int) -> dict:
    return dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
                PYTHONUNBUFFERED="1")


def start(module: str, domain: int, *args: str, prefix: tuple[str, ...] = (), env: dict | None = None,
          cwd: Path = REPO) -> subprocess.Popen:
    """``python -m module args`` as a separate process on ``domain``; output to pipes.

    ``prefix``: a command that runs it (e.g. ``setpriv ...``); ``env``: variables to add."""
    return subprocess.Popen([*prefix, sys.executable, "-m", module, *map(str, args)], cwd=cwd,
                            env={**ros_env(domain), **(env or {})}, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)


def stop(process: subprocess.Popen, timeout: float = 10.0) -> str:
    """Kill ``process`` if still running; return its output."""
    if process.poll() is None:
        process.kill()
    output, _ = process.communicate(timeout=timeout)
    return output or ""


class Probe:
    """An rclpy node in its own context in the test process: subscribes, calls services."""

    def __init__(self, domain: int, name: str = "test_probe"):
        import rclpy
        from rclpy.executors import SingleThreadedExecutor

        os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain)
        self.node = rclpy.create_node(name, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.subscriptions: dict = {}

    def subscribe(self, message_type, topic: str, latched: bool = False, depth: int = 10) -> list:
        """The messages received on ``topic`` (appended while the probe spins); ``depth``: how many
        the reader keeps between two spins."""
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

        received: list = []
        qos = QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)
        self.subscriptions[topic] = self.node.create_subscription(message_type, topic, received.append, qos)
        return received

    def matched(self, *topics: str) -> bool:
        """Whether every subscription on ``topics`` is matched to a publisher (DDS discovery done)."""
        return all(self.subscriptions[topic].get_publisher_count() > 0 for topic in topics)

    def spin_while(self, process, timeout: float) -> int | None:
        """Spin (taking what arrives) until ``process`` ends; its exit code, None on timeout."""
        self.spin_until(lambda: process.poll() is not None, timeout)
        return process.poll()

    def spin_until(self, done, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if done():
                return True
            self.executor.spin_once(timeout_sec=0.05)
        return done()

    def call(self, service_type, name: str, timeout: float = 20.0):
        client = self.node.create_client(service_type, name)
        assert self.spin_until(client.service_is_ready, timeout), f"service {name} not available"
        future = client.call_async(service_type.Request())
        assert self.spin_until(future.done, timeout), f"service {name} did not answer"
        return future.result()

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self.context.try_shutdown()


class NodeLog:
    """Reads a process's output line by line on a thread, so a test can wait for a log line
    while the process runs (``stop`` would only give the output once it has ended)."""

    def __init__(self, process: subprocess.Popen):
        self.process = process
        self.lines: list[str] = []
        self._changed = threading.Condition()
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _read(self) -> None:
        for line in self.process.stdout:
            with self._changed:
                self.lines.append(line)
                self._changed.notify_all()
        with self._changed:
            self._changed.notify_all()

    def mark(self) -> int:
        """A position in the output: ``wait_for(..., since=mark)`` looks only at what comes after."""
        with self._changed:
            return len(self.lines)

    def find(self, pattern: str, since: int = 0) -> list[re.Match]:
        with self._changed:
            lines = self.lines[since:]
        return [match for match in map(re.compile(pattern).search, lines) if match]

    def wait_for(self, pattern: str, since: int = 0, timeout: float = 30.0, count: int = 1) -> list[re.Match]:
        """The first ``count`` matches of ``pattern`` after ``since``; [] on timeout or exit."""
        deadline = time.monotonic() + timeout
        with self._changed:
            while True:
                found = self.find(pattern, since)
                if len(found) >= count:
                    return found[:count]
                remaining = deadline - time.monotonic()
                if remaining <= 0 or not self._thread.is_alive():
                    return []
                self._changed.wait(min(remaining, 0.2))

    def text(self, since: int = 0) -> str:
        with self._changed:
            return "".join(self.lines[since:])

    def close(self, timeout: float = 10.0) -> str:
        """Stop the process if still running (Ctrl-C, then kill); the whole output.

        A clean stop lets Fast DDS remove its shared-memory segment (32 MB with the large-data
        profile); a killed process leaves it in /dev/shm.
        """
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGINT)
            try:
                self.process.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                self.process.kill()
        self.process.wait(timeout=timeout)
        self._thread.join(timeout=timeout)
        return self.text()


def odometry_to_pose(msg: Any) -> np.ndarray:
    """nav_msgs/Odometry (or a Pose, PoseStamped, PoseWithCovariance) -> 4x4 pose."""
    pose = msg
    while hasattr(pose, "pose"):
        pose = pose.pose
    p, o = pose.position, pose.orientation
    return pose_from_translation_quaternion(np.array([p.x, p.y, p.z], np.float64),
                                            np.array([o.x, o.y, o.z, o.w], np.float64))


def unpack_rgb(packed: np.ndarray) -> np.ndarray:
    """(...) float32 packed 0x00RRGGBB -> (..., 3) uint8 RGB."""
    bits = np.ascontiguousarray(packed, dtype=np.float32).view(np.uint32)
    return np.stack([(bits >> 16) & 0xFF, (bits >> 8) & 0xFF, bits & 0xFF], axis=-1).astype(np.uint8)

"""Helpers for tests that talk to real ROS 2 processes over DDS."""

import itertools
import os
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
_domains = itertools.count()


def domain_id() -> int:
    """A ROS_DOMAIN_ID in 1..100, different per test and per pytest process."""
    return 1 + (os.getpid() * 13 + next(_domains)) % 100


def ros_env(domain: int) -> dict:
    return dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
                PYTHONUNBUFFERED="1")


def start(module: str, domain: int, *args: str) -> subprocess.Popen:
    """``python -m module args`` as a separate process on ``domain``; output to pipes."""
    return subprocess.Popen([sys.executable, "-m", module, *map(str, args)], cwd=REPO, env=ros_env(domain),
                            stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


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

    def subscribe(self, message_type, topic: str, latched: bool = False) -> list:
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

        received: list = []
        qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)
        self.node.create_subscription(message_type, topic, received.append, qos)
        return received

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

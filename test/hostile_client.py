"""A hostile participant on the mapper's ROS domain: one attack per run, in a process of its own.

``python test/hostile_client.py ATTACK --domain D [--node /convbki_mapper] [--arg VALUE ...]``
prints one JSON object: what each request was answered (parameter results, service responses)
or what was sent. It uses nothing but what anyone on the domain has: rclpy and the message
types; no credentials, no file access to the robot. ``test/ros/test_hostile.py`` runs it.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

WAIT = 30.0


class Client:
    def __init__(self, domain: int, node: str):
        import rclpy
        from rclpy.executors import SingleThreadedExecutor

        os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
        self.rclpy = rclpy
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain)
        self.node = rclpy.create_node(f"hostile_{os.getpid()}", context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.target = node

    def spin_until(self, done, timeout: float = WAIT) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if done():
                return True
            self.executor.spin_once(timeout_sec=0.02)
        return done()

    def call(self, service_type, name: str, request=None, timeout: float = WAIT):
        client = self.node.create_client(service_type, name)
        if not self.spin_until(client.service_is_ready, timeout):
            raise SystemExit(f"service {name} is not there")
        future = client.call_async(request if request is not None else service_type.Request())
        if not self.spin_until(future.done, timeout):
            return None
        return future.result()

    def trigger(self, service: str) -> dict:
        from std_srvs.srv import Trigger

        started = time.monotonic()
        response = self.call(Trigger, f"{self.target}/{service}")
        if response is None:
            return {"answered": False}
        return {"answered": True, "success": response.success, "message": response.message,
                "seconds": time.monotonic() - started}

    def set_raw(self, *parameters) -> list[dict]:
        """SetParameters with rcl_interfaces/Parameter messages as given (any type, any value)."""
        from rcl_interfaces.srv import SetParameters

        response = self.call(SetParameters, f"{self.target}/set_parameters",
                             SetParameters.Request(parameters=list(parameters)))
        if response is None:
            return [{"answered": False}]
        if not response.results:  # the whole request failed on the node's side, which answered nothing more
            return [{"answered": True, "successful": False, "reason": "an empty answer"}]
        return [{"answered": True, "successful": r.successful, "reason": r.reason} for r in response.results]

    def set(self, **values) -> list[dict]:
        from rclpy.parameter import Parameter

        try:
            messages = [Parameter(name, value=value).to_parameter_msg() for name, value in values.items()]
            return self.set_raw(*messages)
        except Exception as error:  # rclpy itself may refuse to send it (a NUL byte in a string)
            return [{"answered": False, "not sent": f"{error.__class__.__name__}: {error}"}]

    def publisher(self, message_type, topic: str, depth: int = 10, latched: bool = False):
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

        qos = QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)
        publisher = self.node.create_publisher(message_type, topic, qos)
        if not self.spin_until(lambda: publisher.get_subscription_count() > 0):
            raise SystemExit(f"nobody subscribes {topic}")
        return publisher

    def flush(self, publisher, timeout: float = WAIT) -> bool:
        """Wait until every reliable reader acknowledged what ``publisher`` sent."""
        return publisher.wait_for_all_acked(self.rclpy.duration.Duration(seconds=timeout))

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self.context.try_shutdown()


# ----------------------------------------------------------------------------- attacks


def files(client: Client, args) -> dict:
    """map_file and ply_file set to what a request must never write, each followed by the
    service that would write it."""
    results = {}
    for name, service in (("map_file", "save_map"), ("ply_file", "export_ply")):
        for value in args.arg:
            results[f"{name}={value!r}"] = {"set": client.set(**{name: value})[0], "then": client.trigger(service)}
    return results


def weird_parameters(client: Client, args) -> dict:
    """Parameter messages no check foresees: a path too long for the file system, a NUL byte,
    a name nobody declared, the wrong type, a type id that does not exist, resource limits
    raised at run time, a timer period of a nanosecond."""
    from rcl_interfaces.msg import Parameter as ParameterMsg
    from rcl_interfaces.msg import ParameterType, ParameterValue

    long_name = "/tmp/" + "a" * 300 + "/map.npz"
    results = {
        "long map_file": client.set(map_file=long_name)[0],
        "long name in the folder": client.set(map_file="b" * 300 + ".npz")[0],
        "NUL in map_file": client.set(map_file="/etc/passwd\0.npz")[0],
        "undeclared": client.set(no_such_parameter=1)[0],
        "map_file as an integer": client.set(map_file=7)[0],
        "unknown type id": client.set_raw(ParameterMsg(name="map_file", value=ParameterValue(type=200)))[0],
        "string array for a box": client.set_raw(ParameterMsg(name="clear_box_min", value=ParameterValue(
            type=ParameterType.PARAMETER_STRING_ARRAY, string_array_value=["x"] * 3)))[0],
        "huge box": client.set(clear_box_min=[1e308] * 300)[0],
        "cloud_queue_megabytes": client.set(cloud_queue_megabytes=1e6)[0],
        "cloud_queue_size": client.set(cloud_queue_size=10000)[0],
        "view_max_points": client.set(view_max_points=100_000_000)[0],
        "costmap_max_cells": client.set(costmap_max_cells=1_000_000_000)[0],
        "max_map_megabytes": client.set(max_map_megabytes=0.0)[0],
        "map_folder": client.set(map_folder="/")[0],
        "autosave_period": client.set(autosave_period=1e-9)[0],
        "use_sim_time": client.set(use_sim_time=True)[0],
    }
    return results


def cloud_lies(client: Client, args) -> dict:
    """Clouds whose data disagrees with their header: one point declared, 2 MB carried; and
    a consistent cloud over max_cloud_megabytes (``--arg`` its megabytes)."""
    from sensor_msgs.msg import PointCloud2, PointField

    publisher = client.publisher(PointCloud2, "cloud_in")
    fields = [PointField(name=n, offset=4 * i, datatype=PointField.FLOAT32, count=1) for i, n in enumerate("xyz")]
    fields.append(PointField(name="label", offset=12, datatype=PointField.UINT32, count=1))
    one_point = PointCloud2(height=1, width=1, fields=fields, point_step=16, row_step=16, is_dense=True)
    one_point.header.frame_id = "velo_link"
    one_point.data = bytes(2_000_000)  # under the cap: refused for disagreeing with its header
    megabytes = float(args.arg[0])
    points = int(megabytes * 1e6) // 16 + 1
    too_big = PointCloud2(height=1, width=points, fields=fields, point_step=16, row_step=16 * points, is_dense=True)
    too_big.header.frame_id = "velo_link"
    too_big.data = bytes(16 * points)
    long_frame = PointCloud2(height=1, width=1, fields=fields, point_step=16, row_step=16, is_dense=True)
    long_frame.header.frame_id = "f" * 100_000
    long_frame.data = bytes(16)
    for msg in (one_point, too_big, long_frame):
        publisher.publish(msg)
    return {"sent": 3, "acknowledged": client.flush(publisher)}


def path_flood(client: Client, args) -> dict:
    """A Path of ``--arg`` poses on pose_corrections, then the time a service takes to answer.
    Sent as its serialized bytes, as anyone may: rclpy's serializer makes them for three poses
    (every pose after the first is 8-aligned, so the third's bytes repeat), the rest repeats."""
    import struct

    from geometry_msgs.msg import PoseStamped
    from nav_msgs.msg import Path
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from rclpy.serialization import deserialize_message, serialize_message

    count = int(args.arg[0])
    publisher = client.node.create_publisher(Path, "pose_corrections", QoSProfile(
        depth=5, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE))
    if not client.spin_until(lambda: publisher.get_subscription_count() > 0):
        raise SystemExit("nobody subscribes pose_corrections")
    path = Path()
    path.header.frame_id = "map"
    stamped = PoseStamped()
    stamped.header.frame_id = "map"
    stamped.pose.orientation.w = 1.0
    path.poses = [stamped] * 2
    two = serialize_message(path)
    path.poses = [stamped] * 3
    three = serialize_message(path)
    repeated = three[len(two):]
    count_at = 4 + 8 + 4 + len(b"map\0")  # encapsulation, stamp, frame id: the pose count follows
    data = bytearray(two + repeated * (count - 2))
    struct.pack_into("<I", data, count_at, count)
    assert len(deserialize_message(bytes(two[:count_at]) + struct.pack("<I", 3) + two[count_at + 4:] + repeated,
                                   Path).poses) == 3  # the bytes are a Path's
    publisher.publish(bytes(data))
    acknowledged = client.flush(publisher)
    return {"poses": count, "bytes": len(data), "acknowledged": acknowledged, "then": client.trigger("export_ply")}


def tf_flood(client: Client, args) -> dict:
    """Thousands of frames on /tf, and one frame's records stamped a nanosecond apart (``--arg``
    frames and records)."""
    from geometry_msgs.msg import TransformStamped
    from tf2_msgs.msg import TFMessage

    frames, records = int(args.arg[0]), int(args.arg[1])
    publisher = client.publisher(TFMessage, "/tf", depth=100)

    def transform(child: str, stamp_ns: int) -> TransformStamped:
        msg = TransformStamped(child_frame_id=child)
        msg.header.frame_id = "map"
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, 10**9)
        msg.transform.rotation.w = 1.0
        return msg

    batch = 2000
    for start in range(0, frames, batch):
        publisher.publish(TFMessage(transforms=[transform(f"frame_{i}", 1) for i in range(start,
                                                                                          min(frames, start + batch))]))
    for start in range(0, records, batch):
        publisher.publish(TFMessage(transforms=[transform("flooded", 10**9 + i) for i in range(start,
                                                                                               min(records,
                                                                                                   start + batch))]))
    long_frame = transform("f" * 100_000, 1)
    publisher.publish(TFMessage(transforms=[long_frame]))
    return {"acknowledged": client.flush(publisher)}


def odometry_lies(client: Client, args) -> dict:
    """Odometry whose child frame id is 100,000 characters long (it would be kept with every pose)."""
    from nav_msgs.msg import Odometry

    publisher = client.publisher(Odometry, "odom")
    msg = Odometry(child_frame_id="c" * 100_000)
    msg.header.frame_id = "map"
    msg.pose.pose.orientation.w = 1.0
    publisher.publish(msg)
    return {"sent": 1, "acknowledged": client.flush(publisher)}


def drive(client: Client, args) -> dict:
    """Odometry that takes the robot over new ground, ``--arg`` places 100 m apart, with a cloud
    at each: spoofed, or a runaway odometry; every place's voxels leave the window and would stay."""
    from mapper_rig import cloud, odometry
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import PointCloud2

    places = int(args.arg[0])
    clouds, poses = client.publisher(PointCloud2, "cloud_in", depth=100), client.publisher(Odometry, "odom", depth=100)
    for place in range(places):
        stamp = 10**15 + place * 10**9  # far after whatever the robot sent: time goes on
        poses.publish(odometry(stamp, translation=np.array([100.0 * place, 0.0, 0.5])))
        clouds.publish(cloud(stamp))
    if not (client.flush(poses) and client.flush(clouds)):
        raise SystemExit("the node did not take the messages")
    return {"places": places}


def trigger(client: Client, args) -> dict:
    """The node's Trigger services in the order given (``--arg save_map --arg reset ...``)."""
    return {f"{number}: {service}": client.trigger(service) for number, service in enumerate(args.arg)}


ATTACKS = {function.__name__: function for function in (files, weird_parameters, cloud_lies, path_flood, tf_flood,
                                                        odometry_lies, drive, trigger)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("attack", choices=sorted(ATTACKS))
    parser.add_argument("--domain", type=int, required=True)
    parser.add_argument("--node", default="/convbki_mapper")
    parser.add_argument("--arg", action="append", default=[])
    args = parser.parse_args()
    np.seterr(all="ignore")
    client = Client(args.domain, args.node)
    try:
        result = ATTACKS[args.attack](client, args)
    finally:
        client.close()
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())

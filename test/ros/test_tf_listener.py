"""The TF buffer's ROS side: its listener over DDS (tf2's QoS), and make_tf_lookup (the numpy
buffer with its listener in every install, tf2_ros or not; none without tf2_msgs)."""

import subprocess
import sys
import types

import numpy as np
import pytest

from convbki_ros.inputs.tf_buffer import (
    BufferLookup,
    TransformBuffer,
    TransformListener,
    make_tf_lookup,
)
from convbki_ros.inputs.transforms import NS_PER_S


def test_importing_the_module_does_not_import_rclpy():
    code = "import sys, convbki_ros.inputs.tf_buffer; sys.exit('rclpy' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code], check=False).returncode == 0


def ros_transform(parent, child, stamp_ns, translation=(0.0, 0.0, 0.0), quaternion=(0.0, 0.0, 0.0, 1.0)):
    """A geometry_msgs/TransformStamped, as tf2 broadcasters send them."""
    from geometry_msgs.msg import TransformStamped

    msg = TransformStamped()
    msg.header.frame_id, msg.child_frame_id = parent, child
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, NS_PER_S)
    msg.transform.translation.x, msg.transform.translation.y, msg.transform.translation.z = translation
    rotation = msg.transform.rotation
    rotation.x, rotation.y, rotation.z, rotation.w = quaternion
    return msg


@pytest.fixture
def tf_sender():
    """A second participant on a domain of its own: it sends TF, and its graph shows the
    readers another participant offers, as DDS reports them."""
    from ros_helpers import Probe, domain_id

    sender = Probe(domain_id(), "tf_sender")
    yield sender
    sender.close()


def _send(sender, topic: str, transforms: list, static: bool = False):
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from tf2_msgs.msg import TFMessage

    durability = DurabilityPolicy.TRANSIENT_LOCAL if static else DurabilityPolicy.VOLATILE
    publisher = sender.node.create_publisher(TFMessage, topic, QoSProfile(
        depth=10, reliability=ReliabilityPolicy.RELIABLE, durability=durability))
    if not static:  # a volatile sample reaches only the readers matched when it goes out
        assert sender.spin_until(lambda: publisher.get_subscription_count() > 0, 20), f"no reader on {topic}"
    publisher.publish(TFMessage(transforms=transforms))
    return publisher


def test_listener_offers_tf2s_qos_over_dds_and_fills_the_buffer(tf_sender):
    """A real node's listener: its readers, as DDS shows them to another participant, are
    reliable, /tf volatile and /tf_static transient local (tf2_ros's QoS): a mount sent once
    before the listener existed still arrives, the odometry after it, and a broken transform
    is skipped and counted."""
    from rclpy.qos import DurabilityPolicy, ReliabilityPolicy
    from ros_helpers import Probe

    _send(tf_sender, "/tf_static", [ros_transform("base_link", "velo", 0, (0.0, 0.0, 1.0))], static=True)
    listening = Probe(int(tf_sender.context.get_domain_id()), "tf_listener")
    buffer = TransformBuffer()
    listener = TransformListener(listening.node, buffer)
    try:
        def offered(topic: str):
            return [info.qos_profile for info in tf_sender.node.get_subscriptions_info_by_topic(topic)
                    if info.node_name == "tf_listener"]

        assert tf_sender.spin_until(lambda: offered("/tf") and offered("/tf_static"), 20)
        for topic, durability in (("/tf", DurabilityPolicy.VOLATILE), ("/tf_static", DurabilityPolicy.TRANSIENT_LOCAL)):
            [qos] = offered(topic)
            assert qos.reliability == ReliabilityPolicy.RELIABLE and qos.durability == durability, (topic, qos)
        _send(tf_sender, "/tf", [ros_transform("odom", "base_link", NS_PER_S, (1.0, 0.0, 0.0)),
                                 ros_transform("odom", "broken", NS_PER_S, quaternion=(0.0, 0.0, 0.0, 0.0))])
        assert listening.spin_until(lambda: buffer.can_transform("odom", "velo", NS_PER_S)[0] and listener.skipped, 20)
        np.testing.assert_allclose(buffer.lookup("odom", "velo")[:3, 3], [1.0, 0.0, 1.0])
        assert listener.skipped == 1
        assert buffer.can_transform("odom", "velo", 2 * NS_PER_S)[0] is False  # /tf records are not static
    finally:
        listener.destroy()
        listening.close()


def test_listener_without_tf2_msgs_says_what_is_missing(monkeypatch, tf_sender):
    monkeypatch.setitem(sys.modules, "tf2_msgs", None)
    monkeypatch.setitem(sys.modules, "tf2_msgs.msg", None)
    with pytest.raises(ImportError, match=r"needs tf2_msgs \(TFMessage\) for rclpy, which is not importable"):
        TransformListener(tf_sender.node, TransformBuffer())


def test_make_tf_lookup_takes_the_bounded_numpy_buffer_even_beside_tf2_ros_and_then_none(monkeypatch, tf_sender):
    """Where tf2_ros is importable (a stand-in here: a ROS 2 install has it) the node still reads TF
    into its own buffer, bounded by count as tf2's is not: a real listener, which TF sent over DDS
    fills; without tf2_msgs: none, and why."""
    from ros_helpers import Probe

    monkeypatch.setitem(sys.modules, "tf2_ros", types.ModuleType("tf2_ros"))  # never asked for anything
    listening = Probe(int(tf_sender.context.get_domain_id()), "tf_listener")
    try:
        lookup, backend = make_tf_lookup(listening.node, cache_seconds=2.0)
        assert isinstance(lookup, BufferLookup) and "TransformBuffer" in backend
        assert lookup.buffer.cache_ns == 2 * NS_PER_S
        _send(tf_sender, "/tf", [ros_transform("odom", "base_link", 5)])
        assert listening.spin_until(lambda: lookup.can_transform("odom", "base_link", 5)[0], 20)
        np.testing.assert_array_equal(lookup.lookup("odom", "base_link", 5), np.eye(4))
        assert lookup.can_transform("odom", "base_link", 6)[0] is False
        monkeypatch.setitem(sys.modules, "tf2_msgs", None)
        monkeypatch.setitem(sys.modules, "tf2_msgs.msg", None)
        nothing, why = make_tf_lookup(listening.node)
        assert nothing is None and "tf2_msgs" in why and "base_to_sensor" in why
    finally:
        listening.close()

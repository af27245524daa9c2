"""TF messages for tests without ROS: stand-ins with the fields of a geometry_msgs/TransformStamped."""

from types import SimpleNamespace

from convbki_ros.inputs.transforms import NS_PER_S


def transform_msg(parent, child, stamp_ns, translation=(0.0, 0.0, 0.0), quaternion=(0.0, 0.0, 0.0, 1.0)):
    """A tf2_msgs TransformStamped's fields, as SimpleNamespaces: what TransformBuffer.add_message reads."""
    sec, nanosec = divmod(stamp_ns, NS_PER_S)
    t = SimpleNamespace(x=translation[0], y=translation[1], z=translation[2])
    r = SimpleNamespace(x=quaternion[0], y=quaternion[1], z=quaternion[2], w=quaternion[3])
    return SimpleNamespace(header=SimpleNamespace(frame_id=parent, stamp=SimpleNamespace(sec=sec, nanosec=nanosec)),
                           child_frame_id=child, transform=SimpleNamespace(translation=t, rotation=r))

"""The numpy TF buffer: lookups through the tree, interpolation, errors, and properties of random
trees (its listener and the backend choice: test_tf_listener.py)."""

from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from tf_messages import transform_msg

from convbki_core.geometry.poses import (
    interpolate_pose,
    pose_from_translation_quaternion,
    pose_to_translation_quaternion,
)
from convbki_ros.inputs.tf_buffer import (
    MAX_FRAME_ID_LENGTH,
    MAX_FRAMES,
    MAX_GRAPH_DEPTH,
    MAX_RECORDS,
    MIN_RECORDS_PER_FRAME,
    ConnectivityError,
    ExtrapolationError,
    InvalidTransformError,
    TransformBuffer,
    TransformError,
    UnknownFrameError,
)
from convbki_ros.inputs.transforms import NS_PER_S


def rotation_pose(translation, axis, angle):
    axis = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    quaternion = np.append(axis * np.sin(angle / 2), np.cos(angle / 2))
    return pose_from_translation_quaternion(np.asarray(translation, np.float64), quaternion)


def yaw_pose(x, y, yaw):
    return rotation_pose([x, y, 0.0], [0.0, 0.0, 1.0], yaw)


def robot(buffer=None):
    """map -> odom -> base_link (both dynamic, 100..300 ns) -> velo (static mount)."""
    buffer = buffer or TransformBuffer()
    edges = {
        "odom": {100: yaw_pose(1.0, 0.0, 0.1), 300: yaw_pose(1.2, 0.4, 0.3)},
        "base_link": {100: yaw_pose(0.0, 0.0, 0.0), 300: yaw_pose(2.0, 4.0, 1.0)},
    }
    buffer.add("map", "odom", 100, edges["odom"][100])
    buffer.add("map", "odom", 300, edges["odom"][300])
    buffer.add("odom", "base_link", 100, edges["base_link"][100])
    buffer.add("odom", "base_link", 300, edges["base_link"][300])
    mount = rotation_pose([0.3, -0.1, 1.2], [1.0, 1.0, 0.0], 0.4)
    buffer.add("base_link", "velo", 0, mount, static=True)
    return buffer, edges, mount


# ----------------------------------------------------------------------------- one edge


def test_exact_stamp_returns_the_record():
    buffer = TransformBuffer()
    buffer.add("odom", "base_link", 100, yaw_pose(0.0, 0.0, 0.0))
    buffer.add("odom", "base_link", 300, yaw_pose(2.0, 4.0, 1.0))
    np.testing.assert_allclose(buffer.lookup("odom", "base_link", 300), yaw_pose(2.0, 4.0, 1.0), atol=1e-15)
    np.testing.assert_allclose(buffer.lookup("odom", "base_link", 100), np.eye(4), atol=1e-15)


def test_interpolation_half_way_lerps_translation_and_slerps_rotation():
    buffer = TransformBuffer()
    buffer.add("odom", "base_link", 100, yaw_pose(0.0, 0.0, 0.0))
    buffer.add("odom", "base_link", 300, yaw_pose(2.0, 4.0, 1.0))
    half = buffer.lookup("odom", "base_link", 200)
    np.testing.assert_allclose(half[:3, 3], [1.0, 2.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(half, yaw_pose(1.0, 2.0, 0.5), atol=1e-12)
    np.testing.assert_allclose(buffer.lookup("odom", "base_link", 150), yaw_pose(0.5, 1.0, 0.25), atol=1e-12)


def test_out_of_order_inserts_are_placed_in_order_and_a_repeated_stamp_replaces():
    buffer = TransformBuffer()
    buffer.add("odom", "base_link", 300, yaw_pose(9.0, 9.0, 0.0))
    buffer.add("odom", "base_link", 100, yaw_pose(0.0, 0.0, 0.0))
    buffer.add("odom", "base_link", 200, yaw_pose(2.0, 0.0, 0.0))
    # 150 lies between 100 and 200, not between 100 and 300.
    np.testing.assert_allclose(buffer.lookup("odom", "base_link", 150), yaw_pose(1.0, 0.0, 0.0), atol=1e-12)
    buffer.add("odom", "base_link", 200, yaw_pose(4.0, 0.0, 0.0))
    np.testing.assert_allclose(buffer.lookup("odom", "base_link", 150), yaw_pose(2.0, 0.0, 0.0), atol=1e-12)


def test_records_older_than_the_cache_behind_the_newest_are_forgotten():
    buffer = TransformBuffer(cache_seconds=1.0)
    for seconds in (0.0, 0.5, 1.5):
        buffer.add("odom", "base_link", int(seconds * NS_PER_S), yaw_pose(seconds, 0.0, 0.0))
    with pytest.raises(ExtrapolationError, match=r"known from 0\.500 s to 1\.500 s \(extrapolation into the past\)"):
        buffer.lookup("odom", "base_link", NS_PER_S // 4)
    np.testing.assert_allclose(buffer.lookup("odom", "base_link", NS_PER_S), yaw_pose(1.0, 0.0, 0.0), atol=1e-12)
    buffer.add("odom", "base_link", NS_PER_S // 10, yaw_pose(5.0, 0.0, 0.0))  # too old on arrival: dropped
    assert not buffer.can_transform("odom", "base_link", NS_PER_S // 10)[0]
    # Another edge keeps its own history: pruning is per edge.
    buffer.add("map", "odom", 0, np.eye(4))
    buffer.add("map", "odom", NS_PER_S // 2, np.eye(4))
    assert buffer.can_transform("map", "odom", NS_PER_S // 4) == (True, None)


def test_the_buffer_is_bounded_by_count_whatever_is_published(monkeypatch):
    """Records stamped a nanosecond apart stay within the cache's time but not its count: a frame
    keeps the newest MAX_RECORDS (its share once other frames come, never below
    MIN_RECORDS_PER_FRAME); frames beyond MAX_FRAMES and frame ids beyond MAX_FRAME_ID_LENGTH are
    refused, and the frames already known keep answering."""
    import convbki_ros.inputs.tf_buffer as tf_buffer

    monkeypatch.setattr(tf_buffer, "MAX_RECORDS", 1000)  # the bounds' logic at a tenth of the cost
    monkeypatch.setattr(tf_buffer, "MAX_FRAMES", 50)
    buffer = TransformBuffer(cache_seconds=60.0)
    for stamp in range(1, 1501):
        buffer.add("map", "flooded", stamp, yaw_pose(stamp * 1e-3, 0.0, 0.0))
    edge = buffer._edges["flooded"]
    assert len(edge.stamps) == 1000 and edge.stamps[0] == 501 and edge.stamps[-1] == 1500
    np.testing.assert_allclose(buffer.lookup("map", "flooded", 1500), yaw_pose(1.5, 0.0, 0.0), atol=1e-12)
    for number in range(49):
        buffer.add("map", f"frame_{number}", 1, np.eye(4))
    with pytest.raises(InvalidTransformError, match="50 frames are known already"):
        buffer.add("map", "one_too_many", 1, np.eye(4))
    buffer.add("map", "flooded", 1501, yaw_pose(1.501, 0.0, 0.0))  # its share is now 1000 // 50
    assert len(edge.stamps) == max(MIN_RECORDS_PER_FRAME, 1000 // 50) and edge.stamps[-1] == 1501
    with pytest.raises(InvalidTransformError, match=f"more than {MAX_FRAME_ID_LENGTH}"):
        buffer.add("map", "f" * (MAX_FRAME_ID_LENGTH + 1), 1, np.eye(4))
    for number in range(5000):  # re-parented each time: the names of parents no record holds are forgotten
        buffer.add(f"parent_{number}", "frame_0", 2 + number, np.eye(4))
    assert len(buffer.frames()) <= 2 * 50 + MIN_RECORDS_PER_FRAME
    assert (MAX_FRAMES, MAX_RECORDS) == (1000, 100_000)  # what the node runs with


def test_extrapolation_into_the_past_and_the_future_is_refused_with_the_known_span():
    buffer = TransformBuffer()
    buffer.add("odom", "base_link", 12_500_000_000, np.eye(4))
    buffer.add("odom", "base_link", 20_000_000_000, np.eye(4))
    with pytest.raises(ExtrapolationError) as past:
        buffer.lookup("odom", "base_link", 12_300_000_000)
    assert str(past.value) == ("no transform 'odom' -> 'base_link' at 12.300 s: it is known from 12.500 s to "
                               "20.000 s (extrapolation into the past)")
    with pytest.raises(ExtrapolationError) as future:
        buffer.lookup("base_link", "odom", 20_000_000_001)  # either direction needs the same edge
    assert str(future.value) == ("no transform 'odom' -> 'base_link' at 20.000000001 s: it is known from 12.500 s "
                                 "to 20.000 s (extrapolation into the future)")
    assert isinstance(future.value, TransformError) and isinstance(future.value, LookupError)
    single = TransformBuffer()
    single.add("odom", "base_link", 12_500_000_000, np.eye(4))
    with pytest.raises(ExtrapolationError, match=r"it is known only at 12\.500 s"):
        single.lookup("odom", "base_link", 13_000_000_000)


# ----------------------------------------------------------------------------- chains


def test_chain_through_a_static_mount_is_the_product_of_its_edges():
    buffer, edges, mount = robot()
    expected = edges["odom"][300] @ edges["base_link"][300] @ mount
    np.testing.assert_allclose(buffer.lookup("map", "velo", 300), expected, atol=1e-12)
    middle = (interpolate_pose(edges["odom"][100], edges["odom"][300], 0.25)
              @ interpolate_pose(edges["base_link"][100], edges["base_link"][300], 0.25) @ mount)
    np.testing.assert_allclose(buffer.lookup("map", "velo", 150), middle, atol=1e-12)


def test_inverse_direction_with_the_source_above_the_target():
    buffer, edges, mount = robot()
    forward = edges["odom"][300] @ edges["base_link"][300] @ mount
    np.testing.assert_allclose(buffer.lookup("velo", "map", 300), np.linalg.inv(forward), atol=1e-12)
    np.testing.assert_allclose(buffer.lookup("velo", "map", 300) @ buffer.lookup("map", "velo", 300), np.eye(4),
                               atol=1e-12)


def test_siblings_meet_at_their_common_ancestor_and_only_that_path_counts():
    buffer, _, mount = robot()
    camera = rotation_pose([0.5, 0.0, 0.8], [0.0, 1.0, 0.0], -0.2)
    buffer.add("base_link", "camera", 0, camera, static=True)
    expected = np.linalg.inv(camera) @ mount
    # 5000 ns is outside map -> odom -> base_link's records: edges above base_link are not needed.
    np.testing.assert_allclose(buffer.lookup("camera", "velo", 5000), expected, atol=1e-12)
    with pytest.raises(ExtrapolationError):
        buffer.lookup("odom", "velo", 5000)


def test_latest_common_time_is_the_oldest_newest_stamp_on_the_path():
    buffer, _, mount = robot()
    buffer.add("map", "odom", 500, yaw_pose(3.0, 3.0, 0.5))  # map -> odom now reaches 500, odom -> base_link 300
    assert buffer.latest_stamp("map", "velo") == 300  # the static mount does not hold it back
    assert buffer.latest_stamp("map", "odom") == 500
    at_300 = buffer.lookup("map", "velo", 300)
    np.testing.assert_allclose(buffer.lookup("map", "velo"), at_300, atol=1e-15)
    np.testing.assert_allclose(buffer.lookup("map", "velo", 0), at_300, atol=1e-15)  # tf2's Time()
    np.testing.assert_allclose(buffer.lookup("map", "odom"), yaw_pose(3.0, 3.0, 0.5), atol=1e-12)
    assert buffer.latest_stamp("base_link", "velo") is None  # static only: any time
    np.testing.assert_allclose(buffer.lookup("base_link", "velo"), mount, atol=1e-15)


def test_latest_common_time_outside_another_edges_records_is_an_error():
    buffer = TransformBuffer()
    buffer.add("map", "odom", 100, np.eye(4))
    buffer.add("map", "odom", 200, np.eye(4))
    buffer.add("odom", "base_link", 150_000, np.eye(4))  # known only long after map -> odom ends
    with pytest.raises(ExtrapolationError, match=r"'odom' -> 'base_link' at 0\.000000200 s"):
        buffer.lookup("map", "base_link")


def test_a_child_may_change_parent_and_the_latest_parent_wins_from_its_first_stamp():
    buffer = TransformBuffer()
    buffer.add("world", "odom", 0, yaw_pose(10.0, 0.0, 0.0), static=True)
    buffer.add("world", "odom2", 0, yaw_pose(-10.0, 0.0, 0.0), static=True)
    buffer.add("odom", "base_link", 100, yaw_pose(1.0, 0.0, 0.0))
    buffer.add("odom", "base_link", 200, yaw_pose(3.0, 0.0, 0.0))
    buffer.add("odom2", "base_link", 300, yaw_pose(5.0, 0.0, 0.0))
    buffer.add("odom2", "base_link", 400, yaw_pose(7.0, 0.0, 0.0))
    np.testing.assert_allclose(buffer.lookup("world", "base_link", 150)[:3, 3], [12.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(buffer.lookup("world", "base_link", 350)[:3, 3], [-4.0, 0.0, 0.0], atol=1e-12)
    # Between the parents: the record under odom (200) is held, not blended with one under odom2.
    np.testing.assert_allclose(buffer.lookup("world", "base_link", 250)[:3, 3], [13.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(buffer.lookup("world", "base_link")[:3, 3], [-3.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(buffer.lookup("odom2", "base_link", 350)[:3, 3], [6.0, 0.0, 0.0], atol=1e-12)


def test_a_static_transform_replaces_the_previous_one_and_the_last_kind_added_wins():
    buffer = TransformBuffer()
    buffer.add("base_link", "velo", 0, yaw_pose(1.0, 0.0, 0.0), static=True)
    buffer.add("base_link", "velo", 0, yaw_pose(2.0, 0.0, 0.0), static=True)
    np.testing.assert_allclose(buffer.lookup("base_link", "velo", 123)[:3, 3], [2.0, 0.0, 0.0], atol=1e-15)
    buffer.add("base_footprint", "velo", 0, yaw_pose(3.0, 0.0, 0.0), static=True)  # re-mounted elsewhere
    with pytest.raises(ConnectivityError):
        buffer.lookup("base_link", "velo")
    buffer.add("base_footprint", "velo", 500, yaw_pose(4.0, 0.0, 0.0))  # now dynamic: the static is gone
    with pytest.raises(ExtrapolationError):
        buffer.lookup("base_footprint", "velo", 123)
    buffer.add("base_footprint", "velo", 0, yaw_pose(5.0, 0.0, 0.0), static=True)  # and back: the record is gone
    np.testing.assert_allclose(buffer.lookup("base_footprint", "velo", 500)[:3, 3], [5.0, 0.0, 0.0], atol=1e-15)


# ----------------------------------------------------------------------------- errors


def test_unknown_frames_disconnected_trees_and_the_same_frame():
    buffer, _, _ = robot()
    with pytest.raises(UnknownFrameError) as unknown:
        buffer.lookup("map", "lidar", 200)
    assert str(unknown.value) == "frame 'lidar' is unknown"
    buffer.add("world", "rover", 0, np.eye(4), static=True)
    with pytest.raises(ConnectivityError) as apart:
        buffer.lookup("velo", "rover", 200)
    assert str(apart.value) == "'velo' and 'rover' are not connected (trees rooted at 'map' and 'world')"
    assert buffer.can_transform("velo", "rover") == (False, str(apart.value))
    assert buffer.can_transform("map", "velo", 200) == (True, None)
    np.testing.assert_array_equal(buffer.lookup("velo", "velo", 99_999), np.eye(4))
    with pytest.raises(UnknownFrameError):
        buffer.lookup("lidar", "lidar")
    with pytest.raises(UnknownFrameError):
        buffer.latest_stamp("map", "lidar")
    assert buffer.frames() == ["base_link", "map", "odom", "rover", "velo", "world"]


def test_a_loop_is_reported_not_walked_for_ever():
    buffer = TransformBuffer()
    buffer.add("a", "b", 0, np.eye(4), static=True)
    buffer.add("b", "c", 0, np.eye(4), static=True)
    buffer.add("c", "a", 0, np.eye(4), static=True)
    buffer.add("c", "d", 0, np.eye(4), static=True)
    with pytest.raises(ConnectivityError) as loop:
        buffer.lookup("a", "d")
    assert "form a loop" in str(loop.value) and "'c' -> 'b' -> 'a' -> 'c'" in str(loop.value)


def test_a_chain_deeper_than_the_graph_limit_is_refused():
    buffer = TransformBuffer()
    for depth in range(MAX_GRAPH_DEPTH + 1):
        buffer.add(f"f{depth}", f"f{depth + 1}", 0, np.eye(4), static=True)
    with pytest.raises(ConnectivityError, match=f"more than {MAX_GRAPH_DEPTH} frames above 'f{MAX_GRAPH_DEPTH + 1}'"):
        buffer.lookup("f0", f"f{MAX_GRAPH_DEPTH + 1}")
    np.testing.assert_allclose(buffer.lookup("f0", f"f{MAX_GRAPH_DEPTH}"), np.eye(4))  # 100 parents still walk


def test_add_refuses_bad_frames_and_poses():
    buffer = TransformBuffer()
    with pytest.raises(InvalidTransformError, match="same frame on both ends"):
        buffer.add("/odom", "odom", 0, np.eye(4))
    with pytest.raises(InvalidTransformError, match="child frame id is empty"):
        buffer.add("odom", "/", 0, np.eye(4))
    with pytest.raises(InvalidTransformError, match="not a rigid transform"):
        buffer.add("odom", "base_link", 0, np.diag([2.0, 1.0, 1.0, 1.0]))
    with pytest.raises(InvalidTransformError, match="not a rigid transform"):
        buffer.add("odom", "base_link", 0, np.diag([-1.0, 1.0, 1.0, 1.0]))  # a reflection
    with pytest.raises(InvalidTransformError, match="not finite"):
        buffer.add("odom", "base_link", 0, np.full((4, 4), np.nan))
    with pytest.raises(InvalidTransformError, match="must be 4x4"):
        buffer.add("odom", "base_link", 0, np.eye(3))
    with pytest.raises(ValueError):
        TransformBuffer(cache_seconds=0.0)
    assert buffer.frames() == []


def test_add_message_strips_slashes_skips_bad_transforms_and_keeps_the_rest():
    buffer = TransformBuffer()
    message = SimpleNamespace(transforms=[
        transform_msg("/odom", "/base_link", 2 * NS_PER_S, (1.0, 2.0, 3.0)),
        transform_msg("odom", "base_link", 3 * NS_PER_S, (2.0, 2.0, 3.0), (0.0, 0.0, np.sin(0.5), np.cos(0.5))),
        transform_msg("odom", "bad_zero", NS_PER_S, quaternion=(0.0, 0.0, 0.0, 0.0)),
        transform_msg("odom", "bad_nan", NS_PER_S, quaternion=(np.nan, 0.0, 0.0, 1.0)),
        transform_msg("odom", "bad_position", NS_PER_S, translation=(np.inf, 0.0, 0.0)),
        transform_msg("", "bad_empty", NS_PER_S),
        transform_msg("odom", "/odom", NS_PER_S),
    ])
    skipped = buffer.add_message(message)
    assert len(skipped) == 5
    assert skipped[0].startswith("transform 'odom' -> 'bad_zero': ") and "norm 0" in skipped[0]
    assert skipped[1].startswith("transform 'odom' -> 'bad_nan': ") and "not finite" in skipped[1]
    assert skipped[2].startswith("transform 'odom' -> 'bad_position': position")
    assert skipped[3] == "transform '' -> 'bad_empty': the parent frame id is empty"
    assert skipped[4] == "transform 'odom' -> 'odom' has the same frame on both ends"
    assert buffer.frames() == ["base_link", "odom"]
    half = buffer.lookup("odom", "base_link", 2 * NS_PER_S + NS_PER_S // 2)
    np.testing.assert_allclose(half, rotation_pose([1.5, 2.0, 3.0], [0.0, 0.0, 1.0], 0.5), atol=1e-12)
    static = SimpleNamespace(transforms=[transform_msg("base_link", "velo", 0, (0.0, 0.0, 1.5))])
    assert buffer.add_message(static, static=True) == []
    np.testing.assert_allclose(buffer.lookup("base_link", "velo", 7 * NS_PER_S)[:3, 3], [0.0, 0.0, 1.5])


# ----------------------------------------------------------------------------- properties


def random_pose(draw):
    translation = draw(st.lists(st.floats(-5.0, 5.0), min_size=3, max_size=3))
    axis = draw(st.lists(st.floats(-1.0, 1.0), min_size=3, max_size=3).filter(lambda v: np.linalg.norm(v) > 0.1))
    return rotation_pose(translation, axis, draw(st.floats(-3.0, 3.0)))


@st.composite
def random_tree(draw):
    """Frames f0..fn, each fi (i > 0) a child of some fj, j < i; edges static or known at 1000 and 2000 ns."""
    count = draw(st.integers(2, 7))
    edges = {}
    for child in range(1, count):
        parent = draw(st.integers(0, child - 1))
        static = draw(st.booleans())
        edges[child] = (parent, static, random_pose(draw), random_pose(draw))
    return edges


def fill(edges):
    buffer = TransformBuffer()
    for child, (parent, static, first, last) in edges.items():
        if static:
            buffer.add(f"f{parent}", f"f{child}", 0, first, static=True)
        else:
            buffer.add(f"f{parent}", f"f{child}", 1000, first)
            buffer.add(f"f{parent}", f"f{child}", 2000, last)
    return buffer


def root_from(edges, frame, stamp):
    """f0 <- frame at ``stamp``, composed here from the edges directly."""
    pose = np.eye(4)
    while frame:
        parent, static, first, last = edges[frame]
        pose = (first if static else interpolate_pose(first, last, (stamp - 1000) / 1000)) @ pose
        frame = parent
    return pose


@given(random_tree(), st.data(), st.integers(1000, 2000))  # not 0: that is 'latest'
def test_lookups_there_and_back_are_the_identity_and_match_the_composed_tree(edges, data, stamp):
    buffer = fill(edges)
    count = len(edges) + 1
    a = data.draw(st.integers(0, count - 1))
    b = data.draw(st.integers(0, count - 1))
    there = buffer.lookup(f"f{a}", f"f{b}", stamp)
    back = buffer.lookup(f"f{b}", f"f{a}", stamp)
    np.testing.assert_allclose(there @ back, np.eye(4), atol=1e-9)
    expected = np.linalg.inv(root_from(edges, a, stamp)) @ root_from(edges, b, stamp)
    np.testing.assert_allclose(there, expected, atol=1e-9)


@given(st.lists(st.tuples(st.booleans(), st.integers(0, 10**6)), min_size=1, max_size=8), st.data())
def test_a_random_chain_is_the_product_of_its_edges(links, data):
    buffer = TransformBuffer()
    product = np.eye(4)
    stamp = 5 * NS_PER_S
    for index, (static, offset) in enumerate(links):
        pose = random_pose(data.draw)
        if static:
            buffer.add(f"c{index}", f"c{index + 1}", 0, pose, static=True)
        else:  # records on both sides of the stamp, the pose exact at it: interpolation is tested elsewhere
            later = random_pose(data.draw)
            buffer.add(f"c{index}", f"c{index + 1}", stamp - offset, pose)
            buffer.add(f"c{index}", f"c{index + 1}", stamp + 10**6 + 1, later)
            pose = interpolate_pose(pose, later, offset / (offset + 10**6 + 1))
        product = product @ pose
    np.testing.assert_allclose(buffer.lookup("c0", f"c{len(links)}", stamp), product, atol=1e-9)
    _, quaternion = pose_to_translation_quaternion(buffer.lookup("c0", f"c{len(links)}", stamp))
    assert abs(np.linalg.norm(quaternion) - 1.0) < 1e-12

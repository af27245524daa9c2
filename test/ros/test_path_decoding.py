"""nav_msgs/Path read straight from its CDR bytes (convbki_ros.inputs.path_decoding).

Every message is written by rclpy's own serializer (``serialize_message``: Fast CDR, what the
node's raw subscription receives) and the decoded fields are compared with the message's;
big-endian copies come from rosbags' CDR writer, an independent implementation. Whatever the
bytes, the decoder returns a DecodedPath or raises PathError, never another exception, and
when it accepts damaged bytes it reads exactly what rclpy's deserializer reads from them.
"""

from __future__ import annotations

import dataclasses
import functools
import struct
import tracemalloc
from unittest import mock

import numpy as np
import pytest
from builtin_interfaces.msg import Time
from geometry_msgs.msg import PoseStamped
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from nav_msgs.msg import Path
from rclpy.serialization import deserialize_message, serialize_message
from std_msgs.msg import Header

from convbki_ros.inputs import path_decoding
from convbki_ros.inputs.path_decoding import (
    MAX_FRAME_ID_BYTES,
    DecodedPath,
    PathError,
    decode_path,
    path_pose_count,
)

NS = 1_000_000_000


def fuzz(examples: int) -> settings:
    """The loaded profile (derandomised in CI) with this many examples and no deadline."""
    return settings(max_examples=examples, deadline=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


def pose_stamped(sec: int, nanosec: int, frame_id: str, values) -> PoseStamped:
    """A PoseStamped; ``values`` are position x y z then orientation x y z w (floats)."""
    msg = PoseStamped()
    msg.header.stamp.sec, msg.header.stamp.nanosec, msg.header.frame_id = sec, nanosec, frame_id
    position, orientation = msg.pose.position, msg.pose.orientation
    position.x, position.y, position.z = values[0], values[1], values[2]
    orientation.x, orientation.y, orientation.z, orientation.w = values[3], values[4], values[5], values[6]
    return msg


def path_message(frame_id: str, sec: int, nanosec: int, poses: list[PoseStamped]) -> Path:
    return Path(header=Header(stamp=Time(sec=sec, nanosec=nanosec), frame_id=frame_id), poses=poses)


def simple_path(frames: list[str], frame_id: str = "map") -> Path:
    """A Path with one pose per frame id, distinct stamps and values."""
    return path_message(frame_id, 17, 5, [pose_stamped(i, 3 * i, frame, [i + 0.5, -float(i), 2.0 * i, 0, 0, 0, 1.0])
                                          for i, frame in enumerate(frames)])


@functools.cache
def rosbags_store():
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


def big_endian(raw: bytes) -> bytes:
    """The same Path in big-endian CDR (encapsulation 00 00), written by rosbags."""
    store = rosbags_store()
    return bytes(store.serialize_cdr(store.deserialize_cdr(raw, "nav_msgs/msg/Path"), "nav_msgs/msg/Path",
                                     little_endian=False))


def assert_matches(decoded: DecodedPath, msg: Path) -> None:
    """Every field of ``decoded`` equals ``msg``'s; floats bit for bit (NaN payloads, -0.0)."""
    assert decoded.frame_id == msg.header.frame_id
    assert decoded.stamp_ns == msg.header.stamp.sec * NS + msg.header.stamp.nanosec
    count = len(msg.poses)
    assert len(decoded) == count
    stamps = np.array([p.header.stamp.sec * NS + p.header.stamp.nanosec for p in msg.poses], np.int64)
    assert decoded.stamps_ns.dtype == np.int64 and np.array_equal(decoded.stamps_ns, stamps)
    values = np.array([[p.pose.position.x, p.pose.position.y, p.pose.position.z, p.pose.orientation.x,
                        p.pose.orientation.y, p.pose.orientation.z, p.pose.orientation.w] for p in msg.poses],
                      np.float64).reshape(count, 7)
    assert decoded.positions.shape == (count, 3) and decoded.positions.dtype == np.float64
    assert decoded.orientations.shape == (count, 4) and decoded.orientations.dtype == np.float64
    assert decoded.positions.tobytes() == values[:, :3].tobytes()
    assert decoded.orientations.tobytes() == values[:, 3:].tobytes()
    frames = tuple(p.header.frame_id for p in msg.poses)
    assert decoded.frame_ids == frames
    assert decoded.frame_names == tuple(dict.fromkeys(frames))  # distinct, first seen first
    assert decoded.frame_index.dtype == np.int32


def assert_same(a: DecodedPath, b: DecodedPath) -> None:
    assert (a.frame_id, a.stamp_ns, a.frame_names) == (b.frame_id, b.stamp_ns, b.frame_names)
    for name in ("stamps_ns", "positions", "orientations", "frame_index"):
        assert getattr(a, name).dtype == getattr(b, name).dtype
        assert getattr(a, name).tobytes() == getattr(b, name).tobytes(), name


# ----------------------------------------------------------------------------- round trips

# Frame ids as rclpy can send them: any text but surrogates, and no NUL (rclpy's C string stops there).
any_text = st.text(st.characters(exclude_categories=("Cs",), exclude_characters="\0"), max_size=12)
frame_ids = st.one_of(st.sampled_from(["", "map", "odom", "größe", "地図", "🗺", "x" * MAX_FRAME_ID_BYTES]), any_text)
poses_values = st.lists(st.floats(width=64), min_size=7, max_size=7)  # NaN and inf included
seconds = st.integers(-2**31, 2**31 - 1)
nanoseconds = st.one_of(st.integers(0, NS - 1), st.integers(0, 2**32 - 1))


@st.composite
def paths(draw) -> Path:
    """Paths of 0..50 poses: one frame id for all, ids of one length (the strided layout), or any."""
    count = draw(st.integers(0, 50))
    kind = draw(st.sampled_from(["one", "one", "same length", "any"]))
    if kind == "one":
        frames = [draw(frame_ids)] * count
    elif kind == "same length":
        size = draw(st.integers(0, 6))
        frames = draw(st.lists(st.text("mapo", min_size=size, max_size=size), min_size=count, max_size=count))
    else:
        frames = draw(st.lists(frame_ids, min_size=count, max_size=count))
    poses = [pose_stamped(draw(seconds), draw(nanoseconds), frame, draw(poses_values)) for frame in frames]
    return path_message(draw(frame_ids), draw(seconds), draw(nanoseconds), poses)


@fuzz(40)
@given(paths(), st.sampled_from([bytes, bytearray, memoryview]))
def test_round_trip_against_rclpy(msg: Path, container) -> None:
    """Each field as rclpy serialised it; the per-pose loop and big-endian CDR read the same."""
    raw = serialize_message(msg)
    assert path_pose_count(container(raw)) == len(msg.poses)
    decoded = decode_path(container(raw), max_poses=50)
    assert_matches(decoded, msg)
    with mock.patch.object(path_decoding, "_uniform", return_value=False):  # every pose through the loop
        assert_same(decode_path(raw, max_poses=50), decoded)
    swapped = big_endian(raw)
    assert swapped[:2] == b"\x00\x00" and path_pose_count(swapped) == len(msg.poses)
    assert_same(decode_path(swapped, max_poses=50), decoded)
    assert_same(decode_path(raw + bytes(8), max_poses=50), decoded)  # bytes after the last pose: ignored


def test_first_pose_outside_and_frame_table() -> None:
    decoded = decode_path(serialize_message(simple_path(["map", "", "map", "odom", "x", "odom"])), 10)
    assert decoded.frame_names == ("map", "", "odom", "x")
    assert decoded.frame_index.tolist() == [0, 1, 0, 2, 3, 2]
    assert decoded.first_pose_outside({"", "map"}) == 3
    assert decoded.first_pose_outside(["", "map", "odom"]) == 4
    assert decoded.first_pose_outside({"", "map", "odom", "x"}) is None
    empty = decode_path(serialize_message(simple_path([])), 0)
    assert len(empty) == 0 and empty.frame_names == () and empty.first_pose_outside(()) is None
    assert empty.positions.shape == (0, 3) and empty.orientations.shape == (0, 4)
    with pytest.raises(dataclasses.FrozenInstanceError):
        decoded.frame_id = "odom"


def test_frame_id_quirks_read_as_rclpy_reads_them() -> None:
    """A frame id cut by a NUL (rclpy keeps what is before it) and a length-0 string (read as "")."""
    raw = bytearray(serialize_message(simple_path(["mxp", "mxp", "abc"], frame_id="mxp")))
    raw[raw.find(b"mxp") + 1] = 0  # the Path's
    raw[raw.rfind(b"mxp") + 1] = 0  # pose 1's
    decoded = decode_path(bytes(raw), 3)
    assert_matches(decoded, deserialize_message(bytes(raw), Path))
    assert decoded.frame_id == "m" and decoded.frame_ids == ("mxp", "m", "abc")
    empty_string = b"\x00\x01\x00\x00" + struct.pack("<iII", 4, 5, 0) + struct.pack("<I", 0)
    assert_matches(decode_path(empty_string, 0), deserialize_message(empty_string, Path))


# ----------------------------------------------------------------------------- refusals


def test_count_is_read_without_parsing_the_poses() -> None:
    """A huge declared count is refused from the header alone, before anything is allocated for it."""
    head = serialize_message(simple_path([]))  # ends right after the count
    raw = head[:-4] + struct.pack("<I", 300_000)
    assert path_pose_count(raw) == 300_000
    with pytest.raises(PathError, match=r"declares 300000 poses, over the cap of 100000"):
        decode_path(raw, max_poses=100_000)
    with pytest.raises(PathError, match=r"declares 300000 poses but only 0 bytes follow"):
        decode_path(raw, max_poses=10**6)
    # 2^31 poses declared on a 20-byte message, or with a few real poses' worth of bytes after it.
    tiny = b"\x00\x01\x00\x00" + struct.pack("<iII", 0, 0, 0) + struct.pack("<I", 2**31)
    full = serialize_message(simple_path(["map"] * 3, frame_id=""))
    count_at = 4 + 8 + 4 + 4  # "" is length 1 + NUL, padded to 4
    assert path_pose_count(full) == 3
    lying = full[:count_at] + struct.pack("<I", 2**31) + full[count_at + 4:]
    tracemalloc.start()
    try:
        for message in (tiny, lying):
            assert path_pose_count(message) == 2**31
            with pytest.raises(PathError, match=r"declares 2147483648 poses but only \d+ bytes follow"):
                decode_path(message, max_poses=2**32)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 64 * 1024


@pytest.mark.parametrize(("raw", "problem"), [
    (b"", "too short for a CDR encapsulation header"),
    (b"\x00\x01\x00", "too short for a CDR encapsulation header"),
    (b"\x00\x07\x00\x00" + bytes(16), "unknown encapsulation 0007"),
    (b"\x01\x00\x00\x00" + bytes(16), "unknown encapsulation 0100"),
    (b"\x00\x01\x00\x00" + bytes(11), "too short for a Path header"),
    (b"\x00\x01\x00\x00" + struct.pack("<iII", 0, 0, 5) + b"map\x00", "runs past the end"),
    (b"\x00\x00\x00\x00" + struct.pack(">iII", 0, 0, 5) + b"map\x00", "runs past the end"),
    (b"\x00\x01\x00\x00" + struct.pack("<iII", 0, 0, 2**32 - 1) + b"map\x00", "over the cap of 256"),
    (b"\x00\x01\x00\x00" + struct.pack("<iII", 0, 0, 4) + b"map\x00\x00\x00", "ends before its pose count"),
])
def test_unreadable_headers(raw: bytes, problem: str) -> None:
    for read in (path_pose_count, lambda message: decode_path(message, 10)):
        with pytest.raises(PathError, match=problem):
            read(raw)


@pytest.mark.parametrize(("frames", "targets", "where"), [
    (["abc"] * 3, [0], "the Path's"),
    (["abc"] * 3, [1], "pose 0's"),
    (["", "abc", "abc"], [2, 3], "pose 1's"),  # the strided read, one id for poses 1..
    (["abc", "abc", "abc", "xyz"], [4], "pose 3's"),  # the strided read, ids of one length
    (["abc", "", "abc", "xyz"], [4], "pose 3's"),  # the per-pose loop
])
@pytest.mark.parametrize("damage", ["utf-8", "nul"])
def test_bad_frame_ids(frames: list[str], targets: list[int], where: str, damage: str) -> None:
    raw = serialize_message(simple_path(frames, frame_id="abc"))
    strings = ["abc", *frames]  # as they lie in the bytes: the Path's, then each pose's
    damaged = bytearray(raw)
    for target in targets:
        at = -1
        for _ in range(strings[:target + 1].count(strings[target])):
            at = raw.index(strings[target].encode(), at + 1)
        if damage == "utf-8":
            damaged[at:at + 3] = b"\xff\xfe\xfd"
        else:
            damaged[at + 3] = ord("!")  # the NUL
    problem = "not valid UTF-8" if damage == "utf-8" else "not NUL-terminated"
    with pytest.raises(PathError, match=f"{where} frame id is {problem}"):
        decode_path(bytes(damaged), 10)


@pytest.mark.parametrize("frames", [["ok"] * 3, ["", "ok", "ok"], ["ok", "", "ok"]])
def test_frame_id_cap(frames: list[str]) -> None:
    longest = "é" * (MAX_FRAME_ID_BYTES // 2)  # 256 bytes of UTF-8
    decoded = decode_path(serialize_message(simple_path([longest if f else f for f in frames], longest)), 3)
    assert decoded.frame_id == longest and longest in decoded.frame_names
    with pytest.raises(PathError, match=r"the Path's frame id is 258 bytes long .*over the cap of 256"):
        decode_path(serialize_message(simple_path(frames, longest + "x")), 3)
    first = next(i for i, frame in enumerate(frames) if frame)
    with pytest.raises(PathError, match=f"pose {first}'s frame id is 258 bytes long"):
        decode_path(serialize_message(simple_path([longest + "x" if f else f for f in frames])), 3)


# ----------------------------------------------------------------------------- damaged bytes

SAMPLES = [serialize_message(simple_path(frames, frame_id)) for frames, frame_id in [
    ([], "map"), (["map"] * 4, "map"), (["", "map", "odom", "map"], ""), (["ab", "cd", "ab"], "地図"), (["x"], "")]]
SAMPLES += [big_endian(raw) for raw in SAMPLES[1:3]]


def test_every_truncation_is_refused() -> None:
    for raw in SAMPLES:
        assert decode_path(raw, 10).stamp_ns == 17 * NS + 5
        for cut in range(len(raw)):
            with pytest.raises(PathError):
                decode_path(raw[:cut], 10)


def well_formed(decoded: DecodedPath) -> None:
    count = len(decoded)
    assert decoded.stamps_ns.shape == (count,) and decoded.positions.shape == (count, 3)
    assert decoded.orientations.shape == (count, 4) and decoded.frame_index.shape == (count,)
    assert all(len(name.encode()) <= MAX_FRAME_ID_BYTES for name in (decoded.frame_id, *decoded.frame_names))
    assert set(decoded.frame_index.tolist()) == set(range(len(decoded.frame_names)))


@st.composite
def plausible_bytes(draw) -> bytes:
    """A little-endian Path header with a short frame id and a small count, then random bytes."""
    frame = draw(st.binary(max_size=6))
    head = b"\x00\x01\x00\x00" + draw(st.binary(min_size=8, max_size=8)) + struct.pack("<I", len(frame)) + frame
    head += bytes(-len(head) % 4) + struct.pack("<I", draw(st.integers(0, 3)))
    return head + draw(st.binary(max_size=400))


@fuzz(200)
@given(st.one_of(st.binary(max_size=400), st.binary(max_size=400).map(lambda tail: b"\x00\x01\x00\x00" + tail),
                 plausible_bytes()))
def test_random_bytes_raise_only_path_error(raw: bytes) -> None:
    try:
        decoded = decode_path(raw, 10)
    except PathError:
        return
    well_formed(decoded)


@fuzz(200)
@given(st.sampled_from(SAMPLES), st.lists(st.tuples(st.integers(0, 10**6), st.integers(0, 255)), min_size=1,
                                          max_size=4))
def test_flipped_bytes_raise_path_error_or_read_as_rclpy(raw: bytes, flips) -> None:
    """Damaged bytes either are refused or read exactly as rclpy's deserializer reads them."""
    damaged = bytearray(raw)
    for at, value in flips:
        damaged[at % len(damaged)] = value
    damaged = bytes(damaged)
    try:
        decoded = decode_path(damaged, 10)
    except PathError:
        return
    well_formed(decoded)
    if damaged[:2] == b"\x00\x01":  # rclpy reads little-endian messages only
        assert_matches(decoded, deserialize_message(damaged, Path))


# ----------------------------------------------------------------------------- size


def test_100000_poses() -> None:
    """A LIO-SAM-sized Path and then some, from rclpy's serializer, with one frame id (the strided
    read) gives every value back; with a few poses in other frames (the per-pose loop), the same."""
    count, distinct = 100_000, 10_000  # rclpy takes ~10 us per PoseStamped: 10,000 objects, each 10 times
    rng = np.random.default_rng(7)
    values = rng.normal(size=(distinct, 7))
    values[::1000, 2] = np.nan
    secs = rng.integers(-2**31, 2**31, distinct)
    nanosecs = rng.integers(0, NS, distinct)
    poses = [pose_stamped(sec, nanosec, "map", row)
             for sec, nanosec, row in zip(secs.tolist(), nanosecs.tolist(), values.tolist())]
    uniform = decode_path(serialize_message(path_message("map", 1_700_000_000, 5, poses * 10)), count)
    assert uniform.frame_id == "map" and uniform.stamp_ns == 1_700_000_000 * NS + 5
    assert np.array_equal(uniform.stamps_ns, np.tile(secs * NS + nanosecs, 10))
    assert uniform.positions.tobytes() == np.tile(values[:, :3], (10, 1)).tobytes()
    assert uniform.orientations.tobytes() == np.tile(values[:, 3:], (10, 1)).tobytes()
    assert uniform.frame_names == ("map",) and uniform.first_pose_outside({"", "map"}) is None

    for pose in poses[5::7]:
        pose.header.frame_id = ""
    poses[7_777].header.frame_id = "odom"
    mixed = decode_path(serialize_message(path_message("map", 1_700_000_000, 5, poses)), count)
    assert mixed.frame_names == ("map", "", "odom") and mixed.first_pose_outside({"", "map"}) == 7_777
    assert np.array_equal(np.flatnonzero(mixed.frame_index == 1), np.arange(5, distinct, 7))
    assert np.flatnonzero(mixed.frame_index == 2).tolist() == [7_777]
    for name in ("stamps_ns", "positions", "orientations"):
        assert getattr(mixed, name).tobytes() == getattr(uniform, name)[:distinct].tobytes()

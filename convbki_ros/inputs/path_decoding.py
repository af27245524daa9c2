"""nav_msgs/Path -> numpy, read straight from the serialized CDR bytes.

Why raw bytes: ``pose_corrections`` is open to anyone on the ROS domain, and rclpy turns a
Path into one Python object per field before the callback sees it: a 300,000-pose Path holds
the executor for seconds, and even a normal SLAM path re-sent at 5 Hz costs Python-object
time. Subscribed with ``raw=True``, the callback gets the bytes instead; this module reads the
declared pose count first (``path_pose_count``: the header and one length field, O(1)) and
refuses a Path over the caller's cap, or one whose count cannot fit in its bytes, before
parsing or allocating anything for its poses.

The layout (plain CDR, XCDRv1, as Fast DDS writes these final types in Jazzy)::

    encapsulation  4 bytes: 00 01 = CDR little-endian, 00 00 = CDR big-endian (2 option bytes)
    Path.header    int32 sec, uint32 nanosec, string frame_id
    poses          uint32 count, then count x PoseStamped:
        header       int32 sec, uint32 nanosec, string frame_id
        pose         float64 x 7 (position x y z, orientation x y z w)

A string is a uint32 length counting its terminating NUL, the bytes, the NUL. Every primitive
is aligned to its own size (8 for float64) relative to the start of the body, i.e. offset 4
in the raw buffer; the padding's content is undefined (Fast DDS leaves it uninitialised).

Speed: a SLAM stamps every pose in one frame (all "map", or all ""), so every PoseStamped has
the same size. The decoder checks that (every length field at a fixed stride equals the first)
and then reads all stamps and poses through strided numpy views, with no per-pose Python;
only a Path whose frame ids differ in length goes through a per-pose loop (``struct``), and
both give identical results. Float values (NaN and inf included) pass through untouched: the
caller checks them. Imports no rclpy.
"""

from __future__ import annotations

import struct
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

MAX_FRAME_ID_BYTES = 256  # UTF-8 bytes, without the NUL; far beyond any real TF frame name

NS_PER_S = 1_000_000_000
ENCAPSULATION_BYTES = 4
# Encapsulation identifier -> struct / numpy byte order. XCDRv2 (00 06, 00 07) lays sequences
# of structs out differently (a DHEADER, 4-byte alignment of float64) and is refused.
_BYTE_ORDERS = {b"\x00\x00": ">", b"\x00\x01": "<"}
POSE_BYTES = 7 * 8  # geometry_msgs/Pose: Point (3 float64) + Quaternion (4 float64)
# The fewest bytes one PoseStamped can take: stamp (8) + string length (4) + pose (56), with an
# empty (length 0) frame id and no padding. A declared count times this must fit in what follows.
MIN_POSE_STAMPED_BYTES = 8 + 4 + POSE_BYTES


class PathError(ValueError):
    """A serialized Path that cannot be read; the message names the problem in one line."""


@dataclass(frozen=True, eq=False)
class DecodedPath:
    """The content of a nav_msgs/Path, K poses.

    ``stamp_ns`` and ``frame_id`` are the Path header's; ``stamps_ns`` (K,) int64 are the poses'
    header stamps (sec * 10**9 + nanosec, ns); ``positions`` (K, 3) float64 in metres and
    ``orientations`` (K, 4) float64 quaternions (x, y, z, w), as sent (not checked).

    Per-pose frame ids are stored once each: pose i's ``header.frame_id`` is
    ``frame_names[frame_index[i]]``; ``frame_names`` holds the distinct ids in order of first
    appearance (``()`` for an empty Path). ``first_pose_outside({"", "map"})`` answers "which
    pose, if any, is in another frame" without K Python strings; ``frame_ids`` builds them.
    """

    frame_id: str
    stamp_ns: int
    stamps_ns: np.ndarray  # (K,) int64, ns
    positions: np.ndarray  # (K, 3) float64, m
    orientations: np.ndarray  # (K, 4) float64, x y z w
    frame_names: tuple[str, ...]  # distinct pose frame ids, in order of first appearance
    frame_index: np.ndarray  # (K,) int32 into frame_names

    def __len__(self) -> int:
        return int(self.stamps_ns.shape[0])

    @property
    def frame_ids(self) -> tuple[str, ...]:
        """Every pose's header frame id, in pose order (K strings: for tests and small Paths)."""
        return tuple(self.frame_names[i] for i in self.frame_index.tolist())

    def first_pose_outside(self, allowed: Iterable[str]) -> int | None:
        """The index of the first pose whose frame id is not in ``allowed``; None when all are."""
        allowed = set(allowed)
        outside = [i for i, name in enumerate(self.frame_names) if name not in allowed]
        if not outside:
            return None
        return int(np.flatnonzero(np.isin(self.frame_index, outside))[0])


@dataclass(frozen=True)
class _Header:
    """Where the Path's parts lie in the raw buffer (absolute offsets)."""

    order: str  # "<" or ">"
    sec: int
    nanosec: int
    frame_at: int
    frame_length: int  # the string length field: bytes including the NUL (0 is read as "")
    count: int
    poses_at: int  # the first PoseStamped


def _byte_view(raw: bytes | bytearray | memoryview) -> memoryview:
    view = memoryview(raw)
    if view.ndim != 1 or view.itemsize != 1:
        try:
            view = view.cast("B")
        except TypeError as error:  # a non-contiguous buffer has no byte layout to read
            raise PathError(f"a Path must be contiguous bytes ({error})") from None
    return view


def _align(offset: int, size: int) -> int:
    """``offset`` (absolute) moved up to a multiple of ``size`` relative to the CDR body."""
    return offset + (-(offset - ENCAPSULATION_BYTES)) % size


def _string_length(length: int, at: int, size: int, what: str) -> None:
    """Refuses a string length field over the cap or running past the end of the buffer."""
    if length > MAX_FRAME_ID_BYTES + 1:
        raise PathError(f"{what} frame id is {length} bytes long (at byte {at}), over the cap of "
                        f"{MAX_FRAME_ID_BYTES}")
    if at + length > size:
        raise PathError(f"{what} frame id of {length} bytes at byte {at} runs past the end ({size} bytes)")


def _read_header(view: memoryview) -> _Header:
    size = len(view)
    if size < ENCAPSULATION_BYTES:
        raise PathError(f"{size} bytes: too short for a CDR encapsulation header")
    order = _BYTE_ORDERS.get(bytes(view[:2]))
    if order is None:
        raise PathError(f"unknown encapsulation {bytes(view[:2]).hex()} (expected 0001 or 0000: plain CDR)")
    if size < ENCAPSULATION_BYTES + 12:
        raise PathError(f"{size} bytes: too short for a Path header")
    sec, nanosec, length = struct.unpack_from(order + "iII", view, ENCAPSULATION_BYTES)
    frame_at = ENCAPSULATION_BYTES + 12
    _string_length(length, frame_at, size, "the Path's")
    count_at = _align(frame_at + length, 4)
    if count_at + 4 > size:
        raise PathError(f"{size} bytes: the Path ends before its pose count")
    (count,) = struct.unpack_from(order + "I", view, count_at)
    return _Header(order, sec, nanosec, frame_at, length, count, count_at + 4)


def path_pose_count(raw: bytes | bytearray | memoryview) -> int:
    """The number of poses a serialized Path declares, read from its header and one length field (O(1))."""
    return _read_header(_byte_view(raw)).count


def _frame_name(data: bytes, what: str) -> str:
    """A CDR string's bytes (with its NUL) -> str; like rclpy, stops at the first NUL."""
    if data and data[-1] != 0:
        raise PathError(f"{what} frame id is not NUL-terminated")
    try:
        return data.partition(b"\0")[0].decode("utf-8")
    except UnicodeDecodeError as error:
        raise PathError(f"{what} frame id is not valid UTF-8 ({error.reason} at byte {error.start})") from None


class _Names:
    """Distinct frame ids (decoded once each) -> their index in the table being built."""

    def __init__(self) -> None:
        self.table: list[str] = []
        self._index: dict[str, int] = {}

    def add(self, data: bytes, what: str) -> int:
        name = _frame_name(data, what)
        index = self._index.get(name)
        if index is None:  # distinct bytes may give one name ("a\0b\0", "a\0c\0" -> "a")
            index = self._index[name] = len(self.table)
            self.table.append(name)
        return index


def decode_path(raw: bytes | bytearray | memoryview, max_poses: int) -> DecodedPath:
    """A serialized nav_msgs/Path (CDR, with its 4-byte encapsulation header) -> DecodedPath.

    Refuses (PathError), before reading any pose, a Path declaring more than ``max_poses``
    poses or more than its bytes can hold; then any truncation, a frame id over
    ``MAX_FRAME_ID_BYTES``, not NUL-terminated or not UTF-8. Bytes after the last pose are ignored.
    """
    view = _byte_view(raw)
    header = _read_header(view)
    count = header.count
    if count > max_poses:
        raise PathError(f"the Path declares {count} poses, over the cap of {max_poses}")
    room = len(view) - header.poses_at
    if count * MIN_POSE_STAMPED_BYTES > room:
        raise PathError(f"the Path declares {count} poses but only {room} bytes follow its count (each pose "
                        f"takes at least {MIN_POSE_STAMPED_BYTES})")
    # From here the work is bounded by the buffer's size. bytes: slices and struct are fastest
    # on it, and rclpy's raw callback hands bytes already (no copy then).
    buffer = view.obj if type(view.obj) is bytes and len(view.obj) == len(view) else view.tobytes()
    frame_id = _frame_name(buffer[header.frame_at:header.frame_at + header.frame_length], "the Path's")

    order = header.order
    stamps_ns = np.empty(count, np.int64)
    positions = np.empty((count, 3), np.float64)
    orientations = np.empty((count, 4), np.float64)
    frame_index = np.empty(count, np.int32)
    names = _Names()
    if count:
        words = np.frombuffer(buffer, order + "u4", (len(buffer) - ENCAPSULATION_BYTES) // 4, ENCAPSULATION_BYTES)
        floats = np.frombuffer(buffer, order + "f8", (len(buffer) - ENCAPSULATION_BYTES) // 8, ENCAPSULATION_BYTES)
        # Pose 0 starts 4 bytes after an offset only 4-aligned; every later one starts 8-aligned,
        # so poses 1.. share one layout when their frame ids have one length.
        done, after = _loop(buffer, order, header.poses_at, 0, 1, words, floats, names,
                            stamps_ns, positions, orientations, frame_index)
        if count > 1 and not _uniform(buffer, order, after, count, words, floats, names,
                                      stamps_ns, positions, orientations, frame_index):
            _loop(buffer, order, after, done, count, words, floats, names, stamps_ns, positions, orientations,
                  frame_index)
    return DecodedPath(frame_id=frame_id, stamp_ns=header.sec * NS_PER_S + header.nanosec, stamps_ns=stamps_ns,
                       positions=positions, orientations=orientations, frame_names=tuple(names.table),
                       frame_index=frame_index)


def _uniform(buffer: bytes, order: str, start: int, count: int, words: np.ndarray, floats: np.ndarray,
             names: _Names, stamps_ns: np.ndarray, positions: np.ndarray, orientations: np.ndarray,
             frame_index: np.ndarray) -> bool:
    """Poses 1..count-1 read through strided views, if they all have pose 1's size; False if not.

    ``start`` (8-aligned) is pose 1's. If every length field read at the stride of pose 1's size
    equals pose 1's, each pose ends where the stride puts the next one (by induction), so the
    views are exactly the poses.
    """
    rest = count - 1
    if start + 12 > len(buffer):
        return False  # the loop says where it is truncated
    (length,) = struct.unpack_from(order + "I", buffer, start + 8)
    if length > MAX_FRAME_ID_BYTES + 1:
        return False
    pose_at = _align(start + 12 + length, 8)
    stride = pose_at + POSE_BYTES - start  # a multiple of 8
    if start + rest * stride > len(buffer):
        return False
    word, step = (start - ENCAPSULATION_BYTES) // 4, stride // 4
    lengths = words[word + 2:word + 2 + rest * step:step]
    if not (lengths == length).all():
        return False
    seconds = words[word:word + rest * step:step].view(order + "i4")
    nanoseconds = words[word + 1:word + 1 + rest * step:step]
    stamps_ns[1:] = seconds.astype(np.int64) * NS_PER_S + nanoseconds.astype(np.int64)
    first = (pose_at - ENCAPSULATION_BYTES) // 8
    poses = np.lib.stride_tricks.as_strided(floats[first:], (rest, 7), (stride, 8), writeable=False)
    positions[1:] = poses[:, :3]
    orientations[1:] = poses[:, 3:]

    raw_names = np.lib.stride_tricks.as_strided(np.frombuffer(buffer, np.uint8, offset=start + 12), (rest, length),
                                                (stride, 1), writeable=False)
    if (raw_names == raw_names[0]).all():  # the common case: one frame id for every pose
        frame_index[1:] = names.add(buffer[start + 12:start + 12 + length], "pose 1's")
        return True
    # Same length, different ids ("map"/"odm"): the distinct rows, decoded once each, first seen first.
    rows = np.ascontiguousarray(raw_names).view(f"V{length}").ravel()
    distinct, first_seen, inverse = np.unique(rows, return_index=True, return_inverse=True)
    table = np.empty(len(distinct), np.int32)
    for row in np.argsort(first_seen, kind="stable"):
        table[row] = names.add(distinct[row].tobytes(), f"pose {first_seen[row] + 1}'s")
    frame_index[1:] = table[inverse.ravel()]
    return True


def _loop(buffer: bytes, order: str, at: int, begin: int, end: int, words: np.ndarray, floats: np.ndarray,
          names: _Names, stamps_ns: np.ndarray, positions: np.ndarray, orientations: np.ndarray,
          frame_index: np.ndarray) -> tuple[int, int]:
    """Poses begin..end-1 one by one from byte ``at`` -> (end, the byte after them).

    Python only finds where each pose lies (a frame id's length decides where the next starts);
    numpy then gathers the stamps and poses from those offsets. Inlined and list-based: this is
    the per-pose cost of a Path whose frame ids differ in length.
    """
    size = len(buffer)
    length_field = struct.Struct(order + "I").unpack_from
    cap = MAX_FRAME_ID_BYTES + 1
    starts: list[int] = []
    pose_ats: list[int] = []
    indices: list[int] = []
    known: dict[bytes, int] = {}
    for i in range(begin, end):
        if at + 12 > size:
            raise PathError(f"the Path ends inside pose {i}'s header ({size} bytes)")
        (length,) = length_field(buffer, at + 8)
        text_at = at + 12
        if length > cap or text_at + length > size:
            _string_length(length, text_at, size, f"pose {i}'s")
        data = buffer[text_at:text_at + length]
        index = known.get(data)
        if index is None:
            index = known[data] = names.add(data, f"pose {i}'s")
        indices.append(index)
        pose_at = text_at + length
        pose_at += (ENCAPSULATION_BYTES - pose_at) & 7  # _align(pose_at, 8), inlined
        if pose_at + POSE_BYTES > size:
            raise PathError(f"the Path ends inside pose {i} ({size} bytes)")
        starts.append(at)
        pose_ats.append(pose_at)
        at = pose_at + POSE_BYTES
    word = (np.array(starts, np.int64) - ENCAPSULATION_BYTES) // 4
    stamps_ns[begin:end] = words[word].view(order + "i4").astype(np.int64) * NS_PER_S + words[word + 1]
    poses = floats[((np.array(pose_ats, np.int64) - ENCAPSULATION_BYTES) // 8)[:, None] + np.arange(7)]
    positions[begin:end] = poses[:, :3]
    orientations[begin:end] = poses[:, 3:]
    frame_index[begin:end] = indices
    return end, at

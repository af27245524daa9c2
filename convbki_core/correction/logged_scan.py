"""One integrated scan as the scan log keeps it (``LoggedScan``), and the logged scans' stamps
and poses as arrays (``LogTable``): what a correction maps again, and what it is planned on.

A scan is kept bit for bit as it entered the map: its stamp (ns), the pose it was integrated
with (map <- sensor) and the sensor's mount on the body whose poses a SLAM corrects (body <-
sensor); its points (float32 or float64) as byte planes (each value's most significant byte,
then the next, ...), the top plane (sign and exponent, nearly constant over a scan) compressed
with zlib and the others as they are (the mantissa's bytes are noise to a compressor, and
compressing them would cost the update thread time for little); its labels (the smallest
integer type that holds them, compressed) or its class probabilities (byte planes like the
points). The encoded bytes (``ScanBytes``) are shared by every copy of the scan at another
pose, and live in memory, in a file of the log's folder (``log_folder``), or both.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass

import numpy as np

# Values of a logged scan's ``kind``: integer labels, or rows of class probabilities.
LABELS, PROBABILITIES = 0, 1
# The integer types labels are kept in, the smallest first.
_LABEL_TYPES = (np.uint8, np.int8, np.uint16, np.int16, np.int32, np.int64)
# What a logged scan costs besides its data (its fields and their objects), bytes.
_SCAN_OVERHEAD = 300


def encode_floats(values: np.ndarray) -> bytes:
    """A float32/float64 array as byte planes, the most significant plane compressed."""
    values = np.ascontiguousarray(values, dtype=values.dtype.newbyteorder("<"))
    width = values.dtype.itemsize
    planes = values.reshape(-1).view(np.uint8).reshape(-1, width).T  # little endian: the last plane is the top
    top = zlib.compress(np.ascontiguousarray(planes[width - 1]).tobytes(), 1)
    rest = np.ascontiguousarray(planes[:width - 1]).tobytes()
    return len(top).to_bytes(8, "little") + top + rest


def decode_floats(data: bytes, dtype, shape: tuple[int, ...]) -> np.ndarray:
    """The inverse of ``encode_floats``."""
    width = np.dtype(dtype).itemsize
    count = int(np.prod(shape))
    top_size = int.from_bytes(data[:8], "little")
    top = np.frombuffer(zlib.decompress(data[8:8 + top_size]), np.uint8)
    rest = np.frombuffer(data, np.uint8, offset=8 + top_size).reshape(width - 1, count)
    planes = np.empty((count, width), np.uint8)
    planes[:, :width - 1] = rest.T
    planes[:, width - 1] = top
    return planes.reshape(-1).view(np.dtype(dtype).newbyteorder("<")).astype(dtype, copy=False).reshape(shape)


def _label_type(labels: np.ndarray):
    if not len(labels):
        return np.uint8
    low, high = int(labels.min()), int(labels.max())
    return next(kind for kind in _LABEL_TYPES if np.iinfo(kind).min <= low and high <= np.iinfo(kind).max)


class ScanBytes:
    """A logged scan's encoded points and values: in memory until the log's folder holds them
    (``place``) and the log lets them go (``release``); read back from the file then. One
    object for every copy of the scan (``LoggedScan.at``), so a scan is written once."""

    __slots__ = ("__weakref__", "_data", "place", "points_size", "values_size")

    def __init__(self, points_data: bytes, values_data: bytes, place: tuple | None = None):
        self.points_size, self.values_size = len(points_data), len(values_data)
        self._data: tuple[bytes, bytes] | None = (points_data, values_data)
        self.place = place  # (the ``LogFolder``, its file's name, the offset there) once written

    @classmethod
    def in_file(cls, place: tuple, points_size: int, values_size: int) -> ScanBytes:
        """The bytes of a scan a file holds (a map file's log read back)."""
        data = cls(b"", b"", place)
        data.points_size, data.values_size, data._data = int(points_size), int(values_size), None
        return data

    @property
    def size(self) -> int:
        return self.points_size + self.values_size

    @property
    def in_memory(self) -> bool:
        return self._data is not None

    def parts(self) -> tuple[bytes, bytes]:
        """(points bytes, values bytes), from memory or from the file."""
        data = self._data  # read once: the writer may release it meanwhile
        if data is not None:
            return data
        folder, name, offset = self.place
        raw = folder.read(name, offset, self.size)
        return raw[:self.points_size], raw[self.points_size:]

    def release(self) -> int:
        """Let the memory copy go where the file holds the bytes; returns the bytes let go."""
        if self.place is None or self._data is None:
            return 0
        self._data = None
        return self.size


@dataclass
class LoggedScan:
    """One integrated scan as the log keeps it (see the module docstring)."""

    stamp_ns: int
    pose: np.ndarray  # (4, 4) float64 map <- sensor, as integrated
    mount: np.ndarray  # (4, 4) float64 body <- sensor
    count: int  # points
    points_dtype: str
    kind: int  # LABELS or PROBABILITIES
    values_dtype: str
    columns: int  # probability columns (0 for labels)
    data: ScanBytes

    @property
    def points_data(self) -> bytes:
        return self.data.parts()[0]

    @property
    def values_data(self) -> bytes:
        return self.data.parts()[1]

    @property
    def nbytes(self) -> int:
        """What the scan costs the log: its encoded data and its fixed fields."""
        return self.data.size + _SCAN_OVERHEAD

    def points(self) -> np.ndarray:
        return decode_floats(self.points_data, np.dtype(self.points_dtype), (self.count, 3))

    def values(self) -> np.ndarray:
        if self.kind == LABELS:
            return np.frombuffer(zlib.decompress(self.values_data), np.dtype(self.values_dtype)).copy()
        return decode_floats(self.values_data, np.dtype(self.values_dtype), (self.count, self.columns))

    def decoded(self) -> tuple[np.ndarray, np.ndarray]:
        """(points, values), the bytes read once."""
        points_data, values_data = self.data.parts()
        points = decode_floats(points_data, np.dtype(self.points_dtype), (self.count, 3))
        if self.kind == LABELS:
            return points, np.frombuffer(zlib.decompress(values_data), np.dtype(self.values_dtype)).copy()
        return points, decode_floats(values_data, np.dtype(self.values_dtype), (self.count, self.columns))

    def at(self, pose: np.ndarray) -> LoggedScan:
        """The same scan at another pose (the data shared)."""
        return LoggedScan(self.stamp_ns, np.array(pose, np.float64), self.mount, self.count, self.points_dtype,
                          self.kind, self.values_dtype, self.columns, self.data)

    @classmethod
    def of(cls, points: np.ndarray, values: np.ndarray, pose: np.ndarray, stamp_ns: int,
           mount: np.ndarray | None = None) -> LoggedScan:
        """Encode one scan (points (N, 3) float32/float64, labels (N,) or probabilities (N, C))."""
        points = np.asarray(points)
        points = points.astype("<f4" if points.dtype == np.float32 else "<f8", copy=False)
        values = np.asarray(values)
        if values.ndim == 1:
            labels = values.astype(_label_type(values))
            kind, values_dtype, columns = LABELS, labels.dtype.str, 0
            values_data = zlib.compress(labels.tobytes(), 1)
        else:
            probabilities = values.astype("<f8" if values.dtype == np.float64 else "<f4", copy=False)
            kind, values_dtype, columns = PROBABILITIES, probabilities.dtype.str, int(values.shape[1])
            values_data = encode_floats(probabilities)
        mount = np.eye(4) if mount is None else np.array(mount, np.float64)
        return cls(int(stamp_ns), np.array(pose, np.float64), mount, int(points.shape[0]), points.dtype.str, kind,
                   values_dtype, columns, ScanBytes(encode_floats(points), values_data))


@dataclass
class LogTable:
    """The logged scans' stamps and poses as arrays (oldest first), what a Path's correction is
    planned on without touching the scans' data."""

    indices: np.ndarray  # (n,) int64: the drive's scan index
    stamps_ns: np.ndarray  # (n,) int64
    poses: np.ndarray  # (n, 4, 4) float64 map <- sensor, as integrated
    mounts: np.ndarray  # (n, 4, 4) float64 body <- sensor

    def __len__(self) -> int:
        return len(self.indices)

    @classmethod
    def of(cls, scans: list[tuple[int, LoggedScan]]) -> LogTable:
        """The table of (index, scan) pairs."""
        if not scans:
            return cls(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 4, 4)), np.zeros((0, 4, 4)))
        return cls(np.array([index for index, _ in scans], np.int64),
                   np.array([scan.stamp_ns for _, scan in scans], np.int64),
                   np.stack([scan.pose for _, scan in scans]), np.stack([scan.mount for _, scan in scans]))

    @classmethod
    def joined(cls, parts: list[LogTable]) -> LogTable:
        parts = [part for part in parts if len(part)] or [cls.of([])]
        return cls(*(np.concatenate([getattr(part, name) for part in parts])
                     for name in ("indices", "stamps_ns", "poses", "mounts")))

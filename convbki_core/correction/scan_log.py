"""The scan log: what the map needs to move the scans it has integrated.

A SLAM that closes a loop moves the poses of scans the map integrated long ago. The map can
follow it exactly when it can map those scans again at their new poses, in the order they
came, from the map as it was before the first of them: ConvBKI's sum (Eq. 4), free space,
clamping and the movers' rules then all give what mapping from scratch with the corrected
poses gives (``correction``). The log keeps what that takes:

* every integrated scan bit for bit as it entered the map (``LoggedScan``): its stamp (ns),
  the pose it was integrated with (map <- sensor) and the sensor's mount on the body whose
  poses a SLAM corrects (body <- sensor); its points (float32 or float64) as byte planes (each
  value's most significant byte, then the next, ...), the top plane (sign and exponent, nearly
  constant over a scan) compressed with zlib and the others as they are (the mantissa's bytes
  are noise to a compressor, and compressing them would cost the update thread time for
  little); its labels (the smallest integer type that holds them, compressed) or its class
  probabilities (byte planes like the points);
* the map as it was when each *segment* of the log began (``Segment.base``: a copy of the
  global store, which shares every chunk the map has not changed since).

The log is bounded by a number of scans and by bytes (what its scans and bases hold in
memory, and add to the map file it is saved with). A segment closes when it holds half the
bound; when the log exceeds the bound its oldest segment falls out: those scans are frozen
into the map (their evidence stays, no correction can move them), and a correction reaches
back at least half the bound and at most all of it (``reach_ns``).
"""

from __future__ import annotations

import ctypes
import threading
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from convbki_core.correction.logged_scan import (  # noqa: F401 (the log's scans, named here too)
    LABELS,
    PROBABILITIES,
    LoggedScan,
    LogTable,
    decode_floats,
    encode_floats,
)

FELL_OUT = "they fell out of the scan log (its bounds: scans, megabytes)"


def _load_malloc_trim():
    try:
        function = ctypes.CDLL(None).malloc_trim  # glibc
    except (OSError, AttributeError):
        return None
    function.argtypes, function.restype = [ctypes.c_size_t], ctypes.c_int
    return function


_MALLOC_TRIM = _load_malloc_trim()


def return_freed_memory() -> None:
    """Hand the pages of freed blocks back to the system (glibc; nothing elsewhere). A log that
    drops its oldest segment frees thousands of scan-sized blocks among live ones; the
    allocator would keep their pages, and the process would grow though the log is bounded."""
    if _MALLOC_TRIM is not None:
        _MALLOC_TRIM(0)


@dataclass
class Segment:
    """Consecutive logged scans and the map as it was before the first of them."""

    first_index: int  # the drive's index of its first scan (the map had integrated this many)
    base: object | None  # a ``VoxelStore`` copy of the map before its first scan; None: an empty map
    base_position: np.ndarray | None  # the sensor's position then (map frame, m)
    base_bytes: int = 0  # what the base holds that the map's store does not share (refreshed as the map changes)
    scans: list = field(default_factory=list)
    scan_bytes: int = 0
    # The table of its scans as far as it was last read (``table``): a segment's scans only grow.
    _table: LogTable | None = field(default=None, repr=False, compare=False)

    @property
    def nbytes(self) -> int:
        return self.base_bytes + self.scan_bytes

    def table(self, count: int | None = None) -> LogTable:
        """Its first ``count`` scans' stamps and poses (``LogTable``; default: all), the rows read
        before kept."""
        known = self._table
        count = len(self.scans) if count is None else count
        if known is None:
            known = LogTable.of([])
        if len(known) < count:
            start = len(known)
            known = LogTable.joined([known, LogTable.of([(self.first_index + number, self.scans[number])
                                                         for number in range(start, count)])])
            self._table = known
        if len(known) > count:
            known = LogTable(known.indices[:count], known.stamps_ns[:count], known.poses[:count], known.mounts[:count])
        return known


# The per-scan fields a map file keeps of a log (one row per scan), beside the bytes.
_TABLE = np.dtype([("stamp_ns", "<i8"), ("pose", "<f8", (4, 4)), ("mount", "<f8", (4, 4)), ("count", "<i8"),
                   ("points_dtype", "S4"), ("kind", "<i1"), ("values_dtype", "S4"), ("columns", "<i4"),
                   ("points_bytes", "<i8"), ("values_bytes", "<i8")])


class ScanLog:
    """The log's segments, oldest first, within ``max_scans`` scans and ``max_bytes`` bytes (0:
    no such bound). Thread-safe: the mapper appends while a correction reads."""

    def __init__(self, max_scans: int = 0, max_bytes: int = 0, calibration: np.ndarray | None = None):
        self.max_scans, self.max_bytes = int(max_scans), int(max_bytes)
        self.calibration = calibration  # velodyne -> camera of the dataset the scans came from, if any
        self.frozen = 0  # scans before the oldest segment: frozen into the map
        self.frozen_stamp_ns: int | None = None  # the stamp of the newest frozen scan
        self.frozen_why = ""  # why the frozen scans cannot move, in words (for the one line that says so)
        # Scans from this index on stay while a correction still has to map them (``hold``).
        self.held_from: int | None = None
        # A SLAM's Path not yet applied (a correction under way, or waiting): (keyframe stamps (K,)
        # ns, their poses (K, 4, 4) map <- body). Saved with the log, so that ``map_tool correct``
        # applies it to a map saved before it was.
        self.pending: tuple[np.ndarray, np.ndarray] | None = None
        self._changes = 0  # bumped by every change of what the log holds
        self._table: tuple | None = None  # (``_changes`` then, the ``LogTable``) when last read
        self._segments: deque[Segment] = deque([Segment(0, None, None)])
        self._lock = threading.Lock()

    # -- what it holds -------------------------------------------------------------------------
    def __len__(self) -> int:
        with self._lock:
            return sum(len(segment.scans) for segment in self._segments)

    @property
    def nbytes(self) -> int:
        with self._lock:
            return sum(segment.nbytes for segment in self._segments)

    @property
    def first_index(self) -> int:
        """The drive's index of the oldest logged scan (scans 0 .. first_index - 1 are frozen)."""
        with self._lock:
            return self._segments[0].first_index

    @property
    def next_index(self) -> int:
        """The drive's index the next logged scan gets."""
        with self._lock:
            last = self._segments[-1]
            return last.first_index + len(last.scans)

    @property
    def newest_ns(self) -> int | None:
        """The stamp of the newest logged scan (None: none logged)."""
        with self._lock:
            newest = next((segment.scans[-1] for segment in reversed(self._segments) if segment.scans), None)
            return None if newest is None else newest.stamp_ns

    @property
    def reach_ns(self) -> int | None:
        """The stamp of the oldest scan a correction can still move (None: none logged)."""
        with self._lock:
            first = next((segment.scans[0] for segment in self._segments if segment.scans), None)
            return None if first is None else first.stamp_ns

    def scans(self, since: int = 0) -> list[tuple[int, LoggedScan]]:
        """(drive index, scan) of every logged scan with an index of at least ``since``, oldest first."""
        with self._lock:
            return [(segment.first_index + number, scan) for segment in self._segments
                    for number, scan in enumerate(segment.scans) if segment.first_index + number >= since]

    def table(self, since: int = 0) -> LogTable:
        """The stamps and poses of the logged scans with an index of at least ``since`` (``LogTable``)."""
        with self._lock:  # the segments and how many scans each holds now; their scans never change
            held = [(segment, len(segment.scans)) for segment in self._segments]
            key = self._changes
        cached = self._table
        if cached is not None and cached[0] == key:
            table = cached[1]
        else:
            table = LogTable.joined([segment.table(count) for segment, count in held])
            self._table = (key, table)
        if since and len(table) and table.indices[0] < since:
            keep = table.indices >= since
            table = LogTable(table.indices[keep], table.stamps_ns[keep], table.poses[keep], table.mounts[keep])
        return table

    def segments(self) -> list[Segment]:
        """The segments as they are now (copies of their lists; bases and scans shared)."""
        with self._lock:
            return self._segment_copies()

    def _segment_copies(self) -> list[Segment]:
        return [Segment(s.first_index, s.base, s.base_position, s.base_bytes, list(s.scans), s.scan_bytes, s._table)
                for s in self._segments]

    def segment_for(self, index: int) -> Segment | None:
        """The segment holding scan ``index`` (its list as it is now), None when it is not logged."""
        for segment in self.segments():
            if segment.first_index <= index < segment.first_index + len(segment.scans):
                return segment
        return None

    # -- growing -------------------------------------------------------------------------------
    def append(self, scan: LoggedScan) -> int:
        """Log the newest scan; the oldest segments fall out past the bounds. Returns how many
        scans fell out."""
        with self._lock:
            last = self._segments[-1]
            last.scans.append(scan)
            self._changes += 1
            last.scan_bytes += scan.nbytes
            dropped = self._drop_over_bounds()
        if dropped:
            return_freed_memory()
        return dropped

    def _drop_over_bounds(self) -> int:
        """Drop the oldest segments while the log is over a bound (lock held); what they held is
        frozen into the map. Returns how many scans fell out."""
        dropped = 0
        while len(self._segments) > 1 and (self.held_from is None or self._segments[1].first_index <= self.held_from) \
                and (
                (self.max_scans and sum(len(s.scans) for s in self._segments) > self.max_scans)
                or (self.max_bytes and sum(s.nbytes for s in self._segments) > self.max_bytes)):
            old = self._segments.popleft()
            self._changes += 1
            dropped += len(old.scans)
            self.frozen += len(old.scans)
            self.frozen_why = FELL_OUT
            if old.scans:
                self.frozen_stamp_ns = old.scans[-1].stamp_ns
        return dropped

    def hold(self, index: int | None) -> None:
        """Keep the scans from ``index`` on, whatever the bounds, until ``hold(None)``: a
        correction maps them into its new map after the live map took them."""
        with self._lock:
            self.held_from = index
            if index is None:
                self._drop_over_bounds()

    def wants_segment(self) -> bool:
        """The newest segment holds half the bound: the next one should begin (``begin_segment``)."""
        with self._lock:  # the scans alone: a base larger than half the bound must not begin one a scan
            last = self._segments[-1]
            return bool(last.scans) and bool((self.max_scans and 2 * len(last.scans) >= self.max_scans)
                                             or (self.max_bytes and 2 * last.scan_bytes >= self.max_bytes))

    def begin_segment(self, base, base_position: np.ndarray | None, base_bytes: int) -> int:
        """Begin a segment whose base is the map as it is now (``base``: a ``VoxelStore`` copy);
        the oldest segments fall out past the bounds. Returns how many scans fell out."""
        with self._lock:
            last = self._segments[-1]
            self._changes += 1
            self._segments.append(Segment(last.first_index + len(last.scans), base,
                                          None if base_position is None else np.array(base_position), base_bytes))
            dropped = self._drop_over_bounds()
        if dropped:
            return_freed_memory()
        return dropped

    def refresh_base_bytes(self, store) -> None:
        """Count again what each base holds beside ``store`` (the map's): a base shares the
        store's chunks when it is made, and comes to own those the map rewrites since."""
        with self._lock:
            bases = [segment for segment in self._segments if segment.base is not None]
        for segment in bases:  # outside the lock: a base never changes, and the count takes a while
            segment.base_bytes = segment.base.bytes_not_shared_with(store)

    def replace_from(self, index: int, segments: list[Segment]) -> None:
        """Replace the segments from the one whose first scan is ``index`` on with ``segments``
        (a correction's: the same scans, at their corrected poses, and the bases it saw)."""
        with self._lock:
            kept = [segment for segment in self._segments if segment.first_index < index]
            self._segments = deque(kept + list(segments))
            self._changes += 1

    def clear(self) -> None:
        """Forget every scan; the map from now on is the base of the next one (the caller's)."""
        with self._lock:
            self._segments = deque([Segment(0, None, None)])
            self._changes += 1
            self.frozen = 0
            self.frozen_stamp_ns = None
            self.frozen_why = ""
            self.pending = None

    def restart(self, base, base_position: np.ndarray | None, base_bytes: int, first_index: int,
                why: str = "") -> None:
        """Forget every scan and begin again from ``base`` (a map loaded from a file without a
        log, a forgotten box); ``why``: what froze the scans before, in words."""
        with self._lock:
            self._changes += 1
            self._segments = deque([Segment(first_index, base, None if base_position is None
                                            else np.array(base_position), base_bytes)])
            self.frozen = first_index
            self.frozen_stamp_ns = None
            self.frozen_why = why
            self.pending = None

    def copy(self) -> ScanLog:
        """A copy as it is now (segment lists copied; bases and scans shared: they do not change)."""
        other = ScanLog(self.max_scans, self.max_bytes, self.calibration)
        with self._lock:  # one hold: the segments and what they froze agree
            other.frozen, other.frozen_stamp_ns, other.frozen_why = self.frozen, self.frozen_stamp_ns, self.frozen_why
            other.pending = self.pending
            other._segments = deque(self._segment_copies())
        return other

    # -- in a map file -----------------------------------------------------------------------
    def to_arrays(self) -> dict[str, np.ndarray]:
        """The log as map-file members: per segment ``scan_log_{i}_table`` (one row per scan),
        ``scan_log_{i}_data`` (its scans' bytes) and its base's rows (``scan_log_{i}_base_index``,
        ``_count``, ``_class``, ``_value``, as the map's own), and ``scan_log_meta`` (JSON)."""
        import json

        from convbki_core.memory.compact_rows import compress_rows

        arrays, segments = {}, self.segments()
        described = []
        for number, segment in enumerate(segments):
            table = np.zeros(len(segment.scans), _TABLE)
            for row, scan in zip(table, segment.scans):
                row["stamp_ns"], row["pose"], row["mount"] = scan.stamp_ns, scan.pose, scan.mount
                row["count"], row["points_dtype"], row["kind"] = scan.count, scan.points_dtype.encode(), scan.kind
                row["values_dtype"], row["columns"] = scan.values_dtype.encode(), scan.columns
                row["points_bytes"], row["values_bytes"] = len(scan.points_data), len(scan.values_data)
            arrays[f"scan_log_{number}_table"] = table
            arrays[f"scan_log_{number}_data"] = np.frombuffer(
                b"".join(part for scan in segment.scans for part in (scan.points_data, scan.values_data)), np.uint8)
            if segment.base is not None:
                indices, alpha = segment.base.items()
                counts, classes, values = compress_rows(alpha, segment.base.prior)
                arrays[f"scan_log_{number}_base_index"] = indices.astype(np.int32)
                arrays[f"scan_log_{number}_base_count"] = counts
                arrays[f"scan_log_{number}_base_class"] = classes
                arrays[f"scan_log_{number}_base_value"] = values.view(np.float32)
            described.append({"first_index": segment.first_index, "base": segment.base is not None,
                              "base_position": None if segment.base_position is None
                              else [float(v) for v in segment.base_position]})
        meta = {"segments": described, "frozen": self.frozen, "frozen_stamp_ns": self.frozen_stamp_ns,
                "frozen_why": self.frozen_why,
                "calibration": None if self.calibration is None else np.asarray(self.calibration).tolist()}
        arrays["scan_log_meta"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
        if self.pending is not None:
            arrays["scan_log_pending_stamps"] = np.asarray(self.pending[0], "<i8")
            arrays["scan_log_pending_poses"] = np.asarray(self.pending[1], "<f8")
        return arrays

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], meta: dict, num_classes: int, prior: float) -> ScanLog:
        """The log of map-file members (``to_arrays``); raises ValueError when they do not fit."""
        from convbki_core.memory.compact_rows import expand_rows
        from convbki_core.memory.store import VoxelStore

        log = cls()
        segments = []
        described = meta.get("segments")
        if not isinstance(described, list) or not described:
            raise ValueError("its metadata lists no segment")
        for number, about in enumerate(described):
            table, data = arrays.get(f"scan_log_{number}_table"), arrays.get(f"scan_log_{number}_data")
            if table is None or data is None or table.dtype != _TABLE or data.dtype != np.uint8 or data.ndim != 1:
                raise ValueError(f"segment {number}'s scans are missing or of unexpected types")
            sizes = table["points_bytes"].astype(np.int64) + table["values_bytes"]
            if (sizes < 0).any() or int(sizes.sum()) != data.size:
                raise ValueError(f"segment {number}'s table names {int(sizes.sum())} bytes, its data holds {data.size}")
            if not np.isfinite(table["pose"]).all() or not np.isfinite(table["mount"]).all():
                raise ValueError(f"segment {number} holds a pose that is not finite")
            scans, offset, raw = [], 0, data.tobytes()
            for row in table:
                points_end = offset + int(row["points_bytes"])
                values_end = points_end + int(row["values_bytes"])
                scans.append(LoggedScan(int(row["stamp_ns"]), row["pose"].copy(), row["mount"].copy(),
                                        int(row["count"]), row["points_dtype"].decode(), int(row["kind"]),
                                        row["values_dtype"].decode(), int(row["columns"]), raw[offset:points_end],
                                        raw[points_end:values_end]))
                offset = values_end
            base, base_bytes = None, 0
            if about.get("base"):
                parts = [arrays.get(f"scan_log_{number}_base_{name}") for name in ("index", "count", "class", "value")]
                if any(part is None for part in parts):
                    raise ValueError(f"segment {number}'s base is missing")
                index, counts, classes, values = parts
                base = VoxelStore(num_classes, prior)
                base.write(index.astype(np.int64), expand_rows(counts, classes, values.astype(np.float32), prior,
                                                               num_classes))
                base_bytes = base.resident_bytes
            position = about.get("base_position")
            segments.append(Segment(int(about.get("first_index", 0)), base,
                                    None if position is None else np.asarray(position, np.float64), base_bytes, scans,
                                    sum(scan.nbytes for scan in scans)))
        log._segments = deque(segments)
        log.frozen = int(meta.get("frozen", 0))
        log.frozen_stamp_ns = meta.get("frozen_stamp_ns")
        log.frozen_why = str(meta.get("frozen_why") or "")
        stamps, poses = arrays.get("scan_log_pending_stamps"), arrays.get("scan_log_pending_poses")
        if stamps is not None or poses is not None:
            if (stamps is None or poses is None or stamps.ndim != 1 or poses.shape != (len(stamps), 4, 4)
                    or not np.isfinite(poses).all() or (np.diff(stamps) <= 0).any()):
                raise ValueError("its pending correction's keyframes are damaged")
            log.pending = (stamps.astype(np.int64), poses.astype(np.float64))
        calibration = meta.get("calibration")
        log.calibration = None if calibration is None else np.asarray(calibration, np.float64)
        return log

    def adopt(self, other: ScanLog) -> None:
        """Take ``other``'s segments (a map file's log), keeping this log's bounds: its oldest
        segments fall out (frozen) where they exceed them."""
        with other._lock:
            segments, frozen, frozen_stamp = list(other._segments), other.frozen, other.frozen_stamp_ns
            calibration, why, pending = other.calibration, other.frozen_why, other.pending
        with self._lock:
            self.pending = pending
            self._segments = deque(segments)
            self._changes += 1
            self.frozen, self.frozen_stamp_ns, self.calibration = frozen, frozen_stamp, calibration
            self.frozen_why = why
            self._drop_over_bounds()

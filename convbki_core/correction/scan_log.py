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

Without a folder the log lives in memory, bounded by a number of scans and by bytes (what its
scans and bases hold, and add to the map file it is saved with). A segment closes when it
holds half the byte bound; when the log exceeds a bound its oldest segment falls out: those
scans are frozen into the map (their evidence stays, no correction can move them), and a
correction reaches back at least half the bound and at most all of it (``reach_ns``).

With a folder (``use_folder``, ``log_folder``) every scan and base is also written there, off
the mapping thread; the byte bound is then on memory (past it the oldest segments written
leave memory, read back from their files when a correction needs them), a segment closes at a
quarter of it (a correction maps again from the base of the segment that holds its first
moved scan: shorter segments, less mapped again for nothing), and the folder's own bound
(``LogFolder.max_bytes``) is where the oldest segments fall out. A map file saved then names
the folder's files instead of holding the scans (``log_file``).
"""

from __future__ import annotations

import ctypes
import threading
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from convbki_core.correction.log_folder import LogFolder, SegmentBase
from convbki_core.correction.logged_scan import (  # noqa: F401 (the log's scans, named here too)
    LABELS,
    PROBABILITIES,
    LoggedScan,
    LogTable,
    decode_floats,
    encode_floats,
)

FELL_OUT = "they fell out of the scan log (its bounds: scans, megabytes, disk gigabytes)"


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
    base: SegmentBase | None  # the map before its first scan; None: an empty map
    base_position: np.ndarray | None  # the sensor's position then (map frame, m)
    scans: list = field(default_factory=list)
    scan_bytes: int = 0  # its scans' encoded bytes (and fixed fields)
    resident: bool = True  # its scans' bytes are in memory (False: only in the log's folder)
    # The table of its scans as far as it was last read (``table``): a segment's scans only grow.
    _table: LogTable | None = field(default=None, repr=False, compare=False)

    @property
    def nbytes(self) -> int:
        """The memory it takes: its scans' bytes while resident, its base's while in memory."""
        base = self.base.memory_bytes if self.base is not None and self.base.in_memory else 0
        return base + (self.scan_bytes if self.resident else _RELEASED_SCAN_BYTES * len(self.scans))

    @property
    def disk_bytes(self) -> int:
        """What it takes in the log's folder (once written)."""
        return self.scan_bytes + (self.base.disk_bytes if self.base is not None else 0)

    def written(self) -> bool:
        """Its scans and base are all in the log's folder."""
        return (self.base is None or self.base.place is not None) and all(
            scan.data.place is not None for scan in self.scans)

    def release(self) -> None:
        """Let the memory copies of its scans and base go (written: ``written``)."""
        for scan in self.scans:
            scan.data.release()
        if self.base is not None:
            self.base.release()
        self.resident = False

    def base_store(self):
        """The map as it was where the segment began (a ``VoxelStore``; None: an empty map)."""
        return None if self.base is None else self.base.store()

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


# What a scan whose bytes left memory still costs it (its pose, mount and fields).
_RELEASED_SCAN_BYTES = 450


class ScanLog:
    """The log's segments, oldest first, within ``max_scans`` scans and ``max_bytes`` bytes of
    memory (0: no such bound), and, with a folder, its folder's bound. Thread-safe: the mapper
    appends while a correction reads."""

    def __init__(self, max_scans: int = 0, max_bytes: int = 0, calibration: np.ndarray | None = None):
        self.max_scans, self.max_bytes = int(max_scans), int(max_bytes)
        self.folder: LogFolder | None = None  # where its scans and bases are written (``use_folder``)
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
        """The memory it takes."""
        with self._lock:
            return sum(segment.nbytes for segment in self._segments)

    @property
    def disk_bytes(self) -> int:
        """What it takes in its folder (0 without one)."""
        if self.folder is None:
            return 0
        with self._lock:
            return sum(segment.disk_bytes for segment in self._segments)

    def use_folder(self, folder: LogFolder | None) -> None:
        """Write its scans and bases to ``folder`` from now on, those it holds already too."""
        with self._lock:
            self.folder = folder
            segments = list(self._segments)
        if folder is None:
            return
        folder.hold(self)
        for segment in segments:
            if segment.base is not None and segment.base.place is None:
                folder.put_base(segment.base)
            for scan in segment.scans:
                if scan.data.place is None:
                    folder.put_scan(scan.data)

    def file_names(self, folder: LogFolder) -> set[str]:
        """The files of ``folder`` its scans and bases are in."""
        with self._lock:
            segments = list(self._segments)
        names = set()
        for segment in segments:
            for place in [scan.data.place for scan in list(segment.scans)] + \
                    [segment.base.place if segment.base is not None else None]:
                if place is not None and folder.same(place[0]):
                    names.add(place[1])
            base = segment.base
            if base is not None and base.place is not None and folder.same(base.place[0]):
                names |= base.depends
        return names

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
        return [Segment(s.first_index, s.base, s.base_position, list(s.scans), s.scan_bytes, s.resident, s._table)
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
        if self.folder is not None and scan.data.place is None:
            self.folder.put_scan(scan.data)
        with self._lock:
            last = self._segments[-1]
            last.scans.append(scan)
            self._changes += 1
            last.scan_bytes += scan.nbytes
            dropped = self._drop_over_bounds()
        if dropped:
            return_freed_memory()
        return dropped

    def _release_over_memory(self) -> None:
        """With a folder: while the log takes more memory than its bound, let the oldest written
        segments (never the newest) leave memory (lock held)."""
        if self.folder is None or not self.max_bytes:
            return
        total = sum(s.nbytes for s in self._segments)
        for segment in list(self._segments)[:-1]:
            if total <= self.max_bytes:
                return
            if segment.resident and segment.written():
                before = segment.nbytes
                segment.release()
                total -= before - segment.nbytes

    def _over_bounds(self) -> bool:
        if self.max_scans and sum(len(s.scans) for s in self._segments) > self.max_scans:
            return True
        if self.folder is None:
            return bool(self.max_bytes) and sum(s.nbytes for s in self._segments) > self.max_bytes
        if self.folder.max_bytes and sum(s.disk_bytes for s in self._segments) > self.folder.max_bytes:
            return True
        # Writes that fail (a full disk) keep scans in memory: memory bounds the log again then.
        return self.folder.error is not None and bool(self.max_bytes) and \
            sum(s.nbytes for s in self._segments) > self.max_bytes

    def _drop_over_bounds(self) -> int:
        """Drop the oldest segments while the log is over a bound (lock held); what they held is
        frozen into the map. Returns how many scans fell out."""
        self._release_over_memory()
        dropped = 0
        while len(self._segments) > 1 and (self.held_from is None or self._segments[1].first_index <= self.held_from) \
                and self._over_bounds():
            old = self._segments.popleft()
            self._changes += 1
            dropped += len(old.scans)
            self.frozen += len(old.scans)
            self.frozen_why = FELL_OUT
            if old.scans:
                self.frozen_stamp_ns = old.scans[-1].stamp_ns
        if dropped and self.folder is not None:
            self.folder.tidy()
        return dropped

    def trim(self) -> int:
        """Let the oldest segments fall out where the log is over a bound now (a bound is checked at
        each scan logged; the folder counts a base once written). Returns how many scans fell out."""
        with self._lock:
            return self._drop_over_bounds()

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
            if self.folder is not None and self.folder.error is None and last.base is not None \
                    and last.base.place is None:
                return False  # one base at most waits for the writer: the segment grows meanwhile
            share = 4 if self.folder is not None else 2
            return bool(last.scans) and bool((self.max_scans and 2 * len(last.scans) >= self.max_scans)
                                             or (self.max_bytes and share * last.scan_bytes >= self.max_bytes))

    def _new_base(self, base: SegmentBase | None) -> SegmentBase | None:
        if base is None:
            return None
        if self.folder is not None and self.folder.error is None:
            self.folder.put_base(base)  # built there, off the update thread
        else:
            base.build()
        return base

    def begin_segment(self, base: SegmentBase | None, base_position: np.ndarray | None) -> int:
        """Begin a segment whose base is the map as it is now (``base``: None for an empty map);
        the oldest segments fall out past the bounds. Returns how many scans fell out."""
        segment_base = self._new_base(base)
        with self._lock:
            last = self._segments[-1]
            self._changes += 1
            self._segments.append(Segment(last.first_index + len(last.scans), segment_base,
                                          None if base_position is None else np.array(base_position)))
            dropped = self._drop_over_bounds()
        if dropped:
            return_freed_memory()
        return dropped

    def refresh_base_bytes(self, store) -> None:
        """Count again what each base in memory holds beside ``store`` (the map's): a base shares
        the store's chunks when it is made, and comes to own those the map rewrites since."""
        with self._lock:
            bases = [segment.base for segment in self._segments if segment.base is not None]
        for base in bases:  # outside the lock: a base never changes, and the count takes a while
            held = base.held_store()
            if held is not None:
                base.memory_bytes = held.bytes_not_shared_with(store)

    def replace_from(self, index: int, segments: list[Segment]) -> None:
        """Replace the segments from the one whose first scan is ``index`` on with ``segments``
        (a correction's: the same scans, at their corrected poses, and the bases it saw)."""
        with self._lock:
            kept = [segment for segment in self._segments if segment.first_index < index]
            self._segments = deque(kept + list(segments))
            self._changes += 1
            self._drop_over_bounds()  # the replaced segments' bases may leave memory now
        if self.folder is not None:
            self.folder.tidy()

    def clear(self) -> None:
        """Forget every scan; the map from now on is the base of the next one (the caller's)."""
        with self._lock:
            self._segments = deque([Segment(0, None, None)])
            self._changes += 1
            self.frozen = 0
            self.frozen_stamp_ns = None
            self.frozen_why = ""
            self.pending = None
        if self.folder is not None:
            self.folder.tidy()

    def restart(self, base: SegmentBase | None, base_position: np.ndarray | None, first_index: int,
                why: str = "") -> None:
        """Forget every scan and begin again from ``base`` (a map loaded from a file without a
        log, a forgotten box); ``why``: what froze the scans before, in words."""
        segment_base = self._new_base(base)
        with self._lock:
            self._changes += 1
            self._segments = deque([Segment(first_index, segment_base, None if base_position is None
                                            else np.array(base_position))])
            self.frozen = first_index
            self.frozen_stamp_ns = None
            self.frozen_why = why
            self.pending = None
        if self.folder is not None:
            self.folder.tidy()

    def copy(self) -> ScanLog:
        """A copy as it is now (segment lists copied; bases and scans shared: they do not change)."""
        other = ScanLog(self.max_scans, self.max_bytes, self.calibration)
        with self._lock:  # one hold: the segments and what they froze agree
            other.frozen, other.frozen_stamp_ns, other.frozen_why = self.frozen, self.frozen_stamp_ns, self.frozen_why
            other.pending = self.pending
            other._segments = deque(self._segment_copies())
            other.folder = self.folder
        if other.folder is not None:
            other.folder.hold(other)
        return other

    def adopt(self, other: ScanLog) -> None:
        """Take ``other``'s segments (a map file's log), keeping this log's bounds and folder (what
        the map file held itself is written there): its oldest segments fall out (frozen) where
        they exceed the bounds."""
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
        self.use_folder(self.folder)

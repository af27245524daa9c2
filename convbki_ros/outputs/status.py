"""What the mapper node has done, safe to update from its threads, and how it is reported.

The node has three kinds of threads: the executor's (clouds and odometry arrive, services
run), the update thread and the publishing thread. Each of them counts something, so every
change goes through one lock. Two reports read the same numbers: the counters line in the
log (every ``stats_period``) and ``/diagnostics`` (``diagnostic_msgs/DiagnosticArray``,
about once a second), whose level says whether the node is healthy:

* OK: every cloud that came was integrated or is on its way;
* WARN: clouds were dropped since the last report, or clouds wait for odometry;
* ERROR: clouds arrive but no usable odometry has come for ``odometry_timeout`` seconds.
"""

from __future__ import annotations

import itertools
import re
import statistics
import threading
import time
from collections import deque
from dataclasses import dataclass, field

OK, WARN, ERROR = 0, 1, 2  # diagnostic_msgs/DiagnosticStatus levels
TIMING_HISTORY = 100  # update and publish times kept for the medians
# Distinct problems the warnings throttle remembers: a source inventing a new frame name for every
# message must not grow it (nor the log) without bound.
MAX_PROBLEM_KEYS = 1000
PLAUSIBLE_DELAY_MS = 3_600_000.0  # odometry "delayed" by more than an hour is stamped in another clock


def problem_key(message: str) -> str:
    """A throttling key for a problem described in words: the message with its numbers blanked,
    so "data holds 10 bytes" and "data holds 12 bytes" are one problem, while a missing field and
    a wrong datatype are two (each gets its own warning)."""
    return re.sub(r"[-+]?\d[\d.eE+-]*", "#", message)


class WarningThrottle:
    """One warning per problem per ``period`` seconds; counts what it held back."""

    def __init__(self, logger, period: float = 5.0):
        self.logger = logger
        self.period = period
        self._last: dict[str, float] = {}
        self._held: dict[str, int] = {}
        self._lock = threading.Lock()

    def warn(self, key: str, message: str, period: float | None = None) -> None:
        now = time.monotonic()
        with self._lock:
            if key not in self._last and len(self._last) >= MAX_PROBLEM_KEYS:
                self._forget_quiet(now)
                if len(self._last) >= MAX_PROBLEM_KEYS:  # a flood of distinct problems: one key for the rest
                    key = "many distinct problems"
            if now - self._last.get(key, -1e9) < (self.period if period is None else period):
                self._held[key] = self._held.get(key, 0) + 1
                return
            held = self._held.pop(key, 0)
            self._last[key] = now
        self.logger.warning(message + (f" ({held} more like this since the last warning)" if held else ""))

    def _forget_quiet(self, now: float) -> None:
        """Forget the problems not warned about for an hour and with nothing held back (call
        with the lock held): their next warning is due anyway."""
        quiet = [key for key, last in self._last.items() if now - last > 3600.0 and not self._held.get(key)]
        for key in quiet:
            del self._last[key]


@dataclass
class Snapshot:
    """The counters at one instant (a consistent copy, read without the lock)."""

    scans_in: int
    integrated: int
    dropped: dict[str, int]
    odometry_in: int
    odometry_rejected: int
    queue: int
    queue_peak: int
    waiting_for_pose: int
    map_voxels: int
    last_update_ms: float
    median_update_ms: float
    last_publish_ms: float
    median_publish_ms: float
    maps_published: int
    median_cycle_ms: float
    map_version: int  # bumped by every change of the map (an update, a load, a reset)
    odometry_delay_ms_median: float = 0.0
    odometry_delay_ms_max: float = 0.0
    odometry_gap_ms_max: float = 0.0
    publishers: dict[str, int] = field(default_factory=dict)  # per input: the publishers its reader has matched
    cycles_published: int = 0  # publish cycles (updates, view, costmap) that sent something
    # False where the node's clock follows the data (use_sim_time: a bag's /clock is set to the
    # stamps it plays), so an arrival minus its stamp measures nothing.
    odometry_delay_measured: bool = True

    @property
    def dropped_total(self) -> int:
        return sum(self.dropped.values())

    def line(self) -> str:
        """The counters line of the log. A figure is left out until it was measured (nothing
        integrated, no map published, no publish cycle, no odometry), never shown as 0."""
        reasons = ", ".join(f"{reason} {count}" for reason, count in sorted(self.dropped.items()))
        parts = [f"scans in {self.scans_in}, integrated {self.integrated}, dropped {self.dropped_total}"
                 f"{f' ({reasons})' if reasons else ''}",
                 f"odometry in {self.odometry_in} (rejected {self.odometry_rejected})", f"queue {self.queue}",
                 f"map voxels {self.map_voxels}"]
        if self.integrated:
            parts.append(f"last update {self.last_update_ms:.0f} ms")
        if self.maps_published:
            parts.append(f"last map publish {self.last_publish_ms:.0f} ms")
        parts.append(f"queue peak {self.queue_peak}")
        if self.cycles_published:
            parts.append(f"cycle median {self.median_cycle_ms:.0f} ms")
        odometry = self.odometry_text()
        return ", ".join(parts + ([odometry] if odometry else []))

    def odometry_text(self) -> str:
        """How the odometry arrives, for the counters line ("" before any has)."""
        if self.odometry_in - self.odometry_rejected <= 0:
            return ""
        gap = f"longest gap between odometry arrivals {self.odometry_gap_ms_max:.0f} ms"
        if not self.odometry_delay_measured:
            return gap
        if abs(self.odometry_delay_ms_median) > PLAUSIBLE_DELAY_MS:
            return f"odometry stamps not in the node's clock (a bag without /clock and use_sim_time?), {gap}"
        return (f"odometry delay median {self.odometry_delay_ms_median:.0f} ms "
                f"(max {self.odometry_delay_ms_max:.0f}), {gap}")


@dataclass
class MapperStatus:
    """Counters of the node, changed from several threads under one lock."""

    scans_in: int = 0
    integrated: int = 0
    dropped: dict[str, int] = field(default_factory=dict)
    odometry_in: int = 0
    odometry_rejected: int = 0
    queue_peak: int = 0
    maps_published: int = 0
    update_ms: deque = field(default_factory=lambda: deque(maxlen=TIMING_HISTORY))
    publish_ms: deque = field(default_factory=lambda: deque(maxlen=TIMING_HISTORY))  # the whole map
    cycle_ms: deque = field(default_factory=lambda: deque(maxlen=TIMING_HISTORY))  # updates and view
    # Per usable odometry message: its arrival in the node's clock minus its stamp (the delivery
    # delay, where the source's stamps and the node's clock agree: a live robot, or a bag played
    # with /clock to a node on use_sim_time), and its arrival in steady time (the longest gap
    # between two arrivals shows odometry held back and delivered in a burst, whatever the clocks).
    odometry_delay_ns: deque = field(default_factory=lambda: deque(maxlen=TIMING_HISTORY))
    odometry_arrival_ns: deque = field(default_factory=lambda: deque(maxlen=TIMING_HISTORY))
    last_cloud_received: float | None = None  # time.monotonic()
    last_odometry_received: float | None = None
    started: float = field(default_factory=time.monotonic)  # reset when the node is ready
    uses_odometry: bool = True  # False: poses come from TF alone (pose_source tf)
    # Per input ("cloud_in", "odom"): how many publishers the node's reader has matched. DDS
    # matches each side of a connection on its own: a player's writer can count this reader
    # while the reader has not yet matched the writer, and what is sent meanwhile is lost.
    publishers: dict[str, int] = field(default_factory=dict)
    cycles_published: int = 0
    odometry_delay_measured: bool = True  # False on use_sim_time (see Snapshot)
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)
    _dropped_at_last_report: int = 0

    def ready(self) -> None:
        """The node subscribed and can take input: time without odometry counts from now."""
        with self._lock:
            self.started = time.monotonic()

    def cloud_received(self) -> None:
        with self._lock:
            self.scans_in += 1
            self.last_cloud_received = time.monotonic()

    def odometry_received(self, usable: bool) -> None:
        with self._lock:
            self.odometry_in += 1
            if usable:
                self.last_odometry_received = time.monotonic()
            else:
                self.odometry_rejected += 1

    def odometry_delay(self, delay_ns: int) -> None:
        """A usable odometry message arrived ``delay_ns`` after its stamp (in the node's clock)."""
        with self._lock:
            self.odometry_delay_ns.append(delay_ns)
            self.odometry_arrival_ns.append(time.monotonic_ns())

    def publishers_matched(self, name: str, count: int) -> None:
        with self._lock:
            self.publishers[name] = count

    def drop(self, reason: str, count: int = 1) -> None:
        if count:
            with self._lock:
                self.dropped[reason] = self.dropped.get(reason, 0) + count

    def queued(self, length: int) -> None:
        with self._lock:
            self.queue_peak = max(self.queue_peak, length)

    def integrated_one(self, update_ms: float) -> None:
        with self._lock:
            self.integrated += 1
            self.update_ms.append(update_ms)

    def published(self, what: str, milliseconds: float) -> None:
        """A publish of ``what`` ("map": the whole map; "cycle": updates and view) took this long."""
        with self._lock:
            if what == "map":
                self.maps_published += 1
                self.publish_ms.append(milliseconds)
            else:
                self.cycles_published += 1
                self.cycle_ms.append(milliseconds)

    def snapshot(self, queue: int, waiting_for_pose: int, map_voxels: int, map_version: int) -> Snapshot:
        with self._lock:
            return Snapshot(
                self.scans_in, self.integrated, dict(self.dropped), self.odometry_in, self.odometry_rejected,
                queue, self.queue_peak, waiting_for_pose, map_voxels,
                self.update_ms[-1] if self.update_ms else 0.0,
                statistics.median(self.update_ms) if self.update_ms else 0.0,
                self.publish_ms[-1] if self.publish_ms else 0.0,
                statistics.median(self.publish_ms) if self.publish_ms else 0.0,
                self.maps_published, statistics.median(self.cycle_ms) if self.cycle_ms else 0.0, map_version,
                *self._odometry_delays(), dict(self.publishers), self.cycles_published,
                self.odometry_delay_measured)

    def _odometry_delays(self) -> tuple[float, float, float]:
        """(median delay, largest delay, longest arrival gap) of the recent odometry, in ms (lock held)."""
        if not self.odometry_delay_ns:
            return 0.0, 0.0, 0.0
        arrivals = list(self.odometry_arrival_ns)
        gap = max((b - a for a, b in itertools.pairwise(arrivals)), default=0)
        return statistics.median(self.odometry_delay_ns) / 1e6, max(self.odometry_delay_ns) / 1e6, gap / 1e6

    def odometry_missing(self, timeout: float) -> tuple[str, float] | None:
        """(what is missing, for how many seconds) while clouds arrive and no usable odometry has
        for ``timeout`` seconds; None otherwise (odometry flows, or no input at all)."""
        if not self.uses_odometry:  # poses from TF alone: no odometry is expected
            return None
        now = time.monotonic()
        with self._lock:
            if self.last_cloud_received is None or now - self.last_cloud_received > timeout:
                return None  # no input at all (nothing played yet, or the bag ended)
            since = now - (self.last_odometry_received or self.started)
            what = "no usable odometry" if self.odometry_in else "no odometry at all"
        return (what, since) if since >= timeout else None

    def health(self, snapshot: Snapshot, odometry_timeout: float) -> tuple[int, str]:
        """Level and message of the next diagnostics report (it remembers the drops reported)."""
        with self._lock:
            new_drops = snapshot.dropped_total - self._dropped_at_last_report
            self._dropped_at_last_report = snapshot.dropped_total
        missing = self.odometry_missing(odometry_timeout)
        if missing:
            return ERROR, f"{missing[0]} for {missing[1]:.1f} s while clouds arrive"
        if new_drops > 0:
            return WARN, f"dropped {new_drops} clouds since the last report"
        if snapshot.waiting_for_pose:
            source = "odometry" if self.uses_odometry else "TF"
            return WARN, f"{snapshot.waiting_for_pose} clouds wait for {source} covering their stamps"
        if snapshot.integrated:
            return OK, "mapping"
        return OK, f"{snapshot.queue} clouds queued, none integrated yet" if snapshot.queue else "waiting for clouds"


def diagnostic_values(snapshot: Snapshot) -> list[tuple[str, str]]:
    """The key-value pairs of the node's diagnostic status (names stable: tools read them)."""
    values = [
        ("scans_in", snapshot.scans_in), ("integrated", snapshot.integrated),
        ("dropped", snapshot.dropped_total),
        *((f"dropped.{reason}", count) for reason, count in sorted(snapshot.dropped.items())),
        ("odometry_in", snapshot.odometry_in), ("odometry_rejected", snapshot.odometry_rejected),
        ("queue", snapshot.queue), ("queue_peak", snapshot.queue_peak),
        ("waiting_for_pose", snapshot.waiting_for_pose), ("map_voxels", snapshot.map_voxels),
        ("update_ms_last", f"{snapshot.last_update_ms:.1f}"), ("update_ms_median", f"{snapshot.median_update_ms:.1f}"),
        ("publish_ms_last", f"{snapshot.last_publish_ms:.1f}"),
        ("publish_ms_median", f"{snapshot.median_publish_ms:.1f}"),
        ("maps_published", snapshot.maps_published), ("map_version", snapshot.map_version),
        ("cycle_ms_median", f"{snapshot.median_cycle_ms:.1f}"),
        ("odometry_delay_ms_median", f"{snapshot.odometry_delay_ms_median:.1f}"),
        ("odometry_delay_ms_max", f"{snapshot.odometry_delay_ms_max:.1f}"),
        ("odometry_gap_ms_max", f"{snapshot.odometry_gap_ms_max:.1f}"),
        *((f"publishers.{name}", count) for name, count in sorted(snapshot.publishers.items())),
    ]
    return [(key, str(value)) for key, value in values]

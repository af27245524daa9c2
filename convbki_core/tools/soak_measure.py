"""The measuring loop of ``soak``: integrate a drive into one mapper back to back and sample,
every few scans, the map's size, the process's memory and the scans' update and query times.

Memory is read as the process sees it (VmRSS), as the store counts it, and as malloc counts
it (glibc's mallinfo2): RSS alone cannot tell a leak from an allocator that keeps freed pages.
"""

from __future__ import annotations

import ctypes
import gc
import math
import os
import statistics
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import numpy as np

from convbki_core.mapper import ConvBKIMapper
from convbki_core.offline import query_ms, update_ms
from convbki_core.tools.cli import UserError

MB = 2**20


def resident_bytes() -> int:
    """Resident set size of this process now (VmRSS of /proc/self/status), in bytes.

    Not the peak (``ru_maxrss``): a leak shows as a current size that keeps rising.
    """
    try:
        with open("/proc/self/status", encoding="ascii") as status:
            for line in status:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    raise UserError("the resident memory of a process can only be read on Linux (/proc/self/status)")


class _MallInfo2(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks",
                                                     "fsmblks", "uordblks", "fordblks", "keepcost")]


def _load_mallinfo2():
    try:
        function = ctypes.CDLL(None).mallinfo2  # glibc 2.33 and later
    except (OSError, AttributeError):
        return None
    function.restype = _MallInfo2
    return function


_MALLINFO2 = _load_mallinfo2()


def malloc_bytes() -> tuple[float, float]:
    """(bytes live in malloc'd blocks, free bytes malloc holds in its arenas), NaN without glibc.

    RSS alone cannot tell a leak from an allocator that keeps freed pages for reuse; the live
    bytes only grow when something still holds the memory.
    """
    if _MALLINFO2 is None:
        return math.nan, math.nan
    info = _MALLINFO2()
    return float(info.uordblks + info.hblkhd), float(info.fordblks)


class OtherLoad:
    """CPU used by other processes on the machine between two calls, in cores (Linux /proc/stat).

    A soak on a shared machine cannot stop others' jobs; this says which rows they slowed.
    """

    def __init__(self) -> None:
        self._last = self._counters()

    @staticmethod
    def _counters() -> tuple[float, float, float] | None:
        try:
            with open("/proc/stat", encoding="ascii") as stat:
                fields = [int(v) for v in stat.readline().split()[1:]]
        except (OSError, ValueError):
            return None
        ticks = os.sysconf("SC_CLK_TCK")
        idle = fields[3] + (fields[4] if len(fields) > 4 else 0)  # idle + iowait
        busy = (sum(fields[:8]) - idle) / ticks  # guest time is already inside user time
        own = os.times()
        return busy, own.user + own.system, time.perf_counter()

    def lap(self) -> float:
        now = self._counters()
        if now is None or self._last is None:
            return math.nan
        busy, own, wall = (a - b for a, b in zip(now, self._last))
        self._last = now
        return max(busy - own, 0.0) / wall if wall > 0 else math.nan


@dataclass
class Checkpoint:
    """One row of the soak table: the state after ``scans`` scans."""

    scans: int
    voxels: int  # voxels with evidence in the whole map (store + window)
    store_voxels: int  # of those, held by the global store (the rest sit in the dense window)
    rss_mb: float  # resident memory of the process
    store_mb: float  # the store's own bytes (arrays + chunk bookkeeping)
    rss_per_voxel_b: float  # rss / voxels: falls as the fixed window and runtime are spread thinner
    rss_growth_per_voxel_b: float  # (rss - rss at the baseline) / (voxels - voxels at the baseline)
    store_per_voxel_b: float  # store bytes / store voxels
    excess_mb: float  # RSS growth since the baseline minus the store's and the scan log's: memory nothing explains
    live_excess_mb: float  # the same for the bytes live in malloc (glibc): what is still referenced
    malloc_free_mb: float  # freed bytes malloc keeps in its arenas instead of returning them
    occupied: int  # median voxels with points per scan (what the update's cost follows)
    update_ms: float  # median voxelise + update of the scans since the previous row
    query_ms: float  # median window move (write-back + fetch) of the same scans
    # 10th percentiles: on a shared machine another process can slow a run of scans several
    # fold; the fastest scans show what the work itself costs.
    update_p10_ms: float
    query_p10_ms: float
    other_cores: float  # CPU cores other processes kept busy during the row (shared machines)
    elapsed_s: float  # wall time since the first scan, including reading the scans
    live_mb: float  # bytes live in malloc'd blocks (glibc's mallinfo2), NaN elsewhere
    log_mb: float = 0.0  # the scan log's bytes (scans and segment copies; bounded by the mapper's scan_log settings)
    log_scans: int = 0  # scans the log holds


@dataclass
class SoakResult:
    """Baseline (right after the first scan: code compiled, window allocated) and the rows."""

    baseline: Checkpoint
    checkpoints: list[Checkpoint] = field(default_factory=list)
    # Per scan after the first: voxelise + update ms, window-move ms, voxels with points, and
    # voxels in the map after the scan, so update time can be plotted against map size.
    update_ms: list[float] = field(default_factory=list)
    query_ms: list[float] = field(default_factory=list)
    occupied: list[int] = field(default_factory=list)
    voxels: list[int] = field(default_factory=list)

    def summary(self) -> dict:
        """The figures the soak is about (first and last row, and how they compare)."""
        if not self.checkpoints:
            return {}
        first, last = self.checkpoints[0], self.checkpoints[-1]
        rows = self.checkpoints
        return {
            "scans": last.scans,
            "voxels": last.voxels,
            "rss_mb": last.rss_mb,
            "rss_growth_mb": last.rss_mb - self.baseline.rss_mb,
            "store_growth_mb": last.store_mb - self.baseline.store_mb,
            "log_mb": last.log_mb, "log_mb_max": max(r.log_mb for r in rows), "log_scans": last.log_scans,
            "excess_mb": last.excess_mb,
            "excess_mb_max": max(r.excess_mb for r in rows),
            "live_excess_mb": last.live_excess_mb,
            "live_excess_mb_max": max(r.live_excess_mb for r in rows),
            "other_cores_max": max(r.other_cores for r in rows),
            "rss_growth_per_voxel_b": {"first": first.rss_growth_per_voxel_b, "last": last.rss_growth_per_voxel_b},
            "store_per_voxel_b": {"first": first.store_per_voxel_b, "last": last.store_per_voxel_b},
            "update_ms": {"first": first.update_ms, "last": last.update_ms,
                          "median": statistics.median(r.update_ms for r in rows),
                          "p10_first": first.update_p10_ms, "p10_last": last.update_p10_ms},
            "query_ms": {"first": first.query_ms, "last": last.query_ms,
                         "median": statistics.median(r.query_ms for r in rows),
                         "p10_first": first.query_p10_ms, "p10_last": last.query_p10_ms},
            # Update cost per voxel with points: the work a scan brings, whatever the map holds.
            "update_us_per_occupied_voxel": {"first": 1e3 * first.update_ms / max(first.occupied, 1),
                                             "last": 1e3 * last.update_ms / max(last.occupied, 1)},
            "voxels_ratio_last_first": last.voxels / max(first.voxels, 1),
            "update_ms_ratio_last_first": last.update_ms / max(first.update_ms, 1e-9),
        }


def _sample(mapper: ConvBKIMapper, scans: int, baseline: Checkpoint | None, update: list[float],
            query: list[float], occupied: list[int], other_cores: float, started: float) -> Checkpoint:
    # Collect cyclic garbage first so a row measures what is still referenced, not what the
    # collector simply has not reached yet.
    gc.collect()
    rss, store = resident_bytes(), mapper.store.resident_bytes
    log = mapper.scan_log
    log_bytes, log_scans = (log.nbytes, len(log)) if log is not None else (0, 0)
    live, held_free = malloc_bytes()
    voxels, store_voxels = len(mapper), len(mapper.store)
    rss_growth = rss - baseline.rss_mb * MB if baseline else 0.0
    # What the map holds: the store's growth and the scan log's (bounded: flat once it is full).
    store_growth = store - baseline.store_mb * MB if baseline else 0.0
    store_growth += log_bytes - baseline.log_mb * MB if baseline else 0.0
    new_voxels = voxels - baseline.voxels if baseline else 0
    return Checkpoint(
        scans=scans, voxels=voxels, store_voxels=store_voxels, rss_mb=rss / MB, store_mb=store / MB,
        rss_per_voxel_b=rss / max(voxels, 1),
        rss_growth_per_voxel_b=rss_growth / new_voxels if new_voxels > 0 else math.nan,
        store_per_voxel_b=store / store_voxels if store_voxels else math.nan,
        excess_mb=(rss_growth - store_growth) / MB,
        live_excess_mb=(live - baseline.live_mb * MB - store_growth) / MB if baseline else 0.0,
        malloc_free_mb=held_free / MB, occupied=int(statistics.median(occupied)) if occupied else 0,
        update_ms=statistics.median(update) if update else math.nan,
        query_ms=statistics.median(query) if query else math.nan,
        update_p10_ms=float(np.percentile(update, 10)) if update else math.nan,
        query_p10_ms=float(np.percentile(query, 10)) if query else math.nan,
        other_cores=other_cores, elapsed_s=time.perf_counter() - started, live_mb=live / MB,
        log_mb=log_bytes / MB, log_scans=log_scans)


def soak(mapper: ConvBKIMapper, frames: Iterable[tuple[np.ndarray, np.ndarray, np.ndarray]], every: int,
         on_checkpoint: Callable[[Checkpoint], None] | None = None) -> SoakResult:
    """Integrate ``frames`` ((points, labels or probabilities, pose) each) into ``mapper`` back to back.

    The baseline is taken after the first scan, once the compiled code is loaded and the window
    has been written to; then one ``Checkpoint`` every ``every`` scans, and one after the last
    scan when the count is not a multiple of ``every``. Time spent sampling is not in any timing.
    """
    if every < 1:
        raise ValueError(f"every must be at least 1, got {every}")
    started = time.perf_counter()
    load = OtherLoad()
    result: SoakResult | None = None
    since = 0  # scans since the previous row
    count = 0

    def row() -> Checkpoint:
        # Measure the load first: the sample's own gc pass is this process's work, not others'.
        other = load.lap()
        checkpoint = _sample(mapper, count, result.baseline, result.update_ms[-since:], result.query_ms[-since:],
                             result.occupied[-since:], other, started)
        result.checkpoints.append(checkpoint)
        if on_checkpoint:
            on_checkpoint(checkpoint)
        return checkpoint

    for points, values, pose in frames:
        integrated = mapper.integrate(points, values, pose)
        count += 1
        if result is None:
            result = SoakResult(_sample(mapper, count, None, [], [], [], load.lap(), started))
            continue
        result.update_ms.append(update_ms(integrated))
        result.query_ms.append(query_ms(integrated))
        result.occupied.append(integrated.occupied_voxels)
        # Voxels grow by the new ones of this scan (a window move only relocates voxels).
        result.voxels.append((result.voxels[-1] if result.voxels else result.baseline.voxels)
                             + integrated.new_voxels)
        since += 1
        if count % every == 0:
            row()
            since = 0
    if result is None:
        raise ValueError("the drive holds no scans")
    if since:
        row()
    return result

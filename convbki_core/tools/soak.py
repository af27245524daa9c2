"""``soak``: map a long drive at full speed and watch memory and update time as the map grows.

A node that maps for hours must hold memory in proportion to the voxels it stores, and its
update must cost what the local window costs, never what the whole map costs. The soak
replays a long synthetic drive (``synth``, a 64-beam LiDAR looping through a street scene)
into one ``ConvBKIMapper`` with the paper's set-up (compound kernel, bounds
[-40,-40,-2.6]..[40,40,2.6] m, 0.2 m voxels) as fast as it can, and every ``--every`` scans
records: stored voxels, resident memory of the process (VmRSS), the store's own bytes,
bytes per stored voxel both ways, and the median update and query times of the scans since
the previous row. It prints the table as it goes and writes CSV, JSON and a PNG plot.

How to read it: the window is a fixed allocation, so after the first scan RSS should grow as
the store grows. ``excess_mb`` is the RSS growth the store does not explain; ``live_excess_mb``
is the same for the bytes malloc reports live, which a leak raises and which freed pages that
the allocator keeps for reuse (``malloc_free_mb``) do not. Update time should stay flat while
the map grows; ``other_cores`` says which rows other processes on the machine slowed.
"""

from __future__ import annotations

import argparse
import csv
import ctypes
import gc
import io
import json
import math
import os
import platform
import resource
import statistics
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from convbki_core.io.atomic import atomic_write_bytes
from convbki_core.mapper import ConvBKIMapper
from convbki_core.tools.bench import PAPER_BOUNDS
from convbki_core.tools.cli import UserError, positive, run

PROG = "soak"
# Seed 7 builds the longest loop of the generator's first sixteen seeds (582 m around 1 x 2
# blocks): at 8 m/s cruise the first lap takes about 850 scans, so the map grows for a good
# part of a 2,000-scan drive before the car revisits streets it has mapped.
DEFAULT_SEED = 7
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
    excess_mb: float  # RSS growth since the baseline minus the store's growth: memory no voxel explains
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
    live, held_free = malloc_bytes()
    voxels, store_voxels = len(mapper), len(mapper.store)
    rss_growth = rss - baseline.rss_mb * MB if baseline else 0.0
    store_growth = store - baseline.store_mb * MB if baseline else 0.0
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
        other_cores=other_cores, elapsed_s=time.perf_counter() - started, live_mb=live / MB)


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
        timing = integrated.timing_ms
        result.update_ms.append(timing["voxelize"] + timing["update"])
        result.query_ms.append(timing["query"])
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


# -- the drive ---------------------------------------------------------------------------------
def ensure_drive(folder: Path, scans: int, seed: int, beams: int = 64, azimuth_steps: int = 2083,
                 quiet: bool = False):
    """A ``synth`` drive of at least ``scans`` scans in ``folder`` (sequence 00), written when missing.

    A drive already there is reused when ``synth.yaml`` says it has the same seed and LiDAR and
    enough scans; an older, shorter or different synthetic drive is rewritten. A folder holding
    anything else is never overwritten.
    """
    from convbki_core.datasets.semantic_kitti import SemanticKittiSequence
    from convbki_core.tools.synth import read_synth_record

    sequence_folder = folder / "sequences" / "00"
    record = read_synth_record(sequence_folder)
    lidar = (record or {}).get("lidar") or {}
    if (record and record.get("seed") == seed and int(record.get("frames", 0)) >= scans
            and lidar.get("beams") == beams and lidar.get("azimuth_steps") == azimuth_steps):
        return SemanticKittiSequence(folder, "00")
    if record is None and sequence_folder.exists() and any(sequence_folder.iterdir()):
        raise UserError(f"{sequence_folder} holds something that is not a synth drive; "
                        "pick an empty or new --drive-dir")
    from convbki_core.tools.synth import main as synth

    if not quiet:
        print(f"{PROG}: simulating a {scans}-scan drive (seed {seed}) into {folder}, about 0.25 s a scan; "
              "it is kept for later runs", file=sys.stderr)
    code = synth(["--out", str(folder), "--sequence", "00", "--frames", str(scans), "--seed", str(seed),
                  "--beams", str(beams), "--azimuth-steps", str(azimuth_steps), "--noise-strength", "0.35",
                  "--force", "--quiet"])
    if code != 0:
        raise UserError(f"the synthetic drive could not be written to {folder}")
    return SemanticKittiSequence(folder, "00")


def drive_frames(dataset, scans: int):
    """(points, input labels, pose) of the first ``scans`` scans of a sequence, read one at a time."""
    for position in range(scans):
        frame = dataset[position]
        yield frame.points, frame.input_values, frame.pose


# -- outputs -----------------------------------------------------------------------------------
# (field, header, width, format) of the printed table; the CSV and JSON hold every field.
COLUMNS = [("scans", "scans", 6, "d"), ("voxels", "voxels", 10, ",d"), ("store_voxels", "in store", 10, ",d"),
           ("rss_mb", "RSS MB", 7, ".0f"), ("store_mb", "store MB", 8, ".1f"),
           ("rss_per_voxel_b", "RSS B/vx", 8, ".0f"),
           ("rss_growth_per_voxel_b", "dRSS B/vx", 9, ".1f"), ("store_per_voxel_b", "store B/vx", 10, ".1f"),
           ("excess_mb", "excess MB", 9, ".1f"), ("live_excess_mb", "live exc", 8, ".1f"),
           ("malloc_free_mb", "free MB", 7, ".1f"), ("occupied", "occupied", 8, ",d"),
           ("update_ms", "update ms", 9, ".1f"), ("update_p10_ms", "p10", 5, ".1f"), ("query_ms", "query ms", 8, ".1f"),
           ("query_p10_ms", "p10", 5, ".1f"), ("other_cores", "others", 6, ".2f")]


def table_header() -> str:
    return " ".join(f"{header:>{width}}" for _, header, width, _ in COLUMNS)


def table_row(row: Checkpoint) -> str:
    values = asdict(row)
    cells = []
    for name, _, width, spec in COLUMNS:
        value = values[name]
        text = "-" if isinstance(value, float) and math.isnan(value) else format(value, spec)
        cells.append(f"{text:>{width}}")
    return " ".join(cells)


def csv_bytes(result: SoakResult) -> bytes:
    buffer = io.StringIO()
    names = list(asdict(result.baseline))
    writer = csv.DictWriter(buffer, fieldnames=names, lineterminator="\n")
    writer.writeheader()
    for row in result.checkpoints:
        writer.writerow({k: (round(v, 4) if isinstance(v, float) else v) for k, v in asdict(row).items()})
    return buffer.getvalue().encode()


def _json_safe(value):
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_json_safe(v) for v in value]
    return value


def plot_png(result: SoakResult, title: str) -> bytes:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = result.checkpoints
    scans = [r.scans for r in rows]
    figure, (memory, per_voxel, timing) = plt.subplots(1, 3, figsize=(17, 4.6), gridspec_kw={"wspace": 0.38})
    memory.plot(scans, [r.rss_mb - result.baseline.rss_mb for r in rows], "o-", label="RSS growth since scan 1")
    memory.plot(scans, [r.store_mb - result.baseline.store_mb for r in rows], "s-", label="store growth")
    memory.plot(scans, [r.excess_mb for r in rows], "^-", label="excess (RSS growth - store growth)")
    memory.set_ylabel("MB")
    voxels = memory.twinx()
    voxels.plot(scans, [r.voxels / 1e6 for r in rows], "--", color="grey", label="stored voxels")
    voxels.set_ylabel("stored voxels [millions]")
    voxels.set_ylim(bottom=0)
    handles = memory.get_legend_handles_labels()[0] + voxels.get_legend_handles_labels()[0]
    memory.legend(handles, [h.get_label() for h in handles], loc="upper left", fontsize=8)
    memory.set_title("memory and map size")
    per_voxel.plot(scans, [r.rss_growth_per_voxel_b for r in rows], "o-", label="RSS growth / new voxels")
    per_voxel.plot(scans, [r.store_per_voxel_b for r in rows], "s-", label="store bytes / store voxels")
    per_voxel.set_ylabel("bytes per voxel")
    per_voxel.legend(fontsize=8)
    per_voxel.set_title("memory per stored voxel")
    # Every scan in drive order: on a shared machine another process slows whole stretches of
    # scans, which shows as a burst in time, while a cost that followed the map would rise with
    # the stored voxels of the left panel.
    scan_numbers = range(2, len(result.update_ms) + 2)
    timing.plot(scan_numbers, result.update_ms, ".", markersize=2, alpha=0.4, label="update (voxelise + update)")
    timing.plot(scan_numbers, result.query_ms, ".", markersize=2, alpha=0.4, label="query (window move)")
    timing.plot(scans, [r.update_ms for r in rows], "o-", color="C0", label="update, median of each row")
    timing.plot(scans, [r.update_p10_ms for r in rows], "v:", color="C0", label="update, 10th percentile")
    timing.plot(scans, [r.query_ms for r in rows], "s-", color="C1", label="query, median of each row")
    timing.set_ylabel("ms per scan")
    if result.update_ms:  # the odd scan that waits on another process would squash the rest
        timing.set_ylim(0, 1.5 * float(np.percentile(result.update_ms + result.query_ms, 99)))
    others = timing.twinx()
    others.plot(scans, [r.other_cores for r in rows], "--", color="grey", label="other processes (right axis)")
    others.set_ylabel("CPU cores used by other processes")
    others.set_ylim(0, max(2.0, os.cpu_count() or 1))
    handles = timing.get_legend_handles_labels()[0] + others.get_legend_handles_labels()[0]
    timing.legend(handles, [h.get_label() for h in handles], fontsize=8, loc="upper left")
    timing.set_title("time per scan")
    for axis in (memory, per_voxel, timing):
        axis.set_xlabel("scans")
        axis.set_ylim(bottom=0)
        axis.grid(alpha=0.3)
    figure.suptitle(title, fontsize=10)
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=100, bbox_inches="tight")
    plt.close(figure)
    return buffer.getvalue()


def write_outputs(result: SoakResult, folder: Path, settings: dict) -> dict[str, Path]:
    """soak.csv, soak.json and soak.png in ``folder``, each written atomically."""
    folder.mkdir(parents=True, exist_ok=True)
    paths = {kind: folder / f"soak.{kind}" for kind in ("csv", "json", "png")}
    atomic_write_bytes(paths["csv"], csv_bytes(result))
    report = {"settings": settings, "summary": result.summary(), "baseline": asdict(result.baseline),
              "checkpoints": [asdict(r) for r in result.checkpoints],
              "per_scan": {"update_ms": [round(t, 3) for t in result.update_ms],
                           "query_ms": [round(t, 3) for t in result.query_ms],
                           "occupied": result.occupied, "voxels": result.voxels}}
    atomic_write_bytes(paths["json"], (json.dumps(_json_safe(report), indent=2) + "\n").encode())
    title = (f"soak: {settings['scans']} scans, seed {settings['seed']}, bounds {settings['bounds']}, "
             f"{settings['machine']}")
    atomic_write_bytes(paths["png"], plot_png(result, title))
    return paths


# -- command line ------------------------------------------------------------------------------
def _bounds(values: Sequence[float]) -> tuple[tuple[float, ...], tuple[float, ...]]:
    low, high = tuple(values[:3]), tuple(values[3:])
    if not all(math.isfinite(v) for v in values) or not all(lo < hi for lo, hi in zip(low, high)):
        raise UserError(f"--bounds must be six finite numbers with each minimum below its maximum, got {values}")
    return low, high


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=PROG, description=__doc__.split("\n\n")[1].replace("\n", " ").replace("``", ""),
        epilog="Columns: voxels = stored voxels (store + window); RSS B/vx = RSS / voxels; dRSS B/vx = RSS growth "
        "since scan 1 / voxels added since; store B/vx = store bytes / voxels in the store; excess MB = RSS growth "
        "minus store growth since scan 1; live exc = the same for bytes live in malloc (a leak raises it, freed "
        "pages malloc keeps do not); free MB = freed bytes malloc holds; occupied = median voxels with points "
        "per scan; update ms = median voxelise + update; query ms = median window move; p10 = their 10th "
        "percentiles (the scans no other process slowed); others = CPU cores other processes kept busy "
        "during the row. "
        "Outputs: OUT/soak.csv, OUT/soak.json, OUT/soak.png. Example: "
        "soak --scans 2000 --out out/soak (the first run simulates the drive, about 5 GB and 10 min)")
    p.add_argument("--scans", default=2000, type=positive(int, "scans"), metavar="N",
                   help="length of the drive in scans, 10 a second (default: %(default)s)")
    p.add_argument("--every", default=100, type=positive(int, "every"), metavar="N",
                   help="scans between two rows of the table (default: %(default)s)")
    p.add_argument("--out", default="out/soak", metavar="DIR", type=Path,
                   help="folder for soak.csv, soak.json and soak.png (default: %(default)s)")
    p.add_argument("--drive-dir", default="out/soak/drive", metavar="DIR", type=Path,
                   help="where the synthetic drive is kept between runs; written when missing, rewritten when "
                   "shorter or made with other settings (default: %(default)s)")
    p.add_argument("--seed", default=DEFAULT_SEED, type=int, metavar="S",
                   help="seed of the synthetic scene and drive; 7 gives a 582 m loop, so the map grows for "
                   "the first ~850 scans and then the car revisits its streets (default: %(default)s)")
    p.add_argument("--beams", default=64, type=positive(int, "beams"), metavar="B",
                   help="LiDAR beams of the simulated drive, at most 64 (default: %(default)s)")
    p.add_argument("--azimuth-steps", default=2083, type=positive(int, "azimuth-steps"), metavar="A",
                   help="LiDAR columns per revolution; 2083 is the HDL-64E, about 116 k points a scan "
                   "(default: %(default)s)")
    p.add_argument("--bounds", nargs=6, type=float, default=[*PAPER_BOUNDS[0], *PAPER_BOUNDS[1]],
                   metavar=("XMIN", "YMIN", "ZMIN", "XMAX", "YMAX", "ZMAX"),
                   help="local window around the sensor in m (default: the paper's -40 -40 -2.6 40 40 2.6)")
    p.add_argument("--kernel", default=None, metavar="YAML",
                   help="kernel file (default: config/kernels/semantic_kitti_compound.yaml, the paper's lengths)")
    return p


def _soak(args: argparse.Namespace) -> int:
    import torch

    from convbki_core.paths import kernel_path

    bounds = _bounds(args.bounds)
    if args.every > args.scans:
        raise UserError(f"--every {args.every} is more than --scans {args.scans}: the table would have no rows")
    if args.beams > 64:
        raise UserError(f"--beams must be at most 64 (the HDL-64E), got {args.beams}")
    if args.out.exists() and not args.out.is_dir():
        raise UserError(f"--out {args.out} exists and is not a folder")
    torch.set_num_threads(os.cpu_count() or 1)
    kernel = Path(args.kernel) if args.kernel else kernel_path("semantic_kitti_compound")
    dataset = ensure_drive(args.drive_dir, args.scans, args.seed, args.beams, args.azimuth_steps)
    if len(dataset) < args.scans:
        raise UserError(f"{args.drive_dir} holds {len(dataset)} scans, fewer than --scans {args.scans}")
    mapper = ConvBKIMapper(kernel, local_bounds=bounds, device="cpu")
    settings = {"scans": args.scans, "every": args.every, "seed": args.seed, "beams": args.beams,
                "azimuth_steps": args.azimuth_steps, "bounds": [*bounds[0], *bounds[1]], "kernel": str(kernel),
                "resolution": mapper.resolution, "window_dims": [int(d) for d in mapper.geometry.dims],
                "window_mb": mapper.window.nbytes / MB, "drive": str(args.drive_dir),
                "machine": f"{platform.machine()}, {os.cpu_count()} cores, torch {torch.__version__}"}
    print(f"{PROG}: {args.scans} scans of {args.drive_dir} at full speed; window "
          f"{'x'.join(map(str, settings['window_dims']))} ({settings['window_mb']:.0f} MB, fixed)", file=sys.stderr)
    from tqdm import tqdm

    bar = tqdm(total=args.scans, unit="scan", desc=PROG, file=sys.stderr, dynamic_ncols=True, mininterval=1.0)

    def frames():
        for frame in drive_frames(dataset, args.scans):
            yield frame
            bar.update(1)

    def show(row: Checkpoint) -> None:
        tqdm.write(table_row(row), file=sys.stdout)
        sys.stdout.flush()

    tqdm.write(table_header(), file=sys.stdout)
    try:
        result = soak(mapper, frames(), args.every, on_checkpoint=show)
    finally:
        bar.close()
    settings["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    settings["baseline_rss_mb"] = result.baseline.rss_mb
    paths = write_outputs(result, args.out, settings)
    summary = result.summary()
    print(f"{PROG}: RSS grew {summary['rss_growth_mb']:.0f} MB and the store {summary['store_growth_mb']:.0f} MB "
          f"for {summary['voxels']:,} voxels; RSS growth per new voxel {summary['rss_growth_per_voxel_b']['first']:.0f}"
          f" -> {summary['rss_growth_per_voxel_b']['last']:.0f} B; update {summary['update_ms']['first']:.1f} -> "
          f"{summary['update_ms']['last']:.1f} ms; wrote {', '.join(str(p) for p in paths.values())}")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the process exit code."""
    return run(PROG, _soak, build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())

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
import math
import os
import platform
import resource
import sys
from collections.abc import Sequence
from pathlib import Path

from convbki_core.config import PAPER_BOUNDS, PAPER_KERNEL
from convbki_core.offline import drive_frames, paper_mapper
from convbki_core.paths import kernel_path
from convbki_core.synth.cached_drive import ensure_drive
from convbki_core.tools.cli import UserError, positive, run
from convbki_core.tools.soak_measure import MB, Checkpoint, soak
from convbki_core.tools.soak_report import table_header, table_row, write_outputs

PROG = "soak"
# Seed 7 builds the longest loop of the generator's first sixteen seeds (582 m around 1 x 2
# blocks): at 8 m/s cruise the first lap takes about 850 scans, so the map grows for a good
# part of a 2,000-scan drive before the car revisits streets it has mapped.
DEFAULT_SEED = 7


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
        "minus store growth since scan 1; log MB = the scan log's bytes (its growth is subtracted from the "
        "excess too); live exc = the same for bytes live in malloc (a leak raises it, freed pages malloc keeps do "
        "not); free MB = freed bytes malloc holds; occupied = median voxels with points "
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
    p.add_argument("--scan-log-megabytes", default=None, type=float, metavar="MB",
                   help="bound of the scan log kept for SLAM corrections (default: the mapper's); a small bound "
                   "shows the log filling, then staying flat while its oldest scans fall out")
    p.add_argument("--scan-log-scans", default=None, type=int, metavar="N",
                   help="the most scans the log keeps (default: the mapper's)")
    p.add_argument("--kernel", default=None, metavar="YAML",
                   help="kernel file (default: config/kernels/semantic_kitti_compound.yaml, the paper's lengths)")
    return p


def _soak(args: argparse.Namespace) -> int:
    import torch

    bounds = _bounds(args.bounds)
    if args.every > args.scans:
        raise UserError(f"--every {args.every} is more than --scans {args.scans}: the table would have no rows")
    if args.beams > 64:
        raise UserError(f"--beams must be at most 64 (the HDL-64E), got {args.beams}")
    if args.out.exists() and not args.out.is_dir():
        raise UserError(f"--out {args.out} exists and is not a folder")
    torch.set_num_threads(os.cpu_count() or 1)
    kernel = Path(args.kernel) if args.kernel else kernel_path(PAPER_KERNEL)
    dataset = ensure_drive(args.drive_dir, args.scans, args.seed, beams=args.beams, azimuth_steps=args.azimuth_steps,
                           on_simulate=lambda: print(
                               f"{PROG}: simulating a {args.scans}-scan drive (seed {args.seed}) into "
                               f"{args.drive_dir}; it is kept for later runs", file=sys.stderr))
    if len(dataset) < args.scans:
        raise UserError(f"{args.drive_dir} holds {len(dataset)} scans, fewer than --scans {args.scans}")
    log_bounds = {name: value for name, value in (("scan_log_megabytes", args.scan_log_megabytes),
                                                   ("scan_log_scans", args.scan_log_scans)) if value is not None}
    if any(value < 0 for value in log_bounds.values()):
        raise UserError(f"the scan log's bounds must be 0 (no bound) or more, got {log_bounds}")
    mapper = paper_mapper(kernel, local_bounds=bounds, **log_bounds)
    log_config = mapper.config.scan_log
    settings = {"scans": args.scans, "every": args.every, "seed": args.seed, "beams": args.beams,
                "azimuth_steps": args.azimuth_steps, "bounds": [*bounds[0], *bounds[1]], "kernel": str(kernel),
                "resolution": mapper.resolution, "window_dims": [int(d) for d in mapper.geometry.dims],
                "window_mb": mapper.window.nbytes / MB, "drive": str(args.drive_dir),
                "scan_log": {"enabled": log_config.enabled, "max_scans": log_config.max_scans,
                             "max_megabytes": log_config.max_megabytes},
                "machine": f"{platform.machine()}, {os.cpu_count()} cores, torch {torch.__version__}"}
    print(f"{PROG}: {args.scans} scans of {args.drive_dir} at full speed; window "
          f"{'x'.join(map(str, settings['window_dims']))} ({settings['window_mb']:.0f} MB, fixed)", file=sys.stderr)
    from tqdm import tqdm

    bar = tqdm(total=args.scans, unit="scan", desc=PROG, file=sys.stderr, dynamic_ncols=True, mininterval=1.0)

    def frames():
        for frame in drive_frames(dataset, range(args.scans)):
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

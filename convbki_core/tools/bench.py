"""bench: the ConvBKI benchmark (the figures are described in docs/benchmark.md).

Inputs are scans of the project's own LiDAR simulation (``synth``: a 64-beam sensor on a
drive through a synthetic street), in the paper's SemanticKITTI set-up: bounds
[-40, -40, -2.6] .. [40, 40, 2.6] m, 0.2 m voxels, f = 5, 20 classes, the compound kernel,
labels as input (and once 20-class probabilities).

Figures (medians over the drive; a shared machine is noisy, so compare ratios from one run):
  voxelize_ms, update_ms (voxelise + ConvBKI update), update_probs_ms, update_free_ms (labels
  with free space on), dense_reference_ms
  (the paper's dense conv3d(groups=C) in torch's default layout, same input, same run),
  speedup_vs_dense, query_ms (move the local window over the global store: the slabs that
  leave are written back, those that enter are fetched; the paper's "query"),
  query_ms_ratio_large_map (query with 10 M stored voxels / with 100 k), encode_ms_per_million
  (map voxels -> PointCloud2 bytes), correction_ms_per_scan (a loop closure moving every scan of
  the drive's first 150, mapped again in a map of its own, per moved scan; _first_: with a new
  window; correction_ratio: over integrating the same scans; correction_free_*: the same with
  free space), scan_log_bytes_per_scan and scan_log_encode_ms (the log a correction reads),
  bytes_per_voxel (resident bytes of the global store, its Python bookkeeping included, over
  the voxels it holds); bytes_per_voxel_with_window
  also counts the fixed dense window over every map voxel,
  publish_ms (one publish cycle of the node after one scan: the changed voxels as point
  records for semantic_map/updates, applied to the chunked whole map, and the view within
  30 m; 1 M voxels stored), publish_ms_ratio_large_map (the same with 10 M / with 1 M),
  updates_bytes_per_scan (bytes of semantic_map/updates one scan makes),
  costmap_ms (one refresh of the planner's rolling costmap over the window after one scan,
  free space on, 1 M voxels stored), costmap_ms_40m (the same for a 40 m grid around the
  sensor, costmap_size 40), costmap_ms_ratio_large_map (the same with 10 M / 1 M),
  scan_to_map_ms (decode a PointCloud2 + pose lookup + update + window move),
  cold_start_s and warm_start_s (the mapper node's process start to "ready", without a
  compiled-kernel cache and with the one set-up leaves) and, for each, the update time the
  node reports for its first and its tenth scan (cold_first_scan_ms, cold_tenth_scan_ms, ...).
encode_ms_per_million, scan_to_map_ms and the start figures run the node's code
(``python -m convbki_ros.tools.bench_ros``, in its own process after the other figures);
without convbki_ros they are reported as not measured.
Then an ablation table (resolution 0.4 / 0.2 / 0.1 m at f = 5; f = 3 / 5 / 7 / 9 at 0.2 m)
with latency and peak memory, and a PNG plot of update time against points per scan and
against filter size.
"""

from __future__ import annotations

import argparse
import gc
import importlib.util
import io
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path

from convbki_core.io.atomic import atomic_write_bytes
from convbki_core.tools.cli import UserError, device_arg, positive, run

PROG = "bench"
TARGETS = {"update_ms": ("<=", 12), "update_probs_ms": ("<=", 50), "update_free_ms": ("<=", 30),
           "speedup_vs_dense": (">=", 50), "query_ms": ("<=", 25), "query_ms_ratio_large_map": ("<=", 1.5),
           "scan_to_map_ms": ("<=", 50), "encode_ms_per_million": ("<=", 40), "bytes_per_voxel": ("<=", 40),
           "publish_ms_ratio_large_map": ("<=", 1.5), "warm_start_s": ("<=", 3), "costmap_ms": ("<=", 5),
           "costmap_ms_ratio_large_map": ("<=", 1.5),
           "cold_first_scan_ratio": ("<=", 1.5), "warm_first_scan_ratio": ("<=", 1.5),
           "correction_ratio": ("<=", 1.5), "correction_free_ratio": ("<=", 1.5)}
CORRECTION_SCANS = 150  # a loop closure that moves a whole 150-scan drive
# The figures of the printed report, in its order (the JSON holds more).
REPORTED = ("voxelize_ms", "update_ms", "update_probs_ms", "update_free_ms", "correction_ms_per_scan",
            "correction_first_ms_per_scan", "correction_ratio", "correction_free_ms_per_scan", "correction_free_ratio",
            "scan_log_bytes_per_scan", "scan_log_encode_ms", "dense_reference_ms", "speedup_vs_dense",
            "query_ms", "query_ms_ratio_large_map", "encode_ms_per_million", "bytes_per_voxel",
            "bytes_per_voxel_with_window", "publish_ms", "publish_ms_10m", "publish_ms_ratio_large_map",
            "updates_bytes_per_scan", "costmap_ms", "costmap_ms_40m", "costmap_ms_10m", "costmap_ms_ratio_large_map",
            "scan_to_map_ms", "cold_start_s", "warm_start_s", "cold_first_scan_ms",
            "cold_tenth_scan_ms", "cold_first_scan_ratio", "warm_first_scan_ms", "warm_tenth_scan_ms",
            "warm_first_scan_ratio")
ROS_FIGURES = "convbki_ros.tools.bench_ros"
NOT_MEASURED = "not measured: convbki_ros is not installed, or its figures failed"
# The figures bench_ros measures, None in the report where it cannot run.
ROS_ENCODE_KEYS = ("encode_ms_per_million", "encoded_voxels")
ROS_SCAN_TO_MAP_KEYS = ("scan_to_map_ms",)
ROS_START_KEYS = ("cold_start_s", "warm_start_s", "cold_first_scan_ms", "cold_tenth_scan_ms", "cold_first_scan_ratio",
                  "warm_first_scan_ms", "warm_tenth_scan_ms", "warm_first_scan_ratio")


def ros_side_figures(args: argparse.Namespace, drive_map: Path | None = None) -> dict:
    """The figures that run the node's ROS-side code, from ``convbki_ros.tools.bench_ros`` in its
    own process (the core never imports convbki_ros), on the same drive and, when given, the map
    bench made of it (``drive_map``, a map file); each None (not measured) where convbki_ros is
    not installed or that process fails."""
    keys = ROS_ENCODE_KEYS + ROS_SCAN_TO_MAP_KEYS + (() if args.skip_start else ROS_START_KEYS)
    if importlib.util.find_spec("convbki_ros") is None:
        return dict.fromkeys(keys)
    with tempfile.TemporaryDirectory(prefix="bench_ros_") as folder:
        out = Path(folder) / "ros.json"
        command = [sys.executable, "-m", ROS_FIGURES, "--drive-dir", str(args.drive_dir), "--scans", str(args.scans),
                   "--repeat", str(args.repeat), "--seed", str(args.seed), "--json", str(out)]
        if args.skip_start:
            command.append("--skip-start")
        if drive_map is not None:
            command += ["--map", str(drive_map)]
        finished = subprocess.run(command, stdin=subprocess.DEVNULL, capture_output=True, text=True)
        if finished.returncode != 0 or not out.exists():
            reason = (finished.stderr.strip().splitlines() or ["no output"])[-1]
            print(f"{PROG}: the ROS-side figures were not measured: {reason}", file=sys.stderr)
            return dict.fromkeys(keys)
        measured = json.loads(out.read_text())
    return {key: measured.get(key) for key in keys}


def save_plot(points_rows: list[dict], ablation_rows: list[dict], path: Path) -> None:
    """Update time against points per scan (left) and against the filter size (right), as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, (left, right) = plt.subplots(1, 2, figsize=(11, 4))
    left.plot([r["points"] / 1e3 for r in points_rows], [r["update_ms"] for r in points_rows], "o-")
    left.set_xlabel("points per scan [thousands]")
    left.set_ylabel("update time [ms] (voxelise + update)")
    left.set_title("update time vs points per scan (0.2 m, f = 5)")
    filters = [r for r in ablation_rows if r["resolution"] == 0.2]
    filters.sort(key=lambda r: r["filter_size"])
    right.plot([r["filter_size"] for r in filters], [r["update_ms"] for r in filters], "o-")
    right.set_xlabel("filter size f")
    right.set_ylabel("update time [ms]")
    right.set_title("update time vs filter size (0.2 m)")
    for axis in (left, right):
        axis.grid(alpha=0.3)
        axis.set_ylim(bottom=0)
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=110, bbox_inches="tight")
    plt.close(figure)
    atomic_write_bytes(path, buffer.getvalue())


def format_report(figures: dict, ablation_rows: list[dict]) -> str:
    """The printed report: each figure against its target, then the ablation table."""
    lines = [f"ConvBKI benchmark: {figures['machine']}, mapping on {figures.get('device', 'cpu')}", "",
             f"{'figure':<30}{'value':>12}  target"]
    for key in REPORTED:
        if key not in figures:
            continue
        value = figures[key]
        if value is None:
            lines.append(f"{key:<30}{'':>12}  {NOT_MEASURED}")
            continue
        target = TARGETS.get(key)
        verdict = ""
        if target:
            op, limit = target
            ok = value <= limit if op == "<=" else value >= limit
            verdict = f"{op} {limit}  {'met' if ok else 'MISSED'}"
        lines.append(f"{key:<30}{value:>12.2f}  {verdict}")
    lines += ["", f"{'resolution':>10} {'f':>3} {'window':>14} {'update ms':>10} {'map MB':>9} {'voxels':>10}"]
    for row in ablation_rows:
        lines.append(f"{row['resolution']:>10.1f} {row['filter_size']:>3} {row['window']:>14} "
                     f"{row['update_ms']:>10.1f} {row['map_memory_mb']:>9.0f} {row['voxels']:>10,}")
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", default="semantic_kitti", choices=("semantic_kitti",),
                   help="benchmark set-up: semantic_kitti = bounds [-40,-40,-2.6]..[40,40,2.6] m, 0.2 m voxels, "
                   "f = 5, 20 classes, compound kernel (default: %(default)s)")
    p.add_argument("--repeat", default=30, type=positive(int, "repeat"), metavar="N",
                   help="scans timed per figure; medians are reported (default: %(default)s)")
    p.add_argument("--json", default=None, metavar="FILE",
                   help="also write the figures (update_ms, query_ms, speedup_vs_dense, ...) as JSON to this file")
    p.add_argument("--scans", default=500, type=positive(int, "scans"), metavar="N",
                   help="length of the synthetic drive mapped before the query figure (default: %(default)s)")
    p.add_argument("--drive-dir", default="out/bench/drive", metavar="DIR",
                   help="where the synthetic drive is cached (default: %(default)s)")
    p.add_argument("--plot", default=None, metavar="PNG",
                   help="plot of update time vs points per scan and vs filter size (default: next to --json, "
                   "else out/bench/bench.png)")
    p.add_argument("--skip-ablation", action="store_true", help="leave out the ablation table and the plot")
    p.add_argument("--skip-start", action="store_true",
                   help="leave out the start figures (they start the mapper node twice, once compiling every kernel)")
    p.add_argument("--seed", type=int, default=5, help="seed of the synthetic drive (default: %(default)s)")
    p.add_argument("--device", default="cpu", type=device_arg,
                   help="torch device to map on: cpu (the compiled CPU path) or cuda[:N] (the torch path, the "
                   "window resident on the GPU); the same figures either way (default: %(default)s)")
    return p


def _bench(args: argparse.Namespace) -> int:
    with tempfile.TemporaryDirectory(prefix="bench_") as scratch:
        return _bench_with_scratch(args, Path(scratch))


def _bench_with_scratch(args: argparse.Namespace, scratch: Path) -> int:
    # The method (torch, numba) loads here, once the arguments are read: --help and a wrong flag
    # answer at once.
    import torch

    from convbki_core.synth.cached_drive import ensure_drive
    from convbki_core.tools.bench_figures import (
        ablation,
        correction_figures,
        costmap_figures,
        dense_reference_figure,
        drive_figures,
        free_space_figure,
        large_map_ratio,
        map_memory_bytes,
        points_sweep,
        probabilities_figure,
        publish_figures,
    )

    torch.set_num_threads(os.cpu_count() or 1)
    dataset = ensure_drive(Path(args.drive_dir), args.scans, args.seed, on_simulate=lambda: print(
        f"{PROG}: simulating a {args.scans}-scan drive into {args.drive_dir} (cached for later runs)",
        file=sys.stderr))
    if len(dataset) < args.scans:
        raise UserError(f"{args.drive_dir} holds {len(dataset)} scans, fewer than --scans {args.scans}")
    figures, mapper, frames = drive_figures(dataset, args.scans, args.repeat, args.device)
    figures["machine"] = f"{platform.machine()}, {os.cpu_count()} cores, torch {torch.__version__}"
    figures["device"] = str(mapper.device) + (f" ({torch.cuda.get_device_name(mapper.device)})"
                                              if mapper.device.type == "cuda" else "")
    figures["cores"] = os.cpu_count()
    store_bytes, window_bytes = map_memory_bytes(mapper)
    figures["stored_voxels"] = len(mapper)
    figures["stored_voxels_in_store"] = len(mapper.store)
    figures["bytes_per_voxel"] = store_bytes / max(len(mapper.store), 1)
    figures["window_mb"] = window_bytes / 1e6
    figures["bytes_per_voxel_with_window"] = (store_bytes + window_bytes) / max(len(mapper), 1)
    drive_map = scratch / "drive_map.npz"  # the ROS-side figures encode this map, not a second mapping of the drive
    mapper.save(drive_map)
    del mapper
    gc.collect()
    figures["update_probs_ms"] = probabilities_figure(frames, min(args.repeat, 10), args.device)
    figures["update_free_ms"] = free_space_figure(dataset, args.scans, args.device)
    correction_scans = min(args.scans, CORRECTION_SCANS)
    figures.update(correction_figures(dataset, correction_scans, args.device))
    figures.update(correction_figures(dataset, correction_scans, args.device, free_space=True))
    figures["dense_reference_ms"] = dense_reference_figure(frames[0], args.repeat, args.device)
    figures["speedup_vs_dense"] = figures["dense_reference_ms"] / figures["update_ms"]
    large = large_map_ratio(frames, min(args.repeat, 15), args.device)
    figures["query_ms_100k"] = large[100_000]["query_ms"]
    figures["query_ms_10m"] = large[10_000_000]["query_ms"]
    figures["query_ms_ratio_large_map"] = figures["query_ms_10m"] / max(figures["query_ms_100k"], 1e-6)
    publishing = publish_figures(frames, min(args.repeat, 15), args.device)
    figures["publish_ms"] = publishing[1_000_000]["publish_ms"]
    figures["publish_ms_10m"] = publishing[10_000_000]["publish_ms"]
    figures["publish_ms_ratio_large_map"] = figures["publish_ms_10m"] / max(figures["publish_ms"], 1e-6)
    figures["updates_bytes_per_scan"] = publishing[1_000_000]["updates_bytes_per_scan"]
    costmap = costmap_figures(frames, min(args.repeat, 15), args.device)
    figures["costmap_ms"] = costmap[1_000_000]["costmap_ms"]
    figures["costmap_ms_10m"] = costmap[10_000_000]["costmap_ms"]
    figures["costmap_ms_40m"] = costmap[1_000_000]["costmap_ms_40m"]
    figures["costmap_ms_ratio_large_map"] = figures["costmap_ms_10m"] / max(figures["costmap_ms"], 1e-6)
    ablation_rows, sweep = [], []
    if not args.skip_ablation:
        ablation_rows = ablation(frames, min(args.repeat, 8), args.device)
        sweep = points_sweep(frames, min(args.repeat, 8), args.device)
        plot = Path(args.plot) if args.plot else (Path(args.json).with_suffix(".png") if args.json
                                                   else Path("out/bench/bench.png"))
        plot.parent.mkdir(parents=True, exist_ok=True)
        save_plot(sweep, ablation_rows, plot)
        figures["plot"] = str(plot)
    figures.update(ros_side_figures(args, drive_map))
    figures["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(format_report(figures, ablation_rows))
    if args.json:
        report = {**figures, "ablation": ablation_rows, "points_sweep": sweep}
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(Path(args.json), (json.dumps(report, indent=2) + "\n").encode())
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the process exit code."""
    return run(PROG, _bench, build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())

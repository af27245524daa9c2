"""``bench``: the ConvBKI benchmark (../shared/BENCHMARKS.md).

Inputs are scans of the project's own LiDAR simulation (``synth``: a 64-beam sensor,
about 115 k points a scan, on a drive through a synthetic street), in the paper's
SemanticKITTI set-up: bounds [-40, -40, -2.6] .. [40, 40, 2.6] m, 0.2 m voxels, f = 5,
20 classes, the compound kernel, labels as input (and once 20-class probabilities).

Figures (medians over the drive; this machine is noisy, so compare ratios from one run):
  voxelize_ms, update_ms (voxelise + ConvBKI update), update_probs_ms, dense_reference_ms
  (the paper's dense conv3d(groups=C) in torch's default layout, same input, same run),
  speedup_vs_dense, query_ms (move the local window over the global store: the slabs that
  leave are written back, those that enter are fetched; the paper's "query"),
  query_ms_ratio_large_map (query with 10 M stored voxels / with 100 k), encode_ms_per_million
  (map voxels -> PointCloud2 bytes), bytes_per_voxel (resident bytes of the global store,
  its Python bookkeeping included, over the voxels it holds, as BENCHMARKS.md defines it;
  bytes_per_voxel_with_window also counts the fixed dense window, 338 MB in this set-up,
  over every map voxel),
  publish_ms (one publish cycle of the node after one scan: the changed voxels as point
  records for semantic_map/updates, applied to the chunked whole map, and the view within
  30 m; 1 M voxels stored), publish_ms_ratio_large_map (the same with 10 M / with 1 M),
  updates_bytes_per_scan (bytes of semantic_map/updates one scan makes),
  scan_to_map_ms (decode a PointCloud2 + pose lookup + update + window move).
Then an ablation table (resolution 0.4 / 0.2 / 0.1 m at f = 5; f = 3 / 5 / 7 / 9 at 0.2 m)
with latency and peak memory, and a PNG plot of update time against points per scan and
against filter size.
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import io
import json
import os
import platform
import resource
import statistics
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import torch

from convbki_core.datasets.labels import load_label_map
from convbki_core.datasets.semantic_kitti import SemanticKittiSequence
from convbki_core.io.atomic import atomic_write_bytes
from convbki_core.mapper import ConvBKIMapper
from convbki_core.paths import kernel_path
from convbki_core.records import change_records, packed_palette, view_records
from convbki_core.shown_map import ShownMap
from convbki_core.tools.cli import UserError, positive, progress, run
from convbki_core.volume import WindowGeometry, transform_points, voxelize

PROG = "bench"
PAPER_BOUNDS = ((-40.0, -40.0, -2.6), (40.0, 40.0, 2.6))
TARGETS = {"update_ms": ("<=", 12), "update_probs_ms": ("<=", 50), "speedup_vs_dense": (">=", 50),
           "query_ms": ("<=", 25), "query_ms_ratio_large_map": ("<=", 1.5), "scan_to_map_ms": ("<=", 50),
           "encode_ms_per_million": ("<=", 40), "bytes_per_voxel": ("<=", 40),
           "publish_ms_ratio_large_map": ("<=", 1.5)}


def median_ms(function: Callable[[], object], repeat: int) -> float:
    times = []
    for _ in range(repeat):
        started = time.perf_counter()
        function()
        times.append(1e3 * (time.perf_counter() - started))
    return statistics.median(times)


def ensure_drive(folder: Path, scans: int, seed: int) -> SemanticKittiSequence:
    """A cached synthetic drive of ``scans`` full-size scans (written once, ~0.15 s a scan)."""
    sequence_folder = folder / "sequences" / "00"
    if not (sequence_folder / "poses.txt").exists() or len(list((sequence_folder / "velodyne").glob("*.bin"))) < scans:
        from convbki_core.tools.synth import main as synth
        from convbki_core.tools.synth import read_synth_record

        if folder.exists() and not folder.is_dir():
            raise UserError(f"--drive-dir {folder}: exists and is not a folder")
        if read_synth_record(sequence_folder) is None and sequence_folder.exists() and any(sequence_folder.iterdir()):
            # synth --force below would replace the scans: never do that to a folder synth did not write.
            raise UserError(f"--drive-dir {folder}: {sequence_folder} holds data that is not a synthetic drive "
                            "(no synth.yaml); pick an empty or new folder")

        print(f"{PROG}: simulating a {scans}-scan drive into {folder} (cached for later runs)", file=sys.stderr)
        errors = io.StringIO()
        with contextlib.redirect_stderr(errors):  # synth's own error line becomes part of bench's one line
            code = synth(["--out", str(folder), "--sequence", "00", "--frames", str(scans), "--seed", str(seed),
                          "--noise-strength", "0.35", "--force", "--quiet"])
        if code != 0:
            reason = (errors.getvalue().strip().splitlines() or ["synth failed"])[-1].removeprefix("synth: error: ")
            raise UserError(f"the synthetic drive could not be written: {reason}")
    return SemanticKittiSequence(folder, "00")


def soft_probabilities(labels: np.ndarray, num_classes: int, rng: np.random.Generator) -> np.ndarray:
    """20-class probability rows peaked at ``labels`` (timing input for the probabilities path)."""
    logits = rng.normal(0.0, 1.0, (labels.size, num_classes)).astype(np.float32)
    logits[np.arange(labels.size), np.clip(labels, 0, num_classes - 1)] += 4.0
    logits -= logits.max(axis=1, keepdims=True)
    probabilities = np.exp(logits)
    return probabilities / probabilities.sum(axis=1, keepdims=True)


def map_memory_bytes(mapper: ConvBKIMapper) -> tuple[int, int]:
    """(bytes of the global store incl. its bookkeeping, bytes of the resident window)."""
    return mapper.store.resident_bytes, mapper.window.nbytes


def drive_figures(dataset: SemanticKittiSequence, scans: int, repeat: int) -> tuple[dict, ConvBKIMapper, list]:
    """Map the drive with the paper's set-up; per-scan timings; the map at the end."""
    mapper = ConvBKIMapper(kernel_path("semantic_kitti_compound"), local_bounds=PAPER_BOUNDS, device="cpu")
    frames_kept, timings = [], []
    for position in progress(range(scans), total=scans, description="drive"):
        frame = dataset[position]
        result = mapper.integrate(frame.points, frame.input_labels, frame.pose)
        timings.append(result.timing_ms)
        if len(frames_kept) < repeat and position >= scans // 2:
            frames_kept.append(frame)
    steady = timings[min(5, len(timings) - 1):]  # the first scans load compiled code and fill the window
    figures = {
        "voxelize_ms": statistics.median(t["voxelize"] for t in steady),
        "update_ms": statistics.median(t["voxelize"] + t["update"] for t in steady),
        "query_ms": statistics.median(t["query"] for t in steady),
        "points_per_scan": int(np.median([len(dataset[p].points) for p in range(0, scans, max(1, scans // 10))])),
        "drive_scans": scans,
    }
    return figures, mapper, frames_kept


def probabilities_figure(frames: list, repeat: int) -> float:
    mapper = ConvBKIMapper(kernel_path("semantic_kitti_compound"), local_bounds=PAPER_BOUNDS, device="cpu")
    rng = np.random.default_rng(0)
    inputs = [(f.points, soft_probabilities(f.input_labels, 20, rng), f.pose) for f in frames[:repeat]]
    mapper.integrate(*inputs[0])  # warm up
    times = []
    for points, probabilities, pose in inputs:
        result = mapper.integrate(points, probabilities, pose)
        times.append(result.timing_ms["voxelize"] + result.timing_ms["update"])
    return statistics.median(times)


def dense_reference_figure(frame, repeat: int) -> float:
    """The paper's dense update as the reference code runs it: conv3d(groups=C), default layout."""
    mapper = ConvBKIMapper(kernel_path("semantic_kitti_compound"), local_bounds=PAPER_BOUNDS, device="cpu",
                           update_path="dense")
    points_map = transform_points(frame.points, frame.pose)
    origin = mapper.geometry.origin_for(frame.pose[:3, 3])

    def dense_update():
        volume = voxelize(points_map, frame.input_labels, origin, mapper.geometry.dims, 0.2, 20)
        with torch.no_grad():
            return mapper.layer(torch.full((20, *mapper.geometry.dims.tolist()), 1e-3), volume.to_dense())

    dense_update()
    return median_ms(dense_update, max(1, min(repeat, 3)))


def far_strip(frames: list, count: int, num_classes: int, prior: float) -> tuple[np.ndarray, np.ndarray]:
    """About ``count`` voxels of a long drive far from the benchmark frames (a street strip), each
    with evidence for 1 to 3 classes like the voxels of a real map: (indices, alpha)."""
    rng = np.random.default_rng(1)
    far = frames[0].pose[:3, 3] / 0.2 + np.array([5000.0, 5000.0, 0.0])
    strip = np.stack([rng.integers(0, count // 600 + 1, count), rng.integers(-150, 150, count),
                      rng.integers(-10, 10, count)], axis=1) + far.astype(np.int64)
    strip = np.unique(strip, axis=0)
    alpha = np.full((len(strip), num_classes), prior, np.float32)
    for _ in range(3):
        rows = np.flatnonzero(rng.random(len(strip)) < 0.6)
        alpha[rows, rng.integers(1, num_classes, len(rows))] += rng.random(len(rows), dtype=np.float32) * 5
    return strip, alpha


def large_map_ratio(frames: list, repeat: int) -> dict:
    """Window moves (query + write-back) with 100 k vs 10 M voxels stored elsewhere in the map."""
    results = {}
    for stored in (100_000, 10_000_000):
        mapper = ConvBKIMapper(kernel_path("semantic_kitti_compound"), local_bounds=PAPER_BOUNDS, device="cpu")
        strip, alpha = far_strip(frames, stored, mapper.num_classes, mapper.prior)
        mapper.store.write(strip, alpha)
        times = []
        for frame in frames[:repeat]:
            result = mapper.integrate(frame.points, frame.input_labels, frame.pose)
            times.append(result.timing_ms["query"])
        results[stored] = {"stored_elsewhere": len(strip), "query_ms": statistics.median(times[1:] or times)}
        del mapper, strip, alpha
        gc.collect()
    return results


def publish_figures(frames: list, repeat: int) -> dict:
    """One publish cycle of the node after one scan's change: the updates (the changed voxels as
    point records, applied to the chunked whole map) and the view (the map within 30 m), with
    1 M and with 10 M voxels stored elsewhere in the map; and the bytes of one scan's updates.
    The whole map is sent at its own, slower period and is not part of the cycle."""
    palette = packed_palette(load_label_map("semantic_kitti").colors)
    results = {}
    for stored in (1_000_000, 10_000_000):
        mapper = ConvBKIMapper(kernel_path("semantic_kitti_compound"), local_bounds=PAPER_BOUNDS, device="cpu",
                               track_changes=True)
        mapper.store.write(*far_strip(frames, stored, mapper.num_classes, mapper.prior))
        shown = ShownMap()
        changes = mapper.take_changes(everything=True)
        shown.apply(changes.indices, change_records(changes.removed, changes.indices, changes.alpha,
                                                    mapper.resolution, palette))
        cycle_ms, update_bytes = [], []
        for frame in frames[:repeat]:
            mapper.integrate(frame.points, frame.input_labels, frame.pose)
            started = time.perf_counter()
            changes = mapper.take_changes()
            records = change_records(changes.removed, changes.indices, changes.alpha, mapper.resolution, palette)
            shown.apply(np.concatenate([changes.removed, changes.indices]), records)
            view_records(mapper.window_records(palette), frame.pose[:3, 3], 30.0, 600_000)
            cycle_ms.append(1e3 * (time.perf_counter() - started))
            update_bytes.append(records.nbytes)
        results[stored] = {"publish_ms": statistics.median(cycle_ms[1:] or cycle_ms),
                           "updates_bytes_per_scan": statistics.median(update_bytes[1:] or update_bytes),
                           "shown_voxels": len(shown)}
        del mapper, shown, changes
        gc.collect()
    return results


def encode_figure(mapper: ConvBKIMapper, repeat: int) -> tuple[float, int]:
    """Map voxels -> PointCloud2 field bytes (the node's /semantic_map encoding), ms per million."""
    from convbki_core.datasets.labels import load_label_map

    try:  # the encoder lives on the ROS side; it imports no rclpy
        from convbki_ros.pointcloud import map_cloud_fields, pack_fields
    except ImportError:  # pragma: no cover - convbki_ros ships with convbki_core
        return float("nan"), 0
    voxels = mapper.voxels()
    colours = load_label_map().colors
    elapsed = median_ms(lambda: pack_fields(map_cloud_fields(voxels, colours)), repeat)
    return elapsed / (len(voxels) / 1e6), len(voxels)


def scan_to_map_figure(frames: list, repeat: int) -> float:
    """The node's whole path for one scan: decode PointCloud2 + pose lookup + update + window move."""
    from convbki_core.datasets.labels import load_label_map

    try:
        from convbki_ros.pointcloud import decode_cloud, pack_fields
        from convbki_ros.pose_buffer import OdometryBuffer
    except ImportError:  # pragma: no cover
        return float("nan")
    label_map = load_label_map()
    mapper = ConvBKIMapper(kernel_path("semantic_kitti_compound"), local_bounds=PAPER_BOUNDS, device="cpu")
    poses = OdometryBuffer()
    clouds = []
    for number, frame in enumerate(frames[:repeat]):
        raw = label_map.to_raw(frame.input_labels).astype(np.uint32)
        layout, point_step, data = pack_fields({"x": frame.points[:, 0], "y": frame.points[:, 1],
                                                "z": frame.points[:, 2], "intensity": frame.remission,
                                                "label": raw})
        clouds.append((number, _CloudView(layout, point_step, data.tobytes(), len(frame.points))))
        poses.add(number * 100_000_000, frame.pose, "velo_link")
        poses.add(number * 100_000_000 + 50_000_000, frame.pose, "velo_link")
    times = []
    for number, cloud in clouds:
        started = time.perf_counter()
        decoded = decode_cloud(cloud, 20)
        pose = poses.lookup(number * 100_000_000 + 10_000_000).pose
        mapper.integrate(decoded.points, label_map.to_learning(decoded.labels), pose)
        times.append(1e3 * (time.perf_counter() - started))
    return statistics.median(times[1:] or times)


class _CloudView:
    """Just the PointCloud2 attributes the decoder reads."""

    def __init__(self, layout, point_step, data, count):
        from types import SimpleNamespace

        self.fields = [SimpleNamespace(name=n, offset=o, datatype=d, count=1) for n, o, d in layout]
        self.point_step, self.row_step, self.data = point_step, point_step * count, data
        self.width, self.height, self.is_bigendian, self.is_dense = count, 1, False, True
        self.header = SimpleNamespace(frame_id="velo_link", stamp=SimpleNamespace(sec=0, nanosec=0))


def ablation(frames: list, repeat: int) -> list[dict]:
    """Latency and peak memory of the update for the paper's resolution and filter-size ablations."""
    rows = []
    settings = [(0.4, 5), (0.2, 5), (0.1, 5), (0.2, 3), (0.2, 7), (0.2, 9)]
    for resolution, filter_size in progress(settings, total=len(settings), description="ablation"):
        gc.collect()
        mapper = ConvBKIMapper(kernel_path("semantic_kitti_compound"), local_bounds=PAPER_BOUNDS, device="cpu",
                               resolution=resolution, filter_size=filter_size)
        times = []
        for frame in frames[:repeat]:
            result = mapper.integrate(frame.points, frame.input_labels, frame.pose)
            times.append(result.timing_ms["voxelize"] + result.timing_ms["update"])
        store_bytes, window_bytes = map_memory_bytes(mapper)
        rows.append({"resolution": resolution, "filter_size": filter_size,
                     "window": "x".join(str(int(d)) for d in WindowGeometry(resolution).dims),
                     "update_ms": statistics.median(times[1:] or times),
                     "map_memory_mb": (store_bytes + window_bytes) / 2**20, "voxels": len(mapper)})
        del mapper
    return rows


def points_sweep(frames: list, repeat: int) -> list[dict]:
    """Update time against points per scan (random subsets of the same scans)."""
    rows = []
    rng = np.random.default_rng(2)
    for fraction in (0.125, 0.25, 0.5, 1.0):
        mapper = ConvBKIMapper(kernel_path("semantic_kitti_compound"), local_bounds=PAPER_BOUNDS, device="cpu")
        times, counts = [], []
        for frame in frames[:repeat]:
            keep = rng.random(len(frame.points)) < fraction
            result = mapper.integrate(frame.points[keep], frame.input_labels[keep], frame.pose)
            times.append(result.timing_ms["voxelize"] + result.timing_ms["update"])
            counts.append(int(keep.sum()))
        rows.append({"points": int(np.median(counts)), "update_ms": statistics.median(times[1:] or times)})
    return rows


def save_plot(points_rows: list[dict], ablation_rows: list[dict], path: Path) -> None:
    import io

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
    lines = [f"ConvBKI benchmark: {figures['machine']}", "",
             f"{'figure':<26}{'value':>12}  target"]
    for key in ("voxelize_ms", "update_ms", "update_probs_ms", "dense_reference_ms", "speedup_vs_dense", "query_ms",
                "query_ms_ratio_large_map", "encode_ms_per_million", "bytes_per_voxel", "bytes_per_voxel_with_window",
                "publish_ms", "publish_ms_10m", "publish_ms_ratio_large_map", "updates_bytes_per_scan",
                "scan_to_map_ms"):
        value = figures[key]
        target = TARGETS.get(key)
        verdict = ""
        if target:
            op, limit = target
            ok = value <= limit if op == "<=" else value >= limit
            verdict = f"{op} {limit}  {'met' if ok else 'MISSED'}"
        lines.append(f"{key:<26}{value:>12.2f}  {verdict}")
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
    p.add_argument("--seed", type=int, default=5, help="seed of the synthetic drive (default: %(default)s)")
    return p


def _bench(args: argparse.Namespace) -> int:
    torch.set_num_threads(os.cpu_count() or 1)
    dataset = ensure_drive(Path(args.drive_dir), args.scans, args.seed)
    if len(dataset) < args.scans:
        raise UserError(f"{args.drive_dir} holds {len(dataset)} scans, fewer than --scans {args.scans}")
    figures, mapper, frames = drive_figures(dataset, args.scans, args.repeat)
    figures["machine"] = f"{platform.machine()}, {os.cpu_count()} cores, torch {torch.__version__}"
    figures["cores"] = os.cpu_count()
    store_bytes, window_bytes = map_memory_bytes(mapper)
    figures["stored_voxels"] = len(mapper)
    figures["stored_voxels_in_store"] = len(mapper.store)
    figures["bytes_per_voxel"] = store_bytes / max(len(mapper.store), 1)
    figures["window_mb"] = window_bytes / 1e6
    figures["bytes_per_voxel_with_window"] = (store_bytes + window_bytes) / max(len(mapper), 1)
    figures["encode_ms_per_million"], figures["encoded_voxels"] = encode_figure(mapper, max(3, args.repeat // 5))
    del mapper
    gc.collect()
    figures["update_probs_ms"] = probabilities_figure(frames, min(args.repeat, 10))
    figures["dense_reference_ms"] = dense_reference_figure(frames[0], args.repeat)
    figures["speedup_vs_dense"] = figures["dense_reference_ms"] / figures["update_ms"]
    large = large_map_ratio(frames, min(args.repeat, 15))
    figures["query_ms_100k"] = large[100_000]["query_ms"]
    figures["query_ms_10m"] = large[10_000_000]["query_ms"]
    figures["query_ms_ratio_large_map"] = figures["query_ms_10m"] / max(figures["query_ms_100k"], 1e-6)
    publishing = publish_figures(frames, min(args.repeat, 15))
    figures["publish_ms"] = publishing[1_000_000]["publish_ms"]
    figures["publish_ms_10m"] = publishing[10_000_000]["publish_ms"]
    figures["publish_ms_ratio_large_map"] = figures["publish_ms_10m"] / max(figures["publish_ms"], 1e-6)
    figures["updates_bytes_per_scan"] = publishing[1_000_000]["updates_bytes_per_scan"]
    figures["scan_to_map_ms"] = scan_to_map_figure(frames, args.repeat)
    ablation_rows, sweep = [], []
    if not args.skip_ablation:
        ablation_rows = ablation(frames, min(args.repeat, 8))
        sweep = points_sweep(frames, min(args.repeat, 8))
        plot = Path(args.plot) if args.plot else (Path(args.json).with_suffix(".png") if args.json
                                                   else Path("out/bench/bench.png"))
        plot.parent.mkdir(parents=True, exist_ok=True)
        save_plot(sweep, ablation_rows, plot)
        figures["plot"] = str(plot)
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

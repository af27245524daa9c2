"""The measurements of ``bench`` that need only the core: update, query, memory, publishing
cost and the ablations, each on the paper's set-up (``offline.paper_mapper``).

Timings are medians; the first scans of a mapper load compiled code and fill the window,
so figures that time a few scans drop the first one where there is more than one.
"""

from __future__ import annotations

import gc
import statistics
import time
from collections.abc import Callable

import numpy as np
import torch

from convbki_core.datasets import SequenceDataset
from convbki_core.geometry.grid import WindowGeometry, transform_points
from convbki_core.geometry.volume import voxelize
from convbki_core.io.labels import load_label_map
from convbki_core.mapper import ConvBKIMapper
from convbki_core.offline import integrate_frames, paper_mapper, query_ms, read_frames, update_ms
from convbki_core.outputs.records import change_records, packed_palette, view_records
from convbki_core.outputs.shown_map import ShownMap
from convbki_core.tools.cli import progress


def median_ms(function: Callable[[], object], repeat: int) -> float:
    """Median wall time of ``repeat`` calls of ``function``, in ms."""
    times = []
    for _ in range(repeat):
        started = time.perf_counter()
        function()
        times.append(1e3 * (time.perf_counter() - started))
    return statistics.median(times)


def steady(times: list[float]) -> float:
    """Median without the first scan, which pays for warming up (unless it is the only one)."""
    return statistics.median(times[1:] or times)


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


def drive_figures(dataset: SequenceDataset, scans: int, repeat: int,
                  device: str = "cpu") -> tuple[dict, ConvBKIMapper, list]:
    """Map the drive with the paper's set-up; per-scan timings; the map at the end; and
    ``repeat`` frames from the second half of the drive for the other figures."""
    mapper = paper_mapper(device=device)
    frames_kept, timings = [], []
    frames = progress(read_frames(dataset, range(scans)), total=scans, description="drive")
    for position, (frame, result) in enumerate(integrate_frames(mapper, frames)):
        timings.append(result.timing_ms)
        if len(frames_kept) < repeat and position >= scans // 2:
            frames_kept.append(frame)
    settled = timings[min(5, len(timings) - 1):]  # the first scans load compiled code and fill the window
    figures = {
        "voxelize_ms": statistics.median(t["voxelize"] for t in settled),
        "update_ms": statistics.median(t["voxelize"] + t["update"] for t in settled),
        "query_ms": statistics.median(t["query"] for t in settled),
        "points_per_scan": int(np.median([len(dataset[p].points) for p in range(0, scans, max(1, scans // 10))])),
        "drive_scans": scans,
    }
    return figures, mapper, frames_kept


def probabilities_figure(frames: list, repeat: int, device: str = "cpu") -> float:
    """Update time with 20-class probabilities as input instead of labels."""
    mapper = paper_mapper(device=device)
    rng = np.random.default_rng(0)
    inputs = [(f.points, soft_probabilities(f.input_labels, 20, rng), f.pose) for f in frames[:repeat]]
    mapper.integrate(*inputs[0])  # warm up
    return statistics.median(update_ms(mapper.integrate(*values)) for values in inputs)


def free_space_figure(dataset: SequenceDataset, scans: int, device: str = "cpu") -> float:
    """Update time with labels and free space on, measured like ``update_ms``: the whole drive
    mapped again with free space, the median from the sixth scan on (the cost of free space
    grows with the evidence the window holds, so a fresh map would understate it)."""
    mapper = paper_mapper(free_space=True, device=device)
    frames = progress(read_frames(dataset, range(scans)), total=scans, description="drive, free space")
    times = [update_ms(result) for _, result in integrate_frames(mapper, frames)]
    return statistics.median(times[min(5, len(times) - 1):])


def correction_figures(dataset: SequenceDataset, scans: int, device: str = "cpu", free_space: bool = False) -> dict:
    """A loop closure's correction of ``scans`` scans (the first of the drive): every logged scan
    moved (a turn of half a degree about the first sensor position and 0.3 m sideways), mapped
    again in a map of its own (``ConvBKIMapper.corrected``): ms per moved scan with a window
    already in memory (as the node's corrections after its first) and with a new one, against
    integrating them (the mean of the same scans' whole integration: voxelise, window move,
    update, free space, log), and the scan log's bytes and encoding time per scan."""
    mapper = paper_mapper(device=device, free_space=free_space)
    frames = progress(read_frames(dataset, range(scans)), total=scans,
                      description=f"correction{', free space' if free_space else ''}")
    timings = [result.timing_ms for _, result in integrate_frames(mapper, frames)]
    logged = mapper.scan_log.scans()
    first = logged[0][1].pose[:3, 3]
    angle = np.radians(0.5)
    turn = np.eye(4)
    turn[:2, :2] = [[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]]
    change = np.eye(4)
    change[:3, 3] = first + [0.0, 0.3, 0.0]
    change = change @ turn
    change[:3, 3] -= change[:3, :3] @ first
    moves = {index: change @ scan.pose for index, scan in logged}
    new, first_result = mapper.corrected(moves)
    _, result = mapper.corrected(moves, reuse=new)
    integrate = statistics.mean(t["total"] for t in timings[1:])
    key = "correction_free" if free_space else "correction"
    figures = {f"{key}_ms_per_scan": 1e3 * result.seconds / result.scans,
               f"{key}_first_ms_per_scan": 1e3 * first_result.seconds / first_result.scans,
               f"{key}_integrate_ms_per_scan": integrate, f"{key}_scans": result.scans}
    figures[f"{key}_ratio"] = figures[f"{key}_ms_per_scan"] / integrate
    if not free_space:
        figures["scan_log_bytes_per_scan"] = sum(scan.nbytes for _, scan in logged) / len(logged)
        figures["scan_log_encode_ms"] = statistics.median(t["log"] for t in timings[1:])
    return figures


def dense_reference_figure(frame, repeat: int, device: str = "cpu") -> float:
    """The paper's dense update as the reference code runs it: conv3d(groups=C), default layout."""
    mapper = paper_mapper(update_path="dense", device=device)
    points_map = transform_points(frame.points, frame.pose)
    origin = mapper.geometry.origin_for(frame.pose[:3, 3])

    def dense_update():
        volume = voxelize(points_map, frame.input_labels, origin, mapper.geometry.dims, 0.2, 20)
        with torch.no_grad():
            prior = torch.full((20, *mapper.geometry.dims.tolist()), 1e-3, device=mapper.device)
            result = mapper.layer(prior, volume.to_dense(mapper.device))
        if mapper.device.type == "cuda":
            torch.cuda.synchronize(mapper.device)  # the time of the work, not of queueing it
        return result

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


def large_map_ratio(frames: list, repeat: int, device: str = "cpu") -> dict:
    """Window moves (query + write-back) with 100 k vs 10 M voxels stored elsewhere in the map."""
    results = {}
    for stored in (100_000, 10_000_000):
        mapper = paper_mapper(device=device)
        strip, alpha = far_strip(frames, stored, mapper.num_classes, mapper.prior)
        mapper.store.write(strip, alpha)
        times = [query_ms(result) for _, result in integrate_frames(mapper, frames[:repeat])]
        results[stored] = {"stored_elsewhere": len(strip), "query_ms": steady(times)}
        del mapper, strip, alpha
        gc.collect()
    return results


def publish_figures(frames: list, repeat: int, device: str = "cpu") -> dict:
    """One publish cycle of the node after one scan's change: the updates (the changed voxels as
    point records, applied to the chunked whole map) and the view (the map within 30 m), with
    1 M and with 10 M voxels stored elsewhere in the map; and the bytes of one scan's updates.
    The whole map is sent at its own, slower period and is not part of the cycle."""
    palette = packed_palette(load_label_map("semantic_kitti").colors)
    results = {}
    for stored in (1_000_000, 10_000_000):
        mapper = paper_mapper(track_changes=True, device=device)
        mapper.store.write(*far_strip(frames, stored, mapper.num_classes, mapper.prior))
        shown = ShownMap()
        changes = mapper.take_changes(everything=True)
        shown.apply(changes.indices, change_records(changes.removed, changes.indices, changes.alpha,
                                                    mapper.resolution, palette))
        cycle_ms, update_bytes = [], []
        for frame, _ in integrate_frames(mapper, frames[:repeat]):
            started = time.perf_counter()
            changes = mapper.take_changes()
            records = change_records(changes.removed, changes.indices, changes.alpha, mapper.resolution, palette)
            shown.apply(np.concatenate([changes.removed, changes.indices]), records)
            view_records(mapper.window_records(palette), frame.pose[:3, 3], 30.0, 600_000)
            cycle_ms.append(1e3 * (time.perf_counter() - started))
            update_bytes.append(records.nbytes)
        results[stored] = {"publish_ms": steady(cycle_ms), "updates_bytes_per_scan": steady(update_bytes),
                           "shown_voxels": len(shown)}
        del mapper, shown, changes
        gc.collect()
    return results


def costmap_figures(frames: list, repeat: int, device: str = "cpu") -> dict:
    """One refresh of the planner's rolling costmap (the car profile's grid over the paper's
    window, read from the window in place, as the node does) after each scan, free space on,
    with 1 M and with 10 M voxels stored elsewhere in the map; and, with 1 M, a refresh of a
    40 m grid centred on the sensor (``costmap_size`` 40), which reads only its own columns."""
    from convbki_core.costmap.grid import rolling_geometry
    from convbki_core.costmap.profile import load_profile
    from convbki_core.costmap.window_pass import grid_of_window
    from convbki_core.paths import traversability_profile

    label_map = load_label_map("semantic_kitti")
    profile = load_profile(traversability_profile("car"), label_map.class_names)
    results = {}
    for stored in (1_000_000, 10_000_000):
        mapper = paper_mapper(free_space=True, device=device)
        mapper.store.write(*far_strip(frames, stored, mapper.num_classes, mapper.prior))
        times, times_40m = [], []
        extent = float(mapper.window.dims[0]) * mapper.resolution
        for frame, _ in integrate_frames(mapper, frames[:repeat]):
            started = time.perf_counter()
            grid_of_window(mapper.window, mapper.resolution, profile, mapper.prior)
            times.append(1e3 * (time.perf_counter() - started))
            if stored == 1_000_000:
                origin, cells = rolling_geometry(frame.pose[:3, 3], mapper.resolution, 40.0, extent)
                started = time.perf_counter()
                grid_of_window(mapper.window, mapper.resolution, profile, mapper.prior, (origin, (cells, cells)))
                times_40m.append(1e3 * (time.perf_counter() - started))
        results[stored] = {"costmap_ms": steady(times), "window_voxels": mapper.window.count()}
        if times_40m:
            results[stored]["costmap_ms_40m"] = steady(times_40m)
        del mapper
        gc.collect()
    return results


def ablation(frames: list, repeat: int, device: str = "cpu") -> list[dict]:
    """Latency and peak memory of the update for the paper's resolution and filter-size ablations."""
    rows = []
    settings = [(0.4, 5), (0.2, 5), (0.1, 5), (0.2, 3), (0.2, 7), (0.2, 9)]
    for resolution, filter_size in progress(settings, total=len(settings), description="ablation"):
        gc.collect()
        mapper = paper_mapper(resolution=resolution, filter_size=filter_size, device=device)
        times = [update_ms(result) for _, result in integrate_frames(mapper, frames[:repeat])]
        store_bytes, window_bytes = map_memory_bytes(mapper)
        rows.append({"resolution": resolution, "filter_size": filter_size,
                     "window": "x".join(str(int(d)) for d in WindowGeometry(resolution).dims),
                     "update_ms": steady(times),
                     "map_memory_mb": (store_bytes + window_bytes) / 2**20, "voxels": len(mapper)})
        del mapper
    return rows


def points_sweep(frames: list, repeat: int, device: str = "cpu") -> list[dict]:
    """Update time against points per scan (random subsets of the same scans)."""
    rows = []
    rng = np.random.default_rng(2)
    for fraction in (0.125, 0.25, 0.5, 1.0):
        mapper = paper_mapper(device=device)
        times, counts = [], []
        for frame in frames[:repeat]:
            keep = rng.random(len(frame.points)) < fraction
            times.append(update_ms(mapper.integrate(frame.points[keep], frame.input_labels[keep], frame.pose)))
            counts.append(int(keep.sum()))
        rows.append({"points": int(np.median(counts)), "update_ms": steady(times)})
    return rows

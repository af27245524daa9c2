"""The torch path on a device against the compiled CPU path: every stage's time, and the maps.

    python scripts/gpu_check.py [--device cuda] [--drive out/gpu/drive] [--scans 150] [--repeat 10] [--out out/gpu]

Writes (or reuses) the benchmark's synthetic drive (its grid: 80 x 80 x 5.2 m at 0.2 m) and
maps its scans on both paths, the compiled CPU path and the torch path on ``--device``, in two
set-ups: the paper's (labels, no free space) and the node's defaults (free space walked on
the device, clamping, the ground rule and the movers' rules). Per set-up it prints a table of
median milliseconds per scan, stage by stage, side by side: voxelise, the window move, the
ConvBKI update, free space, the movers' rules, one costmap refresh (the car's profile, the
node's 40 m grid) and the gather of the window's records that the node publishes; then the
maps' differences: voxels, labels, the largest relative difference of the concentrations,
costmap cells; the same as JSON in OUT/stages.json. Then it runs ``bench --device`` on the same
drive into OUT (not with ``--device cpu``, a dry run of the torch path on the CPU device).

Needs numpy, numba, torch and pyyaml only, so it runs from a checkout on ``PYTHONPATH``.
Exits 2 when the device is not there, 1 when the two paths' maps differ.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

from convbki_core.costmap.device import device_window_grid
from convbki_core.costmap.grid import rolling_geometry
from convbki_core.costmap.profile import load_profile
from convbki_core.costmap.window_pass import grid_of_window
from convbki_core.inference.statistics import dirichlet_statistics
from convbki_core.io.labels import load_label_map
from convbki_core.offline import paper_mapper
from convbki_core.outputs.records import packed_palette
from convbki_core.paths import config_dir
from convbki_core.synth.cached_drive import ensure_drive

BENCH_SEED = 5  # bench's default drive, so that bench reuses the drive written here
CONFIGURATIONS = {
    "paper": {},
    "node defaults": {"free_space": True, "max_concentration": 300.0},
}
STAGES = ("voxelise", "window move", "update", "free space", "movers' rules", "costmap refresh", "publish gather",
          "scan (all)")
COSTMAP_SIZE = 40.0  # m, the node's default costmap


def costmap(mapper, profile, region=None):
    """The costmap as the mapper's path computes it: the compiled column pass, or the device's
    (also for the torch path on the CPU device, which the node would read in place)."""
    window = mapper.window
    if mapper.update_path == "torch":
        return device_window_grid(window.alpha, window.mask, window.origin, mapper.resolution, profile, mapper.prior,
                                  region)
    return grid_of_window(window, mapper.resolution, profile, mapper.prior, region)


def map_drive(frames, device: str, update_path: str, options: dict, profile, palette) -> dict:
    """The drive mapped on one path: per-stage times (ms per scan), the map and its costmap."""
    mapper = paper_mapper(device=device, update_path=update_path, **options)

    def synchronize():
        if mapper.device.type == "cuda":
            torch.cuda.synchronize(mapper.device)

    times = {stage: [] for stage in STAGES}
    extent = float(mapper.geometry.dims[0]) * mapper.resolution
    started = time.perf_counter()
    for frame in frames:
        result = mapper.integrate(frame.points, frame.input_values, frame.pose, frame.input_moving)
        synchronize()
        timing = result.timing_ms
        movers = timing.get("movers", 0.0)
        for stage, value in (("voxelise", timing["voxelize"]), ("window move", timing["query"]),
                             ("update", timing["update"]), ("free space", timing["free"] - movers),
                             ("movers' rules", movers)):
            times[stage].append(value)
        begun = time.perf_counter()
        origin, cells = rolling_geometry(frame.pose[:3, 3], mapper.resolution, COSTMAP_SIZE, extent)
        grid = costmap(mapper, profile, (origin, (cells, cells)))
        synchronize()
        gathered = time.perf_counter()
        mapper.window_records(palette)
        synchronize()
        times["costmap refresh"].append(1e3 * (gathered - begun))
        times["publish gather"].append(1e3 * (time.perf_counter() - gathered))
        times["scan (all)"].append(timing["total"])
    wall = time.perf_counter() - started
    indices, alpha = mapper.items()
    order = np.lexsort(indices.T)
    whole = costmap(mapper, profile)
    skip = min(5, len(frames) - 1)  # the first scans compile and allocate
    return {"mapper": mapper, "indices": indices[order], "alpha": alpha[order], "wall": wall, "grid": whole.values,
            "last_grid": grid.values, "medians": {stage: statistics.median(values[skip:]) if values[skip:] else 0.0
                                                  for stage, values in times.items()}}


def compare(frames, name: str, options: dict, device: str, profile, palette, report: dict) -> bool:
    host = map_drive(frames, "cpu", "fast", options, profile, palette)
    other = map_drive(frames, device, "torch", options, profile, palette)
    print(f"\n{name}: {len(frames)} scans, {len(host['indices']):,} voxels "
          f"(cpu {host['wall']:.1f} s, {device} {other['wall']:.1f} s in all)")
    header = ("stage (median ms per scan)", "cpu (compiled)", f"{device} (torch)", f"cpu / {device}")
    print(f"  {header[0]:<28} {header[1]:>15} {header[2]:>15} {header[3]:>12}")
    for stage in STAGES:
        a, b = host["medians"][stage], other["medians"][stage]
        ratio = f"{a / b:.2f}x" if b > 0 else "-"
        print(f"  {stage:<28} {a:>15.2f} {b:>15.2f} {ratio:>12}")
    if not np.array_equal(host["indices"], other["indices"]):
        common = len({tuple(v) for v in host["indices"]} & {tuple(v) for v in other["indices"]})
        print(f"  DIFFERENT voxels: cpu {len(host['indices']):,}, {device} {len(other['indices']):,}, "
              f"common {common:,}")
        return False
    labels = dirichlet_statistics(host["alpha"]).label, dirichlet_statistics(other["alpha"]).label
    differing = int(np.count_nonzero(labels[0] != labels[1]))
    worst = float(np.max(np.abs(other["alpha"] - host["alpha"]) / host["alpha"])) if len(host["alpha"]) else 0.0
    cells = int(np.count_nonzero(host["grid"] != other["grid"])) if host["grid"].shape == other["grid"].shape \
        else -1
    print(f"  maps: the same voxels; labels differ in {differing} of {len(labels[0]):,}; largest relative "
          f"difference of the concentrations {worst:.2e}; costmap cells differing {cells} of {host['grid'].size:,}",
          flush=True)
    report[name] = {"scans": len(frames), "voxels": len(host["indices"]), "compiled_cpu_ms": host["medians"],
                    "torch_device_ms": other["medians"], "labels_differing": differing,
                    "largest_relative_difference": worst, "costmap_cells_differing": cells}
    return differing == 0 and worst <= 1e-5 and cells == 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda", help="torch device of the torch path (cpu: a dry run)")
    parser.add_argument("--drive", default="out/gpu/drive")
    parser.add_argument("--scans", type=int, default=150)
    parser.add_argument("--repeat", type=int, default=10, help="bench's --repeat")
    parser.add_argument("--out", default="out/gpu")
    parser.add_argument("--skip-bench", action="store_true")
    args = parser.parse_args(argv)
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        print("gpu_check: no CUDA device here", file=sys.stderr)
        return 2
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "the CPU"
    print(f"device: {name}, torch {torch.__version__}, CUDA {torch.version.cuda}", flush=True)
    started = time.perf_counter()
    dataset = ensure_drive(args.drive, args.scans, BENCH_SEED)
    print(f"drive: {args.scans} scans ready in {time.perf_counter() - started:.0f} s", flush=True)
    label_map = load_label_map("semantic_kitti")
    profile = load_profile(config_dir() / "traversability" / "car.yaml", label_map.class_names)
    palette = packed_palette(label_map.colors)
    frames = [dataset[i] for i in range(min(args.scans, len(dataset)))]
    same = True
    report = {"device": name, "torch": torch.__version__, "cuda": torch.version.cuda}
    for setup, options in CONFIGURATIONS.items():
        if options.get("free_space"):
            options = {**options, "ignore_classes": label_map.ignore_classes}
        same &= compare(frames, setup, options, args.device, profile, palette, report)
    Path(args.out).mkdir(parents=True, exist_ok=True)
    (Path(args.out) / "stages.json").write_text(json.dumps(report, indent=1))  # the table, for the note
    if args.skip_bench or device.type == "cpu":
        return 0 if same else 1
    code = subprocess.call([sys.executable, "-m", "convbki_core.tools.bench", "--device", args.device,
                            "--drive-dir", args.drive, "--scans", str(args.scans), "--repeat", str(args.repeat),
                            "--skip-start", "--json", str(Path(args.out) / "bench.json"),
                            "--plot", str(Path(args.out) / "bench.png")])
    return code if same else 1


if __name__ == "__main__":
    sys.exit(main())

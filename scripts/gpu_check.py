"""The GPU path on a machine with CUDA: the same map as the CPU path, and its timings.

    python scripts/gpu_check.py [--drive out/gpu/drive] [--scans 150] [--repeat 10] [--out out/gpu]

Writes (or reuses) the benchmark's synthetic drive, maps its first scans on both paths (the
compiled CPU path and the torch path on ``cuda``) in two configurations: the paper's
(labels, no free space) and the node's defaults (free space, clamping, the movers' rules).
For each it checks that both paths keep the same voxels with the same labels (and prints the
largest relative difference of the concentrations) and prints the median update and
window-move times of each path. Then it runs ``bench --device cuda`` on the same drive
(every benchmark figure but the node's start, which needs ROS, and the ablation table) into
OUT. Needs numpy, numba, torch and pyyaml only, so it runs from a checkout on
``PYTHONPATH``. Exits 2 without CUDA, 1 when the two paths' maps differ.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

from convbki_core.datasets.labels import load_label_map
from convbki_core.offline import paper_mapper
from convbki_core.statistics import dirichlet_statistics
from convbki_core.synth.cached_drive import ensure_drive

BENCH_SEED = 5  # bench's default drive, so that bench reuses the drive written here
CONFIGURATIONS = {
    "paper": {},
    "node defaults": {"free_space": True, "max_concentration": 300.0},
}


def map_drive(frames, device: str, options: dict):
    mapper = paper_mapper(device=device, **options)
    update, move = [], []
    started = time.perf_counter()
    for frame in frames:
        result = mapper.integrate(frame.points, frame.input_values, frame.pose, frame.input_moving)
        if device == "cuda":
            torch.cuda.synchronize()
        update.append(result.timing_ms["voxelize"] + result.timing_ms["update"] + result.timing_ms.get("free", 0.0))
        move.append(result.timing_ms["query"])
    wall = time.perf_counter() - started
    indices, alpha = mapper.items()
    order = np.lexsort(indices.T)
    return mapper, indices[order], alpha[order], statistics.median(update[5:]), statistics.median(move[5:]), wall


def compare(frames, name: str, options: dict) -> bool:
    runs = {}
    for device in ("cpu", "cuda"):
        mapper, indices, alpha, update_ms, move_ms, wall = map_drive(frames, device, options)
        runs[device] = (indices, alpha)
        print(f"{name}, {device} ({mapper.update_path} path): update {update_ms:.2f} ms, window move {move_ms:.2f} ms"
              f" (medians), {len(frames)} scans in {wall:.1f} s, {len(indices):,} voxels", flush=True)
    (cpu_indices, cpu_alpha), (gpu_indices, gpu_alpha) = runs["cpu"], runs["cuda"]
    if not np.array_equal(cpu_indices, gpu_indices):
        common = len({tuple(v) for v in cpu_indices} & {tuple(v) for v in gpu_indices})
        print(f"{name}: DIFFERENT voxels: cpu {len(cpu_indices):,}, cuda {len(gpu_indices):,}, common {common:,}")
        return False
    cpu_labels = dirichlet_statistics(cpu_alpha).label
    gpu_labels = dirichlet_statistics(gpu_alpha).label
    differing = int(np.count_nonzero(cpu_labels != gpu_labels))
    worst = float(np.max(np.abs(gpu_alpha - cpu_alpha) / cpu_alpha))
    print(f"{name}: same voxels; labels differ in {differing} of {len(cpu_labels):,}; "
          f"largest relative difference of the concentrations {worst:.2e}", flush=True)
    return differing == 0 and worst <= 1e-4


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--drive", default="out/gpu/drive")
    parser.add_argument("--scans", type=int, default=150)
    parser.add_argument("--repeat", type=int, default=10, help="bench's --repeat")
    parser.add_argument("--out", default="out/gpu")
    parser.add_argument("--skip-bench", action="store_true")
    args = parser.parse_args(argv)
    if not torch.cuda.is_available():
        print("gpu_check: no CUDA device here", file=sys.stderr)
        return 2
    print(f"device: {torch.cuda.get_device_name(0)}, torch {torch.__version__}", flush=True)
    started = time.perf_counter()
    dataset = ensure_drive(args.drive, args.scans, BENCH_SEED)
    print(f"drive: {args.scans} scans ready in {time.perf_counter() - started:.0f} s", flush=True)
    label_map = load_label_map("semantic_kitti")
    frames = [dataset[i] for i in range(min(args.scans, len(dataset)))]
    same = True
    for name, options in CONFIGURATIONS.items():
        if options.get("free_space"):
            options = {**options, "ignore_classes": label_map.ignore_classes}
        same &= compare(frames, name, options)
    if args.skip_bench:
        return 0 if same else 1
    Path(args.out).mkdir(parents=True, exist_ok=True)
    code = subprocess.call([sys.executable, "-m", "convbki_core.tools.bench", "--device", "cuda",
                            "--drive-dir", args.drive, "--scans", str(args.scans), "--repeat", str(args.repeat),
                            "--skip-start", "--json", str(Path(args.out) / "bench.json"),
                            "--plot", str(Path(args.out) / "bench.png")])
    return code if same else 1


if __name__ == "__main__":
    sys.exit(main())

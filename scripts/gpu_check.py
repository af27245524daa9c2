"""The GPU path on a machine with CUDA: the same map as the CPU path, and its timings.

    .venv/bin/python scripts/gpu_check.py [--drive out/bench/drive] [--scans 200] [--out out/gpu]

Maps the first scans of a drive twice, with the compiled CPU path and with the torch path on
``cuda``, checks that both keep the same voxels with the same labels (concentrations within
1e-5 relative), prints the median update and window-move times of each, then runs
``bench --device cuda`` (every benchmark figure and the ablation table on the GPU) into OUT.
Exits 2 without CUDA.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
from pathlib import Path

import numpy as np
import torch

from convbki_core.datasets.semantic_kitti import SemanticKittiSequence
from convbki_core.pipeline import paper_mapper
from convbki_core.statistics import dirichlet_statistics


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--drive", default="out/bench/drive")
    parser.add_argument("--scans", type=int, default=200)
    parser.add_argument("--out", default="out/gpu")
    args = parser.parse_args(argv)
    if not torch.cuda.is_available():
        print("gpu_check: no CUDA device here", file=sys.stderr)
        return 2
    dataset = SemanticKittiSequence(args.drive, "00")
    frames = [dataset[i] for i in range(min(args.scans, len(dataset)))]
    maps = {}
    for name, options in (("cpu fast", {"device": "cpu"}), ("cuda torch", {"device": "cuda"})):
        mapper = paper_mapper(**options)
        update, query = [], []
        for frame in frames:
            result = mapper.integrate(frame.points, frame.input_labels, frame.pose)
            update.append(result.timing_ms["voxelize"] + result.timing_ms["update"])
            query.append(result.timing_ms["query"])
        indices, alpha = mapper.items()
        order = np.lexsort(indices.T)
        maps[name] = (indices[order], alpha[order])
        print(f"{name}: update {statistics.median(update[5:]):.2f} ms, window move {statistics.median(query[5:]):.2f}"
              f" ms (medians), {len(indices):,} voxels ({mapper.update_path} path)")
    (cpu_indices, cpu_alpha), (gpu_indices, gpu_alpha) = maps["cpu fast"], maps["cuda torch"]
    same = np.array_equal(cpu_indices, gpu_indices)
    print(f"same voxels: {same}")
    if same:
        labels_same = np.array_equal(dirichlet_statistics(cpu_alpha).label, dirichlet_statistics(gpu_alpha).label)
        print(f"labels identical: {labels_same}")
        print(f"largest relative difference: {float(np.max(np.abs(gpu_alpha - cpu_alpha) / cpu_alpha)):.2e}")
    Path(args.out).mkdir(parents=True, exist_ok=True)
    return subprocess.call([sys.executable, "-m", "convbki_core.bench", "--device", "cuda", "--drive-dir", args.drive,
                            "--json", str(Path(args.out) / "bench.json")])


if __name__ == "__main__":
    sys.exit(main())

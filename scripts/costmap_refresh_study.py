"""How much of the window one scan changes: the bound on any incremental costmap refresh.

    .venv/bin/python scripts/costmap_refresh_study.py --dataset out/demo/data [--sequence 00] [--scans 40]

Maps the first scans of a drive with the paper's window (free space on, the shipped
defaults) and, per scan after the first ten, counts the window's columns holding evidence,
the columns that hold a voxel whose class concentrations the scan's update changed (the
columns a cached per-voxel cost would have to read again, all C classes of each), the
columns with any change (free space included), and times one full refresh of the rolling
grid (``grid_of_window``) and one pass that only reads the window's bytes (the floor of any
refresh that reads every class of every column). Prints medians.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

import numpy as np

from convbki_core.costmap.profile import load_profile
from convbki_core.costmap.window_pass import grid_of_window
from convbki_core.datasets.semantic_kitti import SemanticKittiSequence
from convbki_core.memory.window import CHANGED, EVIDENCE
from convbki_core.offline import paper_mapper
from convbki_core.paths import traversability_profile


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", required=True)
    parser.add_argument("--sequence", default="00")
    parser.add_argument("--scans", type=int, default=40)
    args = parser.parse_args(argv)
    dataset = SemanticKittiSequence(args.dataset, args.sequence)
    profile = load_profile(traversability_profile("car"), dataset.label_map.class_names)
    mapper = paper_mapper(free_space=True)
    window = mapper.window
    rows = []
    for position in range(min(args.scans, len(dataset))):
        frame = dataset[position]
        window.mask &= np.uint8(0xFF & ~CHANGED)
        # The update alone: the class concentrations of these voxels change this scan.
        before = window.alpha[1:].copy() if position >= 10 else None
        mapper.integrate(frame.points, frame.input_values, frame.pose)
        if before is None:
            continue
        class_changed = (window.alpha[1:] != before).any(axis=0)
        del before
        evident_columns = ((window.mask & EVIDENCE) != 0).any(axis=2)
        started = time.perf_counter()
        grid_of_window(window, mapper.resolution, profile, mapper.prior)
        refresh_ms = 1e3 * (time.perf_counter() - started)
        started = time.perf_counter()
        float(window.alpha.sum(dtype=np.float32))  # every byte of the window read once
        read_ms = 1e3 * (time.perf_counter() - started)
        rows.append({"evident_columns": int(evident_columns.sum()),
                     "class_changed_columns": int(class_changed.any(axis=2).sum()),
                     "class_changed_voxels": int(class_changed.sum()),
                     "changed_columns": int(((window.mask & CHANGED) != 0).any(axis=2).sum()),
                     "refresh_ms": refresh_ms, "read_ms": read_ms})
    columns = int(np.prod(window.dims[:2]))
    print(f"window {'x'.join(str(int(d)) for d in window.dims)} x {window.alpha.shape[0]} classes "
          f"({window.alpha.nbytes / 2**20:.0f} MB of concentrations), {columns:,} columns; "
          f"medians over {len(rows)} scans:")
    for key in ("evident_columns", "class_changed_columns", "changed_columns"):
        value = statistics.median(r[key] for r in rows)
        print(f"  {key}: {value:,.0f} ({100 * value / columns:.1f} % of the columns)")
    print(f"  class_changed_voxels: {statistics.median(r['class_changed_voxels'] for r in rows):,.0f}")
    print(f"  full refresh: {statistics.median(r['refresh_ms'] for r in rows):.1f} ms; "
          f"reading the window's concentrations once: {statistics.median(r['read_ms'] for r in rows):.1f} ms")
    return 0


if __name__ == "__main__":
    sys.exit(main())

#!/usr/bin/env python3
"""Store query benchmark: does fetching + writing back the local window depend on map size?

Builds two global stores whose voxels inside the paper's local window are identical
(a street-like slab: ground, walls, some clutter, about 100 k voxels) and adds voxels
outside that window to reach the requested totals (default 100 k and 5 M). Rows are what a
map holds: the prior in every class but one to three with evidence. Then times
``query_window`` followed by ``write_window`` of the touched voxels of one scan (each with
more evidence in its strongest class), median of ``--repeat`` runs, and reports the store's
resident bytes per voxel. Prints a table and optionally writes JSON. Reports, never asserts.

    .venv/bin/python scripts/bench_store_query.py [--sizes 100000 5000000] [--repeat 15] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time

import numpy as np

from convbki_core.geometry.grid import WindowGeometry, linear_index
from convbki_core.memory.store import VoxelStore

NUM_CLASSES = 20
PRIOR = np.float32(1e-3)


def street_voxels(rng: np.random.Generator, x_range: tuple[int, int], count: int) -> np.ndarray:
    """Unique global voxel indices of a street strip along x: ground, two walls, clutter."""
    parts = []
    while sum(len(p) for p in parts) < count * 1.2:
        x = rng.integers(x_range[0], x_range[1], count)
        kind = rng.random(count)
        y = np.where(kind < 0.6, rng.integers(-100, 100, count),  # ground
                     np.where(kind < 0.85, rng.choice([-110, 110], count) + rng.integers(-2, 3, count),  # walls
                              rng.integers(-150, 150, count)))  # clutter
        z = np.where(kind < 0.6, rng.integers(-9, -7, count), rng.integers(-9, 12, count))
        parts.append(np.stack([x, y, z], axis=1))
    voxels = np.unique(np.concatenate(parts), axis=0)
    return voxels[rng.permutation(len(voxels))[:count]]


def map_rows(rng: np.random.Generator, count: int) -> np.ndarray:
    """(count, C) float32 rows: the prior, plus evidence in 1 (half the rows), 2 or 3 classes."""
    rows = np.full((count, NUM_CLASSES), PRIOR, np.float32)
    classes = rng.choice([1, 2, 3], count, p=[0.5, 0.3, 0.2])
    for k in range(3):
        chosen = np.flatnonzero(classes > k)
        rows[chosen, rng.integers(0, NUM_CLASSES, len(chosen))] += rng.random(len(chosen), dtype=np.float32) * 9
    return rows


def build_store(total: int, window_voxels: np.ndarray, rng: np.random.Generator) -> VoxelStore:
    store = VoxelStore(NUM_CLASSES, prior=PRIOR)
    store.write(window_voxels, map_rows(rng, len(window_voxels)))
    remaining = total - len(window_voxels)
    start = 1000  # beyond the window (which spans x in [-200, 200))
    while remaining > 0:
        batch = min(remaining, 1_000_000)
        length = max(batch // 800, 1)
        outside = street_voxels(rng, (start, start + length), batch)
        store.write(outside, map_rows(rng, len(outside)))
        remaining -= len(outside)
        start += length
    return store


def time_query(store: VoxelStore, geometry: WindowGeometry, touched: np.ndarray, repeat: int) -> dict:
    origin = geometry.origin_for(np.zeros(3))
    dims = geometry.dims
    touched_linear = np.unique(linear_index(touched - origin, dims))
    query_ms, write_ms = [], []
    for _ in range(repeat):
        started = time.perf_counter()
        linear, alpha = store.query_window(origin, dims)
        fetched = time.perf_counter()
        position = np.minimum(np.searchsorted(linear, touched_linear), len(linear) - 1)
        rows = alpha[position]
        rows[np.arange(len(rows)), rows.argmax(axis=1)] += 0.01
        store.write_window(origin, dims, touched_linear, rows)
        written = time.perf_counter()
        query_ms.append(1e3 * (fetched - started))
        write_ms.append(1e3 * (written - fetched))
    return {"stored_voxels": len(store), "window_voxels": len(linear), "written_voxels": len(touched_linear),
            "query_ms": statistics.median(query_ms), "write_back_ms": statistics.median(write_ms),
            "query_plus_write_ms": statistics.median(q + w for q, w in zip(query_ms, write_ms)),
            "bytes_per_voxel": store.resident_bytes / max(len(store), 1)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", type=int, nargs="+", default=[100_000, 5_000_000],
                        help="total stored voxels of each map (default: 100000 5000000)")
    parser.add_argument("--window-voxels", type=int, default=100_000, help="stored voxels inside the window")
    parser.add_argument("--repeat", type=int, default=15, help="timed repetitions per size (median reported)")
    parser.add_argument("--json", help="also write the results to this JSON file")
    args = parser.parse_args(argv)
    if any(size < args.window_voxels for size in args.sizes):
        parser.error("every size must be at least --window-voxels")
    geometry = WindowGeometry(0.2)
    rng = np.random.default_rng(0)
    window_voxels = street_voxels(rng, (-200, 200), args.window_voxels)
    touched = window_voxels[rng.random(len(window_voxels)) < 0.5]
    results = []
    for size in args.sizes:
        store = build_store(size, window_voxels, np.random.default_rng(1))
        results.append(time_query(store, geometry, touched, args.repeat))
        del store
    print(f"{'stored voxels':>14} {'in window':>10} {'written':>8} {'query ms':>9} {'write ms':>9} {'total ms':>9} "
          f"{'B/voxel':>8}")
    for r in results:
        print(f"{r['stored_voxels']:>14,} {r['window_voxels']:>10,} {r['written_voxels']:>8,} {r['query_ms']:>9.1f} "
              f"{r['write_back_ms']:>9.1f} {r['query_plus_write_ms']:>9.1f} {r['bytes_per_voxel']:>8.1f}")
    ratio = results[-1]["query_plus_write_ms"] / results[0]["query_plus_write_ms"]
    print(f"ratio largest / smallest map: {ratio:.2f}")
    if args.json:
        with open(args.json, "w") as handle:
            json.dump({"results": results, "ratio_largest_to_smallest": ratio}, handle, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())

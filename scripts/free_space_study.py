"""Free space on a drive with movers: trail voxels and mIoU with and without it, and a picture.

    .venv/bin/python scripts/free_space_study.py --dataset out/movers11 [--sequence 00] [--out out/free_space]

Maps the sequence twice with the same kernel (free space off, then on) under the paper's
protocol, prints a table (mIoU, trail voxels, shown voxels, update time) and writes
OUT/free_space.png: the same stretch of street from above, without and with free space,
around the place where the most moving points were seen (movable classes in colour).
OUT/free_space.json holds the figures.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from convbki_core.config import DEFAULTS
from convbki_core.datasets.semantic_kitti import SemanticKittiSequence
from convbki_core.geometry.grid import transform_points
from convbki_core.io.atomic import atomic_write_bytes
from convbki_core.paths import kernel_path
from convbki_core.tools.evaluate_run import evaluate_kernel
from convbki_core.tools.plots import _pyplot


def busiest_place(dataset: SemanticKittiSequence, positions: range, half_width: float) -> np.ndarray:
    """(x, y) of the square of ``2 * half_width`` metres that saw the most moving points."""
    points = [transform_points(f.points[f.moving], f.pose)[:, :2] for f in (dataset[p] for p in positions)]
    moving = np.concatenate(points)
    cells = np.floor(moving / (2 * half_width)).astype(np.int64)
    keys, counts = np.unique(cells, axis=0, return_counts=True)
    return (keys[counts.argmax()] + 0.5) * 2 * half_width


def street_raster(voxels, centre: np.ndarray, half_width: float, movable: tuple[int, ...], colours: np.ndarray):
    """Top-down picture of the square around ``centre``: every shown voxel's column in light
    grey, and on top of it the columns holding a voxel of a movable class, in its colour (so a
    trail shows even where the road under it holds more evidence)."""
    size = round(2 * half_width / 0.2)
    rgb = np.ones((size, size, 3))
    shown = voxels.label != 0
    cells = np.floor((voxels.centres[:, :2] - (centre - half_width)) / 0.2).astype(np.int64)
    inside = shown & (cells >= 0).all(axis=1) & (cells < size).all(axis=1)
    rgb[cells[inside, 1], cells[inside, 0]] = 0.85
    mover = inside & np.isin(voxels.label, movable)
    rgb[cells[mover, 1], cells[mover, 0]] = colours[voxels.label[mover]] / 255.0
    extent = [centre[0] - half_width, centre[0] + half_width, centre[1] - half_width, centre[1] + half_width]
    return rgb, extent


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", required=True)
    parser.add_argument("--sequence", default="00")
    parser.add_argument("--out", default="out/free_space")
    parser.add_argument("--half-width", type=float, default=25.0, help="half the picture's side in metres")
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    dataset = SemanticKittiSequence(args.dataset, args.sequence)
    positions = range(len(dataset))
    runs = {}
    for free_space in (False, True):
        run = evaluate_kernel(dataset, positions, kernel_path("semantic_kitti_compound"),
                              DEFAULTS.replace(device="cpu", free_space=free_space), None, None)
        voxels = run.mapper.voxels()
        runs[free_space] = (run, voxels)
    figures = {}
    for free_space, (run, voxels) in runs.items():
        figures["on" if free_space else "off"] = {
            "miou": run.map_scores.miou(), "trail_voxels": run.trail_voxels,
            "shown_voxels": int(np.count_nonzero(voxels.label != 0)),
            "update_ms_median": float(np.median(run.update_ms))}
    off, on = figures["off"], figures["on"]
    print(f"{'free space':<12}{'mIoU':>8}{'trail voxels':>14}{'shown voxels':>14}{'update ms':>11}")
    for name, row in figures.items():
        print(f"{name:<12}{row['miou']:>8.4f}{row['trail_voxels']:>14,}{row['shown_voxels']:>14,}"
              f"{row['update_ms_median']:>11.1f}")
    if off["trail_voxels"]:
        print(f"trail voxels with free space: {100 * on['trail_voxels'] / off['trail_voxels']:.1f} % of plain")

    centre = busiest_place(dataset, positions, args.half_width)
    plt = _pyplot()
    figure, axes = plt.subplots(1, 2, figsize=(14, 7.4))
    label_map = dataset.label_map
    for axis, free_space in zip(axes, (False, True)):
        run, voxels = runs[free_space]
        rgb, extent = street_raster(voxels, centre, args.half_width, label_map.movable_classes, label_map.colors)
        axis.imshow(rgb, origin="lower", extent=extent, interpolation="nearest")
        row = figures["on" if free_space else "off"]
        axis.set_title(f"free space {'on' if free_space else 'off'}: {row['trail_voxels']:,} trail voxels, "
                       f"mIoU {row['miou']:.3f}")
        axis.set_xlabel("x [m]")
        axis.set_ylabel("y [m]")
    figure.suptitle(f"{args.dataset} sequence {args.sequence}, where the most moving points were seen: voxels of "
                    "movable classes in colour, everything else grey")
    figure.tight_layout()
    figure.savefig(out / "free_space.png", dpi=110)
    atomic_write_bytes(out / "free_space.json", (json.dumps(figures, indent=2) + "\n").encode())
    print(f"picture: {out / 'free_space.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

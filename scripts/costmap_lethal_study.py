"""Where the costmap loses lethal recall, and what growing its lethal cells by one cell would give.

    .venv/bin/python scripts/costmap_lethal_study.py --dataset out/costmap61 [--sequence 00] [--profile car]

Maps the drive as ``evaluate --costmap-report`` does (shipped defaults), builds the map's and
the ground truth's grids, and prints:

* the ground-truth lethal cells the map misses (over cells both observed): how the map calls
  them, how many the projected-occupancy baseline misses too, the share that touch a cell the
  map calls lethal, the ground-truth class most frequent in their columns, and the ground-truth
  points per column;
* the scores (free precision, lethal recall and precision, costly recall, paths crossing a
  ground-truth lethal cell, paths within 5 % of the truth's length) of the map's grid as it is
  and with every lethal cell grown into its 8 neighbours (what a planner's inflation of one
  cell does), for comparison. The product does not grow cells: Nav2's inflation layer does.
"""

from __future__ import annotations

import argparse
import collections

import numpy as np

from convbki_core.config import DEFAULTS
from convbki_core.costmap.profile import LETHAL, load_profile
from convbki_core.datasets.semantic_kitti import SemanticKittiSequence
from convbki_core.measures.costmap_eval import (
    GroundTruthVoxels,
    grids_for,
    group_of,
    planning_check,
    road_cells,
    score_grid,
)
from convbki_core.paths import kernel_path, traversability_profile
from convbki_core.tools.evaluate_run import evaluate_kernel

FREE, COSTLY, LETHAL_GROUP = 0, 1, 2


def grown(values: np.ndarray) -> np.ndarray:
    """``values`` with every lethal cell grown into its 8 neighbours (observed cells only)."""
    lethal = values >= LETHAL
    around = lethal.copy()
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            around |= np.roll(np.roll(lethal, dy, 0), dx, 1)
    return np.where(around & (values >= 0), LETHAL, values).astype(values.dtype)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", required=True)
    parser.add_argument("--sequence", default="00")
    parser.add_argument("--profile", default="car")
    args = parser.parse_args(argv)
    dataset = SemanticKittiSequence(args.dataset, args.sequence)
    label_map = dataset.label_map
    profile = load_profile(traversability_profile(args.profile), label_map.class_names)
    truth = GroundTruthVoxels(label_map.num_classes, 0.2)
    run = evaluate_kernel(dataset, range(len(dataset)), kernel_path("semantic_kitti_compound"),
                          DEFAULTS.replace(device="cpu"), None, None, show_progress=False, truth_voxels=truth)
    indices, alpha = run.mapper.items()
    grids = grids_for(indices, alpha, truth, run.mapper.resolution, run.mapper.prior, profile)
    mine, theirs, baseline = (group_of(grids[name].values) for name in ("map", "truth", "baseline"))
    observed_lethal = (theirs == LETHAL_GROUP) & (mine >= 0)
    missed = observed_lethal & (mine != LETHAL_GROUP)
    print(f"ground-truth lethal cells observed by both: {int(observed_lethal.sum()):,}; the map misses "
          f"{int(missed.sum()):,} (costly {int((missed & (mine == COSTLY)).sum()):,}, free "
          f"{int((missed & (mine == FREE)).sum()):,}); the baseline misses "
          f"{int((missed & (baseline >= 0) & (baseline != LETHAL_GROUP)).sum()):,} of them")
    touching = grown(grids["map"].values) >= LETHAL
    print(f"missed cells touching a cell the map calls lethal: {100 * float(np.mean(touching[missed])):.0f} %")
    columns: dict[tuple[int, int], list[np.ndarray]] = collections.defaultdict(list)
    for (x, y, _), counts in zip(*truth.items(), strict=True):
        columns[(int(x), int(y))].append(counts)
    origin = grids["truth"].origin
    dominant, points = collections.Counter(), []
    for row, column in np.argwhere(missed):
        counts = np.sum(columns.get((int(column + origin[0]), int(row + origin[1])), [np.zeros(len(alpha[0]))]),
                        axis=0)
        points.append(float(counts.sum()))
        counts[list(profile.ground_classes)] = 0
        counts[0] = 0
        if counts.any():
            dominant[label_map.class_names[int(counts.argmax())]] += 1
    print(f"ground-truth points per missed column: median {np.median(points):.0f}; most frequent obstacle class: "
          + ", ".join(f"{name} {count}" for name, count in dominant.most_common(5)))
    road = road_cells(truth, grids["truth"], label_map.class_names.index("road"))
    for name, values in (("map", grids["map"].values), ("map, lethal grown by one cell", grown(grids["map"].values))):
        scores = score_grid(values, grids["truth"].values)
        check = planning_check(values, grids["truth"].values, road).summary()
        percent = {key: "-" if value is None else f"{100 * value:.1f}" for key, value in (
            ("free", scores.precision["free"]), ("lethal_recall", scores.recall["lethal"]),
            ("lethal_precision", scores.precision["lethal"]), ("costly", scores.recall["costly"]),
            ("within", check["within_5_percent"]))}
        print(f"{name}: free precision {percent['free']}, lethal recall {percent['lethal_recall']}, lethal precision "
              f"{percent['lethal_precision']}, costly recall {percent['costly']}, paths crossing truth-lethal "
              f"{check['crossing_truth_lethal']}, within 5 % {percent['within']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

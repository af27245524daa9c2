"""``evaluate``'s computation: one kernel's run over a sequence, every frame scored as it is
integrated (the paper's protocol, docs/evaluation.md), and on a drift drive the maps without
correction, corrected and from scratch.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from convbki_core.config import MapperConfig
from convbki_core.datasets import DatasetError
from convbki_core.datasets.semantic_kitti import SemanticKittiSequence
from convbki_core.geometry.grid import transform_points
from convbki_core.io.kernel_file import load_kernel_file
from convbki_core.mapper import ConvBKIMapper
from convbki_core.measures.metrics import ConfusionMatrix
from convbki_core.measures.trails import StaticCoverage, SweptSpace
from convbki_core.measures.uncertainty import (
    CalibrationStats,
    MapCalibration,
    input_distribution,
    tempered_distribution,
)
from convbki_core.offline import map_frame_labels
from convbki_core.tools.cli import UserError, progress
from convbki_core.warm_up import warm_up


@dataclass
class KernelRun:
    """The outcome of mapping one sequence with one kernel."""

    kernel_file: str
    kernel: str
    map_scores: ConfusionMatrix
    update_ms: list[float] = field(default_factory=list)
    query_ms: list[float] = field(default_factory=list)
    mapper: ConvBKIMapper | None = None
    trail_voxels: int | None = None  # None: the ground truth marks no moving objects
    static_coverage: float | None = None  # share of every tenth scan's static points the final map shows
    moving_labels_used: bool = False  # some frame's input marked moving points, and they were used
    # The same protocol on the points the ground truth marks as moving only: input and map.
    moving_input_scores: ConfusionMatrix | None = None
    moving_map_scores: ConfusionMatrix | None = None
    # ... and on the points it does not mark as moving (parked and standing objects, everything
    # static): the movable classes' IoU there says whether the map keeps what did not move.
    static_input_scores: ConfusionMatrix | None = None
    static_map_scores: ConfusionMatrix | None = None
    calibration: MapCalibration | None = None  # the map's uncertainty on the scored points


def write_label_file(path: Path, learning_labels: np.ndarray, label_map) -> None:
    """One submission file: uint32 raw ids (learning_map_inv), file order kept.

    Written plainly: the command writes into a staging folder that becomes visible only
    when the whole run succeeded (``NewOutputs``).
    """
    path.write_bytes(label_map.to_raw(learning_labels).astype("<u4").tobytes())


def evaluate_kernel(dataset: SemanticKittiSequence, positions: Sequence[int], kernel_file: str | Path,
                    mapper_config: MapperConfig, input_scores: ConfusionMatrix | None, labels_folder: Path | None,
                    show_progress: bool = True, input_calibration: CalibrationStats | None = None,
                    tempered_calibration: CalibrationStats | None = None, truth_voxels=None,
                    moving_labels: bool = True, input_voxels=None) -> KernelRun:
    """Map ``positions`` of ``dataset`` with one kernel and score every frame as it is integrated.

    ``input_scores`` (when given) also receives the input segmentation's confusion counts, and
    ``input_calibration`` (when given) the input's class probabilities (frames without any are skipped),
    and ``tempered_calibration`` (when given) the same calibrated by the kernel's temperature;
    the run's ``calibration`` measures the map's class distributions on the scored points;
    ``labels_folder`` (when given, an existing folder) receives one NNNNNN.label per frame.
    Where the ground truth marks moving objects, the run also counts the map's trail voxels.
    ``mapper_config``: how to map (the dataset's label map decides the ignored and movable classes).
    ``truth_voxels`` (a ``costmap_eval.GroundTruthVoxels``, when given) receives every frame's
    ground-truth points, for the costmap's report, and ``input_voxels`` (the same, when given) the
    input's labels of those points. ``moving_labels``: where the input marks
    moving points (raw ids such as 252-259), they are evidence for their scan only
    (``present_movers``); False maps them as their static classes.
    """
    config = load_kernel_file(kernel_file)
    label_map = dataset.label_map
    if config.num_classes != label_map.num_classes:
        raise UserError(f"{kernel_file}: kernel has {config.num_classes} classes, the dataset {label_map.num_classes}")
    mapper_config = mapper_config.replace(ignore_classes=label_map.ignore_classes,
                                          movable_classes=label_map.movable_classes,
                                          ground_classes=label_map.ground_classes)
    mapper = ConvBKIMapper(mapper_config, config)
    if mapper.scan_log is not None:  # map_tool correct reads a poses file with the scans' calibration
        mapper.scan_log.calibration = dataset.calibration
    warm_up(mapper)  # every kernel compiled (or loaded) before the first timed frame
    run_result = KernelRun(str(kernel_file), config.kernel, ConfusionMatrix(label_map.num_classes,
                                                                             label_map.ignore_classes), mapper=mapper)
    run_result.calibration = MapCalibration(label_map.num_classes, label_map.ignore_classes,
                                            free_space=mapper.free_space)
    run_result.static_input_scores = ConfusionMatrix(label_map.num_classes, label_map.ignore_classes)
    run_result.static_map_scores = ConfusionMatrix(label_map.num_classes, label_map.ignore_classes)
    out_folder = labels_folder
    swept = SweptSpace(mapper.resolution)
    coverage = StaticCoverage(mapper.resolution)
    frames = (dataset[position] for position in positions)
    if show_progress:
        frames = progress(frames, total=len(positions), description=f"{Path(kernel_file).stem}")
    for frame in frames:
        if frame.ground_truth is None:
            raise DatasetError(f"{dataset.folder}: no labels/ folder, so there is no ground truth to score against")
        input_labels = frame.input_labels if frame.input_labels is not None else frame.probabilities.argmax(axis=1)
        moving = frame.input_moving if moving_labels else None
        run_result.moving_labels_used |= moving is not None
        result = mapper.integrate(frame.points, frame.input_values, frame.pose, moving,
                                  stamp_ns=round(frame.stamp * 1e9))
        started = time.perf_counter()
        predicted = map_frame_labels(mapper, frame.points, frame.pose, input_labels)
        labelling_ms = 1e3 * (time.perf_counter() - started)
        timing = result.timing_ms
        run_result.update_ms.append(timing["voxelize"] + timing["update"] + timing["free"])
        run_result.query_ms.append(timing["query"] + labelling_ms)
        run_result.map_scores.add(frame.ground_truth, predicted)
        points_map = transform_points(frame.points, frame.pose)  # for the uncertainty and the trails
        run_result.calibration.add(mapper, points_map, frame.ground_truth)
        if input_scores is not None:
            input_scores.add(frame.ground_truth, input_labels)
        if input_calibration is not None and frame.probabilities is not None:
            input_calibration.add(frame.ground_truth, input_distribution(frame.probabilities))
        if tempered_calibration is not None and frame.probabilities is not None:
            tempered_calibration.add(frame.ground_truth, tempered_distribution(frame.probabilities, config.temperature))
        if out_folder is not None:
            write_label_file(out_folder / f"{frame.name}.label", predicted, label_map)
        still = ~frame.moving if frame.moving is not None else slice(None)
        run_result.static_input_scores.add(frame.ground_truth[still], input_labels[still])
        run_result.static_map_scores.add(frame.ground_truth[still], predicted[still])
        if frame.moving is not None and label_map.movable_classes:
            swept.add(points_map, frame.moving)
            if run_result.moving_map_scores is None:
                run_result.moving_input_scores = ConfusionMatrix(label_map.num_classes, label_map.ignore_classes)
                run_result.moving_map_scores = ConfusionMatrix(label_map.num_classes, label_map.ignore_classes)
            run_result.moving_input_scores.add(frame.ground_truth[frame.moving], input_labels[frame.moving])
            run_result.moving_map_scores.add(frame.ground_truth[frame.moving], predicted[frame.moving])
        coverage.add(points_map, frame.ground_truth, frame.moving)
        if truth_voxels is not None:
            truth_voxels.add(points_map, frame.ground_truth, frame.moving, frame.pose[:3, 3],
                             mapper_config.window.local_bounds)
        if input_voxels is not None:  # the input's labels of the points the truth counts (not its unlabelled ones)
            input_voxels.add(points_map, np.where(frame.ground_truth > 0, input_labels, 0), frame.moving,
                             frame.pose[:3, 3], mapper_config.window.local_bounds)
    voxels = mapper.voxels()
    if swept.moving_points:
        run_result.trail_voxels = swept.trail_voxels(voxels.indices, voxels.label, label_map.movable_classes)
    run_result.static_coverage = coverage.coverage(voxels.indices, voxels.label)
    return run_result


def drift_study_of(dataset, positions, kernel_file, mapper_config: MapperConfig, quiet: bool):
    """On a drift drive (``loop_closure.yaml``) whose frames cross the loop closure: the maps
    without correction, corrected and from scratch (``correction_eval``); else None."""
    from convbki_core.datasets.drift import read_loop_closure
    from convbki_core.measures.correction_eval import drift_study

    closure = read_loop_closure(dataset)
    if closure is None or not positions[0] < closure.closure_frame <= positions[-1]:
        return None
    label_map = dataset.label_map
    config = mapper_config.replace(ignore_classes=label_map.ignore_classes, movable_classes=label_map.movable_classes,
                                   ground_classes=label_map.ground_classes, scan_log=True)
    kernel = load_kernel_file(kernel_file)

    def show(frames, what):
        return frames if quiet else progress(frames, total=len(positions), description=f"drift: {what}")

    return drift_study(dataset, positions, closure, lambda: ConvBKIMapper(config, kernel), show)


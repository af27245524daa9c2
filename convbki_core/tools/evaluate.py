"""``evaluate``: offline ConvBKI mapping and scoring of a SemanticKITTI-format sequence.

Protocol (the paper's, docs/evaluation.md): frames in order; update the map with each
frame, then label every point of that frame by the arg-max class of its voxel (points
outside the window or in voxels with no evidence beyond the prior keep the input label);
one confusion matrix over all frames, ground-truth class 0 ignored; IoU per class, mIoU over
the classes present in the ground truth; the input segmentation is scored the same way.
On the same points the map's uncertainty is measured (``calibration``): ECE, NLL and Brier
score of its class distributions (and of the input's, given probabilities), the paper's
variance-filter curve, and a reliability diagram.
Several ``--kernel`` files are evaluated one after another on the same frames (ablations).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from convbki_core.config import DEFAULTS, UPDATE_PATHS, MapperConfig
from convbki_core.datasets import DatasetError, parse_frames
from convbki_core.datasets.semantic_kitti import SemanticKittiSequence
from convbki_core.free_space.clamping import check_limit
from convbki_core.geometry.volume import tempers, transform_points
from convbki_core.io.atomic import atomic_write_bytes
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
from convbki_core.tools.cli import (
    NewOutputs,
    UserError,
    device_arg,
    frames_arg,
    output_folder,
    progress,
    run,
    say_notices,
    sequence_arg,
    window_bounds,
)
from convbki_core.warm_up import warm_up

PROG = "evaluate"


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


def format_table(class_names: Sequence[str], input_scores: ConfusionMatrix, runs: Sequence[KernelRun]) -> str:
    """Per-class IoU (%) table: one row per class present in the ground truth, one column per input/kernel."""
    headers = ["class", "input"] + [Path(r.kernel_file).stem.replace("semantic_kitti_", "") for r in runs]
    width = max(12, *(len(h) for h in headers[1:]))
    lines = [f"{headers[0]:<14}" + "".join(f"{h:>{width + 1}}" for h in headers[1:])]
    ious = [input_scores.iou()] + [r.map_scores.iou() for r in runs]
    for class_id in np.flatnonzero(input_scores.present):
        lines.append(f"{class_names[class_id]:<14}" + "".join(f"{100 * iou[class_id]:>{width + 1}.1f}" for iou in ious))
    scores = [input_scores] + [r.map_scores for r in runs]
    lines.append(f"{'mIoU':<14}" + "".join(f"{100 * s.miou():>{width + 1}.1f}" for s in scores))
    lines.append(f"{'accuracy':<14}" + "".join(f"{100 * s.accuracy():>{width + 1}.1f}" for s in scores))
    return "\n".join(lines)


def build_report(sequence: str, frame_count: int, class_names: Sequence[str], input_scores: ConfusionMatrix,
                 runs: Sequence[KernelRun], input_calibration: CalibrationStats | None = None,
                 tempered: tuple[float, CalibrationStats] | None = None,
                 movable_classes: Sequence[int] = ()) -> dict:
    """report.json (docs/evaluation.md): the first kernel at the top level, every kernel under "runs".

    ``input_calibration``: the input's probabilities measured (None: labels only, so the input's
    ECE, NLL and Brier score are null); ``tempered``: (the first kernel's temperature, the input's
    probabilities measured after calibration by it), when that temperature is not 1;
    ``movable_classes``: where the ground truth marks movers, the classes that move, whose IoU
    the report gives for the input and the map side by side.
    """

    def recall(scores: ConfusionMatrix | None, c: int) -> float | None:
        if scores is None or not scores.counts[c].sum():
            return None
        return float(scores.counts[c, c] / scores.counts[c].sum())

    def iou(scores: ConfusionMatrix | None, c: int) -> float | None:
        if scores is None or not scores.present[c]:
            return None
        return float(scores.iou()[c])

    def movable_entry(run_result: KernelRun) -> dict:
        """Per movable class: IoU of input and map over all points; over the points the ground
        truth does not mark as moving (parked and standing objects) and over those it does;
        and the share of the moving points that each labels right."""
        input_iou, map_iou = input_scores.iou(), run_result.map_scores.iou()
        return {class_names[c]: {"input_iou": float(input_iou[c]), "map_iou": float(map_iou[c]),
                                 "map_minus_input": float(map_iou[c] - input_iou[c]),
                                 "static_input_iou": iou(run_result.static_input_scores, c),
                                 "static_map_iou": iou(run_result.static_map_scores, c),
                                 "moving_input_iou": iou(run_result.moving_input_scores, c),
                                 "moving_map_iou": iou(run_result.moving_map_scores, c),
                                 "moving_points_input_recall": recall(run_result.moving_input_scores, c),
                                 "moving_points_map_recall": recall(run_result.moving_map_scores, c)}
                for c in movable_classes if input_scores.present[c]}

    def run_entry(run_result: KernelRun) -> dict:
        scores = run_result.map_scores.summary(class_names)
        if run_result.calibration is not None:
            scores.update(run_result.calibration.summary())
        if run_result.trail_voxels is not None:
            scores["trail_voxels"] = run_result.trail_voxels
        scores["static_coverage"] = run_result.static_coverage
        if movable_classes:
            scores["movable_classes"] = movable_entry(run_result)
        return {"kernel": run_result.kernel, "kernel_file": run_result.kernel_file,
                "free_space": run_result.mapper.free_space, "moving_labels": run_result.moving_labels_used,
                "forget_movers": run_result.mapper.forgetting is not None,
                "max_concentration": run_result.mapper.max_concentration, "map": scores,
                "timing_ms": {"update_median": float(np.median(run_result.update_ms)),
                              "query_median": float(np.median(run_result.query_ms))}}

    entries = [run_entry(r) for r in runs]
    input_entry = input_scores.summary(class_names)
    if input_calibration is not None and input_calibration.points:
        input_entry.update(input_calibration.summary(with_curve=False))
        input_entry["calibration_points"] = input_calibration.points
    else:
        input_entry.update({"ece": None, "nll": None, "brier": None})
    if tempered is not None and tempered[1].points:
        input_entry["tempered"] = {"temperature": tempered[0], **tempered[1].summary(with_curve=False)}
    report = {"sequence": sequence, "frames": frame_count, "kernel": entries[0]["kernel"],
              "kernel_file": entries[0]["kernel_file"], "input": input_entry,
              "free_space": entries[0]["free_space"], "max_concentration": entries[0]["max_concentration"],
              "map": entries[0]["map"], "timing_ms": entries[0]["timing_ms"]}
    if len(entries) > 1:
        report["runs"] = entries
    return report


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=PROG,
        description="Map a SemanticKITTI-format sequence offline with ConvBKI and score the map's labels and the "
        "input segmentation against the ground truth (IoU per class, mIoU over classes present in the ground "
        "truth, accuracy) and the uncertainty of the map's class distributions on the same points (ECE, NLL, "
        "Brier score, the variance-filter curve). Prints a per-class table, writes report.json, a bird's-eye PNG "
        "of each map and a reliability diagram beside it.")
    p.add_argument("--dataset", required=True, metavar="ROOT",
                   help="dataset root holding sequences/SS/{velodyne,labels,...}, poses.txt and calib.txt")
    p.add_argument("--sequence", required=True, metavar="SS", type=sequence_arg, help="sequence id, e.g. 08")
    p.add_argument("--predictions-dir", default="predictions", metavar="DIR",
                   help="folder under sequences/SS with the input segmentation NNNNNN.label (uint32 raw ids) "
                   "(default: %(default)s)")
    p.add_argument("--probabilities-dir", default=None, metavar="DIR",
                   help="folder under sequences/SS with per-point class probabilities NNNNNN.npy (N x C "
                   "float16/float32); when given, the map is updated with these instead of one-hot labels")
    p.add_argument("--kernel", nargs="+", default=None, metavar="FILE",
                   help="one or more kernel files (YAML); each is evaluated on the same frames and reported "
                   "(ablations). Default: config/kernels/semantic_kitti_compound.yaml")
    p.add_argument("--frames", default=None, metavar="A:B", type=frames_arg,
                   help="only frames A (inclusive) to B (exclusive); default: all")
    p.add_argument("--report", required=True, metavar="JSON",
                   help="write the report (sequence, frames, kernel, input and map mIoU, IoU per class, accuracy, "
                   "ECE, NLL, Brier score, the map's variance-filter curve, median update and query times in ms) to "
                   "this file, and REPORT_reliability.png beside it; with several kernels, all are under 'runs'")
    p.add_argument("--write-labels", default=None, metavar="OUTROOT",
                   help="also write the map's labels as OUTROOT/sequences/SS/predictions/NNNNNN.label (uint32 raw "
                   "ids, one per input point), the format the semantic-kitti-api evaluator reads (first kernel)")
    p.add_argument("--picture", default=None, metavar="PNG",
                   help="bird's-eye picture of the final map (classes and variance side by side); default: next "
                   "to the report, REPORT_map.png (REPORT_<kernel>_map.png with several kernels)")
    p.add_argument("--save-map", default=None, metavar="FILE",
                   help="also write the final map (first kernel) as a map file (.npz) that the mapper node can "
                   "load (map_file) and map_tool reads; written only when the whole run succeeded")
    p.add_argument("--local-bounds", nargs=6, type=float, default=None, metavar=("XMIN", "YMIN", "ZMIN", "XMAX",
                   "YMAX", "ZMAX"), help="local window around the sensor in metres (default: the paper's "
                   "-40 -40 -2.6 40 40 2.6)")
    p.add_argument("--device", default=DEFAULTS.compute.device, type=device_arg,
                   help="torch device: auto (CUDA when present), cpu, cuda or cuda:N (default: %(default)s)")
    p.add_argument("--update-path", default=DEFAULTS.compute.update_path, choices=UPDATE_PATHS,
                   help="how the update is computed: fast (compiled sparse scatter, the CPU default), torch (the "
                   "window resident on the torch device, the CUDA default), dense (the paper's depthwise conv3d, "
                   "the reference) (default: %(default)s)")
    p.add_argument("--no-free-space", dest="free_space", action="store_false",
                   help="map without free space: the rays between the sensor and its returns add no evidence "
                   "that the voxels they cross are empty (the paper's ConvBKI; movers then leave trails)")
    p.add_argument("--max-concentration", default=DEFAULTS.free_space.max_concentration, type=float,
                   help="with free space: a voxel that rays first find empty while its concentrations sum to more "
                   "than this is scaled down to it (clamping), so a bounded number of rays can empty what a mover "
                   "left; 0 = never (default: %(default)s, as the node)")
    p.add_argument("--prior", default=DEFAULTS.window.prior, type=float,
                   help="initial concentration of every class in a new voxel (default: %(default)s)")
    p.add_argument("--no-forget-movers", dest="forget_movers", action="store_false",
                   help="with free space: keep the movable classes' evidence as free space leaves it (by default "
                        "it is forgotten where a return shows another class and where it floats over empty space)")
    p.add_argument("--ignore-moving-labels", dest="moving_labels", action="store_false",
                   help="map points the input marks as moving (raw ids 252-259) as their static classes; by "
                        "default they are evidence for their own scan only and stay out of the map")
    p.add_argument("--costmap-report", default=None, metavar="JSON",
                   help="also score the final map's traversability costmap (the node's semantic_map/costmap) "
                   "against the ground truth's, with the projected-occupancy baseline, the input segmentation's "
                   "own grid and a planning check; writes JSON and a picture beside it")
    p.add_argument("--costmap-profile", default="car", metavar="PROFILE",
                   help="traversability profile for --costmap-report: car, small_robot or a YAML file (default: car)")
    p.add_argument("--no-scan-log", dest="scan_log", action="store_false",
                   help="keep no scan log: the map of --save-map then holds no log, so map_tool correct cannot "
                   "move its scans (default: the log is kept and saved)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def check_writable_file(path: str | Path, flag: str) -> None:
    """Refuse, before the long work, a file that could not be written at the end."""
    folder = output_folder(path, flag.lstrip("-").replace("-", " "))
    if Path(path).is_dir():
        raise UserError(f"{path}: is a folder; {flag} names a file")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise UserError(f"{folder}: folder is not writable (for {flag} {path})")


def _drift_study(dataset, positions, kernel_file, mapper_config: MapperConfig, quiet: bool):
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


def _evaluate(args: argparse.Namespace) -> int:
    outputs = NewOutputs()
    try:
        return _evaluate_into(args, outputs)
    except BaseException:
        outputs.discard()  # a failed run leaves none of its outputs (older results are kept)
        raise


def _evaluate_into(args: argparse.Namespace, outputs: NewOutputs) -> int:
    kernels = args.kernel or [str(DEFAULTS.kernel_path())]
    for kernel_file in kernels:
        load_kernel_file(kernel_file)  # fail before any work on a bad kernel file
    if not args.prior > 0:
        raise UserError(f"--prior must be positive, got {args.prior}")
    try:
        check_limit(args.max_concentration)
    except ValueError:
        raise UserError("--max-concentration must be 0 (off) or a positive number, "
                        f"got {args.max_concentration}") from None
    mapper_config = DEFAULTS.replace(local_bounds=window_bounds(args.local_bounds) or DEFAULTS.window.local_bounds,
                                     prior=args.prior, device=args.device, update_path=args.update_path,
                                     free_space=args.free_space, max_concentration=args.max_concentration,
                                     forget_movers=args.forget_movers, scan_log=args.scan_log)
    report_path = Path(args.report)
    output_folder(report_path, "report")
    if report_path.is_dir():
        raise UserError(f"{report_path}: is a folder; --report names a JSON file")
    if args.picture:
        output_folder(args.picture, "picture")
    if args.save_map:
        check_writable_file(args.save_map, "--save-map")
    dataset = SemanticKittiSequence(args.dataset, args.sequence, args.predictions_dir, args.probabilities_dir)
    say_notices(PROG, dataset.notices)
    if dataset.predictions_folder is None and dataset.probabilities_folder is None:
        raise UserError("no input segmentation: give --predictions-dir or --probabilities-dir")
    if not dataset.has_ground_truth:
        raise DatasetError(f"{dataset.folder}: no labels/ folder, so there is no ground truth to score against")
    try:
        positions = parse_frames(args.frames, len(dataset))
    except ValueError as error:
        raise UserError(str(error)) from None
    dataset.check_files(positions)  # every file there and sized right, before anything is written
    labels_folder = None
    if args.write_labels:
        if Path(args.write_labels).exists() and not Path(args.write_labels).is_dir():
            raise UserError(f"{args.write_labels}: not a folder (--write-labels names a dataset root to write)")
        labels_folder = outputs.staging(Path(args.write_labels) / "sequences" / dataset.sequence / "predictions")
    label_map = dataset.label_map
    costmap_profile = truth_voxels = input_voxels = None
    if args.costmap_report:
        from convbki_core.costmap.columns import ProfileError, load_profile
        from convbki_core.measures.costmap_eval import GroundTruthVoxels
        from convbki_core.paths import traversability_profile

        output_folder(args.costmap_report, "costmap report")
        try:
            costmap_profile = load_profile(traversability_profile(args.costmap_profile), label_map.class_names)
        except ProfileError as error:
            raise UserError(str(error)) from None
        truth_voxels = GroundTruthVoxels(label_map.num_classes, load_kernel_file(kernels[0]).resolution)
        input_voxels = GroundTruthVoxels(label_map.num_classes, truth_voxels.resolution)
    input_scores = ConfusionMatrix(label_map.num_classes, label_map.ignore_classes)
    # The input has a class distribution only when it is given as probabilities.
    input_calibration = (CalibrationStats(label_map.num_classes, label_map.ignore_classes, thresholds=None)
                         if dataset.probabilities_folder is not None else None)
    # The first kernel's temperature calibrates probability inputs: the input is measured as
    # given and as the map receives it.
    temperature = load_kernel_file(kernels[0]).temperature
    tempered = None
    if input_calibration is not None and tempers(temperature):
        tempered = (temperature, CalibrationStats(label_map.num_classes, label_map.ignore_classes, thresholds=None))
    runs = []
    for number, kernel_file in enumerate(kernels):
        runs.append(evaluate_kernel(dataset, positions, kernel_file, mapper_config,
                                    input_scores if number == 0 else None,
                                    labels_folder if number == 0 else None,
                                    show_progress=not args.quiet,
                                    input_calibration=input_calibration if number == 0 else None,
                                    tempered_calibration=tempered[1] if number == 0 and tempered else None,
                                    truth_voxels=truth_voxels if number == 0 else None,
                                    input_voxels=input_voxels if number == 0 else None,
                                    moving_labels=args.moving_labels))
    movable = label_map.movable_classes
    report = build_report(dataset.sequence, len(positions), label_map.class_names, input_scores, runs,
                          input_calibration, tempered, movable)
    drift = _drift_study(dataset, positions, kernels[0], mapper_config, args.quiet)
    if drift is not None:
        report["drift"] = drift.report()

    from convbki_core.tools.plots import save_map_picture, save_reliability_diagram

    pictures = []
    for run_result in runs:
        if args.picture and len(runs) == 1:
            picture = Path(args.picture)
        else:
            suffix = "" if len(runs) == 1 else "_" + Path(run_result.kernel_file).stem
            picture = report_path.with_name(f"{report_path.stem}{suffix}_map.png")
        voxels = run_result.mapper.voxels()
        title = (f"sequence {dataset.sequence}, {len(positions)} frames, {Path(run_result.kernel_file).stem}: "
                 f"map mIoU {run_result.map_scores.miou():.3f} (input {input_scores.miou():.3f})")
        save_map_picture(voxels, label_map, run_result.mapper.resolution, outputs.file(picture), title)
        pictures.append(picture)
        suffix = "" if len(runs) == 1 else "_" + Path(run_result.kernel_file).stem
        reliability_path = report_path.with_name(f"{report_path.stem}{suffix}_reliability.png")
        stats = run_result.calibration.stats
        diagrams = {"map": (stats.reliability(), stats.ece())}
        if input_calibration is not None and input_calibration.points:
            diagrams["input"] = (input_calibration.reliability(), input_calibration.ece())
        if tempered is not None and tempered[1].points and run_result is runs[0]:
            diagrams[f"input, T = {tempered[0]:.3g}"] = (tempered[1].reliability(), tempered[1].ece())
        save_reliability_diagram(diagrams, outputs.file(reliability_path), stats.variance_curve(),
                                 title=f"sequence {dataset.sequence}, {len(positions)} frames, "
                                 f"{Path(run_result.kernel_file).stem}")
        pictures.append(reliability_path)
    if drift is not None:
        from convbki_core.tools.plots import save_maps_side_by_side

        drift_picture = report_path.with_name(f"{report_path.stem}_drift.png")
        before, after = drift.maps[0], drift.maps[1]
        save_maps_side_by_side(
            [(f"{before.name}: double surface {before.double_surface:.3f}, mIoU {before.miou:.3f}",
              before.mapper.voxels()),
             (f"{after.name}: double surface {after.double_surface:.3f}, mIoU {after.miou:.3f}",
              after.mapper.voxels())],
            label_map, before.mapper.resolution, outputs.file(drift_picture),
            f"sequence {dataset.sequence}: the loop closes at frame {drift.closure_frame}, the odometry "
            f"{drift.drift_m:.2f} m off")
        pictures.append(drift_picture)
    costmap_lines = []
    if args.costmap_report:
        costmap_lines = write_costmap_report(runs[0].mapper, truth_voxels, costmap_profile, label_map,
                                             Path(args.costmap_report), outputs, input_voxels)
    if args.save_map:
        runs[0].mapper.save(outputs.file(args.save_map))  # atomic; removed again if the report fails
    # The report and the labels last: they are what scripts look for to tell that a run finished.
    atomic_write_bytes(outputs.file(report_path), (json.dumps(report, indent=2) + "\n").encode())
    outputs.commit()

    print(f"sequence {dataset.sequence}, {len(positions)} frames: IoU per class (%)")
    print(format_table(label_map.class_names, input_scores, runs))
    for run_result in runs:
        print(f"{Path(run_result.kernel_file).stem}: map mIoU {run_result.map_scores.miou():.4f} vs input "
              f"{input_scores.miou():.4f} ({run_result.map_scores.miou() - input_scores.miou():+.4f}); "
              f"update {np.median(run_result.update_ms):.1f} ms, query {np.median(run_result.query_ms):.1f} ms "
              f"(median), {len(run_result.mapper)} voxels"
              + ("" if run_result.trail_voxels is None else f", {run_result.trail_voxels} trail voxels")
              + ("" if run_result.static_coverage is None
                 else f", static coverage {100 * run_result.static_coverage:.1f} %")
              + (", the input's moving labels used" if run_result.moving_labels_used else ""))
        if movable:
            entry = (report["runs"][runs.index(run_result)] if "runs" in report else report)["map"]["movable_classes"]
            print("  movable classes, IoU % input -> map; not moving (parked, standing) | moving: " + ", ".join(
                f"{name} {100 * v['input_iou']:.1f} -> {100 * v['map_iou']:.1f}; "
                + _pair(v["static_input_iou"], v["static_map_iou"]) + " | " + _pair(v["moving_input_iou"],
                                                                                      v["moving_map_iou"])
                for name, v in entry.items()))
        calibration = run_result.calibration.summary()
        line = (f"  uncertainty on {calibration['calibration_points']} scored points with map evidence "
                f"({calibration['points_without_evidence']} without): map ECE {_number(calibration['ece'])}, "
                f"NLL {_number(calibration['nll'])}, Brier {_number(calibration['brier'])}")
        if run_result is runs[0]:
            line += (f"; input ECE {_number(report['input']['ece'])}, NLL {_number(report['input']['nll'])}, "
                     f"Brier {_number(report['input']['brier'])}")
            if "tempered" in report["input"]:
                scaled = report["input"]["tempered"]
                line += (f"; input at temperature {scaled['temperature']:g}: ECE {_number(scaled['ece'])}, "
                         f"NLL {_number(scaled['nll'])}, Brier {_number(scaled['brier'])}")
        print(line)
    for line in costmap_lines:
        print(line)
    for line in drift.lines() if drift is not None else []:
        print(line)
    print(f"report: {report_path}; pictures: {', '.join(map(str, pictures))}")
    if args.write_labels:
        print(f"labels: {Path(args.write_labels) / 'sequences' / dataset.sequence / 'predictions'}")
    if args.save_map:
        print(f"map: {args.save_map} ({len(runs[0].mapper)} voxels)")
    return 0


def write_costmap_report(mapper, truth_voxels, profile, label_map, path: Path, outputs: NewOutputs,
                         input_voxels=None) -> list[str]:
    """Score the map's costmap, the projected-occupancy baseline and (``input_voxels`` given) the
    input segmentation's grid against the ground truth's (``costmap_eval``); write the JSON and a
    picture (map, baseline, truth; one planned path); return the lines to print."""
    from convbki_core.measures.costmap_eval import grids_for, planning_check, road_cells, score_grid
    from convbki_core.tools.plots import save_costmap_pictures

    indices, alpha = mapper.items()
    grids = grids_for(indices, alpha, truth_voxels, mapper.resolution, mapper.prior, profile, input_voxels)
    road = road_cells(truth_voxels, grids["truth"], label_map.class_names.index("road"))
    report = {"profile": profile.name, "resolution": mapper.resolution, "cells": int(grids["truth"].values.size)}
    lines = [f"costmap ({profile.name}) against the ground truth's, on "
             f"{int((grids['truth'].values >= 0).sum())} observed cells:"]
    for name in [name for name in ("map", "baseline", "input") if name in grids]:
        scores = score_grid(grids[name].values, grids["truth"].values)
        check = planning_check(grids[name].values, grids["truth"].values, road)
        report[name] = {"precision": scores.precision, "recall": scores.recall,
                        "unknown_share": scores.unknown_share, "planning": check.summary()}
        summary = check.summary()

        def pct(value):
            return "-" if value is None else f"{100 * value:.1f}"

        lines.append(f"  {name:8s} precision free {pct(scores.precision['free'])} costly "
                     f"{pct(scores.precision['costly'])} lethal {pct(scores.precision['lethal'])}; recall free "
                     f"{pct(scores.recall['free'])} costly {pct(scores.recall['costly'])} lethal "
                     f"{pct(scores.recall['lethal'])}; unknown {pct(scores.unknown_share)} %; paths "
                     f"{summary['planned_on_both']}/{summary['pairs']}, crossing truth-lethal "
                     f"{summary['crossing_truth_lethal']}, length ratio median "
                     f"{_number(summary['length_ratio_median'])}")
    picture = path.with_suffix(".png")
    save_costmap_pictures({name: grids[name] for name in ("map", "baseline", "truth")}, road,
                          outputs.file(picture), title=f"costmap, {profile.name} profile")
    atomic_write_bytes(outputs.file(path), (json.dumps(report, indent=2) + "\n").encode())
    lines.append(f"costmap report: {path}; picture: {picture}")
    return lines


def _pair(before: float | None, after: float | None) -> str:
    """``input -> map`` IoU in %, or ``-`` where the class has no such points."""
    return "-" if before is None or after is None else f"{100 * before:.1f} -> {100 * after:.1f}"


def _number(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.4f}"


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the process exit code."""
    return run(PROG, _evaluate, build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())

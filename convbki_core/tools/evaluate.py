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
This module is the command line; ``evaluate_run`` maps and scores, ``evaluate_report`` writes
the report, the figures and the printed summary.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Sequence
from pathlib import Path

from convbki_core.config import DEFAULTS, UPDATE_PATHS
from convbki_core.datasets import DatasetError, parse_frames
from convbki_core.tools.cli import (
    NewOutputs,
    UserError,
    device_arg,
    frames_arg,
    output_folder,
    run,
    say_notices,
    sequence_arg,
    window_bounds,
)

PROG = "evaluate"


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


def _evaluate(args: argparse.Namespace) -> int:
    outputs = NewOutputs()
    try:
        return _evaluate_into(args, outputs)
    except BaseException:
        outputs.discard()  # a failed run leaves none of its outputs (older results are kept)
        raise


def _evaluate_into(args: argparse.Namespace, outputs: NewOutputs) -> int:
    # The method (torch, numba) loads here, once the arguments are read: --help and a wrong flag
    # answer at once.
    from convbki_core.datasets.semantic_kitti import SemanticKittiSequence
    from convbki_core.free_space.clamping import check_limit
    from convbki_core.geometry.volume import tempers
    from convbki_core.io.atomic import atomic_write_bytes
    from convbki_core.io.kernel_file import load_kernel_file
    from convbki_core.measures.metrics import ConfusionMatrix
    from convbki_core.measures.uncertainty import CalibrationStats
    from convbki_core.tools.evaluate_report import build_report, print_summary, save_pictures, write_costmap_report
    from convbki_core.tools.evaluate_run import drift_study_of, evaluate_kernel

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
        from convbki_core.costmap.profile import ProfileError, load_profile
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
    drift = drift_study_of(dataset, positions, kernels[0], mapper_config, args.quiet)
    if drift is not None:
        report["drift"] = drift.report()

    pictures = save_pictures(dataset, positions, runs, input_scores, input_calibration, tempered, drift,
                             report_path, args.picture, outputs)
    costmap_lines = []
    if args.costmap_report:
        costmap_lines = write_costmap_report(runs[0].mapper, truth_voxels, costmap_profile, label_map,
                                             Path(args.costmap_report), outputs, input_voxels)
    if args.save_map:
        runs[0].mapper.save(outputs.file(args.save_map))  # atomic; removed again if the report fails
    # The report and the labels last: they are what scripts look for to tell that a run finished.
    atomic_write_bytes(outputs.file(report_path), (json.dumps(report, indent=2) + "\n").encode())
    outputs.commit()

    print_summary(dataset, positions, runs, input_scores, report, report_path, pictures, costmap_lines, drift,
                  args.write_labels, args.save_map)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the process exit code."""
    return run(PROG, _evaluate, build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())

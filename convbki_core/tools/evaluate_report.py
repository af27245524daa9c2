"""``evaluate``'s reports: the per-class table and the lines it prints, report.json, the
figures beside it (each map, its reliability diagram, a drift drive's maps) and the costmap's
report.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from convbki_core.datasets.semantic_kitti import SemanticKittiSequence
from convbki_core.io.atomic import atomic_write_bytes
from convbki_core.measures.metrics import ConfusionMatrix
from convbki_core.measures.uncertainty import CalibrationStats
from convbki_core.tools.cli import NewOutputs
from convbki_core.tools.evaluate_run import KernelRun

if TYPE_CHECKING:
    from convbki_core.measures.correction_eval import DriftStudy


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


def save_pictures(dataset: SemanticKittiSequence, positions: Sequence[int], runs: Sequence[KernelRun],
                  input_scores: ConfusionMatrix, input_calibration: CalibrationStats | None,
                  tempered: tuple[float, CalibrationStats] | None, drift: DriftStudy | None, report_path: Path,
                  map_picture: str | None, outputs: NewOutputs) -> list[Path]:
    """The figures beside the report: each map's bird's-eye picture (``map_picture``: the one
    map's, when given) and reliability diagram, and on a drift drive (``drift``, else None) its
    maps before and after the correction; returns their paths."""
    from convbki_core.tools.plots import save_map_picture, save_reliability_diagram

    label_map = dataset.label_map
    pictures = []
    for run_result in runs:
        if map_picture and len(runs) == 1:
            picture = Path(map_picture)
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
    return pictures


def print_summary(dataset: SemanticKittiSequence, positions: Sequence[int], runs: Sequence[KernelRun],
                  input_scores: ConfusionMatrix, report: dict, report_path: Path, pictures: Sequence[Path],
                  costmap_lines: Sequence[str], drift: DriftStudy | None, write_labels: str | None,
                  save_map: str | None) -> None:
    """What ``evaluate`` prints once its outputs are written: the IoU table, each kernel's scores,
    timings and uncertainty, the costmap's and drift study's lines, and where the outputs are."""
    label_map = dataset.label_map
    movable = label_map.movable_classes
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
    if write_labels:
        print(f"labels: {Path(write_labels) / 'sequences' / dataset.sequence / 'predictions'}")
    if save_map:
        print(f"map: {save_map} ({len(runs[0].mapper)} voxels)")
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


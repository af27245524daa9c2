"""How much a SLAM's correction of the map is worth, on a drift drive (``synth --drift``).

Three maps of the same scans:

* without correction: every scan where the robot mapped it (its odometry, which drifts,
  then the SLAM's pose after the loop closes), as a mapper that cannot move scans leaves it;
* corrected: the same, with the SLAM's keyframes applied to the map's scan log when the
  loop closes (``ConvBKIMapper.corrected``), then the rest of the drive;
* from scratch: every scan mapped once at its corrected pose.

Each is scored by its final map over every frame's points at the true poses (mIoU, points
without map evidence keep the input's label), by its double surface (the occupied voxels
farther than one voxel from every ground-truth point of the static scene, as a share of the
occupied voxels: the street mapped twice), and by the share of the voxels occupied in
either map whose labels equal the from-scratch map's.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from convbki_core.correction.replay import CorrectionResult
from convbki_core.geometry.grid import TOUCHING_OFFSETS, transform_points, voxel_keys
from convbki_core.inference.statistics import dirichlet_statistics
from convbki_core.measures.metrics import ConfusionMatrix


@dataclass
class DriftMap:
    """One of the three maps and its scores."""

    name: str
    mapper: object
    miou: float = 0.0
    double_surface: float = 0.0
    labels_equal: float = 1.0  # to the from-scratch map, over the voxels occupied in either
    occupied: int = 0


@dataclass
class DriftStudy:
    maps: list[DriftMap]
    correction: CorrectionResult
    integrate_ms: list[float] = field(default_factory=list)  # per scan of the uncorrected map
    closure_frame: int = 0
    drift_m: float = 0.0  # the odometry's error at the closure

    def report(self) -> dict:
        moved_ms = 1e3 * self.correction.seconds / max(self.correction.scans, 1)
        return {
            "closure_frame": self.closure_frame, "drift_at_closure_m": round(self.drift_m, 3),
            "maps": {m.name: {"miou": m.miou, "double_surface": m.double_surface, "labels_equal": m.labels_equal,
                              "occupied_voxels": m.occupied} for m in self.maps},
            "correction": {"scans_moved": self.correction.scans, "scans_mapped_again": self.correction.replayed,
                           "largest_move_m": round(self.correction.largest_move, 3),
                           "seconds": round(self.correction.seconds, 3),
                           "ms_per_moved_scan": round(moved_ms, 2),
                           "integrate_ms_median": round(float(np.median(self.integrate_ms)), 2),
                           "integrate_ms_mean": round(float(np.mean(self.integrate_ms)), 2)},
        }

    def lines(self) -> list[str]:
        """The study as a table, for the terminal."""
        rows = [f"drift drive: the loop closes at frame {self.closure_frame}, where the odometry is "
                f"{self.drift_m:.2f} m off",
                f"  {'map':<20}{'mIoU':>8}{'double surface':>16}{'labels equal':>14}"]
        for m in self.maps:
            rows.append(f"  {m.name:<20}{m.miou:>8.4f}{m.double_surface:>16.4f}{m.labels_equal:>14.4f}")
        c = self.report()["correction"]
        rows.append(f"  correction: {c['scans_moved']} scans moved (largest move {c['largest_move_m']:.2f} m), "
                    f"{c['scans_mapped_again']} mapped again in {c['seconds']:.2f} s: {c['ms_per_moved_scan']:.1f} ms "
                    f"a moved scan against {c['integrate_ms_mean']:.1f} ms to integrate one (mean)")
        return rows


def static_truth_keys(dataset, positions, poses: np.ndarray, resolution: float) -> np.ndarray:
    """Sorted keys of the voxels within one voxel of a ground-truth point of the static scene
    (labelled, not moving), every frame at its true pose."""
    keys = []
    for position in positions:
        frame = dataset[position]
        keep = frame.ground_truth > 0
        if frame.moving is not None:
            keep &= ~frame.moving
        voxels = np.unique(np.floor(transform_points(frame.points[keep], poses[position]) / resolution)
                           .astype(np.int64), axis=0)
        keys.append(np.unique(voxel_keys((voxels[:, None, :] + TOUCHING_OFFSETS[None]).reshape(-1, 3))))
    return np.unique(np.concatenate(keys)) if keys else np.zeros(0, np.int64)


def occupied_labels(mapper) -> tuple[np.ndarray, np.ndarray]:
    """(sorted keys, labels) of the map's occupied voxels (expected class other than 0)."""
    indices, alpha = mapper.items()
    labels = dirichlet_statistics(alpha).label
    occupied = labels != 0
    keys = voxel_keys(indices[occupied])
    order = np.argsort(keys)
    return keys[order], labels[occupied][order]


def double_surface(keys: np.ndarray, static_keys: np.ndarray) -> float:
    """The share of occupied voxels (``keys``) farther than one voxel from the static truth."""
    if not len(keys):
        return 0.0
    return float(np.count_nonzero(~np.isin(keys, static_keys, assume_unique=True)) / len(keys))


def labels_equal(keys: np.ndarray, labels: np.ndarray, other_keys: np.ndarray, other_labels: np.ndarray) -> float:
    """The share of the voxels occupied in either map whose labels agree (absent: label 0)."""
    union = np.union1d(keys, other_keys)
    if not len(union):
        return 1.0
    mine = np.zeros(len(union), labels.dtype)
    theirs = np.zeros(len(union), other_labels.dtype)
    mine[np.searchsorted(union, keys)] = labels
    theirs[np.searchsorted(union, other_keys)] = other_labels
    return float(np.mean(mine == theirs))


def final_map_miou(mapper, dataset, positions, poses: np.ndarray) -> float:
    """mIoU of the final map over every frame's points at ``poses`` (the true ones); points
    without map evidence keep the input's label."""
    label_map = dataset.label_map
    scores = ConfusionMatrix(label_map.num_classes, label_map.ignore_classes)
    for position in positions:
        frame = dataset[position]
        labels, has_evidence = mapper.labels_at(transform_points(frame.points, poses[position]), within_window=False)
        scores.add(frame.ground_truth, np.where(has_evidence, labels, frame.input_labels))
    return float(scores.miou())


def drift_study(dataset, positions, closure, mapper_factory, show=lambda frames, what: frames) -> DriftStudy:
    """The three maps of ``positions`` of a drift drive (``closure``: its ``LoopClosure``),
    each made by ``mapper_factory()``, and their scores. ``show(frames, what)`` may wrap an
    iterable in a progress bar."""
    robot, corrected = closure.robot_poses(), closure.corrected_poses()
    positions = list(positions)
    uncorrected, fixed, result, integrate_ms = mapper_factory(), None, CorrectionResult(), []
    for position in show(positions, "without and with correction"):
        if position == closure.closure_frame and fixed is None:
            # The SLAM closes the loop: its keyframes move the scans logged so far.
            from convbki_core.correction.replay import keyframe_corrections

            keyframes = closure.keyframes[np.isin(closure.keyframes, positions)]
            moves = keyframe_corrections(uncorrected.scan_log.scans(), closure.stamps_ns[keyframes],
                                         closure.truth[keyframes])
            fixed, result = uncorrected.corrected(moves)
            if fixed is uncorrected:
                fixed = None
        frame = dataset[position]
        started = time.perf_counter()
        stamp = int(closure.stamps_ns[position])
        uncorrected.integrate(frame.points, frame.input_values, robot[position], frame.input_moving, stamp_ns=stamp)
        integrate_ms.append(1e3 * (time.perf_counter() - started))
        if fixed is not None:
            fixed.integrate(frame.points, frame.input_values, robot[position], frame.input_moving, stamp_ns=stamp)
    scratch = mapper_factory()
    for position in show(positions, "from scratch"):
        frame = dataset[position]
        scratch.integrate(frame.points, frame.input_values, corrected[position], frame.input_moving,
                          stamp_ns=int(closure.stamps_ns[position]))
    maps = [DriftMap("without correction", uncorrected), DriftMap("corrected", fixed or uncorrected),
            DriftMap("from scratch", scratch)]
    static = static_truth_keys(dataset, positions, closure.truth, scratch.resolution)
    scratch_keys, scratch_labels = occupied_labels(scratch)
    for entry in maps:
        keys, labels = occupied_labels(entry.mapper)
        entry.occupied = len(keys)
        entry.double_surface = double_surface(keys, static)
        entry.labels_equal = labels_equal(keys, labels, scratch_keys, scratch_labels)
        entry.miou = final_map_miou(entry.mapper, dataset, positions, closure.truth)
    last = max(p for p in positions if p < closure.closure_frame) if closure.closure_frame > positions[0] else 0
    drift = float(np.linalg.norm(closure.odometry[last][:3, 3] - closure.truth[last][:3, 3]))
    return DriftStudy(maps, result, integrate_ms, closure.closure_frame, drift)

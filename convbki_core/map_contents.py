"""What a ConvBKI map holds, as its readers see it: queries, every voxel, and its changes.

``MapContents`` is a mixin of ``mapper.ConvBKIMapper``: the queries of the map (the
concentrations and expected class under points, every voxel with its Dirichlet statistics
(Eq. 2), the window's point records) and the changes other than a scan's (a reset, a
forgotten box) with the bookkeeping the outputs that send only what changed take
(``take_changes``). A mixin rather than one-line delegates: these methods read the mapper's
store and window directly and share its change bookkeeping, and keeping them methods keeps the
mapper's public surface where its users call it. ``MapChanges`` and ``VoxelSet`` are what they
return.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from convbki_core.free_space.present_movers import labels_now
from convbki_core.free_space.update import FREE_CLASS
from convbki_core.geometry.grid import voxel_centres, voxel_indices, voxel_keys, voxels_of_keys
from convbki_core.inference.statistics import dirichlet_statistics
from convbki_core.outputs.records import RECORD, records_from_alpha, window_records
from convbki_core.torch_path.window import TorchWindow


@dataclass
class MapChanges:
    """What changed in the map since the changes were last taken.

    ``removed``: global indices (R, 3) of voxels that left the map (a reset, a load, dropped by a
    full map as they left the window);
    ``indices`` (N, 3) and ``alpha`` (N, C): voxels whose concentrations changed, in order
    (a voxel may appear more than once: its last row is its state). Applying the removals
    first and then the rows to a copy of the map as it was gives the map as it is.
    """

    removed: np.ndarray
    indices: np.ndarray
    alpha: np.ndarray


@dataclass
class VoxelSet:
    """Voxels with their statistics. Centres in the map frame (m)."""

    indices: np.ndarray  # (N, 3) int64 global voxel indices
    centres: np.ndarray  # (N, 3) float32
    alpha: np.ndarray  # (N, C) float32 concentrations
    label: np.ndarray  # (N,) int64 expected class
    confidence: np.ndarray  # (N,) float32
    variance: np.ndarray  # (N,) float32

    def __len__(self) -> int:
        return int(self.indices.shape[0])


class MapContents:
    """Reading the map and changing it other than by a scan (a mixin of ``ConvBKIMapper``)."""

    # -- reading the map -------------------------------------------------------------------
    def concentrations_at(self, points_map: np.ndarray,
                          within_window: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """Concentrations of the voxel under each map-frame point: (alpha (N, C) float32,
        has_evidence (N,) bool); rows are zero where the voxel holds no evidence, or (with
        ``within_window``) lies outside the current window, or the point is not finite."""
        points_map = np.asarray(points_map, dtype=np.float64).reshape(-1, 3)
        usable = np.isfinite(points_map).all(axis=1)
        indices = np.zeros((points_map.shape[0], 3), np.int64)
        indices[usable] = voxel_indices(points_map[usable], self.resolution)
        in_window = usable & self.window.inside(indices)
        alpha = np.zeros((points_map.shape[0], self.num_classes), np.float32)
        has_evidence = np.zeros(points_map.shape[0], bool)
        alpha[in_window], has_evidence[in_window] = self.window.lookup(indices[in_window])
        if not within_window:
            elsewhere = usable & ~in_window
            alpha[elsewhere], has_evidence[elsewhere] = self.store.lookup(indices[elsewhere])
        alpha[~has_evidence] = 0.0
        return alpha, has_evidence

    def labels_at(self, points_map: np.ndarray, within_window: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """Expected class of the voxel under each map-frame point.

        Returns (labels (N,) int64, has_evidence (N,) bool); labels are -1 where the voxel
        holds no evidence, or (with ``within_window``) lies outside the current window. With
        free space, the class is the most likely of the others: a query point is a return,
        so the question is what the surface there is, not whether the voxel is empty. A voxel
        that holds the last scan's moving points reads as their most likely class.
        """
        alpha, has_evidence = self.concentrations_at(points_map, within_window)
        labels = np.full(alpha.shape[0], -1, np.int64)
        if self.free_space:
            alpha[:, FREE_CLASS] = 0.0
        labels[has_evidence] = dirichlet_statistics(alpha[has_evidence]).label
        if self.present_movers is not None:
            points_map = np.asarray(points_map, dtype=np.float64).reshape(-1, 3)
            usable = np.isfinite(points_map).all(axis=1)
            now = np.full(len(labels), -1, np.int64)
            held = np.zeros(len(labels), bool)
            now[usable], held[usable] = labels_now(self.present_movers, voxel_indices(points_map[usable],
                                                                                      self.resolution))
            labels[held], has_evidence = now[held], has_evidence | held
        return labels, has_evidence

    def items(self) -> tuple[np.ndarray, np.ndarray]:
        """Every voxel with evidence: (global indices (N, 3) int64, alpha (N, C) float32)."""
        # One allocation filled by both parts: a map of millions of voxels is hundreds of MB,
        # and the node does this for every map it publishes.
        stored, in_window = len(self.store), self.window.count()
        indices = np.empty((stored + in_window, 3), np.int64)
        alpha = np.empty((stored + in_window, self.num_classes), np.float32)
        self.store.items(indices[:stored], alpha[:stored])
        self.window.items(indices[stored:], alpha[stored:])
        return indices, alpha

    def voxel_keys(self) -> np.ndarray:
        """The linear keys (``voxel_keys``) of every voxel with evidence, without their
        concentrations (a map of tens of millions of voxels would take gigabytes with them)."""
        window_indices, _ = self.window.items()
        return np.concatenate([self.store.voxel_keys(), voxel_keys(window_indices)])

    def voxels(self) -> VoxelSet:
        """Every voxel that ever received evidence, with its statistics."""
        return self.voxel_set(*self.items())

    def local_voxels(self) -> VoxelSet:
        """The voxels with evidence in the current window."""
        return self.voxel_set(*self.window.items())

    def window_records(self, palette: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """Records (``records.RECORD``: centre, colour, class, variance, probability) of the voxels
        with evidence in the current window, computed from the window in place; ``out``: as
        many records as ``window.count()`` to fill."""
        window = self.window
        if window.origin is None:
            return np.empty(0, RECORD) if out is None else out
        if isinstance(window, TorchWindow):  # made on the device: one copy of the records
            return window.records(self.resolution, palette, out)
        count = window.count() if out is None else len(out)
        return window_records(window.alpha, window.mask, window.origin, window.dims, count, self.resolution,
                              palette, out)

    def voxel_set(self, indices: np.ndarray, alpha: np.ndarray) -> VoxelSet:
        """Statistics of the given voxels (e.g. a copy taken from ``items()``)."""
        stats = dirichlet_statistics(alpha)
        return VoxelSet(indices, voxel_centres(indices, self.resolution).astype(np.float32), alpha,
                        stats.label, stats.confidence, stats.variance)

    def __len__(self) -> int:
        return len(self.store) + self.window.count()

    # -- forgetting, and the changes the outputs take --------------------------------------
    def reset(self) -> None:
        """Forget every voxel, and the scan log (the kernel and settings stay)."""
        self._removed.append(self.items()[0])
        self._clear()

    def retire(self) -> None:
        """Forget every voxel and the log without reporting them as removed: a map another took
        the place of, kept only for its window (``corrected``'s ``reuse``)."""
        self._clear()
        self._removed, self._everything_changed, self._replaced_keys = [], False, None
        if self.window.track_changes:
            self.window.take_dropped()

    def _clear(self) -> None:
        self.store.clear()
        self.window.clear()
        if self.scan_log is not None:
            self.scan_log.clear()
        self.scans_integrated = 0
        self.sensor_position = None
        self.present_movers = None
        if self.forgetting is not None:
            self.forgetting.clear()

    def forget_box(self, box_min: Sequence[float], box_max: Sequence[float]) -> np.ndarray:
        """Forget the evidence of every voxel whose centre lies in the box ``box_min`` ..
        ``box_max`` (x, y, z in the map frame, m), as if it had never been observed (octomap's
        clear_bbox). Returns the global indices (n, 3) of the voxels forgotten; they are
        reported as removed by ``take_changes``."""
        box_min, box_max = np.asarray(box_min, np.float64), np.asarray(box_max, np.float64)
        if box_min.shape != (3,) or box_max.shape != (3,) or not np.isfinite([box_min, box_max]).all():
            raise ValueError(f"a box needs finite x, y, z corners, got {box_min.tolist()} and {box_max.tolist()}")
        # Voxel i's centre is (i + 0.5) * resolution: the first and one past the last voxel inside.
        lo = np.ceil(box_min / self.resolution - 0.5).astype(np.int64)
        hi = np.floor(box_max / self.resolution - 0.5).astype(np.int64) + 1
        if (hi <= lo).any():
            return np.zeros((0, 3), np.int64)
        forgotten = np.concatenate([self.store.forget_box(lo, hi), self.window.forget_box(lo, hi)])
        self._removed.append(forgotten)
        if len(forgotten):
            # A correction mapping older scans again would bring the box back.
            self._restart_log("a box of the map was forgotten after them")
        return forgotten

    def _take_removed(self) -> np.ndarray:
        """The voxels that left the map since the changes were last taken (global indices (R, 3)):
        a reset's, a load's, a forgotten box's, and those a full store dropped (``memory.budget``)."""
        removed = [*self._removed, self.window.take_dropped()] if self.window.track_changes else self._removed
        self._removed = []
        return np.concatenate(removed) if removed else np.zeros((0, 3), np.int64)

    def take_changes(self, everything: bool = False) -> MapChanges:
        """The voxels that changed or left the map since the last call (``everything``: every
        voxel of the map, as after a load), for outputs that send only what changed."""
        removed = self._take_removed()
        indices, alpha = self.window.take_changes()
        if everything or self._everything_changed:
            self._everything_changed = False
            indices, alpha = self.items()
            if self._replaced_keys is not None:  # what the map this one replaced had and this one has not
                gone = np.setdiff1d(self._replaced_keys, voxel_keys(indices), assume_unique=True)
                removed = np.concatenate([removed, voxels_of_keys(gone)])
                self._replaced_keys = None
        return MapChanges(removed, indices, alpha)

    def take_change_records(self, palette: np.ndarray, everything: bool = False) -> tuple[np.ndarray, np.ndarray,
                                                                                          np.ndarray]:
        """``take_changes`` as (removed (R, 3), changed voxels' indices (N, 3), their records
        (``records.RECORD``)): for a window on a torch device the records are made there, so
        the changes come to the host as records, not as concentrations."""
        if isinstance(self.window, TorchWindow) and not (everything or self._everything_changed):
            removed = self._take_removed()
            indices, records = self.window.take_change_records(self.resolution, palette)
            return removed, indices, records
        changes = self.take_changes(everything)
        return changes.removed, changes.indices, records_from_alpha(changes.indices, changes.alpha, self.resolution,
                                                                    palette)

    def announce_replacement(self, previous_keys: np.ndarray) -> None:
        """This map took the place of another (a correction's): the next changes are every voxel,
        and the other's voxels (``previous_keys``: its ``voxel_keys()``) this map does not have as
        removed, so a copy kept from the changes becomes this map."""
        self._replaced_keys = np.unique(previous_keys)
        self._everything_changed = True


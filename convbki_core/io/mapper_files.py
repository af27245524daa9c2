"""A mapper's map files: save, snapshot, load and PLY export.

``MapFiles`` is a mixin of ``convbki_core.mapper.ConvBKIMapper``: writing the map's voxels and
its set-up into one self-describing map file (``map_file``), reading one back in its place
(checked against the mapper's classes, resolution and prior first), and the PLY export. A mixin
rather than one-line delegates: loading replaces the mapper's store, window and change
bookkeeping, which its methods own; the node and the tools call these on the mapper. It never
imports the mapper: it works on the mapper it is part of.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from convbki_core.geometry.grid import voxel_centres
from convbki_core.io.kernel_file import kernel_config_to_dict
from convbki_core.io.map_file import MAP_FORMAT, MAP_VERSION, MapSetupError, MapSnapshot, read_map, setup_differences
from convbki_core.io.ply import write_voxels_ply


class MapFiles:
    """The map as a file: ``save`` / ``snapshot``, ``load`` (``check_compatible`` and
    ``replace_with``), ``export_ply``."""

    def save(self, path: str | Path) -> None:
        """Write the whole map to one self-describing file, atomically (the memory budget plays no part)."""
        self.snapshot().write(path)

    def snapshot(self) -> MapSnapshot:
        """A copy of everything a map file holds (``items()`` returns fresh arrays), with its
        metadata: take it under a lock, ``write()`` it later."""
        indices, alpha = self.items()
        metadata = {
            "format": MAP_FORMAT,
            "version": MAP_VERSION,
            "resolution": self.resolution,
            "num_classes": self.num_classes,
            "num_voxels": int(indices.shape[0]),
            "frame_id": self.frame_id,
            "prior": self.prior,
            "local_bounds": [list(self.geometry.bounds_min), list(self.geometry.bounds_max)],
            "kernel": kernel_config_to_dict(self.kernel.to_config()),
            "scans_integrated": self.scans_integrated,
            "mapping": self.config.replace(frame_id=self.frame_id).mapping_record(self.resolution,
                                                                                  self.kernel.filter_size),
        }
        if self.sensor_position is not None:
            metadata["sensor_position"] = [float(v) for v in self.sensor_position]
        return MapSnapshot(metadata, indices, alpha, self.scan_log.copy() if self.scan_log is not None else None)

    def load(self, path: str | Path) -> dict:
        """Replace the map's voxels with those of a map file (resolution, classes and prior must
        match); the map is untouched if the file is unusable. Returns the file's metadata."""
        metadata, indices, alpha = read_map(path, with_scan_log=True)
        self.check_compatible(path, metadata)
        self.replace_with(metadata, indices, alpha)
        return metadata

    def check_compatible(self, path: str | Path, metadata: dict) -> None:
        """Raise ``MapSetupError`` unless a map file with this metadata (``read_map``) can be
        loaded into this mapper: the same classes, resolution and prior."""
        differences = setup_differences(metadata, self.resolution, self.num_classes, self.prior)
        if not differences:
            return
        first = differences[0]
        if first.what == "num_classes":
            message = f"{path}: map has {first.in_file} classes, the mapper {first.here}"
        elif first.what == "resolution":
            message = f"{path}: map resolution {first.in_file} m differs from the mapper's {first.here} m"
        else:
            message = (f"{path}: map prior {first.in_file} differs from the mapper's {first.here}: its voxels' "
                       "unobserved classes would hold the wrong concentration")
        raise MapSetupError(message, differences)

    def replace_with(self, metadata: dict, indices: np.ndarray, alpha: np.ndarray) -> None:
        """Make the map the given one (a map file's contents, ``read_map``, checked with
        ``check_compatible``). The window is placed around the sensor position the file
        recorded (else the centre of its voxels), so the map around the robot is at hand
        before the next scan. A map bigger than the mapper's memory budget is loaded whole (the
        user's file); the map is then full at once (``memory_state``)."""
        self.reset()  # its voxels count as removed
        self.store.write(indices, alpha, bounded=False)
        self.scans_integrated = int(metadata.get("scans_integrated", 0))
        position = metadata.get("sensor_position")
        if position is None and len(indices):
            position = voxel_centres((indices.min(axis=0) + indices.max(axis=0)) // 2, self.resolution)
        if position is not None:
            self.sensor_position = np.asarray(position, np.float64)
            self.window.move_to(self.geometry.origin_for(self.sensor_position))
        if self.scan_log is not None and metadata.get("scan_log") is not None:
            self.scan_log.adopt(metadata["scan_log"])
        else:  # a file without a (usable) log: its map is where corrections begin
            self._restart_log(metadata.get("scan_log_missing") or "they came from a map file without a scan log")
        self._everything_changed = True

    def export_ply(self, path: str | Path, max_variance: float | None = None) -> int:
        """Write the map as a PLY point cloud in class colours; returns the number of voxels written."""
        return write_voxels_ply(self.voxels(), path, max_variance=max_variance)

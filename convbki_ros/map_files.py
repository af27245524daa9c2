"""The node's files: the map loaded at start, saved on request, on a timer and at shutdown,
and exported as PLY.

Every write copies the map under the lock (a fraction of the time a write takes) and
writes the copy without it, atomically (a temporary file, fsync, rename): updates go on
while a large map is written, and a failed write leaves the previous file as it was. The
service and autosave callbacks run in their own callback group, off the thread that takes
clouds and odometry.
"""

from __future__ import annotations

import os
from pathlib import Path

from convbki_core.io.map_file import MapFileError
from convbki_core.io.ply import write_voxels_ply


class MapFiles:
    """Load, save and export for ``MapperNode`` (whose ``core`` holds the map and its lock)."""

    def __init__(self, node):
        self.node = node
        self.core = node.core
        self.saved_version = 0  # map_version at the last save (or load): autosave skips an unchanged map
        self.unreadable_map_file: str | None = None  # moved aside before the first save overwrites it

    def load_at_start(self) -> None:
        path = self.node.param("map_file")
        if not path or not Path(path).exists():
            return
        try:
            self.core.mapper.load(path)
        except MapFileError as error:
            if self.node.param("refuse_bad_map_file"):
                raise MapFileError(f"{error} (refuse_bad_map_file is true: not starting)") from None
            self.unreadable_map_file = path
            self.node.get_logger().error(
                f"{error}; starting with an EMPTY map. The file is kept: the first save moves it to "
                f"{path}.unreadable before writing the new map (set refuse_bad_map_file to exit instead)")
            return
        self.core.map_version += 1
        self.saved_version = self.core.map_version
        self.node.get_logger().info(f"loaded {len(self.core.mapper)} voxels from {path}")

    def save_map(self) -> tuple[bool, str]:
        """Write the map to map_file; (success, what happened)."""
        path = self.node.param("map_file")
        if not path:
            return False, "map_file parameter is empty: nowhere to save"
        try:
            if self.unreadable_map_file == path and os.path.lexists(path):
                os.replace(path, path + ".unreadable")
                self.node.get_logger().warning(f"moved the unreadable map file {path} to {path}.unreadable")
            self.unreadable_map_file = None
            with self.core.map_lock:
                snapshot = self.core.mapper.snapshot()
                version = self.core.map_version
            snapshot.write(path)
            self.saved_version = version
        except (OSError, ValueError) as error:
            return False, f"could not save {path}: {getattr(error, 'strerror', None) or error}"
        return True, f"saved {len(snapshot)} voxels to {path}"

    def on_save_map(self, request, response):
        response.success, response.message = self.save_map()
        self._log_outcome(response.success, response.message)
        return response

    def on_export_ply(self, request, response):
        path = self.node.param("ply_file")
        if not path:
            map_file = self.node.param("map_file")
            path = str(Path(map_file).with_suffix(".ply")) if map_file else "convbki_map.ply"
        try:
            with self.core.map_lock:
                indices, alpha = self.core.mapper.items()
            voxels = self.core.mapper.voxel_set(indices, alpha)
            count = write_voxels_ply(voxels, path, max_variance=self.node.param("max_variance") or None)
            response.success, response.message = True, f"wrote {count} voxels to {path}"
        except OSError as error:
            response.success, response.message = False, f"could not write {path}: {error.strerror or error}"
        self._log_outcome(response.success, response.message)
        return response

    def autosave(self) -> None:
        if self.node.param("map_file") and self.core.map_version != self.saved_version:
            ok, message = self.save_map()
            self._log_outcome(ok, f"autosave: {message}")

    def save_on_shutdown(self) -> str | None:
        """Save at shutdown when asked to and the map changed; what happened, or None."""
        path = self.node.param("map_file")
        if not (self.node.param("save_on_shutdown") and path and self.core.map_version):
            return None
        if self.core.map_version == self.saved_version:
            return f"the map is unchanged since it was last saved to (or loaded from) {path}"
        return self.save_map()[1]

    def _log_outcome(self, ok: bool, message: str) -> None:
        # Two call sites on purpose: rclpy remembers the severity of each logging call site
        # and raises (stopping the node) when one line logs at two severities.
        if ok:
            self.node.get_logger().info(message)
        else:
            self.node.get_logger().error(message)

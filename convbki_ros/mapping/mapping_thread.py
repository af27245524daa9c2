"""The node's mapping side: inputs in, the map updated, on its own thread.

``MappingCore`` builds the ``ConvBKIMapper`` from the node's checked start-up settings
(``settings``), takes clouds and odometry from the executor (``intake``: cheap checks only: a
cloud that can never be used is refused on arrival, before it waits or fills the queue), and runs
the update thread (``update_thread``), which places each cloud at its sensor pose (odometry
interpolated at the cloud's stamp, times the sensor's mount) and integrates it. Bad input never
touches the map: every rejection is counted and warned about once per problem (throttled). Here:
the set-up, the changes to the map other than scans (reset, cleared box, loaded file, a
correction's map) and what the outputs take from it.
"""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from convbki_core.io.map_file import MapSetupError, SetupDifference, read_map
from convbki_core.mapper import ConvBKIMapper
from convbki_core.warm_up import WarmUpReport, warm_up
from convbki_ros.inputs.sync import CloudQueue, Missing, PendingCloud, SensorFrames
from convbki_ros.inputs.tf_buffer import make_tf_lookup
from convbki_ros.inputs.transforms import stamp_to_ns
from convbki_ros.mapping.intake import InputIntake
from convbki_ros.mapping.update_thread import ScanIntegration
from convbki_ros.outputs.costmap import rolling_grid
from convbki_ros.params import StartupError
from convbki_ros.settings import StartSettings

TF_CACHE_S = 60.0  # seconds of TF kept: clouds may wait in the queue that long behind the newest


class MappingCore(InputIntake, ScanIntegration):
    """Inputs, the cloud queue, the update thread and the map, for ``MapperNode``."""

    def __init__(self, node, settings: StartSettings, status, warnings, label_map):
        self.node, self.status, self.warnings, self.label_map = node, status, warnings, label_map
        self.pose_source = settings.pose_source
        # TF is read (tf2_ros where a ROS 2 install has it, else the package's own buffer) unless
        # nothing can need it: the odometry's own frame and a fixed mount.
        self.tf, self.tf_missing = make_tf_lookup(node, TF_CACHE_S)
        self.frames = SensorFrames(settings.mount, self.tf, settings.map_frame)
        if self.tf is None and self.pose_source == "tf":
            raise StartupError(f"pose_source tf needs TF, which cannot be read here: {self.tf_missing}")
        if self.tf is None:
            node.get_logger().warning(f"TF is not read: {self.tf_missing}")
        # Every kernel is compiled (or loaded) while the map's window is allocated and filled.
        with ThreadPoolExecutor(max_workers=1) as pool:
            warming = pool.submit(warm_up, settings.mapper, settings.kernel)
            self.mapper = ConvBKIMapper(settings.mapper, settings.kernel)
            self.warm_up_report: WarmUpReport = warming.result()
        self.queue = CloudQueue(max_pose_jump=node.param("max_pose_jump"), placer=self._place,
                                locate=self._locate_by_tf if self.pose_source == "tf" else None)
        self.queue.transform_timeout = node.param("transform_timeout")
        self.costmap_profile = settings.costmap_profile
        self.map_lock = threading.Lock()
        self.map_version = 0  # bumped by every change of the map
        # Bumped whenever the map loses evidence (a reset, a forgotten box) or is replaced by a load:
        # a map file saved before then may hold what the map no longer does.
        self.lineage = 0
        self.forgotten_by: str | None = None  # what last made the map lose evidence, for the user
        self.newest_odometry_stamp: int | None = None  # ns, of accepted odometry
        self.odometry_frame: str | None = None
        self.last_stamp = None  # header stamp of the last integrated cloud
        self.position = np.zeros(3)  # the sensor's position in the map at the last integrated cloud
        self.on_integrated = lambda: None  # set by the node: the local window may be published

    @property
    def stopping(self) -> bool:
        return self.queue.stopping

    # -- set-up ----------------------------------------------------------------------------
    def mount_text(self) -> str:
        """The pose source, in words, for the start-up line."""
        if self.pose_source == "tf":
            return f"poses from TF ('{self.frames.map_frame}' -> each cloud's frame)"
        if self.frames.fixed is not None:
            mount = "sensor mount from base_to_sensor"
        else:
            mount = "sensor mount from TF" if self.tf is not None else "clouds in the odometry's child frame"
        if self.frames.map_frame and self.tf is not None:
            mount += f", map in '{self.frames.map_frame}' through TF where the odometry's frame differs"
        return f"poses from odometry, {mount}"

    def _place(self, pending: PendingCloud, lookup) -> tuple[np.ndarray | None, Missing | None]:
        """The cloud frame's pose in the map, from its odometry (the queue asks, lock held)."""
        return self.frames.place(self.odometry_frame or "", lookup, pending.msg.header.frame_id,
                                 stamp_to_ns(pending.msg.header.stamp))

    def _locate_by_tf(self, pending: PendingCloud):
        return self.frames.locate(pending.msg.header.frame_id, stamp_to_ns(pending.msg.header.stamp))

    def set_max_pose_jump(self, metres: float) -> None:
        with self.queue.changed:
            self.queue.poses.max_jump = float(metres)

    @property
    def frame(self) -> str:
        """The frame the map is built and published in: map_frame where TF takes the clouds
        into it, else the odometry's, once known."""
        if self.frames.map_frame and (self.tf is not None or self.pose_source == "tf"):
            return self.frames.map_frame
        return self.odometry_frame or self.mapper.frame_id

    def reset_map(self, why: str) -> int:
        """Clear the map; clouds received before now are stale (their poses may be too). Returns
        how many voxels it forgot; ``why`` says what asked for it (for the user)."""
        return self.take_and_reset(why)[0]

    def take_and_reset(self, why: str, keep: bool = False):
        """``reset_map``, returning (voxels forgotten, a snapshot of the map before, when ``keep``):
        both under one hold of the lock, so no scan falls between the two."""
        self.queue.new_generation()
        with self.map_lock:
            forgotten = len(self.mapper)
            snapshot = self.mapper.snapshot() if keep else None
            self.mapper.reset()
            self._lost_evidence(why)
        return forgotten, snapshot

    def clear_box(self, box_min, box_max) -> int:
        """Forget the voxels whose centres lie in the box (map frame, m); returns how many."""
        with self.map_lock:
            forgotten = len(self.mapper.forget_box(box_min, box_max))
            if forgotten:
                self._lost_evidence("~/clear_box")
        return forgotten

    def load_map(self, path: str, contents: tuple | None = None) -> tuple[int, int]:
        """Replace the map with a map file's; (voxels loaded, voxels replaced). The file is read
        (unless its ``read_map`` ``contents`` are given) and checked without the lock (mapping
        goes on meanwhile): ``MapFileError`` when it cannot be read or was built for another
        grid, classes, prior or frame, and the map is untouched."""
        metadata, indices, alpha = contents if contents is not None else read_map(path, with_scan_log=True)
        self.mapper.check_compatible(path, metadata)
        frame = metadata.get("frame_id") or None
        known = (self.frame if self.odometry_frame or self.frames.map_frame else None) or None
        if frame and known and frame != known:
            raise MapSetupError(f"{path}: the map was built in frame '{frame}', this node maps in '{known}'",
                                [SetupDifference("frame_id", frame, known)])
        with self.map_lock:
            replaced = len(self.mapper)
            self.mapper.replace_with(metadata, indices, alpha)
            if frame and not known:
                self.mapper.frame_id = frame
            if self.mapper.sensor_position is not None:
                self.position = self.mapper.sensor_position.copy()
            self._lost_evidence(f"~/load_map of {path}" if replaced else None)
        return len(indices), replaced

    def replace_mapper(self, mapper) -> None:
        """Put ``mapper`` in the place of the map (a correction's; call with the map lock held)."""
        self.mapper = mapper
        self.map_version += 1

    def _lost_evidence(self, why: str | None) -> None:
        """The map changed other than by adding evidence (call with the map lock held)."""
        self.map_version += 1
        self.lineage += 1
        if why:
            self.forgotten_by = why

    # -- what the outputs show (taken under the lock, encoded and sent without it) ------------
    def take_changes(self, everything: bool = False):
        """``MapChanges`` since the last call (``everything``: every voxel of the map)."""
        with self.map_lock:
            return self.mapper.take_changes(everything)

    def take_change_records(self, palette: np.ndarray, everything: bool = False):
        """(removed, changed voxels' indices, their records) since the last take (``everything``:
        every voxel of the map); the records made where the map lives."""
        with self.map_lock:
            return self.mapper.take_change_records(palette, everything)

    def map_copy(self):
        """(indices, alpha, map_version) of the whole map."""
        with self.map_lock:
            indices, alpha = self.mapper.items()
            return indices, alpha, self.map_version

    def rolling_costmap(self, size: float, window_extent: float):
        """(map_version, the planner's rolling grid around the sensor), from the window in place."""
        with self.map_lock:
            mapper = self.mapper
            grid = rolling_grid(mapper.window, mapper.resolution, mapper.prior, self.costmap_profile, self.position,
                                size, window_extent)
            return self.map_version, grid

    def window_records(self, palette: np.ndarray):
        """(map_version, the sensor's position (x, y, z) in the map, records of the window's voxels)."""
        with self.map_lock:
            return self.map_version, self.position.copy(), self.mapper.window_records(palette)

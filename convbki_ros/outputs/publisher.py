"""The node's map outputs, sent from one publishing thread so that no output slows mapping.

What each topic costs follows what it shows, never the whole map, except the whole map:

* ``semantic_map/updates`` (every ``publish_period``): the voxels whose shown statistics
  changed since the last updates message, and those that left the shown map (label 0). A
  receiver that applies every message in order holds exactly ``semantic_map``;
* ``semantic_map/view`` (every ``publish_period``, latched): the voxels within
  ``view_radius`` of the sensor, at most ``view_max_points``: what RViz draws by default,
  bounded whatever the map's size;
* ``semantic_map/local`` (after updates, at most every ``local_period``): the whole window
  around the sensor;
* ``semantic_map/costmap`` (with the cycle, latched, when the map changed): the planner's
  nav_msgs/OccupancyGrid around the sensor (``costmap_output``);
* ``semantic_map`` and ``semantic_map/variance`` (every ``map_period``, latched): the whole
  map, for late joiners and tools; sent only when it changed and someone listens. Its
  records are kept chunk by chunk (``ShownMap``) from the same changes the updates carry,
  so sending it copies bytes, never the map's concentrations under the map's lock.

Every topic is computed only while someone subscribes to it; the record layout
(``convbki_core.outputs.records.RECORD``) is the point layout, so records become message data
without another copy.
"""

from __future__ import annotations

import threading
import time

import numpy as np
from nav_msgs.msg import OccupancyGrid
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2

from convbki_core.outputs.records import RECORD, change_records, updates_records, view_records
from convbki_core.outputs.shown_map import ShownMap
from convbki_ros.outputs.cloud_encoding import encode_cloud, records_cloud
from convbki_ros.outputs.costmap import occupancy_grid

LATCHED = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
OUTPUTS = ("cycle", "map", "local")  # what a request may ask for


def _copy_into(records: np.ndarray):
    def fill(out: np.ndarray) -> None:
        np.copyto(out, records)

    return fill


class MapOutputs:
    """Publishers and the publishing thread of ``MapperNode`` (``node.core`` holds the map)."""

    def __init__(self, node):
        self.node = node
        self.core = node.core
        self.map = node.create_publisher(PointCloud2, "semantic_map", LATCHED)
        self.variance = node.create_publisher(PointCloud2, "semantic_map/variance", LATCHED)
        self.updates = node.create_publisher(PointCloud2, "semantic_map/updates", QoSProfile(
            depth=node.param("updates_depth"), reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.VOLATILE))
        self.view = node.create_publisher(PointCloud2, "semantic_map/view", LATCHED)
        self.local = node.create_publisher(PointCloud2, "semantic_map/local", 2)
        self.costmap = node.create_publisher(OccupancyGrid, "semantic_map/costmap", LATCHED)
        self.costmap_version_shown = -1
        self.costmap_sent = False  # then kept current, as the other latched topics
        self.changed = threading.Condition()
        self.due = dict.fromkeys(OUTPUTS, False)
        self.refresh_updates = False  # the shown map changed as a whole (max_variance): send every voxel
        self.view_version_shown = -1
        self.view_sent = False  # a view was sent: the latched topic holds one (then kept current)
        self.resend_view = False  # the map changed as a whole: send the view even to nobody
        self.shown: ShownMap | None = None  # built when the whole map is first asked for
        self.shown_changed = True  # since the whole map was last sent
        # semantic_map, semantic_map/variance were sent: their latched samples are kept current from then on
        self.map_sent = self.variance_sent = False
        self.thread = threading.Thread(target=self._loop, name="convbki_publish", daemon=True)

    def start(self) -> None:
        self.thread.start()

    def request(self, what: str, refresh: bool = False) -> None:
        """Ask for an output ("cycle": updates and view; "map": the whole map; "local")."""
        with self.changed:
            self.due[what] = True
            if refresh:  # everything is shown anew: the view and every voxel as an update
                self.refresh_updates = True
                self.view_version_shown = -1
            self.changed.notify_all()

    def map_replaced(self, refresh_updates: bool = False) -> None:
        """The shown map changed as a whole (a reset, a load, a forgotten box; with
        ``refresh_updates``, a new ``max_variance``): send the updates, the view and the whole
        map now, the latched ones even while nobody listens, so that the next subscriber never
        first receives the map as it was."""
        with self.changed:
            self.due["cycle"] = self.due["map"] = True
            self.refresh_updates = self.refresh_updates or refresh_updates
            self.view_version_shown = -1
            self.resend_view = True
            self.changed.notify_all()

    def stop(self) -> None:
        with self.changed:
            self.changed.notify_all()
        self.thread.join(timeout=0.3)

    def _loop(self) -> None:
        """The local window is sent the newest only and at most once per ``local_period``: when
        updates come faster than it can be encoded or watched, windows are skipped rather than
        queued, so watching the map never slows mapping down."""
        last_local = -1e9
        while True:
            with self.changed:
                while not self.core.stopping:
                    local_wait = last_local + self.node.param("local_period") - time.monotonic()
                    if self.due["cycle"] or self.due["map"] or (self.due["local"] and local_wait <= 0):
                        break
                    self.changed.wait(min(0.5, local_wait) if self.due["local"] else 0.5)
                if self.core.stopping:
                    return
                jobs = [what for what in OUTPUTS if self.due[what] and (what != "local" or local_wait <= 0)]
                for what in jobs:
                    self.due[what] = False
            if "local" in jobs:
                last_local = time.monotonic()
            for what in jobs:
                try:
                    getattr(self, f"_publish_{what}")()
                except Exception as error:  # a failed publish must not end the thread
                    if not self.node.context.ok():  # SIGINT/SIGTERM shut ROS down under it: the node is stopping
                        return
                    self.node.get_logger().error(f"publishing {what} failed: {error.__class__.__name__}: {error}")

    # -- the cycle: updates and view ---------------------------------------------------------
    def _publish_cycle(self) -> None:
        started = time.perf_counter()
        with self.changed:
            everything, self.refresh_updates = self.refresh_updates, False
        frame, stamp = self.core.frame, self.node.get_clock().now().nanoseconds
        sent = False
        listeners = self.updates.get_subscription_count()
        # Always taken, so that the changes do not pile up; as records only where they are sent or kept.
        if listeners or self.shown is not None:
            removed, indices, changed = self.core.take_change_records(self.node.palette, everything)
        else:
            self.core.take_changes(everything)
            removed = indices = ()
        if len(removed) or len(indices):
            records = updates_records(removed, changed, self.core.mapper.resolution, self.node.param("max_variance"))
            if self.shown is not None:
                self.shown.apply(np.concatenate([removed, indices]), records)
                self.shown_changed = True
            if listeners:
                self.updates.publish(records_cloud(stamp, frame, RECORD, len(records), _copy_into(records)))
                sent = True
        with self.changed:
            resend_view, self.resend_view = self.resend_view and self.view_sent, False
        if (self.view.get_subscription_count() or resend_view) and self.view_version_shown != self.core.map_version:
            version, centre, window = self.core.window_records(self.node.palette)
            records = view_records(self._shown(window), centre, self.node.param("view_radius"),
                                   self.node.param("view_max_points"))
            self.view.publish(records_cloud(stamp, frame, RECORD, len(records), _copy_into(records)))
            self.view_version_shown = version
            self.view_sent = sent = True
        if (self.costmap.get_subscription_count() or self.costmap_sent) and \
                self.costmap_version_shown != self.core.map_version:
            self._publish_costmap()
            sent = True
        if sent:
            self.node.status.published("cycle", 1e3 * (time.perf_counter() - started))

    def _publish_costmap(self) -> None:
        bounds = self.node.param("local_bounds")
        version, grid = self.core.rolling_costmap(self.node.param("costmap_size"), bounds[3] - bounds[0])
        stamp = self.core.last_stamp or self.node.get_clock().now().nanoseconds
        self.costmap.publish(occupancy_grid(grid, stamp, self.core.frame))
        self.costmap_version_shown = version
        self.costmap_sent = True

    def _shown(self, records: np.ndarray) -> np.ndarray:
        """The records of voxels in the shown map: not empty (class 0, free space) and, with a
        variance filter, confident enough."""
        keep = records["label"] != 0
        max_variance = self.node.param("max_variance")
        if max_variance > 0:
            keep &= records["variance"] <= max_variance
        return records if keep.all() else records[keep]

    # -- the local window ---------------------------------------------------------------------
    def _publish_local(self) -> None:
        if self.node.param("publish_local") and self.local.get_subscription_count():
            _, _, records = self.core.window_records(self.node.palette)
            records = records[records["label"] != 0]  # voxels seen empty (free space) are not shown
            stamp = self.core.last_stamp or 0
            self.local.publish(records_cloud(stamp, self.core.frame, RECORD, len(records), _copy_into(records)))

    # -- the whole map ------------------------------------------------------------------------
    def _publish_map(self) -> None:
        """``semantic_map`` and ``semantic_map/variance`` when the map changed and anyone listens,
        or once they were sent: a latched topic's sample is what the next subscriber gets first,
        so it is kept current even while nobody listens."""
        map_listeners = self.map.get_subscription_count() or self.map_sent
        variance_listeners = self.variance.get_subscription_count() or self.variance_sent
        if not (map_listeners or variance_listeners):
            return
        started = time.perf_counter()
        if self.shown is None:  # built once from a copy; the cycles keep it up to date from then on
            indices, alpha, _ = self.core.map_copy()
            records = change_records(np.zeros((0, 3), np.int64), indices, alpha, self.core.mapper.resolution,
                                     self.node.palette, self.node.param("max_variance"))
            del alpha
            self.shown = ShownMap()
            self.shown.apply(indices, records)
            self.shown_changed = True
        if not self.shown_changed:
            return
        stamp, frame = self.node.get_clock().now().nanoseconds, self.core.frame
        msg = records_cloud(stamp, frame, RECORD, len(self.shown), self.shown.fill)
        if map_listeners:
            self.map.publish(msg)
            self.map_sent = True
        if variance_listeners:
            records = np.frombuffer(msg.data, RECORD, count=msg.width)
            fields = {name: records[name] for name in ("x", "y", "z")}
            self.variance.publish(encode_cloud(stamp, frame, {**fields, "intensity": records["variance"]}))
            self.variance_sent = True
        self.shown_changed = False
        self.node.status.published("map", 1e3 * (time.perf_counter() - started))

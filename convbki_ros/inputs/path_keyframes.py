"""A SLAM's Path, decoded (``path_decoding``), checked and turned into keyframes: stamps and
poses of the body in the map frame, or one line that says why it cannot be used."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from convbki_core.geometry.poses import quaternion_to_matrix
from convbki_ros.inputs.path_decoding import DecodedPath
from convbki_ros.inputs.pose_buffer import QUATERNION_NORM_TOLERANCE, pose_problem

# How an RTAB-Map user gets a Path the node can place (the optimised graph, each node with its own stamp).
# (rtabmap.launch.py's namespace and node name; it publishes only while mapPath has a subscriber: this node.)
RTABMAP_PUBLISH_MAP = ('ros2 service call /rtabmap/rtabmap/publish_map rtabmap_msgs/srv/PublishMap '
                       '"{global_map: true, optimized: true, graph_only: true}"')


@dataclass
class Keyframes:
    """A Path's keyframes, checked: stamps (K,) ns ascending, poses (K, 4, 4) map <- body."""

    stamps_ns: np.ndarray
    poses: np.ndarray
    received: float  # time.monotonic() on arrival


def path_keyframes(path: DecodedPath, map_frame: str) -> Keyframes | str:
    """The keyframes of a decoded ``nav_msgs/Path``, or why it cannot be used (one line)."""
    if path.frame_id != map_frame:
        return f"its frame is '{path.frame_id}', not the map's '{map_frame}'"
    if not len(path):
        return "it holds no pose"
    outside = path.first_pose_outside(("", map_frame))
    if outside is not None:
        return f"pose {outside} is in frame '{path.frame_ids[outside]}', not the map's '{map_frame}'"
    positions, orientations = path.positions, path.orientations
    norms = np.linalg.norm(orientations, axis=1)
    usable = (np.isfinite(positions).all(axis=1) & np.isfinite(norms)
              & (np.abs(norms - 1.0) <= QUATERNION_NORM_TOLERANCE))
    if not usable.all():
        number = int(np.flatnonzero(~usable)[0])
        return f"pose {number}: {pose_problem(positions[number], orientations[number])}"
    stamps = path.stamps_ns
    if len(stamps) > 1 and (stamps == stamps[0]).all():
        return (f"its {len(stamps)} poses all share one stamp ({stamps[0] / 1e9:.3f} s), so no scan can be placed "
                f"between them by time. RTAB-Map's periodic mapPath is such a Path: its publish_map service "
                f"publishes mapPath with each node's own stamp, e.g. {RTABMAP_PUBLISH_MAP}")
    if (np.diff(stamps) <= 0).any():
        number = int(np.flatnonzero(np.diff(stamps) <= 0)[0]) + 1
        return (f"its stamps are not in ascending order (pose {number} at {stamps[number] / 1e9:.3f} s after "
                f"{stamps[number - 1] / 1e9:.3f} s)")
    poses = np.zeros((len(path), 4, 4))
    poses[:, :3, :3] = quaternion_to_matrix(orientations / norms[:, None])
    poses[:, :3, 3] = positions
    poses[:, 3, 3] = 1.0
    return Keyframes(stamps.copy(), poses, time.monotonic())

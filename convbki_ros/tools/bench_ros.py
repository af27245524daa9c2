"""The figures of ``bench`` that go through the node's ROS-side code (PointCloud2 encoding and
decoding, the odometry buffer). ``bench`` lives in the core, which must run without
convbki_ros, so it looks this module up at run time and reports these figures as not
measured where convbki_ros is not installed. Imports no rclpy: the codec works on plain
objects with the PointCloud2 attributes.
"""

from __future__ import annotations

import time
from types import SimpleNamespace

import numpy as np

from convbki_core.datasets.labels import load_label_map
from convbki_core.mapper import ConvBKIMapper
from convbki_core.pipeline import paper_mapper
from convbki_core.tools.bench_figures import median_ms, steady
from convbki_ros.cloud_encoding import map_cloud_fields, pack_fields
from convbki_ros.pointcloud import decode_cloud
from convbki_ros.pose_buffer import OdometryBuffer

# The keys the functions below add to bench's figures.
ENCODE_KEYS = ("encode_ms_per_million", "encoded_voxels")
SCAN_TO_MAP_KEYS = ("scan_to_map_ms",)
SCAN_PERIOD_NS = 100_000_000  # 10 Hz, the KITTI LiDAR


def encode_figures(mapper: ConvBKIMapper, repeat: int) -> dict:
    """Map voxels -> PointCloud2 field bytes (the ``/semantic_map`` point layout): ms per million
    voxels, and the voxels encoded."""
    voxels = mapper.voxels()
    colours = load_label_map().colors
    elapsed = median_ms(lambda: pack_fields(map_cloud_fields(voxels, colours)), repeat)
    return {"encode_ms_per_million": elapsed / (len(voxels) / 1e6), "encoded_voxels": len(voxels)}


def scan_to_map_figures(frames: list, repeat: int) -> dict:
    """The node's whole path for one scan: decode PointCloud2 + pose lookup + update + window move."""
    label_map = load_label_map()
    mapper = paper_mapper()
    poses = OdometryBuffer()
    clouds = []
    for number, frame in enumerate(frames[:repeat]):
        raw = label_map.to_raw(frame.input_labels).astype(np.uint32)
        layout, point_step, data = pack_fields({"x": frame.points[:, 0], "y": frame.points[:, 1],
                                                "z": frame.points[:, 2], "intensity": frame.remission,
                                                "label": raw})
        clouds.append((number, _CloudView(layout, point_step, data.tobytes(), len(frame.points))))
        # Odometry on both sides of the scan's stamp, so the lookup interpolates as the node's does.
        poses.add(number * SCAN_PERIOD_NS, frame.pose, "velo_link")
        poses.add(number * SCAN_PERIOD_NS + SCAN_PERIOD_NS // 2, frame.pose, "velo_link")
    times = []
    for number, cloud in clouds:
        started = time.perf_counter()
        decoded = decode_cloud(cloud, 20)
        pose = poses.lookup(number * SCAN_PERIOD_NS + SCAN_PERIOD_NS // 10).pose
        mapper.integrate(decoded.points, label_map.to_learning(decoded.labels), pose)
        times.append(1e3 * (time.perf_counter() - started))
    return {"scan_to_map_ms": steady(times)}


class _CloudView:
    """Just the PointCloud2 attributes the decoder reads."""

    def __init__(self, layout, point_step, data, count):
        self.fields = [SimpleNamespace(name=n, offset=o, datatype=d, count=1) for n, o, d in layout]
        self.point_step, self.row_step, self.data = point_step, point_step * count, data
        self.width, self.height, self.is_bigendian, self.is_dense = count, 1, False, True
        self.header = SimpleNamespace(frame_id="velo_link", stamp=SimpleNamespace(sec=0, nanosec=0))

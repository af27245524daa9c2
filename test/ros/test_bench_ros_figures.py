"""bench's ROS-side figures (encoding the map, scan to map, the node's start): bench_ros measures
them in a process of its own, on bench's drive or bench's own map of it; where convbki_ros is not
there, bench reports them as not measured, under the keys bench_ros fills."""

from __future__ import annotations

import importlib.util
from types import SimpleNamespace

import numpy as np

from convbki_core.tools import bench


def test_bench_without_convbki_ros_keeps_the_keys_and_says_why(monkeypatch):
    """The core never imports convbki_ros: bench runs the ROS-side figures as a process and,
    where convbki_ros is not there, reports them as not measured, under the keys bench_ros fills."""
    from convbki_core.offline import paper_mapper
    from convbki_ros.tools import bench_ros

    assert bench.ROS_ENCODE_KEYS == bench_ros.ENCODE_KEYS and bench.ROS_SCAN_TO_MAP_KEYS == bench_ros.SCAN_TO_MAP_KEYS
    assert set(bench_ros.START_KEYS) < set(bench.ROS_START_KEYS) <= set(bench.REPORTED)
    rng = np.random.default_rng(0)
    frame = SimpleNamespace(points=rng.uniform(-5, 5, (2000, 3)).astype(np.float32),
                            remission=np.zeros(2000, np.float32), input_labels=rng.integers(1, 20, 2000),
                            pose=np.eye(4))
    mapper = paper_mapper(local_bounds=((-8.0, -8.0, -2.0), (8.0, 8.0, 2.0)))
    mapper.integrate(frame.points, frame.input_labels, frame.pose)
    assert tuple(bench_ros.encode_figures(mapper, 1)) == bench_ros.ENCODE_KEYS
    assert tuple(bench_ros.scan_to_map_figures([frame], 1)) == bench_ros.SCAN_TO_MAP_KEYS

    find_spec = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *rest: None if name == "convbki_ros" else find_spec(name, *rest))
    args = SimpleNamespace(skip_start=False, drive_dir="unused", scans=3, repeat=1, seed=5)
    assert bench.ros_side_figures(args) == dict.fromkeys(bench.ROS_ENCODE_KEYS + bench.ROS_SCAN_TO_MAP_KEYS
                                                          + bench.ROS_START_KEYS)
    figures = {**dict.fromkeys(bench.REPORTED, 1.0), "machine": "test", **bench.ros_side_figures(args)}
    rows = {line.split()[0]: line for line in bench.format_report(figures, []).splitlines()[3:] if line}
    unmeasured = [key for key in bench.REPORTED if rows[key].endswith(bench.NOT_MEASURED)]
    assert unmeasured == ["encode_ms_per_million", "scan_to_map_ms", *bench.ROS_START_KEYS]


def test_bench_measures_the_ros_side_figures_in_a_process_of_their_own(tmp_path):
    """With convbki_ros there, bench_ros runs as its own process on bench's drive and every
    figure it owns comes back as a number."""
    args = SimpleNamespace(skip_start=True, drive_dir=str(tmp_path / "drive"), scans=4, repeat=2, seed=5)
    figures = bench.ros_side_figures(args)
    assert set(figures) == set(bench.ROS_ENCODE_KEYS + bench.ROS_SCAN_TO_MAP_KEYS)
    assert figures["encoded_voxels"] > 1000 and figures["encode_ms_per_million"] > 0 and figures["scan_to_map_ms"] > 0
    # Given bench's own map of the drive, bench_ros encodes that map instead of mapping the drive again.
    from convbki_core.offline import paper_mapper
    from convbki_core.synth.cached_drive import ensure_drive

    mapper = paper_mapper(local_bounds=((-8.0, -8.0, -2.0), (8.0, 8.0, 2.0)))
    frame = ensure_drive(tmp_path / "drive", 4, 5)[0]
    mapper.integrate(frame.points, frame.input_values, frame.pose)
    mapper.save(tmp_path / "small.npz")
    with_map = bench.ros_side_figures(args, tmp_path / "small.npz")
    assert with_map["encoded_voxels"] == len(mapper.voxels()) != figures["encoded_voxels"]

"""``realtime_check``'s reading of the node's counters line and of its arguments (no ROS needed)."""

from __future__ import annotations

import subprocess
import sys

import pytest

from convbki_ros.outputs.status import Snapshot
from convbki_ros.tools.realtime_check import LISTENERS, listeners_arg, parse_counters


def logged(snapshot: Snapshot) -> str:
    """The counters line as the node logs it every stats_period (``Snapshot.line``, through its logger)."""
    return f"[INFO] [1712345678.123456789] [convbki_mapper]: {snapshot.line()}"


def snapshot(**changes) -> Snapshot:
    values = dict(scans_in=150, integrated=146, dropped={"queue full": 3, "no pose": 1}, odometry_in=151,
                  odometry_rejected=2, queue=5, queue_peak=7, waiting_for_pose=1, map_voxels=2186145,
                  last_update_ms=12.4, median_update_ms=11.0, last_publish_ms=309.7, median_publish_ms=300.0,
                  maps_published=40, median_cycle_ms=25.0, map_version=146, odometry_delay_ms_median=3.0,
                  odometry_delay_ms_max=9.0, odometry_gap_ms_max=120.0, cycles_published=12)
    return Snapshot(**{**values, **changes})


def expected_sample(counters: Snapshot) -> dict:
    sample = {"scans_in": counters.scans_in, "integrated": counters.integrated, "dropped": counters.dropped_total,
              "queue": counters.queue, "voxels": counters.map_voxels, "queue_peak": counters.queue_peak,
              "reasons": counters.dropped}
    if counters.integrated:
        sample["update_ms"] = round(counters.last_update_ms)
    if counters.maps_published:
        sample["publish_ms"] = round(counters.last_publish_ms)
    return sample


def test_the_node_s_counters_line_is_read_back() -> None:
    with_drops = snapshot()
    assert parse_counters(logged(with_drops)) == expected_sample(with_drops)
    # No drops (no reasons in brackets), and odometry stamped in another clock (brackets and a
    # question mark after the numbers the parser reads).
    none_dropped = snapshot(scans_in=90, integrated=88, dropped={}, queue=0, queue_peak=3, map_voxels=51,
                            last_update_ms=7.0, last_publish_ms=0.0, odometry_delay_ms_median=5e9)
    line = logged(none_dropped)
    assert "odometry stamps not in the node's clock" in line
    assert parse_counters(line) == expected_sample(none_dropped)
    assert parse_counters("[INFO] [1.0] [convbki_mapper]: ConvBKI mapper ready: compound kernel") is None


def test_the_counters_line_leaves_out_what_was_not_measured() -> None:
    """Before anything was integrated or published, and on simulated time (a bag's /clock is set
    to the stamps it plays), the line shows no update, publish, cycle or odometry delay figure
    rather than a 0; each figure appears once it is measured."""
    replay = snapshot(integrated=0, maps_published=0, cycles_published=0, odometry_delay_measured=False,
                      last_update_ms=0.0, last_publish_ms=0.0, median_cycle_ms=0.0, odometry_delay_ms_median=0.0,
                      odometry_delay_ms_max=0.0)
    line = replay.line()
    for unmeasured in ("last update", "last map publish", "cycle median", "odometry delay", "0 ms,"):
        assert unmeasured not in line, line
    assert line.endswith("queue peak 7, longest gap between odometry arrivals 120 ms"), line
    assert parse_counters(logged(replay)) == expected_sample(replay)
    # No odometry at all (pose_source tf): no odometry figures either.
    assert snapshot(odometry_in=0, odometry_rejected=0).line().endswith("cycle median 25 ms")
    measured = snapshot(last_update_ms=31.0, last_publish_ms=88.0, median_cycle_ms=14.0)
    assert ("last update 31 ms, last map publish 88 ms, queue peak 7, cycle median 14 ms, odometry delay median 3 ms "
            "(max 9), longest gap between odometry arrivals 120 ms") in measured.line()


def test_listeners_argument() -> None:
    assert listeners_arg("map,local") == ("map", "local")
    assert listeners_arg("none") == ()
    assert set(LISTENERS) >= {"map", "local", "variance", "updates", "view"}
    assert LISTENERS["map"].qos == "latched" and LISTENERS["local"].qos == "volatile"


BAD_ARGUMENTS = [["--listeners", "foo"], ["--listeners", "map,map"], ["--busy-cores", "-1"],
                 ["--publication-mode", "fast"]]


@pytest.fixture(scope="module")
def bad_argument_runs():
    """realtime_check on each of BAD_ARGUMENTS as a process of its own, the four started together
    (each spends its second or two importing, on one core): {argv: process}."""
    processes = {tuple(argv): subprocess.Popen([sys.executable, "-m", "convbki_ros.tools.realtime_check", *argv],
                                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                               stdin=subprocess.DEVNULL) for argv in BAD_ARGUMENTS}
    yield processes
    for process in processes.values():
        if process.poll() is None:
            process.kill()
        process.communicate()


@pytest.mark.parametrize("argv", BAD_ARGUMENTS)
def test_bad_argument_is_one_line_exit_2(bad_argument_runs, argv: list[str]) -> None:
    process = bad_argument_runs[tuple(argv)]
    stdout, stderr = process.communicate(timeout=60)
    assert process.returncode == 2 and stdout == ""
    assert stderr.count("\n") == 1 and stderr.startswith("realtime_check: error: ")

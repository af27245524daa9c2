"""``realtime_check``'s reading of the node's counters line and of its arguments (no ROS needed)."""

from __future__ import annotations

import subprocess
import sys

import pytest

from convbki_ros.tools.realtime_check import LISTENERS, listeners_arg, parse_counters

LINE = ("[INFO] [1.0] [convbki_mapper]: scans in 150, integrated 146, dropped 4 (queue full 3, no pose 1), "
        "odometry in 150 (rejected 0), queue 2, map voxels 2186145, last update 12 ms, last map publish 310 ms")


def test_counters_line_with_and_without_queue_peak() -> None:
    sample = parse_counters(LINE)
    assert sample == {"scans_in": 150, "integrated": 146, "dropped": 4, "queue": 2, "voxels": 2186145,
                      "update_ms": 12, "publish_ms": 310, "reasons": {"queue full": 3, "no pose": 1}}
    newer = parse_counters(LINE.replace("dropped 4 (queue full 3, no pose 1)", "dropped 0") + ", queue peak 3")
    assert newer["dropped"] == 0 and newer["reasons"] == {} and newer["queue_peak"] == 3
    assert parse_counters("ConvBKI mapper ready") is None


def test_listeners_argument() -> None:
    assert listeners_arg("map,local") == ("map", "local")
    assert listeners_arg("none") == ()
    assert set(LISTENERS) >= {"map", "local", "variance", "updates", "view"}
    assert LISTENERS["map"].qos == "latched" and LISTENERS["local"].qos == "volatile"


@pytest.mark.parametrize("argv", [["--listeners", "foo"], ["--listeners", "map,map"], ["--busy-cores", "-1"],
                                  ["--publication-mode", "fast"]])
def test_bad_argument_is_one_line_exit_2(argv: list[str]) -> None:
    result = subprocess.run([sys.executable, "-m", "convbki_ros.tools.realtime_check", *argv], capture_output=True,
                            text=True, stdin=subprocess.DEVNULL, timeout=60)
    assert result.returncode == 2 and result.stdout == ""
    assert result.stderr.count("\n") == 1 and result.stderr.startswith("realtime_check: error: ")

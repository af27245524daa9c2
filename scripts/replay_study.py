"""Replay a bag to a fresh mapper node, the way a user does, and report what reached the map.

Each replay starts a node with the shipped parameters (``config/mapper.yaml``, ``use_sim_time``),
plays the bag with ``play_bag --clock`` (at ``--rate`` or paced with ``--wait-for-node``),
optionally stops the player with SIGSTOP for some seconds and resumes it, and prints one JSON
line per replay: scans integrated and dropped, the queue's peak, how many "no usable odometry"
warnings the node logged, the worst ``/diagnostics`` level it published, the odometry delay it
reported last, the corrections it applied (a drift bag's ``/pose_corrections``), and play_bag's
exit code and seconds; with ``--measure``, also the node's peak RSS, its last ``/diagnostics``
figures of the scan log and corrections, the seconds a ``~/save_map`` takes at the end, the
map file's size and its scan log folder's, and every 2 s the node's RSS beside the memory it
reports (``memory_N.jsonl``).

    scripts/venv_exec.sh .venv/bin/python scripts/replay_study.py out/demo/bag --replays 10
    scripts/venv_exec.sh .venv/bin/python scripts/replay_study.py out/demo/bag --stop-after 4 --stop-for 20
    scripts/venv_exec.sh .venv/bin/python scripts/replay_study.py out/demo/bag --wait-for-node
    scripts/venv_exec.sh .venv/bin/python scripts/replay_study.py out/drift/bag --param map_frame:=map \
        --expect-corrections 1

Run it alone on the machine: the figures are timings.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

from convbki_core.paths import config_dir
from convbki_ros.tools.demo import COUNTERS, LineReader

ODOMETRY_DELAY = re.compile(r"odometry delay median (\d+) ms \(max (\d+)\), longest gap between odometry arrivals "
                            r"(\d+) ms")


class DiagnosticsWatch:
    """The worst level the mapper published on /diagnostics, from a subscriber in this process."""

    def __init__(self, domain: str):
        os.environ["ROS_DOMAIN_ID"] = domain
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray

        self.rclpy = rclpy
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node("replay_study_diagnostics", context=self.context)
        self.worst = -1
        self.messages = []
        self.last: dict[str, str] = {}
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_message, 50)
        self.executor = rclpy.executors.SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self) -> None:
        try:
            while self.context.ok():
                self.executor.spin_once(timeout_sec=0.2)
        except self.rclpy.executors.ExternalShutdownException:
            pass  # close() shut the context down

    def _on_message(self, message) -> None:
        for status in message.status:
            if "convbki" in status.name or "mapper" in status.name:
                self.last = {item.key: item.value for item in status.values}
                level = int.from_bytes(status.level, "little") if isinstance(status.level, bytes) else int(status.level)
                if level > self.worst:
                    self.worst = level
                if level >= 2:
                    self.messages.append(status.message)

    def save_seconds(self) -> float | None:
        """Call the node's ~/save_map and time it (None: it failed)."""
        from std_srvs.srv import Trigger

        client = self.node.create_client(Trigger, "/convbki_mapper/save_map")
        if not client.wait_for_service(timeout_sec=30):
            return None
        started = time.monotonic()
        future = client.call_async(Trigger.Request())
        while not future.done() and time.monotonic() - started < 600:
            time.sleep(0.01)
        return round(time.monotonic() - started, 2) if future.done() and future.result().success else None

    def close(self) -> None:
        self.rclpy.shutdown(context=self.context)
        self.thread.join(5)


MEMORY_KEYS = ("map_megabytes", "scan_log_megabytes", "scan_log_disk_megabytes", "scan_log_write_backlog_megabytes",
               "correction_progress", "corrections_done", "live_lag_s")


def sample_memory(node: subprocess.Popen, watch: DiagnosticsWatch, path: Path, started: float) -> None:
    """Append the node's RSS (MB) and its last /diagnostics figures of memory to ``path`` every
    2 s while it runs (JSON lines)."""
    with path.open("w") as stream:
        while node.poll() is None:
            try:
                status = Path(f"/proc/{node.pid}/status").read_text()
            except OSError:
                return
            row = {"s": round(time.monotonic() - started, 1),
                   "rss_mb": int(re.search(r"VmRSS:\s+(\d+)", status).group(1)) // 1000,
                   **{key: watch.last.get(key) for key in MEMORY_KEYS}}
            stream.write(json.dumps(row) + "\n")
            stream.flush()
            time.sleep(2.0)


def replay(args: argparse.Namespace, index: int, out: Path) -> dict:
    domain = str(random.randint(1, 100))
    env = dict(os.environ, ROS_DOMAIN_ID=domain, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", PYTHONUNBUFFERED="1")
    watch = DiagnosticsWatch(domain)
    map_file = out / f"map_{index}.npz"
    node = subprocess.Popen(
        [sys.executable, "-m", "convbki_ros.main", "--ros-args", "--params-file", str(config_dir() / "mapper.yaml"),
         "-r", "cloud_in:=/kitti/velo/pointcloud", "-r", "odom:=/kitti/odom", "-p", "use_sim_time:=true",
         "-p", f"map_file:={map_file}", "-p", "stats_period:=1.0", "-p", "save_on_shutdown:=false",
         *[word for parameter in args.param for word in ("-p", parameter)]],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    result = {"replay": index}
    odometry_warnings = 0
    corrections: list[str] = []
    counters = (0, 0, 0, 0)
    peak = 0
    delay = None
    try:
        with (out / f"mapper_{index}.log").open("w") as log:
            reader = LineReader(node, log)
            reader.wait_for("mapper ready", timeout=180)
            command = [sys.executable, "-m", "convbki_ros.tools.play_bag", str(args.bag), "--clock"]
            command += ["--wait-for-node"] if args.wait_for_node else ["--rate", str(args.rate)]
            started = time.monotonic()
            player = subprocess.Popen(command, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
            stopped = False
            if args.measure:  # the node's memory beside what it says it holds, every 2 s
                sampler = threading.Thread(target=sample_memory, daemon=True,
                                           args=(node, watch, out / f"memory_{index}.jsonl", started))
                sampler.start()
            player_out: list[str] = []
            pump = threading.Thread(target=lambda: player_out.extend(player.stdout), daemon=True)
            pump.start()
            while True:
                if args.stop_for and not stopped and time.monotonic() - started >= args.stop_after:
                    player.send_signal(signal.SIGSTOP)
                    time.sleep(args.stop_for)  # the fault injected: the source stops for this long
                    player.send_signal(signal.SIGCONT)
                    stopped = True
                try:
                    line = reader.next(timeout=1.0 if args.stop_for and not stopped else 60)
                except Exception:
                    if player.poll() is None and args.stop_for and not stopped:
                        continue
                    raise
                odometry_warnings += "no usable odometry" in line
                if "pose_corrections applied" in line:
                    corrections.append(line[line.index("pose_corrections applied"):].strip())
                match = COUNTERS.search(line)
                if match:
                    counters = tuple(int(v) for v in match.groups())
                    peak = int(re.search(r"queue peak (\d+)", line).group(1))
                found = ODOMETRY_DELAY.search(line)
                if found:
                    delay = [int(v) for v in found.groups()]
                scans_in, integrated, dropped, queued = counters
                if player.poll() is not None and integrated + dropped == scans_in and queued == 0 \
                        and scans_in >= args.expect and len(corrections) >= args.expect_corrections:
                    break
                if player.poll() is not None and time.monotonic() - started > args.give_up:
                    break
            result["play_bag_seconds"] = round(time.monotonic() - started, 1)
            result["play_bag_rc"] = player.wait()
            pump.join(5)
            result["play_bag_said"] = [line.strip() for line in player_out if line.strip()][-3:]
            if args.measure:
                result["save_map_s"] = watch.save_seconds()
                status = Path(f"/proc/{node.pid}/status").read_text()
                result["peak_rss_mb"] = int(re.search(r"VmHWM:\s+(\d+)", status).group(1)) // 1000
                result["diagnostics"] = {key: value for key, value in watch.last.items()
                                         if key.startswith(("scan_log", "correction", "live_lag", "queue"))}
                folder = Path(f"{map_file}.scan_log")
                result["map_file_mb"] = round(map_file.stat().st_size / 1e6, 1) if map_file.exists() else None
                result["log_folder_mb"] = round(sum(f.stat().st_size for f in folder.iterdir()) / 1e6, 1) \
                    if folder.is_dir() else None
            node.send_signal(signal.SIGINT)
            node.wait(timeout=30)
            reader.finish()
    finally:
        if node.poll() is None:
            node.kill()
        watch.close()
    result.update(scans_in=counters[0], integrated=counters[1], dropped=counters[2], queue_peak=peak,
                  odometry_warnings=odometry_warnings, worst_diagnostics=watch.worst,
                  errors=watch.messages[:3], last_odometry_delay_ms=delay, corrections=corrections)
    return result


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("bag")
    parser.add_argument("--replays", type=int, default=1)
    parser.add_argument("--rate", type=float, default=1.0)
    parser.add_argument("--wait-for-node", action="store_true")
    parser.add_argument("--stop-after", type=float, default=4.0, help="seconds into the replay to stop the player")
    parser.add_argument("--stop-for", type=float, default=0.0, help="seconds the player stays stopped (0: never)")
    parser.add_argument("--expect", type=int, default=150, help="clouds in the bag")
    parser.add_argument("--expect-corrections", type=int, default=0, metavar="N",
                        help="wait for the node to apply N corrections (a drift bag's /pose_corrections)")
    parser.add_argument("--param", action="append", default=[], metavar="NAME:=VALUE",
                        help="a node parameter more (e.g. map_frame:=map for a drift bag's corrections)")
    parser.add_argument("--give-up", type=float, default=600.0, metavar="S",
                        help="seconds from the start of play after which a finished player's replay ends")
    parser.add_argument("--measure", action="store_true",
                        help="also the node's peak RSS, its last /diagnostics figures, a timed ~/save_map and the "
                        "sizes of the map file and its scan log folder")
    parser.add_argument("--out", default="out/replay_study")
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for index in range(args.replays):
        print(json.dumps(replay(args, index, out)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

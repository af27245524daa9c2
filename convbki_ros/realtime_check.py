"""``realtime_check``: does the mapper node keep up with a 10 Hz LiDAR while someone watches the map?

BENCHMARKS.md's node figure: replaying a 10 Hz bag of ~120 k-point scans at rate 1, the node
integrates every scan (none dropped) while publishing ``/semantic_map`` once a second. This
runs exactly that with the package's own programs, each in its own process over DDS:

* a drive in SemanticKITTI layout (``--dataset``; by default a synthetic one is simulated),
  turned into a bag with ``kitti_to_bag``;
* the ``mapper`` node with ``config/mapper.yaml`` (its default queue of 20 clouds, simulated
  time, ``publish_period`` 1 s, counters logged every second);
* a listener that subscribes ``/semantic_map`` the way RViz does (so the node really encodes
  and sends the whole map every second) and records when each map arrives;
* ``play_bag --clock --rate 1``.

It prints and writes (``OUT/realtime.json``) the node's own counters (scans in, integrated,
dropped), the maps received and their spacing, and the node's update and publish times.
It is a measurement, not a test: the exit code is 0 whenever the run completed, and 3
when the node dropped scans or the map was not published about once a second.

    .venv/bin/python -m convbki_ros.realtime_check [--frames 300] [--out out/realtime]
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import queue
import random
import re
import signal
import statistics
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from convbki_core.cli import UserError, positive, run
from convbki_core.fileio import atomic_write_bytes
from convbki_core.paths import config_dir
from convbki_ros.demo import LineReader, run_module

PROG = "realtime_check"
COUNTERS = re.compile(r"scans in (\d+), integrated (\d+), dropped (\d+).*queue (\d+), map voxels (\d+), "
                      r"last update (\d+) ms, last map publish (\d+) ms")

# The listener: an rclpy node that subscribes /semantic_map like RViz (reliable, transient
# local) and prints one line per map received: monotonic time, voxels, bytes.
_LISTENER = """
import signal, sys, time, rclpy
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2
rclpy.init()
node = rclpy.create_node("convbki_realtime_listener")
qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
def received(msg):
    print(f"map {time.monotonic():.3f} {msg.width} {len(msg.data)}", flush=True)
node.create_subscription(PointCloud2, "/semantic_map", received, qos)
signal.signal(signal.SIGTERM, lambda *_: (_ for _ in ()).throw(KeyboardInterrupt()))
print("listener ready", flush=True)
try:
    rclpy.spin(node)
except KeyboardInterrupt:
    pass
"""


def _step(message: str) -> None:
    print(f"[{PROG}] {message}", flush=True)


def _prepare_bag(args: argparse.Namespace, out: Path) -> tuple[Path, int]:
    if args.dataset:
        root, sequence = Path(args.dataset), args.sequence
    else:
        root, sequence = out / "data", "00"
        if not (root / "sequences" / sequence / "poses.txt").exists():
            _step(f"simulating a {args.frames}-scan drive into {root} (about 0.3 s a scan)")
            run_module("convbki_core.synthetic", "--out", str(root), "--sequence", sequence, "--frames",
                        str(args.frames), "--seed", str(args.seed), "--force", "--quiet")
    bag = out / "bag"
    _step(f"kitti_to_bag: scans 0:{args.frames} of {root / 'sequences' / sequence} -> {bag}")
    run_module("convbki_ros.kitti_to_bag", "--dataset", str(root), "--sequence", sequence, "--out", str(bag),
                "--frames", f"0:{args.frames}", "--force")
    return bag, args.frames


def _check(args: argparse.Namespace) -> int:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    bag, scans = _prepare_bag(args, out)
    domain = os.environ.get("ROS_DOMAIN_ID") or str(random.randint(1, 100))
    env = dict(os.environ, ROS_DOMAIN_ID=domain, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", PYTHONUNBUFFERED="1")

    def start(*command: str) -> subprocess.Popen:
        return subprocess.Popen([sys.executable, *command], env=env, stdin=subprocess.DEVNULL,
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)

    _step(f"mapper node (config/mapper.yaml, publish_period {args.publish_period} s) + /semantic_map listener + "
          f"play_bag --clock --rate {args.rate} (ROS_DOMAIN_ID {domain})")
    mapper = start("-m", "convbki_ros.mapper", "--ros-args", "--params-file", str(config_dir() / "mapper.yaml"),
                   "-r", "cloud_in:=/kitti/velo/pointcloud", "-r", "odom:=/kitti/odom", "-p", "use_sim_time:=true",
                   "-p", f"publish_period:={args.publish_period}", "-p", "stats_period:=1.0",
                   "-p", "save_on_shutdown:=false")
    listener = start("-c", _LISTENER)
    samples, arrivals = [], []
    counters = None
    # The logs stay open until both processes have ended: they print while shutting down.
    with (out / "mapper.log").open("w") as mapper_log, (out / "listener.log").open("w") as listener_log:
        node_lines = LineReader(mapper, mapper_log)
        listener_lines = LineReader(listener, listener_log)
        readers = (node_lines, listener_lines)
        try:
            node_lines.wait_for("mapper ready", timeout=120)
            listener_lines.wait_for("listener ready", timeout=60)
            played = time.monotonic()
            player = subprocess.Popen([sys.executable, "-m", "convbki_ros.play_bag", str(bag), "--clock", "--rate",
                                       str(args.rate)], env=env, stdin=subprocess.DEVNULL)
            unchanged_since = None  # when the counters last changed after the bag ended
            while True:
                line = node_lines.next(timeout=30)
                match = COUNTERS.search(line)
                if not match:
                    continue
                previous, counters = counters, tuple(int(v) for v in match.groups())
                samples.append(counters)
                print(f"\r[{PROG}]     {line.split(']: ')[-1].strip()}", end="", flush=True)
                if player.poll() is None:
                    continue
                if player.returncode != 0:
                    print()
                    raise UserError(f"play_bag failed with exit code {player.returncode}")
                scans_in, integrated, dropped, queued = counters[:4]
                if scans_in >= scans and integrated + dropped == scans_in and queued == 0:
                    break
                # Clouds lost on the way never arrive: stop once nothing has changed for 10 s.
                if unchanged_since is None or counters[:4] != (previous or ())[:4]:
                    unchanged_since = time.monotonic()
                elif time.monotonic() - unchanged_since > 10.0:
                    break
            print()
            replay_s = time.monotonic() - played
            time.sleep(2 * args.publish_period)  # the last map
            while True:
                try:
                    line = listener_lines.lines.get_nowait()
                except queue.Empty:  # everything read
                    break
                if line.startswith("map "):
                    _, at, width, size = line.split()
                    arrivals.append((float(at), int(width), int(size)))
        finally:
            for process in (mapper, listener):
                if process.poll() is None:
                    process.send_signal(signal.SIGINT)
            for process in (mapper, listener):
                try:
                    process.wait(timeout=20)
                except subprocess.TimeoutExpired:
                    process.kill()
                    process.wait()
            for reader in readers:
                reader.finish()
    return _report(args, out, scans, counters, samples, arrivals, replay_s)


def _report(args, out: Path, scans: int, counters, samples, arrivals, replay_s: float) -> int:
    scans_in, integrated, dropped, _, voxels = counters[:5]
    # Counter lines while scans were arriving (the last ones repeat after the bag ended).
    busy = [s for s in samples if 0 < s[1] < scans]
    update_ms = [s[5] for s in busy]
    publish_ms = [s[6] for s in busy if s[6] > 0]
    gaps = [b[0] - a[0] for a, b in itertools.pairwise(arrivals)]
    figures = {
        "scans_in_bag": scans, "scans_in": scans_in, "integrated": integrated, "dropped": dropped,
        "max_queue": max((s[3] for s in samples), default=0), "map_voxels": voxels,
        "replay_s": round(replay_s, 1), "rate": args.rate, "publish_period_s": args.publish_period,
        "maps_received": len(arrivals),
        "map_interval_median_s": round(statistics.median(gaps), 2) if gaps else None,
        "map_interval_max_s": round(max(gaps), 2) if gaps else None,
        "last_map_voxels": arrivals[-1][1] if arrivals else 0,
        "last_map_megabytes": round(arrivals[-1][2] / 1e6, 1) if arrivals else 0.0,
        "node_update_ms_median": statistics.median(update_ms) if update_ms else None,
        "node_update_ms_max": max(update_ms, default=None),
        "node_publish_ms_median": statistics.median(publish_ms) if publish_ms else None,
        "node_publish_ms_max": max(publish_ms, default=None),
        "cores": os.cpu_count(),
    }
    atomic_write_bytes(out / "realtime.json", (json.dumps(figures, indent=2) + "\n").encode())
    print(f"  scans in bag {scans}: received {scans_in}, integrated {integrated}, dropped {dropped} "
          f"(largest queue {figures['max_queue']})")
    print(f"  /semantic_map: {len(arrivals)} maps received in {replay_s:.0f} s of replay, "
          f"interval median {figures['map_interval_median_s']} s, max {figures['map_interval_max_s']} s; "
          f"last map {figures['last_map_voxels']:,} voxels, {figures['last_map_megabytes']} MB")
    print(f"  node: update median {figures['node_update_ms_median']} ms (max {figures['node_update_ms_max']}), "
          f"map publish median {figures['node_publish_ms_median']} ms (max {figures['node_publish_ms_max']})")
    print(f"  figures: {out / 'realtime.json'}; logs: {out / 'mapper.log'}, {out / 'listener.log'}")
    kept_up = dropped == 0 and integrated == scans and bool(gaps) and max(gaps) < 2.5 * args.publish_period
    if not kept_up:
        print(f"{PROG}: the node did NOT keep real time (see above)", file=sys.stderr)
    return 0 if kept_up else 3


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="out/realtime", help="results folder (default: %(default)s)")
    p.add_argument("--frames", type=positive(int, "frames"), default=300,
                   help="scans to replay (default: %(default)s = 30 s at 10 Hz)")
    p.add_argument("--seed", type=int, default=5, help="seed of the synthetic drive (default: %(default)s)")
    p.add_argument("--rate", type=positive(float, "rate"), default=1.0,
                   help="bag replay rate (default: %(default)s = real time)")
    p.add_argument("--publish-period", type=positive(float, "publish-period"), default=1.0,
                   help="the node's publish_period in seconds (default: %(default)s)")
    p.add_argument("--dataset", default=None, metavar="ROOT",
                   help="replay this SemanticKITTI-layout dataset instead of simulating one (e.g. out/bench/drive)")
    p.add_argument("--sequence", default="00", help="sequence of --dataset (default: %(default)s)")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    return run(PROG, _check, build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())

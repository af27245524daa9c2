"""``realtime_check``: does the mapper node keep up with a 10 Hz LiDAR while people watch its maps?

README's node figure: replaying a 10 Hz bag at rate 1, the node integrates every scan
(none dropped) while it publishes its map topics to processes that watch them. This runs
exactly that with the package's own programs, each in its own process over DDS:

* a drive in SemanticKITTI layout (``--dataset``; by default a synthetic one is simulated),
  turned into a bag with ``kitti_to_bag``;
* the ``mapper`` node with ``config/mapper.yaml`` (its default queue of clouds, simulated
  time, ``publish_period`` and ``map_period`` from the options, counters logged every second), with
  Fast DDS's publication mode chosen by ``--publication-mode``;
* one listener process per ``--listeners`` entry (``convbki_ros.tools.topic_listener``): an rclpy
  node that subscribes the topic the way RViz or ``ros2 topic echo`` does (so the node really
  encodes and sends what is watched) and records when each message arrives;
* ``--busy-cores`` processes that each keep one core busy all along, standing for another
  program on the robot's computer;
* ``play_bag --clock --rate 1 --wait-for-inputs``.

It prints and writes (``OUT/realtime.json``) the node's own counters (scans in, integrated,
dropped and why, queue peak, update and publish times, map voxels), the node's peak resident
memory, and per listener the messages received from the start of the replay, their spacing
and the last one's size. Logs:
``OUT/mapper.log``, ``OUT/listener_NAME.log``, ``OUT/busy_N.log``. It is a measurement: the
exit code is 0 when the node kept up (no scan dropped, every scan integrated), 3 when it did
not, 2 when the run could not be made (bad arguments, a program that failed). Maps that
arrived more than 2.5 publish periods apart are reported (``maps_on_time``), not judged: DDS
decides when a sent message arrives.

    .venv/bin/python -m convbki_ros.tools.realtime_check [--frames 300] [--out out/realtime]
        [--listeners map,updates,view,local] [--busy-cores 1] [--publication-mode synchronous]
        [--param forget_movers:=false ...]
"""

from __future__ import annotations

import argparse
import contextlib
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
from typing import NamedTuple

from convbki_core.io.atomic import atomic_write_bytes
from convbki_core.paths import config_dir
from convbki_core.tools.cli import UserError, positive, run
from convbki_ros.tools.demo import LineReader, run_module

PROG = "realtime_check"
COUNTERS = re.compile(
    r"scans in (?P<scans_in>\d+), integrated (?P<integrated>\d+), dropped (?P<dropped>\d+)(?: \((?P<reasons>[^)]*)\))?"
    r".*?, queue (?P<queue>\d+), map voxels (?P<voxels>\d+)(?:, last update (?P<update_ms>\d+) ms)?"
    r"(?:, last map publish (?P<publish_ms>\d+) ms)?, queue peak (?P<queue_peak>\d+)")
REASON = re.compile(r"\s*(.+?) (\d+)$")


class Watch(NamedTuple):
    """How a listener subscribes its topic (always reliable, like RViz)."""

    topic: str
    qos: str  # "latched" (transient local) or "volatile"
    depth: int
    type: str = "sensor_msgs/msg/PointCloud2"


# The known listeners: a new topic to watch is one line here.
LISTENERS: dict[str, Watch] = {
    "map": Watch("/semantic_map", "latched", 1),
    "local": Watch("/semantic_map/local", "volatile", 2),
    "variance": Watch("/semantic_map/variance", "latched", 1),
    "updates": Watch("/semantic_map/updates", "volatile", 10),
    "view": Watch("/semantic_map/view", "latched", 1),
    "costmap": Watch("/semantic_map/costmap", "latched", 1, "nav_msgs/msg/OccupancyGrid"),
}
PUBLICATION_MODES = {"default": None, "asynchronous": "ASYNCHRONOUS", "synchronous": "SYNCHRONOUS"}
MODE_VARIABLE = "RMW_FASTRTPS_PUBLICATION_MODE"  # convbki_ros.dds: the node keeps a value set by the user

# A busy core: a plain spin loop until SIGINT.
_BUSY = "import signal, sys\nsignal.signal(signal.SIGINT, lambda *_: sys.exit(0))\nprint('busy', flush=True)\n" \
        "while True:\n    pass\n"


def _step(message: str) -> None:
    print(f"[{PROG}] {message}", flush=True)


def listeners_arg(text: str) -> tuple[str, ...]:
    """argparse type: ``map,local``, or ``none``."""
    names = tuple(name.strip() for name in text.split(",") if name.strip())
    if names == ("none",):
        return ()
    unknown = [name for name in names if name not in LISTENERS]
    if unknown or not names or len(set(names)) != len(names):
        problem = f"unknown listener {unknown[0]!r}" if unknown else f"listeners must name each one once, got {text!r}"
        raise argparse.ArgumentTypeError(f"{problem} (known: {', '.join(LISTENERS)}; or none)")
    return names


def param_arg(text: str) -> str:
    """argparse type: ``name:=value``, a name the node declares."""
    from convbki_ros.params import SPECS

    name, separator, value = text.partition(":=")
    if not separator or not value:
        raise argparse.ArgumentTypeError(f"expected NAME:=VALUE, got {text!r}")
    if name not in SPECS:
        raise argparse.ArgumentTypeError(f"the mapper node has no parameter {name!r}")
    return text


def non_negative_int(text: str) -> int:
    if not text.isdigit():
        raise argparse.ArgumentTypeError(f"busy-cores must be 0 or a positive whole number, got {text!r}")
    return int(text)


def parse_counters(line: str) -> dict | None:
    """The node's counters line as numbers (``reasons``: why scans were dropped); None for other lines."""
    match = COUNTERS.search(line)
    if not match:
        return None
    sample = {key: int(value) for key, value in match.groupdict().items() if key != "reasons" and value is not None}
    sample["reasons"] = {m.group(1): int(m.group(2)) for part in (match["reasons"] or "").split(",")
                         if (m := REASON.match(part))}
    return sample


def _progress(sample: dict) -> tuple:
    return sample["scans_in"], sample["integrated"], sample["dropped"], sample["queue"]


def _peak_rss_mb(pid: int) -> float | None:
    """VmHWM of a live process (Linux), in MB."""
    with contextlib.suppress(OSError, ValueError, IndexError):
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return round(int(line.split()[1]) * 1024 / 1e6, 1)
    return None


def _prepare_bag(args: argparse.Namespace, out: Path) -> tuple[Path, int]:
    if args.dataset:
        root, sequence = Path(args.dataset), args.sequence
    else:
        root, sequence = out / "data", "00"
        if not (root / "sequences" / sequence / "poses.txt").exists():
            _step(f"simulating a {args.frames}-scan drive into {root} (about 0.3 s a scan)")
            run_module("convbki_core.tools.synth", "--out", str(root), "--sequence", sequence, "--frames",
                        str(args.frames), "--seed", str(args.seed), "--force", "--quiet")
    bag = out / "bag"
    _step(f"kitti_to_bag: scans 0:{args.frames} of {root / 'sequences' / sequence} -> {bag}")
    run_module("convbki_ros.tools.kitti_to_bag", "--dataset", str(root), "--sequence", sequence, "--out", str(bag),
                "--frames", f"0:{args.frames}", "--force")
    return bag, args.frames


def _messages(reader: LineReader, into: list, timeout: float = 0.0) -> None:
    """Move the listener's ``message`` lines read so far into ``into`` as (time, width, bytes);
    with a timeout, wait that long for one more line first."""
    with contextlib.suppress(queue.Empty):
        while True:
            line = reader.lines.get(timeout=timeout) if timeout > 0 else reader.lines.get_nowait()
            timeout = 0.0
            if line.startswith("message "):
                _, at, width, size = line.split()
                into.append((float(at), int(width), int(size)))


def _stop(processes: Sequence[subprocess.Popen]) -> None:
    """SIGINT, then a kill for what has not ended within 20 s."""
    for process in processes:
        if process.poll() is None:
            process.send_signal(signal.SIGINT)
    for process in processes:
        try:
            process.wait(timeout=20)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


def _check(args: argparse.Namespace) -> int:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for stale in (*out.glob("listener_*.log"), *out.glob("busy_*.log")):  # an earlier run's
        stale.unlink()
    bag, scans = _prepare_bag(args, out)
    domain = os.environ.get("ROS_DOMAIN_ID") or str(random.randint(1, 100))
    env = dict(os.environ, ROS_DOMAIN_ID=domain, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", PYTHONUNBUFFERED="1")
    node_env = {k: v for k, v in env.items() if k != MODE_VARIABLE}  # default: the node chooses
    if PUBLICATION_MODES[args.publication_mode]:
        node_env[MODE_VARIABLE] = PUBLICATION_MODES[args.publication_mode]
    watched = ", ".join(LISTENERS[name].topic for name in args.listeners) or "no listener"
    _step(f"mapper node (publish_period {args.publish_period} s, publication mode {args.publication_mode}) + "
          f"{watched} + {args.busy_cores} busy cores + play_bag --clock --rate {args.rate} (ROS_DOMAIN_ID {domain})")
    readers: dict[str, LineReader] = {}
    player = None
    samples: list[dict] = []
    arrivals: dict[str, list] = {name: [] for name in args.listeners}
    # The logs stay open until every process has ended: they print while shutting down.
    with contextlib.ExitStack() as logs:
        def start(name: str, what: str, *command: str, environment: dict = env) -> LineReader:
            process = subprocess.Popen([sys.executable, *command], env=environment, stdin=subprocess.DEVNULL,
                                       stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
            readers[name] = LineReader(process, logs.enter_context((out / f"{name}.log").open("w")), what)
            return readers[name]

        try:
            node = start("mapper", "the mapper node", "-m", "convbki_ros.main", "--ros-args", "--params-file",
                         str(config_dir() / "mapper.yaml"), "-r", "cloud_in:=/kitti/velo/pointcloud",
                         "-r", "odom:=/kitti/odom", "-p", "use_sim_time:=true",
                         "-p", f"publish_period:={args.publish_period}", "-p", f"map_period:={args.map_period}",
                         "-p", "stats_period:=1.0",
                         "-p", "save_on_shutdown:=false",
                         *[item for param in args.param for item in ("-p", param)], environment=node_env)
            for name in args.listeners:
                watch = LISTENERS[name]
                start(f"listener_{name}", f"the {name} listener", "-m", "convbki_ros.tools.topic_listener", "--topic",
                      watch.topic, "--qos", watch.qos, "--depth", str(watch.depth), "--type", watch.type)
            for index in range(1, args.busy_cores + 1):
                start(f"busy_{index}", f"busy process {index}", "-c", _BUSY)
            node.wait_for("mapper ready", timeout=120)
            for name, reader in readers.items():
                if name != "mapper":
                    reader.wait_for("listener ready" if name.startswith("listener_") else "busy", timeout=60)
            played = time.monotonic()
            player = subprocess.Popen([sys.executable, "-m", "convbki_ros.tools.play_bag", str(bag), "--clock",
                                       "--rate", str(args.rate), "--wait-for-inputs"], env=env,
                                      stdin=subprocess.DEVNULL)
            unchanged_since = None  # when the counters last changed after the bag ended
            while True:
                line = node.next(timeout=30)
                sample = parse_counters(line)
                if sample is None:
                    continue
                previous = samples[-1] if samples else None
                samples.append(sample)
                print(f"\r[{PROG}]     {line.split(']: ')[-1].strip()}", end="", flush=True)
                if player.poll() is None:
                    continue
                if player.returncode != 0:
                    print()
                    raise UserError(f"play_bag failed with exit code {player.returncode}")
                if sample["scans_in"] >= scans and sample["integrated"] + sample["dropped"] == sample["scans_in"] \
                        and sample["queue"] == 0:
                    break
                # Clouds lost on the way never arrive: stop once nothing has changed for 10 s.
                if previous is None or unchanged_since is None or _progress(sample) != _progress(previous):
                    unchanged_since = time.monotonic()
                elif time.monotonic() - unchanged_since > 10.0:
                    break
            print()
            replay_s = time.monotonic() - played
            # The last map: wait until the map listener holds one of the final size (bounded wait).
            deadline = time.monotonic() + 2.5 * args.map_period + 5.0
            for name, reader in readers.items():
                if name.startswith("listener_"):
                    _messages(reader, arrivals[name[len("listener_"):]])
            maps = arrivals.get("map")
            while maps is not None and not (maps and maps[-1][1] == samples[-1]["voxels"]) \
                    and time.monotonic() < deadline:
                _messages(readers["listener_map"], maps, timeout=deadline - time.monotonic())
            for name, reader in readers.items():
                if name != "mapper" and reader.process.poll() is not None:
                    raise UserError(f"{reader.name} stopped early (exit code {reader.process.returncode}); "
                                    f"see {out / (name + '.log')}")
            peak_rss_mb = _peak_rss_mb(node.process.pid)
        finally:
            _stop([p for p in (player, *(r.process for r in readers.values())) if p is not None])
            for reader in readers.values():
                reader.finish()
    for name, reader in readers.items():  # the lines printed while shutting down
        if name.startswith("listener_"):
            _messages(reader, arrivals[name[len("listener_"):]])
    # What a latched topic held before the replay (the empty map) is not a publication of the replay.
    arrivals = {name: [m for m in received if m[0] >= played] for name, received in arrivals.items()}
    return _report(args, out, scans, samples, arrivals, replay_s, peak_rss_mb)


def _median(values: list) -> float | None:
    return statistics.median(values) if values else None


def _listener_figures(watch: Watch, received: list) -> dict:
    gaps = [b[0] - a[0] for a, b in itertools.pairwise(received)]
    return {"topic": watch.topic, "qos": watch.qos, "depth": watch.depth, "messages": len(received),
            "interval_median_s": round(_median(gaps), 2) if gaps else None,
            "interval_max_s": round(max(gaps), 2) if gaps else None,
            "last_points": received[-1][1] if received else 0,
            "last_megabytes": round(received[-1][2] / 1e6, 1) if received else 0.0}


def _report(args, out: Path, scans: int, samples: list[dict], arrivals: dict, replay_s: float,
            peak_rss_mb: float | None) -> int:
    last = samples[-1]
    # Counter lines while scans were arriving (the last ones repeat after the bag ended).
    busy = [s for s in samples if 0 < s["integrated"] < scans]
    update_ms = [s["update_ms"] for s in busy]
    publish_ms = [s["publish_ms"] for s in busy if s.get("publish_ms", 0) > 0]
    listeners = {name: _listener_figures(LISTENERS[name], received) for name, received in arrivals.items()}
    figures = {
        "scans_in_bag": scans, "scans_in": last["scans_in"], "integrated": last["integrated"],
        "dropped": last["dropped"], "dropped_reasons": last["reasons"],
        "max_queue": max(max(s["queue"], s.get("queue_peak", 0)) for s in samples), "map_voxels": last["voxels"],
        "node_update_ms_median": _median(update_ms), "node_update_ms_max": max(update_ms, default=None),
        "node_publish_ms_median": _median(publish_ms), "node_publish_ms_max": max(publish_ms, default=None),
        "node_peak_rss_mb": peak_rss_mb, "listeners": listeners, "busy_cores": args.busy_cores,
        "publication_mode": args.publication_mode, "replay_s": round(replay_s, 1), "rate": args.rate,
        "publish_period_s": args.publish_period, "map_period_s": args.map_period, "cores": os.cpu_count(),
    }
    map_gap = listeners["map"]["interval_max_s"] if "map" in listeners else None
    figures["kept_up"] = kept_up = figures["dropped"] == 0 and figures["integrated"] == scans
    # Reported, not judged: a late map is a DDS delivery delay the node cannot shorten.
    figures["maps_on_time"] = "map" not in listeners or (map_gap is not None and
                                                         map_gap <= 2.5 * args.map_period)
    atomic_write_bytes(out / "realtime.json", (json.dumps(figures, indent=2) + "\n").encode())
    reasons = ", ".join(f"{reason} {count}" for reason, count in figures["dropped_reasons"].items())
    print(f"  scans in bag {scans}: received {figures['scans_in']}, integrated {figures['integrated']}, "
          f"dropped {figures['dropped']}{f' ({reasons})' if reasons else ''}; queue peak {figures['max_queue']}")
    print(f"  node: update median {figures['node_update_ms_median']} ms (max {figures['node_update_ms_max']}), "
          f"map publish median {figures['node_publish_ms_median']} ms (max {figures['node_publish_ms_max']}); "
          f"map voxels {figures['map_voxels']:,}; peak RSS {peak_rss_mb} MB")
    for name, f in listeners.items():
        print(f"  listener {name} ({f['topic']}, {f['qos']}, depth {f['depth']}): {f['messages']} messages, "
              f"interval median {f['interval_median_s']} s, max {f['interval_max_s']} s; "
              f"last {f['last_points']:,} points, {f['last_megabytes']} MB")
    if not listeners:
        print("  no listener")
    print(f"  {replay_s:.0f} s of replay at rate {args.rate}, publish period {args.publish_period} s, "
          f"publication mode {args.publication_mode}, busy cores {args.busy_cores} of {figures['cores']}")
    print(f"  figures: {out / 'realtime.json'}; logs: {out}/*.log")
    if not figures["maps_on_time"]:
        print(f"  note: maps arrived up to {map_gap} s apart (map period {args.map_period} s)")
    if not kept_up:
        print(f"{PROG}: the node did NOT keep real time: scans were dropped (see above)", file=sys.stderr)
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
    known = "; ".join(f"{name} = {w.topic} ({w.qos}, depth {w.depth})" for name, w in LISTENERS.items())
    p.add_argument("--map-period", type=positive(float, "map-period"), default=5.0,
                   help="the node's map_period (the whole map) in seconds (default: %(default)s)")
    p.add_argument("--listeners", type=listeners_arg, default=listeners_arg("map,updates,view,local"), metavar="LIST",
                   help="comma-separated topics to watch, each from its own subscriber process, the way RViz "
                        f"does (reliable): {known}; or none (default: map,updates,view,local)")
    p.add_argument("--busy-cores", type=non_negative_int, default=0, metavar="N",
                   help="processes that each keep one core busy during the replay, standing for another "
                        "program on the robot's computer (default: %(default)s)")
    p.add_argument("--publication-mode", choices=tuple(PUBLICATION_MODES), default="default",
                   help=f"Fast DDS publication mode of the node ({MODE_VARIABLE}): default leaves it to the "
                        "node (which chooses asynchronous), or asynchronous / synchronous (default: %(default)s)")
    p.add_argument("--param", action="append", default=[], type=param_arg, metavar="NAME:=VALUE",
                   help="a mapper node parameter over config/mapper.yaml (repeatable), e.g. forget_movers:=false")
    p.add_argument("--dataset", default=None, metavar="ROOT",
                   help="replay this SemanticKITTI-layout dataset instead of simulating one (e.g. out/bench/drive)")
    p.add_argument("--sequence", default="00", help="sequence of --dataset (default: %(default)s)")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    return run(PROG, _check, build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())

"""``make demo``: synthetic drive -> rosbag2 -> mapper node + play_bag over DDS -> map, pictures, mIoU.

Every step is one of the package's own programs, run the way a user would run them:
``synth`` writes a drive in SemanticKITTI layout (skipped when it is already there),
``kitti_to_bag`` turns it into a bag, then ``mapper`` and ``play_bag --clock`` run as
separate processes talking over DDS (simulated time). When every scan is integrated the
demo calls the node's ``~/save_map`` and ``~/export_ply`` services, stops the node with
SIGINT, draws the saved map from above (classes and variance) and scores it: the input
segmentation and the final map against the ground truth, over every point of the drive.

    .venv/bin/python -m convbki_ros.tools.demo [--out out/demo] [--frames 150] [--dataset ROOT --sequence SS]
"""

from __future__ import annotations

import argparse
import json
import os
import queue
import random
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from convbki_core.config import MapperConfig
from convbki_core.datasets.semantic_kitti import SemanticKittiSequence
from convbki_core.geometry.grid import transform_points
from convbki_core.measures.metrics import ConfusionMatrix
from convbki_core.measures.trails import SweptSpace
from convbki_core.paths import config_dir, kernel_path
from convbki_core.synth.cached_drive import read_synth_record
from convbki_core.tools.cli import UserError, positive, run

PROG = "demo"
COUNTERS = re.compile(r"scans in (\d+), integrated (\d+), dropped (\d+).*queue (\d+)")


def _step(message: str) -> None:
    print(f"[demo] {message}", flush=True)


def _python_module(module: str, *args: str, env: dict | None = None, **kwargs) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", module, *args], env=env, stdin=subprocess.DEVNULL, **kwargs)


def run_module(module: str, *args: str) -> None:
    """``python -m module args`` to completion; a non-zero exit is a one-line UserError."""
    code = subprocess.call([sys.executable, "-m", module, *args], stdin=subprocess.DEVNULL)
    if code != 0:
        raise UserError(f"{module} {' '.join(args)} failed with exit code {code}")


def score_final_map(map_file: Path, dataset: SemanticKittiSequence) -> dict:
    """Input and final-map scores over every point of the drive (points without map evidence keep the input
    label), and the map's trail voxels where the ground truth marks moving objects."""
    from convbki_core.mapper import ConvBKIMapper  # torch loads for the scoring only

    mapper = ConvBKIMapper(MapperConfig.paper(device="cpu", free_space=True), kernel_path("semantic_kitti_compound"))
    mapper.load(map_file)
    swept = SweptSpace(mapper.resolution)
    label_map = dataset.label_map
    input_scores = ConfusionMatrix(label_map.num_classes, label_map.ignore_classes)
    map_scores = ConfusionMatrix(label_map.num_classes, label_map.ignore_classes)
    for frame in dataset:
        points_map = transform_points(frame.points, frame.pose)
        labels, has_evidence = mapper.labels_at(points_map, within_window=False)
        input_scores.add(frame.ground_truth, frame.input_labels)
        map_scores.add(frame.ground_truth, np.where(has_evidence, labels, frame.input_labels))
        if frame.moving is not None:
            swept.add(points_map, frame.moving)
    voxels = mapper.voxels()
    trails = swept.trail_voxels(voxels.indices, voxels.label, label_map.movable_classes)
    return {"input": input_scores.summary(label_map.class_names), "map": map_scores.summary(label_map.class_names),
            "voxels": int(np.count_nonzero(voxels.label != 0)), "trail_voxels": trails,
            "moving_points": swept.moving_points, "mapper": mapper}


def save_costmap_picture(map_file: Path, label_map, path: Path) -> None:
    """The saved map's costmap for the car profile (what the node's ~/get_costmap answers), with
    a path planned between two road cells far apart."""
    from convbki_core.costmap.columns import column_costs
    from convbki_core.costmap.grid import rasterise
    from convbki_core.costmap.profile import load_profile
    from convbki_core.io.map_file import read_map
    from convbki_core.paths import traversability_profile
    from convbki_core.tools.plots import save_costmap_pictures

    metadata, indices, alpha = read_map(map_file)
    resolution = float(metadata["resolution"])
    profile = load_profile(traversability_profile("car"), label_map.class_names)
    columns = column_costs(indices, alpha, resolution, profile, float(metadata["prior"]))
    grid = rasterise(columns, resolution)
    # Road cells: columns whose ground voxel is most likely road.
    road = np.zeros(grid.values.shape, bool)
    ground_voxels = {tuple(cell) + (int(z),) for cell, z in zip(columns.cells.tolist(), columns.ground)}
    keep = np.array([tuple(i) in ground_voxels for i in indices.tolist()])
    on_road = keep & (alpha.argmax(axis=1) == label_map.class_names.index("road"))
    local = indices[on_road, :2] - grid.origin
    road[local[:, 1], local[:, 0]] = True
    save_costmap_pictures({"costmap (car profile)": grid}, road, path,
                          title="semantic_map/costmap of the demo's map: 0 free (white) .. 100 lethal (black)")


def _demo(args: argparse.Namespace) -> int:
    out = Path(args.out)
    if args.dataset:  # a wrong --dataset is reported before anything is created
        SemanticKittiSequence(args.dataset, args.sequence).check_files()
    if out.exists() and not out.is_dir():
        raise UserError(f"{out}: not a folder (--out names the results folder)")
    out.mkdir(parents=True, exist_ok=True)
    started = time.monotonic()
    if args.dataset:
        root, sequence = Path(args.dataset), args.sequence
    else:
        root, sequence = out / "data", "00"
        record = read_synth_record(root / "sequences" / sequence) or {}
        wanted = (args.seed, args.frames, args.movers)
        written = (record.get("seed"), record.get("frames"), (record.get("movers") or {}).get("requested", 0))
        if written != wanted or not (root / "sequences" / sequence / "poses.txt").exists():
            _step(f"1/5 synthetic drive: {args.frames} scans -> {root}")
            run_module("convbki_core.tools.synth", "--out", str(root), "--sequence", sequence, "--frames",
                        str(args.frames), "--seed", str(args.seed), "--movers", str(args.movers), "--force")
        else:
            _step(f"1/5 synthetic drive: reusing {root / 'sequences' / sequence}")
    dataset = SemanticKittiSequence(root, sequence)
    bag = out / "bag"
    _step(f"2/5 kitti_to_bag -> {bag}")
    run_module("convbki_ros.tools.kitti_to_bag", "--dataset", str(root), "--sequence", sequence, "--out", str(bag),
                "--force")

    domain = os.environ.get("ROS_DOMAIN_ID") or str(random.randint(1, 100))
    env = dict(os.environ, ROS_DOMAIN_ID=domain, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", PYTHONUNBUFFERED="1")
    map_file = out / "map.npz"
    map_file.unlink(missing_ok=True)
    _step(f"3/5 mapper node + play_bag --clock --rate {args.rate} (ROS_DOMAIN_ID {domain})")
    mapper = _python_module(
        "convbki_ros.main", "--ros-args", "--params-file", str(config_dir() / "mapper.yaml"),
        "-r", "cloud_in:=/kitti/velo/pointcloud", "-r", "odom:=/kitti/odom", "-p", "use_sim_time:=true",
        "-p", f"map_file:={map_file}", "-p", "stats_period:=1.0", "-p", "cloud_queue_size:=1000",
        "-p", "save_on_shutdown:=false", env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    log_path = out / "mapper.log"
    counters = (0, 0, 0, 0)
    try:
        with log_path.open("w") as log:
            reader = LineReader(mapper, log)
            reader.wait_for("mapper ready", timeout=120)
            # --wait-for-inputs: the first message goes out once the node's readers have matched.
            player = _python_module("convbki_ros.tools.play_bag", str(bag), "--clock", "--rate", str(args.rate),
                                    "--wait-for-inputs", env=env)
            while True:  # follow the node's counters until every scan is in
                line = reader.next(timeout=30)
                match = COUNTERS.search(line)
                if match:
                    counters = tuple(int(v) for v in match.groups())
                    print(f"\r[demo]     {line.split(']: ')[-1].strip()}", end="", flush=True)
                scans_in, integrated, dropped, queued = counters
                if player.poll() is not None and scans_in >= len(dataset) and integrated + dropped == scans_in \
                        and queued == 0:
                    break
            print()
            if player.wait() != 0:
                raise UserError("play_bag failed")
            _call_services(env)
            mapper.send_signal(signal.SIGINT)
            mapper.wait(timeout=20)
    finally:
        if mapper.poll() is None:
            mapper.kill()
    if counters[2]:
        _step(f"warning: the node dropped {counters[2]} scans (see {log_path})")

    _step("4/5 scoring the saved map against the ground truth")
    scores = score_final_map(map_file, dataset)
    _step("5/5 pictures")
    from convbki_core.tools.plots import save_map_picture

    picture = out / "map.png"
    title = (f"convbki_ros demo: {len(dataset)} scans, {scores['voxels']:,} voxels; mIoU input "
             f"{scores['input']['miou']:.3f} -> map {scores['map']['miou']:.3f}")
    save_map_picture(scores.pop("mapper").voxels(), dataset.label_map, 0.2, picture, title)
    costmap_picture = out / "costmap.png"
    save_costmap_picture(map_file, dataset.label_map, costmap_picture)
    summary = {"scans": len(dataset), "integrated": counters[1], "dropped": counters[2], "voxels": scores["voxels"],
               "input_miou": scores["input"]["miou"], "map_miou": scores["map"]["miou"],
               "moving_points": scores["moving_points"], "trail_voxels": scores["trail_voxels"],
               "iou": {"input": scores["input"]["iou"], "map": scores["map"]["iou"]},
               "seconds": round(time.monotonic() - started, 1)}
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    print()
    print(f"  scans {len(dataset)}: integrated {counters[1]}, dropped {counters[2]}; map voxels {scores['voxels']:,}; "
          f"trail voxels {scores['trail_voxels']:,} ({scores['moving_points']:,} moving points in the drive)")
    print(f"  {'class':<14}{'input IoU':>10}{'map IoU':>10}")
    for name, value in scores["input"]["iou"].items():
        print(f"  {name:<14}{100 * value:>10.1f}{100 * scores['map']['iou'][name]:>10.1f}")
    print(f"  {'mIoU':<14}{100 * scores['input']['miou']:>10.1f}{100 * scores['map']['miou']:>10.1f}")
    print(f"  map: {map_file}  ply: {out / 'map.ply'}  pictures: {picture}, {costmap_picture}  bag: {bag}")
    print(f"  done in {summary['seconds']:.0f} s")
    return 0


class LineReader:
    """Reads a process's output on a thread, so waiting for a line can time out."""

    def __init__(self, process: subprocess.Popen, log, name: str = "the mapper node"):
        self.process = process
        self.log = log
        self.name = name  # who is waited for, in error messages
        self.lines: queue.Queue[str] = queue.Queue()
        self.thread = threading.Thread(target=self._pump, daemon=True)
        self.thread.start()

    def finish(self, timeout: float = 5.0) -> None:
        """Wait (after the process ended) until its last lines are in the log; then it may be closed."""
        self.thread.join(timeout)

    def _pump(self) -> None:
        for line in self.process.stdout:
            self.log.write(line)
            self.log.flush()
            self.lines.put(line)

    def next(self, timeout: float) -> str:
        try:
            return self.lines.get(timeout=timeout)
        except queue.Empty:
            if self.process.poll() is not None:
                raise UserError(f"{self.name} stopped (exit code {self.process.returncode}); see its log") \
                    from None
            raise UserError(f"{self.name} said nothing for {timeout:.0f} s; see its log") from None

    def wait_for(self, text: str, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while text not in self.next(max(0.1, deadline - time.monotonic())):
            if time.monotonic() > deadline:
                raise UserError(f"{self.name} did not say '{text}' within {timeout:.0f} s")


def _call_services(env: dict) -> None:
    """Call ~/save_map and ~/export_ply from a short-lived rclpy node on the demo's domain."""
    code = subprocess.call([sys.executable, "-c", _SERVICE_CALLER], env=env, stdin=subprocess.DEVNULL)
    if code != 0:
        raise UserError("calling the mapper's services failed")


_SERVICE_CALLER = """
import sys, rclpy
from std_srvs.srv import Trigger
rclpy.init()
node = rclpy.create_node("convbki_demo_client")
for name in ("/convbki_mapper/save_map", "/convbki_mapper/export_ply"):
    client = node.create_client(Trigger, name)
    if not client.wait_for_service(timeout_sec=30):
        sys.exit(f"{name} not available")
    future = client.call_async(Trigger.Request())
    rclpy.spin_until_future_complete(node, future, timeout_sec=120)
    result = future.result()
    print(f"[demo]     {name}: {result.message}", flush=True)
    if not result.success:
        sys.exit(1)
node.destroy_node()
rclpy.shutdown()
"""


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0] + ".",
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="out/demo", help="results folder (default: %(default)s)")
    p.add_argument("--frames", type=positive(int, "frames"), default=150,
                   help="scans of the synthetic drive (default: %(default)s)")
    p.add_argument("--seed", type=int, default=11, help="seed of the synthetic drive (default: %(default)s)")
    p.add_argument("--movers", type=int, default=12,
                   help="moving road users (cars, trucks, cyclists, pedestrians) in the synthetic drive "
                   "(default: %(default)s)")
    p.add_argument("--rate", type=positive(float, "rate"), default=1.0,
                   help="bag replay rate (default: %(default)s = real time)")
    p.add_argument("--dataset", default=None, metavar="ROOT",
                   help="map this SemanticKITTI-layout dataset instead of a synthetic drive (e.g. the real one)")
    p.add_argument("--sequence", default="08", help="sequence of --dataset (default: %(default)s)")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    return run(PROG, _demo, build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())

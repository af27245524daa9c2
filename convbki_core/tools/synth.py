"""``synth``: write a synthetic SemanticKITTI-format drive (64-beam LiDAR scans).

A procedural street scene (roads, parking lanes, raised sidewalks with curbs, buildings,
fences, hedges, street trees, poles, traffic signs, parked cars, trucks, buses, bicycles,
motorcycles, people, cyclists; all static) is scanned by a simulated Velodyne HDL-64E on a
car driving a loop of city blocks at 10 Hz. With ``--movers N`` it also has N moving road
users (cars, trucks, buses, cyclists, motorcyclists, pedestrians), labelled with the moving
raw ids (252-259) and their own instance ids; ``--traffic varied`` adds movers that stop and
go on, slow cyclists by the kerb, close passes and pedestrians pausing on the sidewalk. Output:
ROOT/sequences/SS/ with velodyne/, labels/ (ground truth with instance ids), predictions/ (the
ground truth with realistic, calibrated segmentation noise: the input segmentation; with
``--moving-labels`` it tells moving from static as a multi-scan network does), optionally
probabilities/, and calib.txt, poses.txt, times.txt, synth.yaml (the settings and what was
measured), plus movers.json with movers (their boxes, scan by scan; format in
convbki_core.synth.movers).
See convbki_core/synth/ for the models.
"""

from __future__ import annotations

import argparse
import math
import shutil
import sys
from collections.abc import Sequence
from pathlib import Path

from convbki_core.tools.cli import sequence_arg

PROG = "synth"
# The behaviour mixes of --traffic: the keys of convbki_core.synth.traffic.TRAFFIC (not imported
# here, so that --help needs no numpy).
TRAFFIC_CHOICES = ("classic", "varied")


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors (exit 2), no usage dump."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(2, f"{self.prog}: error: {message}\n")


def _positive_int(what: str, upper: int | None = None):
    def parse(text: str) -> int:
        try:
            n = int(text)
        except ValueError:
            n = 0
        if n <= 0 or (upper is not None and n > upper):
            bound = f" in 1..{upper}" if upper else ""
            raise argparse.ArgumentTypeError(f"{what} must be a positive integer{bound}, got {text!r}")
        return n
    return parse


frames_count = _positive_int("frames")


def _count(what: str, upper: int):
    def parse(text: str) -> int:
        try:
            n = int(text)
        except ValueError:
            n = -1
        if not 0 <= n <= upper:
            raise argparse.ArgumentTypeError(f"{what} must be an integer in 0..{upper}, got {text!r}")
        return n
    return parse


def _float_in(what: str, lo: float, hi: float, lo_open: bool = False):
    def parse(text: str) -> float:
        try:
            x = float(text)
        except ValueError:
            x = math.nan
        if not (math.isfinite(x) and (x > lo if lo_open else x >= lo) and x <= hi):
            left = "(" if lo_open else "["
            raise argparse.ArgumentTypeError(f"{what} must be a number in {left}{lo:g}, {hi:g}], got {text!r}")
        return x
    return parse


def build_parser() -> argparse.ArgumentParser:
    """Command-line parser."""
    p = _Parser(
        prog=PROG,
        description="Write a synthetic drive in SemanticKITTI format: LiDAR scans, ground-truth labels, "
        "a noisy input segmentation, poses, calibration and stamps.",
        epilog="Example: synth --out data/synthetic --sequence 00 --frames 200 --seed 0 --probabilities",
    )
    p.add_argument("--out", required=True, metavar="ROOT", type=Path,
                   help="dataset root to write; the drive goes to ROOT/sequences/SS")
    p.add_argument("--sequence", default="00", metavar="SS", type=sequence_arg,
                   help="sequence id to write (default: %(default)s)")
    p.add_argument("--frames", default=100, type=frames_count, metavar="N",
                   help="number of scans, 0.1 s apart (default: %(default)s)")
    p.add_argument("--seed", default=0, type=int, metavar="S",
                   help="random seed of the scene layout, route, sensor noise and segmentation noise: the same "
                   "seed writes the same drive, byte for byte (default: %(default)s)")
    p.add_argument("--input-miou", default=0.55, type=_float_in("--input-miou", 0.0, 1.0, lo_open=True),
                   metavar="M", help="target mIoU of the input segmentation in predictions/ (fraction, class 0 "
                   "ignored, mean over classes in the ground truth); the noise strength is calibrated to reach it "
                   "(within about 0.01) on a sample of the drive's own points, simulated in a first pass "
                   "(default: %(default)s)")
    p.add_argument("--noise-strength", default=None, type=_float_in("--noise-strength", 0.0, 12.0), metavar="K",
                   help="use this segmentation-noise strength (0 = perfect input; about 0.3-0.45 gives mIoU "
                   "0.55, depending on the scene) instead of calibrating to --input-miou; skips the first pass")
    p.add_argument("--probabilities", action="store_true",
                   help="also write probabilities/NNNNNN.npy: float16 (N, 20) class probabilities over the "
                   "learning classes, arg-max equal to the predicted label")
    p.add_argument("--beams", default=64, type=_positive_int("--beams", 64), metavar="B",
                   help="number of lasers, picked evenly from the HDL-64E's 64 (+2.0 to -24.9 deg) "
                   "(default: %(default)s)")
    p.add_argument("--azimuth-steps", default=2083, type=_positive_int("--azimuth-steps", 20000), metavar="A",
                   help="columns per revolution; 2083 is the HDL-64E at 10 Hz (0.17 deg), about 120k points per "
                   "scan; small values make tiny scans for tests (default: %(default)s)")
    p.add_argument("--speed", default=8.0, type=_float_in("--speed", 0.0, 30.0, lo_open=True), metavar="V",
                   help="cruise speed of the car in m/s; it slows down in turns (default: %(default)s)")
    p.add_argument("--max-range", default=90.0, type=_float_in("--max-range", 5.0, 200.0), metavar="R",
                   help="LiDAR range in m: rays with no hit closer are dropped (default: %(default)s)")
    p.add_argument("--range-noise", default=0.02, type=_float_in("--range-noise", 0.0, 1.0), metavar="SIGMA",
                   help="standard deviation of the gaussian range noise in m (default: %(default)s)")
    p.add_argument("--movers", default=0, type=_count("--movers", 1000), metavar="N",
                   help="moving road users over the drive: cars and trucks or buses oncoming and ahead, "
                   "pedestrians crossing in front of the car, cyclists and vehicles on cross streets; labelled "
                   "moving-car, moving-person, ... (raw ids 252-259) with their own instance ids, predicted as the "
                   "static class; their boxes, scan by scan, go to movers.json. Fewer are placed when a short "
                   "drive has no room for them (default: %(default)s: a static scene)")
    p.add_argument("--traffic", default="classic", choices=TRAFFIC_CHOICES,
                   help="behaviours of the movers: classic (oncoming, lead, crossing pedestrians, cross traffic, "
                   "all at constant speed; the drives of earlier versions) or varied (those, and vehicles that "
                   "stop at an intersection for 1.5-4 s and drive on, slow cyclists by the kerb, vehicles "
                   "passing the car 1-2 m away, pedestrians pausing on the sidewalk; named in movers.json's "
                   "behaviour field) (default: %(default)s)")
    p.add_argument("--moving-labels", action="store_true",
                   help="predict moving objects as a multi-scan network does: a mover's point whose predicted "
                   "class is the mover's gets the moving raw id (252 moving-car instead of 10 car, ...); all "
                   "other predictions stay as without the option")
    p.add_argument("--drift", default=0.0, type=_float_in("--drift", -90.0, 90.0), metavar="DEG",
                   help="also write the odometry of a car whose heading drifts by DEG degrees per 100 m driven "
                   "(odometry.txt, poses in poses.txt's convention), and what a SLAM publishes when it closes the "
                   "loop (loop_closure.yaml: its frame, and the keyframes it then re-publishes, their corrected "
                   "poses poses.txt's); evaluate and kitti_to_bag read them (docs/slam.md) (default: %(default)s: "
                   "no drift, no odometry.txt)")
    p.add_argument("--drift-scale", default=0.0, type=_float_in("--drift-scale", -0.5, 0.5), metavar="F",
                   help="the odometry's scale error, a fraction of each step (e.g. 0.01: 1 %% too long) "
                   "(default: %(default)s)")
    p.add_argument("--loop-closure", default=None, type=_positive_int("--loop-closure", 1_000_000), metavar="K",
                   help="with --drift or --drift-scale, the frame at which the SLAM closes the loop (default: "
                   "the first frame after one lap of the route, else the last frame)")
    p.add_argument("--force", action="store_true",
                   help="write into an existing non-empty sequence folder, replacing its scans")
    p.add_argument("--quiet", action="store_true", help="no progress bar and no summary")
    return p


def _summary(result, names) -> str:
    summary = result.confusion.summary(names)
    lines = [
        f"wrote {result.frames} frames to {result.sequence_dir}",
        f"  points/frame: {sum(result.points) / len(result.points):.0f} (min {min(result.points)}, "
        f"max {max(result.points)})",
        f"  time/frame:   {result.seconds_per_frame:.2f} s (scene, noise calibration, simulation, writing)",
        f"  input mIoU:   {summary['miou']:.3f} (accuracy {summary['accuracy']:.3f}; noise strength "
        f"{result.strength:.3f}{', calibrated' if result.calibrated else ''})",
        "  input IoU:    " + ", ".join(f"{k} {v:.2f}" for k, v in summary["iou"].items()),
    ]
    if result.moving_points:
        placed, mean = len(result.placed_movers), sum(result.moving_points) / len(result.moving_points)
        lines.append(f"  movers:       {placed} placed, {mean:.0f} moving points/frame (movers.json)")
    return "\n".join(lines)


def _remove_created(folder: Path | None) -> None:
    """Remove the folder this run created (none when every folder already existed)."""
    if folder is not None and folder.is_dir():
        shutil.rmtree(folder, ignore_errors=True)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the process exit code."""
    args = build_parser().parse_args(argv)
    try:
        from tqdm import tqdm

        from convbki_core.io.labels import load_label_map
        from convbki_core.synth.drive import DriveConfig, SynthError, check_destination, generate_drive
        from convbki_core.synth.lidar import MissingDependency, require_numba
    except ImportError as error:
        print(f"{PROG}: error: {error}", file=sys.stderr)
        return 1
    config = DriveConfig(out=args.out, sequence=args.sequence, frames=args.frames, seed=args.seed,
                         input_miou=args.input_miou, noise_strength=args.noise_strength,
                         probabilities=args.probabilities, beams=args.beams, azimuth_steps=args.azimuth_steps,
                         speed=args.speed, max_range=args.max_range, range_noise=args.range_noise, force=args.force,
                         movers=args.movers, traffic=args.traffic, moving_labels=args.moving_labels,
                         drift_heading=args.drift, drift_scale=args.drift_scale, loop_closure=args.loop_closure)
    bar = None
    # The top-most folder of ROOT/sequences/SS that this run creates: removed again on failure.
    sequence_folder = Path(args.out) / "sequences" / args.sequence
    created = next((p for p in reversed((sequence_folder, *sequence_folder.parents)) if not p.exists()), None)
    try:
        # Before the progress bar, so that a refusal is one clean line.
        require_numba()
        check_destination(config)
        passes = 1 if args.noise_strength is not None else 2  # calibration pre-pass, then writing
        bar = tqdm(total=passes * args.frames, unit="scan", desc=PROG, disable=args.quiet, file=sys.stderr)

        def status(text: str) -> None:
            bar.set_description(f"{PROG}: {text}")

        result = generate_drive(config, progress=lambda k: bar.update(k - bar.n), status=status)
    except SynthError as error:
        if bar is not None:
            bar.close()
        _remove_created(created)
        print(f"{PROG}: error: {error}", file=sys.stderr)
        return 2
    except MissingDependency as error:
        if bar is not None:
            bar.close()
        print(f"{PROG}: error: {error}", file=sys.stderr)
        return 1
    except OSError as error:
        if bar is not None:
            bar.close()
        _remove_created(created)
        where = f"{error.filename}: " if error.filename else ""
        print(f"{PROG}: error: cannot write the drive: {where}{error.strerror or error}", file=sys.stderr)
        return 2
    except BaseException:
        if bar is not None:
            bar.close()
        _remove_created(created)  # Ctrl-C or a bug: no half-written drive in a folder this run made
        raise
    bar.close()
    if not args.quiet:
        print(_summary(result, load_label_map().class_names))
    return 0


if __name__ == "__main__":
    sys.exit(main())

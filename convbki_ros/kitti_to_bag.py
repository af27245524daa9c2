"""``kitti_to_bag``: a SemanticKITTI-format sequence -> rosbag2 (mcap or sqlite3).

Topics: /kitti/velo/pointcloud (PointCloud2, frame velo_link, fields x, y, z, intensity
and label or prob_i), /kitti/odom (nav_msgs/Odometry, frame map, child velo_link), /tf.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

PROG = "kitti_to_bag"
ISSUE = 4


def sequence_arg(text: str) -> str:
    """Sequence id as the two-digit folder name: ``8`` -> ``08``."""
    if not text.isdigit():
        raise argparse.ArgumentTypeError(f"sequence must be a number such as 08, got {text!r}")
    return f"{int(text):02d}"


def frames_arg(text: str) -> tuple[int | None, int | None]:
    """``A:B`` -> (A, B): frames A (inclusive) to B (exclusive); either may be empty."""
    start, sep, stop = text.partition(":")
    try:
        if not sep:
            raise ValueError
        a = int(start) if start else None
        b = int(stop) if stop else None
    except ValueError:
        raise argparse.ArgumentTypeError(f"frames must be A:B, e.g. 0:200, got {text!r}") from None
    if (a is not None and a < 0) or (a is not None and b is not None and b <= a):
        raise argparse.ArgumentTypeError(f"frames must satisfy 0 <= A < B, got {text!r}")
    return a, b


def build_parser() -> argparse.ArgumentParser:
    """Command-line parser."""
    p = argparse.ArgumentParser(
        prog=PROG,
        description="Write a SemanticKITTI-format sequence (scans, input segmentation, "
        "poses) to a rosbag2: /kitti/velo/pointcloud, /kitti/odom and /tf. Ground truth "
        "stays in the dataset folder. Stamps come from times.txt when present, else 0.1 s "
        "apart from a fixed epoch, so a replay is deterministic.",
    )
    p.add_argument("--dataset", required=True, metavar="ROOT",
                   help="dataset root holding sequences/SS/{velodyne,labels,...}, "
                   "poses.txt and calib.txt")
    p.add_argument("--sequence", required=True, metavar="SS", type=sequence_arg,
                   help="sequence id, e.g. 08")
    p.add_argument("--out", required=True, metavar="BAG",
                   help="output bag directory (must not exist yet)")
    p.add_argument("--predictions-dir", default="predictions", metavar="DIR",
                   help="folder under sequences/SS with the input segmentation "
                   "NNNNNN.label (uint32 raw ids), written as the uint32 `label` field "
                   "(default: %(default)s)")
    p.add_argument("--probabilities-dir", default=None, metavar="DIR",
                   help="folder under sequences/SS with per-point class probabilities "
                   "NNNNNN.npy (N x C float16/float32); when given, the cloud carries "
                   "float32 fields prob_0..prob_{C-1} instead of `label`")
    p.add_argument("--frames", default=None, metavar="A:B", type=frames_arg,
                   help="only frames A (inclusive) to B (exclusive); default: all")
    p.add_argument("--storage", default="mcap", choices=("mcap", "sqlite3"),
                   help="rosbag2 storage plugin (default: %(default)s)")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the process exit code."""
    build_parser().parse_args(argv)
    print(f"{PROG}: not implemented yet (see issue {ISSUE})", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())

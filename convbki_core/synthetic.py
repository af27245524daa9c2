"""``synth``: write a synthetic SemanticKITTI-format drive (64-beam LiDAR scans).

Output: ROOT/sequences/SS/{velodyne,labels,predictions}/NNNNNN.*, poses.txt, calib.txt,
times.txt; the segmentation in predictions/ is the ground truth with synthetic noise.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

PROG = "synth"
ISSUE = 3


def sequence_arg(text: str) -> str:
    """Sequence id as the two-digit folder name: ``8`` -> ``08``."""
    if not text.isdigit():
        raise argparse.ArgumentTypeError(f"sequence must be a number such as 08, got {text!r}")
    return f"{int(text):02d}"


def frames_count(text: str) -> int:
    """Number of scans: a positive integer."""
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n <= 0:
        raise argparse.ArgumentTypeError(f"frames must be a positive integer, got {text!r}")
    return n


def build_parser() -> argparse.ArgumentParser:
    """Command-line parser."""
    p = argparse.ArgumentParser(
        prog=PROG,
        description="Write a synthetic drive in SemanticKITTI format: LiDAR scans, "
        "ground-truth labels, a noisy input segmentation, poses, calibration and stamps.",
    )
    p.add_argument("--out", required=True, metavar="ROOT",
                   help="dataset root to write; the drive goes to ROOT/sequences/SS")
    p.add_argument("--sequence", default="00", metavar="SS", type=sequence_arg,
                   help="sequence id to write (default: %(default)s)")
    p.add_argument("--frames", default=100, type=frames_count, metavar="N",
                   help="number of scans, 0.1 s apart (default: %(default)s)")
    p.add_argument("--seed", default=0, type=int, metavar="S",
                   help="random seed: the same seed writes the same drive, byte for byte "
                   "(default: %(default)s)")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the process exit code."""
    build_parser().parse_args(argv)
    print(f"{PROG}: not implemented yet (see issue {ISSUE})", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())

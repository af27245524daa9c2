"""``evaluate``: offline ConvBKI mapping and scoring of a SemanticKITTI-format sequence.

Protocol (the paper's): frames in order; update the map with each frame, then label every
point of that frame by the arg-max class of its voxel (points outside the window or in
voxels with no evidence keep the input label); one confusion matrix over all frames,
ground-truth class 0 ignored; the input segmentation is scored the same way.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

PROG = "evaluate"
ISSUE = 3


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
        description="Map a SemanticKITTI-format sequence offline with ConvBKI and score the "
        "map's labels and the input segmentation against the ground truth (IoU per "
        "class, mIoU over classes present in the ground truth, accuracy).",
    )
    p.add_argument("--dataset", required=True, metavar="ROOT",
                   help="dataset root holding sequences/SS/{velodyne,labels,...}, "
                   "poses.txt and calib.txt")
    p.add_argument("--sequence", required=True, metavar="SS", type=sequence_arg,
                   help="sequence id, e.g. 08")
    p.add_argument("--predictions-dir", default="predictions", metavar="DIR",
                   help="folder under sequences/SS with the input segmentation "
                   "NNNNNN.label (uint32 raw ids) (default: %(default)s)")
    p.add_argument("--probabilities-dir", default=None, metavar="DIR",
                   help="folder under sequences/SS with per-point class probabilities "
                   "NNNNNN.npy (N x C float16/float32); when given, the map is updated "
                   "with these instead of the one-hot input labels")
    p.add_argument("--kernel", default=None, metavar="FILE",
                   help="kernel file (YAML), e.g. config/kernels/semantic_kitti_compound.yaml; "
                   "default: the shipped compound kernel")
    p.add_argument("--frames", default=None, metavar="A:B", type=frames_arg,
                   help="only frames A (inclusive) to B (exclusive); default: all")
    p.add_argument("--report", required=True, metavar="JSON",
                   help="write the report (sequence, frames, kernel, input and map mIoU, IoU "
                   "per class, accuracy, median update and query times in ms) to this file")
    p.add_argument("--write-labels", default=None, metavar="OUTROOT",
                   help="also write the map's labels as "
                   "OUTROOT/sequences/SS/predictions/NNNNNN.label (uint32 raw ids, one per "
                   "input point), the format the semantic-kitti-api evaluator reads")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the process exit code."""
    build_parser().parse_args(argv)
    print(f"{PROG}: not implemented yet (see issue {ISSUE})", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())

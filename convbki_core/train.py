"""``train``: learn ConvBKI kernel lengths on SemanticKITTI-format sequences.

The paper's recipe: T past scans moved into the current frame, one voxelisation, one
convolution, class-weighted NLL on the current scan's ground truth, Adam, lengths
initialised at 0.5 m and kept positive. Writes a kernel file (YAML).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

PROG = "train"
ISSUE = 3


def sequence_arg(text: str) -> str:
    """Sequence id as the two-digit folder name: ``8`` -> ``08``."""
    if not text.isdigit():
        raise argparse.ArgumentTypeError(f"sequence must be a number such as 08, got {text!r}")
    return f"{int(text):02d}"


def _positive(kind: type[int] | type[float], name: str):
    def parse(text: str) -> int | float:
        try:
            value = kind(text)
        except ValueError:
            value = 0
        if not value > 0:
            raise argparse.ArgumentTypeError(f"{name} must be a positive number, got {text!r}")
        return value

    return parse


def build_parser() -> argparse.ArgumentParser:
    """Command-line parser."""
    p = argparse.ArgumentParser(
        prog=PROG,
        description="Learn the kernel lengths of a ConvBKI layer on SemanticKITTI-format "
        "sequences and write them as a kernel file. Train on sequences other than those "
        "you score on.",
    )
    p.add_argument("--dataset", required=True, metavar="ROOT",
                   help="dataset root holding sequences/SS/{velodyne,labels,...}, "
                   "poses.txt and calib.txt")
    p.add_argument("--sequences", required=True, nargs="+", metavar="SS", type=sequence_arg,
                   help="training sequence ids, e.g. 00 01")
    p.add_argument("--kernel", default="compound", choices=("single", "per_class", "compound"),
                   help="kernel variant to learn: single (one length ell), per_class (one "
                   "ell per class) or compound (horizontal ell_h and vertical ell_z per "
                   "class) (default: %(default)s)")
    p.add_argument("--out", required=True, metavar="FILE",
                   help="kernel file (YAML) to write")
    p.add_argument("--frames-per-sample", default=10, type=_positive(int, "frames-per-sample"),
                   metavar="T",
                   help="scans per training sample: the current scan and T-1 past scans "
                   "moved into its frame (default: %(default)s)")
    p.add_argument("--epochs", default=1, type=_positive(int, "epochs"), metavar="N",
                   help="passes over the training samples (default: %(default)s)")
    p.add_argument("--lr", default=0.007, type=_positive(float, "lr"), metavar="LR",
                   help="Adam learning rate (default: %(default)s)")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the process exit code."""
    build_parser().parse_args(argv)
    print(f"{PROG}: not implemented yet (see issue {ISSUE})", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())

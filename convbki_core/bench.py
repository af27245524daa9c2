"""``bench``: the ConvBKI benchmark (see BENCHMARKS.md): latency of voxelisation, update,
map query and PointCloud2 encoding, memory per voxel, an ablation table and plots.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

PROG = "bench"
ISSUE = 5


def repeat_arg(text: str) -> int:
    """Number of timed repetitions: a positive integer."""
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n <= 0:
        raise argparse.ArgumentTypeError(f"repeat must be a positive integer, got {text!r}")
    return n


def build_parser() -> argparse.ArgumentParser:
    """Command-line parser."""
    p = argparse.ArgumentParser(
        prog=PROG,
        description="Benchmark ConvBKI on synthetic 64-beam scans (about 120,000 points) in "
        "the paper's SemanticKITTI set-up; prints a table of medians in ms and optionally "
        "writes JSON.",
    )
    p.add_argument("--config", default="semantic_kitti", choices=("semantic_kitti",),
                   help="benchmark set-up: semantic_kitti = bounds [-40,-40,-2.6]..[40,40,2.6] m, "
                   "0.2 m voxels, f = 5, 20 classes, compound kernel (default: %(default)s)")
    p.add_argument("--repeat", default=30, type=repeat_arg, metavar="N",
                   help="timed repetitions per figure; medians are reported "
                   "(default: %(default)s)")
    p.add_argument("--json", default=None, metavar="FILE",
                   help="also write the figures (update_ms, query_ms, speedup_vs_dense, ...) "
                   "as JSON to this file")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the process exit code."""
    build_parser().parse_args(argv)
    print(f"{PROG}: not implemented yet (see issue {ISSUE})", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())

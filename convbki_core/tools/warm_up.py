"""warm_up: compile every kernel of the mapper and its outputs into numba's cache, and exit.

Set-up runs it (``make setup``, and every ``colcon build`` through the package's install
step), so a freshly installed node starts warm. With ``--tools`` (what ``make setup`` asks
for) it also compiles the kernels of the tools that have their own: the synthetic drive's LiDAR
and movers (``synth``, the demo; a quarter of a minute on a cold cache), ``label_noise``'s
neighbour search and ``evaluate``'s planning check, so that their first run starts warm too.
Run it again after moving the cache (``NUMBA_CACHE_DIR``) or when building an image for a
robot:

    .venv/bin/python -m convbki_core.tools.warm_up

It compiles the kernels of the copy of the package Python imports (the source tree from the
repository root; the installed copy once ``install/setup.bash`` is sourced and the working
folder is another).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from convbki_core.tools.cli import run

PROG = "warm_up"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=PROG, description="Compile every kernel the mapper and its outputs run "
                                     "(numba) into the cache, so that the next start is warm.")
    parser.add_argument("--quiet", action="store_true", help="print nothing when all went well")
    parser.add_argument("--tools", action="store_true",
                        help="also compile the kernels of synth (and the demo), label_noise and evaluate")
    return parser


def warm_up_tools() -> float:
    """Compile the tools' own kernels: a two-scan synthetic drive with movers in a temporary
    folder, a neighbour search and a planned path on toy inputs of the types the tools pass.
    Returns the seconds it took."""
    import tempfile
    import time

    import numpy as np

    from convbki_core.datasets.label_noise_neighbours import nearest_other
    from convbki_core.measures.costmap_eval import planning_check
    from convbki_core.tools import synth

    started = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="convbki_warm_up_") as folder:
        if synth.main(["--out", str(Path(folder) / "drive"), "--sequence", "00", "--frames", "2", "--beams", "8",
                       "--azimuth-steps", "64", "--movers", "2", "--quiet"]) != 0:
            raise RuntimeError("the synthetic drive of the warm-up failed (see above)")
    points = np.array([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0], [3.0, 0.0, 0.0]])
    nearest_other(points, np.array([1, 2, 1]), 1.0)
    free = np.zeros((3, 3), np.int8)  # an occupancy grid of free cells: one path planned on it
    planning_check(free, free, np.ones((3, 3), bool), pairs=1, min_distance=1.0)
    return time.monotonic() - started


def _warm_up(args: argparse.Namespace) -> int:
    import convbki_core
    from convbki_core.warm_up import warm_up

    report = warm_up()
    if not args.quiet:
        print(f"{PROG}: {report.line()} for {Path(convbki_core.__file__).parent}")
    if args.tools:
        seconds = warm_up_tools()
        if not args.quiet:
            print(f"{PROG}: the tools' kernels (synth, label_noise, evaluate) ready in {seconds:.1f} s")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    return run(PROG, _warm_up, build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())

"""warm_up: compile every kernel of the mapper and its outputs into numba's cache, and exit.

Set-up runs it (``make setup``, and every ``colcon build`` through the package's install
step), so a freshly installed node starts warm. Run it again after moving the cache
(``NUMBA_CACHE_DIR``) or when building an image for a robot:

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
    return parser


def _warm_up(args: argparse.Namespace) -> int:
    import convbki_core
    from convbki_core.warm_up import warm_up

    report = warm_up()
    if not args.quiet:
        print(f"{PROG}: {report.line()} for {Path(convbki_core.__file__).parent}")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    return run(PROG, _warm_up, build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())

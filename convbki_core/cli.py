"""What every command-line front end shares: argument types, clean errors, progress bars."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Iterable, Sequence
from typing import TypeVar

T = TypeVar("T")


class UserError(Exception):
    """A problem with the user's input: printed as one line, exit code 2, no traceback."""


def sequence_arg(text: str) -> str:
    """Sequence id as the two-digit folder name: ``8`` -> ``08``."""
    if not text.isdigit():
        raise argparse.ArgumentTypeError(f"sequence must be a number such as 08, got {text!r}")
    return f"{int(text):02d}"


def frames_arg(text: str) -> str:
    """``A:B``: frames A (inclusive) to B (exclusive); either side may be empty."""
    start, separator, stop = text.partition(":")
    try:
        if not separator:
            raise ValueError
        first = int(start) if start else None
        last = int(stop) if stop else None
    except ValueError:
        raise argparse.ArgumentTypeError(f"frames must be A:B, e.g. 0:200, got {text!r}") from None
    if (first is not None and first < 0) or (first is not None and last is not None and last <= first):
        raise argparse.ArgumentTypeError(f"frames must satisfy 0 <= A < B, got {text!r}")
    return text


def positive(kind: type, name: str) -> Callable[[str], int | float]:
    """argparse type: a positive int or float."""

    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            value = 0
        if not value > 0:
            raise argparse.ArgumentTypeError(f"{name} must be a positive number, got {text!r}")
        return value

    return parse


def progress(items: Iterable[T], total: int | None = None, description: str = "") -> Iterable[T]:
    """A tqdm progress bar on stderr (plain iteration when tqdm is missing)."""
    try:
        from tqdm import tqdm
    except ImportError:  # pragma: no cover - tqdm is a pinned dependency
        return items
    return tqdm(items, total=total, desc=description, unit="frame", file=sys.stderr, dynamic_ncols=True,
                mininterval=1.0)


def run(prog: str, body: Callable[[argparse.Namespace], int], parser: argparse.ArgumentParser,
        argv: Sequence[str] | None) -> int:
    """Parse ``argv``, run ``body``; known input problems become ``prog: error: ...`` and exit 2."""
    from convbki_core.datasets import DatasetError
    from convbki_core.kernels import KernelFileError
    from convbki_core.mapfile import MapFileError

    args = parser.parse_args(argv)
    try:
        return body(args)
    except (UserError, DatasetError, KernelFileError, MapFileError) as error:
        print(f"{prog}: error: {error}", file=sys.stderr)
        return 2
    except OSError as error:
        where = f"{error.filename}: " if error.filename else ""
        print(f"{prog}: error: {where}{error.strerror or error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130

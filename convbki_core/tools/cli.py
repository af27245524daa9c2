"""What every command-line front end shares: argument types, clean errors, progress bars."""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import TypeVar

from convbki_core.io.atomic import remove_stale_staging_folders, staging_prefix

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


def device_arg(text: str) -> str:
    """argparse type: a torch device this machine has (``auto``, ``cpu``, ``cuda[:N]``), checked
    while the arguments are parsed, before any work; returns ``text`` unchanged. ``auto`` and
    ``cpu`` exist everywhere: they are taken without loading torch (argparse also checks the
    default this way, and a mistyped flag should be said at once)."""
    if text in ("", "auto", "cpu"):
        return text
    from convbki_core.devices import resolve_device

    try:
        resolve_device(text)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None
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


def non_negative(kind: type) -> Callable[[str], int | float]:
    """argparse type: an int or float that is 0 or more."""

    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"expected a {'whole ' if kind is int else ''}number, got {text!r}") from None
        if not value >= 0:
            raise argparse.ArgumentTypeError(f"must be 0 or more, got {text}")
        return value

    return parse


def window_bounds(values: Sequence[float] | None):
    """``--local-bounds XMIN YMIN ZMIN XMAX YMAX ZMAX`` as ((min), (max)), None when not given;
    ``UserError`` unless each minimum lies below its maximum."""
    if not values:
        return None
    bounds = (tuple(values[:3]), tuple(values[3:]))
    if any(not low < high for low, high in zip(*bounds)):
        raise UserError(f"--local-bounds must have each minimum below its maximum, got {list(values)}")
    return bounds


def output_folder(path: str | Path, what: str = "output") -> Path:
    """``path``'s folder, which must exist: a command checks this before it does any work."""
    folder = Path(path).parent if str(Path(path).parent) else Path(".")
    if not folder.is_dir():
        raise UserError(f"{folder}: {what} folder does not exist" if not folder.exists()
                        else f"{folder}: not a folder (for {path})")
    return folder


class NewOutputs:
    """What a command creates, so that a failure part-way leaves nothing of it behind.

    ``folder`` / ``file`` record paths that did not exist before; ``staging`` makes a hidden
    folder whose contents ``commit`` moves into place once everything succeeded. ``discard``
    (called on any failure) removes the staging folders and everything recorded. Files that
    existed before are never recorded, so a failed run never deletes a user's older results.
    """

    def __init__(self) -> None:
        self.created: list[Path] = []
        self.staged: list[tuple[Path, Path]] = []

    def folder(self, path: str | Path) -> Path:
        """Create ``path`` and its missing parents, recording the top-most one created."""
        path = Path(path)
        missing = [p for p in (path, *path.parents) if not p.exists()]
        path.mkdir(parents=True, exist_ok=True)
        if missing:
            self.created.append(missing[-1])
        return path

    def file(self, path: str | Path) -> Path:
        """Record ``path`` (about to be written) when it is new."""
        path = Path(path)
        if not path.exists():
            self.created.append(path)
        return path

    def staging(self, final: str | Path) -> Path:
        """A hidden folder beside ``final`` to write into; ``commit`` moves its files into ``final``."""
        final = Path(final)
        self.folder(final.parent)
        remove_stale_staging_folders(final)
        stage = Path(tempfile.mkdtemp(dir=final.parent, prefix=staging_prefix(final)))
        self.staged.append((stage, final))
        return stage

    def commit(self) -> None:
        """Move every staged file into its final folder (each move atomic), then drop the staging folders."""
        for stage, final in self.staged:
            self.folder(final)
            for entry in sorted(stage.iterdir()):
                os.replace(entry, final / entry.name)
            stage.rmdir()
        self.staged.clear()
        self.created.clear()  # committed outputs are the user's now: a later discard() must not touch them

    def discard(self) -> None:
        for stage, _ in self.staged:
            shutil.rmtree(stage, ignore_errors=True)
        self.staged.clear()
        for path in reversed(self.created):
            if path.is_dir() and not path.is_symlink():
                shutil.rmtree(path, ignore_errors=True)
            else:
                path.unlink(missing_ok=True)
        self.created.clear()


def say_notices(prog: str, notices: Sequence[str]) -> None:
    """What a user should know about how their input was read (``prog: note: ...`` on stderr,
    one line each), e.g. a dataset's poses that were not used."""
    for notice in notices:
        print(f"{prog}: note: {notice}", file=sys.stderr)


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
    from convbki_core.io.kernel_file import KernelFileError
    from convbki_core.io.map_file import MapFileError

    # argparse prints the whole usage before its error; one line is easier to read in a log.
    parser.error = lambda message: parser.exit(2, f"{prog}: error: {message} (see {prog} --help)\n")
    args = parser.parse_args(argv)
    said = _kernel_cache_note(prog, said=False)
    try:
        return body(args)
    except (UserError, DatasetError, KernelFileError, MapFileError) as error:
        one_line = " ".join(str(error).split())  # a quoted file name may carry a newline
        print(f"{prog}: error: {one_line}", file=sys.stderr)
        return 2
    except OSError as error:
        where = f"{error.filename}: " if error.filename else ""
        text = str(error.strerror or error).strip().splitlines()
        print(f"{prog}: error: {where}{text[0] if text else error.__class__.__name__}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130
    finally:
        _kernel_cache_note(prog, said)


def _kernel_cache_note(prog: str, said: bool) -> bool:
    """Print, once, why compiled kernels are cached somewhere unusual or not at all (only where
    the command uses compiled kernels); True once said or nothing to say."""
    native = sys.modules.get("convbki_core.compiled")
    if said or native is None:
        return said
    note = native.kernel_cache().note
    if note:
        print(f"{prog}: warning: {note}", file=sys.stderr)
    return True

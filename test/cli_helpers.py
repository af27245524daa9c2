"""Helpers for the tests of the command-line tools' errors: what a failed command printed, and what it left."""

from __future__ import annotations

from pathlib import Path


def one_line_error(capsys, code: int, prog: str, *needles: str, after_progress: bool = False) -> str:
    """The command's stderr is exactly one line ``prog: error: ...`` holding every needle.

    ``after_progress``: the failure came part-way through, so a progress bar may precede it.
    """
    err = capsys.readouterr().err
    assert code == 2, err
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    if after_progress:
        assert all("%|" in line for line in lines[:-1]), err  # nothing but the bar before the error
        lines = lines[-1:]
    assert len(lines) == 1, err
    assert lines[0].startswith(f"{prog}: error: "), lines[0]
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    return lines[0]


def tree(folder: Path) -> set[str]:
    """Every path under ``folder`` (hidden ones too), relative."""
    return {str(p.relative_to(folder)) for p in folder.rglob("*")}

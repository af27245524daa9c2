"""Which torch device a mapper runs on, decided once, with one clear line when it cannot be had."""

from __future__ import annotations

import torch

DEVICE_CHOICES = "auto, cpu or cuda[:N]"


def resolve_device(device: str | torch.device) -> torch.device:
    """The torch device to map on: ``auto`` (or "") -> CUDA when present, else CPU; ``cpu``;
    ``cuda`` or ``cuda:N``.

    Raises ``ValueError`` with one line naming the device and why for a name torch does not
    know, a device type other than CPU and CUDA, and a CUDA device this machine lacks, so
    a program fails at once rather than at its first update.
    """
    name = str(device)
    if name in ("", "auto"):
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        resolved = torch.device(name)
    except (RuntimeError, ValueError, TypeError):
        raise ValueError(f"unknown device {name!r}: use {DEVICE_CHOICES}") from None
    if resolved.type == "cpu":
        return resolved
    if resolved.type != "cuda":
        raise ValueError(f"device {name!r} is not supported: use {DEVICE_CHOICES}")
    if not torch.cuda.is_available():
        why = ("it is built without CUDA" if torch.version.cuda is None and torch.version.hip is None
               else "no GPU is visible or its driver is missing")
        raise ValueError(f"device {name!r} requested, but this torch ({torch.__version__}) has no CUDA device "
                         f"({why}); use device auto or cpu")
    count = torch.cuda.device_count()
    if resolved.index is not None and resolved.index >= count:
        present = "cuda:0" if count == 1 else f"cuda:0 .. cuda:{count - 1}"
        raise ValueError(f"device {name!r} requested, but this machine has {count} CUDA "
                         f"device{'' if count == 1 else 's'} ({present}); use device auto, cpu or {present}")
    return resolved

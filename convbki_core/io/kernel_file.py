"""The kernel file: a small YAML mapping holding a trained kernel (its kind, resolution,
filter size, class count and lengths, optionally the free-space length and the temperature
of probability inputs), and ``KernelConfig``, its contents in memory.

Reading checks everything a mapper relies on and raises ``KernelFileError`` naming the file
and the problem; writing is atomic. The format is described in docs/file_formats.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from convbki_core.io.atomic import atomic_write_bytes

KERNEL_KINDS = ("single", "per_class", "compound")
# Sanity limits of a kernel file: a filter of f^3 taps per class is built in memory, and
# label ids are 16-bit. Far beyond any useful value, small enough to refuse absurd files.
MAX_FILTER_SIZE = 63
MAX_CLASSES = 1024
# A temperature far outside this range turns every probability row into one-hot or uniform
# evidence (and 1 / T overflows a power of float32 values); refuse it as a broken file.
MIN_TEMPERATURE = 0.01
MAX_TEMPERATURE = 100.0


@dataclass
class KernelConfig:
    """The contents of a kernel file (docs/file_formats.md): the unit of trained weights."""

    kernel: str = "compound"
    resolution: float = 0.2
    filter_size: int = 5
    num_classes: int = 20
    ell: list[float] = field(default_factory=list)  # single: [l]; per_class: one per class
    ell_h: list[float] = field(default_factory=list)  # compound only
    ell_z: list[float] = field(default_factory=list)  # compound only
    free_ell: float | None = None  # the free-space category's length; None: one voxel (no spreading)
    # Temperature T of class-probability inputs: each row p becomes softmax(log p / T) before it
    # is voxelised (T < 1 sharpens, T > 1 softens); None: 1, the probabilities as given.
    temperature: float | None = None

    def validate(self) -> KernelConfig:
        """Raise ``KernelFileError`` with a readable reason when the config is inconsistent."""
        if not isinstance(self.kernel, str) or self.kernel not in KERNEL_KINDS:
            raise KernelFileError(f"kernel must be one of {', '.join(KERNEL_KINDS)}, got {_shown(self.kernel)}")
        if not (_is_int(self.filter_size) and 1 <= self.filter_size <= MAX_FILTER_SIZE
                and self.filter_size % 2 == 1):
            raise KernelFileError(f"filter_size must be a positive odd integer up to {MAX_FILTER_SIZE}, "
                                  f"got {_shown(self.filter_size)}")
        if not (_is_int(self.num_classes) and 1 <= self.num_classes <= MAX_CLASSES):
            raise KernelFileError(f"num_classes must be a positive integer up to {MAX_CLASSES}, "
                                  f"got {_shown(self.num_classes)}")
        if not (_is_finite_number(self.resolution) and self.resolution > 0):
            raise KernelFileError(f"resolution must be a positive number of metres, got {_shown(self.resolution)}")
        expected = {"single": {"ell": 1}, "per_class": {"ell": self.num_classes},
                    "compound": {"ell_h": self.num_classes, "ell_z": self.num_classes}}[self.kernel]
        for name in ("ell", "ell_h", "ell_z"):
            if name not in expected and getattr(self, name):
                raise KernelFileError(f"a {self.kernel} kernel has no {name} (it uses {' and '.join(expected)})")
        if self.free_ell is not None and not (_is_finite_number(self.free_ell) and self.free_ell > 0):
            raise KernelFileError(f"free_ell must be a positive finite length in metres, got {_shown(self.free_ell)}")
        if self.temperature is not None and not (_is_finite_number(self.temperature)
                                                 and MIN_TEMPERATURE <= self.temperature <= MAX_TEMPERATURE):
            raise KernelFileError(f"temperature must be a number from {MIN_TEMPERATURE:g} to {MAX_TEMPERATURE:g}, "
                                  f"got {_shown(self.temperature)}")
        for name, count in expected.items():
            values = getattr(self, name)
            if len(values) != count:
                raise KernelFileError(f"{self.kernel} kernel needs {count} value(s) in {name}, got {len(values)}")
            for value in values:
                if not (_is_finite_number(value) and value > 0):
                    raise KernelFileError(f"{name} lengths must be positive finite metres, got {_shown(value)}")
        return self


class KernelFileError(ValueError):
    """A kernel file that cannot be used; the message names the problem."""


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _is_int(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)  # YAML's true is not a filter size


def _is_finite_number(value) -> bool:
    """An int or float that is finite as a float (YAML integers can be too large for one)."""
    if not _is_number(value):
        return False
    try:
        return math.isfinite(float(value))
    except OverflowError:
        return False


def _shown(value, limit: int = 60) -> str:
    """``repr`` cut to one short line: an error message quotes what it refuses, not a whole document."""
    text = repr(value).replace("\n", " ")
    return text if len(text) <= limit else text[: limit - 3] + "..."


def load_kernel_file(path: str | Path) -> KernelConfig:
    """Read and validate a kernel YAML file. Raises ``KernelFileError`` naming the file."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as error:
        raise KernelFileError(f"{path}: cannot read kernel file ({error.strerror or error})") from None
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        raise KernelFileError(f"{path}: not a kernel file (not UTF-8 text)") from None
    return parse_kernel_text(text, str(path))


def parse_kernel_text(text: str, source: str = "<kernel>") -> KernelConfig:
    """Parse and validate the text of a kernel file; errors are ``KernelFileError`` naming ``source``."""
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as error:
        where = getattr(error, "problem_mark", None)
        at = f" at line {where.line + 1}" if where is not None else ""
        raise KernelFileError(f"{source}: not valid YAML{at} ({error.__class__.__name__})") from None
    except RecursionError:
        raise KernelFileError(f"{source}: not a kernel file (YAML nested too deeply)") from None
    except (ValueError, OverflowError) as error:  # e.g. a date such as 2024-13-45 that YAML tries to build
        raise KernelFileError(f"{source}: not valid YAML ({error})") from None
    if not isinstance(data, dict):
        raise KernelFileError(f"{source}: a kernel file is a YAML mapping, found {type(data).__name__}")
    try:
        return kernel_config_from_dict(data)
    except KernelFileError as error:
        raise KernelFileError(f"{source}: {error}") from None


def kernel_config_from_dict(data: dict) -> KernelConfig:
    """Build a validated ``KernelConfig`` from a kernel-file mapping."""
    if not isinstance(data, dict):
        raise KernelFileError(f"a kernel file is a mapping, found {type(data).__name__}")
    known = {"kernel", "resolution", "filter_size", "num_classes", "ell", "ell_h", "ell_z", "free_ell", "temperature"}
    unknown = sorted(_shown(key, 30) for key in data if key not in known)  # quoted: a key may hold a newline
    if unknown:
        raise KernelFileError(f"unknown key(s) {', '.join(unknown[:5])}{' ...' if len(unknown) > 5 else ''}")
    for key in ("kernel", "resolution", "filter_size", "num_classes"):
        if key not in data:
            raise KernelFileError(f"missing key {key!r}")

    def as_list(name: str) -> list:
        value = data.get(name, [])
        if value is None:
            return []
        return list(value) if isinstance(value, (list, tuple)) else [value]

    config = KernelConfig(kernel=data["kernel"], resolution=data["resolution"],
                          filter_size=data["filter_size"], num_classes=data["num_classes"],
                          ell=as_list("ell"), ell_h=as_list("ell_h"), ell_z=as_list("ell_z"),
                          free_ell=data.get("free_ell"), temperature=data.get("temperature"))
    config.validate()
    if config.free_ell is not None:
        config.free_ell = float(config.free_ell)
    if config.temperature is not None:
        config.temperature = float(config.temperature)
    config.resolution = float(config.resolution)
    # Lengths as floats: a file may write 1 for 1.0, and the kernel module expects floats.
    config.ell, config.ell_h, config.ell_z = ([float(v) for v in values]
                                              for values in (config.ell, config.ell_h, config.ell_z))
    return config


def kernel_config_to_dict(config: KernelConfig) -> dict:
    """The mapping written to a kernel file (only the keys the variant uses)."""
    data = {"kernel": config.kernel, "resolution": float(config.resolution),
            "filter_size": int(config.filter_size), "num_classes": int(config.num_classes)}
    if config.kernel == "single":
        data["ell"] = round(float(config.ell[0]), 6)
    elif config.kernel == "per_class":
        data["ell"] = [round(float(v), 6) for v in config.ell]
    else:
        data["ell_h"] = [round(float(v), 6) for v in config.ell_h]
        data["ell_z"] = [round(float(v), 6) for v in config.ell_z]
    if config.free_ell is not None:
        data["free_ell"] = round(float(config.free_ell), 6)
    if config.temperature is not None:
        data["temperature"] = round(float(config.temperature), 6)
    return data


def save_kernel_file(config: KernelConfig, path: str | Path) -> None:
    """Write a kernel file atomically (temp file in the same folder, fsync, rename)."""
    config.validate()
    lines = ["# ConvBKI kernel file (convbki_ros). Lengths in metres."]
    for key, value in kernel_config_to_dict(config).items():
        shown = "[" + ", ".join(f"{v:g}" for v in value) + "]" if isinstance(value, list) else f"{value}"
        lines.append(f"{key}: {shown}")
    text = "\n".join(lines) + "\n"
    atomic_write_bytes(Path(path), text.encode())

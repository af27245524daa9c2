"""The map file: one self-describing, versioned file holding a whole ConvBKI map.

Layout (versions 2 and 3): an uncompressed NumPy ``.npz`` archive (readable from any language
with a zip reader and the .npy spec) with five members:

* ``metadata``: UTF-8 JSON bytes: format name and version, resolution (m), num_classes,
  frame_id, prior, local_bounds, the kernel (kernel-file mapping), class names if known,
  and ``sensor_position`` (x, y, z in frame_id, m: the sensor at the last scan) when known;
* ``voxel_index``: (N, 3) int32 global voxel indices (centre = (index + 0.5) * resolution);
* ``class_count``: (N,) uint8, per voxel the number of classes whose concentration is not
  the prior; those classes follow voxel by voxel in
* ``class_id``: (M,) uint8, ascending within a voxel, M = sum of class_count, and
* ``value``: (M,) float32 Dirichlet concentrations. Every other class holds exactly the
  metadata's ``prior`` (as float32).

Version 3 adds, optionally, the map's scan log (``scan_log``: every scan a correction can
still move, bit for bit as integrated, with its pose, and the map as it was before each
segment of them): members ``scan_log_*`` (``ScanLog.to_arrays``). Versions 1 (a dense
``alpha`` (N, C) float32 member instead of the class lists) and 2 (no log) still load. Saves are atomic
(temp file in the same folder, fsync, rename).
"""

from __future__ import annotations

import json
import math
import os
import stat
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from convbki_core.io.atomic import atomic_write_with
from convbki_core.memory.compact_rows import compress_rows, expand_rows

MAP_FORMAT = "convbki_map"
MAP_VERSION = 3
_MEMBERS = {1: ("metadata", "voxel_index", "alpha"),
            2: ("metadata", "voxel_index", "class_count", "class_id", "value"),
            3: ("metadata", "voxel_index", "class_count", "class_id", "value")}
SCAN_LOG_PREFIX = "scan_log_"  # version 3, optional: the scan log's members (``scan_log.ScanLog.to_arrays``)


class MapFileError(ValueError):
    """A map file that cannot be loaded; the message names the file and the problem."""


@dataclass(frozen=True)
class SetupDifference:
    """One way a readable map file's set-up differs from a mapper's: ``what`` (resolution,
    num_classes, prior or frame_id), the file's value and the mapper's."""

    what: str
    in_file: object
    here: object

    def words(self) -> str:
        """The difference in words, e.g. ``resolution 0.2 m in the file, 0.4 m here``."""
        unit = " m" if self.what == "resolution" else ""
        quote = "'" if self.what == "frame_id" else ""
        return f"{self.what} {quote}{self.in_file}{quote}{unit} in the file, {quote}{self.here}{quote}{unit} here"


class MapSetupError(MapFileError):
    """A whole, readable map file built for another set-up (grid, classes, prior or frame) than
    the mapper that would load it: not damaged, only not this mapper's. ``differences`` says how."""

    def __init__(self, message: str, differences: list[SetupDifference]):
        super().__init__(message)
        self.differences = differences


def setup_differences(metadata: dict, resolution: float, num_classes: int, prior: float,
                      frame_id: str | None = None) -> list[SetupDifference]:
    """How a map file's metadata (``read_map``) differs from a mapper's set-up: the classes, the
    resolution, the prior and (when ``frame_id`` is known) the frame. Empty when it fits."""
    differences = []
    if metadata["num_classes"] != num_classes:
        differences.append(SetupDifference("num_classes", metadata["num_classes"], num_classes))
    if not np.isclose(float(metadata["resolution"]), resolution):
        differences.append(SetupDifference("resolution", metadata["resolution"], resolution))
    if metadata.get("prior") is not None and not np.isclose(float(metadata["prior"]), prior):
        differences.append(SetupDifference("prior", metadata["prior"], prior))
    in_file = metadata.get("frame_id") or None
    if in_file and frame_id and in_file != frame_id:
        differences.append(SetupDifference("frame_id", in_file, frame_id))
    return differences


@dataclass
class MapSnapshot:
    """A copy of a map's contents, taken quickly; writing it to disk can then happen unlocked."""

    metadata: dict
    indices: np.ndarray  # (N, 3) int64
    alpha: np.ndarray  # (N, C) float32
    scan_log: object | None = None  # a ``ScanLog`` copy (``ScanLog.copy``), written with the map

    def __len__(self) -> int:
        return int(self.indices.shape[0])

    def write(self, path: str | Path, new_mode: int | None = None) -> None:
        """Write the map file (the current version, with the scan log when there is one) atomically:
        a failed write leaves the previous file as it was, and a successful one keeps the file it
        replaced as ``NAME.prev``. ``new_mode``: the permissions of a new file (a file replaced
        keeps its own; default 0666 minus the umask).

        Only values that differ from the metadata's ``prior`` are written; the rest is the prior.
        """
        if self.indices.size and (np.abs(self.indices) > np.iinfo(np.int32).max).any():
            raise ValueError("voxel indices exceed the int32 range of the map file")
        prior = self.metadata.get("prior")
        if not _is_positive_number(prior):
            raise ValueError(f"the metadata's prior must be a positive number, got {prior!r}")
        counts, classes, values = compress_rows(self.alpha, prior)
        metadata = {key: value for key, value in self.metadata.items() if key != "scan_log"}
        metadata["version"] = MAP_VERSION
        arrays = {
            "metadata": np.frombuffer(json.dumps(metadata).encode(), dtype=np.uint8),
            "voxel_index": self.indices.astype(np.int32),
            "class_count": counts,
            "class_id": classes,
            "value": values.view(np.float32),
        }
        if self.scan_log is not None:
            from convbki_core.correction.log_file import log_arrays

            arrays.update(log_arrays(self.scan_log, Path(os.path.abspath(path)).parent))
        atomic_write_with(path, lambda handle: np.savez(handle, **arrays), keep_previous=True, new_mode=new_mode)
        folder = None if self.scan_log is None else self.scan_log.folder
        if folder is not None:  # the folder keeps the files this map file (and its .prev) name
            folder.keep_for(os.path.abspath(path), self.scan_log.file_names(folder))


# A map file's metadata is a small JSON object; a member claiming more is not one of ours.
_MAX_METADATA_BYTES = 1 << 20


def map_file_voxels(path: str | Path) -> int | None:
    """How many voxels the map file at ``path`` holds, read from its headers alone (no array is
    loaded); None when ``path`` is not a ConvBKI map file: missing, a link, a folder, another
    program's file, or damaged beyond its headers' reach. What decides whether an existing file
    may be replaced by a map: only a map file may."""
    try:
        descriptor = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK)
    except (OSError, ValueError):  # (ValueError: a path with a NUL byte)
        return None
    try:
        with os.fdopen(descriptor, "rb") as stream:
            if not stat.S_ISREG(os.fstat(stream.fileno()).st_mode):
                return None  # a fifo or a device is never a map file (and reading one may block)
            with zipfile.ZipFile(stream) as archive:
                info = archive.getinfo("metadata.npy")
                if info.file_size > _MAX_METADATA_BYTES:
                    return None
                with archive.open(info) as member:
                    metadata = json.loads(np.lib.format.read_array(member, allow_pickle=False).tobytes().decode())
                if not isinstance(metadata, dict) or metadata.get("format") != MAP_FORMAT:
                    return None
                with archive.open("voxel_index.npy") as member:
                    version = np.lib.format.read_magic(member)
                    read_header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                                   else np.lib.format.read_array_header_2_0)
                    shape = read_header(member)[0]
    except (OSError, ValueError, KeyError, EOFError, RuntimeError, zipfile.BadZipFile, NotImplementedError,
            UnicodeDecodeError):
        return None
    return int(shape[0]) if len(shape) == 2 and shape[1] == 3 else None


def read_map(path: str | Path, with_scan_log: bool = False) -> tuple[dict, np.ndarray, np.ndarray]:
    """Read and check a map file: (metadata, voxel_index (N, 3) int64, alpha (N, C) float32 dense).

    Anything that is not a complete map file of this format (empty, truncated, corrupted,
    another program's .npz or .npy, an unknown format version) raises ``MapFileError``
    naming the file and the problem. Versions 1 and 2 load. ``with_scan_log``: also read the
    scan log, into ``metadata["scan_log"]`` (a ``ScanLog``, or None where the file has none).
    """
    path = Path(path)
    try:
        if path.is_dir():
            raise MapFileError(f"{path}: is a folder, not a map file")
        if path.exists() and path.stat().st_size == 0:
            raise MapFileError(f"{path}: empty file, not a ConvBKI map file")
        _check_magic(path)
        archive = np.load(path, allow_pickle=False)
        if not isinstance(archive, np.lib.npyio.NpzFile):  # a bare .npy array
            raise MapFileError(f"{path}: not a ConvBKI map file (a single NumPy array, not an .npz archive)")
        with archive:
            members = set(archive.files)
            if "metadata" not in members:
                missing = set(_MEMBERS[MAP_VERSION]) - members
                raise MapFileError(f"{path}: not a ConvBKI map file (missing {', '.join(sorted(missing))})")
            metadata = json.loads(archive["metadata"].tobytes().decode())
            _check_format(path, metadata)
            missing = set(_MEMBERS[metadata["version"]]) - members
            if missing:
                raise MapFileError(f"{path}: not a ConvBKI map file (missing {', '.join(sorted(missing))})")
            arrays = {name: archive[name] for name in _MEMBERS[metadata["version"]][1:]}
            if with_scan_log and metadata["version"] >= 3 and f"{SCAN_LOG_PREFIX}meta" in members:
                arrays.update({name: archive[name] for name in members if name.startswith(SCAN_LOG_PREFIX)})
    except MapFileError:
        raise
    except FileNotFoundError:
        raise MapFileError(f"{path}: no such map file") from None
    except MemoryError:
        raise MapFileError(f"{path}: corrupted map file (array sizes beyond the memory of this machine)") from None
    except (OSError, ValueError, zipfile.BadZipFile, EOFError, KeyError, NotImplementedError, RuntimeError,
            json.JSONDecodeError, UnicodeDecodeError) as error:
        # RuntimeError covers encrypted zip members and RecursionError from absurdly nested JSON.
        detail = str(error).splitlines()[0][:200] if str(error) else ""
        raise MapFileError(f"{path}: not a readable ConvBKI map file, truncated or corrupted "
                           f"({error.__class__.__name__}{': ' + detail if detail else ''})") from None
    _check_metadata(path, metadata)
    indices = arrays["voxel_index"]
    alpha = _dense_alpha(path, metadata, indices, arrays) if metadata["version"] >= 2 else arrays["alpha"]
    if with_scan_log:
        metadata["scan_log"] = _scan_log(path, arrays, metadata) if f"{SCAN_LOG_PREFIX}meta" in arrays else None
    num_classes = metadata["num_classes"]
    if indices.ndim != 2 or indices.shape[1] != 3 or alpha.ndim != 2 or alpha.shape != (indices.shape[0], num_classes):
        raise MapFileError(f"{path}: inconsistent arrays (voxel_index {indices.shape}, alpha {alpha.shape}, "
                           f"num_classes {num_classes})")
    if indices.dtype.kind != "i" or alpha.dtype.kind != "f":
        raise MapFileError(f"{path}: unexpected array types ({indices.dtype}, {alpha.dtype})")
    if metadata["version"] == 1 and (not np.isfinite(alpha).all() or (alpha < 0).any()):
        raise MapFileError(f"{path}: concentrations must be finite and non-negative")
    if len(np.unique(indices, axis=0)) != indices.shape[0]:
        raise MapFileError(f"{path}: duplicate voxel indices")
    return metadata, indices.astype(np.int64), alpha.astype(np.float32, copy=False)


def _scan_log(path: Path, arrays: dict, metadata: dict):
    """The scan log of a version 3 file (a ``ScanLog`` without bounds), checked. A log whose
    folder's files are gone leaves the map usable: None, the reason in ``metadata["scan_log_missing"]``."""
    from convbki_core.correction.log_file import MissingLogFiles, log_of_arrays

    try:
        meta = json.loads(arrays[f"{SCAN_LOG_PREFIX}meta"].tobytes().decode())
        if not isinstance(meta, dict):
            raise ValueError("its metadata is not a JSON object")
        return log_of_arrays(arrays, meta, metadata["num_classes"], float(metadata.get("prior") or 1e-3),
                             Path(os.path.abspath(path)).parent)
    except MissingLogFiles as error:
        metadata["scan_log_missing"] = f"the files of its scan log are gone ({str(error)[:200]})"
        return None
    except (ValueError, TypeError, KeyError, json.JSONDecodeError, UnicodeDecodeError) as error:
        raise MapFileError(f"{path}: corrupted scan log ({str(error).splitlines()[0][:200]})") from None


# What a file that is not an .npz archive usually is, by its first bytes.
_OTHER_FILES = ((b"\x89PNG", "a PNG image"), (b"\xff\xd8\xff", "a JPEG image"), (b"\x1f\x8b", "a gzip file"),
                (b"ply\n", "a PLY point cloud"), (b"BZh", "a bzip2 file"), (b"\x7fELF", "a program"),
                (b"SQLite format", "an SQLite database"), (b"\x89HDF", "an HDF5 file"))


def _check_magic(path: Path) -> None:
    """The file starts as a zip archive (an .npz) or a NumPy array does; anything else is
    named, so nobody is sent after numpy's advice about pickles for a picture."""
    with open(path, "rb") as stream:
        head = stream.read(16)
    if head.startswith((b"PK\x03\x04", b"PK\x05\x06", b"\x93NUMPY")):
        return
    what = next((name for magic, name in _OTHER_FILES if head.startswith(magic)), None)
    if what is None:
        what = "text" if head and all(32 <= b < 127 or b in b"\t\r\n" for b in head) else \
            f"a file starting with bytes {head[:8].hex(' ')}"
    raise MapFileError(f"{path}: not a ConvBKI map file (not a NumPy .npz archive: {what})")


def _check_format(path: Path, metadata: object) -> None:
    """The metadata names this format and a version this build reads."""
    if not isinstance(metadata, dict) or metadata.get("format") != MAP_FORMAT:
        raise MapFileError(f"{path}: not a ConvBKI map file (format is {metadata.get('format')!r})"
                           if isinstance(metadata, dict) else f"{path}: not a ConvBKI map file")
    version = metadata.get("version")
    if isinstance(version, bool) or version not in tuple(_MEMBERS):  # a tuple: JSON lists are unhashable
        raise MapFileError(f"{path}: map format version {version!r} is not supported "
                           f"(this build reads versions {', '.join(map(str, _MEMBERS))})")


def _dense_alpha(path: Path, metadata: dict, indices: np.ndarray, arrays: dict) -> np.ndarray:
    """The (N, C) float32 concentrations of a version 2 file, after checking its class lists."""
    counts, classes, values = arrays["class_count"], arrays["class_id"], arrays["value"]
    num_classes, prior = metadata["num_classes"], metadata.get("prior")
    if (indices.ndim != 2 or counts.ndim != 1 or counts.shape[0] != indices.shape[0] or classes.ndim != 1
            or values.shape != classes.shape):
        raise MapFileError(f"{path}: inconsistent arrays (voxel_index {indices.shape}, class_count {counts.shape}, "
                           f"class_id {classes.shape}, value {values.shape})")
    if counts.dtype.kind not in "iu" or classes.dtype.kind not in "iu" or values.dtype.kind != "f":
        raise MapFileError(f"{path}: unexpected array types ({counts.dtype}, {classes.dtype}, {values.dtype})")
    if counts.size and (counts.min() < 0 or counts.max() > num_classes):
        raise MapFileError(f"{path}: inconsistent arrays (class_count beyond 0..{num_classes})")
    if counts.sum(dtype=np.int64) != classes.size:
        raise MapFileError(f"{path}: inconsistent arrays (class_count sums to {counts.sum(dtype=np.int64)}, "
                           f"not the {classes.size} class ids)")
    if classes.size and (classes.min() < 0 or classes.max() >= num_classes):
        raise MapFileError(f"{path}: inconsistent arrays (class_id beyond num_classes {num_classes})")
    # Within a voxel the ids ascend (no class twice); the step into the next voxel may go down.
    ascending = np.diff(classes.astype(np.int64)) > 0
    ends = np.cumsum(counts, dtype=np.int64)[:-1]
    ascending[ends[(ends > 0) & (ends < classes.size)] - 1] = True
    if not ascending.all():
        raise MapFileError(f"{path}: class ids of a voxel must ascend, each class at most once")
    if not np.isfinite(values).all() or (values < 0).any():
        raise MapFileError(f"{path}: concentrations must be finite and non-negative")
    if not _is_positive_number(prior):
        raise MapFileError(f"{path}: metadata prior must be a positive number, got {prior!r}")
    return expand_rows(counts, classes, values.astype(np.float32), prior, num_classes)


def _is_positive_number(value: object) -> bool:
    """A JSON number usable as a float32 prior: finite and positive."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return False
    try:  # float(): json integers may be too large for a float
        prior = np.float32(float(value))
    except OverflowError:
        return False
    return bool(np.isfinite(prior) and prior > 0)


def _check_metadata(path: Path, metadata: dict) -> None:
    """The metadata fields a loader relies on have the right types (a hand-edited file may not)."""

    def is_int(value) -> bool:
        return isinstance(value, int) and not isinstance(value, bool)

    num_classes = metadata.get("num_classes")
    if not (is_int(num_classes) and num_classes >= 1):
        raise MapFileError(f"{path}: metadata num_classes must be a positive integer, got {num_classes!r}")
    resolution = metadata.get("resolution")
    try:  # float(): json integers may be too large for a float
        usable = (isinstance(resolution, (int, float)) and not isinstance(resolution, bool)
                  and math.isfinite(float(resolution)) and resolution > 0)
    except OverflowError:
        usable = False
    if not usable:
        raise MapFileError(f"{path}: metadata resolution must be a positive number of metres, got {resolution!r}")
    scans = metadata.get("scans_integrated", 0)
    if not (is_int(scans) and scans >= 0):
        raise MapFileError(f"{path}: metadata scans_integrated must be a count, got {scans!r}")
    if not isinstance(metadata.get("frame_id", ""), str):
        raise MapFileError(f"{path}: metadata frame_id must be a string, got {metadata.get('frame_id')!r}")
    position = metadata.get("sensor_position")
    if position is not None and not (isinstance(position, list) and len(position) == 3 and all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in position)):
        raise MapFileError(f"{path}: metadata sensor_position must be three finite numbers (m), got {position!r}")

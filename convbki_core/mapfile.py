"""The map file: one self-describing, versioned file holding a whole ConvBKI map.

Layout: an uncompressed NumPy ``.npz`` archive (readable from any language with a zip
reader and the .npy spec) with three members:

* ``metadata``: UTF-8 JSON bytes: format name and version, resolution (m), num_classes,
  frame_id, prior, local_bounds, the kernel (kernel-file mapping), class names if known;
* ``voxel_index``: (N, 3) int32 global voxel indices (centre = (index + 0.5) * resolution);
* ``alpha``: (N, C) float32 Dirichlet concentrations.

Saves are atomic (temp file in the same folder, fsync, rename).
"""

from __future__ import annotations

import json
import math
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from convbki_core.fileio import atomic_write_with
from convbki_core.kernels import kernel_config_to_dict

if TYPE_CHECKING:
    from convbki_core.mapper import ConvBKIMapper

MAP_FORMAT = "convbki_map"
MAP_VERSION = 1


class MapFileError(ValueError):
    """A map file that cannot be loaded; the message names the file and the problem."""


@dataclass
class MapSnapshot:
    """A copy of a map's contents, taken quickly; writing it to disk can then happen unlocked."""

    metadata: dict
    indices: np.ndarray  # (N, 3) int64
    alpha: np.ndarray  # (N, C) float32

    def __len__(self) -> int:
        return int(self.indices.shape[0])

    def write(self, path: str | Path) -> None:
        """Write the map file atomically: a failed write leaves the previous file as it was."""
        if self.indices.size and (np.abs(self.indices) > np.iinfo(np.int32).max).any():
            raise ValueError("voxel indices exceed the int32 range of the map file")
        arrays = {
            "metadata": np.frombuffer(json.dumps(self.metadata).encode(), dtype=np.uint8),
            "voxel_index": self.indices.astype(np.int32),
            "alpha": self.alpha.astype(np.float32, copy=False),
        }
        atomic_write_with(path, lambda handle: np.savez(handle, **arrays))


def snapshot_map(mapper: ConvBKIMapper) -> MapSnapshot:
    """Copy everything a map file holds (``items()`` returns fresh arrays) with the metadata."""
    indices, alpha = mapper.items()
    metadata = {
        "format": MAP_FORMAT,
        "version": MAP_VERSION,
        "resolution": mapper.resolution,
        "num_classes": mapper.num_classes,
        "num_voxels": int(indices.shape[0]),
        "frame_id": mapper.frame_id,
        "prior": mapper.prior,
        "local_bounds": [list(mapper.geometry.bounds_min), list(mapper.geometry.bounds_max)],
        "kernel": kernel_config_to_dict(mapper.kernel.to_config()),
        "scans_integrated": mapper.scans_integrated,
    }
    return MapSnapshot(metadata, indices, alpha)


def save_map(mapper: ConvBKIMapper, path: str | Path) -> None:
    snapshot_map(mapper).write(path)


def read_map(path: str | Path) -> tuple[dict, np.ndarray, np.ndarray]:
    """Read and check a map file: (metadata, voxel_index (N, 3) int64, alpha (N, C) float32).

    Anything that is not a complete map file of this format (empty, truncated, corrupted,
    another program's .npz or .npy, another format version) raises ``MapFileError`` naming
    the file and the problem.
    """
    path = Path(path)
    try:
        if path.is_dir():
            raise MapFileError(f"{path}: is a folder, not a map file")
        if path.exists() and path.stat().st_size == 0:
            raise MapFileError(f"{path}: empty file, not a ConvBKI map file")
        archive = np.load(path, allow_pickle=False)
        if not isinstance(archive, np.lib.npyio.NpzFile):  # a bare .npy array
            raise MapFileError(f"{path}: not a ConvBKI map file (a single NumPy array, not an .npz archive)")
        with archive:
            members = set(archive.files)
            missing = {"metadata", "voxel_index", "alpha"} - members
            if missing:
                raise MapFileError(f"{path}: not a ConvBKI map file (missing {', '.join(sorted(missing))})")
            metadata = json.loads(archive["metadata"].tobytes().decode())
            indices = archive["voxel_index"]
            alpha = archive["alpha"]
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
    if not isinstance(metadata, dict) or metadata.get("format") != MAP_FORMAT:
        raise MapFileError(f"{path}: not a ConvBKI map file (format is {metadata.get('format')!r})"
                           if isinstance(metadata, dict) else f"{path}: not a ConvBKI map file")
    if metadata.get("version") != MAP_VERSION:
        raise MapFileError(f"{path}: map format version {metadata.get('version')!r} is not supported "
                           f"(this build reads version {MAP_VERSION})")
    _check_metadata(path, metadata)
    num_classes = metadata["num_classes"]
    if indices.ndim != 2 or indices.shape[1] != 3 or alpha.ndim != 2 or alpha.shape != (indices.shape[0], num_classes):
        raise MapFileError(f"{path}: inconsistent arrays (voxel_index {indices.shape}, alpha {alpha.shape}, "
                           f"num_classes {num_classes})")
    if indices.dtype.kind != "i" or alpha.dtype.kind != "f":
        raise MapFileError(f"{path}: unexpected array types ({indices.dtype}, {alpha.dtype})")
    if not np.isfinite(alpha).all() or (alpha < 0).any():
        raise MapFileError(f"{path}: concentrations must be finite and non-negative")
    if len(np.unique(indices, axis=0)) != indices.shape[0]:
        raise MapFileError(f"{path}: duplicate voxel indices")
    return metadata, indices.astype(np.int64), alpha.astype(np.float32)


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


def load_map_into(mapper: ConvBKIMapper, path: str | Path) -> None:
    """Replace ``mapper``'s voxels with the file's; the map is untouched if the file is unusable."""
    metadata, indices, alpha = read_map(path)
    if metadata["num_classes"] != mapper.num_classes:
        raise MapFileError(f"{path}: map has {metadata['num_classes']} classes, the mapper {mapper.num_classes}")
    if not np.isclose(float(metadata["resolution"]), mapper.resolution):
        raise MapFileError(f"{path}: map resolution {metadata['resolution']} m differs from the mapper's "
                           f"{mapper.resolution} m")
    mapper.reset()
    mapper.store.write(indices, alpha)
    mapper.scans_integrated = int(metadata.get("scans_integrated", 0))

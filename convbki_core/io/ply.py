"""PLY export of map voxels for CloudCompare, Open3D or MeshLab.

Binary little-endian PLY, one vertex per voxel centre with properties
x, y, z (float32, m), red, green, blue (uint8 class colour), label (uint32 learning id),
variance (float32). Written atomically.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path
from typing import Protocol

import numpy as np

from convbki_core.io.atomic import atomic_write_with
from convbki_core.io.labels import load_label_map


class VoxelArrays(Protocol):
    """What a PLY export reads: one row per voxel (``ConvBKIMapper.voxels()`` returns one)."""

    centres: np.ndarray  # (N, 3) metres
    label: np.ndarray  # (N,) learning ids
    variance: np.ndarray  # (N,) variance of the expected class

    def __len__(self) -> int: ...

PLY_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"),
                      ("blue", "u1"), ("label", "<u4"), ("variance", "<f4")])
PLY_COMMENT = "comment convbki_ros semantic map (voxel centres)"  # what tells this project's PLY files
_PLY_TYPES = {np.dtype("<f4"): "float", np.dtype("u1"): "uchar", np.dtype("<u4"): "uint"}


def class_colours(labels: np.ndarray, colours: np.ndarray | None = None) -> np.ndarray:
    """RGB (N, 3) uint8 for learning labels; labels beyond the palette are grey."""
    if colours is None:
        colours = load_label_map().colors
    labels = np.asarray(labels, dtype=np.int64)
    result = np.full((labels.shape[0], 3), 128, np.uint8)
    known = (labels >= 0) & (labels < colours.shape[0])
    result[known] = colours[labels[known]]
    return result


def write_voxels_ply(voxels: VoxelArrays, path: str | Path, max_variance: float | None = None,
                     colours: np.ndarray | None = None, new_mode: int | None = None) -> int:
    """Write ``voxels`` (those of a class other than 0, optionally only those with variance <=
    ``max_variance``); returns the count. ``new_mode``: the permissions of a new file (a file
    replaced keeps its own; default 0666 minus the umask)."""
    keep = voxels.label != 0  # class 0 holds no semantic class (with free space: the voxel is empty)
    if max_variance:
        keep &= voxels.variance <= max_variance
    vertices = np.zeros(int(keep.sum()), PLY_DTYPE)
    vertices["x"], vertices["y"], vertices["z"] = voxels.centres[keep].T
    rgb = class_colours(voxels.label[keep], colours)
    vertices["red"], vertices["green"], vertices["blue"] = rgb.T
    vertices["label"] = voxels.label[keep]
    vertices["variance"] = voxels.variance[keep]
    header = ["ply", "format binary_little_endian 1.0", PLY_COMMENT,
              f"element vertex {vertices.shape[0]}"]
    header += [f"property {_PLY_TYPES[PLY_DTYPE[name]]} {name}" for name in PLY_DTYPE.names]
    header.append("end_header")
    blob = ("\n".join(header) + "\n").encode("ascii") + vertices.tobytes()
    atomic_write_with(path, lambda handle: handle.write(blob), new_mode=new_mode)
    return int(vertices.shape[0])


def is_own_ply(path: str | Path) -> bool:
    """Whether ``path`` is a PLY file this project wrote (its header's first lines), read without
    following a link; False for anything else, a missing file included."""
    expected = "\n".join(["ply", "format binary_little_endian 1.0", PLY_COMMENT, ""]).encode("ascii")
    try:
        descriptor = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK)
    except (OSError, ValueError):
        return False
    with os.fdopen(descriptor, "rb") as stream:
        try:
            return stat.S_ISREG(os.fstat(stream.fileno()).st_mode) and stream.read(len(expected)) == expected
        except OSError:
            return False



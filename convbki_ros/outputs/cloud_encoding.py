"""numpy -> sensor_msgs/PointCloud2: clouds written from one structured array, straight into
the buffer that becomes the message's ``data`` (no per-point Python, no second copy).

``encode_cloud`` builds rclpy messages or, given a rosbags typestore's classes, bag messages;
``records_cloud`` sends the map's packed records (``convbki_core.outputs.records.RECORD``) as points.
"""

from __future__ import annotations

import array
from collections.abc import Mapping
from typing import Any

import numpy as np

from convbki_ros.inputs.cloud_decoding import DTYPE_TO_DATATYPE
from convbki_ros.inputs.transforms import TypeResolver, make_header, message_types


def _aligned(offset: int, alignment: int) -> int:
    return (offset + alignment - 1) // alignment * alignment


def cloud_layout(fields: Mapping[str, np.ndarray]) -> tuple[list[tuple[str, int, int]], np.dtype, int]:
    """Field list ``(name, offset, datatype)``, the structured dtype and the point count.

    2-D arrays ``(N, K)`` expand into fields ``name_0 .. name_{K-1}``. Fields are laid out
    in the given order, each aligned to its own size (little-endian).
    """
    columns: list[tuple[str, np.ndarray]] = []
    for name, values in fields.items():
        values = np.asarray(values)
        if values.ndim == 1:
            columns.append((name, values))
        elif values.ndim == 2:
            columns.extend((f"{name}_{k}", values[:, k]) for k in range(values.shape[1]))
        else:
            raise ValueError(f"field {name!r} must be (N,) or (N, K), got shape {values.shape}")
    if not columns:
        raise ValueError("a cloud needs at least one field")
    count = columns[0][1].shape[0]
    layout, names, formats, offsets, offset, alignment = [], [], [], [], 0, 1
    for name, values in columns:
        if values.shape[0] != count:
            raise ValueError(f"field {name!r} has {values.shape[0]} values, expected {count}")
        dtype = values.dtype.newbyteorder("<") if values.dtype.itemsize > 1 else values.dtype
        if dtype.str[1:] not in DTYPE_TO_DATATYPE:
            raise ValueError(f"field {name!r} has dtype {values.dtype}, which PointField cannot describe")
        offset = _aligned(offset, dtype.itemsize)
        layout.append((name, offset, DTYPE_TO_DATATYPE[dtype.str[1:]]))
        names.append(name)
        formats.append(dtype)
        offsets.append(offset)
        offset += dtype.itemsize
        alignment = max(alignment, dtype.itemsize)
    point_step = _aligned(offset, alignment)
    dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": point_step})
    return layout, dtype, count


def pack_fields(fields: Mapping[str, np.ndarray],
                out: Any = None) -> tuple[list[tuple[str, int, int]], int, np.ndarray]:
    """Field layout, point_step and the (N,) structured array holding ``fields``.

    ``out``: an optional writable buffer of exactly N * point_step bytes to fill in place
    (e.g. the array.array that becomes the message's ``data``); by default a new array.
    """
    layout, dtype, count = cloud_layout(fields)
    points = np.empty(count, dtype=dtype) if out is None else np.frombuffer(out, dtype=dtype, count=count)
    for name, values in fields.items():
        values = np.asarray(values)
        if values.ndim == 1:
            points[name] = values
        else:
            for k in range(values.shape[1]):
                points[f"{name}_{k}"] = values[:, k]
    return layout, dtype.itemsize, points


def encode_cloud(stamp: Any, frame_id: str, fields: Mapping[str, np.ndarray], *,
                 types: TypeResolver | None = None, is_dense: bool | None = None) -> Any:
    """A PointCloud2 (height 1, little-endian) holding ``fields`` (name -> (N,) or (N, K) array).

    ``stamp``: int ns, (sec, nanosec) or a builtin_interfaces Time. ``types``: message
    class resolver (``transforms.message_types``), rclpy's classes by default, or a rosbags
    typestore's. ``is_dense`` defaults to "x, y, z (when present) are all finite".
    The points are written once, straight into the buffer that becomes ``data``.
    """
    types = types or message_types()
    field_class = types("sensor_msgs/msg/PointField")
    cloud_class = types("sensor_msgs/msg/PointCloud2")
    _, dtype, count = cloud_layout(fields)
    rosbags = hasattr(cloud_class, "__msgtype__")  # rosbags dataclass: uint8[] is an ndarray
    size = count * dtype.itemsize
    data: Any = np.empty(size, np.uint8) if rosbags else array.array("B", [0]) * size
    layout, point_step, points = pack_fields(fields, out=data)
    if is_dense is None:
        is_dense = all(bool(np.isfinite(points[n]).all()) for n in ("x", "y", "z") if n in points.dtype.names)
    del points  # release the view on ``data`` (an exported array.array cannot be resized)
    arguments = {
        "header": make_header(types, stamp, frame_id), "height": 1, "width": count,
        "fields": [field_class(name=name, offset=offset, datatype=datatype, count=1)
                   for name, offset, datatype in layout],
        "is_bigendian": False, "point_step": point_step, "row_step": point_step * count, "is_dense": bool(is_dense)}
    if rosbags:
        return cloud_class(data=data, **arguments)
    msg = cloud_class(**arguments)  # rclpy's constructor would copy ``data``; its setter keeps an array.array
    msg.data = data
    return msg


def pack_rgb(rgb: np.ndarray) -> np.ndarray:
    """(..., 3) uint8 RGB -> (...) float32 whose bits are 0x00RRGGBB (RViz's `rgb` field)."""
    rgb = np.asarray(rgb)
    if rgb.shape[-1] != 3:
        raise ValueError(f"rgb must have shape (..., 3), got {rgb.shape}")
    rgb = rgb.astype(np.uint32)
    return ((rgb[..., 0] << 16) | (rgb[..., 1] << 8) | rgb[..., 2]).astype(np.uint32).view(np.float32)


def map_cloud_fields(voxels: Any, class_colors: np.ndarray) -> dict[str, np.ndarray]:
    """The point fields of ``/semantic_map`` (those of ``convbki_core.outputs.records.RECORD``) from a
    VoxelSet-like object (``centres``, ``label``, ``variance``, ``confidence``): x, y, z (float32
    voxel centre, m), rgb (float32 packed class colour), label (uint32 learning id), variance and
    confidence (float32). ``class_colors``: (C, 3) uint8.
    """
    centres = np.asarray(voxels.centres)
    label = np.asarray(voxels.label)
    palette = pack_rgb(np.asarray(class_colors, dtype=np.uint8))
    return {
        "x": centres[:, 0].astype(np.float32, copy=False),
        "y": centres[:, 1].astype(np.float32, copy=False),
        "z": centres[:, 2].astype(np.float32, copy=False),
        "rgb": palette[label],
        "label": label.astype(np.uint32, copy=False),
        "variance": np.asarray(voxels.variance).astype(np.float32, copy=False),
        "confidence": np.asarray(voxels.confidence).astype(np.float32, copy=False),
    }


def records_cloud(stamp: Any, frame_id: str, dtype: np.dtype, count: int, fill) -> Any:
    """An rclpy PointCloud2 whose points are ``count`` records of the packed structured ``dtype``
    (e.g. ``convbki_core.outputs.records.RECORD``): ``fill(records)`` writes them straight into the
    buffer that becomes ``data``, so a large map is never copied after it is computed."""
    types = message_types()
    field_class = types("sensor_msgs/msg/PointField")
    data = array.array("B", [0]) * (count * dtype.itemsize)
    records = np.frombuffer(data, dtype=dtype, count=count)
    fill(records)
    del records  # an array.array with an exported buffer cannot be handed over
    fields = [field_class(name=name, offset=offset, datatype=DTYPE_TO_DATATYPE[field_dtype.str[1:]], count=1)
              for name, (field_dtype, offset) in dtype.fields.items()]
    msg = types("sensor_msgs/msg/PointCloud2")(
        header=make_header(types, stamp, frame_id), height=1, width=count, fields=fields, is_bigendian=False,
        point_step=dtype.itemsize, row_step=dtype.itemsize * count, is_dense=True)
    msg.data = data
    return msg

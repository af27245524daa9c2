"""sensor_msgs/PointCloud2 -> numpy: the PointField datatypes and the decoder.

No per-point Python: a cloud's bytes are read through one structured dtype with the
message's offsets (``np.frombuffer``, zero copy). Works on any object with the PointCloud2
attributes (rclpy messages, rosbags dataclasses, plain namespaces), and imports no rclpy.
Writing clouds is ``convbki_ros.outputs.cloud_encoding``.

Decoding accepts any field order, padding between fields, padding at the end of rows,
big-endian data (byte-swapped), x/y/z as float32 or float64, a ``label`` field of any
integer type up to 32 bits, and ``prob_0 .. prob_{C-1}`` (float32 or float64).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from convbki_core.geometry.volume import bad_probability_rows
from convbki_ros.inputs.transforms import stamp_to_ns

# sensor_msgs/PointField datatype constants.
INT8, UINT8, INT16, UINT16, INT32, UINT32, FLOAT32, FLOAT64 = range(1, 9)
DATATYPE_TO_DTYPE: dict[int, np.dtype] = {
    INT8: np.dtype("i1"), UINT8: np.dtype("u1"), INT16: np.dtype("<i2"), UINT16: np.dtype("<u2"),
    INT32: np.dtype("<i4"), UINT32: np.dtype("<u4"), FLOAT32: np.dtype("<f4"), FLOAT64: np.dtype("<f8"),
}
DTYPE_TO_DATATYPE: dict[str, int] = {dtype.str[1:]: datatype for datatype, dtype in DATATYPE_TO_DTYPE.items()}
DATATYPE_NAMES = {INT8: "int8", UINT8: "uint8", INT16: "int16", UINT16: "uint16", INT32: "int32",
                  UINT32: "uint32", FLOAT32: "float32", FLOAT64: "float64"}

POINT_TYPES = (FLOAT32, FLOAT64)
LABEL_TYPES = (UINT32, UINT16, INT32, UINT8, INT16, INT8)
PROBABILITY_TYPES = (FLOAT32, FLOAT64)


class CloudError(ValueError):
    """A PointCloud2 that cannot be decoded as asked; the message names the problem."""


# Sanity limits: far beyond any real sensor or semantic cloud, they keep an absurd header
# (a uint32 field filled with garbage) from reaching numpy as a multi-gigabyte dtype.
MAX_POINT_STEP = 1 << 24
MAX_PROBABILITY_FIELDS = 1024


# Why a point is dropped, in the order the checks apply: a point is counted once, under the first.
BAD_POINT_REASONS = ("NaN/inf coordinates", "NaN/inf probabilities", "negative probabilities",
                     "probabilities summing to zero")


@dataclass
class DecodedCloud:
    """The usable content of a PointCloud2: points with finite coordinates and valid probabilities.

    ``points`` are in the cloud's frame (m): float32 when x, y, z are all float32, else
    float64. ``labels`` (int64, as stored: raw or learning ids, the caller knows which) or
    ``probabilities`` ((N, C) float32, every row finite, non-negative, with a positive sum)
    holds the semantics, the other is None. ``bad_points`` counts the dropped points under
    each of ``BAD_POINT_REASONS`` (every reason present, 0 when none).
    """

    points: np.ndarray  # (N, 3) float32 | float64
    labels: np.ndarray | None  # (N,) int64
    probabilities: np.ndarray | None  # (N, C) float32
    raw_label_dtype: np.dtype | None  # the label field's dtype as sent (None for probabilities)
    bad_points: dict[str, int]  # reason (one of BAD_POINT_REASONS) -> points dropped for it
    total_points: int  # width * height
    intensity: np.ndarray | None = None  # (N,) float32 when the cloud has an `intensity` field
    frame_id: str = ""
    stamp_ns: int = 0

    def __len__(self) -> int:
        return int(self.points.shape[0])

    @property
    def dropped(self) -> int:
        """Points dropped, all reasons together (``total_points - len(self)``)."""
        return sum(self.bad_points.values())

    def bad_points_text(self) -> str:
        """One line such as "100 of 5100 points dropped: 60 with NaN/inf coordinates, 40 with
        negative probabilities" (reasons with a count only); "" when no point was dropped."""
        reasons = [f"{self.bad_points[reason]} with {reason}" for reason in BAD_POINT_REASONS
                   if self.bad_points.get(reason)]
        if not reasons:
            return ""
        return f"{self.dropped} of {self.total_points} points dropped: {', '.join(reasons)}"


def _buffer(data: Any) -> np.ndarray:
    """The message's ``data`` (bytes, bytearray, memoryview, array.array('B'), ndarray, list) as uint8."""
    try:
        if isinstance(data, np.ndarray):
            if data.dtype.itemsize == 1:
                return data.reshape(-1).view(np.uint8)
            return np.frombuffer(data.tobytes(), np.uint8)
        try:
            return np.frombuffer(data, dtype=np.uint8)
        except TypeError:
            return np.asarray(data, dtype=np.uint8).reshape(-1)
    except (TypeError, ValueError, OverflowError) as error:
        raise CloudError(f"data is not a byte buffer ({error.__class__.__name__})") from None


def _field_table(fields: list[Any]) -> dict[str, tuple[int, int, int]]:
    """name -> (offset, datatype, count), first occurrence of a name wins."""
    table: dict[str, tuple[int, int, int]] = {}
    for number, field in enumerate(fields):
        try:
            spec = (int(field.offset), int(field.datatype), int(field.count))
        except (TypeError, ValueError, AttributeError):
            raise CloudError(f"field {number} lacks an integer offset, datatype or count") from None
        table.setdefault(str(field.name), spec)
    return table


def _field_list(table: Mapping[str, Any], limit: int = 12) -> str:
    """Field names for a one-line message: odd names quoted (a name may hold a newline), long lists cut."""
    shown = [name if name.isprintable() and name and len(name) <= 32 else repr(name[:32]) for name in table]
    return (", ".join(shown[:limit]) + (f", ... ({len(shown)} fields)" if len(shown) > limit else "")) or "none"


def _header_integers(msg: Any) -> tuple[int, int, int, int]:
    """(point_step, width, height, row_step) as ints, each within what numpy and ROS allow."""
    values = []
    for name in ("point_step", "width", "height", "row_step"):
        try:
            value = int(getattr(msg, name))
        except (TypeError, ValueError, AttributeError):
            raise CloudError(f"{name} is not an integer") from None
        if name != "point_step" and not 0 <= value < 1 << 32:  # uint32 in the message definition
            raise CloudError(f"{name} is {value}, outside the uint32 range")
        values.append(value)
    if values[0] > MAX_POINT_STEP:
        raise CloudError(f"point_step is {values[0]} bytes, more than the {MAX_POINT_STEP} this decoder accepts")
    return values[0], values[1], values[2], values[3]


def _check_field(name: str, spec: tuple[int, int, int], allowed: tuple[int, ...], point_step: int) -> np.dtype:
    offset, datatype, count = spec
    if datatype not in DATATYPE_TO_DTYPE:
        raise CloudError(f"field {name!r} has unknown datatype {datatype}")
    if datatype not in allowed:
        names = ", ".join(DATATYPE_NAMES[d] for d in allowed)
        raise CloudError(f"field {name!r} has unsupported datatype {DATATYPE_NAMES[datatype]} (expected {names})")
    if count != 1:
        raise CloudError(f"field {name!r} has count {count}, expected 1")
    dtype = DATATYPE_TO_DTYPE[datatype]
    if offset < 0 or offset + dtype.itemsize > point_step:
        raise CloudError(f"field {name!r} (offset {offset}, {dtype.itemsize} bytes) does not fit in "
                         f"point_step {point_step}")
    return dtype


def _probability_names(table: Mapping[str, Any], num_classes: int | None) -> list[str]:
    # Only canonical names count: prob_7, not prob_07 (which would alias prob_7).
    present = sorted(int(name[5:]) for name in table
                     if name.startswith("prob_") and name[5:].isdigit() and name == f"prob_{int(name[5:])}")
    if not present:
        return []
    count = num_classes if num_classes is not None else present[-1] + 1
    if count > MAX_PROBABILITY_FIELDS:
        raise CloudError(f"probability fields for {count} classes, more than the {MAX_PROBABILITY_FIELDS} "
                         "this decoder accepts")
    present_set = set(present)
    missing = [i for i in range(count) if i not in present_set]
    extra = [i for i in present if i >= count]
    if missing or extra:
        def listed(indices: list[int]) -> str:
            return ", ".join(f"prob_{i}" for i in indices[:5]) + (" ..." if len(indices) > 5 else "")

        problems = [f"missing {listed(missing)}"] if missing else []
        problems += [f"unexpected {listed(extra)}"] if extra else []
        raise CloudError(f"incomplete probability fields for {count} classes: {'; '.join(problems)}")
    return [f"prob_{i}" for i in range(count)]


def decode_cloud(msg: Any, num_classes: int | None = None, *, require_semantics: bool = True) -> DecodedCloud:
    """Decode a PointCloud2 into finite points and their labels or class probabilities.

    ``num_classes``: when given, probability fields must be exactly ``prob_0 .. prob_{C-1}``;
    when None, C is taken from the fields present (they must still be contiguous from 0).
    Probabilities win when a cloud has both ``label`` and ``prob_*`` fields. Points with
    NaN/inf coordinates, and points whose probability row holds a NaN/inf or a negative
    value or sums to zero, are dropped and counted by reason (``DecodedCloud.bad_points``).
    Raises ``CloudError`` naming the problem for a cloud that cannot be read.
    """
    try:
        fields = list(msg.fields)
    except (TypeError, AttributeError):
        raise CloudError("message has no field list: not a PointCloud2") from None
    table = _field_table(fields)
    point_step, width, height, row_step = _header_integers(msg)
    missing = [name for name in ("x", "y", "z") if name not in table]
    if missing:
        raise CloudError(f"cloud has no {'/'.join(missing)} field (fields: {_field_list(table)})")
    probability_names = _probability_names(table, num_classes)
    label_spec = table.get("label")
    if require_semantics and not probability_names and label_spec is None:
        raise CloudError("cloud has neither a `label` field nor `prob_0..prob_{C-1}` fields "
                         f"(fields: {_field_list(table)})")
    if point_step <= 0:
        raise CloudError(f"point_step is {point_step}")

    used: dict[str, np.dtype] = {}
    for name in ("x", "y", "z"):
        used[name] = _check_field(name, table[name], POINT_TYPES, point_step)
    if probability_names:
        for name in probability_names:
            used[name] = _check_field(name, table[name], PROBABILITY_TYPES, point_step)
    elif label_spec is not None:
        used["label"] = _check_field("label", label_spec, LABEL_TYPES, point_step)
    if "intensity" in table and table["intensity"][1] in DATATYPE_TO_DTYPE and table["intensity"][2] == 1:
        # Optional and informative only: a malformed intensity field is ignored, not an error.
        dtype = DATATYPE_TO_DTYPE[table["intensity"][1]]
        if table["intensity"][0] >= 0 and table["intensity"][0] + dtype.itemsize <= point_step:
            used["intensity"] = dtype

    count = width * height
    row_bytes = width * point_step
    # A row holds width points: a shorter row_step (0 included) is a malformed header, whatever
    # the number of rows (the points it describes cannot be told apart from their neighbours').
    if count and row_step < row_bytes:
        raise CloudError(f"row_step {row_step} is smaller than width * point_step = {row_bytes}")
    raw = _buffer(msg.data)
    needed = row_step * height if count else 0  # height rows of row_step bytes
    if raw.size < needed:
        raise CloudError(f"data holds {raw.size} bytes, expected at least {needed} "
                         f"(width {width} x height {height} x point_step {point_step}, row_step {row_step})")
    if count and height > 1 and row_step != row_bytes:  # padding at the end of each row: drop it (one copy)
        raw = np.ascontiguousarray(raw[: row_step * height].reshape(height, row_step)[:, :row_bytes]).reshape(-1)

    order = ">" if bool(msg.is_bigendian) else "<"
    names = list(used)
    structured = np.dtype({"names": names, "formats": [used[n].newbyteorder(order) for n in names],
                           "offsets": [table[n][0] for n in names], "itemsize": point_step})
    view = np.frombuffer(raw, dtype=structured, count=count)

    point_dtype = np.float32 if all(used[n] == np.dtype("<f4") for n in ("x", "y", "z")) else np.float64
    points = np.empty((count, 3), dtype=point_dtype)
    for column, name in enumerate(("x", "y", "z")):
        points[:, column] = view[name]
    keep = np.isfinite(points).all(axis=1)
    bad_points = dict.fromkeys(BAD_POINT_REASONS, 0)
    bad_points[BAD_POINT_REASONS[0]] = int(count - np.count_nonzero(keep))

    probabilities = labels = raw_label_dtype = None
    if probability_names:
        with np.errstate(over="ignore", invalid="ignore"):  # beyond float32: inf, then dropped
            probabilities = _gather_probabilities(view, table, probability_names, used, order, point_step, raw,
                                                  count)
        for reason, bad in zip(BAD_POINT_REASONS[1:], bad_probability_rows(probabilities)):
            bad &= keep  # a point is counted under its first reason only
            bad_points[reason] = int(np.count_nonzero(bad))
            keep &= ~bad
    elif "label" in used:
        raw_label_dtype = used["label"]
        labels = view["label"].astype(np.int64)
    with np.errstate(over="ignore", invalid="ignore"):  # a float64 beyond float32's range becomes inf, as a cast should
        intensity = view["intensity"].astype(np.float32) if "intensity" in used else None

    if count - np.count_nonzero(keep):
        points = points[keep]
        labels = labels[keep] if labels is not None else None
        probabilities = probabilities[keep] if probabilities is not None else None
        intensity = intensity[keep] if intensity is not None else None
    header = getattr(msg, "header", None)
    try:
        frame_id = str(getattr(header, "frame_id", "")) if header is not None else ""
        stamp_ns = stamp_to_ns(header.stamp) if header is not None else 0
    except (TypeError, ValueError, AttributeError, OverflowError):
        raise CloudError("header has no usable stamp") from None
    return DecodedCloud(points=points, labels=labels, probabilities=probabilities, raw_label_dtype=raw_label_dtype,
                        bad_points=bad_points, total_points=count, intensity=intensity,
                        frame_id=frame_id, stamp_ns=stamp_ns)


def _gather_probabilities(view: np.ndarray, table: Mapping[str, tuple[int, int, int]], names: list[str],
                          used: Mapping[str, np.dtype], order: str, point_step: int, raw: np.ndarray,
                          count: int) -> np.ndarray:
    """(N, C) float32 probabilities; one strided sub-array view when the fields are packed."""
    first = table[names[0]][0]
    dtype = used[names[0]]
    packed = all(used[n] == dtype and table[n][0] == first + i * dtype.itemsize for i, n in enumerate(names))
    if packed:
        block = np.dtype({"names": ["p"], "formats": [(dtype.newbyteorder(order), (len(names),))],
                          "offsets": [first], "itemsize": point_step})
        return np.frombuffer(raw, dtype=block, count=count)["p"].astype(np.float32)
    out = np.empty((count, len(names)), dtype=np.float32)
    for column, name in enumerate(names):
        out[:, column] = view[name]
    return out

"""PointCloud2 codec (pointcloud, cloud_encoding) and pose helpers: property tests on every supported
layout, real rclpy messages."""

from __future__ import annotations

import array
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from ros_helpers import odometry_to_pose, unpack_rgb

from convbki_core.geometry.poses import pose_from_translation_quaternion
from convbki_core.outputs.records import RECORD
from convbki_ros.inputs import cloud_decoding as pc
from convbki_ros.inputs import transforms as tf
from convbki_ros.outputs import cloud_encoding as enc

DTYPE_CODES = {"f4": pc.FLOAT32, "f8": pc.FLOAT64, "u4": pc.UINT32, "u2": pc.UINT16, "i4": pc.INT32,
               "u1": pc.UINT8, "i2": pc.INT16, "i1": pc.INT8}


def make_message(columns: dict[str, np.ndarray], order: list[str], gaps: list[int], tail: int, *,
                 big_endian: bool = False, height: int = 1, row_padding: int = 0, container: str = "bytes",
                 frame_id: str = "velo_link", stamp: tuple[int, int] = (5, 6)) -> SimpleNamespace:
    """A duck-typed PointCloud2 built independently of the encoder: fields in ``order`` with
    ``gaps[i]`` spare bytes before field i, ``tail`` bytes after the last, rows padded."""
    count = len(next(iter(columns.values())))
    offsets, offset = [], 0
    for name, gap in zip(order, gaps):
        offset += gap
        offsets.append(offset)
        offset += columns[name].dtype.itemsize
    point_step = offset + tail
    byte_order = ">" if big_endian else "<"
    dtype = np.dtype({"names": order, "formats": [columns[n].dtype.newbyteorder(byte_order) for n in order],
                      "offsets": offsets, "itemsize": point_step})
    points = np.zeros(count, dtype=dtype)  # zeroed padding, like any sane driver
    for name in order:
        points[name] = columns[name]
    width = count // height
    rows = points.view(np.uint8).reshape(height, width * point_step)
    raw = np.zeros((height, width * point_step + row_padding), np.uint8)
    raw[:, : width * point_step] = rows
    blob = raw.tobytes()
    data = {"bytes": blob, "bytearray": bytearray(blob), "memoryview": memoryview(blob),
            "array": array.array("B", blob), "ndarray": np.frombuffer(blob, np.uint8)}[container]
    fields = [SimpleNamespace(name=n, offset=o, datatype=DTYPE_CODES[columns[n].dtype.str[1:]], count=1)
              for n, o in zip(order, offsets)]
    return SimpleNamespace(header=SimpleNamespace(stamp=SimpleNamespace(sec=stamp[0], nanosec=stamp[1]),
                                                  frame_id=frame_id),
                           height=height, width=width, fields=fields, is_bigendian=big_endian,
                           point_step=point_step, row_step=width * point_step + row_padding, data=data,
                           is_dense=True)


finite32 = st.floats(min_value=-1e6, max_value=1e6, width=32, allow_nan=False, allow_infinity=False)


@st.composite
def layouts(draw):
    """Random clouds: sizes, xyz types, label or probabilities, extra fields, order, gaps, endianness."""
    height = draw(st.sampled_from([1, 1, 2, 3]))
    width = draw(st.integers(0, 12))
    count = width * height
    columns: dict[str, np.ndarray] = {}
    for axis in "xyz":
        dtype = draw(st.sampled_from(["<f4", "<f8"]))
        values = draw(st.lists(finite32, min_size=count, max_size=count))
        columns[axis] = np.array(values, dtype=np.float32).astype(dtype)
    semantics = draw(st.sampled_from(["label", "prob"]))
    num_classes = None
    if semantics == "label":
        code = draw(st.sampled_from(["u4", "u2", "i4", "u1", "i2", "i1"]))
        info = np.iinfo(np.dtype(code))
        values = draw(st.lists(st.integers(int(info.min), int(info.max)), min_size=count, max_size=count))
        columns["label"] = np.array(values, dtype=np.dtype(code).newbyteorder("<"))
    else:
        num_classes = draw(st.integers(1, 5))
        probability_type = draw(st.sampled_from(["<f4", "<f4", "<f8"]))
        table = np.array([draw(st.lists(st.floats(0, 1, width=32), min_size=count, max_size=count))
                          for _ in range(num_classes)], dtype=np.float32).reshape(num_classes, count)
        table[0, ~table.any(axis=0)] = 1.0  # an all-zero row is a bad point: see test_bad_probability_rows_*
        for k in range(num_classes):
            columns[f"prob_{k}"] = table[k].astype(probability_type)
    if draw(st.booleans()):
        values = draw(st.lists(finite32, min_size=count, max_size=count))
        columns["intensity"] = np.array(values, dtype="<f4")
    if draw(st.booleans()):
        columns["ring"] = np.arange(count, dtype="<u2")
    order = draw(st.permutations(list(columns)))
    gaps = draw(st.lists(st.integers(0, 9), min_size=len(order), max_size=len(order)))
    return SimpleNamespace(columns=columns, order=list(order), gaps=gaps, tail=draw(st.integers(0, 7)),
                           big_endian=draw(st.booleans()), height=height,
                           row_padding=draw(st.integers(0, 5)) if height > 1 else 0,
                           container=draw(st.sampled_from(["bytes", "bytearray", "memoryview", "array", "ndarray"])),
                           num_classes=num_classes, semantics=semantics)


def expected_points(columns: dict[str, np.ndarray]) -> np.ndarray:
    all32 = all(columns[a].dtype == np.float32 for a in "xyz")
    out_type = np.float32 if all32 else np.float64
    return np.stack([columns[a].astype(out_type) for a in "xyz"], axis=1)


@given(layouts())
def test_decode_any_layout_to_the_bit(layout) -> None:
    msg = make_message(layout.columns, layout.order, layout.gaps, layout.tail, big_endian=layout.big_endian,
                       height=layout.height, row_padding=layout.row_padding, container=layout.container)
    decoded = pc.decode_cloud(msg, layout.num_classes)
    points = expected_points(layout.columns)
    assert decoded.points.dtype == points.dtype
    assert decoded.points.tobytes() == points.tobytes()
    assert decoded.bad_points == dict.fromkeys(pc.BAD_POINT_REASONS, 0)
    assert decoded.dropped == 0 and decoded.bad_points_text() == ""
    assert decoded.total_points == len(points)
    assert decoded.frame_id == "velo_link"
    assert decoded.stamp_ns == 5_000_000_006
    if layout.semantics == "label":
        assert decoded.probabilities is None
        assert decoded.raw_label_dtype == layout.columns["label"].dtype
        assert decoded.labels.dtype == np.int64
        assert np.array_equal(decoded.labels, layout.columns["label"].astype(np.int64))
    else:
        assert decoded.labels is None
        expected = np.stack([layout.columns[f"prob_{k}"] for k in range(layout.num_classes)], axis=1)
        assert decoded.probabilities.dtype == np.float32
        assert decoded.probabilities.shape == (len(points), layout.num_classes)
        assert decoded.probabilities.tobytes() == expected.astype(np.float32).tobytes()
    if "intensity" in layout.columns:
        assert decoded.intensity.tobytes() == layout.columns["intensity"].astype(np.float32).tobytes()


@given(layouts())
def test_encoder_round_trip_any_field_order(layout) -> None:
    """encode_cloud -> decode_cloud on rclpy's real PointCloud2, through rclpy's CDR serialisation."""
    from rclpy.serialization import deserialize_message, serialize_message
    from sensor_msgs.msg import PointCloud2

    fields = {name: layout.columns[name] for name in layout.order}
    msg = enc.encode_cloud((7, 8), "velo_link", fields)
    assert isinstance(msg, PointCloud2)
    assert [f.name for f in msg.fields] == layout.order
    assert all(f.offset % np.dtype(fields[f.name].dtype).itemsize == 0 for f in msg.fields)  # aligned
    assert msg.row_step == msg.point_step * msg.width and len(msg.data) == msg.row_step
    back = deserialize_message(serialize_message(msg), PointCloud2)
    decoded = pc.decode_cloud(back, layout.num_classes)
    assert decoded.points.tobytes() == expected_points(layout.columns).tobytes()
    assert decoded.stamp_ns == 7_000_000_008
    if layout.semantics == "label":
        assert np.array_equal(decoded.labels, layout.columns["label"].astype(np.int64))
        assert decoded.raw_label_dtype == layout.columns["label"].dtype


def test_rosbags_encoding_is_read_by_rclpy() -> None:
    """The bag writer's path (rosbags dataclasses + CDR) yields what rclpy deserialises and we decode."""
    from rclpy.serialization import deserialize_message
    from rosbags.typesys import Stores, get_typestore
    from sensor_msgs.msg import PointCloud2

    store = get_typestore(Stores.ROS2_JAZZY)
    rng = np.random.default_rng(3)
    xyz = rng.normal(size=(500, 3)).astype(np.float32)
    labels = rng.integers(0, 2**32, 500, dtype=np.uint64).astype(np.uint32)
    probs = rng.random((500, 4)).astype(np.float32)
    msg = enc.encode_cloud(1_700_000_000_123_456_789, "velo_link",
                          {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], "label": labels, "prob": probs},
                          types=tf.message_types(store))
    back = deserialize_message(bytes(store.serialize_cdr(msg, msg.__msgtype__)), PointCloud2)
    assert [f.name for f in back.fields] == ["x", "y", "z", "label", "prob_0", "prob_1", "prob_2", "prob_3"]
    decoded = pc.decode_cloud(back, 4)
    assert decoded.points.tobytes() == xyz.tobytes()
    assert decoded.probabilities.tobytes() == probs.tobytes()  # probabilities win over label
    assert decoded.stamp_ns == 1_700_000_000_123_456_789
    only_labels = pc.decode_cloud(enc.encode_cloud(0, "f", {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2],
                                                           "label": labels}))
    assert np.array_equal(only_labels.labels, labels.astype(np.int64))


@given(st.integers(1, 40), st.data())
def test_non_finite_points_are_dropped_and_counted(count: int, data) -> None:
    rng = np.random.default_rng(count)
    xyz = rng.normal(size=(count, 3)).astype(np.float32)
    labels = np.arange(count, dtype=np.uint32)
    bad = np.array(data.draw(st.lists(st.booleans(), min_size=count, max_size=count)))
    poison = data.draw(st.sampled_from([np.nan, np.inf, -np.inf]))
    axis = rng.integers(0, 3, count)
    xyz[bad, axis[bad]] = poison
    msg = enc.encode_cloud(0, "velo_link", {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], "label": labels})
    assert msg.is_dense == (not bad.any())
    decoded = pc.decode_cloud(msg)
    assert decoded.bad_points == {**dict.fromkeys(pc.BAD_POINT_REASONS, 0), "NaN/inf coordinates": int(bad.sum())}
    assert decoded.dropped == int(bad.sum())
    assert decoded.bad_points_text() == (f"{bad.sum()} of {count} points dropped: {bad.sum()} with NaN/inf "
                                         "coordinates" if bad.any() else "")
    assert decoded.total_points == count
    assert np.array_equal(decoded.labels, labels[~bad].astype(np.int64))
    assert decoded.points.tobytes() == xyz[~bad].tobytes()


def test_bad_probability_rows_are_dropped_and_counted_by_reason() -> None:
    rows = [  # (x, probabilities as float64, the reason it is dropped or None)
        (0.0, [0.5, 0.5, 0.0], None),
        (1.0, [0.2, -0.1, 0.9], "negative probabilities"),
        (2.0, [np.nan, 0.5, 0.5], "NaN/inf probabilities"),
        (3.0, [0.0, 0.0, 0.0], "probabilities summing to zero"),
        (4.0, [0.0, 1.0, 0.0], None),
        (5.0, [np.inf, 0.0, 0.0], "NaN/inf probabilities"),
        (6.0, [-0.0, 0.0, -0.0], "probabilities summing to zero"),  # signed zeros are zero
        (7.0, [-np.inf, 1.0, 1.0], "NaN/inf probabilities"),  # -inf is non-finite before it is negative
        (8.0, [-1.0, np.nan, 1.0], "NaN/inf probabilities"),  # counted once, under its first reason
        (np.nan, [-1.0, 0.0, 0.0], "NaN/inf coordinates"),  # coordinates come first
        (10.0, [1e300, 0.5, 0.5], "NaN/inf probabilities"),  # float64 beyond float32's range: inf
        (11.0, [1e-300, 0.0, 0.0], "probabilities summing to zero"),  # below float32's subnormals: 0
        (12.0, [-1e-30, 1.0, 1.0], "negative probabilities"),
        (13.0, [1e-45, 0.0, 0.0], None),  # float32's smallest subnormal: a positive sum
    ]
    xyz = np.array([[x, 0.0, 0.0] for x, _, _ in rows], np.float32)
    probs = np.array([p for _, p, _ in rows], np.float64)
    msg = enc.encode_cloud(0, "f", {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], "prob": probs})
    decoded = pc.decode_cloud(msg, 3)
    assert decoded.bad_points == {"NaN/inf coordinates": 1, "NaN/inf probabilities": 5, "negative probabilities": 2,
                                  "probabilities summing to zero": 3}
    assert decoded.dropped == 11 and decoded.total_points == 14 and len(decoded) == 3
    assert decoded.bad_points_text() == ("11 of 14 points dropped: 1 with NaN/inf coordinates, 5 with NaN/inf "
                                         "probabilities, 2 with negative probabilities, 3 with probabilities "
                                         "summing to zero")
    good = [i for i, (_, _, reason) in enumerate(rows) if reason is None]
    assert decoded.points[:, 0].tolist() == [0.0, 4.0, 13.0]
    assert decoded.probabilities.tobytes() == probs[good].astype(np.float32).tobytes()


def test_bad_points_text_names_only_the_reasons_present() -> None:
    xyz = np.zeros((5, 3), np.float32)
    probs = np.array([[0.5, 0.5], [-0.5, 1.5], [0.0, 0.0], [-2.0, 0.0], [1.0, 0.0]], np.float32)
    decoded = pc.decode_cloud(enc.encode_cloud(0, "f", {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2],
                                                       "prob": probs}), 2)
    assert decoded.bad_points_text() == ("3 of 5 points dropped: 2 with negative probabilities, 1 with "
                                         "probabilities summing to zero")
    assert np.array_equal(decoded.probabilities, probs[[0, 4]])


@given(st.integers(0, 2**31 - 1))
def test_bad_probability_rows_any_mix(seed: int) -> None:
    """Counts per reason and the surviving rows equal a row-by-row classification in plain Python."""
    import math

    rng = np.random.default_rng(seed)
    count, classes = int(rng.integers(0, 60)), int(rng.integers(1, 5))
    xyz = rng.normal(size=(count, 3)).astype(np.float32)
    probs = rng.random((count, classes)).astype(np.float32)
    poisons = np.array([np.nan, np.inf, -np.inf, -0.5, -0.0, 0.0, 0.0, 0.0], np.float32)
    mask = rng.random((count, classes)) < 0.15
    probs[mask] = poisons[rng.integers(0, len(poisons), int(mask.sum()))]
    probs[rng.random(count) < 0.1] = 0.0
    xyz[rng.random(count) < 0.1, 1] = np.nan

    def reason(point, row) -> str | None:
        if not all(math.isfinite(float(v)) for v in point):
            return "NaN/inf coordinates"
        if not all(math.isfinite(float(v)) for v in row):
            return "NaN/inf probabilities"
        if any(float(v) < 0 for v in row):
            return "negative probabilities"
        if sum(float(v) for v in row) <= 0:
            return "probabilities summing to zero"
        return None

    reasons = [reason(point, row) for point, row in zip(xyz, probs)]
    decoded = pc.decode_cloud(enc.encode_cloud(0, "f", {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2],
                                                       "prob": probs}), classes)
    assert decoded.bad_points == {r: reasons.count(r) for r in pc.BAD_POINT_REASONS}
    assert decoded.dropped + len(decoded) == decoded.total_points == count
    good = np.array([r is None for r in reasons], bool)
    assert decoded.points.tobytes() == xyz[good].tobytes()
    assert decoded.probabilities.tobytes() == probs[good].tobytes()


def _good(**changes) -> SimpleNamespace:
    columns = {"x": np.zeros(4, "<f4"), "y": np.ones(4, "<f4"), "z": np.full(4, 2, "<f4"),
               "label": np.arange(4, dtype="<u4")}
    msg = make_message(columns, list(columns), [0] * 4, 0)
    for key, value in changes.items():
        setattr(msg, key, value)
    return msg


def _field(name, offset, datatype, count=1):
    return SimpleNamespace(name=name, offset=offset, datatype=datatype, count=count)


XYZ = [_field("x", 0, pc.FLOAT32), _field("y", 4, pc.FLOAT32), _field("z", 8, pc.FLOAT32)]


@pytest.mark.parametrize(("changes", "num_classes", "message"), [
    ({"fields": XYZ[1:] + [_field("label", 12, pc.UINT32)]}, None, r"no x field"),
    ({"fields": [XYZ[0], _field("label", 12, pc.UINT32)]}, None, r"no y/z field"),
    ({"fields": XYZ}, None, r"neither a `label` field nor `prob_0"),
    ({"fields": XYZ + [_field("label", 12, pc.FLOAT32)]}, None, r"'label' has unsupported datatype float32"),
    ({"fields": [_field("x", 0, pc.INT32)] + XYZ[1:] + [_field("label", 12, pc.UINT32)]}, None,
     r"'x' has unsupported datatype int32"),
    ({"fields": XYZ + [_field("label", 12, 42)]}, None, r"'label' has unknown datatype 42"),
    ({"fields": XYZ + [_field("label", 12, pc.UINT32, count=3)]}, None, r"'label' has count 3"),
    ({"point_step": 12}, None, r"'label' \(offset 12, 4 bytes\) does not fit in point_step 12"),
    ({"data": b"\0" * 63}, None, r"data holds 63 bytes, expected at least 64"),
    ({"width": 5, "row_step": 80}, None, r"data holds 64 bytes, expected at least 80"),
    ({"row_step": 100}, None, r"data holds 64 bytes, expected at least 100 \(.*row_step 100\)"),
    ({"fields": XYZ + [_field("prob_0", 12, pc.FLOAT32), _field("prob_2", 12, pc.FLOAT32)]}, None,
     r"incomplete probability fields for 3 classes: missing prob_1"),
    ({"fields": XYZ + [_field("prob_0", 12, pc.FLOAT32), _field("prob_1", 12, pc.FLOAT32)]}, 3,
     r"incomplete probability fields for 3 classes: missing prob_2"),
    ({"fields": XYZ + [_field("prob_0", 12, pc.FLOAT32), _field("prob_1", 12, pc.FLOAT32)]}, 1,
     r"incomplete probability fields for 1 classes: unexpected prob_1"),
    ({"fields": XYZ + [_field("prob_0", 12, pc.UINT32)]}, 1, r"'prob_0' has unsupported datatype uint32"),
    ({"height": 2, "width": 2, "row_step": 30}, None, r"row_step 30 is smaller than width \* point_step = 32"),
    # One row or two: the same answer (a row_step of 0 included).
    ({"height": 1, "width": 4, "row_step": 60}, None, r"row_step 60 is smaller than width \* point_step = 64"),
    ({"height": 1, "width": 4, "row_step": 0}, None, r"row_step 0 is smaller than width \* point_step = 64"),
    ({"height": 2, "width": 2, "row_step": 0}, None, r"row_step 0 is smaller than width \* point_step = 32"),
])
def test_malformed_clouds_are_refused_with_a_reason(changes, num_classes, message) -> None:
    with pytest.raises(pc.CloudError, match=message):
        pc.decode_cloud(_good(**changes), num_classes)
    assert issubclass(pc.CloudError, ValueError)


def test_good_reference_cloud_decodes() -> None:
    decoded = pc.decode_cloud(_good())
    assert np.array_equal(decoded.labels, [0, 1, 2, 3])
    assert np.array_equal(decoded.points[:, 1], [1, 1, 1, 1])


def test_big_endian_cloud_is_byte_swapped() -> None:
    columns = {"x": np.array([1.5, -2.25], ">f4").astype("<f4"), "y": np.array([3.0, 4.0], "<f8"),
               "z": np.array([0.0, 1e-3], "<f4"), "label": np.array([0x01020304, 10], "<u4")}
    msg = make_message(columns, ["label", "x", "y", "z"], [0, 4, 0, 0], 3, big_endian=True)
    assert msg.data[:4] == bytes([1, 2, 3, 4])  # really big-endian on the wire
    decoded = pc.decode_cloud(msg)
    assert decoded.points.dtype == np.float64
    assert np.array_equal(decoded.points, [[1.5, 3.0, np.float32(0.0)], [-2.25, 4.0, np.float32(1e-3)]])
    assert np.array_equal(decoded.labels, [0x01020304, 10])


@given(st.lists(st.tuples(st.integers(0, 255), st.integers(0, 255), st.integers(0, 255)), min_size=1, max_size=50))
def test_rgb_pack_unpack_round_trip(colours) -> None:
    rgb = np.array(colours, np.uint8)
    packed = enc.pack_rgb(rgb)
    assert packed.dtype == np.float32
    bits = packed.view(np.uint32)
    assert np.array_equal(bits, (rgb[:, 0].astype(np.uint32) << 16) | (rgb[:, 1].astype(np.uint32) << 8) | rgb[:, 2])
    assert np.array_equal(unpack_rgb(packed), rgb)


def test_rgb_known_value() -> None:
    assert enc.pack_rgb(np.array([255, 0, 0], np.uint8)).view(np.uint32) == 0x00FF0000
    assert enc.pack_rgb(np.array([[1, 2, 3]], np.uint8)).view(np.uint32)[0] == 0x00010203


def test_map_cloud_fields_round_trip() -> None:
    """The /semantic_map point fields survive encoding exactly, in the record layout the node sends."""
    rng = np.random.default_rng(0)
    colors = rng.integers(0, 256, (20, 3)).astype(np.uint8)
    voxels = SimpleNamespace(centres=rng.normal(size=(100, 3)).astype(np.float32), label=rng.integers(0, 20, 100),
                             variance=rng.random(100).astype(np.float32),
                             confidence=rng.random(100).astype(np.float32))
    msg = enc.encode_cloud((1, 2), "map", enc.map_cloud_fields(voxels, colors))
    assert [(f.name, f.offset, f.datatype) for f in msg.fields] == [
        (name, offset, pc.DTYPE_TO_DATATYPE[dtype.str[1:]]) for name, (dtype, offset) in RECORD.fields.items()]
    assert msg.point_step == RECORD.itemsize and msg.width == 100 and msg.header.frame_id == "map"
    view = np.frombuffer(msg.data, dtype=RECORD)
    assert np.array_equal(np.stack([view["x"], view["y"], view["z"]], 1), voxels.centres)
    assert np.array_equal(unpack_rgb(view["rgb"]), colors[voxels.label])
    assert np.array_equal(view["label"], voxels.label) and np.array_equal(view["variance"], voxels.variance)
    assert np.array_equal(view["confidence"], voxels.confidence)
    decoded = pc.decode_cloud(msg)  # the map's own clouds read back with the node's decoder
    assert np.array_equal(decoded.points, voxels.centres) and np.array_equal(decoded.labels, voxels.label)


# ----------------------------------------------------------------------------- transforms


@pytest.mark.parametrize("backend", ["rclpy", "rosbags"])
def test_odometry_and_transform_round_trip(backend: str) -> None:
    if backend == "rosbags":
        from rosbags.typesys import Stores, get_typestore

        types = tf.message_types(get_typestore(Stores.ROS2_JAZZY))
    else:
        types = tf.message_types()
    rng = np.random.default_rng(1)
    q = rng.normal(size=4)
    pose = pose_from_translation_quaternion(rng.normal(size=3) * 100, q / np.linalg.norm(q))
    odom = tf.pose_to_odometry(pose, 1_700_000_000_250_000_001, "map", "velo_link", types)
    assert odom.header.frame_id == "map" and odom.child_frame_id == "velo_link"
    assert (odom.header.stamp.sec, odom.header.stamp.nanosec) == (1_700_000_000, 250_000_001)
    assert np.allclose(odometry_to_pose(odom), pose, atol=1e-12)
    transform = tf.pose_to_transform_stamped(pose, (3, 4), "map", "velo_link", types)
    assert np.allclose(tf.transform_to_pose(transform), pose, atol=1e-12)
    assert tf.stamp_to_ns(transform.header.stamp) == 3_000_000_004


def test_stamps() -> None:
    assert tf.ns_to_stamp(-1) == (-1, 999_999_999)
    assert tf.stamp_to_ns(tf.ns_to_stamp(1_700_000_000_000_000_123)) == 1_700_000_000_000_000_123
    assert tf.seconds_to_ns(0.1) == 100_000_000
    with pytest.raises(TypeError):
        tf.stamp_to_ns(1.5)

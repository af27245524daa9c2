"""Fuzzing the two parsers that read what other programs wrote: PointCloud2 and kernel files.

Whatever arrives, the PointCloud2 decoder either returns a well-formed DecodedCloud or
raises CloudError, and the kernel-file loader either returns a valid KernelConfig or raises
KernelFileError: never another exception. Example counts are set here (not by the profile)
so every run tries thousands of inputs; deadline=None because a 2-core CI machine is slow.
"""

from __future__ import annotations

import array
import math
import string
from types import SimpleNamespace

import numpy as np
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from convbki_core.io.kernel_file import (
    KERNEL_KINDS,
    KernelConfig,
    KernelFileError,
    kernel_config_from_dict,
    load_kernel_file,
    parse_kernel_text,
)
from convbki_ros.inputs.cloud_decoding import BAD_POINT_REASONS, CloudError, DecodedCloud, decode_cloud


def fuzz(examples: int) -> settings:
    """The loaded profile (derandomised in CI) with this many examples and no deadline."""
    return settings(max_examples=examples, deadline=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much,
                                           HealthCheck.data_too_large])

# ----------------------------------------------------------------------------- PointCloud2

FIELD_NAMES = ["x", "y", "z", "label", "intensity", "prob_0", "prob_1", "prob_2", "prob_01", "prob_", "prob_x",
               "rgb", "prob_1023", "prob_99999999", ""]
# Mostly small plausible values, sometimes far outside what a uint32 message field can hold.
small_or_wild = st.one_of(st.integers(-4, 48), st.integers(-4, 48), st.integers(-2**40, 2**40))


@st.composite
def point_fields(draw):
    return SimpleNamespace(name=draw(st.one_of(st.sampled_from(FIELD_NAMES), st.text(max_size=8))),
                           offset=draw(small_or_wild), datatype=draw(st.integers(-1, 10)),
                           count=draw(st.sampled_from([1, 1, 1, 0, 2, -1])))


def _container(draw, blob: bytes):
    kind = draw(st.sampled_from(["bytes", "bytearray", "array", "ndarray", "memoryview"]))
    return {"bytes": lambda: blob, "bytearray": lambda: bytearray(blob), "array": lambda: array.array("B", blob),
            "ndarray": lambda: np.frombuffer(blob, np.uint8), "memoryview": lambda: memoryview(blob)}[kind]()


@st.composite
def arbitrary_clouds(draw):
    """Any header and field list, any bytes (often too few)."""
    fields = draw(st.lists(point_fields(), max_size=10))
    return SimpleNamespace(
        header=SimpleNamespace(stamp=SimpleNamespace(sec=draw(st.integers(0, 2**31)), nanosec=7), frame_id="f"),
        fields=fields, height=draw(st.one_of(st.integers(-1, 4), st.integers(0, 2**33))),
        width=draw(st.one_of(st.integers(-1, 40), st.integers(0, 2**33))),
        point_step=draw(small_or_wild), row_step=draw(small_or_wild), is_bigendian=draw(st.booleans()),
        data=_container(draw, draw(st.binary(max_size=700))), is_dense=draw(st.booleans()))


@st.composite
def damaged_clouds(draw):
    """A well-formed cloud (x, y, z float32/64, label or probabilities, padding) with a few things broken.

    Starting from valid layouts reaches the decoder's deep paths (strides, byte order,
    probability blocks, non-finite values) that random headers rarely get past.
    """
    count = draw(st.integers(0, 12))
    height = draw(st.sampled_from([1, 1, 2])) if count % 2 == 0 else 1
    xyz = draw(st.sampled_from(["<f4", "<f8"]))
    names, formats = ["x", "y", "z"], [xyz] * 3
    semantics = draw(st.sampled_from(["label", "prob", "both", "none"]))
    classes = draw(st.integers(1, 4))
    if semantics in ("label", "both"):
        names.append("label")
        formats.append(draw(st.sampled_from(["<u4", "<u2", "<i4", "u1", "<i2", "i1", "<f4"])))
    if semantics in ("prob", "both"):
        names += [f"prob_{k}" for k in range(classes)]
        formats += [draw(st.sampled_from(["<f4", "<f8"]))] * classes
    if draw(st.booleans()):
        names.append("intensity")
        formats.append(draw(st.sampled_from(["<f4", "u1", "<f8"])))
    order = draw(st.permutations(range(len(names))))
    offsets, offset = [0] * len(names), 0
    for index in order:
        offset += draw(st.integers(0, 3))
        offsets[index] = offset
        offset += np.dtype(formats[index]).itemsize
    point_step = offset + draw(st.integers(0, 4))
    width = count // height
    row_padding = draw(st.integers(0, 5)) if height > 1 else 0
    row_step = width * point_step + row_padding
    blob = bytearray(draw(st.binary(min_size=row_step * height, max_size=row_step * height)))
    # Random bytes are mostly NaN-free garbage; sprinkle real non-finite values in too.
    for _ in range(draw(st.integers(0, 3))):
        if len(blob) >= 4:
            at = draw(st.integers(0, len(blob) - 4))
            blob[at:at + 4] = np.array([draw(st.sampled_from([np.nan, np.inf, -np.inf, 1.5]))], "<f4").tobytes()
    codes = {"i1": 1, "u1": 2, "<i2": 3, "<u2": 4, "<i4": 5, "<u4": 6, "<f4": 7, "<f8": 8}
    fields = [SimpleNamespace(name=n, offset=o, datatype=codes[f], count=1) for n, o, f in zip(names, offsets, formats)]
    msg = SimpleNamespace(header=SimpleNamespace(stamp=SimpleNamespace(sec=1, nanosec=2), frame_id="velo"),
                          fields=fields, height=height, width=width, point_step=point_step, row_step=row_step,
                          is_bigendian=draw(st.booleans()), data=bytes(blob), is_dense=False)
    # Break zero to three things.
    for _ in range(draw(st.integers(0, 3))):
        what = draw(st.sampled_from(["truncate", "offset", "datatype", "count", "point_step", "row_step", "width",
                                     "height", "drop", "duplicate", "rename"]))
        if what == "truncate":
            msg.data = msg.data[: draw(st.integers(0, max(0, len(msg.data) - 1)))]
        elif what in ("offset", "datatype", "count") and msg.fields:
            field = draw(st.sampled_from(msg.fields))
            setattr(field, what, draw(small_or_wild if what == "offset" else st.integers(-1, 10)))
        elif what in ("point_step", "row_step", "width", "height"):
            setattr(msg, what, draw(small_or_wild))
        elif what == "drop" and msg.fields:
            msg.fields.pop(draw(st.integers(0, len(msg.fields) - 1)))
        elif what == "duplicate" and msg.fields:
            copy = SimpleNamespace(**vars(draw(st.sampled_from(msg.fields))))
            copy.offset = draw(small_or_wild)
            msg.fields.insert(draw(st.integers(0, len(msg.fields))), copy)
        elif what == "rename" and msg.fields:
            draw(st.sampled_from(msg.fields)).name = draw(st.sampled_from(FIELD_NAMES))
    return msg


def check_decoded(msg, num_classes) -> str:
    """Decode; on success check every property a caller relies on. Returns the outcome, for statistics."""
    try:
        cloud = decode_cloud(msg, num_classes, require_semantics=num_classes != -1) if num_classes != -1 \
            else decode_cloud(msg, None, require_semantics=False)
    except CloudError as error:
        assert str(error) and "\n" not in str(error)
        return "error"
    assert isinstance(cloud, DecodedCloud)
    n = len(cloud)
    assert cloud.points.ndim == 2 and cloud.points.shape == (n, 3)
    assert cloud.points.dtype in (np.float32, np.float64) and np.isfinite(cloud.points).all()
    assert cloud.total_points == int(msg.width) * int(msg.height) == n + cloud.dropped
    assert set(cloud.bad_points) == set(BAD_POINT_REASONS) and cloud.dropped == sum(cloud.bad_points.values())
    assert (cloud.bad_points_text() == "") == (cloud.dropped == 0)
    assert cloud.labels is not None or cloud.probabilities is not None or num_classes == -1
    if cloud.labels is not None:
        assert cloud.probabilities is None and cloud.labels.shape == (n,) and cloud.labels.dtype == np.int64
    if cloud.probabilities is not None:
        p = cloud.probabilities
        assert p.ndim == 2 and p.shape[0] == n and p.shape[1] >= 1 and p.dtype == np.float32
        assert np.isfinite(p).all() and (p >= 0).all() and (p.max(axis=1, initial=0) > 0).all()
        if num_classes not in (None, -1):
            assert p.shape[1] == num_classes
    if cloud.intensity is not None:
        assert cloud.intensity.shape == (n,)
    return "decoded"


@fuzz(800)  # random headers: most fail at the first check; the damaged clouds below reach deeper
@given(msg=arbitrary_clouds(), num_classes=st.sampled_from([None, 2, 3, -1]))
def test_arbitrary_pointcloud2_decodes_or_raises_cloud_error(msg, num_classes):
    check_decoded(msg, num_classes)


@fuzz(1500)
@given(msg=damaged_clouds(), num_classes=st.sampled_from([None, None, 1, 2, 3, -1]))
def test_damaged_pointcloud2_decodes_or_raises_cloud_error(msg, num_classes):
    check_decoded(msg, num_classes)


def test_undamaged_fuzz_clouds_do_decode():
    """The damaged-cloud strategy does produce decodable clouds (else the fuzz above tests only errors)."""
    outcomes = []

    @settings(max_examples=200, deadline=None, database=None, derandomize=True)
    @given(msg=damaged_clouds())
    def collect(msg):
        outcomes.append(check_decoded(msg, None))

    collect()
    assert outcomes.count("decoded") >= 40 and outcomes.count("error") >= 20, (outcomes.count("decoded"),
                                                                               outcomes.count("error"))


def test_decoder_limits_are_cloud_errors():
    """Header values a uint32 allows but numpy cannot take, and probability fields by the million."""
    def cloud(**changes):
        fields = [SimpleNamespace(name=n, offset=4 * i, datatype=7, count=1) for i, n in enumerate("xyz")]
        fields.append(SimpleNamespace(name="label", offset=12, datatype=6, count=1))
        msg = SimpleNamespace(fields=fields, height=1, width=2, point_step=16, row_step=32, is_bigendian=False,
                              data=bytes(32))
        for key, value in changes.items():
            setattr(msg, key, value)
        return msg

    assert len(decode_cloud(cloud())) == 2
    for changes, message in [
        ({"point_step": 2**32 - 1}, "point_step is 4294967295 bytes"),
        ({"width": -1}, "width is -1"),
        ({"height": 2**32}, "height is 4294967296"),
        ({"data": [300, 1]}, "data is not a byte buffer"),
        ({"fields": None}, "no field list"),
        ({"point_step": "sixteen"}, "point_step is not an integer"),
    ]:
        try:
            decode_cloud(cloud(**changes))
        except CloudError as error:
            assert message in str(error), (message, str(error))
        else:
            raise AssertionError(f"{changes} decoded")
    many = cloud()
    many.fields = many.fields[:3] + [SimpleNamespace(name="prob_99999999", offset=12, datatype=7, count=1)]
    try:
        decode_cloud(many)
    except CloudError as error:
        assert "100000000 classes" in str(error)
    else:
        raise AssertionError("a cloud claiming 10^8 classes decoded")
    aliased = cloud()
    aliased.fields = aliased.fields[:3] + [SimpleNamespace(name="prob_00", offset=12, datatype=7, count=1)]
    assert decode_cloud(aliased, require_semantics=False).probabilities is None  # prob_00 is not prob_0


# ----------------------------------------------------------------------------- kernel files


def check_kernel(parse) -> str:
    try:
        config = parse()
    except KernelFileError as error:
        assert str(error) and "\n" not in str(error)
        return "error"
    assert isinstance(config, KernelConfig) and config.kernel in KERNEL_KINDS
    assert isinstance(config.filter_size, int) and config.filter_size % 2 == 1 and config.filter_size >= 1
    assert isinstance(config.num_classes, int) and not isinstance(config.num_classes, bool)
    assert isinstance(config.resolution, float) and config.resolution > 0 and math.isfinite(config.resolution)
    lengths = {"single": [config.ell], "per_class": [config.ell], "compound": [config.ell_h, config.ell_z]}
    for values in lengths[config.kernel]:
        assert len(values) == (1 if config.kernel == "single" else config.num_classes)
        assert all(isinstance(v, float) and math.isfinite(v) and v > 0 for v in values)
    assert config.validate() is config
    return "valid"


yaml_scalars = st.one_of(st.none(), st.booleans(), st.integers(-3, 30), st.integers(-10**400, 10**400),
                         st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=6),
                         st.sampled_from(["single", "per_class", "compound", "gaussian", ".nan", "0.3"]))
yaml_values = st.recursive(yaml_scalars, lambda inner: st.one_of(st.lists(inner, max_size=4),
                                                                 st.dictionaries(st.text(max_size=5), inner,
                                                                                 max_size=3)), max_leaves=8)
KEYS = ["kernel", "resolution", "filter_size", "num_classes", "ell", "ell_h", "ell_z"]


@st.composite
def kernel_mappings(draw):
    """Kernel-file mappings: often nearly right (a valid one with a few values replaced)."""
    kind = draw(st.sampled_from(KERNEL_KINDS))
    classes = draw(st.integers(1, 4))
    data = {"kernel": kind, "resolution": 0.2, "filter_size": 5, "num_classes": classes}
    lengths = st.floats(0.01, 3.0)
    if kind == "single":
        data["ell"] = draw(lengths)
    elif kind == "per_class":
        data["ell"] = draw(st.lists(lengths, min_size=classes, max_size=classes))
    else:
        data["ell_h"] = draw(st.lists(lengths, min_size=classes, max_size=classes))
        data["ell_z"] = draw(st.lists(lengths, min_size=classes, max_size=classes))
    for _ in range(draw(st.integers(0, 3))):
        key = draw(st.one_of(st.sampled_from(KEYS), st.text(max_size=4), st.integers(), st.booleans()))
        if draw(st.booleans()) and key in data:
            del data[key]
        else:
            data[key] = draw(yaml_values)
    return data


@fuzz(800)
@given(data=st.one_of(kernel_mappings(), st.dictionaries(st.sampled_from(KEYS), yaml_values, max_size=7)))
def test_kernel_mappings_load_or_raise_kernel_file_error(data):
    check_kernel(lambda: kernel_config_from_dict(data))


yaml_text = st.one_of(
    st.text(max_size=200),
    st.text(alphabet=string.printable, max_size=200),
    # Real kernel-file lines, shuffled, cut and joined with junk.
    st.lists(st.sampled_from(["kernel: single", "kernel: compound", "resolution: 0.2", "filter_size: 5",
                              "filter_size: 4", "num_classes: 2", "ell: 0.3", "ell: [0.3, 0.4]", "ell_h: [1, 2]",
                              "ell_z: [0.5, .inf]", "ell: -1", "- 1", "{", "[[[[[[", "a: &x [1]", "b: *x", "? [1]",
                              "resolution: 2024-13-45", "num_classes: 0x10", "  bad indent", "ell: !!binary aGk=",
                              "filter_size: true", "!!python/object:os.system x", "%YAML 9.9", "---", "...", ""]),
             max_size=8).map("\n".join),
    st.builds(lambda depth: "[" * depth + "]" * depth, st.integers(1, 80)),  # deeper: one case below
)


@fuzz(1500)
@given(text=yaml_text)
def test_kernel_text_loads_or_raises_kernel_file_error(text):
    check_kernel(lambda: parse_kernel_text(text, "fuzz.yaml"))


@fuzz(60)
@given(blob=st.one_of(st.binary(max_size=300), yaml_text.map(lambda t: t.encode("utf-8", "surrogatepass"))))
def test_kernel_file_bytes_load_or_raise_kernel_file_error(tmp_path_factory, blob):
    """Through the file: bytes that are not UTF-8 (or not text at all) included."""
    path = tmp_path_factory.mktemp("kernel") / "k.yaml"
    path.write_bytes(blob)
    outcome = check_kernel(lambda: load_kernel_file(path))
    if outcome == "error":
        try:
            load_kernel_file(path)
        except KernelFileError as error:
            assert str(error).startswith(f"{path}: ")


def test_valid_kernel_files_survive_the_fuzzers_checks(tmp_path):
    """check_kernel accepts real kernel files (so 'valid' outcomes above are real ones)."""
    from convbki_core.paths import kernel_path

    for name in ("semantic_kitti_sbki", "semantic_kitti_compound"):
        assert check_kernel(lambda name=name: load_kernel_file(kernel_path(name))) == "valid"
    path = tmp_path / "int_lengths.yaml"
    path.write_text(yaml.safe_dump({"kernel": "per_class", "resolution": 1, "filter_size": 3, "num_classes": 2,
                                    "ell": [1, 2]}))
    config = load_kernel_file(path)
    assert config.ell == [1.0, 2.0] and config.resolution == 1.0
    for text, message in [("filter_size: true\nkernel: single\nresolution: 0.2\nnum_classes: 1\nell: 0.3",
                           "filter_size must be a positive odd integer up to 63, got True"),
                          ("kernel: single\nresolution: 0.2\nfilter_size: 5\nnum_classes: 1\nell: 1" + "0" * 400,
                           "ell lengths must be positive finite metres"),
                          ("kernel: single\nresolution: 2024-13-45\nfilter_size: 5\nnum_classes: 1\nell: 1",
                           "not valid YAML"),
                          ("[" * 5000 + "]" * 5000, "kernel file"),
                          ("kernel: single\nresolution: 0.2\nfilter_size: 101\nnum_classes: 1\nell: 1", "up to 63"),
                          ("kernel: single\nresolution: 0.2\nfilter_size: 5\nnum_classes: 1\nell: 1\n1: 2",
                           "unknown key(s) 1"),
                          ('kernel: single\nresolution: 0.2\nfilter_size: 5\nnum_classes: 1\nell: 1\n"\\n": 2',
                           "unknown key(s) '\\n'")]:  # a key that is a newline, quoted: the message stays one line
        try:
            parse_kernel_text(text, "k.yaml")
        except KernelFileError as error:
            assert message in str(error), (message, str(error))
        else:
            raise AssertionError(f"{text[:40]!r} parsed")

"""Broken map files are refused with a reason: MapFileError naming the file and the problem in one
line, for every kind of damage (empty, cut short, not an archive, missing or inconsistent arrays,
bad metadata, out-of-range values), and never a wrong map from a file cut or overwritten anywhere.
(That a save never leaves such a file behind: test_atomic_save.py.)"""

from __future__ import annotations

import io
import json
import zipfile
from pathlib import Path

import numpy as np
import pytest
from helpers import small_saved_map
from hypothesis import given, settings
from hypothesis import strategies as st

from convbki_core import MapFileError
from convbki_core.io.map_file import MAP_VERSION, read_map


def _npy_bytes(array: np.ndarray) -> bytes:
    """A bare .npy file's bytes (np.save to a path would append .npy to the name)."""
    buffer = io.BytesIO()
    np.save(buffer, array)
    return buffer.getvalue()


def _rewrite(good: Path, out: Path, change) -> Path:
    """A copy of ``good`` with its metadata changed by ``change(dict)``."""
    with np.load(good) as archive:
        arrays = {name: archive[name] for name in archive.files}
    metadata = json.loads(arrays["metadata"].tobytes())
    change(metadata)
    arrays["metadata"] = np.frombuffer(json.dumps(metadata).encode(), np.uint8)
    np.savez(out, **arrays)
    return out


def _rewrite_arrays(good: Path, out: Path, change) -> Path:
    """A copy of ``good`` with its arrays (a dict of writable copies) changed by ``change(dict)``."""
    with np.load(good) as archive:
        arrays = {name: archive[name].copy() for name in archive.files}
    change(arrays)
    np.savez(out, **arrays)
    return out


def _as_version_1(good: Path, out: Path, change, alpha_change=lambda alpha: None) -> Path:
    """``good`` in the version 1 layout (dense ``alpha``), metadata changed by ``change(dict)``."""
    metadata, indices, alpha = read_map(good)
    metadata["version"] = 1
    change(metadata)
    alpha_change(alpha)
    np.savez(out, metadata=np.frombuffer(json.dumps(metadata).encode(), np.uint8),
             voxel_index=indices.astype(np.int32), alpha=alpha)
    return out


@pytest.mark.parametrize("make, message", [
    (lambda good, p: p.write_bytes(b""), "empty file"),
    (lambda good, p: p.write_bytes(good.read_bytes()[:100]), "truncated or corrupted"),
    (lambda good, p: p.write_bytes(good.read_bytes()[:-30]), "truncated or corrupted"),
    (lambda good, p: p.write_text("# a PLY or text file\n"), r"not a NumPy \.npz archive: text"),
    (lambda good, p: p.write_bytes(_npy_bytes(np.zeros((3, 3)))), "single NumPy array"),
    (lambda good, p: np.savez(p, voxels=np.zeros(3)), "missing class_count, class_id, metadata, value, voxel_index"),
    (lambda good, p: zipfile.ZipFile(p, "w").writestr("readme.txt", "hello"), "missing"),
    (lambda good, p: p.mkdir(), "is a folder"),
    (lambda good, p: _rewrite(good, p, lambda m: m.update(version=MAP_VERSION + 1)), "version 4 is not supported"),
    (lambda good, p: _rewrite(good, p, lambda m: m.update(version=[2])), "version \\[2\\] is not supported"),
    (lambda good, p: _rewrite(good, p, lambda m: m.update(format="octomap")), "format is 'octomap'"),
    (lambda good, p: _rewrite(good, p, lambda m: m.update(num_classes="20")), "num_classes"),
    (lambda good, p: _rewrite(good, p, lambda m: m.update(num_classes=3)), "inconsistent arrays"),  # class id 3
    (lambda good, p: _as_version_1(good, p, lambda m: m.update(num_classes=5)), "inconsistent arrays"),
    (lambda good, p: _rewrite(good, p, lambda m: m.update(resolution=-0.2)), "resolution"),
    (lambda good, p: _rewrite(good, p, lambda m: m.update(resolution=10**400)), "resolution"),
    (lambda good, p: _rewrite(good, p, lambda m: m.pop("resolution")), "resolution"),
    (lambda good, p: _rewrite(good, p, lambda m: m.update(scans_integrated=-1)), "scans_integrated"),
    (lambda good, p: _rewrite(good, p, lambda m: m.pop("prior")), "prior must be a positive number"),
    (lambda good, p: _rewrite(good, p, lambda m: m.update(prior=0)), "prior must be a positive number"),
    (lambda good, p: _rewrite(good, p, lambda m: m.update(version=1)), "missing alpha"),
    (lambda good, p: _rewrite_arrays(good, p, lambda a: a.pop("class_id")), "missing class_id"),
    (lambda good, p: _rewrite_arrays(good, p, lambda a: a.update(class_count=a["class_count"][:2])),
     "inconsistent arrays"),
    (lambda good, p: _rewrite_arrays(good, p, lambda a: a.update(value=a["value"][:-1])), "inconsistent arrays"),
    (lambda good, p: _rewrite_arrays(good, p, lambda a: a["class_count"].__setitem__(0, 3)), "sums to 11"),
    (lambda good, p: _rewrite_arrays(good, p, lambda a: a["class_count"].__setitem__(0, 5)), "class_count beyond"),
    (lambda good, p: _rewrite_arrays(good, p, lambda a: a["class_id"].__setitem__(1, 4)), "class_id beyond"),
    (lambda good, p: _rewrite_arrays(good, p, lambda a: a["class_id"].__setitem__(1, 0)), "must ascend"),
    (lambda good, p: _rewrite_arrays(good, p, lambda a: a["class_id"].__setitem__(2, 1)), "must ascend"),
    (lambda good, p: _rewrite_arrays(good, p, lambda a: a["value"].__setitem__(5, -1.0)), "non-negative"),
    (lambda good, p: _rewrite_arrays(good, p, lambda a: a["value"].__setitem__(5, np.inf)), "finite"),
    (lambda good, p: _rewrite_arrays(good, p, lambda a: a["value"].__setitem__(5, np.nan)), "finite"),
    (lambda good, p: _rewrite_arrays(good, p, lambda a: a.update(class_id=a["class_id"].astype(np.float32))),
     "unexpected array types"),
    (lambda good, p: _rewrite_arrays(good, p, lambda a: a.update(voxel_index=a["voxel_index"].astype(np.float32))),
     "unexpected array types"),
    (lambda good, p: _rewrite_arrays(good, p, lambda a: a.update(voxel_index=a["voxel_index"][[0, 1, 1]])),
     "duplicate voxel indices"),
    (lambda good, p: _as_version_1(good, p, lambda m: None, alpha_change=lambda a: a.__setitem__((0, 1), -1.0)),
     "non-negative"),
])
def test_broken_map_files_raise_map_file_error_naming_file_and_problem(tmp_path, make, message):
    good = small_saved_map(tmp_path)
    bad = tmp_path / "bad.npz"
    make(good, bad)
    with pytest.raises(MapFileError, match=message) as error:
        read_map(bad)
    assert str(error.value).startswith(f"{bad}: ") and "\n" not in str(error.value)
    metadata, indices, alpha = read_map(good)  # the good file is fine
    assert metadata["num_classes"] == 4 and indices.shape == (3, 3) and alpha.max() == 11.0


@settings(max_examples=300, deadline=None)
@given(data=st.data())
def test_any_truncation_or_byte_corruption_gives_map_file_error_or_the_map(tmp_path_factory, data):
    """Cut anywhere, or with bytes overwritten: either MapFileError or exactly the saved map."""
    folder = tmp_path_factory.mktemp("corrupt")
    good = small_saved_map(folder)
    blob = bytearray(good.read_bytes())
    if data.draw(st.booleans(), label="truncate"):
        blob = blob[: data.draw(st.integers(0, len(blob) - 1), label="length")]
    else:
        for _ in range(data.draw(st.integers(1, 8), label="edits")):
            at = data.draw(st.integers(0, len(blob) - 1), label="at")
            blob[at] = data.draw(st.integers(0, 255), label="byte")
    bad = folder / "bad.npz"
    bad.write_bytes(bytes(blob))
    try:
        metadata, indices, alpha = read_map(bad)
    except MapFileError as error:
        assert str(error).startswith(f"{bad}: ")
        return
    # A change the zip checksums do not cover (e.g. in a header's padding) may still load: then it is the map.
    _, good_indices, good_alpha = read_map(good)
    np.testing.assert_array_equal(indices, good_indices)
    np.testing.assert_array_equal(alpha, good_alpha)
    assert metadata["num_classes"] == 4

"""Short soak (200 scans): memory grows with the map's voxels and with nothing else.

The full soak (scripts/soak.py, thousands of full-size scans) is too long for CI; this runs the
same measuring loop (``convbki_core.tools.soak_measure``) on a sparser LiDAR and a smaller window,
and asserts memory and map state only (no test asserts a duration).
"""

import csv
import itertools
import json
import math
import mmap
import os
import statistics

import numpy as np
import pytest

from convbki_core.offline import drive_frames, paper_mapper
from convbki_core.synth.cached_drive import ensure_drive
from convbki_core.tools.soak import DEFAULT_SEED, main
from convbki_core.tools.soak_measure import MB, resident_bytes, soak
from convbki_core.tools.soak_report import write_outputs

SCANS = 200
EVERY = 20
# A 32-beam, 720-column LiDAR keeps simulation and mapping quick; a 40 x 40 m window makes the
# fixed window small and makes voxels leave it, so the store is written to all along the drive
# and ends up holding most of the map.
BEAMS, AZIMUTH = 32, 720
BOUNDS = ((-20.0, -20.0, -2.6), (20.0, 20.0, 2.6))
# Memory the store's bytes do not explain may wobble by a few MB (allocator pages, gc); a
# leak of 0.2 MB a scan adds 40 MB over the drive and 20 MB over its second half.
EXCESS_LIMIT_MB = 32.0
SECOND_HALF_LIMIT_MB = 16.0
# The scan log (kept for SLAM corrections) is bounded; a small bound makes it fill in the first
# half, so the second half shows that it stays flat once full.
LOG_MEGABYTES = 20.0


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    root = tmp_path_factory.mktemp("soak") / "drive"
    return root, ensure_drive(root, SCANS, DEFAULT_SEED, beams=BEAMS, azimuth_steps=AZIMUTH)


@pytest.fixture(scope="module")
def soaked(drive):
    mapper = paper_mapper(local_bounds=BOUNDS, scan_log_megabytes=LOG_MEGABYTES)
    return mapper, soak(mapper, drive_frames(drive[1], range(SCANS)), EVERY)


def test_rows_follow_the_map(soaked):
    mapper, result = soaked
    rows = result.checkpoints
    assert [r.scans for r in rows] == list(range(EVERY, SCANS + 1, EVERY))
    assert result.baseline.scans == 1 and result.baseline.store_voxels == 0  # nothing has left the window yet
    last = rows[-1]
    assert last.voxels == len(mapper) and last.store_voxels == len(mapper.store)
    assert last.voxels - last.store_voxels == mapper.window.count()
    # The drive keeps reaching new streets: the map grows at every row, and the store with it.
    voxels = [result.baseline.voxels] + [r.voxels for r in rows]
    assert all(b > a for a, b in itertools.pairwise(voxels))
    assert last.voxels > 4 * result.baseline.voxels
    assert last.store_voxels > last.voxels / 2
    # The per-scan trace adds up each scan's new voxels; it must land on the map's own count,
    # at every row (sampled from the mapper) and at the end.
    assert len(result.update_ms) == len(result.query_ms) == len(result.occupied) == len(result.voxels) == SCANS - 1
    assert [result.voxels[r.scans - 2] for r in rows] == [r.voxels for r in rows]
    assert result.voxels[-1] == len(mapper)
    # Each row summarises exactly the scans since the previous row (scan n is trace entry n - 2;
    # scan 1 is the baseline and in no row).
    for previous, row in zip([result.baseline, *rows], rows):
        since = slice(previous.scans - 1, row.scans - 1)
        assert row.update_ms == statistics.median(result.update_ms[since])
        assert row.query_ms == statistics.median(result.query_ms[since])
        assert row.occupied == int(statistics.median(result.occupied[since])) > 0
    # Other processes' load: a reading on Linux, and never more cores than the machine has.
    assert all(0 <= r.other_cores <= os.cpu_count() + 0.5 for r in rows), [r.other_cores for r in rows]
    assert all(a.elapsed_s < b.elapsed_s for a, b in itertools.pairwise(rows))


def test_store_bytes_per_voxel_stay_at_the_layout(soaked):
    """The store holds a voxel in 3 + 5 k bytes (k classes off the prior, at least one) plus per-chunk
    bookkeeping: at most 40 bytes, whatever the map size."""
    _, result = soaked
    per_voxel = [r.store_per_voxel_b for r in result.checkpoints]
    assert all(3 + 5 <= b <= 40 for b in per_voxel), per_voxel
    assert per_voxel[-1] <= 1.25 * per_voxel[0], per_voxel


def test_memory_grows_with_the_voxels_only(soaked):
    """RSS growth after the first scan is the store's growth; nothing else accumulates per scan."""
    _, result = soaked
    rows = result.checkpoints
    # The test map is big enough for a per-scan leak to stand out: half a million voxels move to the store.
    assert rows[-1].store_voxels - result.baseline.store_voxels > 500_000
    assert max(r.excess_mb for r in rows) <= EXCESS_LIMIT_MB, [round(r.excess_mb, 1) for r in rows]
    # The bytes malloc reports live (glibc) say the same without the allocator's retained pages.
    assert max(r.live_excess_mb for r in rows) <= EXCESS_LIMIT_MB, [round(r.live_excess_mb, 1) for r in rows]
    middle = rows[len(rows) // 2 - 1]
    late_rss = rows[-1].rss_mb - middle.rss_mb
    late_store = rows[-1].store_mb - middle.store_mb + rows[-1].log_mb - middle.log_mb
    assert late_rss <= late_store + SECOND_HALF_LIMIT_MB, (late_rss, late_store)
    # The scan log fills up to its bound and no further: older scans fall out as new ones come.
    assert all(r.log_mb <= LOG_MEGABYTES for r in rows), [round(r.log_mb, 2) for r in rows]
    assert max(r.log_mb for r in rows) > LOG_MEGABYTES / 2 and rows[-1].log_scans < SCANS / 2, \
        [(round(r.log_mb, 2), r.log_scans) for r in rows]


def test_resident_bytes_sees_an_allocation():
    """The RSS reading moves with memory the process really touches (the figure the test relies on)."""
    # An anonymous mapping of its own: fresh pages from the kernel, never memory the allocator
    # already holds resident from earlier tests.
    block = mmap.mmap(-1, 64 * MB)
    before = resident_bytes()
    np.frombuffer(block, dtype=np.uint8)[::4096] = 1  # one write per page makes every page resident
    grown = resident_bytes() - before
    assert grown >= 56 * MB, grown / MB


def test_outputs(soaked, tmp_path):
    _, result = soaked
    settings = {"scans": SCANS, "seed": DEFAULT_SEED, "bounds": [*BOUNDS[0], *BOUNDS[1]], "machine": "test"}
    paths = write_outputs(result, tmp_path / "soak", settings)
    with open(paths["csv"], newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert [int(r["scans"]) for r in rows] == [r.scans for r in result.checkpoints]
    assert math.isclose(float(rows[-1]["rss_mb"]), result.checkpoints[-1].rss_mb, abs_tol=1e-3)
    report = json.loads(paths["json"].read_text())
    assert report["summary"]["voxels"] == result.checkpoints[-1].voxels
    assert len(report["checkpoints"]) == SCANS // EVERY
    assert len(report["per_scan"]["update_ms"]) == SCANS - 1
    assert report["baseline"]["rss_growth_per_voxel_b"] is None  # NaN is written as null, JSON stays valid
    assert paths["png"].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not list(paths["png"].parent.glob(".*.tmp"))  # atomic writes leave no temporary files


def test_command_line(drive, tmp_path, capsys):
    root, _ = drive
    out = tmp_path / "run"
    assert main(["--scans", "30", "--every", "10", "--drive-dir", str(root), "--beams", str(BEAMS),
                 "--azimuth-steps", str(AZIMUTH), "--bounds", "-10", "-10", "-2", "10", "10", "2",
                 "--out", str(out)]) == 0
    table = capsys.readouterr().out.splitlines()
    assert table[0].split()[:2] == ["scans", "voxels"]
    assert [line.split()[0] for line in table[1:4]] == ["10", "20", "30"]
    assert len(json.loads((out / "soak.json").read_text())["checkpoints"]) == 3


@pytest.mark.parametrize("argv, message", [
    (["--bounds", "1", "0", "0", "0", "1", "1"], "minimum below its maximum"),
    (["--scans", "5", "--every", "10"], "more than --scans"),
    (["--scans", "-3"], "positive"),
    (["--beams", "65"], "at most 64"),
])
def test_bad_arguments(argv, message, capsys, tmp_path):
    assert exit_code([*argv, "--out", str(tmp_path / "o"), "--drive-dir", str(tmp_path / "d")]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "d").exists()  # nothing simulated for a refused command


def test_refuses_to_overwrite_a_real_dataset(tmp_path, capsys):
    sequence = tmp_path / "kitti" / "sequences" / "00" / "velodyne"
    sequence.mkdir(parents=True)
    (sequence / "000000.bin").write_bytes(b"\0" * 16)
    assert exit_code(["--scans", "10", "--every", "5", "--drive-dir", str(tmp_path / "kitti"),
                 "--out", str(tmp_path / "o")]) == 2
    assert "not a synthetic drive" in capsys.readouterr().err
    assert (sequence / "000000.bin").read_bytes() == b"\0" * 16


def exit_code(argv):
    """``main``'s exit code, also when argparse refuses the arguments itself (SystemExit)."""
    try:
        return main(argv)
    except SystemExit as stop:
        return stop.code

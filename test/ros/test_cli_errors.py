"""Every CLI on bad input: one line naming the file and the problem, exit code 2, no traceback,
nothing of its own left behind (no report, labels, kernel file, bag, temp or staging file).

Most cases run the commands in-process through ``main(argv)`` (what the console scripts
call); a few run them as real processes to show that no traceback reaches the terminal.
"""

from __future__ import annotations

import importlib.util
import os
import shutil
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
import yaml
from kitti_fixture import write_drive

from convbki_core.io.atomic import writer_tag
from convbki_core.tools import bench, evaluate, train
from convbki_core.tools import synth as synthetic
from convbki_ros.tools import demo, kitti_to_bag, play_bag

REPO = Path(__file__).resolve().parents[2]
SMALL_WINDOW = ["--local-bounds", "-8", "-8", "-2", "8", "8", "2", "--device", "cpu"]


@pytest.fixture(scope="module")
def clean_root(tmp_path_factory) -> Path:
    """A 3-frame sequence 00 with ground truth, predictions and probabilities."""
    root = tmp_path_factory.mktemp("clean") / "data"
    write_drive(root, "00", frames=3)
    folder = root / "sequences" / "00"
    (folder / "probabilities").mkdir()
    for scan in sorted((folder / "velodyne").iterdir()):
        count = scan.stat().st_size // 16
        np.save(folder / "probabilities" / f"{scan.stem}.npy", np.full((count, 20), 0.05, np.float16))
    return root


@pytest.fixture
def root(clean_root, tmp_path) -> Path:
    """A private copy of the clean dataset, to damage."""
    copy = tmp_path / "data"
    shutil.copytree(clean_root, copy)
    return copy


def one_line_error(capsys, code: int, prog: str, *needles: str, after_progress: bool = False) -> str:
    """The command's stderr is exactly one line ``prog: error: ...`` holding every needle.

    ``after_progress``: the failure came part-way through, so a progress bar may precede it.
    """
    err = capsys.readouterr().err
    assert code == 2, err
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    if after_progress:
        assert all("%|" in line for line in lines[:-1]), err  # nothing but the bar before the error
        lines = lines[-1:]
    assert len(lines) == 1, err
    assert lines[0].startswith(f"{prog}: error: "), lines[0]
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    return lines[0]


def tree(folder: Path) -> set[str]:
    """Every path under ``folder`` (hidden ones too), relative."""
    return {str(p.relative_to(folder)) for p in folder.rglob("*")}


def seq(root: Path) -> Path:
    return root / "sequences" / "00"


def _truncate_npy(path: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) - 100])  # header intact (shape checks pass), data cut short


# (how to damage the dataset, what the one line must name: file and problem)
DAMAGE = {
    "missing dataset": (lambda r: shutil.rmtree(r), ("data", "dataset folder not found")),
    "missing sequence": (lambda r: shutil.rmtree(seq(r)), ("sequence 00 not found",)),
    "scan is a folder": (lambda r: ((seq(r) / "velodyne" / "000001.bin").unlink(),
                                    (seq(r) / "velodyne" / "000001.bin").mkdir()), ("000001.bin", "not a file")),
    "scan cut mid-point": (lambda r: (seq(r) / "velodyne" / "000002.bin").write_bytes(b"\0" * 40),
                           ("000002.bin", "16-byte points")),
    "no calibration": (lambda r: (seq(r) / "calib.txt").unlink(), ("calib.txt", "cannot read calibration")),
    "unreadable poses": (lambda r: ((seq(r) / "poses.txt").unlink(), (seq(r) / "poses.txt").mkdir()),
                         ("poses.txt", "cannot read poses")),
    "fewer poses": (lambda r: (seq(r) / "poses.txt").write_text(
        "".join((seq(r) / "poses.txt").read_text().splitlines(keepends=True)[:2])), ("poses.txt", "2 poses for 3")),
    "fewer times": (lambda r: (seq(r) / "times.txt").write_text("0.0\n0.1\n"), ("times.txt", "2 times for 3")),
    "labels short": (lambda r: (seq(r) / "predictions" / "000002.label").write_bytes(b"\0" * 8),
                     ("predictions/000002.label", "2 labels for")),
    "ground truth missing": (lambda r: (seq(r) / "labels" / "000001.label").unlink(),
                             ("labels/000001.label", "label file missing")),
}


@pytest.mark.parametrize("damage", sorted(DAMAGE))
def test_evaluate_broken_dataset(root, tmp_path, capsys, damage):
    change, needles = DAMAGE[damage]
    change(root)
    before = tree(tmp_path)
    code = evaluate.main(["--dataset", str(root), "--sequence", "0", "--report", str(tmp_path / "r.json"),
                          "--write-labels", str(tmp_path / "out"), "--quiet", *SMALL_WINDOW])
    one_line_error(capsys, code, "evaluate", *needles)
    assert tree(tmp_path) == before  # no report, no picture, no labels folder, no staging


@pytest.mark.parametrize("damage", ["missing dataset", "scan is a folder", "fewer poses", "labels short",
                                    "ground truth missing"])
def test_train_broken_dataset(root, tmp_path, capsys, damage):
    change, needles = DAMAGE[damage]
    change(root)
    before = tree(tmp_path)
    code = train.main(["--dataset", str(root), "--sequences", "0", "--out", str(tmp_path / "k.yaml"),
                       "--frames-per-sample", "2", "--quiet"])
    one_line_error(capsys, code, "train", *needles)
    assert tree(tmp_path) == before


@pytest.mark.parametrize("damage", ["missing dataset", "scan cut mid-point", "fewer poses", "fewer times",
                                    "labels short", "unreadable poses"])
def test_kitti_to_bag_broken_dataset(root, tmp_path, capsys, damage):
    change, needles = DAMAGE[damage]
    change(root)
    before = tree(tmp_path)
    code = kitti_to_bag.main(["--dataset", str(root), "--sequence", "0", "--out", str(tmp_path / "bags" / "b")])
    one_line_error(capsys, code, "kitti_to_bag", *needles)
    assert tree(tmp_path) == before  # not even the bags/ folder it would have made


@pytest.mark.parametrize("command", ["evaluate", "train", "kitti_to_bag"])
def test_probabilities_of_the_wrong_shape(root, tmp_path, capsys, command):
    np.save(seq(root) / "probabilities" / "000001.npy", np.zeros((5, 20), np.float16))
    before = tree(tmp_path)
    common = ["--dataset", str(root), "--probabilities-dir", "probabilities"]
    code = {"evaluate": lambda: evaluate.main([*common, "--sequence", "0", "--report", str(tmp_path / "r.json"),
                                               "--quiet", *SMALL_WINDOW]),
            "train": lambda: train.main([*common, "--sequences", "0", "--out", str(tmp_path / "k.yaml"), "--quiet"]),
            "kitti_to_bag": lambda: kitti_to_bag.main([*common, "--sequence", "0", "--out", str(tmp_path / "b")]),
            }[command]()
    one_line_error(capsys, code, command, "probabilities/000001.npy", "shape (5, 20)")
    assert tree(tmp_path) == before


# A damage only found when the frame is read (the header of the .npy is fine): the command
# has already written output for the frames before it, which must all disappear.
def test_evaluate_failing_mid_run_removes_its_outputs_and_keeps_older_ones(root, tmp_path, capsys):
    _truncate_npy(seq(root) / "probabilities" / "000002.npy")
    older = tmp_path / "out" / "sequences" / "00" / "predictions"
    older.mkdir(parents=True)
    (older / "000000.label").write_bytes(b"older run")
    (tmp_path / "r.json").write_text("older report")
    before = tree(tmp_path)
    code = evaluate.main(["--dataset", str(root), "--sequence", "0", "--probabilities-dir", "probabilities",
                          "--report", str(tmp_path / "r.json"), "--write-labels", str(tmp_path / "out"),
                          "--quiet", *SMALL_WINDOW])
    one_line_error(capsys, code, "evaluate", "probabilities/000002.npy", "cannot read probabilities",
                   after_progress=True)
    assert tree(tmp_path) == before  # no staging folder, no picture
    assert (older / "000000.label").read_bytes() == b"older run" and (tmp_path / "r.json").read_text() == "older report"


def test_evaluate_mid_run_failure_into_a_new_folder_leaves_no_folder(root, tmp_path, capsys):
    _truncate_npy(seq(root) / "probabilities" / "000001.npy")
    code = evaluate.main(["--dataset", str(root), "--sequence", "0", "--probabilities-dir", "probabilities",
                          "--report", str(tmp_path / "r.json"), "--write-labels", str(tmp_path / "new" / "root"),
                          "--quiet", *SMALL_WINDOW])
    one_line_error(capsys, code, "evaluate", "000001.npy", after_progress=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data"]


def test_evaluate_writes_labels_only_when_the_run_succeeds(root, tmp_path, capsys):
    """The staging folder really becomes OUTROOT/sequences/SS/predictions on success."""
    code = evaluate.main(["--dataset", str(root), "--sequence", "0", "--report", str(tmp_path / "r.json"),
                          "--write-labels", str(tmp_path / "out"), "--quiet", *SMALL_WINDOW])
    assert code == 0, capsys.readouterr().err
    folder = tmp_path / "out" / "sequences" / "00"
    assert sorted(p.name for p in folder.iterdir()) == ["predictions"]  # the staging folder is gone
    written = sorted(p.name for p in (folder / "predictions").iterdir())
    assert written == ["000000.label", "000001.label", "000002.label"]
    points = (seq(root) / "velodyne" / "000001.bin").stat().st_size // 16
    assert (folder / "predictions" / "000001.label").stat().st_size == 4 * points


def test_train_failing_mid_run_leaves_no_kernel_file(root, tmp_path, capsys):
    _truncate_npy(seq(root) / "probabilities" / "000002.npy")
    code = train.main(["--dataset", str(root), "--sequences", "0", "--probabilities-dir", "probabilities",
                       "--out", str(tmp_path / "k.yaml"), "--frames-per-sample", "2", "--quiet"])
    one_line_error(capsys, code, "train", "000002.npy", "cannot read probabilities", after_progress=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data"]


def test_kitti_to_bag_failing_mid_run_leaves_no_bag(root, tmp_path, capsys):
    _truncate_npy(seq(root) / "probabilities" / "000002.npy")
    code = kitti_to_bag.main(["--dataset", str(root), "--sequence", "0", "--probabilities-dir", "probabilities",
                              "--out", str(tmp_path / "bags" / "b")])
    one_line_error(capsys, code, "kitti_to_bag", "000002.npy", after_progress=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data"]


def test_staging_folders_of_killed_runs_are_removed_by_the_next_run(root, tmp_path, capsys):
    """A kill -9 leaves .NAME.partial-PID-* behind; the next run removes it unless its process lives."""
    dead, alive = 2**22 + 12345, os.getpid()  # above any pid_max: no such process
    leftovers = {}
    for owner in (dead, alive):
        leftover = tmp_path / f".b.partial-{writer_tag(owner)}-x1y2"
        (leftover / "b").mkdir(parents=True)
        (leftover / "b" / "half.mcap").write_bytes(b"\0" * 1000)
        leftovers[owner] = leftover
    remote = tmp_path / f".b.partial-{dead}.0badc0de-z9"  # another host's (NFS): never touched
    remote.mkdir()
    labels_leftover = tmp_path / "out" / "sequences" / "00" / f".predictions.partial-{writer_tag(dead)}-q"
    labels_leftover.mkdir(parents=True)
    assert kitti_to_bag.main(["--dataset", str(root), "--sequence", "0", "--out", str(tmp_path / "b")]) == 0
    assert evaluate.main(["--dataset", str(root), "--sequence", "0", "--report", str(tmp_path / "r.json"),
                          "--write-labels", str(tmp_path / "out"), "--quiet", *SMALL_WINDOW]) == 0
    assert not leftovers[dead].exists() and not labels_leftover.exists()
    assert leftovers[alive].exists() and remote.exists()  # a live run, or one on another machine
    assert (tmp_path / "b").is_dir() and sorted(p.name for p in labels_leftover.parent.iterdir()) == ["predictions"]


# ----------------------------------------------------------------------------- kernel files

BAD_KERNELS = {
    "wrong class count": ({"kernel": "single", "resolution": 0.2, "filter_size": 5, "num_classes": 5, "ell": 0.3},
                          "kernel has 5 classes, the dataset 20"),
    "negative length": ({"kernel": "per_class", "resolution": 0.2, "filter_size": 5, "num_classes": 20,
                         "ell": [0.3] * 19 + [-0.2]}, "ell lengths must be positive finite metres, got -0.2"),
    "even filter": ({"kernel": "single", "resolution": 0.2, "filter_size": 4, "num_classes": 20, "ell": 0.3},
                    "filter_size must be a positive odd integer up to 63, got 4"),
    "compound lengths missing": ({"kernel": "compound", "resolution": 0.2, "filter_size": 5, "num_classes": 20,
                                  "ell_h": [0.5] * 20}, "needs 20 value(s) in ell_z, got 0"),
    "not yaml": (b"kernel: [single\n", "not valid YAML"),
    "binary": (b"\x89PNG\r\n\x1a\n\x00\xff", "not UTF-8"),
    "a list": (b"- 1\n- 2\n", "YAML mapping, found list"),
    "missing": (None, "cannot read kernel file"),
}


@pytest.mark.parametrize("case", sorted(BAD_KERNELS))
def test_evaluate_bad_kernel_file(clean_root, tmp_path, capsys, case):
    content, message = BAD_KERNELS[case]
    kernel = tmp_path / "bad.yaml"
    if isinstance(content, dict):
        kernel.write_text(yaml.safe_dump(content))
    elif content is not None:
        kernel.write_bytes(content)
    before = tree(tmp_path)
    code = evaluate.main(["--dataset", str(clean_root), "--sequence", "0", "--kernel", str(kernel),
                          "--report", str(tmp_path / "r.json"), "--write-labels", str(tmp_path / "out"), "--quiet",
                          *SMALL_WINDOW])
    one_line_error(capsys, code, "evaluate", str(kernel), message)
    assert tree(tmp_path) == before


def test_evaluate_and_train_refuse_missing_output_folders(clean_root, tmp_path, capsys):
    code = evaluate.main(["--dataset", str(clean_root), "--sequence", "0", "--report",
                          str(tmp_path / "no" / "r.json"), "--quiet"])
    one_line_error(capsys, code, "evaluate", str(tmp_path / "no"), "report folder does not exist")
    code = train.main(["--dataset", str(clean_root), "--sequences", "0", "--out", str(tmp_path / "no" / "k.yaml")])
    one_line_error(capsys, code, "train", str(tmp_path / "no"), "output folder does not exist")
    assert sorted(tmp_path.iterdir()) == []


# ----------------------------------------------------------------------------- bags


def _bag_from(root: Path, folder: Path) -> Path:
    bag = folder / "bag"
    assert kitti_to_bag.main(["--dataset", str(root), "--sequence", "0", "--out", str(bag), "--frames", "0:2"]) == 0
    return bag


@pytest.fixture(scope="module")
def good_bag(clean_root, tmp_path_factory) -> Path:
    return _bag_from(clean_root, tmp_path_factory.mktemp("bag"))


def _not_bags(folder: Path, good: Path) -> dict[str, tuple[Path, str]]:
    """Things given to play_bag as a bag, and what its one line must say."""
    cases = {}
    (folder / "empty").mkdir()
    cases["empty folder"] = (folder / "empty", "no such bag")
    (folder / "text.mcap").write_text("hello")
    cases["text as mcap"] = (folder / "text.mcap", "cannot read the bag")
    (folder / "text.db3").write_text("hello")
    cases["text as sqlite"] = (folder / "text.db3", "cannot read the bag")
    (folder / "notes.txt").write_text("hello")
    cases["other file"] = (folder / "notes.txt", "cannot read the bag")
    (folder / "yaml").mkdir()
    (folder / "yaml" / "metadata.yaml").write_text("rosbag2_bagfile_information: [1\n")
    cases["broken metadata"] = (folder / "yaml", "cannot read the bag")
    no_storage = folder / "no_storage"
    shutil.copytree(good, no_storage)
    (no_storage / "bag.mcap").unlink()
    cases["storage file missing"] = (no_storage, "cannot read the bag")
    truncated = folder / "truncated"
    shutil.copytree(good, truncated)
    blob = (truncated / "bag.mcap").read_bytes()
    (truncated / "bag.mcap").write_bytes(blob[: len(blob) // 2])
    cases["truncated mcap"] = (truncated, "cannot read the bag")
    return cases


def test_play_bag_refuses_what_is_not_a_bag(good_bag, tmp_path, capsys):
    for name, (path, message) in _not_bags(tmp_path, good_bag).items():
        before = tree(tmp_path)
        code = play_bag.main([str(path), "--wait-subscribers", "0"])
        line = one_line_error(capsys, code, "play_bag", str(path), message)
        assert tree(tmp_path) == before, name  # reading a bag writes nothing
        assert len(line) < 400, line


def test_play_bag_damaged_index_never_gives_a_traceback(good_bag, tmp_path, capsys):
    """Bytes overwritten in the mcap's summary (its index): exit 2 with one line, or a clean replay.

    rosbags trips over such damage with UnicodeDecodeError, OverflowError or MemoryError, at
    open or while reading; play_bag must turn each into its one-line error.
    """
    blob = (good_bag / "bag.mcap").read_bytes()
    rng = np.random.default_rng(3)
    refused = 0
    for trial in range(24):
        damaged = tmp_path / f"d{trial}"
        shutil.copytree(good_bag, damaged)
        data = bytearray(blob)
        at = int(rng.integers(len(data) - 1500, len(data) - 8))
        data[at:at + 4] = rng.integers(0, 256, 4, dtype=np.uint8).tobytes()
        (damaged / "bag.mcap").write_bytes(bytes(data))
        code = play_bag.main([str(damaged), "--wait-subscribers", "0", "--rate", "1000"])
        err = capsys.readouterr().err
        assert "Traceback" not in err and code in (0, 2), err
        if code == 2:
            last = err.strip().splitlines()[-1]
            assert last.startswith(f"play_bag: error: {damaged}: ") and "bag" in last, last
            refused += 1
        shutil.rmtree(damaged)
    assert refused >= 3, refused  # the damage was real: some bags were refused


# ----------------------------------------------------------------------------- synth, demo, arguments


def test_synth_refuses_a_file_as_root_and_leaves_it(tmp_path, capsys):
    target = tmp_path / "a_file"
    target.write_text("mine")
    code = synthetic.main(["--out", str(target), "--frames", "1", "--azimuth-steps", "64", "--quiet"])
    one_line_error(capsys, code, "synth", "a_file", "not a folder")
    code = synthetic.main(["--out", str(target / "inner"), "--frames", "1", "--azimuth-steps", "64", "--quiet"])
    one_line_error(capsys, code, "synth", "a_file", "not a folder")
    assert target.read_text() == "mine" and sorted(p.name for p in tmp_path.iterdir()) == ["a_file"]


def test_synth_write_failure_is_one_line_exit_2_without_temp_files(tmp_path, capsys):
    """A scan path taken by a folder makes the write fail part-way (after scan 0 was written)."""
    seq_folder = tmp_path / "sequences" / "00"
    (seq_folder / "velodyne" / "000001.bin").mkdir(parents=True)
    code = synthetic.main(["--out", str(tmp_path), "--frames", "2", "--azimuth-steps", "64", "--beams", "8",
                           "--noise-strength", "0.3", "--force", "--quiet"])
    one_line_error(capsys, code, "synth", "000001.bin", after_progress=True)
    assert not [p for p in tmp_path.rglob("*.tmp")]


def test_bench_drive_folder_that_is_a_file(tmp_path, capsys):
    target = tmp_path / "a_file"
    target.write_text("mine")
    code = bench.main(["--drive-dir", str(target), "--scans", "3", "--skip-ablation"])
    one_line_error(capsys, code, "bench", "a_file", "not a folder")
    assert target.read_text() == "mine" and sorted(p.name for p in tmp_path.iterdir()) == ["a_file"]


def test_bench_without_convbki_ros_keeps_the_keys_and_says_why(monkeypatch):
    """The core never imports convbki_ros: bench runs the ROS-side figures as a process and,
    where convbki_ros is not there, reports them as not measured, under the keys bench_ros fills."""
    from convbki_core.offline import paper_mapper
    from convbki_ros.tools import bench_ros

    assert bench.ROS_ENCODE_KEYS == bench_ros.ENCODE_KEYS and bench.ROS_SCAN_TO_MAP_KEYS == bench_ros.SCAN_TO_MAP_KEYS
    assert set(bench_ros.START_KEYS) < set(bench.ROS_START_KEYS) <= set(bench.REPORTED)
    rng = np.random.default_rng(0)
    frame = SimpleNamespace(points=rng.uniform(-5, 5, (2000, 3)).astype(np.float32),
                            remission=np.zeros(2000, np.float32), input_labels=rng.integers(1, 20, 2000),
                            pose=np.eye(4))
    mapper = paper_mapper(local_bounds=((-8.0, -8.0, -2.0), (8.0, 8.0, 2.0)))
    mapper.integrate(frame.points, frame.input_labels, frame.pose)
    assert tuple(bench_ros.encode_figures(mapper, 1)) == bench_ros.ENCODE_KEYS
    assert tuple(bench_ros.scan_to_map_figures([frame], 1)) == bench_ros.SCAN_TO_MAP_KEYS

    find_spec = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *rest: None if name == "convbki_ros" else find_spec(name, *rest))
    args = SimpleNamespace(skip_start=False, drive_dir="unused", scans=3, repeat=1, seed=5)
    assert bench.ros_side_figures(args) == dict.fromkeys(bench.ROS_ENCODE_KEYS + bench.ROS_SCAN_TO_MAP_KEYS
                                                          + bench.ROS_START_KEYS)
    figures = {**dict.fromkeys(bench.REPORTED, 1.0), "machine": "test", **bench.ros_side_figures(args)}
    rows = {line.split()[0]: line for line in bench.format_report(figures, []).splitlines()[3:] if line}
    unmeasured = [key for key in bench.REPORTED if rows[key].endswith(bench.NOT_MEASURED)]
    assert unmeasured == ["encode_ms_per_million", "scan_to_map_ms", *bench.ROS_START_KEYS]


def test_bench_measures_the_ros_side_figures_in_a_process_of_their_own(tmp_path):
    """With convbki_ros there, bench_ros runs as its own process on bench's drive and every
    figure it owns comes back as a number."""
    args = SimpleNamespace(skip_start=True, drive_dir=str(tmp_path / "drive"), scans=4, repeat=2, seed=5)
    figures = bench.ros_side_figures(args)
    assert set(figures) == set(bench.ROS_ENCODE_KEYS + bench.ROS_SCAN_TO_MAP_KEYS)
    assert figures["encoded_voxels"] > 1000 and figures["encode_ms_per_million"] > 0 and figures["scan_to_map_ms"] > 0
    # Given bench's own map of the drive, bench_ros encodes that map instead of mapping the drive again.
    from convbki_core.offline import paper_mapper
    from convbki_core.synth.cached_drive import ensure_drive

    mapper = paper_mapper(local_bounds=((-8.0, -8.0, -2.0), (8.0, 8.0, 2.0)))
    frame = ensure_drive(tmp_path / "drive", 4, 5)[0]
    mapper.integrate(frame.points, frame.input_values, frame.pose)
    mapper.save(tmp_path / "small.npz")
    with_map = bench.ros_side_figures(args, tmp_path / "small.npz")
    assert with_map["encoded_voxels"] == len(mapper.voxels()) != figures["encoded_voxels"]


def test_demo_missing_dataset_creates_nothing(tmp_path, capsys):
    code = demo.main(["--dataset", str(tmp_path / "nowhere"), "--sequence", "0", "--out", str(tmp_path / "demo")])
    one_line_error(capsys, code, "demo", "nowhere", "dataset folder not found")
    assert sorted(tmp_path.iterdir()) == []


@pytest.mark.parametrize("module, argv", [
    (evaluate, ["--dataset", "d", "--sequence", "x", "--report", "r.json"]),
    (train, ["--dataset", "d", "--sequences", "0", "--out", "k.yaml", "--epochs", "0"]),
    (train, ["--dataset", "d", "--sequences", "0", "--out", "k.yaml", "--min-class-points", "-1"]),
    (kitti_to_bag, ["--dataset", "d", "--sequence", "0", "--out", "b", "--frames", "5:2"]),
    (play_bag, ["bag", "--rate", "-1"]),
    (demo, ["--frames", "0"]),
    (synthetic, ["--out", "x", "--frames", "-2"]),
    (evaluate, ["--no-such-flag"]),
])
def test_bad_arguments_are_one_line_exit_2(module, argv, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exit_info:
        module.main(argv)
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and ": error: " in lines[0] and "Traceback" not in err, err
    assert sorted(tmp_path.iterdir()) == []


def _missing_devices() -> list:
    """--device values this machine lacks, with what the one line must name."""
    count = torch.cuda.device_count() if torch.cuda.is_available() else 0
    no_cuda = pytest.mark.skipif(count > 0, reason="this machine has a CUDA device, so --device cuda is valid here")
    return [pytest.param("cuda", ("'cuda' requested", "has no CUDA device", "use device auto or cpu"), marks=no_cuda),
            pytest.param(f"cuda:{count}", (f"'cuda:{count}' requested",)),
            pytest.param("tpu", ("unknown device 'tpu'", "use auto, cpu or cuda[:N]"))]


@pytest.mark.parametrize("device, needles", _missing_devices())
def test_evaluate_refuses_a_device_it_cannot_use_before_any_work(clean_root, tmp_path, capsys, device, needles):
    before = tree(tmp_path)
    with pytest.raises(SystemExit) as exit_info:  # refused while the arguments are parsed
        evaluate.main(["--dataset", str(clean_root), "--sequence", "0", "--report", str(tmp_path / "r.json"),
                       "--write-labels", str(tmp_path / "out"), "--quiet", "--device", device])
    one_line_error(capsys, exit_info.value.code, "evaluate", "argument --device:", *needles)
    assert tree(tmp_path) == before


@pytest.mark.parametrize("device, needles", _missing_devices())
@pytest.mark.parametrize("module, argv", [
    (train, ["--dataset", "d", "--sequences", "0", "--out", "k.yaml"]),
    (bench, []),
])
def test_train_and_bench_refuse_a_device_they_cannot_use_before_any_work(module, argv, device, needles, capsys,
                                                                          tmp_path, monkeypatch):
    """Both run on CUDA when asked (``--device cuda``); a device this machine lacks is one line, exit 2."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exit_info:
        module.main([*argv, "--device", device])
    one_line_error(capsys, exit_info.value.code, module.PROG, "argument --device:", *needles)
    assert sorted(tmp_path.iterdir()) == []


# ----------------------------------------------------------------------------- real processes


def _run(module: str, *args: str, cwd: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]))
    return subprocess.run([sys.executable, "-m", module, *args], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=120, stdin=subprocess.DEVNULL)


def test_processes_print_one_line_and_no_traceback(root, tmp_path):
    """What a user sees in a terminal: stderr is the one error line, nothing else."""
    (seq(root) / "predictions" / "000002.label").write_bytes(b"\0" * 8)
    kernel = tmp_path / "even.yaml"
    kernel.write_text("kernel: single\nresolution: 0.2\nfilter_size: 4\nnum_classes: 20\nell: 0.3\n")
    (tmp_path / "text.mcap").write_text("not a bag")
    before = tree(tmp_path)
    runs = [
        (_run("convbki_core.tools.evaluate", "--dataset", str(root), "--sequence", "0", "--kernel", str(kernel),
              "--report", "r.json", cwd=tmp_path), "evaluate", "even.yaml", "filter_size"),
        (_run("convbki_core.tools.train", "--dataset", str(root), "--sequences", "0", "--out", "k.yaml", cwd=tmp_path),
         "train", "000002.label", "2 labels for"),
        (_run("convbki_ros.tools.play_bag", "text.mcap", cwd=tmp_path), "play_bag", "text.mcap", "cannot read the bag"),
    ]
    for result, prog, *needles in runs:
        assert result.returncode == 2, result.stderr
        assert "Traceback" not in result.stderr + result.stdout
        lines = result.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith(f"{prog}: error: "), result.stderr
        assert all(needle in lines[0] for needle in needles), lines[0]
    assert tree(tmp_path) == before


def test_bench_never_overwrites_a_dataset_it_did_not_write(tmp_path, capsys):
    """A folder of real scans without poses.txt (a velodyne-only download) is refused, not resimulated."""
    velodyne = tmp_path / "kitti" / "sequences" / "00" / "velodyne"
    velodyne.mkdir(parents=True)
    for number in range(3):
        (velodyne / f"{number:06d}.bin").write_bytes(np.zeros(16, np.float32).tobytes())
    before = tree(tmp_path / "kitti")
    code = bench.main(["--drive-dir", str(tmp_path / "kitti"), "--scans", "3", "--skip-ablation"])
    one_line_error(capsys, code, "bench", "not a synthetic drive")
    assert tree(tmp_path / "kitti") == before


def test_outputs_committed_survive_a_later_failure(tmp_path):
    """After commit() the outputs are the user's: a failure afterwards (Ctrl-C while printing) keeps them."""
    from convbki_core.tools.cli import NewOutputs

    outputs = NewOutputs()
    report = outputs.file(outputs.folder(tmp_path / "new" / "reports") / "r.json")
    report.write_text("{}")
    stage = outputs.staging(tmp_path / "new" / "labels")
    (stage / "000000.label").write_bytes(b"\0" * 4)
    outputs.commit()
    outputs.discard()
    assert report.read_text() == "{}" and (tmp_path / "new" / "labels" / "000000.label").exists()

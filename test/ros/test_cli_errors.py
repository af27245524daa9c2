"""Every CLI on a broken dataset or kernel file: one line naming the file and the problem, exit
code 2, no traceback, nothing of its own left behind (no report, labels, kernel file, bag, temp or
staging file), even when the failure comes part-way through the run.

Most cases run the commands in-process through ``main(argv)`` (what the console scripts
call); a few run them as real processes to show that no traceback reaches the terminal.
Bad bags: test_cli_errors_bags.py; bad arguments and output targets: test_cli_errors_arguments.py.
The dataset they damage (``clean_root``) is built once, in conftest.py.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from cli_helpers import one_line_error, tree

from convbki_core.io.atomic import writer_tag
from convbki_core.tools import evaluate, train
from convbki_ros.tools import kitti_to_bag

REPO = Path(__file__).resolve().parents[2]
SMALL_WINDOW = ["--local-bounds", "-8", "-8", "-2", "8", "8", "2", "--device", "cpu"]


@pytest.fixture
def root(clean_root, tmp_path) -> Path:
    """A private copy of the clean dataset, to damage."""
    copy = tmp_path / "data"
    shutil.copytree(clean_root, copy)
    return copy


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


# ----------------------------------------------------------------------------- real processes


def _start(module: str, *args: str, cwd: Path) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]))
    return subprocess.Popen([sys.executable, "-m", module, *args], cwd=cwd, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, stdin=subprocess.DEVNULL)


def _finished(processes: list[subprocess.Popen]) -> list[subprocess.CompletedProcess]:
    """What each of ``processes`` printed, once they have ended (all killed if one takes too long)."""
    try:
        outputs = [process.communicate(timeout=120) for process in processes]
        return [subprocess.CompletedProcess(p.args, p.returncode, *out) for p, out in zip(processes, outputs)]
    finally:
        for process in processes:
            if process.poll() is None:
                process.kill()
                process.communicate()


def test_processes_print_one_line_and_no_traceback(root, tmp_path):
    """What a user sees in a terminal: stderr is the one error line, nothing else."""
    (seq(root) / "predictions" / "000002.label").write_bytes(b"\0" * 8)
    kernel = tmp_path / "even.yaml"
    kernel.write_text("kernel: single\nresolution: 0.2\nfilter_size: 4\nnum_classes: 20\nell: 0.3\n")
    (tmp_path / "text.mcap").write_text("not a bag")
    before = tree(tmp_path)
    # The three run side by side (each mostly imports, on one core).
    started = [
        (_start("convbki_core.tools.evaluate", "--dataset", str(root), "--sequence", "0", "--kernel", str(kernel),
                "--report", "r.json", cwd=tmp_path), "evaluate", "even.yaml", "filter_size"),
        (_start("convbki_core.tools.train", "--dataset", str(root), "--sequences", "0", "--out", "k.yaml",
                cwd=tmp_path), "train", "000002.label", "2 labels for"),
        (_start("convbki_ros.tools.play_bag", "text.mcap", cwd=tmp_path), "play_bag", "text.mcap",
         "cannot read the bag"),
    ]
    runs = [(result, *rest) for result, (_, *rest) in zip(_finished([run[0] for run in started]), started)]
    for result, prog, *needles in runs:
        assert result.returncode == 2, result.stderr
        assert "Traceback" not in result.stderr + result.stdout
        lines = result.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith(f"{prog}: error: "), result.stderr
        assert all(needle in lines[0] for needle in needles), lines[0]
    assert tree(tmp_path) == before


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

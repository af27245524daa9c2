"""``label_noise``: an input segmentation for real scans from their labels (a noise model).

Runs on the real SemanticKITTI scans in ../shared (skipped with a reason where they are
absent), on a few frames only; every output goes to a temporary folder and the shared folder
is checked to be untouched at the end.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers import REAL_SCANS

from convbki_core.datasets import label_noise as noise
from convbki_core.datasets.label_noise_neighbours import nearest_other
from convbki_core.datasets.semantic_kitti import SemanticKittiSequence, read_label_words
from convbki_core.io.labels import load_label_map
from convbki_core.measures.metrics import ConfusionMatrix
from convbki_core.tools import label_noise as tool

REPO = Path(__file__).resolve().parents[2]
SHARED = REAL_SCANS
SEQUENCE = "05"  # urban: cars, trucks, an other-vehicle, a person; 20 classes
FRAMES = "0:4"
TARGET = 0.55
needs_real = pytest.mark.skipif(not (SHARED / "sequences" / SEQUENCE / "velodyne").is_dir(),
                                reason=f"the real SemanticKITTI scans are not here ({SHARED})")
VEHICLES = {1, 4, 5}  # car, truck, other-vehicle


def _snapshot(root: Path) -> dict[str, tuple]:
    """Every entry under ``root``: kind, size and modification time."""
    entries = {}
    for folder, names, files in os.walk(root):
        for name in [*names, *files]:
            info = (Path(folder) / name).lstat()
            entries[str(Path(folder, name).relative_to(root))] = (info.st_mode, info.st_size, info.st_mtime_ns)
    info = root.lstat()
    entries["."] = (info.st_mode, info.st_size, info.st_mtime_ns)
    return entries


@pytest.fixture(scope="module")
def shared_before() -> dict[str, tuple]:
    if not SHARED.is_dir():
        pytest.skip(f"the real SemanticKITTI scans are not here ({SHARED})")
    return _snapshot(SHARED)


def _write(out: Path, *extra: str) -> Path:
    code = tool.main(["--dataset", str(SHARED), "--sequence", SEQUENCE, "--out", str(out), "--frames", FRAMES,
                      "--input-miou", str(TARGET), "--quiet", *extra])
    assert code == 0
    return out / "sequences" / SEQUENCE


@pytest.fixture(scope="module")
def written(shared_before, tmp_path_factory) -> dict[str, Path]:
    """Seed 0 twice (in two folders) and seed 1, frames 0-3 of sequence 05."""
    base = tmp_path_factory.mktemp("label_noise")
    return {"a": _write(base / "a"), "b": _write(base / "b"), "other": _write(base / "c", "--seed", "1")}


def _labels(folder: Path) -> dict[str, bytes]:
    return {path.name: path.read_bytes() for path in sorted(folder.glob("*.label"))}


@needs_real
def test_written_dataset_meets_the_target_miou_and_reads_like_a_dataset(written):
    folder = written["a"]
    report = json.loads((folder / "label_noise.json").read_text())
    for name in ("velodyne", "labels", "poses.txt", "calib.txt", "times.txt"):
        assert (folder / name).is_symlink() and (folder / name).resolve() == (SHARED / "sequences" / SEQUENCE /
                                                                               name).resolve()
    predictions = folder / "predictions"
    assert predictions.is_dir() and not predictions.is_symlink()
    assert sorted(p.name for p in predictions.iterdir()) == [f"{i:06d}.label" for i in range(4)]
    # The exact mIoU of what was written, measured here as evaluate measures it.
    dataset = SemanticKittiSequence(folder.parent.parent, SEQUENCE, predictions_dir="predictions")
    scores = ConfusionMatrix(20)
    for position in range(4):
        frame = dataset[position]
        words = np.fromfile(predictions / f"{frame.name}.label", dtype="<u4")
        assert not (words >> 16).any()  # instance bits 0
        scores.add(frame.ground_truth, frame.input_labels)
    assert abs(scores.miou() - TARGET) <= 0.015
    assert report["measured_miou"] == pytest.approx(scores.miou(), abs=1e-12)
    assert report["target_miou"] == TARGET and report["seed"] == 0 and report["model_version"] == noise.MODEL_VERSION
    assert report["strength"] > 0
    names = load_label_map().class_names
    assert set(report["iou"]) == {names[c] for c in np.flatnonzero(scores.present)}


@needs_real
def test_same_seed_writes_the_same_bytes_and_another_seed_other_labels(written):
    first, again, other = (_labels(written[k] / "predictions") for k in ("a", "b", "other"))
    assert first == again
    assert first.keys() == other.keys() and all(first[name] != other[name] for name in first)


@pytest.fixture(scope="module")
def model_run(written):
    """The model's own view of the written frames: draws, predictions and mechanisms per scan."""
    report = json.loads((written["a"] / "label_noise.json").read_text())
    dataset = SemanticKittiSequence(SHARED, SEQUENCE, predictions_dir=None)
    model = noise.LabelNoiseModel(load_label_map(), 0, SEQUENCE)
    scans = []
    for position in range(4):
        frame = dataset[position]
        words = read_label_words(dataset.labels_folder / f"{frame.name}.label")
        draws = model.draws(frame, words >> np.uint32(16))
        predicted, mechanism = model.predict(draws, report["strength"])
        scans.append((frame, words >> np.uint32(16), draws, predicted, mechanism))
    return model, report, scans


@needs_real
def test_model_predictions_are_what_was_written(model_run, written):
    _, _, scans = model_run
    label_map = load_label_map()
    for frame, _, _, predicted, _ in scans:
        stored = np.fromfile(written["a"] / "predictions" / f"{frame.name}.label", dtype="<u4")
        assert np.array_equal(label_map.to_learning(stored), predicted)


@needs_real
def test_confused_vehicles_stay_in_their_group_and_flicker_between_scans(model_run):
    _, report, scans = model_run
    confused = {o["instance"] for o in report["confused_objects"] if o["class"] in ("car", "truck", "other-vehicle")}
    assert confused, "no vehicle confused: the flicker mechanism did nothing"
    majority: dict[int, set[int]] = {}
    in_group = []
    for _, instances, draws, predicted, mechanism in scans:
        truth = draws.truth.astype(np.int64)
        for instance in confused:
            on = (instances == instance) & np.isin(truth, list(VEHICLES))
            if not on.any():
                continue
            by_object = on & (mechanism == noise.OBJECT)
            # The object mechanism's labels: another class of the vehicle group, never outside it.
            assert np.isin(predicted[by_object], list(VEHICLES)).all()
            assert (predicted[by_object] != truth[by_object]).all()
            in_group.append(np.isin(predicted[on], list(VEHICLES)))
            majority.setdefault(instance, set()).add(int(np.bincount(predicted[on]).argmax()))
    # All in all, the confused vehicles read as some vehicle (the rest: blur and blobs).
    assert np.concatenate(in_group).mean() > 0.85
    # Label flicker of an object that does not move: its majority label changes between scans.
    assert any(len(labels) > 1 for labels in majority.values()), majority
    # Vehicles the model left alone are never relabelled by the object mechanism.
    for _, instances, draws, _, mechanism in scans:
        vehicle = np.isin(draws.truth, list(VEHICLES)) & ~np.isin(instances, list(confused))
        assert not (vehicle & (mechanism == noise.OBJECT)).any()


@needs_real
def test_blur_only_near_borders_and_borders_err_more(model_run):
    _, _, scans = model_run
    frame, _, draws, predicted, mechanism = scans[0]
    truth = draws.truth.astype(np.int64)
    _, distance = nearest_other(frame.points, truth, 1.0)
    # The neighbour search against brute force on a sample of points.
    rng = np.random.default_rng(0)
    points = frame.points.astype(np.float64)
    for k in rng.choice(len(points), 200, replace=False):
        other = (truth != truth[k]) & (truth != 0)
        nearest = np.sqrt(((points[other] - points[k]) ** 2).sum(1)).min(initial=np.inf)
        assert distance[k] == pytest.approx(nearest if nearest < 1.0 else np.inf, abs=1e-5)
    scored = truth > 0
    far = scored & (distance > 1.0)
    border = scored & (distance < 0.2)
    assert far.sum() > 10_000 and border.sum() > 5_000
    assert not (mechanism[far] == noise.BOUNDARY).any()
    assert (mechanism[border] == noise.BOUNDARY).mean() > 0.02
    assert (predicted[border] != truth[border]).mean() > 1.5 * (predicted[far] != truth[far]).mean()


@needs_real
def test_error_rate_grows_with_range(model_run):
    _, _, scans = model_run
    truth = np.concatenate([s[2].truth for s in scans]).astype(np.int64)
    predicted = np.concatenate([s[3] for s in scans])
    distance = np.concatenate([s[2].distance for s in scans])
    rates = []
    for low, high in ((0, 20), (20, 35), (35, np.inf)):
        chosen = (truth > 0) & (distance >= low) & (distance < high)
        rates.append((predicted[chosen] != truth[chosen]).mean())
    assert rates[0] < rates[1] < rates[2], rates
    assert rates[2] > 1.5 * rates[0], rates


@needs_real
def test_in_place_writes_only_the_predictions_and_the_report(shared_before, tmp_path):
    """--out equal to --dataset: a root whose sequence links to the real files gets nothing but
    the predictions folder and label_noise.json; a second run replaces its own folder."""
    root = tmp_path / "root"
    folder = root / "sequences" / SEQUENCE
    folder.mkdir(parents=True)
    for name in ("velodyne", "labels", "poses.txt", "calib.txt", "times.txt"):
        (folder / name).symlink_to(SHARED / "sequences" / SEQUENCE / name)
    arguments = ["--dataset", str(root), "--sequence", SEQUENCE, "--out", str(root), "--frames", "0:2", "--quiet"]
    assert tool.main(arguments) == 0
    assert tool.main([*arguments, "--seed", "1"]) == 0
    assert sorted(p.name for p in folder.iterdir()) == sorted(
        ["velodyne", "labels", "poses.txt", "calib.txt", "times.txt", "predictions", "label_noise.json"])
    assert sorted(p.name for p in (folder / "predictions").iterdir()) == ["000000.label", "000001.label"]
    assert json.loads((folder / "label_noise.json").read_text())["seed"] == 1


def _one_line(capsys, code: int, *needles: str) -> None:
    err = capsys.readouterr().err
    assert code == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("label_noise: error: "), err
    assert all(needle in lines[0] for needle in needles), err


def test_bad_arguments_exit_2_with_one_line(tmp_path, capsys):
    _one_line(capsys, tool.main(["--dataset", str(tmp_path / "nowhere"), "--sequence", "5", "--out",
                                 str(tmp_path / "o")]), "nowhere")
    for bad in (["--input-miou", "1.5"], ["--input-miou", "0"], ["--predictions-dir", "labels"],
                ["--frames", "5"], ["--sequence", "x"]):
        with pytest.raises(SystemExit) as stop:
            tool.main(["--dataset", str(tmp_path), "--sequence", "5", "--out", str(tmp_path / "o"), *bad])
        _one_line(capsys, stop.value.code, bad[0])
    assert not (tmp_path / "o").exists()
    # As a process: no traceback either.
    result = subprocess.run([sys.executable, "-m", "convbki_core.tools.label_noise", "--dataset", str(tmp_path /
                             "nowhere"), "--sequence", "05", "--out", str(tmp_path / "o"), "--input-miou", "1.5"],
                            cwd=REPO, capture_output=True, text=True, timeout=60)
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1 and "--input-miou" in result.stderr


@needs_real
def test_unwritable_or_foreign_outputs_and_unreachable_targets_are_refused(shared_before, tmp_path, capsys):
    arguments = ["--dataset", str(SHARED), "--sequence", SEQUENCE, "--frames", "0:1", "--quiet"]
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o555)
    try:
        _one_line(capsys, tool.main([*arguments, "--out", str(locked)]), "locked", "not writable")
    finally:
        locked.chmod(0o755)
    assert not any(locked.iterdir())
    foreign = tmp_path / "foreign" / "sequences" / SEQUENCE / "predictions"
    foreign.mkdir(parents=True)
    (foreign / "000000.label").write_bytes(b"mine")
    _one_line(capsys, tool.main([*arguments, "--out", str(tmp_path / "foreign")]), "not written by label_noise")
    assert (foreign / "000000.label").read_bytes() == b"mine"
    _one_line(capsys, tool.main([*arguments, "--out", str(tmp_path / "far"), "--input-miou", "0.01"]),
              "out of reach")
    assert not (tmp_path / "far").exists()


@needs_real
def test_zz_shared_folder_untouched(shared_before, written, model_run):
    """Last: every run above left the shared data exactly as it was."""
    assert _snapshot(SHARED) == shared_before

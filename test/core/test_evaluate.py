"""``evaluate`` and ``train`` end to end on small sequences written by the test."""

import json
import types

import numpy as np
import pytest
import yaml
from helpers import kernel_from_file
from kitti_fixture import BUILDING, POLE, ROAD, SIDEWALK, write_drive

from convbki_core import ConvBKIMapper
from convbki_core.paths import kernel_path
from convbki_core.tools import evaluate, evaluate_run, train

# SemanticKITTI's learning_map (semantic-kitti.yaml of the semantic-kitti-api), typed here
# independently of the project's label map.
RAW_TO_LEARNING = {0: 0, 1: 0, 10: 1, 11: 2, 13: 5, 15: 3, 16: 5, 18: 4, 20: 5, 30: 6, 31: 7, 32: 8, 40: 9, 44: 10,
                   48: 11, 49: 12, 50: 13, 51: 14, 52: 0, 60: 9, 70: 15, 71: 16, 72: 17, 80: 18, 81: 19, 99: 0,
                   252: 1, 253: 7, 254: 6, 255: 8, 256: 5, 257: 5, 258: 4, 259: 5}
def independent_scores(dataset_root, labels_root, sequence, frames, folder="predictions"):
    """(mIoU, accuracy) of label files, scored the way the official evaluator would, with plain numpy."""
    lut = np.zeros(1 << 16, np.int64)
    for raw, learning in RAW_TO_LEARNING.items():
        lut[raw] = learning
    matrix = np.zeros((20, 20), np.int64)
    for number in range(frames):
        truth = np.fromfile(dataset_root / "sequences" / sequence / "labels" / f"{number:06d}.label", np.uint32)
        guess = np.fromfile(labels_root / "sequences" / sequence / folder / f"{number:06d}.label", np.uint32)
        assert truth.shape == guess.shape
        np.add.at(matrix, (lut[truth & 0xFFFF], lut[guess & 0xFFFF]), 1)
    matrix[0, :] = 0
    tp = np.diag(matrix).astype(float)
    union = matrix.sum(0) + matrix.sum(1) - tp
    present = matrix.sum(1) > 0
    return float(np.mean(tp[present] / union[present])), float(tp.sum() / matrix.sum())


SMALL_WINDOW = ["--local-bounds", "-20", "-12", "-3", "20", "12", "4"]


def test_evaluate_reports_and_writes_labels_that_score_the_same(tmp_path, capsys, monkeypatch):
    data = write_drive(tmp_path / "data", "08", frames=5)
    # Record the mapper's own per-scan timings, and make labelling frame i take (i + 1) * 7 ms on
    # the clock evaluate reads, so that the reported medians can be checked exactly.
    seen, clock = [], [0.0]
    integrate, label = ConvBKIMapper.integrate, evaluate_run.map_frame_labels

    def watched_integrate(self, *args, **options):
        result = integrate(self, *args, **options)
        if self.geometry.bounds_max[0] == 20:  # the evaluated mapper, not the warm-up's throwaway ones
            seen.append(dict(result.timing_ms))
        return result

    def slow_label(*args):
        clock[0] += 0.007 * len(seen)
        return label(*args)

    monkeypatch.setattr(ConvBKIMapper, "integrate", watched_integrate)
    monkeypatch.setattr(evaluate_run, "map_frame_labels", slow_label)
    monkeypatch.setattr(evaluate_run, "time", types.SimpleNamespace(perf_counter=lambda: clock[0]))
    report_path = tmp_path / "report.json"
    code = evaluate.main(["--dataset", str(tmp_path / "data"), "--sequence", "08", "--report", str(report_path),
                          "--write-labels", str(tmp_path / "out"), "--quiet", "--device", "cpu", *SMALL_WINDOW])
    assert code == 0
    report = json.loads(report_path.read_text())
    assert report["sequence"] == "08" and report["frames"] == 5 and report["kernel"] == "compound"
    assert report["free_space"] is True and report["max_concentration"] == 300.0  # the node's defaults
    assert set(report["input"]["iou"]) == {"road", "sidewalk", "building", "pole"}
    # The input segmentation's files and the label files written, scored independently, give
    # the reported scores.
    for part, labels_root in (("input", tmp_path / "data"), ("map", tmp_path / "out")):
        miou, accuracy = independent_scores(tmp_path / "data", labels_root, "08", 5)
        assert report[part]["miou"] == pytest.approx(miou, abs=1e-9), part
        assert report[part]["accuracy"] == pytest.approx(accuracy, abs=1e-9), part
    # update: the median over the frames of voxelisation + update + free space; query: of the
    # window move + labelling the frame's points.
    assert len(seen) == report["frames"]
    timing = report["timing_ms"]
    update = [t["voxelize"] + t["update"] + t["free"] for t in seen]
    query = [t["query"] + 7.0 * (number + 1) for number, t in enumerate(seen)]
    assert timing["update_median"] == pytest.approx(float(np.median(update)), rel=1e-9)
    assert timing["query_median"] == pytest.approx(float(np.median(query)), rel=1e-9)
    for number, (points, _, _) in enumerate(data):
        written = np.fromfile(tmp_path / "out" / "sequences" / "08" / "predictions" / f"{number:06d}.label", "<u4")
        assert written.size == len(points) and set(np.unique(written)) <= {ROAD, SIDEWALK, POLE, BUILDING}
    # Fusing five noisy views beats the single-view input by a wide margin on this scene.
    assert report["map"]["miou"] > report["input"]["miou"] + 0.1
    assert (tmp_path / "report_map.png").stat().st_size > 10_000
    # Measured uncertainty (test_uncertainty_metrics.py): the map's, and none for an input of labels only.
    assert all(np.isfinite(report["map"][key]) for key in ("ece", "nll", "brier"))
    assert len(report["map"]["variance_curve"]) == 14
    assert report["input"]["ece"] is None and report["input"]["nll"] is None and report["input"]["brier"] is None
    assert (tmp_path / "report_reliability.png").stat().st_size > 10_000
    printed = capsys.readouterr().out
    assert "road" in printed and "mIoU" in printed


def test_evaluate_maps_a_partial_sequence_with_the_whole_sequence_s_poses(tmp_path, capsys):
    """Scans 2-4 of a 6-scan drive beside its whole poses.txt (a partial download): pose k is
    used for scan k, one line says how many were not, and the scores equal those of frames 2:5
    of the whole drive."""
    import shutil

    write_drive(tmp_path / "whole", "08", frames=6)
    partial = tmp_path / "partial" / "sequences" / "08"
    shutil.copytree(tmp_path / "whole" / "sequences" / "08", partial)
    for sub in ("velodyne", "labels", "predictions"):
        for path in (partial / sub).iterdir():
            if int(path.stem) not in (2, 3, 4):
                path.unlink()
    reports = {}
    runs = (("whole", tmp_path / "whole", ["--frames", "2:5"]), ("partial", tmp_path / "partial", []))
    for name, root, frames in runs:
        report = tmp_path / f"{name}.json"
        assert evaluate.main(["--dataset", str(root), "--sequence", "08", "--report", str(report), "--quiet",
                              *SMALL_WINDOW, *frames]) == 0
        reports[name] = json.loads(report.read_text())
        notes = [line for line in capsys.readouterr().err.splitlines() if "note:" in line]
        assert notes == ([] if name == "whole" else
                         [f"evaluate: note: {partial / 'poses.txt'}: 6 poses for 3 numbered scans: row k used for "
                          "scan k, 3 not used"]), notes
    assert reports["partial"]["frames"] == reports["whole"]["frames"] == 3
    for part in ("input", "map"):
        assert reports["partial"][part]["iou"] == reports["whole"][part]["iou"], part
        assert reports["partial"][part]["miou"] == reports["whole"][part]["miou"] > 0


def test_evaluate_compares_several_kernels(tmp_path):
    write_drive(tmp_path / "data", "00", frames=3)
    kernels = [str(kernel_path(name)) for name in ("semantic_kitti_sbki", "semantic_kitti_compound")]
    code = evaluate.main(["--dataset", str(tmp_path / "data"), "--sequence", "0", "--report", str(tmp_path / "r.json"),
                          "--kernel", *kernels, "--quiet", "--device", "cpu", *SMALL_WINDOW])
    assert code == 0
    report = json.loads((tmp_path / "r.json").read_text())
    assert [run["kernel"] for run in report["runs"]] == ["single", "compound"]
    assert report["map"] == report["runs"][0]["map"]
    assert (tmp_path / "r_semantic_kitti_compound_map.png").exists()
    assert all((tmp_path / f"r_{name}_reliability.png").exists()
               for name in ("semantic_kitti_sbki", "semantic_kitti_compound"))
    assert report["runs"][1]["map"]["ece"] >= 0 and "variance_curve" in report["runs"][1]["map"]


@pytest.mark.parametrize("arguments, message", [
    (["--dataset", "{tmp}/nowhere", "--sequence", "00"], "dataset folder not found"),
    (["--dataset", "{tmp}/data", "--sequence", "03"], "sequence 03 not found"),
    (["--dataset", "{tmp}/data", "--sequence", "00", "--kernel", "{tmp}/bad.yaml"], "odd"),
    (["--dataset", "{tmp}/data", "--sequence", "00", "--frames", "50:60"], "selects no frame"),
    (["--dataset", "{tmp}/data", "--sequence", "00", "--predictions-dir", "other"], "predictions folder not found"),
])
def test_evaluate_errors_are_one_line_and_exit_2(tmp_path, capsys, arguments, message):
    write_drive(tmp_path / "data", "00", frames=2)
    (tmp_path / "bad.yaml").write_text(yaml.safe_dump({"kernel": "single", "resolution": 0.2, "filter_size": 4,
                                                       "num_classes": 20, "ell": 0.3}))
    arguments = [a.replace("{tmp}", str(tmp_path)) for a in arguments]
    code = evaluate.main([*arguments, "--report", str(tmp_path / "r.json"), "--quiet"])
    error = capsys.readouterr().err
    assert code == 2
    assert message in error and "Traceback" not in error and len(error.strip().splitlines()) == 1
    assert not (tmp_path / "r.json").exists()


@pytest.mark.parametrize("kind", ["single", "compound"])
def test_train_writes_a_kernel_that_lowers_the_loss(tmp_path, capsys, kind):
    write_drive(tmp_path / "data", "01", frames=8, seed=3)
    out = tmp_path / f"{kind}.yaml"
    code = train.main(["--dataset", str(tmp_path / "data"), "--sequences", "01", "--kernel", kind, "--out", str(out),
                       "--frames-per-sample", "3", "--epochs", "3", "--lr", "0.05", "--quiet", *SMALL_WINDOW,
                       "--min-class-points", "0"])  # a tiny drive: every class is under the default floor
    assert code == 0
    config = kernel_from_file(out).to_config()
    assert config.kernel == kind and config.num_classes == 20
    assert (tmp_path / f"{kind}_loss.png").exists() and (tmp_path / f"{kind}_kernels.png").exists()
    printed = capsys.readouterr().out
    # Samples are shuffled now, so single steps' losses are not comparable: the held-out mIoU must rise.
    line = next(line for line in printed.splitlines() if line.startswith("validation mIoU: start"))
    assert float(line.split("best ")[1].split(" ")[0]) > float(line.split("start ")[1].split(",")[0]), printed
    lengths = config.ell if kind == "single" else config.ell_h + config.ell_z
    assert any(abs(v - 0.5) > 1e-3 for v in lengths), "training must move the lengths off their initial 0.5 m"


def _first_last(printed: str) -> tuple[float, float]:
    line = next(line for line in printed.splitlines() if "(first tenth)" in line)
    first = float(line.split("loss ")[1].split(" ")[0])
    last = float(line.split("-> ")[1].split(" ")[0])
    return first, last

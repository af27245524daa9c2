"""Measured uncertainty (``calibration``): ECE, NLL, Brier, the variance-filter curve, and evaluate's report."""

import itertools
import json
import math

import numpy as np
import pytest
from kitti_fixture import noisy, pose_about_z, street_scene, write_sequence

from convbki_core import ConvBKIMapper
from convbki_core.config import MapperConfig
from convbki_core.measures.metrics import ConfusionMatrix
from convbki_core.measures.uncertainty import (
    BINS,
    PROBABILITY_FLOOR,
    VARIANCE_THRESHOLDS,
    CalibrationStats,
    input_distribution,
    map_concentrations,
    map_distribution,
)
from convbki_core.paths import kernel_path
from convbki_core.tools import evaluate

# Four scored points over classes 1..3 (class 0 ignored), and one ignored point.
PROBABILITIES = np.array([[0.0, 0.9, 0.1, 0.0],     # truth 1: chosen 1 (right), confidence 0.9 -> bin 13
                          [0.0, 0.6, 0.4, 0.0],     # truth 2: chosen 1 (wrong), confidence 0.6 -> bin 9
                          [0.0, 0.2, 0.2, 0.6],     # truth 3: chosen 3 (right), confidence 0.6 -> bin 9
                          [0.0, 0.5, 0.25, 0.25],   # truth 1: chosen 1 (right), confidence 0.5 -> bin 7
                          [1.0, 0.0, 0.0, 0.0]])    # truth 0: ignored
TRUTH = np.array([1, 2, 3, 1, 0])


def test_ece_nll_brier_by_hand():
    stats = CalibrationStats(4, ignore_classes=(0,), thresholds=None)
    stats.add(TRUTH, PROBABILITIES)
    assert stats.points == 4
    # bin 13: 1 point, accuracy 1, confidence 0.9 -> 0.1; bin 9: 2 points, accuracy 0.5, confidence
    # 0.6 -> 0.1; bin 7: 1 point, accuracy 1, confidence 0.5 -> 0.5.
    # ECE = 1/4 * 0.1 + 2/4 * 0.1 + 1/4 * 0.5 = 0.2
    assert stats.ece() == pytest.approx(0.2, abs=1e-12)
    # NLL = -(ln 0.9 + ln 0.4 + ln 0.6 + ln 0.5) / 4 = 0.5564060...
    assert stats.nll() == pytest.approx(0.5564060129644793, abs=1e-12)
    # Brier: 0.1^2 + 0.1^2 = 0.02; 0.6^2 + 0.6^2 = 0.72; 0.2^2 + 0.2^2 + 0.4^2 = 0.24;
    # 0.5^2 + 0.25^2 + 0.25^2 = 0.375; mean 1.355 / 4 = 0.33875
    assert stats.brier() == pytest.approx(0.33875, abs=1e-12)
    reliability = stats.reliability()
    assert reliability.count.tolist() == [0] * 7 + [1, 0, 2, 0, 0, 0, 1, 0] and len(reliability.edges) == BINS + 1
    assert reliability.accuracy[9] == 0.5 and reliability.confidence[9] == pytest.approx(0.6)
    assert stats.summary() == pytest.approx({"ece": 0.2, "nll": 0.5564060129644793, "brier": 0.33875})


def test_streaming_equals_one_batch_and_empty_is_null():
    whole = CalibrationStats(4, thresholds=None)
    whole.add(TRUTH, PROBABILITIES)
    parts = CalibrationStats(4, thresholds=None)
    parts.add(TRUTH[:2], PROBABILITIES[:2])
    parts.add(TRUTH[2:], PROBABILITIES[2:])
    assert (parts.ece(), parts.nll(), parts.brier()) == pytest.approx((whole.ece(), whole.nll(), whole.brier()))
    assert CalibrationStats(4).summary(with_curve=False) == {"ece": None, "nll": None, "brier": None}


def test_nll_floor_and_certain_points():
    stats = CalibrationStats(3, ignore_classes=(0,), thresholds=None)
    # Confidence 1 falls in the last bin; a truth with probability 0 costs -ln(floor) ~ 27.63.
    stats.add(np.array([1, 2]), np.array([[0.0, 1.0, 0.0], [0.0, 1.0, 0.0]]))
    assert stats.bin_count[-1] == 2
    assert stats.nll() == pytest.approx((0.0 + 27.631021115928547) / 2, rel=1e-9)
    assert -math.log(PROBABILITY_FLOOR) == pytest.approx(27.631021115928547)
    assert stats.brier() == pytest.approx((0.0 + 2.0) / 2)  # 0 when right, 2 when confidently wrong
    assert stats.ece() == pytest.approx(0.5)  # one bin: accuracy 0.5, confidence 1


def test_map_distribution_leaves_out_free_space():
    alpha = np.array([[6.0, 1.0, 3.0, 0.0]], np.float32)
    probabilities, chosen, variance = map_distribution(alpha, free_space=True)
    # Class 0 dropped: p = (0, 1/4, 3/4, 0), chosen 2, V = 3/4 * 1/4 / (1 + 4) = 0.0375.
    assert probabilities[0] == pytest.approx([0.0, 0.25, 0.75, 0.0])
    assert chosen.tolist() == [2] and variance[0] == pytest.approx(0.0375)
    probabilities, chosen, variance = map_distribution(alpha, free_space=False)
    # All classes: p = (0.6, 0.1, 0.3, 0), chosen 0, V = 0.6 * 0.4 / 11.
    assert probabilities[0] == pytest.approx([0.6, 0.1, 0.3, 0.0])
    assert chosen.tolist() == [0] and variance[0] == pytest.approx(0.24 / 11)
    assert input_distribution(np.array([[2.0, 2.0], [0.0, 0.0]])) == pytest.approx(np.array([[0.5, 0.5]] * 2))


def test_variance_curve_by_hand_and_monotone():
    stats = CalibrationStats(4, ignore_classes=(0,))
    # Variances: kept from 1e-4 on, from 10^-2.5 on, from 10^-1.25 on, and only without a filter.
    stats.add(TRUTH, PROBABILITIES, variance=np.array([5e-5, 2e-3, 0.05, 0.5, 0.0]))
    curve = stats.variance_curve()
    assert [entry["threshold"] for entry in curve[:-1]] == pytest.approx(list(VARIANCE_THRESHOLDS))
    assert curve[-1]["threshold"] is None and len(curve) == 14
    kept = [entry["kept"] for entry in curve]
    assert kept == [0.25] * 6 + [0.5] * 5 + [0.75] * 2 + [1.0]  # thresholds 10^(-4 + k/4), k = 0 .. 12
    # At 1e-4 only point 1 is kept (class 1, right): mIoU 1. Without a filter: IoU class 1 = 2/3
    # (two right, one point of class 2 predicted 1), class 2 = 0, class 3 = 1 -> mIoU 5/9.
    assert curve[0]["miou"] == 1.0 and curve[-1]["miou"] == pytest.approx(5 / 9)
    assert curve[-1]["accuracy"] == 0.75

    rng = np.random.default_rng(1)
    many = CalibrationStats(6, ignore_classes=(0,))
    variances = []
    for _ in range(3):
        truth = rng.integers(0, 6, 500)
        probabilities = rng.dirichlet(np.ones(6), 500)
        variance = 10.0 ** rng.uniform(-5, 0, 500)
        many.add(truth, probabilities, variance=variance)
        variances.append(variance[truth != 0])
    variances = np.concatenate(variances)
    kept = [entry["kept"] for entry in many.variance_curve()]
    assert all(b >= a for a, b in itertools.pairwise(kept)) and kept[-1] == 1.0
    assert kept[:-1] == pytest.approx([float(np.mean(variances <= t)) for t in VARIANCE_THRESHOLDS], abs=1e-12)


def test_map_concentrations_give_the_protocol_labels():
    rng = np.random.default_rng(2)
    world, truth = street_scene(rng, count=1500)
    labels = np.select([truth == 40, truth == 48, truth == 50], [9, 11, 13], 18)  # road, sidewalk, building, pole
    config = MapperConfig.paper(device="cpu", free_space=True, local_bounds=((-20.0, -12.0, -3.0), (20.0, 12.0, 4.0)))
    mapper = ConvBKIMapper(config, kernel_path("semantic_kitti_compound"))
    pose = pose_about_z(0.3, [0.0, 0.5, 0.2])
    mapper.integrate(((world - pose[:3, 3]) @ pose[:3, :3]).astype(np.float32), labels, pose)
    queries = np.concatenate([world, [[100.0, 0.0, 0.0], [np.nan, 0.0, 0.0]]])
    expected, has = mapper.labels_at(queries)
    alpha, found = map_concentrations(mapper, queries)
    assert np.array_equal(found, has) and not found[-2:].any() and (alpha[~found] == 0).all()
    _, chosen, _ = map_distribution(alpha[found], mapper.free_space)
    assert np.array_equal(chosen, expected[found])


def write_probability_drive(root, frames=3, seed=5):
    """The fixture's street with a noisy input given as labels and as (tempered) probabilities."""
    rng = np.random.default_rng(seed)
    world, truth = street_scene(rng, count=2500)
    learning = {40: 9, 48: 11, 50: 13, 80: 18}
    data, poses, probabilities = [], [], []
    for number in range(frames):
        pose = pose_about_z(0.05 * number + 0.3, [-6.0 + 3.0 * number, 0.5, 0.2])
        visible = rng.random(len(world)) < 0.7
        predicted = noisy(truth[visible], rng, 0.3)
        soft = np.full((visible.sum(), 20), 0.01)
        soft[np.arange(len(predicted)), [learning[int(v)] for v in predicted]] = 0.7
        probabilities.append(soft / soft.sum(axis=1, keepdims=True))
        data.append((((world[visible] - pose[:3, 3]) @ pose[:3, :3]).astype(np.float32), truth[visible], predicted))
        poses.append(pose)
    write_sequence(root, "00", data, poses, probabilities=probabilities)


# A window holding the whole street from every pose: every point's voxel holds evidence.
WIDE_WINDOW = ["--local-bounds", "-25", "-10", "-3", "25", "10", "4"]


@pytest.mark.parametrize("with_probabilities, update_path", [(False, "fast"), (True, "fast"), (False, "torch")])
def test_evaluate_reports_uncertainty(tmp_path, with_probabilities, update_path):
    write_probability_drive(tmp_path / "data")
    extra = ["--probabilities-dir", "probabilities"] if with_probabilities else []
    extra += ["--update-path", update_path]
    report_path = tmp_path / "report.json"
    code = evaluate.main(["--dataset", str(tmp_path / "data"), "--sequence", "00", "--report", str(report_path),
                          "--quiet", "--device", "cpu", *WIDE_WINDOW, *extra])
    assert code == 0
    report = json.loads(report_path.read_text())
    scores = report["map"]
    for key in ("ece", "nll", "brier"):
        assert math.isfinite(scores[key]), key
    assert 0 <= scores["ece"] <= 1 and 0 <= scores["brier"] <= 2 and scores["nll"] >= 0
    assert scores["points_without_evidence"] == 0 and scores["calibration_points"] > 0
    curve = scores["variance_curve"]
    assert len(curve) == 14 and curve[-1]["threshold"] is None
    kept = [entry["kept"] for entry in curve]
    assert all(b >= a for a, b in itertools.pairwise(kept)) and kept[-1] == 1.0
    # Every scored point has map evidence here, so without a filter the curve scores exactly
    # the points and labels the protocol scores.
    assert curve[-1]["miou"] == pytest.approx(scores["miou"], abs=1e-12)
    assert curve[-1]["accuracy"] == pytest.approx(scores["accuracy"], abs=1e-12)
    if with_probabilities:
        for key in ("ece", "nll", "brier"):
            assert math.isfinite(report["input"][key]), key
        # The input gives its label 0.7 / 0.89 = 0.79 (0.01 / 0.89 to each other class) and is
        # right about 70 % of the time: ECE about 0.09.
        assert report["input"]["nll"] > 0 and report["input"]["ece"] < 0.2
    else:
        assert report["input"]["ece"] is None and report["input"]["nll"] is None and report["input"]["brier"] is None
    assert (tmp_path / "report_reliability.png").stat().st_size > 10_000


def test_variance_curve_matches_a_direct_count():
    """The curve's confusion at a threshold equals a ConfusionMatrix of just the kept points."""
    rng = np.random.default_rng(3)
    truth = rng.integers(0, 5, 400)
    probabilities = rng.dirichlet(np.ones(5), 400)
    variance = 10.0 ** rng.uniform(-4.5, -0.5, 400)
    stats = CalibrationStats(5, ignore_classes=(0,))
    stats.add(truth, probabilities, variance=variance)
    for threshold, entry in zip(VARIANCE_THRESHOLDS, stats.variance_curve()):
        direct = ConfusionMatrix(5, (0,))
        keep = variance <= threshold
        direct.add(truth[keep], probabilities[keep].argmax(axis=1))
        if entry["miou"] is None:
            assert not direct.present.any()
        else:
            assert entry["miou"] == pytest.approx(direct.miou())

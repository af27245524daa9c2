"""Temperature scaling of probability inputs: the kernel file's ``temperature``, the mapper's
use of it on every update path, and its fit on validation frames (``training.temperature``)."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
import yaml
from kitti_fixture import pose_about_z, street_scene, write_sequence

from convbki_core import ConvBKIKernel, ConvBKIMapper
from convbki_core.config import DEFAULTS, MapperConfig
from convbki_core.datasets.semantic_kitti import SemanticKittiSequence
from convbki_core.geometry.volume import voxelize
from convbki_core.io.kernel_file import KernelFileError, load_kernel_file, parse_kernel_text, save_kernel_file
from convbki_core.io.labels import load_label_map
from convbki_core.measures.uncertainty import tempered_distribution
from convbki_core.paths import kernel_path
from convbki_core.tools import train
from convbki_core.training import temperature_fit, validation
from convbki_core.training.temperature import fit_input_temperature, input_nll, minimise_temperature

BOUNDS = ((-3.0, -3.0, -1.5), (3.0, 3.0, 1.5))
CLASSES = 6


def kernel(temperature=None, free_ell=None) -> ConvBKIKernel:
    return ConvBKIKernel("compound", CLASSES, 5, 0.25, ell_h=[0.3, 0.5, 0.7, 0.4, 0.9, 0.6],
                         ell_z=[0.6, 0.3, 0.5, 0.8, 0.4, 0.7], free_ell=free_ell, temperature=temperature)


def drive(mapper: ConvBKIMapper, probabilities: bool = True, seed: int = 5) -> None:
    """Five scans along a path that leaves the first window and comes back."""
    rng = np.random.default_rng(seed)
    for step, position in enumerate(([0, 0, 0], [2.0, 0.5, 0.2], [8.0, 1.0, 0], [1.0, -0.5, 0.1], [1.5, 0.2, 0])):
        pose = pose_about_z(0.4 * step, position)
        points = rng.uniform(-2.8, 2.8, (600, 3)) * [1, 1, 0.45]
        values = (rng.dirichlet(np.full(CLASSES, 0.4), 600).astype(np.float32) if probabilities
                  else rng.integers(0, CLASSES, 600))
        mapper.integrate(points, values, pose)


def items(mapper: ConvBKIMapper) -> tuple[np.ndarray, np.ndarray]:
    indices, alpha = mapper.items()
    order = np.lexsort(indices.T)
    return indices[order], alpha[order]


def mapped(temperature, path="fast", probabilities=True, free_space=False):
    mapper = ConvBKIMapper(MapperConfig.paper(local_bounds=BOUNDS, device="cpu", update_path=path,
                                              free_space=free_space), kernel(temperature,
                                                                             free_ell=0.3 if free_space else None))
    drive(mapper, probabilities)
    return items(mapper)


# -- the mapper ------------------------------------------------------------------------------------
@pytest.mark.parametrize("free_space", [False, True])
def test_a_temperature_of_one_is_exactly_the_map_without_one(free_space):
    (plain_indices, plain_alpha) = mapped(None, free_space=free_space)
    (one_indices, one_alpha) = mapped(1.0, free_space=free_space)
    assert len(plain_indices) > 1000
    assert np.array_equal(plain_indices, one_indices)
    assert np.array_equal(plain_alpha, one_alpha)  # bit for bit: T = 1 skips the calibration


def test_the_numpy_voxeliser_skips_a_temperature_of_one_bit_for_bit():
    rng = np.random.default_rng(3)
    points = rng.uniform(-1, 1, (300, 3))
    values = (rng.dirichlet(np.ones(CLASSES), 300) * rng.uniform(0.5, 1.5, (300, 1))).astype(np.float32)
    origin, dims = np.array([-6, -6, -6]), np.array([12, 12, 12])
    plain = voxelize(points, values, origin, dims, 0.2, CLASSES)
    one = voxelize(points, values, origin, dims, 0.2, CLASSES, temperature=1.0)
    assert np.array_equal(plain.features, one.features)


def test_labels_are_untouched_by_a_temperature():
    (plain_indices, plain_alpha) = mapped(None, probabilities=False)
    (hot_indices, hot_alpha) = mapped(0.3, probabilities=False)
    assert np.array_equal(plain_indices, hot_indices) and np.array_equal(plain_alpha, hot_alpha)


@pytest.mark.parametrize("temperature", [0.4, 2.5])
def test_every_update_path_gives_the_same_map_with_a_temperature(temperature):
    maps = {path: mapped(temperature, path) for path in ("fast", "dense", "torch")}
    fast_indices, fast_alpha = maps["fast"]
    for path in ("dense", "torch"):
        indices, alpha = maps[path]
        assert np.array_equal(indices, fast_indices), path
        np.testing.assert_allclose(alpha, fast_alpha, rtol=1e-5, err_msg=path)
    # The temperature did something: the map differs from the one of the rows as given...
    _, plain_alpha = mapped(None)
    assert np.abs(fast_alpha - plain_alpha).max() > 0.05
    # ... and in the expected direction: sharper rows (T < 1) make the winning class of a voxel
    # hold a larger share of its evidence, softer ones a smaller share.
    def top_share(alpha):
        return float(np.mean(alpha.max(axis=1) / alpha.sum(axis=1)))
    assert (top_share(fast_alpha) > top_share(plain_alpha)) == (temperature < 1)


def test_tempered_rows_keep_their_sum_and_match_the_textbook_softmax():
    rng = np.random.default_rng(11)
    rows = rng.dirichlet(np.full(CLASSES, 0.5), 200).astype(np.float32)
    rows[:5, 2] = 0.0  # a class ruled out stays out
    origin, dims = np.array([-1, -1, -1]), np.array([1000, 3, 3])
    points = np.column_stack([np.arange(200) * 0.2 + 0.1 - 0.2, np.zeros(200), np.zeros(200)])  # one voxel each
    volume = voxelize(points, rows * 3.0, origin, dims, 0.2, CLASSES, ignore_classes=(), temperature=0.5)
    expected = tempered_distribution(rows, 0.5) * (3.0 * rows.sum(axis=1, keepdims=True))
    np.testing.assert_allclose(volume.features, expected, rtol=2e-6, atol=1e-7)
    assert (volume.features[:5, 2] == 0).all()


# -- the kernel file -------------------------------------------------------------------------------
def test_a_kernel_file_with_a_temperature_round_trips_and_reaches_the_mapper(tmp_path):
    config = kernel(0.4375).to_config()
    path = tmp_path / "k.yaml"
    save_kernel_file(config, path)
    assert yaml.safe_load(path.read_text())["temperature"] == 0.4375
    loaded = load_kernel_file(path)
    assert loaded.temperature == 0.4375
    mapper = ConvBKIMapper(MapperConfig.paper(local_bounds=BOUNDS, device="cpu"), path)
    assert mapper.temperature == 0.4375
    assert mapper.snapshot().metadata["kernel"]["temperature"] == 0.4375  # saved maps say how they were made


def test_an_old_kernel_file_without_a_temperature_loads_as_one(tmp_path):
    shipped = kernel_path("semantic_kitti_compound")
    assert "temperature" not in yaml.safe_load(shipped.read_text())
    config = load_kernel_file(shipped)
    assert config.temperature is None
    assert ConvBKIMapper(MapperConfig.paper(local_bounds=BOUNDS, device="cpu"), shipped).temperature is None
    save_kernel_file(config, tmp_path / "again.yaml")  # and written back, still without one
    assert "temperature" not in yaml.safe_load((tmp_path / "again.yaml").read_text())


@pytest.mark.parametrize("value", ["0", "-1", "0.001", "1000", "warm", "true", ".nan", ".inf", "[1, 2]"])
def test_a_bad_temperature_is_one_clear_error(value):
    text = f"kernel: single\nresolution: 0.2\nfilter_size: 3\nnum_classes: 4\nell: 0.5\ntemperature: {value}\n"
    with pytest.raises(KernelFileError) as error:
        parse_kernel_text(text, "k.yaml")
    assert "temperature" in str(error.value) and str(error.value).startswith("k.yaml: ")
    assert "\n" not in str(error.value)


# -- the fit ---------------------------------------------------------------------------------------
def logits_and_truth(rng, count=20000, classes=8):
    """Logits z and a ground truth drawn from softmax(z): softmax(z) is calibrated by construction."""
    logits = rng.normal(0, 2.0, (count, classes))
    probabilities = np.exp(logits - logits.max(axis=1, keepdims=True))
    probabilities /= probabilities.sum(axis=1, keepdims=True)
    truth = (probabilities.cumsum(axis=1) < rng.random((count, 1))).sum(axis=1)
    return logits, np.minimum(truth, classes - 1)


@pytest.mark.parametrize("given_temperature", [0.5, 2.0])
def test_the_input_fit_undoes_a_known_temperature(given_temperature):
    """A network that reports softmax(z / T0) is over-confident (T0 < 1) or under-confident
    (T0 > 1); the fit finds T close to 1 / T0, which undoes it."""
    logits, truth = logits_and_truth(np.random.default_rng(1))
    reported = np.exp(logits / given_temperature)
    reported /= reported.sum(axis=1, keepdims=True)
    fitted = fit_input_temperature(reported.astype(np.float32), truth)
    assert fitted.temperature == pytest.approx(1.0 / given_temperature, rel=0.08)
    assert fitted.value < input_nll(reported, truth, 1.0) - 0.01


def test_the_search_finds_the_minimum_of_a_smooth_function_in_log_t():
    found = minimise_temperature(lambda t: (math.log(t) - math.log(0.37)) ** 2)
    assert found.temperature == pytest.approx(0.37, rel=0.03)
    assert len(found.tried) == 7 + 8


# A tiny drive with persistent segmentation errors (whole 1 m cells wrong in every scan, as a
# network's mistakes are) and class probabilities whose confidence the test chooses.
ROAD, SIDEWALK, POLE, BUILDING = 40, 48, 80, 50
SWAP = {ROAD: SIDEWALK, SIDEWALK: ROAD, POLE: BUILDING, BUILDING: POLE}


def write_probability_drive(root, sharpness, frames=12, seed=4):
    """Probability rows softmax(sharpness * z), z = 3 for the predicted class and 1.5 for the
    runner-up (the truth when the prediction is wrong); 30 % of cells are wrong. ``sharpness``
    1 gives a top probability of about 0.47 where 0.7 would be honest (under-confident), 4 about
    0.997 (over-confident)."""
    labels = load_label_map()
    rng = np.random.default_rng(seed)
    world, truth = street_scene(rng, count=3000)
    cell = np.floor(world / 1.0).astype(np.int64)
    wrong = (np.abs(cell @ np.array([73856093, 19349663, 83492791])) % 100) < 30
    predicted = np.where(wrong, [SWAP[int(v)] for v in truth], truth).astype(np.uint32)
    runner_up = np.where(wrong, truth, [SWAP[int(v)] for v in truth])
    logits = np.zeros((len(world), labels.num_classes))
    logits[np.arange(len(world)), labels.to_learning(predicted)] = 3.0
    logits[np.arange(len(world)), labels.to_learning(runner_up.astype(np.uint32))] = 1.5
    rows = np.exp(sharpness * logits)
    rows /= rows.sum(axis=1, keepdims=True)
    poses, data, probabilities = [], [], []
    for number in range(frames):
        pose = pose_about_z(0.05 * number + 0.3, [-6.0 + 1.0 * number, 0.5, 0.2])
        visible = rng.random(len(world)) < 0.7
        sensor = (world[visible] - pose[:3, 3]) @ pose[:3, :3]
        data.append((sensor.astype(np.float32), truth[visible], predicted[visible]))
        probabilities.append(rows[visible])
        poses.append(pose)
    write_sequence(root, "00", data, poses, probabilities=probabilities)
    return SemanticKittiSequence(root, "00", "predictions", "probabilities")


SMALL_BOUNDS = ((-20.0, -12.0, -3.0), (20.0, 12.0, 4.0))


@pytest.mark.parametrize(("sharpness", "direction"), [(1.0, "sharpen"), (4.0, "soften")])
def test_the_map_fit_moves_the_temperature_the_right_way(tmp_path, sharpness, direction):
    dataset = write_probability_drive(tmp_path / "data", sharpness)
    validator = validation.Validator([dataset], [list(range(6, 12))],
                                  DEFAULTS.replace(device="cpu", forget_movers=False, local_bounds=SMALL_BOUNDS))
    config = ConvBKIKernel("compound", 20, 5, 0.2, ell=0.5).to_config()
    fit = temperature_fit.fit_temperature(validator, config, grid=5, golden_steps=5)
    assert fit.start_temperature == 1.0
    if direction == "sharpen":
        assert fit.temperature < 0.8
    else:
        assert fit.temperature > 1.25
    assert fit.map_nll_after < fit.map_nll_before - 0.02
    assert fit.input_nll_after < fit.input_nll_before  # the input's own NLL agrees on the direction
    assert (fit.input_temperature < 1.0) == (direction == "sharpen")


def test_train_fits_and_writes_the_temperature_of_probability_inputs(tmp_path, capsys):
    write_probability_drive(tmp_path / "data", 1.0, frames=14)
    out = tmp_path / "k.yaml"
    code = train.main(["--dataset", str(tmp_path / "data"), "--sequences", "00", "--out", str(out),
                       "--probabilities-dir", "probabilities", "--frames-per-sample", "3", "--epochs", "1",
                       "--quiet", "--local-bounds", *(str(v) for v in (*SMALL_BOUNDS[0], *SMALL_BOUNDS[1]))])
    assert code == 0
    printed = capsys.readouterr().out
    assert "kept at the start" not in printed  # with probabilities every class learns by default
    line = next(line for line in printed.splitlines() if line.startswith("temperature "))
    fitted = float(line.split()[1])
    before, after = (float(v) for v in re.search(r"map NLL ([\d.]+) -> ([\d.]+),", line).groups())
    assert fitted < 0.8 and after < before
    assert load_kernel_file(out).temperature == pytest.approx(fitted, abs=1e-4)


class CurvesValidator:
    """A validator whose map NLL falls towards T = 0.3 while its mIoU falls below T = 1, as
    sharpening a soft network does: each point's vote loses what its second choice knew."""

    def __init__(self):
        self.tried = []

    def measure(self, config):
        temperature = 1.0 if config.temperature is None else config.temperature
        self.tried.append(temperature)
        nll = (math.log(temperature) - math.log(0.3)) ** 2
        miou = 0.7 - 0.1 * max(0.0, -math.log(temperature))
        stats = type("Stats", (), {"nll": lambda self: nll, "ece": lambda self: nll / 10})()
        return miou, type("Calibration", (), {"stats": stats})()

    def input_points(self):
        return np.zeros((0, 3), np.float32), np.zeros(0, np.int64)


@pytest.mark.parametrize("loss", [0.01, 0.05, None])
def test_the_fit_costs_at_most_the_allowed_mIoU(loss):
    config = ConvBKIKernel("single", 3, 3, 0.2, ell=0.5).to_config()
    fit = temperature_fit.fit_temperature(CurvesValidator(), config, miou_loss=loss)
    assert fit.search.temperature == pytest.approx(0.3, rel=0.03)  # the lowest NLL without the bound
    if loss is None:
        assert fit.temperature == pytest.approx(0.3, rel=0.03)
    else:
        boundary = math.exp(-loss / 0.1)  # where the mIoU has fallen by exactly ``loss``
        assert boundary <= fit.temperature < boundary * 1.05
        assert fit.miou_after >= fit.miou_before - loss - 1e-12
    assert fit.map_nll_after < fit.map_nll_before

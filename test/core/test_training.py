"""The trainer's held-out validation, best-kernel selection, --strict and learning-rate schedule,
on tiny drives written by the test (kitti_fixture)."""

import itertools

import numpy as np
import pytest
import yaml
from kitti_fixture import write_drive

from convbki_core.inference.kernels import ConvBKIKernel, load_kernel_file, save_kernel_file
from convbki_core.tools import train
from convbki_core.training import objective, samples, trainer, validation

SMALL_WINDOW = ["--local-bounds", "-20", "-12", "-3", "20", "12", "4"]


def _train_args(tmp_path, out, *extra):
    return ["--dataset", str(tmp_path / "data"), "--sequences", "01", "--kernel", "compound", "--out", str(out),
            "--frames-per-sample", "3", "--quiet", *SMALL_WINDOW, *extra]


def _start_file(tmp_path):
    config = ConvBKIKernel("compound", 20, 5, 0.2, ell_h=np.linspace(0.25, 0.9, 20),
                           ell_z=np.linspace(0.9, 0.3, 20), free_ell=0.3).to_config()
    path = tmp_path / "start.yaml"
    save_kernel_file(config, path)
    return path, load_kernel_file(path)


def _scores_start_best(start, value_else):
    """A Validator.score that rates the start kernel 0.9 and every other kernel ``value_else``."""

    def score(self, config):
        return 0.9 if (config.ell_h == start.ell_h and config.ell_z == start.ell_z) else value_else

    return score


def test_a_start_kernel_that_is_already_best_is_written_back_unchanged(tmp_path, capsys, monkeypatch):
    write_drive(tmp_path / "data", "01", frames=14, seed=3)
    start_path, start = _start_file(tmp_path)
    monkeypatch.setattr(validation.Validator, "score", _scores_start_best(start, 0.5))
    out = tmp_path / "k.yaml"
    code = train.main(_train_args(tmp_path, out, "--init", str(start_path), "--epochs", "2", "--lr", "0.05"))
    assert code == 0
    printed = capsys.readouterr().out
    assert "no trained kernel beat the start kernel" in printed
    written = yaml.safe_load(out.read_text())
    given = yaml.safe_load(start_path.read_text())
    assert written["ell_h"] == given["ell_h"] and written["ell_z"] == given["ell_z"]
    assert written["free_ell"] == given["free_ell"] == 0.3


def test_the_best_validated_kernel_is_written_and_free_ell_is_kept_by_default(tmp_path, capsys, monkeypatch):
    write_drive(tmp_path / "data", "01", frames=14, seed=3)
    start_path, start = _start_file(tmp_path)
    scored = []  # (lengths, validation mIoU) of every kernel the trainer validated, in order
    score = validation.Validator.score

    def spy_score(self, config):
        miou = score(self, config)
        scored.append(((list(config.ell_h), list(config.ell_z)), miou))
        return miou

    monkeypatch.setattr(validation.Validator, "score", spy_score)
    out = tmp_path / "k.yaml"
    code = train.main(_train_args(tmp_path, out, "--init", str(start_path), "--epochs", "2", "--lr", "0.05",
                                  "--validate-every", "3"))
    assert code == 0
    printed = capsys.readouterr().out
    # 18 steps validated every 3, after the start: 7 scores, the first the start kernel's.
    assert len(scored) == 7 and scored[0][0] == (start.ell_h, start.ell_z)
    start_miou, (best_lengths, best_miou) = scored[0][1], max(scored[1:], key=lambda entry: entry[1])
    assert best_miou > start_miou  # training on this drive beats the start on the held-out frames
    assert scored[-1][1] < best_miou  # the last kernel is not the best: writing the last would fail below
    written = load_kernel_file(out)
    assert best_lengths != (start.ell_h, start.ell_z)  # the steps moved the lengths
    np.testing.assert_allclose(written.ell_h, best_lengths[0], atol=1e-6)  # the file keeps 6 decimals
    np.testing.assert_allclose(written.ell_z, best_lengths[1], atol=1e-6)
    assert f"validation mIoU: start {start_miou:.4f}, best {best_miou:.4f}" in printed
    assert written.free_ell == pytest.approx(0.3)  # not learned: the start's value
    assert "free_ell: learned" not in printed


def test_free_ell_is_learned_when_asked_and_written(tmp_path, capsys):
    write_drive(tmp_path / "data", "01", frames=14, seed=3)
    start_path, _start = _start_file(tmp_path)
    out = tmp_path / "k.yaml"
    assert train.main(_train_args(tmp_path, out, "--init", str(start_path), "--epochs", "2", "--lr", "0.05",
                                  "--learn-free-ell")) == 0
    line = next(line for line in capsys.readouterr().out.splitlines() if line.startswith("free_ell: learned"))
    learned = float(line.split()[2])
    assert learned != pytest.approx(0.3, abs=1e-3)  # it moved from the start's 0.3 m
    assert "start kernel: 0.3000 m" in line
    assert load_kernel_file(out).free_ell == pytest.approx(learned, abs=1e-4)


@pytest.mark.parametrize("frames", [14, 40, 100, 253])
def test_validation_frames_are_disjoint_from_training_frames(frames):
    training, held_out = validation.split_validation([range(frames)])
    held, used = set(held_out[0]), set(training[0])
    assert held and used and not held & used
    assert len(held) <= validation.VALIDATION_FRAMES
    # No training frame is a neighbour (within the gap) of a validation frame.
    gap = validation.VALIDATION_GAP if frames >= 2 * validation.VALIDATION_BLOCK else 1  # short drives: shorter gap
    assert min(abs(t - v) for t in used for v in held) > gap
    # Validation frames come in blocks of consecutive frames.
    assert len(held) % validation.VALIDATION_BLOCK == 0 or frames % validation.VALIDATION_BLOCK


def test_the_command_trains_and_validates_on_disjoint_frames(tmp_path, capsys, monkeypatch):
    write_drive(tmp_path / "data", "01", frames=14, seed=3)
    trained, validated = set(), set()
    build, frame = samples.SampleBuilder.build, validation.Validator._frame

    def spy_build(self, number, dataset, position):
        trained.add(position)
        return build(self, number, dataset, position)

    def spy_frame(self, number, position):
        validated.add(position)
        return frame(self, number, position)

    monkeypatch.setattr(samples.SampleBuilder, "build", spy_build)
    monkeypatch.setattr(validation.Validator, "_frame", spy_frame)
    assert train.main(_train_args(tmp_path, tmp_path / "k.yaml", "--epochs", "1")) == 0
    assert trained and validated and not trained & validated
    # 14 frames, a short drive: blocks of 3 (the 4th validates), a gap of 1.
    assert validated == {9, 10, 11} and trained == {*range(0, 8), 13}


def test_strict_refuses_in_one_line_when_nothing_beats_the_start(tmp_path, capsys, monkeypatch):
    write_drive(tmp_path / "data", "01", frames=14, seed=3)
    start_path, start = _start_file(tmp_path)
    monkeypatch.setattr(validation.Validator, "score", _scores_start_best(start, 0.9))  # ties do not beat the start
    out = tmp_path / "k.yaml"
    code = train.main(_train_args(tmp_path, out, "--init", str(start_path), "--epochs", "1", "--strict"))
    error = capsys.readouterr().err
    assert code == 2
    assert "no trained kernel beat the start kernel" in error and "--strict" in error
    assert len(error.strip().splitlines()) == 1 and "Traceback" not in error
    assert not out.exists() and not (tmp_path / "k_loss.png").exists()


def test_the_learning_rate_decays_along_a_cosine_to_five_percent():
    total, lr = 200, 0.007
    rates = [trainer.learning_rate(step, total, lr) for step in range(total)]
    assert rates[0] == pytest.approx(lr)
    assert rates[-1] == pytest.approx(trainer.MIN_LR_FRACTION * lr)
    assert all(later <= earlier for earlier, later in itertools.pairwise(rates))
    assert rates[total // 2] == pytest.approx(lr * (0.05 + 0.95 * 0.5 * (1 + np.cos(np.pi * 100 / 199))))


def test_the_optimiser_follows_the_schedule(tmp_path, monkeypatch):
    write_drive(tmp_path / "data", "01", frames=14, seed=3)
    seen = []
    step = trainer.torch.optim.Adam.step

    def spy_step(self, *args, **kwargs):
        seen.append(self.param_groups[0]["lr"])
        return step(self, *args, **kwargs)

    monkeypatch.setattr(trainer.torch.optim.Adam, "step", spy_step)
    assert train.main(_train_args(tmp_path, tmp_path / "k.yaml", "--epochs", "3", "--lr", "0.01")) == 0
    assert len(seen) == 27 and seen[0] == pytest.approx(0.01) and seen[-1] == pytest.approx(0.0005)
    assert all(later <= earlier for earlier, later in itertools.pairwise(seen))


def test_only_classes_under_the_point_floor_are_kept():
    counts = np.array([0, 40, 50, 0, 1000, 49])
    assert trainer.kept_classes(counts, 50, ignore=[0]).tolist() == [1, 3, 5]
    assert trainer.kept_classes(counts, 0, ignore=[0]).tolist() == []
    weights = objective.class_weights(counts)
    assert weights[0] == weights[3] == 0 and weights[1] > weights[2] > weights[4] > 0
    assert weights[weights > 0].mean() == pytest.approx(1.0)


def test_a_class_under_the_point_floor_keeps_its_start_lengths_while_the_others_learn(tmp_path):
    write_drive(tmp_path / "data", "01", frames=8, seed=3)
    dataset = trainer.SemanticKittiSequence(tmp_path / "data", "01")
    counts = objective.class_counts([dataset], [range(8)], 20, dataset.label_map.ignore_classes)
    present = np.flatnonzero(counts)
    assert len(present) >= 3
    floor = int(np.sort(counts[present])[len(present) // 2])  # about half the classes fall under it
    _path, start = _start_file(tmp_path)
    result = trainer.train_kernel([dataset], [range(8)], "compound", frames_per_sample=3, epochs=2, lr=0.05,
                                  start=start, min_class_points=floor)
    kept = set(result.kept_classes)
    assert kept == set(np.flatnonzero(counts < floor)) - {0}
    learned = [c for c in present if c not in kept]
    assert kept and learned
    for c in kept:  # exactly the start's lengths (held as float32)
        assert result.config.ell_h[c] == float(np.float32(start.ell_h[c]))
        assert result.config.ell_z[c] == float(np.float32(start.ell_z[c]))
    moved = [c for c in learned if abs(result.config.ell_h[c] - start.ell_h[c]) > 1e-3]
    assert moved  # the others learned


def test_the_point_floor_is_given_on_the_command_line_and_reported(tmp_path, capsys):
    write_drive(tmp_path / "data", "01", frames=14, seed=3)
    out = tmp_path / "k.yaml"
    assert train.main(_train_args(tmp_path, out, "--epochs", "1", "--min-class-points", "0")) == 0
    assert "kept at the start" not in capsys.readouterr().out
    assert train.main(_train_args(tmp_path, out, "--epochs", "1", "--min-class-points", "10000000")) == 0
    line = next(line for line in capsys.readouterr().out.splitlines() if line.startswith("kept at the start"))
    assert "under 10000000 ground-truth points" in line and "road" in line
    assert train.main(_train_args(tmp_path, out, "--epochs", "1")) == 0  # labels: the default floor
    line = next(line for line in capsys.readouterr().out.splitlines() if line.startswith("kept at the start"))
    assert f"under {trainer.MIN_CLASS_POINTS} ground-truth points" in line

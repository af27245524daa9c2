"""The synthetic SemanticKITTI drive generator (``synth``, convbki_core.tools.synth / convbki_core.synth).

Drives here are short (2-8 scans) and mostly low-resolution (--azimuth-steps) so the file stays
quick on two cores; one full-size scan checks the ~120k point count. Movers: test_synth_movers.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from convbki_core.io.labels import load_label_map
from convbki_core.measures.metrics import ConfusionMatrix
from convbki_core.synth.drive import DriveConfig, generate_drive, lidar_poses
from convbki_core.synth.scene import build_scene
from convbki_core.tools.synth import main

LABELS = load_label_map()
VALID_RAW = {int(r) for r in np.flatnonzero(LABELS.learning_map)} | {0, 1}  # mapped ids, unlabeled, outlier


def _drive(root: Path, **kw) -> Path:
    config = DriveConfig(out=root, **kw)
    generate_drive(config)
    return root / "sequences" / config.sequence


def _calib_tr(seq: Path) -> np.ndarray:
    for line in (seq / "calib.txt").read_text().splitlines():
        if line.startswith("Tr:"):
            tr = np.eye(4)
            tr[:3, :4] = np.array(line.split()[1:], float).reshape(3, 4)
            return tr
    raise AssertionError("no Tr in calib.txt")


def _lidar_poses(seq: Path) -> np.ndarray:
    """LiDAR poses in the map frame from poses.txt + calib.txt: inv(Tr) @ P @ Tr."""
    tr = _calib_tr(seq)
    rows = np.loadtxt(seq / "poses.txt", ndmin=2).reshape(-1, 3, 4)
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :4] = rows
    return np.linalg.inv(tr) @ poses @ tr


def _scan(seq: Path, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Map-frame points, remission, ground-truth and predicted learning ids of scan k."""
    cloud = np.fromfile(seq / "velodyne" / f"{k:06d}.bin", np.float32).reshape(-1, 4)
    pose = _lidar_poses(seq)[k]
    points = cloud[:, :3].astype(np.float64) @ pose[:3, :3].T + pose[:3, 3]
    truth = LABELS.to_learning(np.fromfile(seq / "labels" / f"{k:06d}.label", np.uint32))
    pred = LABELS.to_learning(np.fromfile(seq / "predictions" / f"{k:06d}.label", np.uint32))
    return points, cloud[:, 3], truth, pred


@pytest.fixture(scope="module")
def small(tmp_path_factory) -> Path:
    """Seed 0, 8 low-resolution scans with probabilities, noise calibrated to mIoU 0.55."""
    return _drive(tmp_path_factory.mktemp("small"), frames=8, seed=0, azimuth_steps=512, probabilities=True)


def test_files_and_counts(small):
    frames = len((small / "times.txt").read_text().split())
    assert frames == 8
    for k in range(frames):
        cloud = np.fromfile(small / "velodyne" / f"{k:06d}.bin", np.float32).reshape(-1, 4)
        labels = np.fromfile(small / "labels" / f"{k:06d}.label", np.uint32)
        preds = np.fromfile(small / "predictions" / f"{k:06d}.label", np.uint32)
        probs = np.load(small / "probabilities" / f"{k:06d}.npy")
        assert len(cloud) == len(labels) == len(preds) == len(probs) > 20000
        assert probs.dtype == np.float16 and probs.shape[1] == LABELS.num_classes
        assert np.all(np.isfinite(cloud)) and cloud[:, 3].min() >= 0.0 and cloud[:, 3].max() <= 1.0
        assert set(np.unique(labels & 0xFFFF).tolist()) <= VALID_RAW
        assert set(np.unique(preds & 0xFFFF).tolist()) <= VALID_RAW
        assert np.any(labels >> 16) and not np.any(preds >> 16)  # instances in the truth only
        np.testing.assert_array_equal(np.argmax(probs, 1), LABELS.to_learning(preds))
        np.testing.assert_allclose(probs.astype(np.float32).sum(1), 1.0, atol=0.02)
        truth = LABELS.to_learning(labels)
        assert np.mean(truth == 0) < 0.01  # class 0 only for the few outliers
    times = np.loadtxt(small / "times.txt")
    np.testing.assert_allclose(np.diff(times), 0.1, atol=1e-9)
    assert (small / "synth.yaml").is_file()


def test_poses_round_trip_and_not_identity(small, tmp_path):
    written = _lidar_poses(small)
    own = lidar_poses(DriveConfig(out=tmp_path, frames=8, seed=0, azimuth_steps=512))
    np.testing.assert_allclose(written, own, atol=1e-6)
    assert not np.allclose(written[0], np.eye(4), atol=1e-3)
    # Rigid, and the car moves forward at city speed, 0.1 s apart.
    np.testing.assert_allclose(written[:, :3, :3] @ written[:, :3, :3].transpose(0, 2, 1),
                               np.broadcast_to(np.eye(3), (8, 3, 3)), atol=1e-9)
    steps = np.linalg.norm(np.diff(written[:, :3, 3], axis=0), axis=1)
    assert np.all((steps > 0.2) & (steps < 1.2))


def test_static_points_land_on_each_other(tmp_path):
    """Solid upright surfaces (walls, vehicles, trunks, poles) of scan 0 and scan 1, moved into
    the map frame, coincide to a few cm (no range noise here); a 0.3 m pose error would show.
    (Ground rings and porous foliage are not resampled at the same places, so they are left out.)"""
    seq = _drive(tmp_path, frames=2, seed=0, range_noise=0.0, noise_strength=0.0)
    solid = [LABELS.class_names.index(n) for n in ("car", "truck", "other-vehicle", "building", "trunk", "pole")]
    (a, _, ta, _), (b, _, tb, _) = _scan(seq, 0), _scan(seq, 1)
    poses = _lidar_poses(seq)
    near_a = (np.linalg.norm(a - poses[0, :3, 3], axis=1) < 25) & np.isin(ta, solid)
    near_b = (np.linalg.norm(b - poses[1, :3, 3], axis=1) < 30) & np.isin(tb, solid)
    query = torch.from_numpy(a[near_a][:: max(1, int(near_a.sum()) // 2000)])
    ref = torch.from_numpy(b[near_b])
    assert len(query) > 500

    def nearest(ref: torch.Tensor) -> np.ndarray:
        return torch.cat([torch.cdist(query[i:i + 500], ref).min(1).values for i in range(0, len(query), 500)]).numpy()

    good = nearest(ref)
    shifted = nearest(ref + torch.tensor([0.3, 0.0, 0.0], dtype=ref.dtype))
    assert np.median(good) < 0.04 and np.percentile(good, 90) < 0.1
    assert np.median(shifted) > 3 * np.median(good)


def test_errors_persist_across_scans(small):
    """Where scans 0 and 1 see the same 0.2 m world voxel (same true class), a wrong prediction
    in scan 0 is repeated in scan 1 far more often than independent noise would repeat it."""
    (a, _, ta, pa), (b, _, tb, pb) = _scan(small, 0), _scan(small, 1)

    def first_per_voxel(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        keys, index = np.unique(np.floor(points / 0.2).astype(np.int64), axis=0, return_index=True)
        return keys, index

    ka, ia = first_per_voxel(a)
    kb, ib = first_per_voxel(b)
    both = np.concatenate([ka, kb])
    _, inverse, counts = np.unique(both, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    in_b = {int(v): int(i) for v, i in zip(inverse[len(ka):], ib)}
    pairs = np.array([(i, in_b[int(v)]) for v, i in zip(inverse[: len(ka)], ia) if counts[v] == 2])
    i, j = pairs[:, 0], pairs[:, 1]
    same = (ta[i] == tb[j]) & (ta[i] > 0)
    i, j = i[same], j[same]
    wrong = pa[i] != ta[i]
    error_rate = float(np.mean(pb[tb > 0] != tb[tb > 0]))
    repeated = float(np.mean(pb[j][wrong] == pa[i][wrong]))
    assert wrong.sum() > 200 and 0.05 < error_rate < 0.4
    # Independent noise repeats a given wrong class with probability below the error rate.
    assert repeated > 0.45 and repeated > 3 * error_rate


def test_input_miou_meets_target(small):
    matrix = ConfusionMatrix(LABELS.num_classes)
    for k in range(8):
        _, _, truth, pred = _scan(small, k)
        matrix.add(truth, pred)
    assert abs(matrix.miou() - 0.55) < 0.04
    # Many classes, as in a real street: at least 16 of the 19 in eight scans.
    assert matrix.present.sum() >= 16


def test_strength_orders_miou_and_range_matters(tmp_path):
    """More strength, lower mIoU; and errors grow with range."""
    seq = _drive(tmp_path / "a", frames=2, seed=1, azimuth_steps=360, noise_strength=0.3)
    weak = ConfusionMatrix(LABELS.num_classes)
    near_err, far_err = [], []
    for k in range(2):
        points, _, truth, pred = _scan(seq, k)
        weak.add(truth, pred)
        rng = np.linalg.norm(points - _lidar_poses(seq)[k, :3, 3], axis=1)
        ok = truth > 0
        near_err.append(np.mean(pred[ok & (rng < 15)] != truth[ok & (rng < 15)]))
        far_err.append(np.mean(pred[ok & (rng > 40)] != truth[ok & (rng > 40)]))
    seq = _drive(tmp_path / "b", frames=2, seed=1, azimuth_steps=360, noise_strength=1.5)
    strong = ConfusionMatrix(LABELS.num_classes)
    for k in range(2):
        _, _, truth, pred = _scan(seq, k)
        strong.add(truth, pred)
    assert strong.miou() < weak.miou() - 0.1
    assert np.mean(far_err) > 1.5 * np.mean(near_err)


def test_deterministic_and_seed_dependent(small, tmp_path):
    again = _drive(tmp_path / "again", frames=8, seed=0, azimuth_steps=512, probabilities=True)
    for path in sorted(small.rglob("*")):
        if path.is_file():
            assert (again / path.relative_to(small)).read_bytes() == path.read_bytes(), path.name
    a, b = build_scene(0), build_scene(1)
    assert a.param.shape != b.param.shape or not np.allclose(a.param, b.param)
    assert a.route.length != b.route.length or not np.array_equal(a.ground_raw, b.ground_raw)


def test_full_size_scan(tmp_path):
    """One full-resolution scan: about 120k points (64 beams x 2083 columns, minus misses and ego body)."""
    seq = _drive(tmp_path, frames=1, seed=2, noise_strength=0.4)
    cloud = np.fromfile(seq / "velodyne" / "000000.bin", np.float32).reshape(-1, 4)
    assert 100_000 < len(cloud) < 135_000
    r = np.linalg.norm(cloud[:, :3], axis=1)
    assert r.max() <= 90.5 and np.median(r) < 30
    elevation = np.degrees(np.arcsin(cloud[:, 2] / r))
    assert np.percentile(elevation, 0.5) > -25.5 and np.percentile(elevation, 99.5) < 2.5


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "convbki_core.tools.synth", *args], capture_output=True, text=True,
                          timeout=120)


@pytest.mark.parametrize("args", [
    ["--frames", "0"],
    ["--input-miou", "1.5"],
    ["--beams", "65"],
    ["--sequence", "x1"],
    ["--speed", "-3"],
])
def test_cli_bad_arguments(tmp_path, args, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["--out", str(tmp_path), *args])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("synth: error:") and "\n" not in err


def test_cli_refuses_non_empty_folder_and_writes(tmp_path):
    run = _cli("--out", str(tmp_path), "--frames", "2", "--azimuth-steps", "256", "--quiet")
    assert run.returncode == 0, run.stderr
    run = _cli("--out", str(tmp_path), "--frames", "2", "--azimuth-steps", "256")
    assert run.returncode == 2
    assert run.stderr.strip().count("\n") == 0 and "--force" in run.stderr and "Traceback" not in run.stderr
    run = _cli("--out", str(tmp_path), "--frames", "1", "--azimuth-steps", "256", "--force")
    assert run.returncode == 0, run.stderr
    assert "input mIoU" in run.stdout
    seq = tmp_path / "sequences" / "00"
    assert sorted(p.name for p in (seq / "velodyne").iterdir()) == ["000000.bin"]  # stale scan removed
    assert len(np.loadtxt(seq / "poses.txt", ndmin=2)) == 1
    assert "--input-miou" in _cli("--help").stdout

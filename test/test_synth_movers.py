"""Movers in the synthetic drive (``synth --movers``): labels, geometry, noise, sidecar, and the
default (no movers) drive left as it was.

Drives here are short (2-12 scans) and low-resolution (--azimuth-steps) so the file stays quick
on two cores.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from convbki_core.datasets.labels import load_label_map
from convbki_core.synth.drive import DriveConfig, _traffic, generate_drive
from convbki_core.synth.movers import MOVING_RAW, load_sidecar
from convbki_core.synth.primitives import obb_distance
from convbki_core.synth.scene import MOVABLE_RAW, build_scene
from convbki_core.tools.synth import main

LABELS = load_label_map()
MOVING = np.array(list(MOVING_RAW))
OUTLIER = 1
RANGE_NOISE = 0.02  # m, the drives' default
FRAMES = 12


def _drive(root: Path, **kw) -> Path:
    config = DriveConfig(out=root, **kw)
    generate_drive(config)
    return root / "sequences" / config.sequence


def _lidar_poses(seq: Path) -> np.ndarray:
    """LiDAR poses in the map frame from poses.txt + calib.txt: inv(Tr) @ P @ Tr."""
    tr = np.eye(4)
    for line in (seq / "calib.txt").read_text().splitlines():
        if line.startswith("Tr:"):
            tr[:3, :4] = np.array(line.split()[1:], float).reshape(3, 4)
    rows = np.loadtxt(seq / "poses.txt", ndmin=2).reshape(-1, 3, 4)
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :4] = rows
    return np.linalg.inv(tr) @ poses @ tr


def _scan(seq: Path, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Map-frame points, ground-truth label words and predicted label words of scan k."""
    cloud = np.fromfile(seq / "velodyne" / f"{k:06d}.bin", np.float32).reshape(-1, 4)
    pose = _lidar_poses(seq)[k]
    points = cloud[:, :3].astype(np.float64) @ pose[:3, :3].T + pose[:3, 3]
    labels = np.fromfile(seq / "labels" / f"{k:06d}.label", np.uint32)
    preds = np.fromfile(seq / "predictions" / f"{k:06d}.label", np.uint32)
    return points, labels, preds


def _box_excess(points: np.ndarray, mover: dict, k: int) -> np.ndarray:
    """How far (m) each point lies outside mover's box in scan k (negative: inside, by that much)."""
    x, y, z, yaw = mover["poses"][k - mover["first_frame"]]
    d = points - np.array([x, y, z])
    c, s = np.cos(yaw), np.sin(yaw)
    local = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]], 1)
    return np.max(np.abs(local) - np.array(mover["size"]) / 2, axis=1)


def _present(mover: dict, k: int) -> bool:
    return mover["first_frame"] <= k <= mover["last_frame"]


@pytest.fixture(scope="module")
def moving(tmp_path_factory) -> Path:
    """Seed 0, 12 low-resolution scans, 10 movers, fixed noise strength."""
    return _drive(tmp_path_factory.mktemp("movers"), frames=FRAMES, seed=0, azimuth_steps=512,
                  noise_strength=0.5, movers=10)


def test_sidecar_format(moving):
    side = load_sidecar(moving)
    assert side["format"] == "convbki-synth-movers" and side["frame"] == "map" and side["frames"] == FRAMES
    movers = side["movers"]
    assert len(movers) == 10
    assert len({m["instance"] for m in movers}) == len(movers) and all(0 < m["instance"] < 2 ** 16 for m in movers)
    for m in movers:
        assert m["raw"] in MOVING_RAW and m["class"].startswith("moving-")
        assert 0 <= m["first_frame"] <= m["last_frame"] < FRAMES
        assert np.shape(m["poses"]) == (m["last_frame"] - m["first_frame"] + 1, 4)
        assert np.all(np.asarray(m["size"]) > 0.2)
    kinds = {m["class"] for m in movers}
    assert "moving-car" in kinds
    assert kinds & {"moving-person", "moving-bicyclist"} and kinds & {"moving-truck", "moving-bus"}
    # The drive's record says the same.
    assert "movers:" in (moving / "synth.yaml").read_text()


def test_moving_labels_and_instances(moving):
    movers = {m["instance"]: m for m in load_sidecar(moving)["movers"]}
    seen: dict[int, int] = {}
    static_instances: set[int] = set()
    for k in range(FRAMES):
        _, labels, _ = _scan(moving, k)
        raw, instance = labels & 0xFFFF, labels >> 16
        is_moving = np.isin(raw, MOVING)
        assert np.all(instance[is_moving] > 0)
        for inst in np.unique(instance[is_moving]):
            mover = movers[int(inst)]
            assert _present(mover, k)
            assert np.all(raw[is_moving & (instance == inst)] == mover["raw"])
            seen[int(inst)] = seen.get(int(inst), 0) + 1
        static_instances |= set(np.unique(instance[~is_moving]).tolist())
    assert not static_instances & set(movers)  # mover instance ids are their own
    # Movers are seen scan after scan, not in a single glimpse.
    assert len(seen) >= 6 and sum(n >= FRAMES // 2 for n in seen.values()) >= 4
    assert {movers[i]["raw"] for i in seen} >= {252}


def test_mover_points_lie_in_their_box(moving):
    side = load_sidecar(moving)["movers"]
    worst, checked = -np.inf, 0
    for k in range(FRAMES):
        points, labels, _ = _scan(moving, k)
        for m in side:
            mine = (labels >> 16) == m["instance"]
            if mine.any():
                worst = max(worst, float(_box_excess(points[mine], m, k).max()))
                checked += int(mine.sum())
    assert checked > 1000
    assert worst < 6 * RANGE_NOISE  # up to the range noise


def test_static_points_are_not_moving(moving):
    """No point of the static scene is labelled moving, and none lies inside a mover's box (shrunk by
    0.2 m: the ground under a car touches its box) except the spurious returns (outliers)."""
    side = load_sidecar(moving)["movers"]
    for k in range(FRAMES):
        points, labels, _ = _scan(moving, k)
        raw = labels & 0xFFFF
        static = ~np.isin(raw, MOVING)
        near = np.full(len(points), np.inf)
        for m in side:
            if _present(m, k):
                near = np.minimum(near, _box_excess(points, m, k))
        assert not np.any(np.isin(raw, MOVING) & (near > 6 * RANGE_NOISE))
        assert not np.any(static & (raw != OUTLIER) & (near < -0.2))


def test_predictions_use_static_classes(moving):
    """The noisy input labels movers with the static class id (car 10 for moving-car 252), with
    segmentation noise on them as on everything else."""
    agree, total = 0, 0
    for k in range(FRAMES):
        _, labels, preds = _scan(moving, k)
        raw, pred = labels & 0xFFFF, preds & 0xFFFF
        assert pred.max() < MOVING.min() and not np.any(preds >> 16)
        is_moving = np.isin(raw, MOVING)
        static_equivalent = LABELS.to_raw(LABELS.to_learning(raw[is_moving]))
        assert set(np.unique(static_equivalent).tolist()) <= {10, 18, 20, 30, 31, 32}
        agree += int(np.sum(pred[is_moving] == static_equivalent))
        total += int(is_moving.sum())
    assert total > 1000 and 0.5 < agree / total < 0.995


def test_swept_space_has_no_static_objects():
    """Where a mover's box passes (every scan), no static object stands lower than its top, and
    parked vehicles, people and bicycles keep well clear (else a map would show them as trail)."""
    config = DriveConfig(out=Path("unused"), frames=30, seed=0, movers=10)  # has parked cars near a mover
    scene = build_scene(config.seed, _traffic(config))
    assert len(scene.movers) == 10
    objects = scene.instance > 0
    bottom = scene.param[:, 2] - scene.param[:, 5]
    reach = np.abs(scene.param[:, 3:5]).sum(1)
    for m in scene.movers:
        first, last = m.frames
        half = m.template.size[:2] / 2
        # The box outline, 0.1 m apart, at each scan.
        u = np.linspace(-1, 1, 2 + int(2 * half.max() / 0.1))
        outline = np.concatenate([np.stack([u, np.full_like(u, s)], 1) for s in (-1, 1)]
                                 + [np.stack([np.full_like(u, s), u], 1) for s in (-1, 1)]) * half
        for x, y, z0, yaw in m.pose[first:last + 1]:
            c, s = np.cos(yaw), np.sin(yaw)
            pts = outline @ np.array([[c, s], [-s, c]]) + [x, y]
            near = objects & (np.hypot(scene.param[:, 0] - x, scene.param[:, 1] - y) < reach + half.sum() + 2)
            near &= bottom < z0 + m.template.size[2]
            for q in np.flatnonzero(near):
                clear = 0.5 if int(scene.raw[q]) in MOVABLE_RAW else 0.05
                assert obb_distance(pts, scene.param[q], int(scene.kind[q])).min() > clear
                # The outline does not see a primitive wholly inside the box: test its centre too.
                centre = np.array([[scene.param[q, 0] - x, scene.param[q, 1] - y]]) @ np.array([[c, -s], [s, c]])
                assert np.any(np.abs(centre[0]) > half)
    # Static objects are dropped only where movers go: most of the scene stays.
    assert objects.sum() > 0.97 * (build_scene(config.seed).instance > 0).sum()


def test_deterministic_with_movers(moving, tmp_path):
    again = _drive(tmp_path, frames=FRAMES, seed=0, azimuth_steps=512, noise_strength=0.5, movers=10)
    for path in sorted(moving.rglob("*")):
        if path.is_file():
            assert (again / path.relative_to(moving)).read_bytes() == path.read_bytes(), path.name


def test_no_movers_by_default(tmp_path):
    """--movers 0 writes exactly what a run without the option writes: no moving ids, no sidecar."""
    base = ["--frames", "3", "--azimuth-steps", "256", "--beams", "32", "--noise-strength", "0.3", "--quiet"]
    assert main(["--out", str(tmp_path / "plain"), *base]) == 0
    assert main(["--out", str(tmp_path / "zero"), *base, "--movers", "0"]) == 0
    plain, zero = tmp_path / "plain" / "sequences" / "00", tmp_path / "zero" / "sequences" / "00"
    files = sorted(p.relative_to(plain) for p in plain.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(zero) for p in zero.rglob("*") if p.is_file())
    for name in files:
        assert (plain / name).read_bytes() == (zero / name).read_bytes(), name
    assert not (plain / "movers.json").exists() and load_sidecar(plain) is None
    assert "movers" not in (plain / "synth.yaml").read_text()
    for k in range(3):
        labels = np.fromfile(plain / "labels" / f"{k:06d}.label", np.uint32)
        assert not np.any(np.isin(labels & 0xFFFF, MOVING))


@pytest.mark.parametrize("value", ["-1", "x", "2.5", "1001"])
def test_cli_bad_movers(tmp_path, value, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["--out", str(tmp_path), "--movers", value])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("synth: error:") and "--movers" in err and "\n" not in err


def test_cli_summary_and_record(tmp_path, capsys):
    assert main(["--out", str(tmp_path), "--frames", "2", "--azimuth-steps", "256", "--beams", "32",
                 "--noise-strength", "0.3", "--movers", "3"]) == 0
    out = capsys.readouterr().out
    assert "movers:" in out and "moving points/frame" in out
    seq = tmp_path / "sequences" / "00"
    record = json.loads((seq / "movers.json").read_text())
    assert 1 <= len(record["movers"]) <= 3

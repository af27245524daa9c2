"""Movers in the synthetic drive (``synth --movers``): labels, geometry, noise, sidecar, the
varied traffic (``--traffic varied``), moving labels in the predictions (``--moving-labels``),
and the default drives (no movers, classic traffic, static predictions) left as they were.

Drives here are short and low-resolution (--azimuth-steps, --beams) so the file stays quick on
two cores; the varied traffic's behaviours are checked on the plan alone (no scans), which is
cheap for a drive long enough to show whole stops.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from convbki_core.io.labels import load_label_map
from convbki_core.synth import traffic, traffic_planner, traffic_varied
from convbki_core.synth.drive import DriveConfig, _traffic, generate_drive
from convbki_core.synth.lidar import EGO_BOXES
from convbki_core.synth.movers import MOVING_RAW, load_sidecar
from convbki_core.synth.primitives import obb_distance
from convbki_core.synth.route import drive
from convbki_core.synth.scene import MOVABLE_RAW, build_scene
from convbki_core.tools.synth import TRAFFIC_CHOICES, main

LABELS = load_label_map()
MOVING = np.array(list(MOVING_RAW))
OUTLIER = 1
RANGE_NOISE = 0.02  # m, the drives' default
FRAMES = 12
NEW_BEHAVIOURS = ("stop-and-go", "kerb-cyclist", "close-pass", "sidewalk-pause")
# A plan of the varied traffic with every new behaviour in it (found by trying seeds).
VARIED = {"frames": 120, "seed": 3, "movers": 16}
TINY = ["--azimuth-steps", "256", "--beams", "32", "--noise-strength", "0.3", "--quiet"]


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


def _assert_clear(scene, mover, pose) -> None:
    """No static object stands lower than the top of ``mover``'s box at ``pose`` (x, y, z0, yaw)
    in its footprint, and parked vehicles, people and bicycles keep well clear of it (else a
    map would show them as trail)."""
    objects = scene.instance > 0
    bottom = scene.param[:, 2] - scene.param[:, 5]
    reach = np.abs(scene.param[:, 3:5]).sum(1)
    half = mover.template.size[:2] / 2
    # The box outline, 0.1 m apart.
    u = np.linspace(-1, 1, 2 + int(2 * half.max() / 0.1))
    outline = np.concatenate([np.stack([u, np.full_like(u, s)], 1) for s in (-1, 1)]
                             + [np.stack([np.full_like(u, s), u], 1) for s in (-1, 1)]) * half
    x, y, z0, yaw = pose
    c, s = np.cos(yaw), np.sin(yaw)
    pts = outline @ np.array([[c, s], [-s, c]]) + [x, y]
    near = objects & (np.hypot(scene.param[:, 0] - x, scene.param[:, 1] - y) < reach + half.sum() + 2)
    near &= bottom < z0 + mover.template.size[2]
    for q in np.flatnonzero(near):
        clear = 0.5 if int(scene.raw[q]) in MOVABLE_RAW else 0.05
        assert obb_distance(pts, scene.param[q], int(scene.kind[q])).min() > clear
        # The outline does not see a primitive wholly inside the box: test its centre too.
        centre = np.array([[scene.param[q, 0] - x, scene.param[q, 1] - y]]) @ np.array([[c, -s], [s, c]])
        assert np.any(np.abs(centre[0]) > half)


def test_swept_space_has_no_static_objects():
    """Where a mover's box passes (every scan), no static object stands in its way."""
    config = DriveConfig(out=Path("unused"), frames=30, seed=0, movers=10)  # has parked cars near a mover
    scene = build_scene(config.seed, _traffic(config))
    assert len(scene.movers) == 10
    for m in scene.movers:
        first, last = m.frames
        for pose in m.pose[first:last + 1]:
            _assert_clear(scene, m, pose)
    # Static objects are dropped only where movers go: most of the scene stays.
    assert (scene.instance > 0).sum() > 0.97 * (build_scene(config.seed).instance > 0).sum()


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


# ---- the varied traffic --------------------------------------------------------------------------
@pytest.fixture(scope="module")
def varied():
    """The scene of a varied-traffic plan (no scans) and the ego vehicle's trajectory in it."""
    config = DriveConfig(out=Path("unused"), traffic="varied", **VARIED)
    scene = build_scene(config.seed, _traffic(config))
    ego = drive(scene.route, config.frames, config.speed, scene.start_s, np.random.default_rng([config.seed, 0xD21]))
    return scene, ego


def _shown(mover) -> np.ndarray:
    """The poses of the scans a mover is in."""
    first, last = mover.frames
    return mover.pose[first:last + 1]


def _still_runs(poses: np.ndarray) -> list[tuple[int, int]]:
    """(first, last) index of each run of two or more identical consecutive poses."""
    same = np.all(poses[1:] == poses[:-1], axis=1)
    runs, start = [], None
    for k, s in enumerate(np.append(same, False)):
        if s and start is None:
            start = k
        elif not s and start is not None:
            runs.append((start, k))
            start = None
    return runs


def _corners(centre, yaw: float, half) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[1, 1], [1, -1], [-1, -1], [-1, 1]]) * half @ np.array([[c, s], [-s, c]]) + centre


def _vertex_to_edges(points: np.ndarray, polygon: np.ndarray) -> float:
    e0, d = polygon, np.roll(polygon, -1, 0) - polygon
    t = np.clip(((points[:, None] - e0) * d).sum(-1) / (d * d).sum(-1), 0, 1)
    return float(np.linalg.norm(points[:, None] - (e0 + t[..., None] * d), axis=-1).min())


def _box_gap(ca, yaw_a: float, half_a, cb, yaw_b: float, half_b) -> float:
    """Distance (m) between two oriented rectangles (0 when they overlap)."""
    a, b = _corners(ca, yaw_a, half_a), _corners(cb, yaw_b, half_b)
    axes = [np.array([np.cos(y), np.sin(y)]) for y in (yaw_a, yaw_a + np.pi / 2, yaw_b, yaw_b + np.pi / 2)]
    if all((a @ u).max() >= (b @ u).min() and (b @ u).max() >= (a @ u).min() for u in axes):
        return 0.0
    return min(_vertex_to_edges(a, b), _vertex_to_edges(b, a))


def _gaps_to_ego(mover, ego) -> np.ndarray:
    """Gap (m) between the mover's box and the ego vehicle's body in each scan it is in, near it."""
    body = EGO_BOXES[0]
    ego_half = np.array([body[1] - body[0], body[3] - body[2]]) / 2
    gaps = []
    for k in range(mover.frames[0], mover.frames[1] + 1):
        yaw = np.arctan2(ego.poses[k, 1, 0], ego.poses[k, 0, 0])
        centre = ego.poses[k, :2, 3] + np.array([np.cos(yaw), np.sin(yaw)]) * (body[0] + body[1]) / 2
        x, y, _, m_yaw = mover.pose[k]
        if np.hypot(x - centre[0], y - centre[1]) < 25:
            gaps.append(_box_gap(centre, yaw, ego_half, (x, y), m_yaw, mover.template.size[:2] / 2))
    return np.array(gaps)


def test_cli_traffic_choices_are_the_planners():
    assert tuple(traffic.TRAFFIC) == TRAFFIC_CHOICES and TRAFFIC_CHOICES[0] == "classic"
    assert set(traffic_planner.BEHAVIOURS) < set(traffic_varied.VARIED_BEHAVIOURS)
    assert set(traffic_varied.VARIED_BEHAVIOURS) - set(traffic_planner.BEHAVIOURS) == set(NEW_BEHAVIOURS)


def test_classic_traffic_is_the_default(tmp_path):
    """--traffic classic writes what a run without the option writes, byte for byte, and its
    record does not mention the option (nor --moving-labels)."""
    base = ["--frames", "3", "--seed", "4", "--movers", "6", *TINY]
    assert main(["--out", str(tmp_path / "plain"), *base]) == 0
    assert main(["--out", str(tmp_path / "classic"), *base, "--traffic", "classic"]) == 0

    def hashes(root: Path) -> dict[str, str]:
        seq = root / "sequences" / "00"
        return {str(p.relative_to(seq)): hashlib.sha256(p.read_bytes()).hexdigest()
                for p in sorted(seq.rglob("*")) if p.is_file()}

    plain = hashes(tmp_path / "plain")
    assert "movers.json" in plain and len(plain) == 3 * 3 + 5
    assert plain == hashes(tmp_path / "classic")
    record = yaml.safe_load((tmp_path / "plain" / "sequences" / "00" / "synth.yaml").read_text())
    assert "moving_labels" not in record and "traffic" not in record["movers"]
    assert list(record["movers"]["behaviours"]) == list(traffic_planner.BEHAVIOURS)


def test_varied_traffic_has_every_behaviour(varied):
    scene, _ = varied
    behaviours = {m.behaviour for m in scene.movers}
    assert behaviours >= set(NEW_BEHAVIOURS)
    assert behaviours <= set(traffic_varied.VARIED_BEHAVIOURS)
    assert behaviours & set(traffic_planner.BEHAVIOURS)  # the classic behaviours are still drawn
    kinds = {b: {m.kind for m in scene.movers if m.behaviour == b} for b in NEW_BEHAVIOURS}
    assert kinds["stop-and-go"] <= {"car", "truck", "bus"} and kinds["kerb-cyclist"] == {"bicyclist"}
    assert kinds["sidewalk-pause"] == {"person"} and "bicyclist" not in kinds["close-pass"]


def test_stop_and_go_stands_still_then_drives_on(varied):
    """A stop-and-go vehicle (a pausing pedestrian) holds one pose for a whole stop, and moves
    in the scans before it and after it."""
    scene, _ = varied
    checked = 0
    for m in scene.movers:
        if m.behaviour not in ("stop-and-go", "sidewalk-pause"):
            continue
        poses = _shown(m)
        runs = _still_runs(poses)
        assert len(runs) == 1
        first, last = runs[0]
        low, high = traffic_varied.STOP_SCANS if m.behaviour == "stop-and-go" else traffic_varied.PAUSE_SCANS
        assert low <= last - first + 1 <= high + 1
        assert first >= 10 and last <= len(poses) - 11  # some motion shown on either side
        stop = poses[first, :2]
        assert np.linalg.norm(poses[first - 10, :2] - stop) > 0.2
        assert np.linalg.norm(poses[last + 10, :2] - stop) > 0.2
        speed = np.linalg.norm(np.diff(poses[:, :2], axis=0), axis=1) / 0.1
        top = traffic_planner.VEHICLES[m.kind][2][1] if m.kind != "person" else traffic_planner.WALK_SPEED[1]
        assert speed.max() <= top + 1e-6 and speed[:first].min() > 0 and speed[last:].min() > 0
        checked += m.behaviour == "stop-and-go"
    assert checked >= 1


def test_kerb_cyclist_is_slow_and_steady(varied):
    scene, _ = varied
    cyclists = [m for m in scene.movers if m.behaviour == "kerb-cyclist"]
    assert cyclists
    for m in cyclists:
        poses = _shown(m)
        speed = np.linalg.norm(np.diff(poses[:, :2], axis=0), axis=1) / 0.1
        low, high = traffic_varied.KERB_CYCLIST_SPEED
        assert low - 1e-6 <= speed.min() <= speed.max() <= high + 1e-6
        assert np.ptp(poses[:, 3]) == 0  # straight along its street


def test_movers_keep_clear_of_the_ego_vehicle(varied):
    """A close pass comes within the drawn gap of the ego vehicle's box, no mover within its margin."""
    scene, ego = varied
    nearest = {}
    for m in scene.movers:
        gaps = _gaps_to_ego(m, ego)
        if len(gaps):
            assert gaps.min() >= traffic_planner.EGO_MARGIN - 0.05  # per scan; the planner checks finer steps
            nearest.setdefault(m.behaviour, []).append(gaps.min())
    close = nearest["close-pass"]
    low, high = traffic_varied.CLOSE_PASS_GAP
    assert close and all(low - 0.05 <= g <= high + 0.05 for g in close)


def test_stops_are_swept_space(varied):
    """Where a mover stands still, the scene has no static object in its way either."""
    scene, _ = varied
    swept = traffic.swept_height([m for m in scene.movers if m.behaviour in ("stop-and-go", "sidewalk-pause")],
                                 scene.raster)
    for m in scene.movers:
        if m.behaviour in ("stop-and-go", "sidewalk-pause"):
            poses = _shown(m)
            first, _ = _still_runs(poses)[0]
            x, y, z0, _ = poses[first]
            ix, iy = int((x - scene.raster.x0) / scene.raster.res), int((y - scene.raster.y0) / scene.raster.res)
            assert swept[iy, ix] >= z0 + m.template.size[2] - 1e-4
            _assert_clear(scene, m, poses[first])


# ---- moving labels in the predictions -------------------------------------------------------------
def test_moving_labels_in_predictions(moving, tmp_path):
    """--moving-labels gives a mover's point the moving raw id exactly where the prediction is
    the mover's class; every other prediction, and every other file, stays as without it."""
    flagged = _drive(tmp_path, frames=FRAMES, seed=0, azimuth_steps=512, noise_strength=0.5, movers=10,
                     moving_labels=True)
    for path in sorted(moving.rglob("*")):
        if path.is_file() and path.parent.name != "predictions" and path.name != "synth.yaml":
            assert (flagged / path.relative_to(moving)).read_bytes() == path.read_bytes(), path.name
    relabelled, kept_static = 0, 0
    for k in range(FRAMES):
        _, labels, plain = _scan(moving, k)
        preds = np.fromfile(flagged / "predictions" / f"{k:06d}.label", np.uint32)
        truth = labels & 0xFFFF
        mover = np.isin(truth, MOVING)
        right_class = LABELS.to_learning(plain) == LABELS.to_learning(truth)
        assert np.array_equal(np.isin(preds, MOVING), mover & right_class)
        assert np.array_equal(preds, np.where(mover & right_class, truth, plain))
        relabelled += int((mover & right_class).sum())
        kept_static += int((mover & ~right_class).sum())
    assert relabelled > 1000 and kept_static > 10
    assert yaml.safe_load((flagged / "synth.yaml").read_text())["moving_labels"] is True
    assert "moving_labels" not in yaml.safe_load((moving / "synth.yaml").read_text())


def test_cli_varied_drive(tmp_path):
    """A written varied drive: the sidecar names the new behaviours and keeps a stop's poses, the
    record names the options, and the predictions carry moving ids."""
    assert main(["--out", str(tmp_path), "--frames", "60", "--seed", "7", "--movers", "8", "--traffic", "varied",
                 "--moving-labels", "--azimuth-steps", "64", "--beams", "8", "--noise-strength", "0.3",
                 "--quiet"]) == 0
    seq = tmp_path / "sequences" / "00"
    side = load_sidecar(seq)["movers"]
    assert {m["behaviour"] for m in side} <= set(traffic_varied.VARIED_BEHAVIOURS)
    stops = [m for m in side if m["behaviour"] == "stop-and-go"]
    assert stops
    for m in stops:
        runs = _still_runs(np.array(m["poses"]))
        assert len(runs) == 1 and runs[0][1] - runs[0][0] + 1 >= traffic_varied.STOP_SCANS[0]
    record = yaml.safe_load((seq / "synth.yaml").read_text())
    assert record["moving_labels"] is True and record["movers"]["traffic"] == "varied"
    assert list(record["movers"]["behaviours"]) == list(traffic_varied.VARIED_BEHAVIOURS)
    assert record["movers"]["behaviours"]["stop-and-go"] == len(stops)
    preds = np.concatenate([np.fromfile(seq / "predictions" / f"{k:06d}.label", np.uint32) for k in range(60)])
    assert np.isin(preds, MOVING).any()


def test_cli_bad_traffic(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["--out", str(tmp_path), "--traffic", "busy"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("synth: error:") and "--traffic" in err and "\n" not in err

"""Write tiny SemanticKITTI-layout sequences for tests (independent of the project's reader)."""

from pathlib import Path

import numpy as np

# A KITTI-like velodyne -> camera calibration (a proper rigid transform).
TR = np.array([[4.276802e-04, -9.999672e-01, -8.084491e-03, -1.198459e-02],
               [-7.210626e-03, 8.081198e-03, -9.999413e-01, -5.403984e-02],
               [9.999738e-01, 4.859485e-04, -7.206933e-03, -2.921968e-01],
               [0.0, 0.0, 0.0, 1.0]])


def orthonormalise(matrix):
    u, _, vt = np.linalg.svd(matrix[:3, :3])
    fixed = matrix.copy()
    fixed[:3, :3] = u @ vt
    return fixed


TR = orthonormalise(TR)


def pose_about_z(yaw, translation):
    pose = np.eye(4)
    c, s = np.cos(yaw), np.sin(yaw)
    pose[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    pose[:3, 3] = translation
    return pose


def write_sequence(root, sequence, frames, lidar_poses, predictions_dir="predictions", times=None,
                   probabilities=None):
    """``frames``: list of (points_sensor (N, 3), ground truth raw words (N,), predicted raw ids (N,))."""
    folder = Path(root) / "sequences" / sequence
    for name in ("velodyne", "labels", predictions_dir):
        (folder / name).mkdir(parents=True, exist_ok=True)
    for number, (points, truth, predicted) in enumerate(frames):
        scan = np.zeros((len(points), 4), np.float32)
        scan[:, :3] = points
        scan[:, 3] = 0.5
        scan.tofile(folder / "velodyne" / f"{number:06d}.bin")
        np.asarray(truth, "<u4").tofile(folder / "labels" / f"{number:06d}.label")
        np.asarray(predicted, "<u4").tofile(folder / predictions_dir / f"{number:06d}.label")
        if probabilities is not None:
            (folder / "probabilities").mkdir(exist_ok=True)
            np.save(folder / "probabilities" / f"{number:06d}.npy", probabilities[number].astype(np.float16))
    camera = [TR @ pose @ np.linalg.inv(TR) for pose in lidar_poses]
    (folder / "poses.txt").write_text("".join(" ".join(f"{v:.12e}" for v in p[:3].reshape(-1)) + "\n" for p in camera))
    p_line = " ".join(["7.07e+02", "0", "6.04e+02", "0", "0", "7.07e+02", "1.80e+02", "0", "0", "0", "1", "0"])
    tr_line = " ".join(f"{v:.12e}" for v in TR[:3].reshape(-1))
    (folder / "calib.txt").write_text(f"P0: {p_line}\nP1: {p_line}\nP2: {p_line}\nP3: {p_line}\nTr: {tr_line}\n")
    if times is not None:
        (folder / "times.txt").write_text("".join(f"{t:.6e}\n" for t in times))
    return folder


ROAD, SIDEWALK, POLE, BUILDING = 40, 48, 80, 50


def street_scene(rng, count=6000):
    """World points of a small street: road, sidewalk, a wall and poles; raw ground-truth ids."""
    road = np.column_stack([rng.uniform(-15, 15, count), rng.uniform(-3, 3, count), np.full(count, -1.7)])
    walk = np.column_stack([rng.uniform(-15, 15, count // 2), rng.uniform(3, 5, count // 2),
                            np.full(count // 2, -1.55)])
    wall = np.column_stack([rng.uniform(-15, 15, count // 2), np.full(count // 2, 5.5),
                            rng.uniform(-1.5, 2.5, count // 2)])
    pole_xy = np.array([[-8, 2.8], [0, 2.8], [8, 2.8]])
    poles = np.concatenate([np.column_stack([np.full(300, x) + rng.normal(0, 0.05, 300),
                                             np.full(300, y) + rng.normal(0, 0.05, 300),
                                             rng.uniform(-1.7, 2.5, 300)]) for x, y in pole_xy])
    points = np.concatenate([road, walk, wall, poles])
    labels = np.concatenate([np.full(len(road), ROAD), np.full(len(walk), SIDEWALK), np.full(len(wall), BUILDING),
                             np.full(len(poles), POLE)]).astype(np.uint32)
    return points, labels


def noisy(labels, rng, rate):
    """Per-frame random confusions (a network's errors): road<->sidewalk, pole->building."""
    swap = {ROAD: SIDEWALK, SIDEWALK: ROAD, POLE: BUILDING, BUILDING: POLE}
    flip = rng.random(len(labels)) < rate
    out = labels.copy()
    out[flip] = [swap[int(v)] for v in labels[flip]]
    return out


def write_drive(root, sequence, frames=5, seed=0, rate=0.3):
    rng = np.random.default_rng(seed)
    world, truth = street_scene(rng)
    poses, data = [], []
    for number in range(frames):
        pose = pose_about_z(0.05 * number + 0.3, [-6.0 + 3.0 * number, 0.5, 0.2])
        visible = rng.random(len(world)) < 0.7
        sensor = (world[visible] - pose[:3, 3]) @ pose[:3, :3]
        data.append((sensor.astype(np.float32), truth[visible], noisy(truth[visible], rng, rate)))
        poses.append(pose)
    write_sequence(root, sequence, data, poses)
    return data

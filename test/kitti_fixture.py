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

"""SemanticKITTI files of a synthetic drive, written atomically (convbki_core.io.atomic).

Layout: ``ROOT/sequences/SS/`` with ``velodyne/NNNNNN.bin`` (float32
x, y, z, remission; sensor frame, m), ``labels/NNNNNN.label`` and ``predictions/NNNNNN.label``
(uint32: raw semantic id | instance << 16; the predictions have no instances, and moving raw
ids only in a drive made with ``moving_labels``), optionally ``probabilities/NNNNNN.npy``
(float16, (N, 20)), and ``calib.txt``, ``poses.txt``, ``times.txt``, ``synth.yaml``, and with
movers ``movers.json`` (format in ``movers``).
"""

from __future__ import annotations

import io
import math
import os
import re
from pathlib import Path

import numpy as np
import yaml

from convbki_core.io.atomic import atomic_write_bytes

SCAN_FOLDERS = {"velodyne": ".bin", "labels": ".label", "predictions": ".label", "probabilities": ".npy"}
_SCAN_NAME = re.compile(r"^\d{6}\.(bin|label|npy)$")


def _rot(axis: int, angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    r = np.eye(3)
    r[i, i], r[i, j], r[j, i], r[j, j] = c, -s, s, c
    return r


def velodyne_to_camera() -> np.ndarray:
    """The KITTI-like ``Tr`` (4x4): Velodyne (x fwd, y left, z up) -> left camera (x right, y down,
    z fwd), with a few tenths of a degree of mounting error and the usual 0.27 m offset."""
    axes = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
    tr = np.eye(4)
    tr[:3, :3] = axes @ _rot(0, 0.0081) @ _rot(1, -0.0074) @ _rot(2, 0.0004)
    tr[:3, 3] = (-0.004, -0.076, -0.27)
    return tr


def _projections() -> list[np.ndarray]:
    """P0..P3: rectified grey and colour cameras, KITTI-like focal length and 0.54 m baseline."""
    f, cx, cy = 718.3, 607.2, 185.2
    k = np.array([[f, 0, cx], [0, f, cy], [0, 0, 1.0]])
    out = []
    for offset in ((0.0, 0.0, 0.0), (-0.537, 0.0, 0.0), (0.06, -0.0003, 0.0027), (-0.473, 0.003, 0.0035)):
        p = np.zeros((3, 4))
        p[:, :3] = k
        p[:, 3] = k @ np.array(offset)
        out.append(p)
    return out


def _row(matrix: np.ndarray) -> str:
    return " ".join(f"{v:.12e}" for v in matrix[:3, :4].reshape(-1))


def calib_text(tr: np.ndarray) -> str:
    lines = [f"P{i}: {_row(p)}" for i, p in enumerate(_projections())]
    return "\n".join(lines + [f"Tr: {_row(tr)}"]) + "\n"


def poses_text(lidar_poses: np.ndarray, tr: np.ndarray) -> str:
    """Camera-frame poses P = Tr @ T_lidar @ inv(Tr), so that inv(Tr) @ P @ Tr = T_lidar."""
    tr_inv = np.linalg.inv(tr)
    return "".join(_row(tr @ pose @ tr_inv) + "\n" for pose in lidar_poses)


def times_text(times: np.ndarray) -> str:
    return "".join(f"{t:.6e}\n" for t in times)


def check_sequence(root: Path, sequence: str, force: bool) -> Path:
    """``ROOT/sequences/SS`` if a drive may be written there (empty, absent, or ``force``)."""
    seq = root / "sequences" / sequence
    existing = next(p for p in (seq, *seq.parents) if p.exists())  # the deepest folder already there
    if not existing.is_dir():
        raise FileExistsError(f"{existing} exists and is not a folder")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise PermissionError(f"{existing} is not writable")
    if seq.is_dir() and any(seq.iterdir()) and not force:
        raise FileExistsError(f"{seq} is not empty (use --force to overwrite it)")
    return seq


def prepare_sequence(root: Path, sequence: str, force: bool, probabilities: bool) -> Path:
    """Create ``ROOT/sequences/SS`` and its scan folders; refuse a non-empty one unless ``force``.

    With ``force``, scan files (NNNNNN.bin/.label/.npy) left from an earlier drive are removed so
    that no stale scan survives past the new drive's end; other files are left alone.
    """
    seq = check_sequence(root, sequence, force)
    if seq.is_dir() and any(seq.iterdir()):
        for folder in SCAN_FOLDERS:
            if (seq / folder).is_dir():
                for path in (seq / folder).iterdir():
                    if _SCAN_NAME.match(path.name) and path.is_file():
                        path.unlink()
    for folder in SCAN_FOLDERS:
        if folder != "probabilities" or probabilities:
            (seq / folder).mkdir(parents=True, exist_ok=True)
    return seq


def write_scan(seq: Path, index: int, points: np.ndarray, remission: np.ndarray, labels: np.ndarray,
               predictions: np.ndarray, probabilities: np.ndarray | None) -> None:
    """One scan's files. ``points`` (N, 3) sensor frame (m); label words uint32."""
    name = f"{index:06d}"
    cloud = np.empty((len(points), 4), np.float32)
    cloud[:, :3] = points
    cloud[:, 3] = remission
    atomic_write_bytes(seq / "velodyne" / f"{name}.bin", cloud.tobytes())
    atomic_write_bytes(seq / "labels" / f"{name}.label", labels.astype(np.uint32).tobytes())
    atomic_write_bytes(seq / "predictions" / f"{name}.label", predictions.astype(np.uint32).tobytes())
    if probabilities is not None:
        buffer = io.BytesIO()
        np.save(buffer, probabilities.astype(np.float16))
        atomic_write_bytes(seq / "probabilities" / f"{name}.npy", buffer.getvalue())


def write_text(path: Path, text: str) -> None:
    atomic_write_bytes(path, text.encode())


def write_yaml(path: Path, data: dict) -> None:
    write_text(path, yaml.safe_dump(data, sort_keys=False))

"""SemanticKITTI sequences (and anything written in their layout, like ``synth`` drives).

Layout (docs/file_formats.md)::

    ROOT/sequences/SS/velodyne/NNNNNN.bin      float32 x, y, z, remission (LiDAR frame)
    ROOT/sequences/SS/labels/NNNNNN.label      uint32 ground truth: raw id | instance << 16
    ROOT/sequences/SS/<predictions>/NNNNNN.label   input segmentation, same format
    ROOT/sequences/SS/<probabilities>/NNNNNN.npy   optional (N, C) class probabilities
    ROOT/sequences/SS/poses.txt                 3x4 camera-frame poses P_i, row-major
    ROOT/sequences/SS/calib.txt                 "Tr:" velodyne -> camera (3x4)
    ROOT/sequences/SS/times.txt                 optional, seconds

The LiDAR pose in the map frame is inv(Tr) @ P_i @ Tr; the first pose is whatever the file
says (never assumed to be identity).
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np

from convbki_core.datasets import DatasetError, Frame
from convbki_core.io.labels import LabelMap, load_label_map


def _first_line(error: BaseException) -> str:
    text = str(error).strip()
    return text.splitlines()[0][:200] if text else error.__class__.__name__


def _file_size(path: Path) -> int:
    try:
        return path.stat().st_size
    except OSError as error:
        raise DatasetError(f"{path}: cannot read ({error.strerror or error})") from None


def _npy_shape(path: Path) -> tuple[int, ...]:
    """The array shape an .npy file declares, from its header alone."""
    if not path.exists():
        raise DatasetError(f"{path}: probabilities file missing")
    try:
        with path.open("rb") as handle:
            version = np.lib.format.read_magic(handle)
            read_header = np.lib.format.read_array_header_1_0 if version == (1, 0) \
                else np.lib.format.read_array_header_2_0
            shape, _, dtype = read_header(handle)
    except (OSError, ValueError, EOFError, SyntaxError) as error:
        raise DatasetError(f"{path}: not a readable .npy file ({_first_line(error)})") from None
    if dtype.kind != "f":
        raise DatasetError(f"{path}: probabilities must be float16/float32, found {dtype}")
    return tuple(shape)


def read_points(path: Path) -> np.ndarray:
    """A velodyne .bin file as (N, 4) float32 (x, y, z, remission)."""
    data = np.fromfile(path, dtype=np.float32)
    if data.size % 4:
        raise DatasetError(f"{path}: size {data.size * 4} bytes is not a whole number of 16-byte points")
    return data.reshape(-1, 4)


def read_label_words(path: Path) -> np.ndarray:
    """A .label file as (N,) uint32 words (semantic id in the low 16 bits)."""
    data = path.read_bytes()
    if len(data) % 4:
        raise DatasetError(f"{path}: size {len(data)} bytes is not a whole number of uint32 labels")
    return np.frombuffer(data, dtype="<u4").copy()


def read_calibration(path: Path) -> np.ndarray:
    """``Tr`` (velodyne -> camera) of a calib.txt as a 4x4 matrix."""
    try:
        lines = path.read_text().splitlines()
    except OSError as error:
        raise DatasetError(f"{path}: cannot read calibration ({error.strerror or error})") from None
    for line in lines:
        key, _, values = line.partition(":")
        if key.strip() == "Tr":
            try:
                numbers = np.array([float(v) for v in values.split()], dtype=np.float64)
            except ValueError:
                raise DatasetError(f"{path}: Tr holds something that is not a number") from None
            if numbers.size != 12 or not np.isfinite(numbers).all():
                raise DatasetError(f"{path}: Tr must hold 12 finite numbers, found {numbers.size}")
            matrix = np.eye(4)
            matrix[:3] = numbers.reshape(3, 4)
            rotation = matrix[:3, :3]
            if not np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-3):
                raise DatasetError(f"{path}: Tr's rotation part is not orthonormal")
            return matrix
    raise DatasetError(f"{path}: no 'Tr:' line (velodyne -> camera calibration)")


def read_poses(path: Path, calibration: np.ndarray) -> np.ndarray:
    """LiDAR poses in the map frame, (N, 4, 4): inv(Tr) @ P_i @ Tr."""
    try:
        text = path.read_text()
    except OSError as error:
        raise DatasetError(f"{path}: cannot read poses ({error.strerror or error})") from None
    rows = [line.split() for line in text.splitlines() if line.strip()]
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    for number, row in enumerate(rows):
        try:
            values = np.array([float(v) for v in row], dtype=np.float64)
        except ValueError:
            raise DatasetError(f"{path}: line {number + 1} holds something that is not a number") from None
        if values.size != 12 or not np.isfinite(values).all():
            raise DatasetError(f"{path}: line {number + 1} must hold 12 finite numbers, found {values.size}")
        poses[number, :3] = values.reshape(3, 4)
    return np.linalg.inv(calibration) @ poses @ calibration


class SemanticKittiSequence:
    """One sequence of a SemanticKITTI-layout dataset, frame by frame.

    ``predictions_dir`` names the input segmentation folder (raw ids, like labels);
    ``probabilities_dir`` optionally names (N, C) .npy class probabilities that are then
    the mapper's input. Ground truth is read when ``labels/`` exists.
    """

    def __init__(self, root: str | Path, sequence: str | int, predictions_dir: str | None = "predictions",
                 probabilities_dir: str | None = None, label_map: LabelMap | None = None):
        self.root = Path(root)
        self.sequence = f"{int(sequence):02d}" if str(sequence).isdigit() else str(sequence)
        self.label_map = label_map or load_label_map("semantic_kitti")
        self.folder = self.root / "sequences" / self.sequence
        if not self.root.is_dir():
            raise DatasetError(f"{self.root}: dataset folder not found")
        if not self.folder.is_dir():
            raise DatasetError(f"{self.folder}: sequence {self.sequence} not found in {self.root}")
        velodyne = self.folder / "velodyne"
        if not velodyne.is_dir():
            raise DatasetError(f"{velodyne}: no velodyne folder")
        self.scan_files = sorted(velodyne.glob("*.bin"))
        if not self.scan_files:
            raise DatasetError(f"{velodyne}: no .bin scans")
        self.names = [path.stem for path in self.scan_files]

        # What a user should know about how the files were read (one line each), e.g. poses not used.
        self.notices: list[str] = []
        self.calibration = read_calibration(self.folder / "calib.txt")
        self.poses = self._one_per_scan(read_poses(self.folder / "poses.txt", self.calibration),
                                        self.folder / "poses.txt", "poses")
        self.times = self._read_times()

        self.labels_folder = self.folder / "labels"
        self.has_ground_truth = self.labels_folder.is_dir()
        self.predictions_folder = self._optional_folder(predictions_dir, "predictions")
        self.probabilities_folder = self._optional_folder(probabilities_dir, "probabilities")

    def _optional_folder(self, name: str | None, what: str) -> Path | None:
        if not name:
            return None
        folder = self.folder / name
        if not folder.is_dir():
            raise DatasetError(f"{folder}: {what} folder not found")
        return folder

    def _read_times(self) -> np.ndarray:
        path = self.folder / "times.txt"
        if not path.exists():
            return 0.1 * np.arange(len(self.scan_files), dtype=np.float64)
        try:
            times = np.array([float(line) for line in path.read_text().split()], dtype=np.float64)
        except ValueError:
            raise DatasetError(f"{path}: holds something that is not a number") from None
        return self._one_per_scan(times, path, "times")

    def _one_per_scan(self, rows: np.ndarray, path: Path, what: str) -> np.ndarray:
        """The rows of a per-scan file (poses.txt, times.txt), one per scan. A file with one row
        per scan is read in order. A longer one is the whole sequence's, beside only some of its
        scans (a partial download, a published excerpt): row k belongs to scan NNNNNN = k, so the
        scans must be numbered; the rows not used are said in ``notices``. Fewer rows than scans
        belong to another sequence or cut: an error."""
        scans = len(self.scan_files)
        if len(rows) == scans:
            return rows
        if len(rows) < scans:
            raise DatasetError(f"{path}: {len(rows)} {what} for {scans} scans")
        if not all(name.isdigit() for name in self.names):
            raise DatasetError(f"{path}: {len(rows)} {what} for {scans} scans, and the scans' names are not their "
                               f"numbers in the sequence (e.g. {next(n for n in self.names if not n.isdigit())}.bin)")
        numbers = np.array([int(name) for name in self.names])
        if numbers.max() >= len(rows):
            raise DatasetError(f"{path}: {len(rows)} {what}, none for scan {self.names[int(numbers.argmax())]} "
                               f"(row {numbers.max() + 1})")
        self.notices.append(f"{path}: {len(rows)} {what} for {scans} numbered scans: row k used for scan k, "
                            f"{len(rows) - scans} not used")
        return rows[numbers]

    def __len__(self) -> int:
        return len(self.scan_files)

    def check_files(self, positions: Iterable[int] | None = None) -> None:
        """Check, before any work, that the files of the frames at ``positions`` (default: all) exist
        and agree in size: one label per point in labels/ and the input segmentation, one row of
        C probabilities per point. Only sizes and .npy headers are read, so a whole sequence
        takes a moment; a command calls this first and fails before writing anything.
        """
        for position in range(len(self)) if positions is None else positions:
            name, scan = self.names[position], self.scan_files[position]
            if not scan.is_file():
                raise DatasetError(f"{scan}: not a file")
            size = _file_size(scan)
            if size % 16:
                raise DatasetError(f"{scan}: size {size} bytes is not a whole number of 16-byte points")
            count = size // 16
            folders = [self.labels_folder] if self.has_ground_truth else []
            folders += [self.predictions_folder] if self.predictions_folder is not None else []
            for folder in folders:
                path = folder / f"{name}.label"
                if not path.exists():
                    raise DatasetError(f"{path}: label file missing")
                if not path.is_file():
                    raise DatasetError(f"{path}: not a file")
                size = _file_size(path)
                if size % 4:
                    raise DatasetError(f"{path}: size {size} bytes is not a whole number of uint32 labels")
                if size // 4 != count:
                    raise DatasetError(f"{path}: {size // 4} labels for {count} points")
            if self.probabilities_folder is not None:
                path = self.probabilities_folder / f"{name}.npy"
                shape = _npy_shape(path)
                expected = (count, self.label_map.num_classes)
                if shape != expected:
                    raise DatasetError(f"{path}: probabilities of shape {shape}, expected {expected}")

    def __iter__(self) -> Iterator[Frame]:
        for position in range(len(self)):
            yield self[position]

    def __getitem__(self, position: int) -> Frame:
        if not -len(self) <= position < len(self):
            raise IndexError(position)
        position %= len(self)
        name = self.names[position]
        scan = read_points(self.scan_files[position])
        # Contiguous (N, 3), as the node decodes a cloud: the voxeliser would copy a strided view.
        points = np.ascontiguousarray(scan[:, :3])
        frame = Frame(index=int(name) if name.isdigit() else position, name=name, points=points,
                      remission=scan[:, 3], pose=self.poses[position], stamp=float(self.times[position]))
        count = scan.shape[0]
        if self.has_ground_truth:
            words = self._labels(self.labels_folder / f"{name}.label", count)
            frame.ground_truth = self.label_map.to_learning(words)
            frame.moving = self.label_map.is_moving(words)
        if self.predictions_folder is not None:
            frame.raw_input_labels = self._labels(self.predictions_folder / f"{name}.label", count)
            frame.moving_raw_ids = self.label_map.moving_raw
            frame.input_labels = self.label_map.to_learning(frame.raw_input_labels)
        if self.probabilities_folder is not None:
            frame.probabilities = self._probabilities(self.probabilities_folder / f"{name}.npy", count)
        return frame

    def _labels(self, path: Path, count: int) -> np.ndarray:
        if not path.exists():
            raise DatasetError(f"{path}: label file missing")
        words = read_label_words(path)
        if words.size != count:
            raise DatasetError(f"{path}: {words.size} labels for {count} points")
        return words

    def _probabilities(self, path: Path, count: int) -> np.ndarray:
        if not path.exists():
            raise DatasetError(f"{path}: probabilities file missing")
        try:
            data = np.load(path, allow_pickle=False)
        except (OSError, ValueError, EOFError) as error:
            raise DatasetError(f"{path}: cannot read probabilities ({_first_line(error)})") from None
        if not isinstance(data, np.ndarray):
            raise DatasetError(f"{path}: not a single .npy array of probabilities")
        expected = self.label_map.num_classes
        if data.ndim != 2 or data.shape != (count, expected):
            raise DatasetError(f"{path}: probabilities of shape {data.shape}, expected ({count}, {expected})")
        return data.astype(np.float32)

"""What the offline programs (``evaluate``, ``bench``, ``soak``) share: the paper's mapping
set-up, the cached synthetic drive, and reading a sequence frame by frame into a mapper.

Progress bars and printing stay with the programs; nothing here writes to a terminal.
"""

from __future__ import annotations

import contextlib
import io
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path

import numpy as np

from convbki_core.datasets import DatasetError, Frame, SequenceDataset
from convbki_core.datasets.labels import load_label_map
from convbki_core.datasets.semantic_kitti import SemanticKittiSequence
from convbki_core.io.kernel_file import KernelConfig
from convbki_core.mapper import ConvBKIMapper, IntegrationResult
from convbki_core.paths import kernel_path
from convbki_core.tools.synth import main as synth
from convbki_core.tools.synth import read_synth_record
from convbki_core.volume import transform_points

# The paper's SemanticKITTI set-up: the local window around the sensor (m) and the kernel.
PAPER_BOUNDS = ((-40.0, -40.0, -2.6), (40.0, 40.0, 2.6))
PAPER_KERNEL = "semantic_kitti_compound"

# The synthetic drive's settings unless a caller asks otherwise: the HDL-64E, and a fixed
# noise strength for the input segmentation, so that synth skips its calibration pass and a
# drive with the same seed is the same drive whoever writes it.
DRIVE_BEAMS = 64
DRIVE_AZIMUTH_STEPS = 2083
DRIVE_NOISE_STRENGTH = 0.35


_device = "cpu"


@contextlib.contextmanager
def mapping_device(device: str) -> Iterator[None]:
    """Within the block, ``paper_mapper`` maps on ``device`` (e.g. ``cuda``) instead of the CPU."""
    global _device
    previous, _device = _device, device
    try:
        yield
    finally:
        _device = previous


def paper_mapper(kernel: str | Path | KernelConfig | None = None, **options) -> ConvBKIMapper:
    """A ``ConvBKIMapper`` with the paper's window and, unless ``kernel`` names another, its
    kernel, on the CPU (or the device of ``mapping_device``); ``options`` (any
    ``ConvBKIMapper`` keyword: local_bounds, resolution, filter_size, update_path, ...)
    override the rest."""
    settings = {"local_bounds": PAPER_BOUNDS, "device": _device, **options}
    if kernel is None and settings.get("free_space") and "movable_classes" not in settings:
        # The product's free space: with the movers' rules of SemanticKITTI's movable classes.
        settings["movable_classes"] = load_label_map("semantic_kitti").movable_classes
    return ConvBKIMapper(kernel_path(PAPER_KERNEL) if kernel is None else kernel, **settings)


def _drive_is_ready(sequence_folder: Path, scans: int, seed: int, beams: int, azimuth_steps: int,
                    noise_strength: float) -> bool:
    record = read_synth_record(sequence_folder)
    if not record:
        return False
    lidar = record.get("lidar") or {}
    noise = record.get("noise") or {}
    same = (record.get("seed") == seed and lidar.get("beams") == beams
            and lidar.get("azimuth_steps") == azimuth_steps and noise.get("strength") == noise_strength)
    # The record says how many scans synth wrote; the files say how many are still there.
    return (same and int(record.get("frames") or 0) >= scans
            and sum(1 for _ in (sequence_folder / "velodyne").glob("*.bin")) >= scans)


def ensure_drive(folder: str | Path, scans: int, seed: int, *, beams: int = DRIVE_BEAMS,
                 azimuth_steps: int = DRIVE_AZIMUTH_STEPS, noise_strength: float = DRIVE_NOISE_STRENGTH,
                 on_simulate: Callable[[], None] | None = None) -> SemanticKittiSequence:
    """A ``synth`` drive of at least ``scans`` scans in ``folder`` (sequence 00), written when missing.

    A drive already there is reused when its ``synth.yaml`` says it has the same seed, LiDAR
    and noise and enough scans; an older, shorter or different synthetic drive is rewritten.
    A folder holding anything else is never overwritten. ``on_simulate`` is called just
    before a drive is simulated (to tell the user why the program pauses). Raises
    ``DatasetError`` with a one-line reason when the drive cannot be had.
    """
    folder = Path(folder)
    sequence_folder = folder / "sequences" / "00"
    if folder.exists() and not folder.is_dir():
        raise DatasetError(f"{folder}: exists and is not a folder")
    if _drive_is_ready(sequence_folder, scans, seed, beams, azimuth_steps, noise_strength):
        return SemanticKittiSequence(folder, "00")
    if read_synth_record(sequence_folder) is None and sequence_folder.is_dir() and any(sequence_folder.iterdir()):
        # synth --force below would replace the scans: never do that to a folder synth did not write.
        raise DatasetError(f"{folder}: {sequence_folder} holds data that is not a synthetic drive "
                           "(no synth.yaml); pick an empty or new folder")
    if on_simulate is not None:
        on_simulate()
    errors = io.StringIO()
    with contextlib.redirect_stderr(errors):  # synth's own error line becomes part of the caller's one line
        code = synth(["--out", str(folder), "--sequence", "00", "--frames", str(scans), "--seed", str(seed),
                      "--beams", str(beams), "--azimuth-steps", str(azimuth_steps),
                      "--noise-strength", str(noise_strength), "--force", "--quiet"])
    if code != 0:
        reason = (errors.getvalue().strip().splitlines() or ["synth failed"])[-1].removeprefix("synth: error: ")
        raise DatasetError(f"the synthetic drive could not be written to {folder}: {reason}")
    return SemanticKittiSequence(folder, "00")


def read_frames(dataset: SequenceDataset, positions: Iterable[int]) -> Iterator[Frame]:
    """The frames at ``positions`` of a sequence, read one at a time (a drive never sits in memory)."""
    for position in positions:
        yield dataset[position]


def drive_frames(dataset: SequenceDataset,
                 positions: Iterable[int]) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """(points, input labels or probabilities, pose) of the frames at ``positions``: what
    ``ConvBKIMapper.integrate`` takes."""
    for frame in read_frames(dataset, positions):
        yield frame.points, frame.input_values, frame.pose


def integrate_frames(mapper: ConvBKIMapper, frames: Iterable[Frame]) -> Iterator[tuple[Frame, IntegrationResult]]:
    """Integrate each frame's input (labels or probabilities) at its pose; yield it with the result."""
    for frame in frames:
        yield frame, mapper.integrate(frame.points, frame.input_values, frame.pose)


def update_ms(result: IntegrationResult) -> float:
    """The update's time for one scan as the benchmarks count it: voxelise + ConvBKI update
    (+ free space when the mapper has it on)."""
    return result.timing_ms["voxelize"] + result.timing_ms["update"] + result.timing_ms["free"]


def query_ms(result: IntegrationResult) -> float:
    """The window move's time for one scan (write-back of the slabs that leave, fetch of those that enter)."""
    return result.timing_ms["query"]


def map_frame_labels(mapper: ConvBKIMapper, points: np.ndarray, pose: np.ndarray,
                     input_labels: np.ndarray) -> np.ndarray:
    """The protocol's per-point labels after the frame was integrated: map label, else input
    label (``evaluate`` scores these; ``train`` validates with them)."""
    map_labels, has_evidence = mapper.labels_at(transform_points(points, pose))
    return np.where(has_evidence, map_labels, input_labels)

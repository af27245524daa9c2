"""The synthetic drive that ``bench``, ``soak``, ``gpu_check`` and the tests share: written
once into a folder, reused while its ``synth.yaml`` says it is the drive asked for.

The drive's settings unless a caller asks otherwise: the HDL-64E, and a fixed noise strength
for the input segmentation, so that no calibration pass runs and a drive with the same seed
is the same drive whoever writes it.
"""

from __future__ import annotations

import shutil
from collections.abc import Callable
from pathlib import Path

import yaml

from convbki_core.datasets import DatasetError
from convbki_core.datasets.semantic_kitti import SemanticKittiSequence

DRIVE_BEAMS = 64
DRIVE_AZIMUTH_STEPS = 2083
DRIVE_NOISE_STRENGTH = 0.35


def read_synth_record(sequence_folder: str | Path) -> dict | None:
    """The ``synth.yaml`` that ``synth`` leaves in a sequence it wrote, or None (not a synth drive)."""
    try:
        record = yaml.safe_load((Path(sequence_folder) / "synth.yaml").read_text())
    except (OSError, UnicodeDecodeError, yaml.YAMLError):
        return None
    return record if isinstance(record, dict) else None


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
    """A synthetic drive of at least ``scans`` scans in ``folder`` (sequence 00), written when missing.

    A drive already there is reused when its ``synth.yaml`` says it has the same seed, LiDAR
    and noise and enough scans; an older, shorter or different synthetic drive is rewritten.
    A folder holding anything else is never overwritten. ``on_simulate`` is called just
    before a drive is simulated (to tell the user why the program pauses). Raises
    ``DatasetError`` with a one-line reason when the drive cannot be had.
    """
    from convbki_core.synth.drive import DriveConfig, SynthError, check_destination, generate_drive
    from convbki_core.synth.lidar import MissingDependency, require_numba

    folder = Path(folder)
    sequence_folder = folder / "sequences" / "00"
    if folder.exists() and not folder.is_dir():
        raise DatasetError(f"{folder}: exists and is not a folder")
    if _drive_is_ready(sequence_folder, scans, seed, beams, azimuth_steps, noise_strength):
        return SemanticKittiSequence(folder, "00")
    if read_synth_record(sequence_folder) is None and sequence_folder.is_dir() and any(sequence_folder.iterdir()):
        # Rewriting would replace the scans: never do that to a folder synth did not write.
        raise DatasetError(f"{folder}: {sequence_folder} holds data that is not a synthetic drive "
                           "(no synth.yaml); pick an empty or new folder")
    if on_simulate is not None:
        on_simulate()
    config = DriveConfig(out=folder, sequence="00", frames=scans, seed=seed, beams=beams,
                         azimuth_steps=azimuth_steps, noise_strength=noise_strength, force=True)
    created = next((p for p in reversed((sequence_folder, *sequence_folder.parents)) if not p.exists()), None)
    try:
        require_numba()
        check_destination(config)
        generate_drive(config)
    except (SynthError, MissingDependency, OSError) as error:
        if created is not None:
            shutil.rmtree(created, ignore_errors=True)
        reason = f"{error.filename}: {error.strerror}" if isinstance(error, OSError) and error.filename else error
        raise DatasetError(f"the synthetic drive could not be written to {folder}: {reason}") from None
    return SemanticKittiSequence(folder, "00")

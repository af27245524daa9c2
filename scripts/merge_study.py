"""How close a merge of two segments' maps comes to the map of the whole drive, as it is and with
a record a later segment could carry: the free evidence its rays gave window voxels that its
own mapper held nothing in (free space adds evidence only to voxels that hold some).

    .venv/bin/python scripts/merge_study.py --dataset out/demo/data --sequence 08 --split 75 \
        --out out/merge_study

Maps frames 0:split, split:end (recording, by wrapping the free-space pass that adds the
counted rays; a study, not product code) and 0:end with ``evaluate``'s defaults, then prints
one markdown row per merge: the sum (``map_tool merge``), the sum with the record added to
the first segment's voxels, the same except on the ground's surface (free space's rule, on
the merged concentrations), and that with clamping where the record first contradicts a
voxel. Also the size of the record and where the remaining differences are.
"""

from __future__ import annotations

import argparse
import io
from pathlib import Path

import numpy as np

import convbki_core.free_space.update as free_space
from convbki_core.free_space.clamping import DEFAULT_LIMIT, clamp_numpy
from convbki_core.io.labels import load_label_map
from convbki_core.io.map_file import read_map
from convbki_core.memory.window import EVIDENCE
from convbki_core.tools import evaluate, map_merge


class MissedEvidence:
    """Wraps the free-space pass of the centre-only free kernel (the shipped one) and keeps, per
    global voxel, the evidence the counted rays carried where the window held nothing."""

    def __init__(self):
        self.keys: list[np.ndarray] = []
        self.values: list[np.ndarray] = []
        self.per_scan: list[int] = []
        self._pass = free_space._apply_centre

    def __enter__(self):
        free_space._apply_centre = self._record
        return self

    def __exit__(self, *_):
        free_space._apply_centre = self._pass

    def _record(self, sensor_x, weight, origin, alpha, mask, counts, shared_plane, *rest):
        size_x, size_y, size_z = mask.shape
        combined = counts.copy()  # window order along x and y, the torus along z (``_count_rays``)
        combined[sensor_x] += shared_plane
        window_mask = mask[(origin[0] + np.arange(size_x)) % size_x][:, (origin[1] + np.arange(size_y)) % size_y]
        i, j, z = np.nonzero((combined > 0) & ((window_mask & EVIDENCE) == 0))
        voxels = np.column_stack([origin[0] + i, origin[1] + j, origin[2] + (z - origin[2]) % size_z])
        self.keys.append(voxels.astype(np.int64))
        self.values.append(combined[i, j, z].astype(np.float64) * float(weight))
        self.per_scan.append(len(i))
        return self._pass(sensor_x, weight, origin, alpha, mask, counts, shared_plane, *rest)

    def totals(self) -> tuple[np.ndarray, np.ndarray]:
        voxels, where = np.unique(np.concatenate(self.keys), axis=0, return_inverse=True)
        return voxels, np.bincount(where.reshape(-1), weights=np.concatenate(self.values))


def key(indices: np.ndarray) -> np.ndarray:
    """One int64 per voxel index (|index| < 50,000)."""
    shifted = indices.astype(np.int64) + 50_000
    return (shifted[:, 0] * 100_000 + shifted[:, 1]) * 100_000 + shifted[:, 2]


def lookup(table_keys: np.ndarray, table_values: np.ndarray, keys: np.ndarray, missing=0.0) -> np.ndarray:
    order = np.argsort(table_keys)
    sorted_keys = table_keys[order]
    position = np.clip(np.searchsorted(sorted_keys, keys), 0, max(len(sorted_keys) - 1, 0))
    found = sorted_keys[position] == keys if len(sorted_keys) else np.zeros(len(keys), bool)
    return np.where(found, table_values[order][position], missing)


def ground_surface(indices: np.ndarray, alpha: np.ndarray, prior: float, ground_classes) -> np.ndarray:
    """Free space's rule: the voxel's arg-max over classes 1.. is a ground class and its ground
    evidence is not below that of the voxels under and over it (0 where there is none)."""
    ground_classes = list(ground_classes)
    best = alpha[:, 1:].argmax(axis=1) + 1
    evidence = (alpha[:, ground_classes].astype(np.float64) - np.float64(np.float32(prior))).sum(axis=1)
    keys = key(indices)
    below = lookup(keys, evidence, key(indices - [0, 0, 1]))
    above = lookup(keys, evidence, key(indices + [0, 0, 1]))
    return np.isin(best, ground_classes) & (evidence >= below) & (evidence >= above)


def clamp_first_contradicted(alpha: np.ndarray, added: np.ndarray, prior: float) -> np.ndarray:
    """``alpha`` (N, C) with clamping's rule (``clamp_numpy``) applied where ``added`` free
    evidence first contradicts a voxel."""
    window = np.ascontiguousarray(alpha.T).reshape(alpha.shape[1], -1, 1, 1)  # (C, N, 1, 1)
    taking = np.nonzero(added > 0)[0]
    zeros = np.zeros_like(taking)
    clamp_numpy(window, (taking, zeros, zeros), window[0, taking, 0, 0].copy(), DEFAULT_LIMIT, prior)
    return window.reshape(alpha.shape[1], -1).T


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--dataset", required=True)
    p.add_argument("--sequence", required=True)
    p.add_argument("--split", type=int, required=True, help="the second segment's first frame")
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    frames = len(list((Path(args.dataset) / "sequences" / args.sequence / "velodyne").glob("*.bin")))

    def mapped(name: str, first: int, end: int) -> Path:
        path = args.out / f"{name}.npz"
        (args.out / f"{name}_report").mkdir(exist_ok=True)
        assert evaluate.main(["--dataset", args.dataset, "--sequence", args.sequence, "--frames", f"{first}:{end}",
                              "--report", str(args.out / f"{name}_report" / "report.json"), "--save-map", str(path),
                              "--quiet"]) == 0
        return path

    first_map = mapped("first", 0, args.split)
    with MissedEvidence() as record:
        second_map = mapped("second", args.split, frames)
    whole_map = mapped("whole", 0, frames)
    missed_voxels, missed = record.totals()
    packed = io.BytesIO()
    linear = np.sort(key(missed_voxels))
    saturated = np.minimum(missed, np.finfo(np.float16).max).astype(np.float16)
    np.savez_compressed(packed, delta=np.diff(linear, prepend=0), evidence=saturated)
    second_held = len(read_map(second_map)[1])
    print(f"record: {len(missed_voxels):,} voxels ({int(np.median(record.per_scan)):,} a scan, median), "
          f"{packed.tell() / 1e6:.1f} MB compressed; the second segment's map holds {second_held:,}")

    metadata, first_indices, first_alpha = read_map(first_map)
    _, second_indices, second_alpha = read_map(second_map)
    _, whole_indices, whole_alpha = read_map(whole_map)
    prior = float(metadata["prior"])
    indices, alpha, _ = map_merge.merge_arrays([(first_indices, first_alpha), (second_indices, second_alpha)], prior)
    keys = key(indices)
    whole_labels = lookup(key(whole_indices), whole_alpha.argmax(axis=1), keys, missing=-1)
    added = np.where(np.isin(keys, key(first_indices)), lookup(key(missed_voxels), missed, keys), 0.0)
    surface = ground_surface(indices, alpha, prior, load_label_map("semantic_kitti").ground_classes)
    off_surface = np.where(surface, 0.0, added)
    merges = {"the sum (`map_tool merge`)": alpha,
              "+ the record on the first segment's voxels": alpha + np.outer(added, np.eye(alpha.shape[1])[0]),
              "+ the record, off the ground's surface": alpha + np.outer(off_surface, np.eye(alpha.shape[1])[0]),
              "the same, clamping where it first contradicts": clamp_first_contradicted(alpha, off_surface, prior)
              + np.outer(off_surface, np.eye(alpha.shape[1])[0])}
    print("| merge | same label as the whole drive | differ | whole empty, merge not | merge empty, whole not |")
    print("|---|---|---|---|---|")
    for name, merged in merges.items():
        labels = merged.argmax(axis=1)
        differ = labels != whole_labels
        print(f"| {name} | {100 * (1 - differ.mean()):.3f} % | {differ.sum():,} | "
              f"{(differ & (whole_labels == 0)).sum():,} | {(differ & (labels == 0)).sum():,} |")
    in_first, in_second = np.isin(keys, key(first_indices)), np.isin(keys, key(second_indices))
    print("last row's differences held by the first segment only, the second only, both:",
          ", ".join(f"{(differ & held).sum():,}" for held in (in_first & ~in_second, ~in_first & in_second,
                                                              in_first & in_second)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

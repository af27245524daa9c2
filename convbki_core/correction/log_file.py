"""The scan log in a map file (version 3 members ``scan_log_*``).

Per segment ``i``: ``scan_log_{i}_table`` (one row per scan: stamp, pose, mount, how its bytes
are encoded and how many), ``scan_log_{i}_data`` (the bytes of its scans the file holds itself),
``scan_log_{i}_where`` (per scan the file of the log's folder that holds its bytes, an index
into the metadata's ``files``, and the offset there; -1: in ``_data``), and its base: rows as
the map's own (``_base_index``, ``_count``, ``_class``, ``_value``) or files of the folder
(the metadata's ``base_file``, its index, and ``base_chunk_files``, the chunk files it names).
``scan_log_meta`` (JSON) lists the segments, what froze, the calibration and ``files``: each
folder file named, relative to the map file's folder where it lies below it. A log with a folder
(``log_folder``) is saved by reference, its gigabytes never copied; a file without ``_where``
(written before folders) holds every scan itself.
"""

from __future__ import annotations

import json
import os
from collections import deque
from pathlib import Path

import numpy as np

from convbki_core.correction.log_folder import LogFolder, SegmentBase, files_of_meta
from convbki_core.correction.logged_scan import LoggedScan, ScanBytes
from convbki_core.correction.scan_log import ScanLog, Segment

# The per-scan fields a map file keeps of a log (one row per scan), beside the bytes.
TABLE = np.dtype([("stamp_ns", "<i8"), ("pose", "<f8", (4, 4)), ("mount", "<f8", (4, 4)), ("count", "<i8"),
                  ("points_dtype", "S4"), ("kind", "<i1"), ("values_dtype", "S4"), ("columns", "<i4"),
                  ("points_bytes", "<i8"), ("values_bytes", "<i8")])


class MissingLogFiles(ValueError):
    """A map file's log names files of a folder that are gone or cut short: the map is usable,
    its log is not."""


def log_arrays(log: ScanLog, map_folder: str | Path) -> dict[str, np.ndarray]:
    """``log`` as map-file members, its folder's files named relative to ``map_folder`` (the map
    file's) where they lie below it. The folder is flushed first: every scan handed to it is
    on disk before a file names it."""
    from convbki_core.memory.compact_rows import compress_rows

    if log.folder is not None:
        log.folder.flush()
    map_folder = os.path.realpath(map_folder)
    arrays, files, described = {}, {}, []

    real_folders: dict[Path, str] = {}  # a folder's real path, looked up once (thousands of scans name it)

    def file_number(place) -> int:
        folder = place[0].path
        if folder not in real_folders:
            real_folders[folder] = os.path.realpath(folder)
        path = os.path.join(real_folders[folder], place[1])
        shown = os.path.relpath(path, map_folder) if path.startswith(map_folder + os.sep) else path
        return files.setdefault(shown, len(files))

    for number, segment in enumerate(log.segments()):
        table = np.zeros(len(segment.scans), TABLE)
        where = np.full((len(segment.scans), 2), -1, np.int64)
        inline = []
        for row, spot, scan in zip(table, where, segment.scans):
            row["stamp_ns"], row["pose"], row["mount"] = scan.stamp_ns, scan.pose, scan.mount
            row["count"], row["points_dtype"], row["kind"] = scan.count, scan.points_dtype.encode(), scan.kind
            row["values_dtype"], row["columns"] = scan.values_dtype.encode(), scan.columns
            row["points_bytes"], row["values_bytes"] = scan.data.points_size, scan.data.values_size
            place = scan.data.place
            if place is not None:
                spot[:] = file_number(place), place[2]
            else:
                inline.extend(scan.data.parts())
        arrays[f"scan_log_{number}_table"] = table
        arrays[f"scan_log_{number}_where"] = where
        arrays[f"scan_log_{number}_data"] = np.frombuffer(b"".join(inline), np.uint8)
        about = {"first_index": segment.first_index, "base": segment.base is not None,
                 "base_position": None if segment.base_position is None
                 else [float(v) for v in segment.base_position]}
        if segment.base is not None and segment.base.place is not None:
            about["base_file"] = file_number(segment.base.place)
            folder = segment.base.place[0]
            about["base_chunk_files"] = [file_number((folder, name)) for name in sorted(segment.base.depends)]
        elif segment.base is not None:
            store = segment.base.store()
            indices, alpha = store.items()
            counts, classes, values = compress_rows(alpha, store.prior)
            arrays[f"scan_log_{number}_base_index"] = indices.astype(np.int32)
            arrays[f"scan_log_{number}_base_count"] = counts
            arrays[f"scan_log_{number}_base_class"] = classes
            arrays[f"scan_log_{number}_base_value"] = values.view(np.float32)
        described.append(about)
    meta = {"segments": described, "frozen": log.frozen, "frozen_stamp_ns": log.frozen_stamp_ns,
            "frozen_why": log.frozen_why, "files": list(files),
            "calibration": None if log.calibration is None else np.asarray(log.calibration).tolist()}
    arrays["scan_log_meta"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    if log.pending is not None:
        arrays["scan_log_pending_stamps"] = np.asarray(log.pending[0], "<i8")
        arrays["scan_log_pending_poses"] = np.asarray(log.pending[1], "<f8")
    return arrays


def named_files(arrays: dict[str, np.ndarray], map_folder: str | Path) -> list[Path]:
    """The folder files a log's members (``log_arrays``) name, as absolute paths."""
    meta = json.loads(arrays["scan_log_meta"].tobytes().decode())
    return [Path(os.path.normpath(os.path.join(map_folder, name))) for name in files_of_meta(meta)]


def log_of_arrays(arrays: dict[str, np.ndarray], meta: dict, num_classes: int, prior: float,
                  map_folder: str | Path) -> ScanLog:
    """The log of map-file members (``log_arrays``); raises ValueError when they do not fit, and
    ``MissingLogFiles`` when the folder's files they name are gone or short."""
    from convbki_core.memory.compact_rows import expand_rows
    from convbki_core.memory.store import VoxelStore

    log = ScanLog()
    described = meta.get("segments")
    if not isinstance(described, list) or not described:
        raise ValueError("its metadata lists no segment")
    paths = named_files(arrays, map_folder)
    folders = {path.parent: LogFolder.reader(path.parent) for path in paths}
    places = [(folders[path.parent], path.name) for path in paths]
    sizes_of = {}
    for path in paths:
        try:
            sizes_of[path] = os.stat(path).st_size
        except OSError as error:
            raise MissingLogFiles(f"{path}: {error.strerror or error}") from None
    segments = []
    for number, about in enumerate(described):
        table, data = arrays.get(f"scan_log_{number}_table"), arrays.get(f"scan_log_{number}_data")
        if table is None or data is None or table.dtype != TABLE or data.dtype != np.uint8 or data.ndim != 1:
            raise ValueError(f"segment {number}'s scans are missing or of unexpected types")
        where = arrays.get(f"scan_log_{number}_where")
        where = np.full((len(table), 2), -1, np.int64) if where is None else where
        if where.shape != (len(table), 2) or where.dtype.kind != "i" or (where[:, 0] >= len(paths)).any():
            raise ValueError(f"segment {number}'s places are damaged")
        sizes = table["points_bytes"].astype(np.int64) + table["values_bytes"]
        in_file = where[:, 0] < 0
        if (sizes < 0).any() or int(sizes[in_file].sum()) != data.size:
            raise ValueError(f"segment {number}'s table names {int(sizes[in_file].sum())} bytes, its data holds "
                             f"{data.size}")
        if not np.isfinite(table["pose"]).all() or not np.isfinite(table["mount"]).all():
            raise ValueError(f"segment {number} holds a pose that is not finite")
        scans, offset, raw = [], 0, data.tobytes()
        for row, (file, at), size in zip(table, where.tolist(), sizes.tolist()):
            points_size, values_size = int(row["points_bytes"]), int(row["values_bytes"])
            if file < 0:
                bytes_of = ScanBytes(raw[offset:offset + points_size], raw[offset + points_size:offset + size])
                offset += size
            else:
                if at < 0 or at + size > sizes_of[paths[file]]:
                    raise MissingLogFiles(f"{paths[file]} is shorter than the scan log names")
                bytes_of = ScanBytes.in_file((*places[file], at), points_size, values_size)
            scans.append(LoggedScan(int(row["stamp_ns"]), row["pose"].copy(), row["mount"].copy(),
                                    int(row["count"]), row["points_dtype"].decode(), int(row["kind"]),
                                    row["values_dtype"].decode(), int(row["columns"]), bytes_of))
        base = None
        if about.get("base") and "base_file" in about:
            file = about["base_file"]
            if not isinstance(file, int) or not 0 <= file < len(paths):
                raise ValueError(f"segment {number}'s base names no file of the list")
            chunk_files = about.get("base_chunk_files") or []
            if not isinstance(chunk_files, list) or not all(isinstance(n, int) and 0 <= n < len(paths)
                                                             for n in chunk_files):
                raise ValueError(f"segment {number}'s base names no chunk file of the list")
            base = SegmentBase(None, place=(*places[file], sizes_of[paths[file]]), num_classes=num_classes,
                               prior=prior, depends=frozenset(paths[n].name for n in chunk_files))
        elif about.get("base"):
            parts = [arrays.get(f"scan_log_{number}_base_{name}") for name in ("index", "count", "class", "value")]
            if any(part is None for part in parts):
                raise ValueError(f"segment {number}'s base is missing")
            index, counts, classes, values = parts
            store = VoxelStore(num_classes, prior)
            store.write(index.astype(np.int64), expand_rows(counts, classes, values.astype(np.float32), prior,
                                                            num_classes))
            base = SegmentBase(store, store.resident_bytes)
        position = about.get("base_position")
        segments.append(Segment(int(about.get("first_index", 0)), base,
                                None if position is None else np.asarray(position, np.float64), scans,
                                sum(scan.nbytes for scan in scans), resident=bool(in_file.all())))
    log._segments = deque(segments)
    log.frozen = int(meta.get("frozen", 0))
    log.frozen_stamp_ns = meta.get("frozen_stamp_ns")
    log.frozen_why = str(meta.get("frozen_why") or "")
    stamps, poses = arrays.get("scan_log_pending_stamps"), arrays.get("scan_log_pending_poses")
    if stamps is not None or poses is not None:
        if (stamps is None or poses is None or stamps.ndim != 1 or poses.shape != (len(stamps), 4, 4)
                or not np.isfinite(poses).all() or (np.diff(stamps) <= 0).any()):
            raise ValueError("its pending correction's keyframes are damaged")
        log.pending = (stamps.astype(np.int64), poses.astype(np.float64))
    calibration = meta.get("calibration")
    log.calibration = None if calibration is None else np.asarray(calibration, np.float64)
    return log

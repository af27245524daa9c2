"""``map_tool info``: what a map file holds (voxels, bounds, classes, settings, sizes, its scan
log), as JSON-ready values and as the plain-text report; and the class names of a map's classes.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


def class_names_for(metadata: dict) -> list[str] | None:
    """Class names for the map's classes: the metadata's, else SemanticKITTI's when the count matches."""
    from convbki_core.io.labels import load_label_map

    names = metadata.get("class_names")
    if isinstance(names, list) and len(names) == metadata["num_classes"]:
        return [str(name) for name in names]
    label_map = load_label_map("semantic_kitti")
    return list(label_map.class_names) if label_map.num_classes == metadata["num_classes"] else None


def map_info(path: str | Path) -> dict:
    """Everything ``info`` reports about one map file, as JSON-ready values (lengths in m)."""
    from convbki_core.inference.statistics import dirichlet_statistics
    from convbki_core.io.map_file import read_map
    from convbki_core.memory.store import VoxelStore

    metadata, indices, alpha = read_map(path, with_scan_log=True)
    resolution = float(metadata["resolution"])
    num_classes = metadata["num_classes"]
    bounds = None
    if len(indices):
        low, high = indices.min(axis=0), indices.max(axis=0)
        # Metres: the box the voxels fill, from the low corner of the first to the high corner of the last.
        bounds = {"index_min": low.tolist(), "index_max": high.tolist(),
                  "metres_min": [round(v, 9) for v in (low * resolution).tolist()],
                  "metres_max": [round(v, 9) for v in ((high + 1) * resolution).tolist()]}
    counts = np.bincount(dirichlet_statistics(alpha).label, minlength=num_classes)
    names = class_names_for(metadata)
    kernel = metadata.get("kernel")
    # Measured: the map as the mapper's global store holds it once loaded.
    store = VoxelStore(num_classes, prior=float(metadata.get("prior") or 1e-3))
    store.write(indices, alpha)
    memory = store.resident_bytes
    del store
    return {
        "file": str(path), "file_bytes": Path(path).stat().st_size,
        "format": metadata.get("format"), "version": metadata.get("version"),
        "frame_id": metadata.get("frame_id"), "resolution": resolution, "num_voxels": len(indices),
        "bounds": bounds, "prior": metadata.get("prior"),
        "kernel": kernel.get("kernel") if isinstance(kernel, dict) else None,
        "scans_integrated": metadata.get("scans_integrated"), "num_classes": num_classes,
        "class_voxels": [{"class": c, "name": names[c] if names else None, "voxels": int(counts[c])}
                         for c in range(num_classes)],
        "bytes_per_voxel": round(memory / len(indices), 1) if len(indices) else 0.0, "memory_bytes": memory,
        "merged_from": metadata.get("merged_from"),
        "scan_log": _log_info(metadata.get("scan_log")),
        "scan_log_missing": metadata.get("scan_log_missing"),
    }


def _log_info(log) -> dict | None:
    """What a map file's scan log holds (None: the file has none)."""
    if log is None:
        return None
    scans = log.scans()
    size = int(sum(scan.nbytes for _, scan in scans))
    folders = sorted({str(scan.data.place[0].path) for _, scan in scans if scan.data.place is not None})
    return {"scans": len(scans), "first_scan": scans[0][0] if scans else None, "folders": folders,
            "first_stamp_s": scans[0][1].stamp_ns / 1e9 if scans else None,
            "last_stamp_s": scans[-1][1].stamp_ns / 1e9 if scans else None,
            "points": int(sum(scan.count for _, scan in scans)), "bytes": size,
            "bytes_per_scan": round(size / len(scans)) if scans else 0, "segments": len(log.segments()),
            "frozen_scans": log.frozen, "frozen_why": log.frozen_why or None,
            "calibration": log.calibration is not None,
            "pending_correction_keyframes": None if log.pending is None else len(log.pending[0])}


def format_info(info: dict) -> str:
    """``info``'s plain-text report."""
    lines = [f"map:         {info['file']} ({_size(info['file_bytes'])})",
             f"frame_id:    {info['frame_id']}",
             f"resolution:  {info['resolution']:g} m",
             f"voxels:      {info['num_voxels']}"]
    bounds = info["bounds"]
    if bounds:
        lines.append("bounds:      index " + ", ".join(f"{axis} {lo}..{hi}" for axis, lo, hi in
                                                     zip("xyz", bounds["index_min"], bounds["index_max"])))
        lines.append("             metres " + ", ".join(f"{axis} {lo:.2f}..{hi:.2f}" for axis, lo, hi in
                                                      zip("xyz", bounds["metres_min"], bounds["metres_max"])))
    lines += [f"prior:       {info['prior']}", f"kernel:      {info['kernel']}"]
    if info["scans_integrated"] is not None:
        lines.append(f"scans:       {info['scans_integrated']}")
    if info["merged_from"]:
        lines.append(f"merged from: {', '.join(map(str, info['merged_from']))}")
    log = info["scan_log"]
    if log is None and info.get("scan_log_missing"):
        lines.append(f"scan log:    unusable: {info['scan_log_missing']} (no scan of this map can be moved)")
    elif log is None:
        lines.append("scan log:    none (no scan of this map can be moved by map_tool correct)")
    elif log["scans"]:
        frozen = f"; the {log['frozen_scans']} before are frozen ({log['frozen_why']})" if log["frozen_scans"] else ""
        lines.append(f"scan log:    scans {log['first_scan']}..{log['first_scan'] + log['scans'] - 1} (stamped "
                     f"{log['first_stamp_s']:.3f}..{log['last_stamp_s']:.3f} s), {_size(log['bytes'])}, "
                     f"{_size(log['bytes_per_scan'])} a scan{frozen}")
        if log["folders"]:
            lines.append(f"             its scans' bytes in {', '.join(log['folders'])}")
    else:
        lines.append(f"scan log:    empty; the {log['frozen_scans']} scans are frozen ({log['frozen_why']})")
    if log is not None and log["pending_correction_keyframes"]:
        lines.append(f"pending:     a SLAM's Path of {log['pending_correction_keyframes']} keyframes the node had not "
                     "applied when it saved: `map_tool correct MAP --out FIXED` applies it")
    lines.append(f"memory:      {info['bytes_per_voxel']:g} bytes per voxel in the mapper's store once loaded, "
                 f"{_size(info['memory_bytes'])} in all")
    lines.append(f"classes:     {info['num_classes']} (voxels per expected class; class 0: seen empty by free "
                 "space, not shown)")
    width = max([len(entry["name"] or "") for entry in info["class_voxels"]] + [8])
    for entry in info["class_voxels"]:
        lines.append(f"  {entry['class']:>3} {entry['name'] or '':<{width}} {entry['voxels']:>10}")
    return "\n".join(lines)


def _size(count: int) -> str:
    for unit, scale in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if count >= scale:
            return f"{count / scale:.1f} {unit}"
    return f"{count} B"


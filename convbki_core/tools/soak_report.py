"""The outputs of ``soak``: the table printed as it goes, and soak.csv, soak.json and soak.png."""

from __future__ import annotations

import csv
import io
import json
import math
import os
from dataclasses import asdict
from pathlib import Path

import numpy as np

from convbki_core.io.atomic import atomic_write_bytes
from convbki_core.tools.soak_measure import Checkpoint, SoakResult

# (field, header, width, format) of the printed table; the CSV and JSON hold every field.
COLUMNS = [("scans", "scans", 6, "d"), ("voxels", "voxels", 10, ",d"), ("store_voxels", "in store", 10, ",d"),
           ("rss_mb", "RSS MB", 7, ".0f"), ("store_mb", "store MB", 8, ".1f"), ("log_mb", "log MB", 7, ".1f"),
           ("rss_per_voxel_b", "RSS B/vx", 8, ".0f"),
           ("rss_growth_per_voxel_b", "dRSS B/vx", 9, ".1f"), ("store_per_voxel_b", "store B/vx", 10, ".1f"),
           ("excess_mb", "excess MB", 9, ".1f"), ("live_excess_mb", "live exc", 8, ".1f"),
           ("malloc_free_mb", "free MB", 7, ".1f"), ("occupied", "occupied", 8, ",d"),
           ("update_ms", "update ms", 9, ".1f"), ("update_p10_ms", "p10", 5, ".1f"), ("query_ms", "query ms", 8, ".1f"),
           ("query_p10_ms", "p10", 5, ".1f"), ("other_cores", "others", 6, ".2f")]


def table_header() -> str:
    return " ".join(f"{header:>{width}}" for _, header, width, _ in COLUMNS)


def table_row(row: Checkpoint) -> str:
    values = asdict(row)
    cells = []
    for name, _, width, spec in COLUMNS:
        value = values[name]
        text = "-" if isinstance(value, float) and math.isnan(value) else format(value, spec)
        cells.append(f"{text:>{width}}")
    return " ".join(cells)


def csv_bytes(result: SoakResult) -> bytes:
    buffer = io.StringIO()
    names = list(asdict(result.baseline))
    writer = csv.DictWriter(buffer, fieldnames=names, lineterminator="\n")
    writer.writeheader()
    for row in result.checkpoints:
        writer.writerow({k: (round(v, 4) if isinstance(v, float) else v) for k, v in asdict(row).items()})
    return buffer.getvalue().encode()


def _json_safe(value):
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_json_safe(v) for v in value]
    return value


def plot_png(result: SoakResult, title: str) -> bytes:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = result.checkpoints
    scans = [r.scans for r in rows]
    figure, (memory, per_voxel, timing) = plt.subplots(1, 3, figsize=(17, 4.6), gridspec_kw={"wspace": 0.38})
    memory.plot(scans, [r.rss_mb - result.baseline.rss_mb for r in rows], "o-", label="RSS growth since scan 1")
    memory.plot(scans, [r.store_mb - result.baseline.store_mb for r in rows], "s-", label="store growth")
    memory.plot(scans, [r.log_mb for r in rows], "d-", label="scan log (bounded)")
    memory.plot(scans, [r.excess_mb for r in rows], "^-", label="excess (RSS growth - store and log growth)")
    memory.set_ylabel("MB")
    voxels = memory.twinx()
    voxels.plot(scans, [r.voxels / 1e6 for r in rows], "--", color="grey", label="stored voxels")
    voxels.set_ylabel("stored voxels [millions]")
    voxels.set_ylim(bottom=0)
    handles = memory.get_legend_handles_labels()[0] + voxels.get_legend_handles_labels()[0]
    memory.legend(handles, [h.get_label() for h in handles], loc="upper left", fontsize=8)
    memory.set_title("memory and map size")
    per_voxel.plot(scans, [r.rss_growth_per_voxel_b for r in rows], "o-", label="RSS growth / new voxels")
    per_voxel.plot(scans, [r.store_per_voxel_b for r in rows], "s-", label="store bytes / store voxels")
    per_voxel.set_ylabel("bytes per voxel")
    per_voxel.legend(fontsize=8)
    per_voxel.set_title("memory per stored voxel")
    # Every scan in drive order: on a shared machine another process slows whole stretches of
    # scans, which shows as a burst in time, while a cost that followed the map would rise with
    # the stored voxels of the left panel.
    scan_numbers = range(2, len(result.update_ms) + 2)
    timing.plot(scan_numbers, result.update_ms, ".", markersize=2, alpha=0.4, label="update (voxelise + update)")
    timing.plot(scan_numbers, result.query_ms, ".", markersize=2, alpha=0.4, label="query (window move)")
    timing.plot(scans, [r.update_ms for r in rows], "o-", color="C0", label="update, median of each row")
    timing.plot(scans, [r.update_p10_ms for r in rows], "v:", color="C0", label="update, 10th percentile")
    timing.plot(scans, [r.query_ms for r in rows], "s-", color="C1", label="query, median of each row")
    timing.set_ylabel("ms per scan")
    if result.update_ms:  # the odd scan that waits on another process would squash the rest
        timing.set_ylim(0, 1.5 * float(np.percentile(result.update_ms + result.query_ms, 99)))
    others = timing.twinx()
    others.plot(scans, [r.other_cores for r in rows], "--", color="grey", label="other processes (right axis)")
    others.set_ylabel("CPU cores used by other processes")
    others.set_ylim(0, max(2.0, os.cpu_count() or 1))
    handles = timing.get_legend_handles_labels()[0] + others.get_legend_handles_labels()[0]
    timing.legend(handles, [h.get_label() for h in handles], fontsize=8, loc="upper left")
    timing.set_title("time per scan")
    for axis in (memory, per_voxel, timing):
        axis.set_xlabel("scans")
        axis.set_ylim(bottom=0)
        axis.grid(alpha=0.3)
    figure.suptitle(title, fontsize=10)
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=100, bbox_inches="tight")
    plt.close(figure)
    return buffer.getvalue()


def write_outputs(result: SoakResult, folder: Path, settings: dict) -> dict[str, Path]:
    """soak.csv, soak.json and soak.png in ``folder``, each written atomically."""
    folder.mkdir(parents=True, exist_ok=True)
    paths = {kind: folder / f"soak.{kind}" for kind in ("csv", "json", "png")}
    atomic_write_bytes(paths["csv"], csv_bytes(result))
    report = {"settings": settings, "summary": result.summary(), "baseline": asdict(result.baseline),
              "checkpoints": [asdict(r) for r in result.checkpoints],
              "per_scan": {"update_ms": [round(t, 3) for t in result.update_ms],
                           "query_ms": [round(t, 3) for t in result.query_ms],
                           "occupied": result.occupied, "voxels": result.voxels}}
    atomic_write_bytes(paths["json"], (json.dumps(_json_safe(report), indent=2) + "\n").encode())
    title = (f"soak: {settings['scans']} scans, seed {settings['seed']}, bounds {settings['bounds']}, "
             f"{settings['machine']}")
    atomic_write_bytes(paths["png"], plot_png(result, title))
    return paths

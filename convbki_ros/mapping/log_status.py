"""The scan log on ``/diagnostics``: how far back a correction reaches (scans, seconds), where
the log lives (memory and its folder) and whether its files are being written."""

from __future__ import annotations


def scan_log_values(log, newest_received_ns: int | None) -> list[tuple[str, object]]:
    """The scan log's key/values (``log``: the mapper's ``ScanLog``); ``newest_received_ns``: the
    stamp of the newest cloud received, for the live map's lag."""
    reach, newest = log.reach_ns, log.newest_ns
    folder = log.folder
    values = [("scan_log_scans", len(log)), ("scan_log_megabytes", f"{log.nbytes / 1e6:.1f}"),
              ("scan_log_frozen", log.frozen),
              ("scan_log_reach_stamp", "" if reach is None else f"{reach / 1e9:.3f}"),
              ("scan_log_reach_s", "" if reach is None else f"{(newest - reach) / 1e9:.1f}"),
              ("scan_log_folder", "" if folder is None else str(folder.path)),
              ("scan_log_disk_megabytes", f"{log.disk_bytes / 1e6:.1f}"),
              ("scan_log_write_backlog_megabytes", "" if folder is None else f"{folder.backlog_bytes / 1e6:.1f}"),
              ("scan_log_write_error", "" if folder is None or folder.error is None else folder.error)]
    if newest_received_ns is not None:
        lag = 0.0 if newest is None else max(0.0, (newest_received_ns - newest) / 1e9)
        values.append(("live_lag_s", f"{lag:.2f}"))
    return values

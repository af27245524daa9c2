"""The correction thread's waits on the live stream: for the clouds a Path reaches, and for the
update thread to take the clouds at hand before each scan a correction maps again."""

from __future__ import annotations

import time

from convbki_ros.inputs.transforms import stamp_to_ns


def wait_for_scans_up_to(core, stamp: int, longest: float = 5.0) -> None:
    """Let the clouds stamped up to ``stamp`` (the newest keyframe's) arrive and the update
    thread integrate them first, for ``longest`` seconds at most: the Path moves them too.
    Arrived means a cloud stamped at or after ``stamp`` is queued or logged: a Path, a small
    message on a topic of its own, can overtake the clouds it reaches, which would then be
    mapped after the correction at their uncorrected poses; the cloud the update thread has
    taken and not yet logged counts as queued. Keyframes more than ``longest``
    seconds newer than the newest cloud are not waited for (no cloud is that late), nor any
    when no cloud is logged or queued."""
    queue = core.queue
    deadline = time.monotonic() + longest
    with queue.changed:
        while not queue.stopping and time.monotonic() < deadline:
            # The cloud the update thread is integrating counts as queued: it is not logged yet.
            queued = [stamp_to_ns(p.msg.header.stamp) for p in queue.clouds] + \
                ([] if queue.in_flight is None else [queue.in_flight])
            logged = core.mapper.scan_log.newest_ns
            newest = max(queued + ([] if logged is None else [logged]), default=None)
            # (Nothing logged nor queued: no stream to wait for, e.g. a map loaded without a log.)
            arrived = newest is None or newest >= stamp or stamp - newest > longest * 1e9
            if arrived and (not queued or min(queued) > stamp):
                return
            queue.changed.wait(0.05)


def let_live_scans_first(queue, stopping, longest: float = 1.0, backlog: int = 4) -> None:
    """Before each scan mapped again: while clouds ready to integrate wait in the queue, let
    the update thread take them first. While at most ``backlog`` wait, for ``longest`` seconds
    at most a scan, so that a stream the update thread only just keeps up with still leaves the
    correction a share; while more wait, until they are fewer, so that a correction never
    makes the live map fall behind and drop clouds (it goes on when the stream pauses or ends)."""
    deadline = time.monotonic() + longest
    with queue.changed:
        while not queue.stopping and not stopping():
            ready = queue.ready()
            if ready == 0 or (ready <= backlog and time.monotonic() >= deadline):
                return
            queue.changed.wait(0.02)

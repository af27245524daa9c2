"""Pacing ``play_bag`` to a mapper's progress (``--wait-for-node``, ``--wait-for-inputs``): the
node's ``/diagnostics`` read on the player's node, clouds let out while at most half of its queue
(and of the writers' history) is in flight, clouds the node never received given up after a while,
and at the end what the node did with them, in one line.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

from convbki_core.tools.cli import UserError
from convbki_ros.tools.bag_player import DEPTH

NODE_SILENT_S = 15.0  # with --wait-for-node: the node sent no /diagnostics for this long: it is gone
LOST_AFTER_S = 10.0  # with --wait-for-node: clouds the node has not received after this long without progress are lost


def _count(values: dict[str, str], key: str, default: int = 0) -> int:
    """A diagnostic value as a count (``default`` when missing or not a number)."""
    try:
        return int(values.get(key, default))
    except ValueError:
        return default


class NodeGone(Exception):
    """The node the replay is paced to stopped reporting."""


@dataclass
class NodeProgress:
    """What one /diagnostics report of the paced node says."""

    scans_in: int
    integrated: int
    dropped: int
    queue: int
    queue_limit: int
    reasons: dict[str, int]
    publishers: dict[str, int]  # per input of the node: the publishers its reader has matched


class NodePacer:
    """Paces the clouds to a mapper's progress as its /diagnostics report it (``--wait-for-node``).

    Clouds in flight are those sent that the node has not yet reported received, plus those in
    its queue; at most half of the node's queue (and of the writers' history) is let in flight,
    so neither the DDS histories nor the node's queue can overflow, whatever its speed.
    """

    def __init__(self, node: Any, target: str):
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.executors import SingleThreadedExecutor

        self.target = target
        self.latest: NodeProgress | None = None
        self.heard = time.monotonic()
        self.baseline: NodeProgress | None = None
        self.published = 0
        self.lost = 0  # clouds given up as lost: sent, never received by the node
        self.progress_at = time.monotonic()  # when the node last received a cloud, or one was sent
        self.received_seen = 0
        self.dropped = self.missing = 0  # set by finish()
        self.first_sent: float | None = None
        self.executor = SingleThreadedExecutor(context=node.context)
        self.executor.add_node(node)
        node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diagnostics, 10)

    def _on_diagnostics(self, array: Any) -> None:
        for status in array.status:
            if status.name.split(":")[0] != self.target:
                continue
            values = {item.key: item.value for item in status.values}
            reasons = {key[len("dropped."):]: _count(values, key) for key in values if key.startswith("dropped.")}
            publishers = {key[len("publishers."):]: _count(values, key) for key in values
                          if key.startswith("publishers.")}
            self.latest = NodeProgress(_count(values, "scans_in"), _count(values, "integrated"),
                                       _count(values, "dropped"), _count(values, "queue"),
                                       _count(values, "queue_limit", 40), reasons, publishers)
            self.heard = time.monotonic()

    def _spin(self, seconds: float) -> None:
        self.executor.spin_once(timeout_sec=seconds)

    def wait_for_node(self, timeout: float, ok: Callable[[], bool]) -> bool:
        """Block until the node has reported once; False when ``ok()`` turned False."""
        deadline = time.monotonic() + timeout
        while self.latest is None:
            if not ok():
                return False
            if time.monotonic() > deadline:
                raise UserError(f"no /diagnostics from {self.target} within {timeout:g} s (is it running? "
                                "--wait-for-node takes its fully qualified name, e.g. /convbki_mapper)")
            self._spin(0.1)
        self.baseline = self.latest
        return True

    def wait_for_inputs(self, timeout: float, ok: Callable[[], bool], unplayed: Iterable[str] = ()) -> list[str]:
        """Block until the node reports a matched publisher on each of its inputs but those in
        ``unplayed`` (inputs the bag has nothing for: no one will publish them), so that nothing
        sent from now on is lost to matching, or ``timeout``; the inputs still without one. A node
        that reports no inputs has none to wait for."""
        deadline = time.monotonic() + timeout
        unplayed = set(unplayed)
        while True:
            unmatched = sorted(name for name, count in self.latest.publishers.items()
                               if count < 1 and name not in unplayed)
            if not unmatched or time.monotonic() > deadline or not ok():
                return unmatched
            self._spin(0.05)

    @property
    def window(self) -> int:
        assert self.latest is not None
        return max(1, min(DEPTH, self.latest.queue_limit) // 2)

    def received(self) -> int:
        assert self.latest is not None and self.baseline is not None
        received = self.latest.scans_in - self.baseline.scans_in
        if received > self.received_seen:
            self.received_seen, self.progress_at = received, time.monotonic()
        return received

    def in_flight(self) -> int:
        return max(0, self.published - self.lost - self.received()) + self.latest.queue

    def _give_up_stalled(self) -> bool:
        """Clouds sent that the node has not received while it went LOST_AFTER_S without
        receiving any are lost (DDS lost them, e.g. after the player was stopped): counted, and
        the replay goes on. True when some were given up now."""
        waiting = self.published - self.lost - self.received()
        if waiting <= 0 or time.monotonic() - self.progress_at < LOST_AFTER_S:
            return False
        self.lost += waiting
        self.progress_at = time.monotonic()
        return True

    def _check_alive(self) -> None:
        silent = time.monotonic() - self.heard
        if silent > NODE_SILENT_S:
            raise NodeGone(f"{self.target} sent no /diagnostics for {silent:.0f} s after {self.published} clouds")

    def wait_for_room(self, clouds: int, ok: Callable[[], bool]) -> bool:
        """Block until ``clouds`` more fit in flight; False when ``ok()`` turned False."""
        self._spin(0.0)
        while self.in_flight() + clouds > self.window:
            if not ok():
                return False
            self._check_alive()
            self._give_up_stalled()
            self._spin(0.05)
        return True

    def sent(self, clouds: int) -> None:
        if self.first_sent is None:
            self.first_sent = time.monotonic()
        self.published += clouds
        self.progress_at = time.monotonic()

    def finish(self, ok: Callable[[], bool]) -> str:
        """Wait until the node has received every cloud sent and emptied its queue (or stops
        reporting); what it did with them, in one line."""
        while ok():
            latest = self.latest
            received = self.received()
            if received >= self.published - self.lost and latest.integrated + latest.dropped >= latest.scans_in:
                break  # every cloud sent arrived (or was given up), every one that arrived was dealt with
            self._check_alive()
            self._give_up_stalled()
            self._spin(0.1)
        latest, baseline = self.latest, self.baseline
        dropped = latest.dropped - baseline.dropped
        reasons = ", ".join(f"{reason} {count - baseline.reasons.get(reason, 0)}"
                            for reason, count in sorted(latest.reasons.items())
                            if count > baseline.reasons.get(reason, 0))
        self.dropped = dropped
        self.missing = self.published - (latest.scans_in - baseline.scans_in)
        took = f" in {time.monotonic() - self.first_sent:.2f} s from the first" if self.first_sent else ""
        return (f"{self.target} received {latest.scans_in - baseline.scans_in} of {self.published} clouds, "
                f"integrated {latest.integrated - baseline.integrated}, dropped {dropped}"
                f"{f' ({reasons})' if reasons else ''}{took}")

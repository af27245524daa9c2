"""No callback ends the node: every subscription, timer, service and parameter callback runs
inside a guard.

rclpy lets an exception raised in a callback leave ``spin()``, and with it the node: one odd
request from anyone on the domain (a path too long for the file system, a value no check
foresaw) would stop the mapping of a whole session. A guarded callback that fails instead

* logs one ERROR line naming the callback and the error (at most one per callback every
  ``REPEAT_S`` seconds: a flood of bad requests does not flood the log),
* is counted (``callback_errors`` on /diagnostics, with the last error),
* answers what its caller waits for: a service responds ``success: false`` with the reason, a
  parameter check refuses the change with the reason.

``MapperNode`` guards every callback made through it, rclpy's own parameter services
included (it overrides ``create_subscription``, ``create_service`` and ``create_timer``), and
the node's ``main`` keeps spinning past anything that still reaches the executor. What a failed
callback did before it raised is not undone; the checks that refuse bad requests come first in
every callback, so a refused request has changed nothing.
"""

from __future__ import annotations

import functools
import inspect
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

REPEAT_S = 5.0  # one error line per callback this often at most


@dataclass
class CallbackErrors:
    """Callbacks that raised, for /diagnostics."""

    count: int = 0
    last: str = ""


def describe(error: BaseException) -> str:
    """An exception in one line: its class and the first line of its message, cut when long."""
    text = str(error).splitlines()[0] if str(error) else ""
    text = text if len(text) <= 300 else text[:300] + "..."
    return f"{error.__class__.__name__}{': ' + text if text else ''}"


class CallbackGuard:
    """Wraps the node's callbacks (see the module's docstring); ``logger`` an rclpy logger."""

    def __init__(self, logger):
        self.logger = logger
        self.errors = CallbackErrors()
        self._lock = threading.Lock()
        self._last_logged: dict[str, float] = {}

    def failed(self, what: str, error: BaseException) -> str:
        """Count and (throttled) log the failure of ``what``; the line said to its caller."""
        line = f"{what} failed: {describe(error)}"
        now = time.monotonic()
        with self._lock:
            self.errors.count += 1
            self.errors.last = line
            quiet = now - self._last_logged.get(what, -REPEAT_S) < REPEAT_S
            if not quiet:
                self._last_logged[what] = now
        if not quiet:
            self.logger.error(f"{line} (the node goes on; {self.errors.count} callback errors so far)")
        return line

    def call(self, what: str, callback: Callable) -> Callable:
        """A subscription's or a timer's callback: a failure is logged and counted."""

        @functools.wraps(callback)
        def guarded(*args):
            try:
                return callback(*args)
            except Exception as error:
                self.failed(what, error)
                return None

        return guarded

    def service(self, what: str, callback: Callable) -> Callable:
        """A service callback ``(request, response) -> response``, plain or async: a failure
        answers ``success: false`` with the reason (where the response has those fields)."""

        def answer(response, error: BaseException):
            line = self.failed(what, error)
            if hasattr(response, "success"):
                response.success = False
                response.message = line
            return response

        if inspect.iscoroutinefunction(callback):
            @functools.wraps(callback)
            async def guarded_async(request, response):
                try:
                    return await callback(request, response)
                except Exception as error:
                    return answer(response, error)

            return guarded_async

        @functools.wraps(callback)
        def guarded(request, response):
            try:
                return callback(request, response)
            except Exception as error:
                return answer(response, error)

        return guarded

    def parameter_check(self, callback: Callable) -> Callable:
        """An on-set-parameters callback: a failure refuses the change, with the reason."""
        from rcl_interfaces.msg import SetParametersResult

        @functools.wraps(callback)
        def guarded(parameters):
            try:
                return callback(parameters)
            except Exception as error:
                return SetParametersResult(successful=False, reason=self.failed("checking parameters", error))

        return guarded

    def parameter_filter(self, callback: Callable) -> Callable:
        """A pre-set-parameters callback (returns the parameters to set): a failure passes them
        on unchanged, for the checks to refuse or accept."""

        @functools.wraps(callback)
        def guarded(parameters):
            try:
                return callback(parameters)
            except Exception as error:
                self.failed("preparing parameters", error)
                return parameters

        return guarded

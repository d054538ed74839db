"""The signals that stop a long-running process, and how a handler is given them: one
place for the API, ``mcam serve``, the worker and its decoding children, the device
daemons and a training run (which all sit above :mod:`models`)."""

from __future__ import annotations

import signal
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from types import FrameType
from typing import Any

#: The signals that stop a long-running process: a terminal's Ctrl-C and a service
#: manager's stop (both reach a whole process group).
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


def handle_stop_signals(handler: Callable[[int, FrameType | None], Any] | signal.Handlers) -> None:
    """Give each of :data:`STOP_SIGNALS` to ``handler``."""
    for stop_signal in STOP_SIGNALS:
        signal.signal(stop_signal, handler)


#: How often :func:`wait_for_stop` looks whether a stop signal came (s).
STOP_POLL_S = 0.1


@contextmanager
def noting_stop_signals() -> Iterator[list[int]]:
    """Handle :data:`STOP_SIGNALS` by noting them, and nothing else, in the list yielded
    (for :func:`wait_for_stop`; those that come while the caller stops are noted too),
    and ignore them on leaving (:func:`ignore_stop_signals`): only the interpreter's exit
    is left then, and it gives them their default action back, so one more ended the
    process by it (exit -15 or -2, no message).

    A handler that set a ``threading.Event`` took the lock inside it: a second signal
    that came while the first's handler (or the main thread) held that lock ran a
    handler that waited for it for good, so the process hung and ignored every later
    signal (``mcam device`` under a burst of SIGINT and SIGTERM), or nested handlers
    until a RecursionError. Appending to a list takes no lock."""
    received: list[int] = []
    handle_stop_signals(lambda signum, _frame: received.append(signum))
    try:
        yield received
    finally:
        ignore_stop_signals()


def ignore_stop_signals() -> None:
    """Ignore :data:`STOP_SIGNALS` from now on, quietly. One that comes while a Python
    handler is being replaced is noted by the C handler and then found with SIG_IGN in
    its place, which Python reports on stderr as a traceback of "OSError: Signal 2
    ignored due to race condition" (3 of 40 stops under a burst of signals). The C
    handler of one that came just before may note it after the new handlers are set, on
    a loaded machine, and the main thread finds it wherever it is later (a Redis client
    disconnecting: 1 in CI's 6 bursts), so that report is left out for the rest of the
    process (:func:`leave_out_signal_races`)."""
    leave_out_signal_races()
    handle_stop_signals(signal.SIG_IGN)


def is_signal_race(unraisable: sys.UnraisableHookArgs) -> bool:
    """Whether ``unraisable`` is Python's report of one of :data:`STOP_SIGNALS` found
    ignored after its C handler noted it ("Signal 2 ignored due to race condition")."""
    return isinstance(unraisable.exc_value, OSError) and str(unraisable.exc_value) in {
        f"Signal {int(stop_signal)} ignored due to race condition" for stop_signal in STOP_SIGNALS
    }


def leave_out_signal_races() -> None:
    """Leave the reports :func:`is_signal_race` out of ``sys.unraisablehook`` from now
    on; every other report goes to the hook there was. Setting it again does nothing."""
    previous = sys.unraisablehook
    if getattr(previous, "leaves_out_signal_races", False):
        return

    def report(unraisable: sys.UnraisableHookArgs) -> None:
        if not is_signal_race(unraisable):
            previous(unraisable)

    report.leaves_out_signal_races = True  # type: ignore[attr-defined]
    sys.unraisablehook = report


def wait_for_stop(received: list[int], finished: Callable[[float], bool] | None = None,
                  poll_s: float = STOP_POLL_S) -> bool:
    """Wait until a stop signal is in ``received`` (from :func:`noting_stop_signals`:
    True) or ``finished`` says the work ended by itself (False); the caller then stops
    the work. ``finished(timeout_s)`` waits up to ``timeout_s`` seconds and says whether
    it ended (``threading.Event.wait`` will do); None: only a signal ends the wait."""
    while not received:
        if finished is None:
            time.sleep(poll_s)
        elif finished(poll_s):
            return False
    return True

"""The signals that stop a long-running process, and how a handler is given them: one
place for the API, ``mcam serve``, the worker and its decoding children, the device
daemons and a training run (which all sit above :mod:`models`)."""

from __future__ import annotations

import signal
from collections.abc import Callable
from types import FrameType
from typing import Any

#: The signals that stop a long-running process: a terminal's Ctrl-C and a service
#: manager's stop (both reach a whole process group).
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


def handle_stop_signals(handler: Callable[[int, FrameType | None], Any] | signal.Handlers) -> None:
    """Give each of :data:`STOP_SIGNALS` to ``handler``."""
    for stop_signal in STOP_SIGNALS:
        signal.signal(stop_signal, handler)

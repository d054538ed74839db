"""Module-level functions for tests/worker/test_child_process.py to run in a spawned child
(a child imports what it runs by name, so these cannot live in the test module's fixtures)."""

from __future__ import annotations

import os
import time

from models.errors import InvalidInputError

#: Set by :func:`mark_started` in the child.
STARTED_VARIABLE = "MCAM_TEST_CHILD_STARTED"


def mark_started(value: str) -> None:
    """An initializer: leaves ``value`` where :func:`started` finds it."""
    os.environ[STARTED_VARIABLE] = value


def started() -> str | None:
    """What the initializer left."""
    return os.environ.get(STARTED_VARIABLE)


def pid() -> int:
    return os.getpid()


def refuse(message: str) -> None:
    raise InvalidInputError(message)


def fail() -> None:
    raise RuntimeError("a bug in the child")


def sleep(seconds: float) -> None:
    time.sleep(seconds)


def exit_now(code: int) -> None:
    os._exit(code)

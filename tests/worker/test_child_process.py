"""Tests of worker/child_process.py: calls in a spawned child, stopped by killing it."""

from __future__ import annotations

import os
import signal
import traceback
from collections.abc import Iterator

import pytest

from models.errors import InvalidInputError
from tests.worker import child_calls
from worker.child_process import ChildDiedError, ChildProcess


class Cancelled(Exception):
    """What the tests' should_stop raises."""


def never() -> None:
    """should_stop for calls that are not stopped."""


def alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


@pytest.fixture
def child() -> Iterator[ChildProcess]:
    process = ChildProcess(child_calls.mark_started, ("yes",))
    yield process
    process.close()


def test_calls_run_in_one_initialized_child(child: ChildProcess) -> None:
    assert child.call(child_calls.started, (), never) == "yes"
    first = child.call(child_calls.pid, (), never)
    assert first != os.getpid() and first == child.pid
    assert child.call(child_calls.pid, (), never) == first
    assert child.call(pow, (2, 10), never) == 1024


def test_the_childs_exceptions_are_raised_here(child: ChildProcess) -> None:
    with pytest.raises(InvalidInputError, match="^bad frame$"):
        child.call(child_calls.refuse, ("bad frame",), never)
    with pytest.raises(RuntimeError, match="a bug in the child"):
        child.call(child_calls.fail, (), never)
    assert child.call(child_calls.started, (), never) == "yes"


def test_a_childs_exception_carries_its_traceback_for_the_caller_to_log_once(
    child: ChildProcess, caplog: pytest.LogCaptureFixture
) -> None:
    """ChildProcess logged the child's traceback of every failed call itself ("call in
    child N failed:"), beside what its caller logged: a job meeting a broken model
    install, which the job processor reports in one line, logged a full traceback too.
    The child's traceback now travels with its exception as a note, which the caller's
    ``log.exception`` prints, and nothing is logged here."""
    with pytest.raises(RuntimeError) as raised:
        child.call(child_calls.fail, (), never)
    assert caplog.records == []
    (note,) = raised.value.__notes__
    assert f"raised in child {child.pid}" in note
    assert 'raise RuntimeError("a bug in the child")' in note
    assert note in "".join(traceback.format_exception(raised.value))


def test_should_stop_kills_the_child_and_the_next_call_starts_another(
    child: ChildProcess,
) -> None:
    first = child.call(child_calls.pid, (), never)
    polls = []

    def stop_on_third_poll() -> None:
        polls.append(1)
        if len(polls) == 3:
            raise Cancelled

    with pytest.raises(Cancelled):
        child.call(child_calls.sleep, (600.0,), stop_on_third_poll)
    assert len(polls) == 3 and not alive(first)
    second = child.pid
    assert second is not None and second != first and alive(second)  # started at once
    assert child.call(child_calls.pid, (), never) == second
    assert child.call(child_calls.started, (), never) == "yes"


def test_a_child_that_dies_fails_its_call_clearly(
    child: ChildProcess, caplog: pytest.LogCaptureFixture
) -> None:
    with pytest.raises(ChildDiedError, match=r"died \(exit 3"):
        child.call(child_calls.exit_now, (3,), never)
    assert "died while it worked (exit 3)" in caplog.text
    assert child.pid is not None and alive(child.pid)
    assert child.call(pow, (3, 2), never) == 9


def test_the_child_leaves_sigterm_to_its_parent(child: ChildProcess) -> None:
    """A service manager's SIGTERM to the process group must not kill the decode."""
    pid = child.call(child_calls.pid, (), never)
    os.kill(pid, signal.SIGTERM)
    assert child.call(child_calls.pid, (), never) == pid


def test_close_ends_the_child() -> None:
    process = ChildProcess()
    pid = process.call(child_calls.pid, (), never)
    process.close()
    assert not alive(pid) and process.pid is None

"""A child process the worker hands one call at a time, and kills when it must stop.

Usage (a job consumer thread of the worker)::

    child = ChildProcess(warm_up, ("auto",))           # spawned now, warms up meanwhile
    result = child.call(decode_still, (name, codes, params), should_stop=ctx.check)
    child.close()

Why: most of a refined or graph-cut decode holds the interpreter lock (PyMaxflow's
min-cuts, seconds each on a large frame). Run in a worker thread, a long one starved
the worker's other threads: its heartbeat went stale (the service reported no worker),
its device leases lapsed, and a cancelled job ran on for minutes since nothing could
stop it between two min-cuts. In a child process the worker's threads keep running,
and ``should_stop`` (polled every :data:`POLL_S` while the child works) ends the call
at once: the child is killed, the exception ``should_stop`` raised propagates, and the
next call starts a fresh child.

The child's own exception is raised in the caller, the child's traceback added to it as
a note (``logging``'s ``exception`` prints it) unless it is a :class:`McamError`: the
caller logs it once, or, for an error it reports in one line (a broken model install),
not at all.

A child that dies while working (killed, out of memory) fails its call with
:class:`ChildDiedError` (and a warning in the log); a new child is started at once
after a kill or a death, so the next call does not wait for one to warm up. Children
ignore SIGINT and SIGTERM and exit by themselves when their worker is gone
(:func:`follow_parent`), so a worker killed outright leaves none behind. They are
started with both signals blocked (:func:`signals_blocked`) until they ignore them: a
Ctrl-C while a child was still starting Python killed it mid-import, with a ``Fatal
Python error: init_import_site`` or a KeyboardInterrupt traceback on the terminal.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import pickle
import signal
import threading
import time
import traceback
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess
from typing import Any

from models.errors import McamError
from models.stop_signals import STOP_SIGNALS, handle_stop_signals

log = logging.getLogger(__name__)

#: How often a waiting call asks ``should_stop`` (s).
POLL_S = 0.2
#: How often a child checks that its worker is still alive (s).
PARENT_CHECK_S = 1.0
#: How long a closing child may take to exit before it is killed (s).
CLOSE_TIMEOUT_S = 5.0


class ChildDiedError(McamError):
    """The child process died while it worked on a call."""

    code = "decoder_crashed"


def follow_parent(parent: int) -> None:
    """In a child, first: leave the group's signals to the parent
    (:func:`leave_signals_to_parent`) and exit with it (:func:`watch_parent`)."""
    watch_parent(parent)
    leave_signals_to_parent()


def watch_parent(parent: int) -> None:
    """In a child: exit once the process ``parent`` (its pid, passed in since it may be
    gone before this runs) is no longer this process's parent. A worker killed outright
    (SIGKILL, out of memory) cannot stop its children, and a child waiting for work
    would otherwise wait for ever."""

    def exit_with_parent() -> None:
        while os.getppid() == parent:
            time.sleep(PARENT_CHECK_S)
        os._exit(0)

    threading.Thread(target=exit_with_parent, daemon=True).start()


def leave_signals_to_parent() -> None:
    """In a child: ignore SIGINT and SIGTERM. A terminal's Ctrl-C or a service manager's
    SIGTERM reaches the whole process group; the worker handles them (it finishes or
    hands back its work) and ends its children itself, by closing their input, by
    SIGKILL, or by dying (:func:`watch_parent`). A child killed by that SIGTERM would
    look like a crashed decode and cost its job a delivery.

    The child was started with these signals blocked (:func:`signals_blocked`): one
    sent to the group while it started waits, and ignoring it drops it here."""
    handle_stop_signals(signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, STOP_SIGNALS)


@contextmanager
def signals_blocked() -> Iterator[None]:
    """Block :data:`STOP_SIGNALS` in the calling thread while children are started in
    it: a child inherits the mask through its exec, so a Ctrl-C that reaches the process
    group while the child starts Python (before :func:`leave_signals_to_parent`) waits
    instead of killing it mid-import. The parent loses none: another of its threads
    takes the signal, or this one as the block ends (as multiprocessing's resource
    tracker starts its own process)."""
    blocked = signal.pthread_sigmask(signal.SIG_BLOCK, STOP_SIGNALS)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, blocked)


def _serve(
    conn: Connection, parent: int, initializer: Callable[..., Any] | None, initargs: tuple
) -> None:
    """The child's loop: run each ``(function, args)`` received, send back ``("ok",
    result)`` or ``("error", exception, traceback text)``; stop at end of input."""
    follow_parent(parent)
    if initializer is not None:
        initializer(*initargs)
    while True:
        try:
            function, args = conn.recv()
        except EOFError:
            return
        try:
            reply: tuple[Any, ...] = ("ok", function(*args))
        except Exception as exc:
            reply = ("error", _portable(exc), traceback.format_exc())
        conn.send(reply)


def _portable(exc: Exception) -> Exception:
    """``exc`` if it survives pickling, else a RuntimeError naming it."""
    try:
        pickle.loads(pickle.dumps(exc))
    except Exception:
        return RuntimeError(f"{type(exc).__name__}: {exc}")
    return exc


class ChildProcess:
    """One spawned child running calls one at a time (see the module docstring)."""

    def __init__(
        self, initializer: Callable[..., Any] | None = None, initargs: tuple = ()
    ) -> None:
        self.initializer = initializer
        self.initargs = initargs
        self._context = multiprocessing.get_context("spawn")
        self._process: BaseProcess | None = None
        self._conn: Connection | None = None
        self.start()

    @property
    def pid(self) -> int | None:
        """The running child's pid (None between a kill and the next call)."""
        return self._process.pid if self._process is not None else None

    def start(self) -> None:
        """Spawn the child if none runs (it initializes while the worker goes on)."""
        if self._process is not None and self._process.is_alive():
            return
        self._discard()
        ours, theirs = self._context.Pipe()
        process = self._context.Process(
            target=_serve,
            args=(theirs, os.getpid(), self.initializer, self.initargs),
            name="mcam-job-decoder",
            daemon=True,
        )
        with signals_blocked():
            process.start()
        theirs.close()
        self._process, self._conn = process, ours

    def call(
        self, function: Callable[..., Any], args: tuple, should_stop: Callable[[], None]
    ) -> Any:
        """``function(*args)`` in the child (both picklable: a module-level function);
        ``should_stop()`` is called while it runs, and whatever it raises kills the
        child and propagates. The function's own exception is raised here, with the
        child's traceback as a note unless it is a McamError (not logged: the caller logs
        what it needs)."""
        self.start()
        assert self._process is not None and self._conn is not None
        try:
            self._conn.send((function, args))
        except OSError:
            raise self._died() from None
        while not self._conn.poll(POLL_S):
            if not self._process.is_alive():
                raise self._died()
            try:
                should_stop()
            except BaseException:
                self.restart()
                raise
        try:
            reply = self._conn.recv()
        except (EOFError, OSError):
            raise self._died() from None
        if reply[0] == "ok":
            return reply[1]
        _, exc, text = reply
        if not isinstance(exc, McamError):  # the caller's mistake: no traceback wanted
            exc.add_note(f"raised in child {self.pid}:\n{text.rstrip()}")
        raise exc

    def restart(self) -> None:
        """Kill the child and start a fresh one at once, so that the next call does not
        wait for it to start and warm up."""
        self.kill()
        self.start()

    def kill(self) -> None:
        """Kill the child now (the next call starts a new one)."""
        if self._process is not None and self._process.is_alive():
            self._process.kill()
            self._process.join()
        self._discard()

    def close(self) -> None:
        """Let the child finish (end of input), killing it if it does not exit soon."""
        if self._conn is not None:
            self._conn.close()
            self._conn = None
        if self._process is not None:
            self._process.join(CLOSE_TIMEOUT_S)
        self.kill()

    def _died(self) -> ChildDiedError:
        code = None
        if self._process is not None:
            self._process.join(CLOSE_TIMEOUT_S)  # its pipe closed first: let it be reaped
            code = self._process.exitcode
        how = f"killed by signal {-code}" if code is not None and code < 0 else f"exit {code}"
        log.warning("child %s died while it worked (%s); starting another", self.pid, how)
        self.restart()
        return ChildDiedError(
            f"the decoding process died ({how}; a signal 9 is often the system out of "
            "memory) while it worked on this job; try a smaller frame or a lighter decoder"
        )

    def _discard(self) -> None:
        if self._conn is not None:
            self._conn.close()
        if self._process is not None:
            self._process.join(0)
        self._process, self._conn = None, None

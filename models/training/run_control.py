"""How a training run's process is kept in hand: one process per run folder (a lock),
a log that a resumed run trims back to its checkpoint, and SIGINT/SIGTERM turned into a
stop after the step in progress (:class:`Stopped`), with a checkpoint to resume from.
"""

from __future__ import annotations

import fcntl
import json
import os
import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from models.errors import InvalidInputError
from models.stop_signals import STOP_SIGNALS, handle_stop_signals

#: A run's log: one JSON record per logged step (:func:`run_steps`).
LOG_FILE = "log.jsonl"


def logged_step(line: str) -> int | None:
    """The step of one log line, None for a line that is not a whole record (a line
    cut short when the process died)."""
    try:
        record = json.loads(line)
    except json.JSONDecodeError:
        return None
    step = record.get("step") if isinstance(record, dict) else None
    return step if isinstance(step, int) else None


def trim_log(log: Path, step: int) -> None:
    """Keep the records of ``log`` up to ``step`` (the checkpoint's; 0 for a fresh run),
    so that the steps a resumed run makes again are logged once. Rewritten atomically
    (a temporary file renamed over it)."""
    if not log.exists():
        return
    lines = log.read_text().splitlines()
    kept = [line for line in lines if (logged := logged_step(line)) is not None and logged <= step]
    if kept == lines:
        return
    tmp = log.with_suffix(".tmp")
    tmp.write_text("".join(f"{line}\n" for line in kept))
    tmp.replace(log)


#: The file of a run folder that its training process holds locked (and writes its pid to).
LOCK_FILE = "lock"


@contextmanager
def run_lock(run_dir: Path) -> Iterator[None]:
    """Hold the exclusive lock of a run folder (created if need be) while training it:
    ``flock`` on ``<run_dir>/lock``, which holds the holder's pid. The system releases
    it when the process ends, however it ends; another process that asks for it meanwhile
    gets an InvalidInputError naming the holder."""
    run_dir.mkdir(parents=True, exist_ok=True)
    path = run_dir / LOCK_FILE
    with path.open("a+") as file:
        try:
            fcntl.flock(file, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            file.seek(0)
            holder = file.read().strip() or "unknown"
            raise InvalidInputError(
                f"{run_dir} is being trained by process {holder} (it holds {path}); wait "
                "for it to end or stop it, or train elsewhere (another --runs-dir or --label)"
            ) from None
        file.truncate(0)
        file.write(f"{os.getpid()}\n")
        file.flush()
        yield


class Stopped(Exception):
    """A run stopped by a signal (:data:`STOP_SIGNALS`) after saving its checkpoint at
    ``step`` of ``total`` steps; calling :func:`train` again resumes there."""

    def __init__(self, signum: int, step: int, total: int, checkpoint: Path) -> None:
        self.signum, self.step, self.total, self.checkpoint = signum, step, total, checkpoint
        super().__init__(
            f"stopped by {signal.Signals(signum).name} after step {step} of {total}; "
            f"checkpoint {checkpoint} saved: run the same command again to resume from "
            f"step {step}"
        )


@contextmanager
def stop_requests() -> Iterator[list[int]]:
    """While open, SIGINT and SIGTERM are noted in the list it gives instead of ending the
    process (the training loop stops after its step); the previous handlers come back
    after. Outside the main thread, where Python cannot handle signals, the list stays
    empty."""
    received: list[int] = []
    if threading.current_thread() is not threading.main_thread():
        yield received
        return
    previous = {signum: signal.getsignal(signum) for signum in STOP_SIGNALS}
    handle_stop_signals(lambda number, _frame: received.append(number))
    try:
        yield received
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)

"""One device stream decoded on several processes, its results taken in stream order.

Usage (inside the worker's device consumer)::

    pool = DecodePool("auto", processes=2)           # starts and warms the processes
    pool.prefetch("cam1", [(entry_id, message), ...]) # a batch read from the stream
    frame = pool.result("cam1", entry_id, message)    # in stream order: DecodedFrame
    pool.discard("cam1")                               # drop what is pending
    pool.forget("cam1")                                # lease lost: drop all kept for it
    pool.close()

Why: the frames of one stream are written in order by the one worker that owns it,
and decoded one after another they use one core. Most of a refined decode (``auto``
at balanced: the min-cuts of guided PUMA, region moves) holds the interpreter lock,
so threads do not help; processes do. Measured on val-256 mantissa frames decoded in
order through a pool (2 cores, 2026-11-26, ``python -m bench.throughput``; the
figures are in the README's Throughput section).

Only ``independent`` decoding uses the pool: each frame is decoded on its own, so
frames can be decoded out of order and taken in order. ``temporal`` decoding needs
the previous frame's result and stays in the worker process.

Each process runs the same frame decoder as the worker would
(:func:`worker.device_state.make_frame_decoder`, ``independent``), one onnxruntime
thread each, and warms it up (:func:`worker.device_state.warm_up`) when it starts.
Frames that decode in a millisecond or two (a dark or unwrapped scene, ``itoh``) gain
nothing from the pool (handing them over costs as much), so a device whose frames
decode faster than :data:`LOCAL_BELOW_MS` on average is decoded in the worker process,
which keeps a warmed decoder of its own; the average follows every frame, so a scene
that turns busy moves back to the pool at the next batch.
A process that dies (killed, out of memory) breaks the pool: the frame whose result
was awaited fails (the device consumer retries it, and dead-letters it after
``max_deliveries``: a frame that kills its process every time), a new pool starts and
every other pending frame is submitted to it again.

A worker killed outright (SIGKILL, out of memory) while it holds a pool leaves the
pool's 9 named POSIX semaphores (its two queues' locks, its barrier) to multiprocessing's
resource tracker, which unlinks them and warns ``There appear to be 9 leaked semaphore
objects to clean up at shutdown``: nothing is left in /dev/shm (checked on Python 3.11).
It is inherent to the spawn start method, whose semaphores must be named until every
process has opened them, and to SIGKILL, which gives their owner no chance to unlink
them; a gracefully stopped worker (SIGTERM, Ctrl-C) closes the pool and prints nothing.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import os
from collections.abc import Sequence
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from multiprocessing.synchronize import Barrier

import numpy as np

from models.decoders.learned import THREAD_VARIABLES
from models.errors import McamError
from models.formation import narrow_winding
from worker.child_process import follow_parent, signals_blocked
from worker.device_state import DecodedFrame, DeviceState, FrameDecoder, make_frame_decoder, warm_up
from worker.frame_message import FrameMessage

log = logging.getLogger(__name__)

#: onnxruntime intra-op threads per pool process: two single-threaded processes decode
#: more frames a second than one process with two threads (bench.throughput).
PROCESS_THREADS = 1
#: A device whose frames decode in less than this (ms, a moving average) is decoded in
#: the worker process: handing a frame to a pool process and its W back costs the worker
#: about 1 ms, more than two processes save on a frame that cheap. Measured (2 cores,
#: 2026-11-26, frames/s in stream order, in the worker / on a pool of 2): the virtual
#: camera's frames with auto-balanced (no residue: 1 ms a frame) 1056 / 500-656; val-256
#: mantissa with itoh (2 ms) 536 / 593, auto-fast (23 ms) 43 / 71.
LOCAL_BELOW_MS = 3.0
#: Weight of the newest frame in that average.
SMOOTHING = 0.2

#: Seconds the processes of a new pool may take to start and warm up together.
START_TIMEOUT_S = 300.0

_decode: FrameDecoder | None = None
_all_started: Barrier | None = None


def _start(decoder: str, all_started: Barrier, worker: int) -> None:
    """Pool process initializer: one thread for onnxruntime and the numerical libraries,
    Ctrl-C and SIGTERM left to the worker (which shuts the pool down) and an exit of its
    own when the worker (pid ``worker``) dies (:func:`worker.child_process.follow_parent`),
    the decoder built and warmed."""
    global _decode, _all_started
    _all_started = all_started
    follow_parent(worker)
    os.environ.update(dict.fromkeys(THREAD_VARIABLES, str(PROCESS_THREADS)))
    from models.allocator import keep_freed_memory

    keep_freed_memory()
    _decode = make_frame_decoder("independent", decoder)
    warm_up(decoder)


def _ready() -> int:
    """Wait until every process of the pool runs this (one task per process, so each
    process takes one: submitting them starts them all at once); the pid."""
    assert _all_started is not None, "pool process started without its barrier"
    _all_started.wait(START_TIMEOUT_S)
    return os.getpid()


def _decode_frame(message: FrameMessage) -> DecodedFrame:
    """Decode in a pool process; W travels back in the narrowest integer type that holds
    it (int16 for any W a 16-bit code can wrap to: 4x less to copy than int64)."""
    assert _decode is not None, "pool process started without its decoder"
    frame = _decode(DeviceState(message.device), message)
    frame.winding = narrow_winding(frame.winding)
    return frame


class DecodePool:
    """``processes`` processes decoding device frames with ``decoder`` (independent
    mode); frames are keyed by their stream entry id, per device."""

    def __init__(self, decoder: str, processes: int) -> None:
        if processes < 2:
            raise McamError(
                f"a decode pool needs at least 2 processes, got {processes}; "
                "with one, decode in the worker process"
            )
        self.decoder = decoder
        self.processes = processes
        self._pending: dict[str, dict[str, tuple[FrameMessage, Future[DecodedFrame]]]] = {}
        self._cost_ms: dict[str, float] = {}
        # The worker's own decoder first: an unknown decoder is refused here, with a
        # clear error, before any process starts.
        self._local = make_frame_decoder("independent", decoder)
        warm_up(decoder)
        self._executor = self._start_executor()

    def _start_executor(self) -> ProcessPoolExecutor:
        """A new executor, its processes started (a spawn executor starts one on each
        submit while it has fewer than it may: the :func:`_ready` tasks start them all,
        with Ctrl-C and SIGTERM blocked until they ignore them)."""
        context = multiprocessing.get_context("spawn")
        executor = ProcessPoolExecutor(
            self.processes,
            mp_context=context,
            initializer=_start,
            initargs=(self.decoder, context.Barrier(self.processes), os.getpid()),
        )
        with signals_blocked():
            self._started = [executor.submit(_ready) for _ in range(self.processes)]
        return executor

    def wait_ready(self) -> set[int]:
        """Wait until every process has started and warmed up; their pids."""
        return {future.result() for future in self._started}

    def prefetch(self, device: str, batch: Sequence[tuple[str, FrameMessage]]) -> None:
        """Start decoding ``batch`` ((entry id, message) pairs read from ``device``'s
        stream); frames pending from an earlier batch and not in this one (skipped as
        already done) are dropped. Nothing starts for a device whose frames are cheap
        (:data:`LOCAL_BELOW_MS`): :meth:`result` decodes them in this process."""
        if self.local(device):
            self.discard(device)
            return
        earlier = self._pending.get(device, {})
        pending = {}
        for entry_id, message in batch:
            pending[entry_id] = earlier.pop(entry_id, None) or (message, self._submit(message))
        for _message, future in earlier.values():
            future.cancel()
        self._pending[device] = pending

    def local(self, device: str) -> bool:
        """Whether ``device``'s frames are decoded in this process: their moving average
        decode time is below :data:`LOCAL_BELOW_MS` (unknown at first: the pool)."""
        return self._cost_ms.get(device, LOCAL_BELOW_MS) < LOCAL_BELOW_MS

    def result(self, device: str, entry_id: str, message: FrameMessage) -> DecodedFrame:
        """The decoded frame of stream entry ``entry_id`` (submitted now if it was not
        prefetched, or failed before; decoded here for a device whose frames are cheap); a
        decoding error is raised as it was raised in the pool process."""
        pending = self._pending.get(device, {}).pop(entry_id, None)
        if pending is None and self.local(device):
            frame = self._local(DeviceState(device), message)
        else:
            frame = self._pooled(device, message, pending)
        took_ms = frame.timings_ns.get("decode", 0) / 1e6
        before = self._cost_ms.get(device, took_ms)
        self._cost_ms[device] = before + SMOOTHING * (took_ms - before)
        return frame

    def _pooled(
        self,
        device: str,
        message: FrameMessage,
        pending: tuple[FrameMessage, Future[DecodedFrame]] | None,
    ) -> DecodedFrame:
        """The frame decoded by a pool process (``pending``: its prefetched future)."""
        _message, future = pending or (message, self._submit(message))
        try:
            frame = future.result()
        except BrokenProcessPool as exc:
            self._restart()
            raise RuntimeError(
                f"a stream decode process died while decoding frame {message.sequence} of "
                f"{device} ({exc}); a new pool is started and the frame will be retried"
            ) from exc
        frame.winding = frame.winding.astype(np.int64)
        return frame

    def _submit(self, message: FrameMessage) -> Future[DecodedFrame]:
        """Start decoding ``message``; on a pool found broken, first start a new one."""
        try:
            return self._executor.submit(_decode_frame, message)
        except BrokenProcessPool:
            self._restart()
            return self._executor.submit(_decode_frame, message)

    def _restart(self) -> None:
        """Replace a broken executor and submit every pending frame to the new one."""
        log.warning("stream decode pool broken; starting %d new processes", self.processes)
        broken = self._executor
        # The survivors ignore SIGTERM (child_process.leave_signals_to_parent), the broken
        # pool's only way to end them: one blocked writing its result to the dead pool's
        # pipe outlived close() and hung the worker's exit.
        for process in list(getattr(broken, "_processes", {}).values()):
            with contextlib.suppress(OSError):
                process.kill()
        broken.shutdown(wait=False, cancel_futures=True)
        self._executor = self._start_executor()
        for pending in self._pending.values():
            for entry_id, (message, _future) in list(pending.items()):
                pending[entry_id] = (message, self._executor.submit(_decode_frame, message))

    def discard(self, device: str) -> None:
        """Drop ``device``'s pending frames (its lease was lost or handed over, or its
        frames are decoded here)."""
        for _message, future in self._pending.pop(device, {}).values():
            future.cancel()

    def forget(self, device: str) -> None:
        """Drop everything kept for ``device``: its pending frames and its average decode
        time (a worker that saw cameras come and go kept one average per camera ever
        owned); its next frames start on the pool, as a new device's do."""
        self.discard(device)
        self._cost_ms.pop(device, None)

    def close(self) -> None:
        """Cancel what is pending and stop the processes (waits for running decodes)."""
        self._pending.clear()
        self._executor.shutdown(wait=True, cancel_futures=True)

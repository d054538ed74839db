"""Frames per second on all the cores: one process with every thread, or one process per core.

bench.tradeoff times one frame at a time (ms/frame, and frames/s as its inverse): what
one stream gets, since a device stream's frames are decoded in order by the one worker
that owns it (and a temporal stream's frames depend on each other). When there is more
than one thing to decode (several cameras, uploads, a batch of stills) what counts is
how many frames all the cores finish per second, and that depends on how the workers
use the cores: onnxruntime spreads a net over its intra-op threads, but the rest of a
decode (scene analysis, the graph cuts of the refinement) runs on one core, and holds
the interpreter lock of its process.

``python -m bench.throughput`` decodes the val-256 frames with each decoder in each
*layout* (processes x job threads per process x onnxruntime threads per job), every
worker decoding all the frames ``--repeats`` times after one warm-up pass, started
together, and reports the frames all of them finished per second of wall time:

- ``1 x 1 x C``: one worker on all ``C`` cores (``mcam serve``'s default worker);
- ``1 x C x 1``: one worker decoding ``C`` jobs at once (``mcam worker --concurrency C
  --threads 1``);
- ``C x 1 x 1``: ``C`` workers of one thread each (``mcam serve --workers C --threads
  1``).

Each job thread decodes in a child process of its own, as a worker's job threads do
(:mod:`worker.job_processor`), so the handover (the codes there, W back) is counted.

And one stream as the device consumer decodes it in independent mode: batches of
frames decoded by a pool of ``C`` single-threaded processes
(:mod:`worker.decode_pool`) and taken in stream order.

The decoded W is the same in every layout (the decoders are deterministic), so the mean
PSNR is measured once per decoder. It prints a Markdown table and writes
``bench/results/throughput.json``.
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import queue
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import numpy as np

from bench import (
    Distinct,
    add_report_option,
    add_val256_frames_option,
    at_least,
    bench_parser,
    entry_point,
    host_facts,
    host_line,
    refuse_unknown_decoders,
)
from models import metrics
from models.decoders import get_decoder
from models.decoders.learned import THREAD_VARIABLES
from models.scenes import ValFrame, val256_frames
from worker.child_process import ChildProcess
from worker.decode_pool import DecodePool
from worker.device_consumer import BATCH
from worker.frame_message import FrameMessage
from worker.job_processor import decode_still, start_job_child

DECODERS = ("itoh", "auto-fast", "auto-balanced", "auto-best")
#: Seconds a worker process may take to start, warm up and decode its share.
WORKER_TIMEOUT_S = 600.0


@dataclass(frozen=True)
class FrameSet:
    """The first ``count`` val-256 frames of ``encoding``: what each worker process
    builds for itself (cheaper to send than the frames)."""

    encoding: str
    count: int

    def load(self) -> list[ValFrame]:
        return val256_frames(self.encoding)[: self.count]


def layouts(cores: int) -> list[tuple[int, int, int]]:
    """(processes, job threads per process, onnxruntime threads per job) to compare on a
    machine with ``cores`` cores (one layout when there is one core)."""
    found = [(1, 1, cores), (1, cores, 1), (cores, 1, 1)]
    return list(dict.fromkeys(found))


def layout_name(layout: tuple[int, int, int]) -> str:
    return " x ".join(str(part) for part in layout)


def decode_share(
    decoder: str, frames_of: FrameSet, repeats: int, jobs: int, start: Any, results: Any
) -> None:
    """One worker process: ``jobs`` job threads, each handing its frames to a child
    process of its own as the worker's job threads do
    (:class:`worker.child_process.ChildProcess`, :func:`worker.job_processor.decode_still`);
    warm up, wait for the others at ``start`` (a barrier), decode every frame of
    ``frames_of`` ``repeats`` times on each thread, and put (first start, last end in
    monotonic ns, frames decoded) on ``results``. The onnxruntime thread count comes
    from the environment the parent set before starting it."""
    frames = frames_of.load()
    children = [ChildProcess(start_job_child, (decoder,)) for _ in range(jobs)]

    def decode_all(child: ChildProcess) -> None:
        for frame in frames:
            child.call(decode_still, (decoder, frame.codes, frame.params), _never)

    for child in children:
        decode_all(child)

    def work(child: ChildProcess) -> None:
        for _ in range(repeats):
            decode_all(child)

    threads = [threading.Thread(target=work, args=(child,)) for child in children]
    start.wait()
    began = time.monotonic_ns()
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    results.put((began, time.monotonic_ns(), jobs * repeats * len(frames)))
    for child in children:
        child.close()


def _never() -> None:
    """A benchmark's decodes are never stopped."""


@contextmanager
def thread_limits(threads: int) -> Iterator[None]:
    """The environment the worker processes started inside inherit: ``threads`` intra-op
    threads for onnxruntime and the numerical libraries, as ``mcam worker --threads``
    sets them (read when a process loads those libraries, so set before it starts)."""
    saved = {name: os.environ.get(name) for name in THREAD_VARIABLES}
    os.environ.update(dict.fromkeys(THREAD_VARIABLES, str(threads)))
    try:
        yield
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


def measure_layout(
    decoder: str, frames_of: FrameSet, layout: tuple[int, int, int], repeats: int
) -> dict[str, Any]:
    """Frames per second of ``decoder`` over all the workers of ``layout``, and each
    worker's mean ms per frame per job thread."""
    processes, jobs, ort_threads = layout
    context = multiprocessing.get_context("spawn")
    start, results = context.Barrier(processes), context.Queue()
    workers = [
        context.Process(
            target=decode_share, args=(decoder, frames_of, repeats, jobs, start, results)
        )
        for _ in range(processes)
    ]
    with thread_limits(ort_threads):
        for worker in workers:
            worker.start()
    shares = collect(results, workers)
    began = min(share[0] for share in shares)
    ended = max(share[1] for share in shares)
    frames = sum(share[2] for share in shares)
    per_job_ms = [(end - begin) / 1e6 / (count / jobs) for begin, end, count in shares]
    return {
        "layout": layout_name(layout),
        "processes": processes,
        "jobs_per_process": jobs,
        "ort_threads": ort_threads,
        "frames": frames,
        "frames_per_s": frames / ((ended - began) / 1e9),
        "ms_per_frame_per_job": float(np.mean(per_job_ms)),
    }


def collect(results: Any, workers: list[Any]) -> list[tuple[int, int, int]]:
    """One share from each worker process on ``results``. A worker that dies first, or
    workers that take longer than :data:`WORKER_TIMEOUT_S`, end the benchmark with one
    line saying so (exit status 1; the other workers are stopped)."""
    shares: list[tuple[int, int, int]] = []
    deadline = time.monotonic() + WORKER_TIMEOUT_S
    try:
        while len(shares) < len(workers):
            try:
                shares.append(results.get(timeout=1.0))
                continue
            except queue.Empty:
                pass
            failed = [worker.exitcode for worker in workers if worker.exitcode not in (None, 0)]
            if failed:
                raise SystemExit(
                    f"bench.throughput: a worker process failed (exit code {failed[0]}); "
                    "its error is printed above"
                )
            if time.monotonic() > deadline:
                raise SystemExit(
                    f"bench.throughput: the worker processes took over {WORKER_TIMEOUT_S:.0f} s"
                )
    finally:
        for worker in workers:
            if worker.is_alive() and len(shares) < len(workers):
                worker.terminate()
            worker.join()
    return shares


def measure_stream_pool(
    decoder: str, frames: list[ValFrame], processes: int, repeats: int
) -> dict[str, Any]:
    """Frames per second of one stream decoded by a :class:`worker.decode_pool.DecodePool`
    of ``processes`` processes and taken in order, in batches of
    :data:`worker.device_consumer.BATCH` as the device consumer reads them (after one
    warm-up pass over ``frames``)."""
    pool = DecodePool(decoder, processes)
    try:
        pool.wait_ready()
        in_order(pool, frames, 1)
        began = time.monotonic_ns()
        count = in_order(pool, frames, repeats)
        seconds = (time.monotonic_ns() - began) / 1e9
    finally:
        pool.close()
    return {"processes": processes, "frames": count, "frames_per_s": count / seconds}


def in_order(pool: DecodePool, frames: list[ValFrame], repeats: int) -> int:
    """Decode ``frames`` ``repeats`` times through ``pool`` as one stream; frames done."""
    messages = [
        FrameMessage("bench", index, index, frame.codes, frame.params)
        for index, frame in enumerate(frames * repeats)
    ]
    for first in range(0, len(messages), BATCH):
        batch = [(str(m.sequence), m) for m in messages[first : first + BATCH]]
        pool.prefetch("bench", batch)
        for entry_id, message in batch:
            pool.result("bench", entry_id, message)
    return len(messages)


def mean_psnr(decoder: str, frames: list[ValFrame]) -> float:
    """Mean linear PSNR (dB) of ``decoder`` on ``frames``, an exact frame's at
    :data:`models.metrics.PSNR_CAP` (its inf made the mean inf)."""
    chosen = get_decoder(decoder)
    return metrics.mean_capped_psnr(
        metrics.psnr(chosen.decode(frame.codes, frame.params).irradiance, frame.x)
        for frame in frames
    )


def run(args: argparse.Namespace) -> dict[str, Any]:
    cores = args.cores or os.cpu_count() or 1
    frames_of = FrameSet(args.encoding, args.frames)
    frames = frames_of.load()
    rows = []
    for decoder in args.decoders:
        row: dict[str, Any] = {"decoder": decoder, "psnr_db": mean_psnr(decoder, frames)}
        row["layouts"] = [
            measure_layout(decoder, frames_of, layout, args.repeats) for layout in layouts(cores)
        ]
        if cores > 1:
            row["stream_pool"] = measure_stream_pool(decoder, frames, cores, args.repeats)
        rows.append(row)
    return {
        **host_facts(),
        "encoding": args.encoding,
        "frames": len(frames),
        "repeats": args.repeats,
        "cores": cores,
        "layouts": [layout_name(layout) for layout in layouts(cores)],
        "results": rows,
    }


def markdown(report: dict[str, Any]) -> str:
    names = report["layouts"]
    pool = f"one stream in order, {report['cores']} processes"
    lines = [
        f"Throughput on val-256 ({report['encoding']}, {report['frames']} frames x "
        f"{report['repeats']} per worker, {report['cores']} cores filled), "
        f"{host_line(report)}. Layout: processes x "
        "job threads per process x onnxruntime threads per job; frames/s over all the "
        "workers (ms a frame per job thread in brackets); the last column: one stream "
        "through the device consumer's decode pool, taken in stream order.",
        "",
        "| decoder | PSNR dB | " + " | ".join(names) + f" | {pool} |",
        "|---|---|" + "---|" * (len(names) + 1),
    ]
    for row in report["results"]:
        cells = [
            f"{layout['frames_per_s']:.1f} ({layout['ms_per_frame_per_job']:.1f} ms)"
            for layout in row["layouts"]
        ]
        cells.append(f"{row['stream_pool']['frames_per_s']:.1f}" if "stream_pool" in row else "-")
        lines.append(f"| {row['decoder']} | {row['psnr_db']:.2f} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = bench_parser(__name__, __doc__)
    parser.add_argument("--decoders", nargs="+", action=Distinct, default=list(DECODERS))
    parser.add_argument("--encoding", choices=("mantissa", "modulo"), default="mantissa")
    add_val256_frames_option(parser)
    parser.add_argument("--repeats", type=at_least(1), default=3, help="passes over the frames")
    parser.add_argument("--cores", type=at_least(1), help="cores to fill (default: all)")
    add_report_option(parser, "throughput.json")
    args = parser.parse_args(argv)
    refuse_unknown_decoders(parser, args.decoders, encodings=[args.encoding])
    cores = os.cpu_count() or 1
    if args.cores is not None and args.cores > cores:
        parser.error(
            f"--cores {args.cores} is more than this machine's {cores} cores: the layouts "
            f"would share them and the report say {args.cores} cores filled; give at most "
            f"{cores}"
        )
    return args


main = entry_point(parse_args, run, markdown, rows="results")


if __name__ == "__main__":
    raise SystemExit(main())

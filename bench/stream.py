"""Live streaming benchmark: camera link -> daemon -> Redis -> worker(s), 256 x 256 frames.

Run as ``python -m bench.stream [--frames N] [--workers 1 2]``. Measures

1. parse only: :class:`LinkParser` on pre-encoded packets in memory (frames/s, one core),
   and parse + publish (XADD to a real redis-server) in one thread: CPU ms per frame;
2. link path: a writer process floods a real pty with pre-encoded packets, the daemon (this
   process) parses and XADDs them to a real redis-server: sustained frames/s and the
   daemon's CPU time per frame (this process's rusage: reader + publisher threads);
3. end to end with 1 and 2 ``mcam worker`` processes (``--decoder``, default itoh, on
   the workers' stream decode pool, ``--stream-processes``): throughput when flooded
   (one device, and as many devices as workers: a device stream is owned by one worker
   at a time, which decodes it on its pool), and latency from the packet
   leaving the camera to the EXR on disk (event ``written_ns`` minus the packet's
   timestamp, both wall clock) when paced below capacity. A run ends when every device's
   last frame is recorded; frames reconstructed are the EXRs in the result store, and the
   latency percentiles cover the frames still in the events stream (its newest ~1000);
4. the decoder's own speed in-process (decode + EXR encode) for comparison.

``--exr-compression`` sets the workers' ``MCAM_STREAM_EXR_COMPRESSION`` and the in-process
encoding alike (default: the workers' default, ``worker.outputs.STREAM_EXR_COMPRESSION``).

Frames are rendered once by the virtual SCAMP-5 (modulo, procedural scene) so rendering
cost is not measured; ``--scenes val256`` sends the first val-256 mantissa frames
instead (crops of real scenes whose dense wraps make ``auto`` refine, the load a decode
pool is for). Prints a Markdown table, writes ``bench/results/stream.json`` (``--out``).
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import resource
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from bench import (
    Distinct,
    above_zero,
    add_report_option,
    at_least,
    entry_point,
    host_facts,
    host_line,
    refuse_unknown_decoders,
)
from device.daemon import DaemonConfig, DeviceDaemon, packet_params
from device.link_parser import LinkParser
from device.link_protocol import DataPacket, encode_data
from device.sim_link import LoopEndpoint, PtyEndpoint
from device.simulator import VirtualScamp5
from models.decoders.base import Decoder
from models.decoders.registry import get_decoder
from models.hdr_io import EXR_COMPRESSIONS
from models.scenes import val256_frames
from worker.embedded_redis import EmbeddedRedis, connect
from worker.frame_message import FrameMessage
from worker.outputs import STREAM_EXR_COMPRESSION, encode_exr_result
from worker.redis_keys import DEVICES_SET, events_stream, frame_stream, last_sequence_key
from worker.result_store import RESULTS_DIR

DECODER = "itoh"
DISTINCT = 16
#: The frames ``--scenes`` sends, and their encoding.
SCENES = {"camera": "modulo", "val256": "mantissa"}


def template_packets(scenes: str = "camera") -> list[DataPacket]:
    """``DISTINCT`` frames: rendered by the virtual camera (``camera``: modulo, gain 1, a
    smooth procedural scene that most decoders finish in a millisecond or two) or the
    first val-256 mantissa frames (``val256``: crops of real scenes, dense wraps)."""
    if scenes == "val256":
        return [
            DataPacket(index, 0, "mantissa", frame.params.alpha, frame.params.bits,
                       float(frame.params.gain or 0.0), frame.codes)
            for index, frame in enumerate(val256_frames("mantissa")[:DISTINCT])
        ]  # fmt: skip
    camera = VirtualScamp5(LoopEndpoint())
    out = []
    for index in range(DISTINCT):
        params = camera.params_for(index)
        frame = camera.render(index, params)
        out.append(DataPacket(index, 0, "modulo", 2.0, 8, float(params.gain or 1.0),
                              frame.codes))
    return out


def stream_bytes(templates: list[DataPacket], count: int, stamp: bool) -> list[bytes]:
    """``count`` packets with sequence 0..count-1 (timestamps now, if ``stamp``)."""
    return [encode_data(replace(templates[i % len(templates)], sequence=i,
                                timestamp_ns=time.time_ns() if stamp else 0))
            for i in range(count)]


def bench_parse(packets: list[bytes]) -> dict[str, float]:
    data = b"".join(packets)
    parser = LinkParser()
    start = time.perf_counter()
    out = [p for i in range(0, len(data), 4096) for p in parser.feed(data[i : i + 4096])]
    seconds = time.perf_counter() - start
    assert len(out) == len(packets)
    return {"frames": len(out), "frames_per_s": len(out) / seconds, "mb_per_s":
            len(data) / seconds / 1e6}


def bench_parse_publish(url: str, packets: list[bytes]) -> dict[str, float]:
    """Parse + FrameMessage + XADD in one thread, the daemon's per-frame work without the
    pty reads and thread hand-offs: CPU ms per frame and frames/s of CPU on one core."""
    client = connect(url, timeout_s=2.0)
    data = b"".join(packets)
    parser = LinkParser()
    cpu = time.process_time()
    published = 0
    for i in range(0, len(data), 4096):
        for packet in parser.feed(data[i : i + 4096]):
            assert isinstance(packet, DataPacket)
            message = FrameMessage("bench-pp", packet.sequence, packet.timestamp_ns,
                                   packet.codes, packet_params(packet))
            client.xadd(frame_stream("bench-pp"), message.to_fields(), maxlen=256,
                        approximate=True)
            published += 1
    seconds = time.process_time() - cpu
    client.delete(frame_stream("bench-pp"))
    return {"frames": published, "cpu_ms_per_frame": 1e3 * seconds / published,
            "frames_per_cpu_s": published / seconds}


def _writer(endpoint: PtyEndpoint, templates: list[DataPacket], count: int,
            fps: float | None) -> None:
    """Child process: write ``count`` packets, stamped at send time, optionally paced."""
    next_t = time.monotonic()
    for i in range(count):
        packet = replace(templates[i % len(templates)], sequence=i, timestamp_ns=time.time_ns())
        endpoint.write(encode_data(packet))
        if fps:
            next_t += 1.0 / fps
            time.sleep(max(0.0, next_t - time.monotonic()))


def recorded_all(client: Any, devices: list[str], count: int) -> bool:
    """Whether every device's worker recorded its last frame (sequence ``count - 1``)."""
    last = [client.hget(last_sequence_key(device), "seq") for device in devices]
    return all(seq is not None and int(seq) >= count - 1 for seq in last)


def stored_frames(results: Path, devices: list[str]) -> int:
    """The device frames' EXRs in a worker's result store."""
    return sum(len(list((results / "devices" / device).glob("*.exr"))) for device in devices)


def run_link(url: str, devices: list[str], count: int, templates: list[DataPacket],
             fps: float | None, workdir: Path, results: Path | None) -> dict[str, Any]:
    """Stream ``count`` packets per device through one pty and daemon each; return timings
    summed over the devices (latency percentiles over the frames in the events streams).
    With ``results`` (the workers' result store), wait for the workers to reconstruct."""
    client = connect(url, timeout_s=2.0)
    endpoints = [PtyEndpoint(workdir / f"{device}.pty") for device in devices]
    daemons = [DeviceDaemon(DaemonConfig(port=endpoint.url, device=device, frames_maxlen=10_000,
                                         queue_size=256), client).start()
               for device, endpoint in zip(devices, endpoints, strict=True)]
    time.sleep(0.3)  # let the daemons open their ports
    cpu0 = resource.getrusage(resource.RUSAGE_SELF)
    start = time.perf_counter()
    writers = [mp.get_context("fork").Process(target=_writer,
                                              args=(endpoint, templates, count, fps))
               for endpoint in endpoints]
    for writer in writers:
        writer.start()
    deadline = time.monotonic() + 300
    total = count * len(devices)

    def published() -> int:
        return sum(daemon.health.counts["frames_ok"] for daemon in daemons)

    while published() < total and time.monotonic() < deadline:
        if not any(w.is_alive() for w in writers) and all(
                d.publisher._queue.empty() for d in daemons):
            time.sleep(0.5)
            if published() < total:
                break
        time.sleep(0.02)
    published_s = time.perf_counter() - start
    cpu1 = resource.getrusage(resource.RUSAGE_SELF)
    ok = published()
    result: dict[str, Any] = {
        "devices": len(devices), "frames_sent": total, "frames_published": ok,
        "dropped": sum(daemon.health.dropped() for daemon in daemons),
        "publish_frames_per_s": ok / published_s,
        "daemon_cpu_ms_per_frame": 1e3 * ((cpu1.ru_utime - cpu0.ru_utime)
                                          + (cpu1.ru_stime - cpu0.ru_stime)) / max(ok, 1),
    }
    if results is not None:
        streams = [events_stream(device) for device in devices]
        while not recorded_all(client, devices, count) and time.monotonic() < deadline:
            time.sleep(0.01)
        done_s = time.perf_counter() - start
        frames = [e for s in streams for e in (
            {k.decode(): v.decode() for k, v in f.items()} for _, f in client.xrange(s))
            if e.get("type") == "frame"]
        latency = np.array([(int(e["written_ns"]) - int(e["timestamp_ns"])) / 1e6
                            for e in frames])
        reconstructed = stored_frames(results, devices)
        result.update({
            "frames_reconstructed": reconstructed,
            "end_to_end_frames_per_s": reconstructed / done_s,
            "latency_ms_p50": float(np.median(latency)) if len(latency) else None,
            "latency_ms_p99": float(np.quantile(latency, 0.99)) if len(latency) else None,
        })
    for writer, daemon, endpoint, device in zip(writers, daemons, endpoints, devices,
                                                strict=True):
        writer.join(10)
        daemon.stop()
        endpoint.close()
        client.xtrim(frame_stream(device), maxlen=0)  # free the memory, keep the stream
        client.srem(DEVICES_SET, device)
    return result


def bench_decoder(
    templates: list[DataPacket],
    compression: str,
    decoder: Decoder,
    repeat: int = 100,
    clock: Callable[[], int] = time.perf_counter_ns,
) -> dict[str, float]:
    """The decoder alone (decode + EXR encode as ``compression``), in-process: frames/s of
    wall time (``clock``, ns) over ``repeat`` frames, after one untimed warm-up frame (a
    net's ONNX session was counted in the figure)."""
    frames = [(packet.codes, packet_params(packet)) for packet in templates]

    def decode_and_encode(index: int) -> None:
        codes, params = frames[index % len(frames)]
        result = decoder.decode(codes, params)
        encode_exr_result(codes, result.winding, params, {}, {"exr_compression": compression})

    decode_and_encode(0)
    start = clock()
    for index in range(repeat):
        decode_and_encode(index)
    return {"frames_per_s": repeat / ((clock() - start) / 1e9)}


def start_workers(
    n: int, url: str, data_dir: Path, args: argparse.Namespace
) -> list[subprocess.Popen[bytes]]:
    """``n`` ``mcam worker`` processes of one onnxruntime thread each, decoding streams
    with ``args.decoder`` on ``args.stream_processes`` processes (None: the default)."""
    env = {**os.environ, "MCAM_REDIS_URL": url, "MCAM_DATA_DIR": str(data_dir),
           "MCAM_STREAM_EXR_COMPRESSION": args.exr_compression}
    if args.stream_processes is not None:
        env["MCAM_STREAM_PROCESSES"] = str(args.stream_processes)
    mcam = Path(sys.executable).parent / "mcam"
    return [subprocess.Popen([mcam, "worker", "--decoder", args.decoder, "--threads", "1",
                              "--log-level", "WARNING"], env=env,
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            for _ in range(n)]


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m bench.stream", description=__doc__)
    parser.add_argument("--frames", type=at_least(1), default=300, help="frames per link run")
    parser.add_argument("--workers", type=at_least(1), nargs="+", action=Distinct, default=[1, 2])
    parser.add_argument("--latency-fps", type=above_zero, default=5.0,
                        help="paced rate for the latency runs (frames/s, above 0)")
    parser.add_argument("--exr-compression", choices=tuple(EXR_COMPRESSIONS),
                        default=STREAM_EXR_COMPRESSION, help="of the device frames' EXRs")
    parser.add_argument("--decoder", default=DECODER, help=f"stream decoder (default {DECODER})")
    parser.add_argument("--stream-processes", type=at_least(1),
                        help="MCAM_STREAM_PROCESSES of the workers (default: theirs)")
    parser.add_argument("--scenes", choices=tuple(SCENES), default="camera",
                        help="frames of the virtual camera (easy) or val-256 (dense wraps)")
    add_report_option(parser, "stream.json")
    args = parser.parse_args(argv)
    refuse_unknown_decoders(parser, [args.decoder], encodings=[SCENES[args.scenes]])
    if args.frames < max(args.workers):
        parser.error(
            f"--frames {args.frames} is fewer than --workers {max(args.workers)}: the flood "
            f"run with {max(args.workers)} devices would give each of them no frame; give "
            f"--frames of at least {max(args.workers)}"
        )
    return args


def measure(args: argparse.Namespace) -> dict[str, dict[str, Any]]:
    """Every run of the benchmark, by name."""
    templates = template_packets(args.scenes)
    rows: dict[str, Any] = {"parse_only": bench_parse(stream_bytes(templates, args.frames,
                                                                     False)),
                            "decoder_in_process": bench_decoder(templates,
                                                                args.exr_compression,
                                                                get_decoder(args.decoder))}
    with tempfile.TemporaryDirectory(prefix="mcam-bench-") as tmp:
        workdir = Path(tmp)
        with EmbeddedRedis(workdir / "redis") as url:
            rows["parse_publish_one_thread"] = bench_parse_publish(
                url, stream_bytes(templates, args.frames, False))
            rows["link_path"] = run_link(url, ["bench0"], args.frames, templates, None, workdir,
                                         None)
            for n in args.workers:
                workers = start_workers(n, url, workdir / f"data{n}", args)
                results = workdir / f"data{n}" / RESULTS_DIR
                time.sleep(2.0)
                for n_devices in sorted({1, n}):
                    names = [f"flood{n}w{n_devices}d{k}" for k in range(n_devices)]
                    rows[f"e2e_{n}w_{n_devices}dev_flood"] = run_link(
                        url, names, args.frames // n_devices, templates, None, workdir, results)
                rows[f"e2e_{n}w_paced"] = run_link(
                    url, [f"paced{n}"], max(20, args.frames // 6), templates, args.latency_fps,
                    workdir, results)
                for worker in workers:
                    worker.terminate()
                for worker in workers:
                    worker.wait(30)
    return rows


def run(args: argparse.Namespace) -> dict[str, Any]:
    """The whole benchmark as a JSON-ready report."""
    return report(args, measure(args))


def report(args: argparse.Namespace, rows: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """The report of measured ``rows``: the host, the settings and the rows."""
    return {**host_facts(), "decoder": args.decoder, "stream_processes": args.stream_processes,
            "frames": "256x256 8-bit " + (
                "val-256 mantissa" if args.scenes == "val256" else "virtual camera, modulo"),
            "exr_compression": args.exr_compression, "latency_fps": args.latency_fps,
            "results": rows}


def markdown(report: dict[str, Any]) -> str:
    """The report as Markdown: a header line (date, machine, load, settings), then one row
    per run and metric."""
    lines = [f"bench.stream, {host_line(report)}. Decoder {report['decoder']} on "
             f"{report['frames']} frames, EXR compression {report['exr_compression']}; the "
             f"paced runs at {report['latency_fps']:g} frames/s.",
             "", "| run | metric | value |", "|---|---|---|"]
    for name, values in report["results"].items():
        for metric, value in values.items():
            shown = f"{value:.3f}" if isinstance(value, float) else str(value)
            lines.append(f"| {name} | {metric} | {shown} |")
    return "\n".join(lines)


main = entry_point(parse_args, run, markdown, rows="results")


if __name__ == "__main__":
    sys.exit(main())

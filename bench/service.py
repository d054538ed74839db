"""Throughput and latency of 256x256 reconstructions through the real API.

Run as ``python -m bench.service``. Starts a private redis-server, the API
(uvicorn, own process) and one worker (own process) on 127.0.0.1, then submits
wrapped frames with ``Prefer: wait`` from 1, 4 and 16 concurrent clients. Reports
jobs/s and p50/p99 request latency (ms) of the jobs that succeeded, lost requests
(any job not succeeded), and the overhead of the API + queue path over calling the
decoder in-process:
``(p50 latency at 1 client - in-process decode time) / in-process decode time``.
Prints a Markdown table and writes ``bench/results/service.json`` and ``service.md``, with
the date, the machine, the package versions and the load average at the end.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from bench import (
    add_report_option,
    at_least,
    bench_parser,
    host_facts,
    host_line,
    import_extra,
    one_line_errors,
    refuse_unknown_decoders,
    write_report,
)
from models.decoders.registry import get_decoder
from models.formation import SensorParams, simulate
from models.frames import encode_frame
from models.timing import median_ns
from worker.embedded_redis import EmbeddedRedis

httpx = import_extra("httpx", "bench", "bench.service")
CLIENTS = (1, 4, 16)
SIZE = 256
KEY = "bench-key-0123456789abcdef"
PARAMS = SensorParams(encoding="mantissa", alpha=2.0, bits=8, gain=1.0)


def test_frame(size: int = SIZE) -> tuple[bytes, np.ndarray]:
    """A seeded smooth HDR ramp with a bright disc, encoded: PNG bytes and codes."""
    y, x = np.mgrid[0:size, 0:size] / size
    scene = 0.01 * np.power(3000.0, x) * (1 + 0.2 * y)
    scene = np.where((x - 0.3) ** 2 + (y - 0.6) ** 2 < 0.02, scene * 4, scene)
    frame = simulate(scene, PARAMS)
    return encode_frame(frame.codes, frame.params, "png"), frame.codes


def in_process_ms(decoder: str, codes: np.ndarray, repeats: int) -> float:
    """Median wall time of ``decode`` in this process (ms), after one warm-up call."""
    dec = get_decoder(decoder)
    return median_ns(lambda: dec.decode(codes, PARAMS), repeats) / 1e6


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


@contextmanager
def process(command: list[str], env: dict[str, str]):  # type: ignore[no-untyped-def]
    child = subprocess.Popen(command, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        yield child
    finally:
        child.terminate()
        try:
            child.wait(30)
        except subprocess.TimeoutExpired:
            child.kill()
            child.wait()


def wait_ready(url: str, timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            if httpx.get(f"{url}/health/ready", timeout=2).status_code == 200:
                return
        except httpx.HTTPError:
            pass
        time.sleep(0.2)
    raise RuntimeError(f"the service at {url} did not become ready in {timeout_s:.0f} s")


def one_job(http: httpx.Client, data: bytes, decoder: str) -> tuple[float, dict[str, Any]]:
    """Submit and wait; returns (latency s, the job's final record)."""
    start = time.perf_counter()
    reply = http.post(
        "/v1/reconstructions",
        files={"file": ("frame.png", data, "image/png")},
        data={"decoder": decoder},
        headers={"Prefer": "wait=60"},
    )
    job = reply.json()
    while reply.status_code == 202:
        reply = http.get(f"/v1/jobs/{job['id']}")
        job = reply.json()
        if job["state"] in ("succeeded", "failed", "cancelled"):
            break
        time.sleep(0.01)
    return time.perf_counter() - start, job


def median_stages(done: list[tuple[float, dict[str, Any]]]) -> dict[str, float]:
    """Median worker stage times (ms) and ``api_http``: request latency minus the job's
    total (HTTP, upload parsing, submit and the wait notification)."""
    if not done:
        return {}
    stages = {
        stage: float(np.median([job["timings_ns"].get(stage, 0) for _, job in done]) / 1e6)
        for stage in ("queue_wait", "decode", "encode", "total")
    }
    api = [latency - job["timings_ns"]["total"] / 1e9 for latency, job in done]
    stages["api_http"] = float(np.median(api) * 1e3)
    return stages


def run_level(url: str, clients: int, jobs: int, data: bytes, decoder: str) -> dict[str, Any]:
    """``jobs`` requests from ``clients`` concurrent clients."""
    with ExitStack() as stack:
        pool = [
            stack.enter_context(
                httpx.Client(base_url=url, headers={"Authorization": f"Bearer {KEY}"}, timeout=120)
            )
            for _ in range(clients)
        ]
        start = time.perf_counter()
        with ThreadPoolExecutor(clients) as executor:
            outcomes = list(
                executor.map(lambda i: one_job(pool[i % clients], data, decoder), range(jobs))
            )
        elapsed = time.perf_counter() - start
    return level_figures(clients, outcomes, elapsed)


def level_figures(
    clients: int, outcomes: list[tuple[float, dict[str, Any]]], elapsed_s: float
) -> dict[str, Any]:
    """One level's figures from its requests' ``outcomes`` (latency in s, the job's final
    record) over ``elapsed_s`` of wall time: the jobs that succeeded per second, their
    p50 and p99 latency in ms (None when none did), and how many were lost. A lost
    request (refused, failed) counted as a job done: answered at once, it raised jobs/s
    and lowered the percentiles."""
    done = [(latency, job) for latency, job in outcomes if job.get("state") == "succeeded"]
    latencies_ms = [1e3 * latency for latency, _ in done]
    return {
        "clients": clients,
        "jobs": len(outcomes),
        "jobs_per_s": len(done) / elapsed_s,
        "p50_ms": float(np.percentile(latencies_ms, 50)) if done else None,
        "p99_ms": float(np.percentile(latencies_ms, 99)) if done else None,
        "lost": len(outcomes) - len(done),
        "median_stage_ms": median_stages(done),
    }


def service_env(data_dir: Path, redis_url: str, port: int, decoder: str) -> dict[str, str]:
    return {
        **os.environ,
        "MCAM_DATA_DIR": str(data_dir),
        "MCAM_REDIS_URL": redis_url,
        "MCAM_API_KEYS": KEY,
        "MCAM_HOST": "127.0.0.1",
        "MCAM_PORT": str(port),
        "MCAM_DEFAULT_DECODER": decoder,
        "MCAM_RATE_LIMIT_PER_MINUTE": "1000000",
        "MCAM_HEARTBEAT_S": "0.5",
    }


def measure(decoder: str, jobs_per_client: int) -> dict[str, Any]:
    data, codes = test_frame()
    decode_ms = in_process_ms(decoder, codes, repeats=20)
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    with tempfile.TemporaryDirectory(prefix="mcam-bench-") as tmp:
        with EmbeddedRedis(Path(tmp) / "redis") as redis_url:
            env = service_env(Path(tmp) / "data", redis_url, port, decoder)
            api = [
                sys.executable,
                "-m",
                "uvicorn",
                "service.main:create_app",
                "--factory",
                "--host",
                "127.0.0.1",
                "--port",
                str(port),
                "--log-level",
                "warning",
            ]
            worker = [
                sys.executable,
                "-m",
                "service.cli.main",
                "worker",
                "--no-devices",
                "--log-level",
                "WARNING",
            ]
            with process(api, env), process(worker, env):
                wait_ready(url)
                run_level(url, 1, 3, data, decoder)  # warm-up: decoder load, connections
                levels = [
                    run_level(url, n, max(jobs_per_client * n, 10), data, decoder) for n in CLIENTS
                ]
    single_ms = levels[0]["p50_ms"]
    overhead_ms = None if single_ms is None else single_ms - decode_ms
    return {
        **host_facts(),
        "decoder": decoder,
        "size": f"{SIZE}x{SIZE}",
        "in_process_decode_ms": decode_ms,
        "overhead_ms": overhead_ms,
        "overhead_pct": None if overhead_ms is None else 100.0 * overhead_ms / decode_ms,
        "levels": levels,
        "lost_total": sum(level["lost"] for level in levels),
    }


def markdown(result: dict[str, Any]) -> str:
    """The report as Markdown: a header line (date, machine, load) and one row per level."""
    overhead = (
        "none measured (no job succeeded)"
        if result["overhead_ms"] is None
        else f"{result['overhead_ms']:.1f} ms ({result['overhead_pct']:.0f}% of decode)"
    )
    lines = [
        f"bench.service, {host_line(result)}. Decoder "
        f"{result['decoder']} at {result['size']}: in-process decode "
        f"{result['in_process_decode_ms']:.1f} ms; API+queue overhead at 1 client "
        f"{overhead}.",
        "",
        "| clients | jobs | jobs/s | p50 ms | p99 ms | lost "
        "| median stages (ms; api_http = latency - worker total) |",
        "|---|---|---|---|---|---|---|",
    ]
    for level in result["levels"]:
        stages = ", ".join(f"{k} {v:.1f}" for k, v in level["median_stage_ms"].items())
        lines.append(
            f"| {level['clients']} | {level['jobs']} | {level['jobs_per_s']:.1f} "
            f"| {shown_ms(level['p50_ms'])} | {shown_ms(level['p99_ms'])} | {level['lost']} "
            f"| {stages} |"
        )
    return "\n".join(lines)


def shown_ms(value: float | None) -> str:
    """A latency in ms for the table (``-``: no job succeeded)."""
    return "-" if value is None else f"{value:.1f}"


@one_line_errors
def main(argv: list[str] | None = None) -> int:
    parser = bench_parser(__name__, __doc__)
    parser.add_argument("--decoder", default="itoh", help="decoder to benchmark (default itoh)")
    parser.add_argument("--jobs-per-client", type=at_least(1), default=5)
    add_report_option(parser, "service.json")
    args = parser.parse_args(argv)
    refuse_unknown_decoders(parser, [args.decoder], encodings=[PARAMS.encoding])
    result = measure(args.decoder, args.jobs_per_client)
    report = markdown(result)
    write_report(result, report, args.out, rows="levels")
    print(report)
    return 1 if result["lost_total"] else 0


if __name__ == "__main__":
    sys.exit(main())

"""End to end: virtual SCAMP-5 -> pty -> daemon -> Redis -> worker -> results, 300 frames.

Every frame is reconstructed, in sequence order, and matches the simulator's ground truth
within the decoder's accuracy (itoh on a smooth modulo scene: W exact on >= 99.9 % of pixels,
so the median relative error is the quantization + noise level, below 1 %).
"""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import redis

from models.formation import reconstruct
from models.hdr_io import read_hdr
from tests.device.conftest import wait_for
from worker.embedded_redis import EmbeddedRedis
from worker.redis_keys import events_stream
from worker.result_store import RESULTS_DIR
from worker.runner import Worker, WorkerConfig

FRAMES = 300


def test_300_frames_reconstructed_in_order(link, client: redis.Redis,
                                           redis_server: EmbeddedRedis, tmp_path: Path) -> None:
    data_dir = tmp_path / "data"
    worker = Worker(WorkerConfig(redis_url=redis_server.url, data_dir=data_dir, decoder="itoh",
                                 heartbeat_s=0.5))
    thread = threading.Thread(target=worker.run, daemon=True)
    thread.start()
    try:
        with link(FRAMES) as run:
            assert wait_for(lambda: client.xlen(events_stream("cam1")) >= FRAMES, 110)
            camera = run.camera
    finally:
        worker.request_stop()
        thread.join(15)
    events = [{k.decode(): v.decode() for k, v in fields.items()}
              for _, fields in client.xrange(events_stream("cam1"))]
    frame_events = [e for e in events if e["type"] == "frame"]
    assert [int(e["sequence"]) for e in frame_events] == list(range(FRAMES))
    rng = np.random.default_rng(0)
    for seq in sorted(rng.choice(FRAMES, 40, replace=False)):
        event = frame_events[seq]
        x_hat = read_hdr(data_dir / RESULTS_DIR / event["key"]).pixels
        truth = camera.ground_truth(int(seq))
        x_true = reconstruct(truth.codes, truth.winding, truth.params)  # the W-exact answer
        exact_w = np.abs(x_hat - x_true) < 0.5
        assert exact_w.mean() >= 0.999, f"frame {seq}: W wrong on {1 - exact_w.mean():.2%}"
        relative = np.abs(x_hat - truth.irradiance) / truth.irradiance
        assert np.median(relative) < 0.01

"""Tests of bench/headroom.py: reachability by Itoh paths, and the report end to end."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from bench import headroom
from models.formation import to_unwrapped
from models.metrics import PSNR_CAP
from tests.bench.exact_frames import exact_and_wrong


def test_a_smooth_ramp_is_reachable_everywhere() -> None:
    u = np.tile(np.linspace(0.0, 4.0, 40), (5, 1))
    assert headroom.reachable(u, np.floor(u).astype(np.int64)).all()


def test_a_plateau_behind_a_cliff_is_unreachable() -> None:
    u = np.zeros((6, 8))
    u[2:4, 5:7] = 3.2
    reach = headroom.reachable(u, np.floor(u).astype(np.int64))
    assert not reach[2:4, 5:7].any()
    assert reach.sum() == u.size - 4


def test_a_cliff_with_a_gentle_way_round_is_reachable() -> None:
    u = np.tile(np.linspace(0.0, 3.0, 10), (3, 1))
    u[1, 4] = 3.0
    reach = headroom.reachable(u, np.floor(u).astype(np.int64))
    assert reach[1, 5:].all() and not reach[1, 4]


def test_report_puts_true_w_back_per_group(tmp_path: Path) -> None:
    out = tmp_path / "headroom.json"
    headroom.main(["--decoders", "itoh", "--encodings", "mantissa", "--frames", "2",
                   "--out", str(out)])  # fmt: skip
    report = json.loads(out.read_text())
    assert len(report["load_average"]) == 3 and report["versions"]["numpy"]
    result = report["results"][0]
    assert 0.8 < result["reachable"]["overall"] <= 1.0
    assert result["reachable"]["per_w"]["0"] == 1.0
    psnr = result["decoders"][0]["psnr"]
    assert set(psnr) == {"as_decoded", *headroom.GROUPS}
    assert psnr["low_w"] >= psnr["as_decoded"] and psnr["high_w"] >= psnr["as_decoded"]
    assert "| itoh |" in out.with_suffix(".md").read_text()


def test_an_exact_frame_counts_at_the_psnr_cap() -> None:
    """Its inf made every mean PSNR of the decoder inf."""
    frames = exact_and_wrong()
    reach = [headroom.reachable(to_unwrapped(f.x, f.params), f.winding) for f in frames]
    both = headroom.decoder_row("itoh", frames, reach)["psnr"]
    wrong = headroom.decoder_row("itoh", frames[1:], reach[1:])["psnr"]
    assert both["as_decoded"] == pytest.approx((PSNR_CAP + wrong["as_decoded"]) / 2)

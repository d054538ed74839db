"""/v1/decoders lists the registry with figures and their source, and marks the default."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import httpx

from models.decoders.registry import available_decoders
from tests.service.conftest import READ_KEY, SUBMIT_KEY

Client = Callable[[str], httpx.Client]
ACCURACY = Path(__file__).resolve().parents[4] / "bench" / "results" / "accuracy.json"


def test_lists_every_registered_decoder(client: Client) -> None:
    reply = client(READ_KEY).get("/v1/decoders")
    assert reply.status_code == 200
    listed = reply.json()
    assert [d["name"] for d in listed] == [spec.name for spec in available_decoders()]
    assert [d["name"] for d in listed if d["default"]] == ["itoh"]
    assert all(isinstance(d["figures"], dict) and d["description"] for d in listed)


def test_every_decoder_has_figures_or_says_why_not(client: Client) -> None:
    """Classical, refined and adaptive decoders listed bare {} (only the learned ones had
    figures, from their model cards): each now has figures with their source."""
    listed = {d["name"]: d for d in client(READ_KEY).get("/v1/decoders").json()}
    assert all(d["figures"] and d["figures_source"] for d in listed.values())
    report = json.loads(ACCURACY.read_text())
    for name in ("itoh", "herraez", "graphcut", "auto", "auto-best", "mantissanet-small+puma"):
        row = next(r for r in report["results"]
                   if r["decoder"] == name and r["encoding"] == "mantissa")
        measured = listed[name]["figures"]["mantissa"]["val256"]["read_noise_0"]
        assert measured["psnr"] == round(row["psnr"], 4), name
        assert listed[name]["figures_source"].startswith("bench/results/accuracy.json")
    assert "read_noise_0.01" in listed["itoh"]["figures"]["mantissa"]["val256"]
    small = listed["mantissanet-small"]
    assert small["figures"]["mantissa"]["gflops_256"] > 0
    assert "models/onnx/mantissanet-small-mantissa.json" in small["figures_source"]


def test_needs_the_read_scope(client: Client) -> None:
    assert client(SUBMIT_KEY).get("/v1/decoders").status_code == 403

"""/v1/decoders lists the registry with figures and their source, and marks the default."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import httpx
import pytest
from pydantic import ValidationError

from models.decoders.registry import available_decoders
from service.core.config import Settings
from service.main import create_app
from tests.service.conftest import READ_KEY, SUBMIT_KEY, make_settings, serve

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


def test_figures_from_the_report_the_settings_name(tmp_path: Path, redis_url: str) -> None:
    """An installed package (the Docker image) has no checkout's bench/results: the
    report named by MCAM_ACCURACY_REPORT gives those decoders their figures."""
    report = json.loads(ACCURACY.read_text())
    for row in report["results"]:
        if "psnr" in row:
            row["psnr"] = 12.3456
    named = tmp_path / "elsewhere" / "accuracy.json"
    named.parent.mkdir()
    named.write_text(json.dumps(report))
    settings = make_settings(tmp_path, redis_url, accuracy_report=named)
    with serve(create_app(settings)) as url:
        reply = httpx.get(f"{url}/v1/decoders", headers={"Authorization": f"Bearer {READ_KEY}"})
    itoh = next(d for d in reply.json() if d["name"] == "itoh")
    assert itoh["figures"]["mantissa"]["val256"]["read_noise_0"]["psnr"] == 12.3456
    assert itoh["figures_source"].startswith(str(named))


def test_a_named_report_that_is_missing_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ValidationError, match="no file at .*python -m bench.accuracy"):
        Settings(_env_file=None, accuracy_report=tmp_path / "gone.json")  # type: ignore[call-arg]


@pytest.mark.parametrize(("named", "problem"), [
    ("folder", "folder is a directory, not a report"),
    ("tradeoff.json", "tradeoff.json is not a complete val-256 benchmark report"),
], ids=["directory", "another-report"])
def test_a_named_report_that_gives_no_figures_is_refused(
    tmp_path: Path, named: str, problem: str
) -> None:
    """A directory was refused as 'no file at' it, and a file that is no accuracy report
    (bench.tradeoff's, say) was taken: the service started with those decoders'
    figures empty and only a log line to say why."""
    (tmp_path / "folder").mkdir()
    (tmp_path / "tradeoff.json").write_text('{"benchmark": "tradeoff", "rows": []}')
    with pytest.raises(ValidationError, match=f"{problem}.*python -m bench.accuracy"):
        Settings(_env_file=None, accuracy_report=tmp_path / named)  # type: ignore[call-arg]


def test_needs_the_read_scope(client: Client) -> None:
    assert client(SUBMIT_KEY).get("/v1/decoders").status_code == 403


def test_a_parametrized_default_is_listed_and_marked(tmp_path: Path, redis_url: str) -> None:
    """MCAM_DEFAULT_DECODER=auto-40ms (a valid default) was in no entry, so none was
    marked default: the viewer, which preselects the marked one and always sends its
    choice, ran every job with the first listed (itoh) instead."""
    settings = make_settings(tmp_path, redis_url, default_decoder="auto-40ms")
    with serve(create_app(settings)) as api:
        reply = httpx.get(f"{api}/v1/decoders", headers={"Authorization": f"Bearer {READ_KEY}"})
    listed = reply.json()
    assert [d["name"] for d in listed if d["default"]] == ["auto-40ms"]
    assert listed[-1]["kind"] == "adaptive" and "40 ms" in listed[-1]["description"]
    assert [d["name"] for d in listed[:-1]] == [spec.name for spec in available_decoders()]

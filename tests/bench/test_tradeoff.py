"""Tests of bench/tradeoff.py: the Pareto front and a tiny end-to-end run (no timings asserted)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from bench import tradeoff
from models import metrics
from models.decoders.adaptive_policy import DEFAULT_TILE
from models.decoders.budget import BudgetDecoder
from models.decoders.classical import ItohDecoder
from models.decoders.registry import get_decoder
from models.formation import SensorParams, dequantize
from models.scene_analysis import analyse
from models.scenes import val256_frames
from tests.bench.exact_frames import exact_and_wrong
from tests.bench.virtual_clock import LATER_NS, VirtualClock


def test_pareto_marks_only_undominated_rows() -> None:
    rows = [
        {"decoder": "fast-bad", "ms_per_frame": 1.0, "psnr_db": 20.0},
        {"decoder": "slow-good", "ms_per_frame": 10.0, "psnr_db": 40.0},
        {"decoder": "dominated", "ms_per_frame": 12.0, "psnr_db": 30.0},
        {"decoder": "twin", "ms_per_frame": 10.0, "psnr_db": 40.0},
    ]
    tradeoff.pareto(rows)
    assert [r["pareto"] for r in rows] == [True, True, False, True]


def test_the_pu21_front_is_taken_on_pu21_psnr() -> None:
    """The plot's PU21-PSNR panel joined the PSNR front (val-256, 2026-11-27: it left out
    mantissanet-small, on the PU21 front but not on the PSNR one)."""
    rows = [
        {"decoder": "fast", "ms_per_frame": 1.0, "psnr_db": 20.0, "pu21_psnr_db": 30.0},
        {"decoder": "psnr-best", "ms_per_frame": 10.0, "psnr_db": 25.0, "pu21_psnr_db": 31.0},
        {"decoder": "pu21-best", "ms_per_frame": 12.0, "psnr_db": 24.0, "pu21_psnr_db": 33.0},
    ]
    assert tradeoff.undominated(rows, "psnr_db") == [True, True, False]
    assert tradeoff.undominated(rows, "pu21_psnr_db") == [True, True, True]


def test_speedups_compare_auto_with_networks_alone_or_refined_at_most_as_accurate() -> None:
    rows = [
        {"decoder": "auto-fast", "ms_per_frame": 2.0, "winding_accuracy": 0.99, "psnr_db": 40.0},
        {"decoder": "net", "gflops_per_s": 1.0, "ms_per_frame": 10.0, "winding_accuracy": 0.9,
         "psnr_db": 20.0},
        {"decoder": "net+puma", "ms_per_frame": 60.0, "winding_accuracy": 0.98, "psnr_db": 45.0},
        {"decoder": "better+puma", "ms_per_frame": 80.0, "winding_accuracy": 0.995,
         "psnr_db": 46.0},
        {"decoder": "itoh", "ms_per_frame": 1.0, "winding_accuracy": 0.5, "psnr_db": 10.0},
    ]  # fmt: skip
    found = {s["network"]: s for s in tradeoff.speedups(rows)}
    assert set(found) == {"net", "net+puma"}
    assert found["net+puma"]["speedup"] == 30.0
    assert found["net+puma"]["network_psnr_db"] == 45.0
    assert found["net"]["auto_psnr_db"] == 40.0


def test_quick_run_writes_json_markdown_and_plot(tmp_path: Path) -> None:
    out = tmp_path / "tradeoff.json"
    plot = tmp_path / "tradeoff.png"
    tradeoff.main(
        ["--quick", "--frames", "1", "--dark", "1", "--glows", "1", "--repeats", "1",
         "--decoders", "itoh", "auto-fast", "--out", str(out), "--plot", str(plot)]
    )  # fmt: skip
    report = json.loads(out.read_text())
    assert set(report["results"]) == {"val-256", "mostly-dark", "glows"}
    assert report["sets"]["glows"] == 1
    decoders = {r["decoder"] for r in report["results"]["val-256"]}
    assert decoders == {"itoh", "auto-fast"}
    rates = report["matmul_gflops_per_s"]
    assert set(rates) == {"numpy", "onnxruntime"} and min(rates.values()) > 0
    assert report["peak_gflops_per_s"] == max(rates.values())
    assert plot.read_bytes()[:4] == b"\x89PNG"
    assert "| itoh |" in out.with_suffix(".md").read_text()
    assert "(numpy " in out.with_suffix(".md").read_text()


class LabelledBudget(BudgetDecoder):
    """A latency budget that chooses a new "quality" on every decode (as a learning budget
    may) and spends its call count in ms of ``clock``: call k is labelled ``k``, takes k
    ms and decodes as itoh."""

    def __init__(self, clock: VirtualClock) -> None:
        super().__init__(2.6)
        self.clock = clock
        self.calls = 0

    def explain_within(
        self, m: np.ndarray, params: SensorParams, budget_ms: float
    ) -> tuple[np.ndarray, dict[str, Any]]:
        self.calls += 1
        self.clock.now += self.calls * LATER_NS
        return ItohDecoder().predict_winding(m, params), {"budget": {"chosen": str(self.calls)}}


def test_a_budget_s_ms_choices_and_share_in_time_come_from_the_same_decodes() -> None:
    """The choices and PSNR came from each frame's first decode, the ms from the median of
    three later ones (which may choose otherwise), and the medians hid decodes over
    budget."""
    clock = VirtualClock()
    frames = val256_frames("mantissa")[:2]
    row = tradeoff.measure(LabelledBudget(clock), frames, repeats=3, clock=clock)
    assert row["chosen"] == {"2": 1, "3": 1}
    assert row["ms_per_frame"] == pytest.approx(2.5)
    assert row["within_budget"] == 0.5


def test_cost_model_ratios_leave_out_frames_without_residues_by_their_analysis() -> None:
    """They were left out by a prediction of 0 ms, which a frame without residues gets
    only when the routing's own cost per pixel calibrates to 0 (it measures 0 or 3-13
    ns a pixel on one host from process to process); a constant prediction stands for
    a host where it does not."""
    frames = tradeoff.glow_frames(12)
    smooth = [
        f
        for f in frames
        if analyse(dequantize(f.codes, f.params.bits), f.params, DEFAULT_TILE).itoh_likely
    ]
    assert smooth
    ratios = tradeoff.prediction_ratios(smooth[:1], 1, predict=lambda *_: 1.0)
    assert ratios == {}


def test_an_exact_frame_counts_at_the_psnr_cap() -> None:
    """It was left out of the mean: one 20 dB frame beside an exact one read 20 dB."""
    frames = exact_and_wrong()
    row = tradeoff.measure(get_decoder("itoh"), frames, repeats=1)
    wrong = metrics.psnr(get_decoder("itoh").decode(frames[1].codes, frames[1].params)
                         .irradiance, frames[1].x)  # fmt: skip
    assert row["exact_frames"] == 1
    assert row["psnr_db"] == pytest.approx((metrics.PSNR_CAP + wrong) / 2)


def test_decoders_without_a_name_is_a_usage_error(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--decoders`` with no name after it gave an empty list, taken as "every decoder":
    the whole 14-minute benchmark ran instead of a usage error."""

    def measured(args: object) -> dict[str, Any]:
        raise AssertionError(f"it measured {args}")

    monkeypatch.setattr(tradeoff, "run", measured)
    with pytest.raises(SystemExit) as exc:
        tradeoff.main(["--decoders", "--quick", "--out", str(tmp_path / "t.json")])
    assert exc.value.code == 2
    assert "argument --decoders: expected at least one argument" in capsys.readouterr().err


def measured_row(decoder: str, **extra: Any) -> dict[str, Any]:
    """A row of a set's table as :func:`bench.tradeoff.run` makes it (figures made up)."""
    return {
        "decoder": decoder, "psnr_db": 30.0, "pu21_psnr_db": 31.0, "winding_accuracy": 0.9,
        "ms_per_frame": 5.0, "frames_per_s": 200.0, "pareto": True, **extra,
    }  # fmt: skip


def report_of(results: dict[str, list[dict[str, Any]]]) -> dict[str, Any]:
    """A report of ``results`` (rows by set), with no frame with residues."""
    return {
        "date": "2026-11-28T00:00:00+00:00",
        "machine": {"cores": 2},
        "load_average": (1.0, 1.0, 1.0),
        "peak_gflops_per_s": 100.0,
        "matmul_gflops_per_s": {"numpy": 100.0},
        "sets": dict.fromkeys(results, 1),
        "results": results,
        "mostly_dark_speedups": tradeoff.speedups(results.get("mostly-dark", [])),
        "latency_predictions": dict.fromkeys(results, {}),
    }


@pytest.mark.parametrize(
    ("decoders", "reasons"),
    [
        (["itoh"], ["Skipped: no latency budget was measured; name one in --decoders",
                    "Skipped: no quality of `auto` (auto, auto-fast, auto-balanced, auto-best) "
                    "was measured on mostly-dark; name one in --decoders",
                    "GFLOP/s: none of these decoders is a network alone",
                    "Pareto: one decoder was measured, so it is the front by itself"]),
        (["itoh", "auto-fast"], ["Skipped: no network (e.g. mantissanet-small, or refined: "
                                 "mantissanet-small+puma) was measured on mostly-dark"]),
        (["auto-fast-tile32"], ["### mostly-dark (1 frames)\n\nSkipped: the tile variants "
                                "(`auto-<quality>-tile<px>`) are measured on val-256 only"]),
    ],
)  # fmt: skip
def test_a_table_a_subset_of_decoders_cannot_fill_says_why_it_is_skipped(
    decoders: list[str], reasons: list[str]
) -> None:
    """With ``--decoders itoh`` the latency-budget and speed-up tables were printed with
    a head and no row, the GFLOP/s column was all dashes and the lone decoder marked as
    the Pareto front; a set no named decoder is measured on (the tile variants are
    val-256's only) had an empty table too."""
    rows = {
        "val-256": [measured_row(name) for name in decoders],
        "mostly-dark": [measured_row(name) for name in decoders if "tile" not in name],
    }
    text = tradeoff.markdown(report_of(rows))
    for reason in reasons:
        assert reason in text
    assert "None: no frame of any set has residues" in text
    lines = text.splitlines()
    empty = [
        line
        for line, after in zip(lines, [*lines[1:], ""], strict=True)
        if line.startswith("|---") and not after.startswith("| ")
    ]
    assert not empty, text


def test_a_network_more_accurate_than_auto_is_said_to_be_so() -> None:
    rows = [measured_row("auto-fast", winding_accuracy=0.8),
            measured_row("mantissanet-tiny", gflops_per_s=1.0, fraction_of_peak=0.01)]  # fmt: skip
    text = tradeoff.markdown(report_of({"val-256": rows, "mostly-dark": rows}))
    assert "None: every network measured is more accurate (W acc) than every `auto`" in text
    assert "GFLOP/s: none" not in text and "Pareto: one decoder" not in text


def test_a_networks_gflops_count_only_the_frames_it_runs_on() -> None:
    """A frame without a residue is integrated, the net not run: counting its pixels put
    mantissanet-large at 144% of the machine's peak on the glows (half of them have
    none)."""
    busy = val256_frames("mantissa")[0]
    calm = tradeoff.frames_at(np.tile(np.linspace(0.1, 3.0, 64), (64, 1)), None, 1.0)
    assert tradeoff.network_pixels([busy, calm]) == busy.codes.size / 2
    row: dict[str, Any] = {"decoder": "mantissanet-small", "ms_per_frame": 50.0}
    tradeoff.add_throughput(row, tradeoff.network_pixels([calm]), peak=100.0)
    assert "gflops_per_s" not in row
    tradeoff.add_throughput(row, tradeoff.network_pixels([busy]), peak=100.0)
    assert row["gflops_per_s"] == pytest.approx(tradeoff.gflops_of("mantissanet-small") / 0.05)

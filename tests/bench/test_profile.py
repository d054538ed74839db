"""Tests of bench/profile.py: FLOP counting, per-operator tables and a tiny end-to-end run
(no timings asserted)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from bench import profile
from models.decoders.learned import load_cards


def conv_event(channels_in: int, channels_out: int, size: int, dur_us: float) -> dict[str, Any]:
    """A profiler event of a 3x3 convolution as onnxruntime writes it."""
    return {
        "cat": "Node",
        "name": "conv_kernel_time",
        "dur": dur_us,
        "args": {
            "op_name": "FusedConv",
            "input_type_shape": [
                {"float": [1, channels_in, size, size]},
                {"float": [channels_out, channels_in, 3, 3]},
                {"float": [channels_out]},
            ],
            "output_type_shape": [{"float": [1, channels_out, size, size]}],
        },
    }


def op_event(op: str, dur_us: float) -> dict[str, Any]:
    return {"cat": "Node", "name": f"{op}_kernel_time", "dur": dur_us, "args": {"op_name": op}}


def test_node_flops_counts_two_per_multiply_add() -> None:
    assert profile.node_flops(conv_event(8, 16, 4, 1.0)) == 2 * 16 * 4 * 4 * 8 * 3 * 3


def test_op_table_takes_the_median_run_and_shares_sum_to_one() -> None:
    runs = [
        [conv_event(8, 8, 4, 3000.0), op_event("Add", 1000.0)],
        [conv_event(8, 8, 4, 9000.0), op_event("Add", 1000.0)],
        [conv_event(8, 8, 4, 5000.0), op_event("Add", 1000.0)],
    ]
    table = profile.op_table(runs)
    assert [row["op"] for row in table] == ["FusedConv", "Add"]
    assert table[0]["ms"] == pytest.approx(5.0)
    assert table[0]["group"] == "convolution"
    assert table[1]["group"] == "element-wise"
    assert sum(row["share"] for row in table) == pytest.approx(1.0)


def test_conv_by_resolution_groups_by_output_width() -> None:
    runs = [[conv_event(8, 16, 64, 2000.0), conv_event(16, 32, 32, 1000.0)]] * 2
    levels = profile.conv_by_resolution(runs)
    assert [level["width"] for level in levels] == [64, 32]
    assert levels[0]["convs"] == 1
    assert levels[0]["out_channels"] == [16]
    assert levels[0]["gflops_per_s"] == pytest.approx(
        profile.node_flops(conv_event(8, 16, 64, 0)) / 1e9 / 0.002
    )


@pytest.mark.skipif(
    not any(card["decoder"] == "mantissanet-tiny" for card in load_cards()),
    reason="mantissanet-tiny is not installed",
)
def test_tiny_run_writes_json_and_markdown(tmp_path: Path) -> None:
    out = tmp_path / "profile.json"
    profile.main(
        ["--models", "mantissanet-tiny", "--runs", "1", "--repeats", "1", "--out", str(out)]
    )
    report = json.loads(out.read_text())
    (result,) = report["profiles"]
    (card,) = [c for c in load_cards() if c["decoder"] == "mantissanet-tiny"
               and c["encoding"] == "mantissa"]  # fmt: skip
    assert result["model"] == card["name"]
    assert 0.5 * result["card_gflops_256"] < result["conv_gflops"] <= result["card_gflops_256"]
    assert sum(row["share"] for row in result["ops"]) == pytest.approx(1.0)
    assert len(report["levers"][card["name"]]) == len(profile.LEVERS)
    assert "| convolution |" in out.with_suffix(".md").read_text()


def test_an_empty_model_list_is_a_usage_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--models`` with no name profiled nothing and wrote an empty report over the
    committed one."""
    out = tmp_path / "profile.json"
    with pytest.raises(SystemExit) as exc:
        profile.main(["--models", "--runs", "1", "--repeats", "1", "--out", str(out)])
    assert exc.value.code == 2
    assert "--models: expected at least one argument" in capsys.readouterr().err
    assert not out.exists()
